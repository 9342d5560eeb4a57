"""`jaxsh render`: render every view of a capture manifest whose lighting and BRDF are given."""

from __future__ import annotations

import contextlib
import math
import os
import re
import sys

import jax.numpy as jnp
import numpy as np

import jaxsh
from jaxsh import io as jio

from ._sharing import render_rbf


def camera_from_manifest(c: dict):
    """A jaxsh camera from a validated manifest camera block."""
    if c["model"] == "pinhole":
        return jaxsh.PinholeCamera(c["fx"], c["fy"], c["cx"], c["cy"], c["width"], c["height"], c["cam_to_world"])
    return jaxsh.OrthographicCamera(c["scale"], c["width"], c["height"], c["cam_to_world"])


def lighting_from_manifest(m: dict, sigma: float, lmax: int | None = None):
    """(slow SH coefficients (n, 3) or None, fast directions (J, 3) or None, fast energy (J, 3) or None)."""
    return lighting_from_block(m["lighting"], sigma, lmax, manifest=m["path"], where="lighting")


def lighting_where(m: dict, blocks, k: int) -> str:
    """The field path of view `k`'s lighting block: `lighting` (the top-level one) or `views[k].lighting`."""
    return "lighting" if blocks is None or blocks[k] is m["lighting"] else f"views[{k}].lighting"


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


def lighting_from_block(lit: dict, sigma: float, lmax: int | None = None, *, manifest: str, where: str):
    """`lighting_from_manifest` for one validated lighting block (top-level or `views[k].lighting`).

    A map that cannot be used (unreadable, not finite) raises `ManifestError` naming `manifest`, the field
    `{where}.envmap` and the file."""
    slow = None
    if lit["envmap"] is not None:
        field = f"{where}.envmap"
        try:
            env = jio.read_envmap(lit["envmap"], up=lit["up"], layout=lit["layout"], encoding=lit.get("encoding"))
        except ValueError as e:
            raise jio.ManifestError(f"{manifest}: `{field}` cannot be used: {e}") from None
        bad = ~np.isfinite(env)
        if bad.any():
            i, j = np.argwhere(bad.any(-1))[0]
            raise jio.ManifestError(
                f"{manifest}: `{field}` has {int(bad.any(-1).sum())} non-finite (NaN/inf) pixels, e.g. (row {i}, "
                f"column {j}), after its conversion to a lat-long map in the library frame: {lit['envmap']}")
        env = env.astype(np.float64)
        h = env.shape[0]
        if lmax is None:
            if h < 2:
                raise jio.ManifestError(
                    f"{manifest}: `{field}` is {h} row high as a lat-long map (an angular map: half its size): too small "
                    f"for the default cut-off min(ceil(4/sigma), H/2 - 1) = -1; set `solve.render_lmax`: {lit['envmap']}")
            lmax = int(min(math.ceil(4.0 / sigma), h // 2 - 1))
        slow = jaxsh.project_latlong(env[..., :3], lmax)
        if lit.get("rotation") is not None:  # map frame -> world: the world's lighting is L(R^T w)
            slow = np.asarray(jaxsh.rotate_sh(slow, np.asarray(lit["rotation"], np.float64), channels=True))
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
    b = m["brdf"]
    if b is not None:
        paths += [b["file"]] if b["model"] == "rbf" else list(b["files"].values())
    return [os.path.abspath(p) for p in paths]


def check_unsupported(m: dict, command: str) -> None:
    """Stop with a one-line `ManifestError` on a parsed field the fitting/rendering code cannot use here.

    Every manifest field is used by both commands, with these exceptions: `jaxsh render` does not read captured
    images, so `views[k].mask`, `exposure`, `saturation` and every `solve` field but `render_lmax` are errors there
    (a view's `image` may still give the camera's size, with its `encoding` and `alpha`); an
    RBF `brdf` renders under directional sources only (Zickler 2006's
    reflectance is sampled under directional light; an environment map
    would need its integral over the RBF); `solve.brdf_model` other than
    `"torrance_sparrow"` needs one directional source per view.
    """
    b = m["brdf"]
    if command == "render":
        given = m.get("given", {})
        for k, keys in enumerate(given.get("views", [])):
            for key in ("mask", "exposure", "saturation"):
                if key in keys:
                    raise jio.ManifestError(
                        f"{m['path']}: `views[{k}].{key}` describes a captured image, which `jaxsh render` does not "
                        "read (it renders the model); remove it, or run `jaxsh fit`")
        unused = [key for key in given.get("solve", []) if key != "render_lmax"]
        if unused:
            raise jio.ManifestError(f"{m['path']}: `solve.{unused[0]}` is a setting of `jaxsh fit`; `jaxsh render` "
                                    "uses only `solve.render_lmax`")
    if command == "render" and b is not None and b["model"] == "rbf":
        for k, lit in enumerate(view_lighting_blocks(m, command) or [m["lighting"]] * len(m["views"])):
            if lit is not None and lit["envmap"] is not None:
                where = "lighting.envmap" if lit is m["lighting"] else f"views[{k}].lighting.envmap"
                raise jio.ManifestError(f"{m['path']}: `{where}` cannot light an RBF `brdf` (model \"rbf\"): "
                                        "`jaxsh render` renders RBF reflectance under `directional` sources only")


def same_camera(views: list) -> bool:
    """Whether every view of a validated manifest has the same camera block (one pixel grid)."""
    c0 = views[0]["camera"]
    return all(v["camera"].keys() == c0.keys() and all(
        np.array_equal(v["camera"][key], c0[key]) for key in c0) for v in views[1:])


def pixel_xy(width: int, height: int) -> np.ndarray:
    """Surface coordinates of a pixel grid for the SBRDF (Zickler eq. 13): $x = (j+\\frac12)/W$, $y = (i+\\frac12)/H$, `(H, W, 2)`."""
    j, i = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(height) + 0.5) / height)
    return np.stack([j, i], -1)


