"""`jaxsh render`: render every view of a capture manifest whose lighting and BRDF are given."""

from __future__ import annotations

import contextlib
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
    return lighting_from_block(m["lighting"], sigma, lmax)


def view_lighting_blocks(m: dict, command: str) -> list[dict] | None:
    """The lighting block of every view: `views[k].lighting`, else the top-level `lighting`.

    `None` when no view has its own lighting (the top-level one, maybe `null`, lights all views).
    Raises `ManifestError` when some views have no lighting at all.
    """
    own = [v.get("lighting") for v in m["views"]]
    if all(x is None for x in own):
        return None
    blocks = [x if x is not None else m["lighting"] for x in own]
    missing = [k for k, x in enumerate(blocks) if x is None]
    if missing:
        raise jio.ManifestError(
            f"{m['path']}: `views[{missing[0]}].lighting` is missing and there is no top-level `lighting`: "
            f"`jaxsh {command}` needs the lighting of every view once one view has its own"
        )
    return blocks


def lighting_from_block(lit: dict, sigma: float, lmax: int | None = None):
    """`lighting_from_manifest` for one validated lighting block (top-level or `views[k].lighting`)."""
    slow = None
    if lit["envmap"] is not None:
        env = jio.read_envmap(lit["envmap"], up=lit["up"], layout=lit["layout"], encoding=lit.get("encoding")).astype(np.float64)
        h = env.shape[0]
        if lmax is None:
            lmax = int(min(math.ceil(4.0 / sigma), h // 2 - 1))
        slow = jaxsh.project_latlong(env[..., :3], lmax)
    fd = fe = None
    if lit["directional"]:
        fd = np.stack([s["direction"] for s in lit["directional"]])
        fe = np.stack([s["radiance"] for s in lit["directional"]])
    return slow, fd, fe


def _inputs(m: dict) -> list[str]:
    """Every file a validated manifest reads (the manifest itself included)."""
    paths = [m["path"]]
    geo = m["geometry"]
    paths += [geo[k] for k in ("mesh", "normal_map") if k in geo]
    lightings = [m["lighting"]] + [v.get("lighting") for v in m["views"]]
    paths += [lit["envmap"] for lit in lightings if lit and lit.get("envmap")]
    for v in m["views"]:
        paths += [v[k] for k in ("image", "mask", "normal_map") if v.get(k)]
    return [os.path.abspath(p) for p in paths]


def check_unsupported(m: dict, command: str) -> None:
    """Stop with a one-line `ManifestError` on a parsed field the fitting/rendering code cannot use yet."""
    fields = []
    if "normal_map" in m["geometry"]:
        fields.append("geometry.normal_map")
    for k, v in enumerate(m["views"]):
        if v.get("normal_map"):
            fields.append(f"views[{k}].normal_map")
    if m["solve"].get("brdf_model", "torrance_sparrow") != "torrance_sparrow":
        fields.append(f"solve.brdf_model = {m['solve']['brdf_model']!r}")
    if fields:
        more = f" (and {len(fields) - 1} more)" if len(fields) > 1 else ""
        raise jio.ManifestError(f"{m['path']}: `{fields[0]}` is not supported yet by `jaxsh {command}`{more}")


def check_outputs(m: dict, out_dir, names) -> list[str]:
    """Check `--out` before any work; return the absolute output paths for `names`.

    Refuses (`ValueError`, one line) an `out_dir` that exists and is not a
    directory, and any output that would replace an input: compared by real
    path (symlinks, `--out .`, an input inside the output folder) and by file
    identity (`st_dev`, `st_ino`: hard links).
    """
    out_dir = os.fspath(out_dir)
    if os.path.lexists(out_dir) and not os.path.isdir(out_dir):
        raise ValueError(f"--out {out_dir}: exists and is not a directory")
    real = {}
    ids = {}
    for p in _inputs(m):
        real[os.path.realpath(p)] = p
        with contextlib.suppress(OSError):
            st = os.stat(p)
            ids[(st.st_dev, st.st_ino)] = p
    outs = []
    for name in names:
        p = os.path.abspath(os.path.join(out_dir, name))
        hit = real.get(os.path.realpath(p))
        if hit is None and os.path.exists(p):
            st = os.stat(p)
            hit = ids.get((st.st_dev, st.st_ino))
        if hit is not None:
            same = "" if os.path.realpath(p) == os.path.realpath(hit) else " (the same file)"
            raise ValueError(f"--out {out_dir}: refusing to overwrite the input file {hit} with the output {p}{same}")
        if os.path.isdir(p):
            raise ValueError(f"--out {out_dir}: the output {p} is a directory")
        outs.append(p)
    return outs


def render_manifest(manifest_path, out_dir, progress: bool = True) -> list[str]:
    """Render all views with the practical model (R&H eq. 24) and write `view_###.exr/.png`.

    Meshes get shadowing (directional and reflected visibility) and
    visibility-weighted irradiance (SH transfer vectors, lmax 2) computed once
    per view (R&H sec. 6.4). Everything is checked before rendering: raises
    `ManifestError`/`ValueError` if lighting or BRDF are not given, a parsed
    field is not supported yet, or an output would overwrite an input.
    Files are written atomically.
    """
    m = jio.read_manifest(manifest_path)
    blocks = view_lighting_blocks(m, "render")
    if (m["lighting"] is None and blocks is None) or m["brdf"] is None:
        raise jio.ManifestError(f"{m['path']}: `jaxsh render` needs both `lighting` and `brdf` in the manifest")
    check_unsupported(m, "render")
    n = len(m["views"])
    outs = check_outputs(m, out_dir, [f"view_{k:03d}{ext}" for k in range(n) for ext in (".exr", ".png")])
    b = m["brdf"]
    lmax = m["solve"].get("render_lmax")
    if blocks is None:
        blocks = [m["lighting"]] * n
    cache = {}  # blocks shared by several views (the top-level one) are read once

    def lit_of(k):
        key = id(blocks[k])
        if key not in cache:
            cache[key] = lighting_from_block(blocks[k], b["sigma"], lmax)
        return cache[key]

    mesh = jio.read_mesh(m["geometry"]["mesh"]) if "mesh" in m["geometry"] else None
    os.makedirs(out_dir, exist_ok=True)
    written = []
    for k, view in enumerate(m["views"]):
        if progress:
            print(f"[{k + 1}/{n}] rendering view {k}", file=sys.stderr, flush=True)
        cam = camera_from_manifest(view["camera"])
        slow, fd, fe = lit_of(k)
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
        for p in outs[2 * k : 2 * k + 2]:
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
