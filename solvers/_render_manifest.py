"""`jaxsh render`: render every view of a capture manifest whose lighting and BRDF are given."""

from __future__ import annotations

import math
import os
import sys

import jax.numpy as jnp
import numpy as np

import jaxsh
from jaxsh import io as jio


def camera_from_manifest(c: dict):
    """A jaxsh camera from a validated manifest camera block."""
    if c["model"] == "pinhole":
        return jaxsh.PinholeCamera(c["fx"], c["fy"], c["cx"], c["cy"], c["width"], c["height"], c["cam_to_world"])
    return jaxsh.OrthographicCamera(c["scale"], c["width"], c["height"], c["cam_to_world"])


def lighting_from_manifest(m: dict, sigma: float, lmax: int | None = None):
    """(slow SH coefficients (n, 3) or None, fast directions (J, 3) or None, fast energy (J, 3) or None)."""
    lit = m["lighting"]
    slow = None
    if lit["envmap"] is not None:
        env = jio.read_envmap(lit["envmap"], up=lit["up"], layout=lit["layout"]).astype(np.float64)
        h = env.shape[0]
        if lmax is None:
            lmax = int(min(math.ceil(4.0 / sigma), h // 2 - 1))
        slow = jaxsh.project_latlong(env[..., :3], lmax)
    fd = fe = None
    if lit["directional"]:
        fd = np.stack([s["direction"] for s in lit["directional"]])
        fe = np.stack([s["radiance"] for s in lit["directional"]])
    return slow, fd, fe


def _inputs(m: dict) -> set:
    paths = {m["path"]}
    if "mesh" in m["geometry"]:
        paths.add(m["geometry"]["mesh"])
    for v in m["views"]:
        paths.update(p for p in (v["image"], v["mask"]) if p)
    if m["lighting"] and m["lighting"]["envmap"]:
        paths.add(m["lighting"]["envmap"])
    return {os.path.abspath(p) for p in paths}


def render_manifest(manifest_path, out_dir, progress: bool = True) -> list[str]:
    """Render all views with the practical model (R&H eq. 24) and write `view_###.exr/.png`.

    Meshes get shadowing (directional and reflected visibility) and
    visibility-weighted irradiance (SH transfer vectors, lmax 2) computed once
    per view (R&H sec. 6.4). Raises `ValueError` if lighting or BRDF are not
    given, or if an output would overwrite an input.
    """
    m = jio.read_manifest(manifest_path)
    if m["lighting"] is None or m["brdf"] is None:
        raise ValueError(f"{m['path']}: `jaxsh render` needs both `lighting` and `brdf` in the manifest")
    b = m["brdf"]
    lmax = m["solve"].get("render_lmax")
    slow, fd, fe = lighting_from_manifest(m, b["sigma"], lmax)
    mesh = jio.read_mesh(m["geometry"]["mesh"]) if "mesh" in m["geometry"] else None
    os.makedirs(out_dir, exist_ok=True)
    inputs = _inputs(m)
    written = []
    n = len(m["views"])
    for k, view in enumerate(m["views"]):
        if progress:
            print(f"[{k + 1}/{n}] rendering view {k}", file=sys.stderr, flush=True)
        cam = camera_from_manifest(view["camera"])
        if mesh is None:
            g = jaxsh.sphere_gbuffer(cam, m["geometry"]["sphere"]["center"], m["geometry"]["sphere"]["radius"])
            extra = {}
        else:
            g = jaxsh.mesh_gbuffer(cam, mesh)
            extra = _mesh_visibility(mesh, g, fd)
        out = jaxsh.render_practical(
            g.normal, g.view, b["kd"], b["ks"], b["mu"], b["sigma"], slow_sh=slow,
            fast_directions=fd, fast_energy=fe, mask=g.mask, **extra,
        )
        img = np.asarray(out.total)
        base = os.path.join(out_dir, f"view_{k:03d}")
        for ext in (".exr", ".png"):
            p = os.path.abspath(base + ext)
            if p in inputs:
                raise ValueError(f"refusing to overwrite the input file {p}")
            jio.write_image(p, img)
            written.append(p)
    return written


def _mesh_visibility(mesh, g, fd):
    mask = np.asarray(g.mask)
    pts = np.asarray(g.position)[mask]
    nrm = np.asarray(g.normal)[mask]
    vws = np.asarray(g.view)[mask]
    shape = mask.shape
    extra = {}
    transfer = np.zeros(shape + (9,))
    transfer[mask] = np.asarray(jaxsh.visibility_sh(mesh, pts, nrm, 2, n_dirs=256))
    extra["transfer"] = jnp.asarray(transfer)
    rv = np.zeros(shape)
    rv[mask] = np.asarray(jaxsh.reflected_visibility(mesh, pts, nrm, vws))
    extra["reflected_visibility"] = jnp.asarray(rv)
    if fd is not None:
        fv = np.zeros(shape + (fd.shape[0],))
        fv[mask] = np.asarray(jaxsh.directional_visibility(mesh, pts, nrm, fd))
        extra["fast_visibility"] = jnp.asarray(fv)
    return extra
