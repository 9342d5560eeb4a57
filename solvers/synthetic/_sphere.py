"""Synthetic sphere captures and a procedural HDR sky: inputs for the demo, notebooks and tests (no files needed)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

import jaxsh

from .._data import Lighting, TorranceSparrow


def procedural_sky(height: int, width: int, sun_dir=(0.5, 0.3, 0.81), sun_size: float = 0.08, rotation=None):
    """An HDR sky: blue-ish gradient above the horizon, a dim ground, a bright sun lobe.

    Lat-long `(height, width, 3)` in the library frame (+z up). The sun is an
    exponential lobe of angular radius ~`sun_size` (radians) carrying most of
    the energy, so the map is far from band-limited — a fair test of projection.
    With `rotation` R (3, 3), returns the rotated sky, omega -> f(R^T omega).
    """
    d = np.asarray(jaxsh.latlong_directions(height, width, dtype=np.float64))
    if rotation is not None:
        d = d @ np.asarray(rotation, dtype=np.float64)  # rows: R^T omega
    z = d[..., 2:3]
    sky = np.where(z > 0, np.array([0.35, 0.55, 1.0]) * (0.4 + 0.6 * z), np.array([0.25, 0.2, 0.15]) * (1 + z))
    s = np.asarray(sun_dir, dtype=np.float64)
    s = s / np.linalg.norm(s)
    cosang = np.clip(d @ s, -1, 1)[..., None]
    sun = np.array([60.0, 55.0, 45.0]) * np.exp((cosang - 1.0) / (sun_size**2))
    return jnp.asarray(sky + sun)


# --------------------------------------------------------------------------- synthetic captures (R&H fig. 11 style)

class SyntheticCapture(NamedTuple):
    """A synthetic capture: views of an object under known lighting, rendered by `jaxsh.render_reference`.

    `images` carry the noise, `clean` do not. `lighting` is the truth in the
    practical model's form (slow SH of the area sources to `lighting_lmax`,
    the directional sources as fast deltas); `disks` and `directional` are
    the sources as the reference renderer saw them.
    """

    cameras: list
    gbuffers: list
    images: list
    clean: list
    lighting: Lighting
    disks: tuple
    directional: tuple
    brdf: TorranceSparrow


def default_sources(dtype=np.float64):
    """The demo's lighting: a large area source, a dim ground disk and a directional source (world, +z up).

    Returns `(disks, directional)` in `render_reference`'s format. The area
    source (radius 0.6 rad) holds most of its energy in low orders, like the
    projection screen of R&H sec. 6; the directional source is the 150 W
    point source of the gantry.
    """
    def unit(v):
        v = np.asarray(v, dtype)
        return v / np.linalg.norm(v)

    disks = (
        np.stack([unit([0.45, -0.55, 0.7]), unit([0.0, 0.0, -1.0])]),
        np.array([0.6, 1.2], dtype),
        np.array([[1.6, 1.5, 1.35], [0.12, 0.11, 0.1]], dtype),
    )
    directional = (unit([-0.35, 0.5, 0.8])[None, :], np.array([[3.0, 3.0, 3.0]], dtype))
    return disks, directional


def view_cameras(n_views: int = 3, size: int = 64, radius: float = 1.0, elevation: float = 0.45,
                 azimuths=None, dtype=np.float64):
    """Orthographic cameras looking at a sphere of `radius` at the origin from `n_views` directions.

    The eyes are 5 units away at `elevation` (radians above the xy plane) and at the `azimuths` (radians from +x;
    default `n_views` values evenly spaced on [-0.5, 1], or 0.2 for one view), `size` × `size` pixels covering
    2.2 `radius`. `azimuths`, when given, must hold `n_views` values; `n_views` < 1 is a `ValueError`."""
    if isinstance(n_views, bool) or not isinstance(n_views, (int, np.integer)) or n_views < 1:
        raise ValueError(f"`n_views` must be an integer >= 1, got {n_views!r}")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise ValueError(f"`size` must be an integer >= 1 (pixels per side), got {size!r}")
    if azimuths is None:
        azimuths = np.linspace(-0.5, 1.0, n_views) if n_views > 1 else np.array([0.2])
    azimuths = np.asarray(azimuths, dtype).reshape(-1)
    if azimuths.shape[0] != n_views:  # (were used as given, n_views ignored without a word)
        raise ValueError(f"`azimuths` must hold `n_views` = {n_views} values, got {azimuths.shape[0]}")
    cams = []
    for az in azimuths:
        eye = 5.0 * np.array([np.cos(elevation) * np.cos(az), np.cos(elevation) * np.sin(az), np.sin(elevation)])
        m = jaxsh.look_at(jnp.asarray(eye, dtype), jnp.zeros(3, dtype), jnp.asarray([0.0, 0.0, 1.0], dtype))
        cams.append(jaxsh.OrthographicCamera(2.2 * radius / size, size, size, m))
    return cams


def sphere_capture(
    brdf: TorranceSparrow,
    *,
    size: int = 64,
    n_views: int = 3,
    noise: float = 0.01,
    seed: int = 0,
    sources=None,
    lighting_lmax: int = 40,
    azimuths=None,
    elevation: float = 0.45,
    disk_nodes=(48, 96),
    dtype=np.float64,
    brdf_model: str = "torrance_sparrow",
) -> SyntheticCapture:
    """Views of a unit sphere rendered by the reference renderer (`jaxsh.render_reference`).

    `brdf_model`: the reference BRDF, `"torrance_sparrow"` (the model the
    solvers fit, R&H sec. 5.2), or a fuller one the solvers cannot reproduce
    exactly, `"cook_torrance"` (Beckmann, Smith G, Fresnel at the half angle)
    or `"ggx"` — so a fit can be checked against data with model error.

    `noise`: additive Gaussian noise with standard deviation `noise` times the
    RMS of each clean image over the object (1 % by default), drawn from
    `seed`. `sources`: `(disks, directional)` as `default_sources()` returns;
    `lighting_lmax`: the band limit of the returned lighting's SH (the truth a
    fit is compared with); `n_views`, `size`, `azimuths`, `elevation`: the
    cameras (`view_cameras`); `disk_nodes`: the reference renderer's quadrature
    of each disk; `dtype`: of the cameras, images and truths.
    """
    disks, directional = default_sources(dtype) if sources is None else sources
    cams = view_cameras(n_views, size, elevation=elevation, azimuths=azimuths, dtype=dtype)
    rng = np.random.default_rng(seed)
    gbs, imgs, clean = [], [], []
    for cam in cams:
        gb = jaxsh.sphere_gbuffer(cam, jnp.zeros(3, dtype), jnp.asarray(1.0, dtype))
        m = np.asarray(gb.mask)
        img = np.zeros(m.shape + (3,), dtype)
        n = np.asarray(gb.normal)[m]
        v = np.asarray(gb.view)[m]
        out = jaxsh.render_reference(
            n, v, brdf.kd, brdf.ks, brdf.mu, brdf.sigma,
            disks=None if disks is None else disks, directional=directional, disk_nodes=disk_nodes,
            brdf_model=brdf_model,
        )
        img[m] = np.asarray(out)
        clean.append(img)
        rms = np.sqrt(np.mean(img[m] ** 2))
        noisy = img.copy()
        noisy[m] += noise * rms * rng.standard_normal(noisy[m].shape)
        imgs.append(noisy)
        gbs.append(gb)
    slow = None
    if disks is not None:
        for k in range(disks[0].shape[0]):
            c = jaxsh.disk_light_sh(jnp.asarray(disks[0][k]), disks[1][k], jnp.asarray(disks[2][k]), lighting_lmax)
            slow = c if slow is None else slow + c
    lighting = Lighting(
        slow, None if directional is None else jnp.asarray(directional[0]),
        None if directional is None else jnp.asarray(directional[1]),
    )
    return SyntheticCapture(cams, gbs, imgs, clean, lighting, disks, directional, brdf)