def view_geometry(m: dict, k: int, mesh, fd, cache: dict):
    """`(GBuffer, visibility keywords)` of view `k`: sphere, mesh (with sec. 6.4 visibility for the sources `fd`) or normal map.

    Normal maps (`geometry.normal_map` or `views[k].normal_map`) give no
    positions and so no shadows (`jaxsh.normal_map_gbuffer`); each file is
    read once (`cache`).
    """
    g = view_gbuffer(m, k, mesh, cache)
    return g, (_mesh_visibility(mesh, g, fd) if mesh is not None else {})


def view_gbuffer(m: dict, k: int, mesh, cache: dict):
    """The `GBuffer` of view `k` (sphere, mesh or normal map), its normals checked to face the camera
    (`_check_facing`). The last one made is kept in `cache` under its camera and normal map: consecutive views
    with one camera (a light stage, photometric stereo) raycast the mesh once."""
    view = m["views"][k]
    geo = m["geometry"]
    key = (tuple((name, np.asarray(value).tobytes()) for name, value in sorted(view["camera"].items())),
           view["normal_map"])
    last = cache.get(_LAST_GBUFFER)
    if last is not None and last[0] == key:
        return last[1]
    cam = camera_from_manifest(view["camera"])
    if mesh is not None:
        # `geometry.normals`: interpolated vertex normals of the merged mesh, or the flat normal of each face
        g = jaxsh.mesh_gbuffer(cam, mesh, smooth=geo.get("normals", "smooth") == "smooth")
        _check_facing(m, k, g, "geometry.mesh", geo["mesh"],
                      "its triangles are wound inside out (normals pointing into the object); reverse the winding "
                      "(trimesh: `mesh.invert()`)")
    elif "sphere" in geo:
        g = jaxsh.sphere_gbuffer(cam, geo["sphere"]["center"], geo["sphere"]["radius"])
    else:
        field = f"views[{k}].normal_map" if view["normal_map"] else "geometry.normal_map"
        g = jaxsh.normal_map_gbuffer(cam, view_normal_map(m, k, cache))
        _check_facing(m, k, g, field, view["normal_map"] or geo["normal_map"],
                      "normals must be in the world frame and point out of the object; a camera-frame map must be "
                      "turned into the world frame by the camera's `cam_to_world` rotation (OpenCV camera axes: +y "
                      "down, +z away from the viewer; many photometric-stereo maps use +y up, +z towards the viewer)")
    cache[_LAST_GBUFFER] = key, g
    return g


_LAST_GBUFFER = ("the last GBuffer",)  # `view_gbuffer`'s entry in the cache of normal maps, which are keyed by path


def _check_facing(m: dict, k: int, g, field: str, path: str, hint: str) -> None:
    """A surface seen by a camera faces it: n . v > 0 on the object (up to noise at the silhouette). When most of the
    object's pixels face away, the normals are in another frame or point inwards; that is a `ManifestError` naming
    the field and the file (before, the fit stopped with `no_signal` and the render was black)."""
    mask = np.asarray(g.mask)
    n_obj = int(mask.sum())
    away = int(np.count_nonzero(mask & (np.sum(np.asarray(g.normal) * np.asarray(g.view), -1) <= 0)))
    if n_obj and 2 * away > n_obj:
        raise jio.ManifestError(
            f"{m['path']}: `{field}`: {away} of the {n_obj} object pixels of `views[{k}]` have normals facing away "
            f"from `views[{k}].camera`: {hint}: {path}")


