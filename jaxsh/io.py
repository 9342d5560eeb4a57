"""File input/output: images (OpenImageIO) and environment maps.

The only module of `jaxsh` that touches files. Images are linear float
radiance `(H, W, C)` float32 NumPy arrays; PNG/JPEG are for viewing only
(written tone-mapped and sRGB-encoded, read back decoded to linear).

Environment maps are returned as lat-long images in the library's frame
(DESIGN.md): +z up, row `i` ↔ θ = π(i+½)/H from +z, column `j` ↔
φ = 2π(j+½)/W from +x towards +y. Files whose up axis is +y (most HDR maps,
e.g. the USC light probes) are converted by an explicit rotation, never by
guessing: with `up="+y"`, file axes $(x, y, z)$ map to library axes
$(x, -z, y)$ — up goes to +z, the image centre (file −z) to +y, and the
file's +x (u = 0.75 of a lat-long file) stays +x.
"""

from __future__ import annotations

import os

import numpy as np

from ._grids import latlong_directions

__all__ = ["read_image", "write_image", "read_envmap", "read_manifest", "read_mesh", "ManifestError", "Y_UP_TO_Z_UP"]

#: Rotation taking a +y-up file frame to the library's +z-up frame: lib = M @ file.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

_LDR = {".png", ".jpg", ".jpeg", ".tif8"}


def _oiio():
    import OpenImageIO as oiio

    return oiio


