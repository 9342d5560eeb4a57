"""Inputs and results of the inverse-rendering solvers (R&H 2001 sec. 6).

* `Observations`: the valid pixels of one or more calibrated views, flattened
  to `N` samples (normal, view, radiance, weight, optional visibility terms
  and texel index). Build it with `observations(gbuffers, images, ...)`,
  which validates the images and drops or rejects bad pixels.
* `Lighting`: slow SH lighting plus fast (delta) sources, the two parts of
  the practical model (R&H sec. 5.3).
* `TorranceSparrow`: the BRDF parameters $K_d, K_s, \\mu, \\sigma$ of R&H
  sec. 5.2, with optional texture maps for $K_d$ / $K_s$ (sec. 6.4).
* `Status`: the outcome of a solve. Every solver result carries one; a
  failed solve is a status, never a silent NaN.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, Real

import jaxsh

from ._results import Status as Status, status_name as status_name  # re-exported for older imports


class Lighting(eqx.Module):
    """Distant lighting in the world frame (+z up): slow SH part plus fast delta sources.

    **Fields:**

    - `slow_sh`: `(n_coeffs, C)` real SH coefficients or `None`.
    - `fast_directions`: `(J, 3)` unit directions towards the sources, or `None`.
    - `fast_energy`: `(J, C)` total energy $L_j$ of each source (eq. 23), or `None`.
    """

    slow_sh: Real[ArrayLike, "n_coeffs C"] | None = None
    fast_directions: Real[ArrayLike, "J 3"] | Sequence[Sequence[float]] | None = None
    fast_energy: Real[ArrayLike, "J C"] | Sequence[Sequence[float]] | None = None

    def __check_init__(self):
        if self.slow_sh is None and self.fast_directions is None:
            raise ValueError("Lighting needs `slow_sh` and/or `fast_directions` + `fast_energy`")
        if (self.fast_directions is None) != (self.fast_energy is None):
            raise ValueError("Lighting: `fast_directions` and `fast_energy` go together")

    @property
    def lmax(self) -> int | None:
        if self.slow_sh is None:
            return None
        return int(round(np.sqrt(self.slow_sh.shape[0]))) - 1

    def total_sh(self, lmax: int) -> Float[Array, "n_coeffs C"]:
        """SH coefficients of all of the lighting (fast sources projected as deltas) to `lmax`."""
        parts = []
        if self.slow_sh is not None:
            s = jnp.asarray(self.slow_sh)
            n = jaxsh.num_coeffs(lmax)
            s = s[:n] if s.shape[0] >= n else jnp.pad(s, ((0, n - s.shape[0]), (0, 0)))
            parts.append(s)
        if self.fast_directions is not None:
            parts.append(jaxsh.directional_light_sh(self.fast_directions, self.fast_energy, lmax))
        out = parts[0]
        for p in parts[1:]:
            out = out + p
        return out


class TorranceSparrow(eqx.Module):
    """R&H sec. 5.2 BRDF parameters: $\\rho = K_d + K_s F(\\mu,\\theta_o) S / (4\\cos\\theta_i\\cos\\theta_o)$.

    `kd`, `ks`: `(C,)` homogeneous, or `(T, C)` per texel (with
    `Observations.texel`). `mu`: scalar index of refraction, or `None` for
    no Fresnel term ($F = 1$, metals in R&H fig. 11). `sigma`: scalar
    roughness (radians).
    """

    kd: Float[Array, "*T C"]
    ks: Float[Array, "*T C"]
    mu: Float[Array, ""] | None
    sigma: Float[Array, ""]


class Observations(eqx.Module):
    """`N` valid pixel samples of one or more views (see `observations`).

    **Fields:** `normals`, `views` `(N, 3)`; `values` `(N, C)` linear
    radiance; `weights` `(N,)` (least-squares weights, 1 by default);
    `transfer` `(N, 9)`, `fast_visibility` `(N, J)`,
    `reflected_visibility` `(N,)`: the visibility terms of R&H sec. 6.4 or
    `None` (convex object); `texel` `(N,)` int texel index or `None`;
    `view_index`, `pixel_index` `(N,)`: where each sample came from, and
    `image_shapes` (static) the `(H, W)` of each view, for `to_images`.
    """

    normals: Float[Array, "N 3"]
    views: Float[Array, "N 3"]
    values: Float[Array, "N C"]
    weights: Float[Array, " N"]
    transfer: Float[Array, "N 9"] | None
    fast_visibility: Float[Array, "N J"] | None
    reflected_visibility: Float[Array, " N"] | None
    texel: Int[Array, " N"] | None
    view_index: Int[Array, " N"]
    pixel_index: Int[Array, " N"]
    image_shapes: tuple = eqx.field(static=True)
    n_texels: int = eqx.field(static=True, default=0)

    @property
    def n_samples(self) -> int:
        return self.values.shape[0]

    @property
    def n_channels(self) -> int:
        return self.values.shape[1]

    def subset(self, index) -> "Observations":
        """The samples at integer `index` (outside jit)."""
        index = np.asarray(index)

        def take(a):
            return None if a is None else a[index]

        return Observations(
            take(self.normals), take(self.views), take(self.values), take(self.weights), take(self.transfer),
            take(self.fast_visibility), take(self.reflected_visibility), take(self.texel), take(self.view_index),
            take(self.pixel_index), self.image_shapes, self.n_texels,
        )

    def to_images(self, values: Real[ArrayLike, "N C"], fill: float = 0.0) -> list[np.ndarray]:
        """Scatter per-sample `values` `(N, C)` back into one `(H, W, C)` image per view."""
        values = np.asarray(values)
        if values.ndim != 2 or values.shape[0] != self.n_samples:
            raise ValueError(f"`values` must have shape ({self.n_samples}, C), got {values.shape}")
        vi = np.asarray(self.view_index)
        pi = np.asarray(self.pixel_index)
        out = []
        for k, (h, w) in enumerate(self.image_shapes):
            img = np.full((h * w, values.shape[1]), fill, values.dtype)
            sel = vi == k
            img[pi[sel]] = values[sel]
            out.append(img.reshape(h, w, values.shape[1]))
        return out


def _per_view(arrs, n_views, name, shape_tail, hw):
    if arrs is None:
        return None
    if len(arrs) != n_views:
        raise ValueError(f"`{name}` must be a list of {n_views} arrays (one per view), got {len(arrs)}")
    out = []
    for k, a in enumerate(arrs):
        a = np.asarray(a)
        want = hw[k] + shape_tail
        if a.shape != want:
            raise ValueError(f"`{name}[{k}]` must have shape {want}, got {a.shape}")
        out.append(a.reshape((-1,) + shape_tail))
    return out


def observations(
    gbuffers: Sequence[jaxsh.GBuffer],
    images: Sequence[Real[ArrayLike, "H W C"]],
    *,
    masks: Sequence | None = None,
    weights: Sequence | None = None,
    saturation: float | None = None,
    invalid: str = "raise",
    transfer: Sequence | None = None,
    fast_visibility: Sequence | None = None,
    reflected_visibility: Sequence | None = None,
    texel: Sequence | None = None,
    n_texels: int | None = None,
) -> Observations:
    """Collect the valid pixels of calibrated views into `Observations`.

    A pixel is used when the G-buffer hit the object, the optional user
    `mask` is set, its weight is positive, and — if `saturation` is given —
    no channel reaches `saturation` (clipped pixels carry no radiance
    information and are dropped). Non-finite pixel values inside the mask
    raise `ValueError` naming the view (`invalid="raise"`, the default) or are
    dropped (`invalid="drop"`).

    **Arguments:**

    - `gbuffers`: one `jaxsh.GBuffer` per view; `images`: matching
      `(H, W, C)` (or `(H, W)`) linear radiance images.
    - `masks`, `weights`: optional per-view `(H, W)` bool / float arrays.
    - `transfer` `(H, W, 9)`, `fast_visibility` `(H, W, J)`,
      `reflected_visibility` `(H, W)`: optional per-view visibility terms
      (`jaxsh.visibility_sh`, `jaxsh.directional_visibility`,
      `jaxsh.reflected_visibility`).
    - `texel`: optional per-view `(H, W)` int texel indices in
      `[0, n_texels)` for textured $K_d(x)$ (R&H sec. 6.4).

    **Returns:** `Observations` (float dtype of the G-buffers). Raises
    `ValueError` if no valid pixel remains, or on mismatched shapes.
    """
    if invalid not in ("raise", "drop"):
        raise ValueError(f"`invalid` must be 'raise' or 'drop', got {invalid!r}")
    gbuffers = list(gbuffers)
    images = list(images)
    if len(gbuffers) == 0:
        raise ValueError("`gbuffers` is empty: give at least one view")
    if len(images) != len(gbuffers):
        raise ValueError(f"`images` must have one image per G-buffer ({len(gbuffers)}), got {len(images)}")
    hw = [tuple(int(s) for s in gb.mask.shape) for gb in gbuffers]
    imgs = []
    chans = None
    for k, img in enumerate(images):
        img = np.asarray(img)
        if img.ndim == 2:
            img = img[..., None]
        if img.ndim != 3 or img.shape[:2] != hw[k]:
            raise ValueError(f"`images[{k}]` must have shape {hw[k]} + (C,), got {img.shape}")
        if chans is None:
            chans = img.shape[2]
        elif img.shape[2] != chans:
            raise ValueError(f"`images[{k}]` has {img.shape[2]} channels, `images[0]` has {chans}")
        imgs.append(img.reshape(-1, chans))
    m_user = _per_view(masks, len(gbuffers), "masks", (), hw)
    w_user = _per_view(weights, len(gbuffers), "weights", (), hw)
    tr = _per_view(transfer, len(gbuffers), "transfer", (9,), hw)
    rv = _per_view(reflected_visibility, len(gbuffers), "reflected_visibility", (), hw)
    tx = _per_view(texel, len(gbuffers), "texel", (), hw)
    fv = None
    if fast_visibility is not None:
        j = np.asarray(fast_visibility[0]).shape[-1]
        fv = _per_view(fast_visibility, len(gbuffers), "fast_visibility", (j,), hw)
    if tx is not None:
        if n_texels is None:
            n_texels = int(max(int(t.max()) for t in tx)) + 1
        for k, t in enumerate(tx):
            if not np.issubdtype(t.dtype, np.integer):
                raise ValueError(f"`texel[{k}]` must be an integer array, got {t.dtype}")
    dt = np.asarray(gbuffers[0].normal).dtype
    cols = {k: [] for k in ("n", "v", "b", "w", "t", "fv", "rv", "tx", "vi", "pi")}
    for k, gb in enumerate(gbuffers):
        sel = np.asarray(gb.mask).reshape(-1).astype(bool)
        if m_user is not None:
            sel &= m_user[k].astype(bool)
        w = np.ones(sel.shape, dt) if w_user is None else w_user[k].astype(dt)
        sel &= w > 0
        vals = imgs[k]
        finite = np.all(np.isfinite(vals), axis=1)
        bad = sel & ~finite
        if bad.any():
            if invalid == "raise":
                raise ValueError(
                    f"`images[{k}]` has {int(bad.sum())} non-finite (NaN/inf) pixels inside the mask; "
                    "fix the image, mask them out, or pass invalid='drop'"
                )
            sel &= finite
        if saturation is not None:
            sel &= ~np.any(vals >= saturation, axis=1)
        if tx is not None:
            t = tx[k]
            if np.any((t[sel] < 0) | (t[sel] >= n_texels)):
                raise ValueError(f"`texel[{k}]` has indices outside [0, {n_texels}) inside the mask")
        idx = np.nonzero(sel)[0]
        cols["n"].append(np.asarray(gb.normal).reshape(-1, 3)[idx])
        cols["v"].append(np.asarray(gb.view).reshape(-1, 3)[idx])
        cols["b"].append(vals[idx].astype(dt))
        cols["w"].append(w[idx])
        cols["vi"].append(np.full(idx.shape, k, np.int32))
        cols["pi"].append(idx.astype(np.int32))
        for key, src in (("t", tr), ("fv", fv), ("rv", rv), ("tx", tx)):
            if src is not None:
                cols[key].append(src[k][idx])
    total = sum(len(x) for x in cols["vi"])
    if total == 0:
        raise ValueError(
            "no valid pixel: every pixel is outside the G-buffer masks, masked out, saturated or non-finite"
        )

    def cat(key, dtype=None):
        if not cols[key]:
            return None
        a = np.concatenate(cols[key])
        return jnp.asarray(a if dtype is None else a.astype(dtype))

    return Observations(
        cat("n", dt), cat("v", dt), cat("b", dt), cat("w", dt), cat("t", dt), cat("fv", dt), cat("rv", dt),
        cat("tx", np.int32), cat("vi"), cat("pi"), tuple(hw), int(n_texels or 0),
    )


def practical_terms_for(obs: Observations, lighting: Lighting, chunk: int = 8192) -> jaxsh.PracticalTerms:
    """`jaxsh.practical_terms` of the observed pixels under `lighting` (visibility included)."""
    if lighting.fast_directions is not None and obs.fast_visibility is not None:
        if obs.fast_visibility.shape[1] != lighting.fast_directions.shape[0]:
            raise ValueError(
                f"`Observations.fast_visibility` has {obs.fast_visibility.shape[1]} sources, the lighting "
                f"has {lighting.fast_directions.shape[0]}"
            )
    return jaxsh.practical_terms(
        obs.normals, obs.views, slow_sh=lighting.slow_sh, fast_directions=lighting.fast_directions,
        fast_energy=lighting.fast_energy, transfer=None if lighting.slow_sh is None else obs.transfer,
        fast_visibility=None if lighting.fast_directions is None else obs.fast_visibility,
        reflected_visibility=None if lighting.slow_sh is None else obs.reflected_visibility, chunk=chunk,
    )


def predict(
    brdf: TorranceSparrow,
    lighting: Lighting,
    normals: Real[ArrayLike, "*#batch 3"],
    views: Real[ArrayLike, "*#batch 3"],
    **visibility,
) -> Float[Array, "*batch C"]:
    """Radiance of `brdf` under `lighting` at new normals / views: `jaxsh.render_practical(...).total`.

    For novel lighting and views from any solver result
    (`predict(result.brdf, new_lighting, gb.normal, gb.view, mask=gb.mask)`).
    Extra keyword arguments (`transfer`, `fast_visibility`,
    `reflected_visibility`, `mask`) go to `render_practical`.
    """
    kd, ks = brdf.kd, brdf.ks
    return jaxsh.render_practical(
        normals, views, kd, ks, brdf.mu, brdf.sigma, slow_sh=lighting.slow_sh,
        fast_directions=lighting.fast_directions, fast_energy=lighting.fast_energy, **visibility,
    ).total
