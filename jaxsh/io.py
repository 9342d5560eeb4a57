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

__all__ = ["read_image", "write_image", "read_envmap", "Y_UP_TO_Z_UP"]

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