def read_image(path) -> np.ndarray:
    """Read an image as float32 `(H, W, C)` linear values.

    EXR, HDR (RGBE), PFM, TIFF are read as stored; 8/16-bit PNG/JPEG are
    decoded from sRGB to linear. Raises `FileNotFoundError` / `ValueError`
    naming the file when it is missing or unreadable.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"image file not found: {path}")
    oiio = _oiio()
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ValueError(f"cannot read image {path!r}: {oiio.geterror()}")
    try:
        data = inp.read_image("float")
        if data is None:
            raise ValueError(f"cannot read image {path!r}: {inp.geterror()}")
        spec = inp.spec()
        colorspace = spec.get_string_attribute("oiio:ColorSpace", "")
    finally:
        inp.close()
    arr = np.asarray(data, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    ext = os.path.splitext(path)[1].lower()
    if ext == ".pfm":
        # PFM stores scanlines bottom to top; OpenImageIO 3.2 returns them in
        # file order (its writer is conformant), so flip to top-to-bottom here.
        arr = arr[::-1].copy()
    if ext in _LDR or colorspace.lower() in ("srgb", "srgb_rec709_scene", "srgb:g22:rec709"):
        arr = _srgb_to_linear(arr)
    return arr


def write_image(path, array, *, exposure: float = 0.0) -> None:
    """Write a float image `(H, W)` or `(H, W, C)`.

    EXR/HDR/PFM/TIFF store linear float values. PNG/JPEG are for viewing:
    the values are scaled by `2**exposure`, clipped to [0, 1] and
    sRGB-encoded to 8 bits. Refuses to overwrite a file that an open input
    of the same path would need (never writes over an input: callers pass
    output directories); raises `ValueError` naming the file on failure.
    """
    path = os.fspath(path)
    arr = np.asarray(array, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3:
        raise ValueError(f"`array` must have shape (H, W) or (H, W, C), got {arr.shape} (writing {path})")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"refusing to write non-finite values to {path}")
    oiio = _oiio()
    ext = os.path.splitext(path)[1].lower()
    h, w, c = arr.shape
    if ext in _LDR:
        data = np.clip(_linear_to_srgb(np.clip(arr * 2.0**exposure, 0.0, 1.0)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        spec = oiio.ImageSpec(w, h, c, "uint8")
    else:
        data = arr
        spec = oiio.ImageSpec(w, h, c, "float" if ext != ".hdr" else "float")
    out = oiio.ImageOutput.create(path)
    if out is None:
        raise ValueError(f"cannot write image {path!r}: {oiio.geterror()}")
    try:
        if not out.open(path, spec):
            raise ValueError(f"cannot write image {path!r}: {out.geterror()}")
        if not out.write_image(np.ascontiguousarray(data)):
            raise ValueError(f"cannot write image {path!r}: {out.geterror()}")
    finally:
        out.close()


def _srgb_to_linear(x):
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _linear_to_srgb(x):
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _bilinear_wrap(img, u, v):
    """Sample img (H, W, C) at continuous pixel coords (u: column, v: row), wrapping in u."""
    h, w = img.shape[:2]
    x = u - 0.5
    y = np.clip(v - 0.5, 0, h - 1)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    y1 = np.minimum(y0 + 1, h - 1)
    x0w, x1w = x0 % w, (x0 + 1) % w
    top = img[y0, x0w] * (1 - fx) + img[y0, x1w] * fx
    bot = img[y1, x0w] * (1 - fx) + img[y1, x1w] * fx
    return top * (1 - fy) + bot * fy


def _bilinear_clamp(img, u, v):
    h, w = img.shape[:2]
    x = np.clip(u - 0.5, 0, w - 1)
    y = np.clip(v - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(int), w - 2 if w > 1 else 0)
    y0 = np.minimum(np.floor(y).astype(int), h - 2 if h > 1 else 0)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    return (img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy) + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy


def read_envmap(path, up: str = "+z", layout: str = "latlong", height: int | None = None) -> np.ndarray:
    """Read an environment map and return it as a lat-long map in the library frame.

    **Arguments:**

    - `path`: an image file (EXR, HDR, PFM, ...).
    - `up`: the file's up axis, `"+z"` (already the library convention) or
      `"+y"` (converted by `Y_UP_TO_Z_UP`). Never guessed.
    - `layout`: `"latlong"` (equirectangular; for `"+y"` files: row 0 at +y,
      u = column/width with u = 0.5 looking along −z and u = 0.75 along +x)
      or `"angular"` (Debevec angular map, see
      `jaxsh.angular_map_directions`; its frame is +y up).
    - `height`: output rows (width = 2·height). Default: the file's height for
      lat-long, half the size for angular maps.

    A `"+y"` lat-long file whose width is a multiple of 4 and whose size is
    kept is remapped exactly (a column permutation); otherwise the map is
    resampled bilinearly (angular maps always are).

    **Returns:** float32 `(H, 2H, C)` (for `"+z"` lat-long files: the file as is).
    """
    if up not in ("+z", "+y"):
        raise ValueError(f'`up` must be "+z" or "+y", got {up!r}')
    if layout not in ("latlong", "angular"):
        raise ValueError(f'`layout` must be "latlong" or "angular", got {layout!r}')
    img = read_image(path)
    fh, fw = img.shape[:2]
    if layout == "latlong":
        if fw != 2 * fh:
            raise ValueError(f"lat-long map {path!r} must be twice as wide as high, got {fw}x{fh}")
        if up == "+z" and height in (None, fh):
            return img
        h = fh if height is None else int(height)
        if up == "+y" and h == fh and fw % 4 == 0:
            # library phi_j <-> file u = 0.75 - (j + 1/2)/W: column k = 3W/4 - 1 - j (mod W)
            cols = (3 * fw // 4 - 1 - np.arange(fw)) % fw
            return np.ascontiguousarray(img[:, cols])
        d = np.asarray(latlong_directions(h, 2 * h, dtype=np.float64))
        fd = d @ Y_UP_TO_Z_UP if up == "+y" else d  # file-frame direction: M^T d
        if up == "+y":
            theta = np.arccos(np.clip(fd[..., 1], -1, 1))
            u = np.mod(np.arctan2(-fd[..., 0], fd[..., 2]) / (2 * np.pi), 1.0)
        else:
            theta = np.arccos(np.clip(fd[..., 2], -1, 1))
            u = np.mod(np.arctan2(fd[..., 1], fd[..., 0]) / (2 * np.pi), 1.0)
        return _bilinear_wrap(img, u * fw, theta / np.pi * fh).astype(np.float32)
    # angular map
    if fw != fh:
        raise ValueError(f"angular map {path!r} must be square, got {fw}x{fh}")
    h = fh // 2 if height is None else int(height)
    d = np.asarray(latlong_directions(h, 2 * h, dtype=np.float64))
    fd = d @ Y_UP_TO_Z_UP if up == "+y" else d
    # file frame of an angular map: x right, y up, centre looking along -z
    ang = np.arccos(np.clip(-fd[..., 2], -1, 1))  # angle from the centre direction
    r = ang / np.pi
    rho = np.hypot(fd[..., 0], fd[..., 1])
    safe = np.where(rho > 0, rho, 1.0)
    uu = np.where(rho > 0, fd[..., 0] / safe, 0.0) * r
    vv = np.where(rho > 0, fd[..., 1] / safe, 0.0) * r
    col = (uu + 1) / 2 * fw
    row = (1 - vv) / 2 * fh
    return _bilinear_clamp(img, col, row).astype(np.float32)


# ----------------------------------------------------------------------------- capture manifests


class ManifestError(ValueError):
    """A capture manifest that cannot be used; the message names the file and the field."""


def _field(d, key, where, path, kind=None, required=True, default=None):
    if not isinstance(d, dict):
        raise ManifestError(f"{path}: `{where}` must be an object")
    if key not in d or d[key] is None:
        if required:
            raise ManifestError(f"{path}: missing field `{where}.{key}`")
        return default
    v = d[key]
    if kind == "number":
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ManifestError(f"{path}: `{where}.{key}` must be a number, got {v!r}")
        return float(v)
    if kind == "string" and not isinstance(v, str):
        raise ManifestError(f"{path}: `{where}.{key}` must be a string, got {v!r}")
    return v


def _array(v, shape, where, path):
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ManifestError(f"{path}: `{where}` must be numeric with shape {shape}") from None
    if shape is not None and a.shape != shape:
        raise ManifestError(f"{path}: `{where}` must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ManifestError(f"{path}: `{where}` has non-finite values")
    return a


def _rgb(v, where, path):
    a = _array(v, None, where, path)
    if a.shape == ():
        return np.full(3, float(a))
    if a.shape != (3,):
        raise ManifestError(f"{path}: `{where}` must be a number or [r, g, b], got shape {a.shape}")
    return a


def read_manifest(path) -> dict:
    """Read and validate a capture manifest (DESIGN.md, "Capture manifest").

    Paths inside are resolved relative to the manifest. Returns a plain dict:

    - `geometry`: `{"sphere": {"center": (3,), "radius": float}}` or `{"mesh": abs_path}`;
    - `views`: list of `{"image": abs_path | None, "mask": abs_path | None, "camera": {...}}`
      with the camera's `model` ("pinhole" or "orthographic"), its intrinsics,
      `width`, `height` (from the camera block, else from the image when it
      exists) and `cam_to_world` `(4, 4)`;
    - `lighting`: None (unknown) or `{"envmap": abs_path | None, "up", "layout",
      "directional": [{"direction": (3,) unit, "radiance": (3,)}]}`;
    - `brdf`: None (unknown) or `{"model": "torrance_sparrow", "kd": (3,), "ks": (3,), "mu", "sigma"}`;
    - `solve`: dict (options, e.g. `lighting_lmax`).

    Every problem raises `ManifestError` (a `ValueError`) naming the file and the field.
    """
    import json

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"manifest not found: {path}")
    try:
        with open(path) as f:
            raw = json.load(f)
    except json.JSONDecodeError as e:
        raise ManifestError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(raw, dict):
        raise ManifestError(f"{path}: the manifest must be a JSON object")
    base = os.path.dirname(os.path.abspath(path))

    def resolve(p, where):
        if not isinstance(p, str) or not p:
            raise ManifestError(f"{path}: `{where}` must be a file name")
        return os.path.normpath(os.path.join(base, p))

    geo = _field(raw, "geometry", "", path)
    if not isinstance(geo, dict) or len(set(geo) & {"mesh", "sphere"}) != 1:
        raise ManifestError(f'{path}: `geometry` must have exactly one of "mesh" or "sphere"')
    if "sphere" in geo:
        sph = geo["sphere"]
        center = _array(_field(sph, "center", "geometry.sphere", path), (3,), "geometry.sphere.center", path)
        radius = _field(sph, "radius", "geometry.sphere", path, "number")
        if radius <= 0:
            raise ManifestError(f"{path}: `geometry.sphere.radius` must be > 0, got {radius}")
        geometry = {"sphere": {"center": center, "radius": radius}}
    else:
        mesh = resolve(geo["mesh"], "geometry.mesh")
        if not os.path.exists(mesh):
            raise ManifestError(f"{path}: `geometry.mesh` file not found: {mesh}")
        geometry = {"mesh": mesh}

    views_raw = _field(raw, "views", "", path)
    if not isinstance(views_raw, list) or not views_raw:
        raise ManifestError(f"{path}: `views` must be a non-empty list")
    views = []
    for k, v in enumerate(views_raw):
        where = f"views[{k}]"
        image = resolve(v["image"], f"{where}.image") if isinstance(v, dict) and v.get("image") else None
        mask = resolve(v["mask"], f"{where}.mask") if isinstance(v, dict) and v.get("mask") else None
        cam = _field(v, "camera", where, path)
        model = _field(cam, "model", f"{where}.camera", path, "string")
        cw = f"{where}.camera"
        c = {"model": model}
        if model == "pinhole":
            for key in ("fx", "fy", "cx", "cy"):
                c[key] = _field(cam, key, cw, path, "number")
            if c["fx"] <= 0 or c["fy"] <= 0:
                raise ManifestError(f"{path}: `{cw}.fx` and `{cw}.fy` must be > 0")
        elif model == "orthographic":
            c["scale"] = _field(cam, "scale", cw, path, "number")
            if c["scale"] <= 0:
                raise ManifestError(f"{path}: `{cw}.scale` must be > 0")
        else:
            raise ManifestError(f'{path}: `{cw}.model` must be "pinhole" or "orthographic", got {model!r}')
        m = _array(_field(cam, "cam_to_world", cw, path), (4, 4), f"{cw}.cam_to_world", path)
        rot = m[:3, :3]
        if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-6 or np.linalg.det(rot) < 0:
            raise ManifestError(f"{path}: `{cw}.cam_to_world` must hold a rotation (orthonormal, det +1)")
        c["cam_to_world"] = m
        w = _field(cam, "width", cw, path, "number", required=False)
        h = _field(cam, "height", cw, path, "number", required=False)
        if (w is None or h is None) and image is not None and os.path.exists(image):
            img = read_image(image)
            h, w = img.shape[:2]
        if w is None or h is None:
            raise ManifestError(f"{path}: `{cw}.width`/`height` are needed (or an existing `{where}.image`)")
        c["width"], c["height"] = int(w), int(h)
        views.append({"image": image, "mask": mask, "camera": c})

    lighting = None
    lraw = raw.get("lighting")
    if lraw is not None:
        if not isinstance(lraw, dict):
            raise ManifestError(f"{path}: `lighting` must be an object or null")
        env = resolve(lraw["envmap"], "lighting.envmap") if lraw.get("envmap") else None
        if env is not None and not os.path.exists(env):
            raise ManifestError(f"{path}: `lighting.envmap` file not found: {env}")
        up = lraw.get("up", "+z")
        layout = lraw.get("layout", "latlong")
        if up not in ("+z", "+y"):
            raise ManifestError(f'{path}: `lighting.up` must be "+z" or "+y", got {up!r}')
        if layout not in ("latlong", "angular"):
            raise ManifestError(f'{path}: `lighting.layout` must be "latlong" or "angular", got {layout!r}')
        dirs = []
        for j, s in enumerate(lraw.get("directional") or []):
            d = _array(_field(s, "direction", f"lighting.directional[{j}]", path), (3,), f"lighting.directional[{j}].direction", path)
            if np.linalg.norm(d) == 0:
                raise ManifestError(f"{path}: `lighting.directional[{j}].direction` must be non-zero")
            r = _rgb(_field(s, "radiance", f"lighting.directional[{j}]", path), f"lighting.directional[{j}].radiance", path)
            dirs.append({"direction": d / np.linalg.norm(d), "radiance": r})
        if env is None and not dirs:
            raise ManifestError(f"{path}: `lighting` has neither an `envmap` nor `directional` sources")
        lighting = {"envmap": env, "up": up, "layout": layout, "directional": dirs}

    brdf = None
    braw = raw.get("brdf")
    if braw is not None:
        model = _field(braw, "model", "brdf", path, "string")
        if model != "torrance_sparrow":
            raise ManifestError(f'{path}: `brdf.model` must be "torrance_sparrow", got {model!r}')
        brdf = {
            "model": model,
            "kd": _rgb(_field(braw, "kd", "brdf", path), "brdf.kd", path),
            "ks": _rgb(_field(braw, "ks", "brdf", path), "brdf.ks", path),
            "mu": _field(braw, "mu", "brdf", path, "number"),
            "sigma": _field(braw, "sigma", "brdf", path, "number"),
        }
        if not brdf["sigma"] > 0:
            raise ManifestError(f"{path}: `brdf.sigma` must be > 0")
        if not brdf["mu"] > 0:
            raise ManifestError(f"{path}: `brdf.mu` must be > 0")
    solve = raw.get("solve") or {}
    if not isinstance(solve, dict):
        raise ManifestError(f"{path}: `solve` must be an object")
    return {"path": os.path.abspath(path), "geometry": geometry, "views": views, "lighting": lighting, "brdf": brdf, "solve": solve}


def read_mesh(path):
    """Load a triangle mesh (OBJ, PLY, STL, ...) with trimesh, positions only, merged vertices."""
    import trimesh

    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        loaded = trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # trimesh raises many types
        raise ValueError(f"cannot read mesh {path!r}: {e}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"mesh {path!r} has no triangles")
    mesh = trimesh.Trimesh(vertices=np.asarray(loaded.vertices), faces=np.asarray(loaded.faces), process=True)
    return mesh