def manifest_mesh(m: dict):
    """The trimesh of `geometry.mesh` (`jaxsh.io.read_mesh`), or None; a file it cannot read is a `ManifestError`."""
    if "mesh" not in m["geometry"]:
        return None
    try:
        return jio.read_mesh(m["geometry"]["mesh"])
    except ValueError as e:
        raise jio.ManifestError(f"{m['path']}: `geometry.mesh` cannot be used: {e}") from None


def view_normal_map(m: dict, k: int, cache: dict):
    """The normal map of view `k` (`views[k].normal_map`, else `geometry.normal_map`), each file read once (`cache`).

    A map `jaxsh.io.read_normal_map` refuses raises `ManifestError` naming the manifest, the field and the file."""
    view = m["views"][k]
    field = f"views[{k}].normal_map" if view["normal_map"] else "geometry.normal_map"
    path = view["normal_map"] or m["geometry"]["normal_map"]
    if path not in cache:
        try:
            cache[path] = jio.read_normal_map(path)
        except ValueError as e:
            raise jio.ManifestError(f"{m['path']}: `{field}` cannot be used: {e}") from None
    return cache[path]


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


# The names of the files `jaxsh fit` and `jaxsh render` write into `--out`
_OUTPUT_NAME = re.compile(r"view_\d{3,}\.(exr|png)|result\.json|lighting\.(exr|png)|brdf_rbf\.npz|k[ds]\.exr")


def stale_outputs(out_dir, written) -> list[str]:
    """The files of `out_dir` named like an output of `jaxsh fit` / `jaxsh render` that are not in `written` (output
    paths of this run), sorted: left by an earlier run into the same folder (e.g. `view_005.exr` of a capture with
    more views). The commands never delete them; they name them (`solvers/cli.py`)."""
    mine = {os.path.realpath(p) for p in written}
    try:
        names = os.listdir(out_dir)
    except OSError:
        return []
    return sorted(os.path.join(out_dir, f) for f in names
                  if _OUTPUT_NAME.fullmatch(f) and os.path.realpath(os.path.join(out_dir, f)) not in mine)


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
    sigma = b["sigma"] if b["model"] == "torrance_sparrow" else 0.1  # an RBF is lit by directional sources only
    if blocks is None:
        blocks = [m["lighting"]] * n
    cache = {}  # blocks shared by several views (the top-level one) are read once

    def lit_of(k):
        key = id(blocks[k])
        if key not in cache:
            cache[key] = lighting_from_block(blocks[k], sigma, lmax, manifest=m["path"],
                                             where=lighting_where(m, blocks, k))
        return cache[key]

    mesh = manifest_mesh(m)
    # every input read (and refused) before the first output is written
    lights = [lit_of(k) for k in range(n)]
    maps = {}
    for k in range(n):  # and every view's geometry (normal maps, the facing checks): one camera, one raycast
        view_gbuffer(m, k, mesh, maps)
    os.makedirs(out_dir, exist_ok=True)
    written = []
    for k, view in enumerate(m["views"]):
        if progress:
            print(f"[{k + 1}/{n}] rendering view {k}", file=sys.stderr, flush=True)
        slow, fd, fe = lights[k]
        g, extra = view_geometry(m, k, mesh, fd, maps)
        if b["model"] == "rbf":
            img = render_rbf_view(b, g, fd, fe, extra.get("fast_visibility"))
        else:
            out = jaxsh.render_practical(
                g.normal, g.view, b["kd"], b["ks"], b["mu"], b["sigma"], slow_sh=slow,
                fast_directions=fd, fast_energy=fe, mask=g.mask, **extra,
            )
            img = np.asarray(out.total)
        for p in outs[2 * k : 2 * k + 2]:
            jio.write_image(p, img)
            written.append(p)
    return written


def render_rbf_view(b: dict, g, fd, fe, fast_visibility=None) -> np.ndarray:
    """One view under directional sources from an RBF `brdf` block: the sum of `solvers.render_rbf` over the sources."""
    rbf = b["rbf"]
    mask = np.asarray(g.mask)
    xy = pixel_xy(rbf["width"], rbf["height"]) if rbf["spatial"] else None
    w = rbf["model"].weights
    c = int(w.shape[1]) if w.ndim == 2 else 1
    # a one-channel (grey) model under RGB sources renders RGB (`render_rbf` broadcasts it)
    img = np.zeros(mask.shape + (3 if c == 1 and fe is not None and np.shape(fe)[-1] == 3 else c,))
    for j in range(0 if fd is None else len(fd)):
        vis = mask if fast_visibility is None else mask & (np.asarray(fast_visibility)[..., j] > 0.5)
        img += np.asarray(render_rbf(rbf["model"], g.normal, g.view, fd[j], fe[j], mask=vis, xy=xy)).reshape(img.shape)
    return img


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
