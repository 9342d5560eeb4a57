"""File input/output: images (OpenImageIO), environment maps, normal maps, meshes, manifests.

The only module of `jaxsh` that touches files. Images are linear float
radiance `(H, W, C)` float32 NumPy arrays.

**Encodings are declared, never guessed.** EXR, HDR (RGBE), PFM and float
TIFF hold linear values. An 8- or 16-bit integer image (PNG, TIFF, JPEG)
holds code values whose meaning the file does not reliably say (a 16-bit
*linear* PNG is as common in photometric capture as an sRGB one), so the
caller declares it: `read_image(path, encoding="linear" | "srgb")`. Code
values are scaled by the format's maximum (255 or 65535) and, for `"srgb"`,
decoded by the IEC 61966-2-1 transfer function. PNG/JPEG *outputs* are for
viewing only (written clipped and sRGB-encoded to 8 bits).

**Pixels as displayed, values as stored.** Row 0 is the top of the image as
displayed (the display window, turned by the EXIF/TIFF orientation tag);
colour is never multiplied or divided by alpha, and an alpha channel is
declared by the caller (`read_radiance(..., alpha=)`), never guessed.

Every file this module writes is written atomically (`atomic_output`): to a
temporary file in the same folder, then renamed over the target, so an
interrupted run never leaves a half-written file.

Environment maps are returned as lat-long images in the library's frame
(docs/conventions.md): +z up, row `i` ↔ θ = π(i+½)/H from +z, column `j` ↔
φ = 2π(j+½)/W from +x towards +y. Files whose up axis is +y (most HDR maps,
e.g. the USC light probes) are converted by an explicit rotation, never by
guessing: with `up="+y"`, file axes $(x, y, z)$ map to library axes
$(x, -z, y)$ — up goes to +z, the image centre (file −z) to +y, and the
file's +x (u = 0.75 of a lat-long file) stays +x.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile

import numpy as np


__all__ = [
    "read_image",
    "read_image_info",
    "read_radiance",
    "read_mask",
    "write_image",
    "write_json",
    "atomic_output",
    "read_envmap",
    "read_normal_map",
    "read_texture",
    "read_rbf",
    "recorded_camera",
    "write_rbf",
    "read_manifest",
    "read_mesh",
    "ManifestError",
    "ENCODINGS",
    "ALPHA_MODES",
    "Y_UP_TO_Z_UP",
]

#: Rotation taking a +y-up file frame to the library's +z-up frame: lib = M @ file.
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

#: The encodings `read_image` accepts for integer images.
ENCODINGS = ("linear", "srgb")

# extensions written as 8-bit sRGB (for viewing)
_LDR = {".png", ".jpg", ".jpeg"}
# the extensions `write_image` writes, and the channel counts each stores as given (other formats, e.g. BMP, TGA or
# WebP, would be quantized to 8 bits without the sRGB curve, or compressed lossily: refused). PNG's 2nd / 4th channel
# is its alpha (grey+alpha, RGBA); RGBE holds RGB; PFM grey or RGB; JPEG has no alpha.
_WRITE_CHANNELS = {".exr": None, ".tif": None, ".tiff": None, ".pfm": (1, 3), ".hdr": (3,), ".png": (1, 2, 3, 4),
                   ".jpg": (1, 3), ".jpeg": (1, 3)}


def _oiio():
    import OpenImageIO as oiio

    return oiio


def _check_readable(path: str, what: str = "image") -> None:
    if not os.path.exists(path):
        raise FileNotFoundError(f"{what} file not found: {path}")
    if os.path.isdir(path):
        raise IsADirectoryError(f"{path}: is a directory, expected a file ({what})")


# EXIF/TIFF `Orientation` (1-8): how the stored rows and columns map to the image as displayed. Each entry turns
# the stored array into the displayed one; 5-8 swap the axes. (OpenImageIO reports the tag and never applies it
# when reading: `ImageBufAlgo.reorient` does, and tests/test_io.py checks these against it.)
_ORIENT = {
    1: lambda a: a,
    2: lambda a: a[:, ::-1],  # mirrored left-right
    3: lambda a: a[::-1, ::-1],  # rotated 180 degrees
    4: lambda a: a[::-1],  # mirrored top-bottom (e.g. a Radiance file whose header says "+Y H +X W")
    5: lambda a: np.swapaxes(a, 0, 1),  # transposed
    6: lambda a: np.swapaxes(a, 0, 1)[:, ::-1],  # stored rotated 90 degrees counter-clockwise: turn clockwise
    7: lambda a: np.swapaxes(a, 0, 1)[::-1, ::-1],  # transverse
    8: lambda a: np.swapaxes(a, 0, 1)[::-1],  # stored rotated 90 degrees clockwise: turn counter-clockwise
}


def _layout(path: str, spec) -> dict:
    """Where the displayed image lies in the stored pixels: the display window's rows and columns inside the data
    window, and the orientation. Raises `ValueError` naming the file when the data window does not cover the display
    window (pixels the file does not hold) or the orientation is not 1-8."""
    orient = int(spec.get_int_attribute("Orientation", 1))
    if orient not in _ORIENT:
        raise ValueError(f"image {path!r}: unsupported orientation {orient} (the EXIF/TIFF tag holds 1-8)")
    x0, y0, w, h = int(spec.x), int(spec.y), int(spec.width), int(spec.height)
    fx, fy, fw, fh = int(spec.full_x), int(spec.full_y), int(spec.full_width), int(spec.full_height)
    if fw <= 0 or fh <= 0:  # formats without a display window
        fx, fy, fw, fh = x0, y0, w, h
    if not (x0 <= fx and y0 <= fy and fx + fw <= x0 + w and fy + fh <= y0 + h):
        raise ValueError(
            f"image {path!r}: its data window ({w}x{h} at ({x0}, {y0})) does not cover its display window "
            f"({fw}x{fh} at ({fx}, {fy})): the file does not hold every pixel of the image; write it with the "
            "data window covering the display window")
    rows, cols = slice(fy - y0, fy - y0 + fh), slice(fx - x0, fx - x0 + fw)
    size = (fh, fw) if orient <= 4 else (fw, fh)
    return {"rows": rows, "cols": cols, "orientation": orient, "height": size[0], "width": size[1]}


def _open(path: str):
    """An `ImageInput` that returns pixels as stored: OpenImageIO would otherwise multiply the colour of PNG/TIFF
    files by their (unassociated) alpha while reading. PFM files store their scanlines bottom to top; `pnm:pfmflip`
    returns them top first (OpenImageIO 3.2 does that by default only when a configuration is passed, as here)."""
    oiio = _oiio()
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    config.attribute("pnm:pfmflip", 1)
    inp = oiio.ImageInput.open(path, config)
    if inp is None:
        raise ValueError(f"cannot read image {path!r}: {oiio.geterror()}")
    return inp


def read_image_info(path) -> dict:
    """The header of an image file, without reading its pixels.

    **Returns:** `{"width", "height", "channels", "float": bool, "max_code": int | None, "bits": int,
    "alpha": bool, "orientation": int}`: `width` and `height` are those of the image as displayed (the file's
    display window, turned by its orientation tag, as `read_image` returns it); `float` is true for
    half/float/double pixels (linear values); `max_code` is 255 or 65535 for 8/16-bit integer pixels (None for
    float files); `alpha` says whether one channel is alpha (OpenImageIO's `alpha_channel`, e.g. the `A` of
    RGBA or grey+alpha); `orientation` is the EXIF/TIFF tag (1 when absent).
    Raises `FileNotFoundError` / `ValueError` naming the file.
    """
    path = os.fspath(path)
    _check_readable(path)
    inp = _open(path)
    try:
        info = _header(path, inp.spec())[0]
        _single_image(path, inp)
        return info
    finally:
        inp.close()


def _header(path: str, spec) -> tuple[dict, dict]:
    """(`read_image_info`'s dict, `_layout`) of an open file's spec."""
    oiio = _oiio()
    base = spec.format.basetype
    lay = _layout(path, spec)
    info = {"width": lay["width"], "height": lay["height"], "channels": int(spec.nchannels),
            "alpha": int(spec.alpha_channel) >= 0, "orientation": lay["orientation"]}
    if base in (oiio.HALF, oiio.FLOAT, oiio.DOUBLE):
        bits = {oiio.HALF: 16, oiio.FLOAT: 32, oiio.DOUBLE: 64}[base]
        return {**info, "float": True, "max_code": None, "bits": bits}, lay
    if base == oiio.UINT8:
        return {**info, "float": False, "max_code": 255, "bits": 8}, lay
    if base == oiio.UINT16:
        return {**info, "float": False, "max_code": 65535, "bits": 16}, lay
    raise ValueError(f"image {path!r}: unsupported pixel type {spec.format} (supported: 8/16-bit unsigned, half, float)")


def _read_pixels(path: str):
    """(float32 (H, W, C) array — integer codes divided by their maximum —, header info).

    The values are as stored (never multiplied by alpha), the rows and columns those of the image as displayed:
    the display window cut from the data window, then the orientation tag applied (`_layout`). Alpha, if any, is
    the channel `alpha_channel` of the file's spec, returned in its place. The file is opened once."""
    _check_readable(path)
    inp = _open(path)
    try:
        spec = inp.spec()
        info, lay = _header(path, spec)
        alpha_channel = int(spec.alpha_channel)
        data = inp.read_image("float")
        if data is None:
            raise ValueError(f"cannot read image {path!r}: {inp.geterror()}")
        _single_image(path, inp)
        scale = _radiance_scale(path) if inp.format_name() == "hdr" else None
    finally:
        inp.close()
    arr = np.asarray(data, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if scale is not None:
        arr = arr / scale[: arr.shape[-1]].astype(np.float32)
    arr = np.ascontiguousarray(_ORIENT[lay["orientation"]](arr[lay["rows"], lay["cols"]]))
    return arr, {**info, "alpha_channel": alpha_channel}


def _single_image(path: str, inp) -> None:
    """A file of several subimages (a multi-part EXR, a multi-page TIFF) is an error: which one holds the image would
    be a guess (only the first used to be read, without a word). Call it after reading: a failed seek leaves an
    error on `inp`, cleared here."""
    if not inp.seek_subimage(1, 0):
        inp.geterror()
        return
    n = 2
    while n < 1000 and inp.seek_subimage(n, 0):
        n += 1
    inp.geterror()
    raise ValueError(f"image {path!r} holds {n} subimages (parts or pages); jaxsh reads files of one image: "
                     "save the one that holds the picture on its own")


def _radiance_scale(path: str) -> np.ndarray | None:
    """Per-channel divisor `(3,)` of a Radiance `.hdr` (RGBE) file's header, or None when it is 1.

    The Radiance file format: "EXPOSURE: a multiplier that has been applied to all the pixels in the file ...
    cumulative, so the original pixel values (radiances) must be derived by taking the values in the file and
    dividing by all the EXPOSURE settings multiplied together"; COLORCORR likewise per channel (e.g. `pfilt`
    writes both). OpenImageIO reports only the last EXPOSURE line, so the header is read here. A GAMMA line other
    than 1 and XYZE pixels (CIE XYZ, not RGB) are errors."""
    with open(path, "rb") as f:
        head = f.read(65536)
    end = head.find(b"\n\n")
    lines = (head if end < 0 else head[:end]).split(b"\n")
    scale = np.ones(3)

    def numbers(line, n):
        try:
            vals = [float(t) for t in line.split(b"=", 1)[1].split()]
        except ValueError:
            vals = []
        if len(vals) != n or not all(np.isfinite(vals)) or not all(v > 0 for v in vals):
            raise ValueError(f"Radiance image {path!r}: cannot read the header line {line.decode(errors='replace')!r}")
        return vals

    for line in lines:
        key = line.split(b"=", 1)[0].strip().upper()
        if key == b"EXPOSURE":
            scale = scale * numbers(line, 1)[0]
        elif key == b"COLORCORR":
            scale = scale * np.asarray(numbers(line, 3))
        elif key == b"GAMMA" and numbers(line, 1)[0] != 1.0:
            raise ValueError(f"Radiance image {path!r}: its header declares {line.decode(errors='replace')!r}; "
                             "linear values are read, and a gamma would make them a guess")
        elif key == b"FORMAT" and b"xyze" in line.lower():
            raise ValueError(f"Radiance image {path!r} holds CIE XYZ pixels (FORMAT=32-bit_rle_xyze), not RGB")
    return None if np.all(scale == 1.0) else scale


def _check_encoding(path: str, encoding, info: dict) -> str:
    if encoding is not None and encoding not in ENCODINGS:
        raise ValueError(f'`encoding` must be "linear", "srgb" or None, got {encoding!r} (reading {path})')
    if info["float"]:
        if encoding == "srgb":
            raise ValueError(
                f'{path}: a float image holds linear values; `encoding="srgb"` is only for 8/16-bit integer images'
            )
        return "linear"
    if encoding is None:
        raise ValueError(
            f'{path}: {info["bits"]}-bit integer image: declare its `encoding` ("linear" or "srgb"); '
            "it is never guessed"
        )
    return encoding


def _decode(arr, enc: str, alpha_channel: int):
    """sRGB-decode the colour channels (alpha is a coverage, scaled linearly, never through a transfer curve)."""
    if enc != "srgb":
        return arr
    out = _srgb_to_linear(arr)
    if alpha_channel >= 0:
        out[..., alpha_channel] = arr[..., alpha_channel]
    return out


def read_image(path, encoding: str | None = None) -> np.ndarray:
    """Read an image as float32 `(H, W, C)` linear values.

    **Arguments:**

    - `path`: EXR, HDR (RGBE), PFM or float TIFF (linear values, read as
      stored), or an 8/16-bit PNG, TIFF or JPEG.
    - `encoding`: how integer code values map to linear values: `"linear"`
      ($v = c / c_\\max$) or `"srgb"` ($v = f^{-1}(c / c_\\max)$ with the
      IEC 61966-2-1 decoding $f^{-1}(x) = x / 12.92$ for $x \\le 0.04045$,
      else $((x + 0.055)/1.055)^{2.4}$), with $c_\\max$ = 255 or 65535.
      **Required for integer images** (`None` raises `ValueError` naming the
      file and `encoding`: metadata such as PNG's sRGB chunk is not trusted).
      Float images are linear: `None` or `"linear"`; `"srgb"` is an error.

    Row 0 is the top of the image as displayed: the file's display window
    (EXR files may store a larger data window, which is cut to it; a smaller
    one is an error) turned by its EXIF/TIFF orientation tag (a Radiance
    `.hdr` stored bottom-up reports tag 4). A Radiance `.hdr` is divided by its
    header's EXPOSURE and COLORCORR lines (cumulative, as the Radiance format
    defines them: the radiance the file represents; `pfilt` writes them); a
    GAMMA line other than 1 and XYZE pixels are errors. A file of several
    subimages (a multi-part EXR, a multi-page TIFF) is an error. Values are
    otherwise **as stored**: an
    alpha channel (`read_image_info(path)["alpha"]`) is returned in its place,
    scaled like the colour but never sRGB-decoded, and the colour is never
    multiplied or divided by it (PNG and TIFF store colour unassociated with
    alpha, EXR associated — premultiplied). `read_radiance` separates it.

    Raises `FileNotFoundError` / `IsADirectoryError` / `ValueError` naming
    the file when it is missing, a directory, unreadable or of an
    unsupported pixel type.
    """
    path = os.fspath(path)
    arr, info = _read_pixels(path)
    return _decode(arr, _check_encoding(path, encoding, info), info["alpha_channel"])


#: What `read_radiance` does with an alpha channel (`alpha=`).
ALPHA_MODES = ("ignore", "mask")


def _split_alpha(path: str, arr, info: dict, alpha, what: str = "image"):
    """(colour channels, alpha channel or None) of `_read_pixels`' output; `alpha` must be declared if there is one."""
    k = info["alpha_channel"]
    if k < 0:
        return arr, None
    if alpha not in ALPHA_MODES:
        raise ValueError(
            f"{what} {path!r} has an alpha channel: declare `alpha` as \"ignore\" (drop it) or \"mask\" (also drop "
            "the pixels whose alpha is at most half of full scale); it is never guessed"
            + ("" if alpha is None else f" (got {alpha!r})"))
    keep = [c for c in range(arr.shape[-1]) if c != k]
    return np.ascontiguousarray(arr[..., keep]), arr[..., k]


def _drop_opaque_alpha(arr, info: dict, refusal: str):
    """The colour channels of `_read_pixels`' output whose alpha channel, if any, is opaque everywhere (a partial
    alpha is a `ValueError` with the message `refusal`: for masks and environment maps it has no declared use)."""
    colour, cover = _split_alpha("", arr, info, "ignore")
    if cover is not None and not np.all(cover >= 1.0):
        raise ValueError(refusal)
    return colour


def read_radiance(path, encoding: str | None = None, exposure: float = 1.0, saturation: float | None = None,
                  alpha: str | None = None):
    """Read a captured image as linear radiance and the mask of its unclipped pixels.

    A pixel is *saturated* when any colour channel reaches `saturation` (`>=`),
    compared in the **file's own units** — code values for integer files,
    stored values for float files — before decoding or scaling. The
    radiance is `exposure · read_image(path, encoding)` without its alpha
    channel.

    **Arguments:**

    - `path`, `encoding`: as `read_image`.
    - `exposure`: a positive finite scale multiplied into the linear values.
    - `saturation`: the threshold; `None` means the format's maximum code
      value (255, 65535) for integer files and no threshold for float files.
    - `alpha`: **required when the file has an alpha channel** (`None` then
      raises `ValueError` naming the file and `alpha`): `"ignore"` drops the
      channel; `"mask"` drops it and marks pixels whose alpha is at most half
      of full scale (code ≤ c_max/2, or ≤ 0.5 in a float file) invalid. The
      colour is used as stored either way (never divided by alpha). Ignored
      for files without alpha.

    **Returns:** `(radiance float32 (H, W, C), valid bool (H, W))`, `C` the
    colour channels.
    """
    path = os.fspath(path)
    if isinstance(exposure, bool) or not isinstance(exposure, (int, float, np.floating, np.integer)) \
            or not math.isfinite(exposure) or exposure <= 0:
        raise ValueError(f"`exposure` must be a positive finite number, got {exposure!r} (reading {path})")
    if saturation is not None and (isinstance(saturation, bool)
                                   or not isinstance(saturation, (int, float, np.floating, np.integer))
                                   or not math.isfinite(saturation) or saturation <= 0):
        raise ValueError(f"`saturation` must be a positive finite number or None, got {saturation!r} (reading {path})")
    if alpha is not None and alpha not in ALPHA_MODES:
        raise ValueError(f'`alpha` must be "ignore", "mask" or None, got {alpha!r} (reading {path})')
    arr, info = _read_pixels(path)
    enc = _check_encoding(path, encoding, info)
    arr, cover = _split_alpha(path, arr, info, alpha)
    if info["float"]:
        file_units = arr
    else:
        file_units = np.round(arr.astype(np.float64) * info["max_code"])  # exact code values
        if saturation is None:
            saturation = info["max_code"]
    valid = np.ones(arr.shape[:2], bool) if saturation is None else ~np.any(file_units >= saturation, axis=-1)
    if cover is not None and alpha == "mask":
        valid &= cover > 0.5
    if enc == "srgb":
        arr = _srgb_to_linear(arr)
    if exposure != 1:
        arr = (arr * np.float32(exposure)).astype(np.float32)
    return arr, valid


def read_mask(path) -> np.ndarray:
    """Read a mask image: `True` where its first channel is above half of full scale.

    Integer files: code > c_max / 2 (c_max = 255 or 65535), with no transfer
    function (a mask is not radiance); float files: value > 0.5. A file with
    an alpha channel is accepted only if the alpha is opaque everywhere:
    otherwise which channel holds the mask would be a guess, and that is a
    `ValueError` naming the file.

    **Returns:** bool `(H, W)`.
    """
    path = os.fspath(path)
    arr, info = _read_pixels(path)
    arr = _drop_opaque_alpha(
        arr, info, f"mask {path!r} has an alpha channel that is not opaque everywhere: which channel holds the mask "
        "would be a guess; save the mask as one channel (a pixel is used where it is above half of full scale)")
    return arr[..., 0] > 0.5


# ----------------------------------------------------------------------------- atomic writes


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_output(path):
    """Context manager for writing `path` atomically.

    Yields a temporary path in the same folder (same extension, so format
    detection by extension still works). When the block exits normally the
    temporary file is renamed over `path` (`os.replace`, atomic on POSIX and
    Windows); if the block raises — or is interrupted — the temporary file
    is removed and `path` is left as it was. Replacing swaps the directory
    entry: a symlink or hard link at `path` is replaced, never written through.

        with atomic_output("out/result.json") as tmp:
            with open(tmp, "w") as f:
                f.write(text)
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        raise IsADirectoryError(f"{path}: is a directory, cannot write a file there")
    folder, base = os.path.split(os.path.abspath(path))
    ext = os.path.splitext(base)[1]
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=f".tmp{ext}", dir=folder)
    except OSError as e:  # a missing or read-only folder: name the target, not the temporary file
        raise type(e)(e.errno, f"{e.strerror} (cannot create a file in {folder})", path) from None
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file ordinary permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def write_json(path, obj, indent: int = 2) -> None:
    """Write `obj` as JSON, atomically (`atomic_output`).

    Non-finite numbers are an error (`ValueError` naming the file): JSON has
    no NaN or Infinity (callers write unknown values as `null`).
    """
    path = os.fspath(path)
    try:
        text = json.dumps(obj, indent=indent, allow_nan=False)
    except ValueError as e:
        raise ValueError(f"refusing to write {path}: {e}") from None
    except TypeError as e:  # e.g. a NumPy scalar: name the file
        raise TypeError(f"cannot write {path}: {e}") from None
    with atomic_output(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text + "\n")


def _write_pixels(path: str, spec, data) -> None:
    """Write `data` with OpenImageIO to `path` (a temporary file of `write_image`)."""
    oiio = _oiio()
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


def write_image(path, array, *, exposure: float = 0.0, camera: dict | None = None) -> None:
    """Write a float image `(H, W)` or `(H, W, C)`, atomically (`atomic_output`).

    The format is the extension's: EXR, PFM and TIFF (`.tif`, `.tiff`) store
    the values as given, as 32-bit floats; HDR (RGBE) stores non-negative RGB
    values with an 8-bit shared-exponent mantissa. PNG/JPEG are for viewing:
    the colour is scaled by `2**exposure`, clipped to [0, 1] and sRGB-encoded
    (IEC 61966-2-1) to 8 bits (read them back with `encoding="srgb"`). A PNG's
    alpha channel (the last of 2 or 4 channels: grey+alpha, RGBA) is stored
    unassociated, as given: clipped to [0, 1] and scaled linearly to 8 bits,
    neither sRGB-encoded nor scaled by `exposure`, and the colour is never
    multiplied or divided by it. Other extensions are refused.

    Channels each format stores: EXR and TIFF any number; PFM 1 or 3; HDR 3;
    PNG 1-4; JPEG 1 or 3.

    `exposure`: a finite number, for PNG/JPEG only (another format with a
    non-zero `exposure` is an error: it stores the values as given).

    `camera`: a camera block as `read_manifest` returns it (`views[k]["camera"]`),
    recorded in the header of an EXR file (attribute `jaxsh:camera`, JSON) for
    maps that hold one value per pixel of that camera (the texture maps of
    `jaxsh fit`); `recorded_camera` reads it back. EXR only.

    Impossible or lossy writes are errors (`ValueError` naming the file):
    complex, integer or non-numeric arrays (bool is written as 0 and 1),
    non-finite values (with their count), values beyond the float32 range,
    negative values to HDR (RGBE cannot store them), channel counts the
    format does not hold, empty arrays and unknown extensions.
    """
    path = os.fspath(path)
    raw = np.asarray(array)
    if np.iscomplexobj(raw):
        raise ValueError(f"{path}: refusing to write a complex array: images are real")
    if np.issubdtype(raw.dtype, np.integer):
        raise ValueError(f"`array` must hold float values (or bool), got dtype {raw.dtype} (writing {path}): integer "
                         "code values are not values; convert them (e.g. codes / 255) before writing")
    if not (np.issubdtype(raw.dtype, np.floating) or raw.dtype == bool):
        raise ValueError(f"`array` must be real numbers, got dtype {raw.dtype} (writing {path})")
    if raw.ndim not in (2, 3):
        raise ValueError(f"`array` must have shape (H, W) or (H, W, C), got {raw.shape} (writing {path})")
    if raw.size == 0:
        raise ValueError(f"`array` must have at least one row, column and channel, got shape {raw.shape} "
                         f"(writing {path})")
    ext = os.path.splitext(path)[1].lower()
    if ext not in _WRITE_CHANNELS:
        raise ValueError(f"{path}: cannot write {ext or 'a file without an extension'!r}: the formats written are "
                         "EXR, PFM, TIFF (.tif, .tiff) and HDR (linear values) and PNG, JPEG (.jpg, .jpeg; 8-bit sRGB, "
                         "for viewing)")
    if isinstance(exposure, bool) or not isinstance(exposure, (int, float, np.integer, np.floating)) \
            or not math.isfinite(exposure):
        raise ValueError(f"`exposure` must be a finite number, got {exposure!r} (writing {path})")
    if exposure != 0 and ext not in _LDR:
        raise ValueError(f"{path}: `exposure` scales PNG/JPEG images for viewing only; {ext} stores the values as "
                         f"given (got exposure {exposure!r})")
    bad = int(raw.size - np.count_nonzero(np.isfinite(raw)))
    if bad:
        raise ValueError(f"{path}: refusing to write non-finite values: {bad} of {raw.size} values are NaN or inf")
    over = int(np.count_nonzero(np.abs(raw) > np.finfo(np.float32).max)) if raw.dtype.itemsize > 4 else 0
    if over:
        raise ValueError(f"{path}: refusing to write {over} values beyond the float32 range "
                         f"(|v| > {float(np.finfo(np.float32).max):.4g}): images are stored as 32-bit floats")
    arr = raw.astype(np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    oiio = _oiio()
    h, w, c = arr.shape
    if ext == ".hdr" and np.any(arr < 0):
        n = int(np.count_nonzero(arr < 0))
        raise ValueError(f"{path}: refusing to write negative values: RGBE (.hdr) cannot store them ({n} values < 0)")
    allowed = _WRITE_CHANNELS[ext]
    if allowed is not None and c not in allowed:
        raise ValueError(f"{path}: a {ext} file holds {' or '.join(map(str, allowed))} channels, got an array of "
                         f"{c} (shape {raw.shape})")
    if camera is not None:
        if ext != ".exr":
            raise ValueError(f"{path}: a `camera` is recorded in EXR headers only")
        if (camera.get("width"), camera.get("height")) != (w, h):
            raise ValueError(f"{path}: `camera` is {camera.get('width')}x{camera.get('height')} but the map {w}x{h}")
    if ext in _LDR:
        data = np.clip(_linear_to_srgb(np.clip(arr * 2.0**exposure, 0.0, 1.0)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        spec = oiio.ImageSpec(w, h, c, "uint8")
        if c in (2, 4):  # PNG's alpha: linear, unscaled, and stored as given (OpenImageIO would divide the colour by it)
            data[..., -1] = (np.clip(arr[..., -1], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
            spec.attribute("oiio:UnassociatedAlpha", 1)
    else:
        data = arr
        spec = oiio.ImageSpec(w, h, c, "float")
    if camera is not None:
        spec.attribute(_CAMERA_ATTR, _camera_json(camera))
    with atomic_output(path) as tmp:
        try:
            _write_pixels(tmp, spec, data)
        except ValueError as e:  # name the target, not the temporary file
            raise ValueError(str(e).replace(tmp, path)) from None
        except OSError as e:
            if e.errno is None:
                raise OSError(f"{path}: {e}") from e
            raise OSError(e.errno, e.strerror, path) from e


def _srgb_to_linear(x):
    """IEC 61966-2-1 decoding (sRGB code value in [0, 1] to linear)."""
    x = np.asarray(x)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _linear_to_srgb(x):
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


# ----------------------------------------------------------------------------- normal maps


def _read_float_array(path: str, what: str, plural: str) -> np.ndarray:
    """A float64 array from `.npy` or a float image (EXR, PFM, float TIFF); integer images are refused."""
    _check_readable(path, what)
    if path.lower().endswith(".npy"):
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise ValueError(f"cannot read {what} {path!r}: {e}") from None
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"{what} {path!r}: dtype must be float, got {arr.dtype} (integer arrays, like 8/16-bit "
                             f"integer images, are not {plural})")
    else:
        arr, info = _read_pixels(path)
        if not info["float"]:
            raise ValueError(f"{what} {path!r}: {info['bits']}-bit integer images are not {plural}; use EXR, PFM or .npy")
    return np.asarray(arr, np.float64)


def read_normal_map(path) -> np.ndarray:
    """Read a world-frame normal map `(H, W, 3)` (EXR, PFM or `.npy`).

    Each pixel holds a unit normal, or the zero vector where the pixel is off
    the object. Validated: finite, three channels, every non-zero vector of
    norm 1 within 1e-3 (renormalized exactly on return). 8/16-bit integer
    files and integer `.npy` arrays are rejected (normals need float storage).

    **Returns:** float64 `(H, W, 3)`; the object mask is `np.any(n != 0, -1)`.
    Raises `FileNotFoundError` / `ValueError` naming the file.
    """
    path = os.fspath(path)
    arr = _read_float_array(path, "normal map", "normal maps")
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"normal map {path!r} must have shape (H, W, 3), got {arr.shape}")
    bad = int(np.count_nonzero(~np.isfinite(arr).all(-1)))
    if bad:
        raise ValueError(f"normal map {path!r}: {bad} pixels are not finite")
    norm = np.linalg.norm(arr, axis=-1)
    on = norm > 0
    off_unit = on & (np.abs(norm - 1.0) > 1e-3)
    if np.any(off_unit):
        i, j = np.argwhere(off_unit)[0]
        raise ValueError(
            f"normal map {path!r}: {int(off_unit.sum())} pixels are neither unit vectors (within 1e-3) nor zero "
            f"(off the object), e.g. pixel (row {i}, column {j}) has norm {norm[i, j]:.6g}"
        )
    return np.where(on[..., None], arr / np.where(on, norm, 1.0)[..., None], 0.0)


def read_texture(path, channels: int = 3) -> np.ndarray:
    """Read a texture map `(H, W, channels)` of non-negative finite values (EXR, PFM or `.npy`).

    For per-pixel BRDF parameters (`result.json`'s `brdf.kd = "kd.exr"`):
    float storage only (8/16-bit integer images and integer `.npy` arrays
    are rejected: parameter maps are not pictures), exactly `channels`
    channels (an RGBA file is an error, not cut to RGB), values finite and
    `>= 0`.

    **Returns:** float64 `(H, W, channels)`. Raises `FileNotFoundError` /
    `ValueError` naming the file.
    """
    path = os.fspath(path)
    arr = _read_float_array(path, "texture map", "parameter maps")
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[-1] != channels:
        raise ValueError(f"texture map {path!r} must have shape (H, W, {channels}), got {arr.shape} (channels are "
                         "neither dropped, e.g. an alpha, nor repeated: which ones hold the values would be a guess)")
    bad = int(np.count_nonzero(~np.isfinite(arr)))
    if bad:
        raise ValueError(f"texture map {path!r}: {bad} values are not finite")
    if np.any(arr < 0):
        raise ValueError(f"texture map {path!r}: {int(np.count_nonzero(arr < 0))} values are negative (must be >= 0)")
    return arr


# ----------------------------------------------------------------------------- RBF reflectance files

#: The `format` tag of the `.npz` files of `write_rbf` / `read_rbf`.
RBF_FORMAT = "jaxsh-rbf-1"


def write_rbf(path, model, *, spatial: bool, width: int | None = None, height: int | None = None,
              camera: dict | None = None) -> None:
    """Write an RBF reflectance (Zickler 2006 eqs. 12-13) to an `.npz` file, atomically.

    **Arguments:**

    - `model`: a `jaxsh.RBFModel` over $(u, v, w)$ (`d = 3`, eq. 12) or
      $(x, y, u, v, w)$ (`d = 5`, eq. 13).
    - `spatial`: `True` for the 5-D SBRDF; then `width`, `height` give the
      pixel grid its surface coordinates come from:
      $x = (j + \\tfrac12)/W$, $y = (i + \\tfrac12)/H$ at row $i$, column $j$.

    The file holds `format` (`RBF_FORMAT`), `centers` `(K, d)`, `weights`
    `(K, C)`, `poly` `(d + 1, C)`, `scale` `(d,)`, `spatial`, `width`,
    `height` (−1 when not spatial), all float64 / int64 — no pickles; and,
    when `camera` (a camera block of `read_manifest`, of that size) is given,
    `camera`: the camera of that pixel grid as a JSON string
    (`recorded_camera`).
    """
    path = os.fspath(path)
    centers = np.asarray(model.centers, np.float64)
    d = centers.shape[1]
    if d != (5 if spatial else 3):
        raise ValueError(f"`model` must have {'5' if spatial else '3'}-D points for spatial={spatial}, got d = {d}")
    if spatial and (width is None or height is None):
        raise ValueError("`width` and `height` (the pixel grid of the surface coordinates) are required when spatial=True")
    w = np.asarray(model.weights, np.float64)
    poly = np.asarray(model.poly, np.float64)
    if model.channels is None:
        w, poly = w[:, :1], poly[:, :1]
    arrays = {"format": np.asarray(RBF_FORMAT), "centers": centers, "weights": w, "poly": poly,
              "scale": np.asarray(model.scale, np.float64), "spatial": np.asarray(bool(spatial)),
              "width": np.asarray(-1 if width is None else int(width)), "height": np.asarray(-1 if height is None else int(height))}
    if camera is not None:
        if not spatial or (camera.get("width"), camera.get("height")) != (width, height):
            raise ValueError(f"{path}: a `camera` is recorded for a spatial RBF only, of its `width` x `height`")
        arrays["camera"] = np.asarray(_camera_json(camera))
    for k, a in arrays.items():
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise ValueError(f"{path}: refusing to write non-finite RBF `{k}`")
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def read_rbf(path) -> dict:
    """Read an RBF reflectance file of `write_rbf`.

    **Returns:** `{"model": jaxsh.RBFModel, "spatial": bool, "width": int | None,
    "height": int | None}`. Every problem (not an `.npz`, a missing or
    mis-shaped array, non-finite values, another `format`) is a `ValueError`
    naming the file and the array.
    """
    from ._rbf import RBFModel

    path = os.fspath(path)
    _check_readable(path, "RBF file")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"cannot read RBF file {path!r} (expected an .npz of jaxsh.io.write_rbf): {e}") from None
    for key in ("format", "centers", "weights", "poly", "scale", "spatial", "width", "height"):
        if key not in data:
            raise ValueError(f"RBF file {path!r}: missing array `{key}`")
    if str(data["format"]) != RBF_FORMAT:
        raise ValueError(f"RBF file {path!r}: `format` is {str(data['format'])!r}, expected {RBF_FORMAT!r}")
    c, w, p, sc = (np.asarray(data[k], np.float64) for k in ("centers", "weights", "poly", "scale"))
    spatial = bool(data["spatial"])
    d = 5 if spatial else 3
    k = c.shape[0] if c.ndim == 2 else -1
    want = {"centers": (k, d), "weights": (k, w.shape[-1] if w.ndim == 2 else -1), "poly": (d + 1, w.shape[-1] if w.ndim == 2 else -1),
            "scale": (d,)}
    for name, a in (("centers", c), ("weights", w), ("poly", p), ("scale", sc)):
        if a.shape != want[name] or k < 1:
            raise ValueError(f"RBF file {path!r}: `{name}` must have shape {want[name]}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"RBF file {path!r}: `{name}` has non-finite values")
    if np.any(sc <= 0):
        raise ValueError(f"RBF file {path!r}: `scale` must be > 0")
    width, height = int(data["width"]), int(data["height"])
    if spatial and (width < 1 or height < 1):
        raise ValueError(f"RBF file {path!r}: a spatial RBF needs `width`, `height` >= 1, got {width}x{height}")
    return {"model": RBFModel(c, w, p, sc), "spatial": spatial,
            "width": width if spatial else None, "height": height if spatial else None}


# ----------------------------------------------------------------------------- environment maps


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


def _latlong_dirs(h: int, w: int) -> np.ndarray:
    """float64 `(h, w, 3)` unit directions of a lat-long grid in the library frame (docs/conventions.md, the same
    as `jaxsh.latlong_directions`): row i at theta = pi (i + 1/2) / h from +z, column j at phi = 2 pi (j + 1/2) / w
    from +x towards +y. NumPy, so that reading a map needs no JAX (nor float64 there)."""
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2.0 * np.pi * (np.arange(w) + 0.5) / w
    st = np.sin(theta)[:, None]
    return np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), np.cos(theta)[:, None]), -1)


def read_envmap(
    path, up: str | None = None, layout: str = "latlong", height: int | None = None, encoding: str | None = None
) -> np.ndarray:
    """Read an environment map and return it as a lat-long map in the library frame.

    **Arguments:**

    - `path`: an image file (EXR, HDR, PFM, ...).
    - `up`: the file's up axis, `"+z"` (already the library convention) or
      `"+y"` (converted by `Y_UP_TO_Z_UP`). Never guessed: None (the default)
      means `"+z"` for a lat-long map and is an error for an angular map,
      whose file frame is +y up (`"+z"` would take its axes, y up, as the
      world's: a 90° turn for a +z-up world).
    - `layout`: `"latlong"` (equirectangular; for `"+y"` files: row 0 at +y,
      u = column/width with u = 0.5 looking along −z and u = 0.75 along +x)
      or `"angular"` (Debevec angular map, see
      `jaxsh.angular_map_directions`; its frame is +y up).
    - `height`: output rows (width = 2·height). Default: the file's height for
      lat-long, half the size for angular maps.
    - `encoding`: for 8/16-bit integer files only, as `read_image` (required there).

    An alpha channel is dropped if it is opaque everywhere and is an error
    otherwise (a map has radiance in every direction). The colour channels must
    be 1 (grey) or 3 (RGB); any other count is an error.

    A `"+y"` lat-long file whose width is a multiple of 4 and whose size is
    kept is remapped exactly (a column permutation); otherwise the map is
    resampled bilinearly (angular maps always are).

    **Returns:** float32 `(H, 2H, C)` (for `"+z"` lat-long files: the file as is).
    """
    if up not in (None, "+z", "+y"):
        raise ValueError(f'`up` must be "+z" or "+y", got {up!r}')
    if layout not in ("latlong", "angular"):
        raise ValueError(f'`layout` must be "latlong" or "angular", got {layout!r}')
    if up is None and layout == "angular":
        raise ValueError('`up` is required for an angular map: its file frame is +y up (x right, the centre looking '
                         'along -z); up="+y" turns it into the library\'s +z-up frame, up="+z" takes its axes as they are')
    up = "+z" if up is None else up
    path = os.fspath(path)
    if height is not None:
        if isinstance(height, bool) or not isinstance(height, (int, float, np.integer, np.floating)) \
                or not (math.isfinite(height) and float(height).is_integer() and height >= 1):
            raise ValueError(f"`height` must be a positive integer or None, got {height!r} (reading {path})")
        height = int(height)
    img, info = _read_pixels(path)
    img = _decode(img, _check_encoding(path, encoding, info), info["alpha_channel"])
    img = _drop_opaque_alpha(img, info, f"environment map {path!r} has an alpha channel that is not opaque "
                             "everywhere: an environment map is radiance from every direction; remove the alpha channel")
    if img.shape[-1] not in (1, 3):
        raise ValueError(f"environment map {path!r} has {img.shape[-1]} colour channels: it must be grey (1) or RGB "
                         "(3), with or without an alpha channel")
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
        d = _latlong_dirs(h, 2 * h)
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
    if fh < 2 and height is None:
        raise ValueError(f"angular map {path!r} is {fw}x{fh}: too small for the default `height` (half its size)")
    h = fh // 2 if height is None else height
    d = _latlong_dirs(h, 2 * h)
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


class _ManifestNotFound(ManifestError, FileNotFoundError):
    """A manifest path that does not exist (both a `ManifestError` and a `FileNotFoundError`)."""


_BRDF_MODELS = ("torrance_sparrow", "sharing", "sharing_spatial")
_PIXEL_CENTERS = ("half", "integer")  # pinhole `pixel_centers`: pixel (i, j) centred at (j + 1/2, i + 1/2) or (j, i)
_MESH_NORMALS = ("smooth", "faces")  # `geometry.normals`
_SOLVE_DEFAULTS = {"lighting_lmax": 12, "render_lmax": None, "fresnel": True, "saturation": None,
                   "brdf_model": "torrance_sparrow", "textured": None, "n_centers": 400, "m_w": 0.3, "m_xy": 0.3,
                   "tol": None, "min_cos": 0.1, "max_samples": 200000}


class _Reader:
    """Validation helpers bound to one manifest file (every message starts with its path)."""

    def __init__(self, path: str):
        self.path = path
        self.base = os.path.dirname(os.path.abspath(path))

    def err(self, where: str, msg: str) -> ManifestError:
        return ManifestError(f"{self.path}: `{where}` {msg}")

    def obj(self, v, where: str, allowed, required=()) -> dict:
        """`v` must be an object whose keys are in `allowed`; keys starting with "_" are comments."""
        if not isinstance(v, dict):
            raise self.err(where, f"must be an object, got {_show(v)}")
        for key in v:
            if key.startswith("_") or key in allowed:
                continue
            import difflib

            close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
            hint = f'; did you mean "{close[0]}"?' if close else f" (allowed: {', '.join(sorted(allowed))})"
            raise ManifestError(f"{self.path}: unknown field `{_join(where, key)}`{hint}")
        for key in required:
            if v.get(key) is None:
                raise ManifestError(f"{self.path}: missing field `{_join(where, key)}`")
        return v

    def number(self, v, where: str, *, gt=None, ge=None) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.err(where, f"must be a number, got {_show(v)}")
        try:
            x = float(v)
        except OverflowError:
            raise self.err(where, f"must be a finite number, got {_show(v)}") from None
        if not math.isfinite(x):
            raise self.err(where, f"must be a finite number, got {x}")
        if gt is not None and not x > gt:
            raise self.err(where, f"must be > {gt}, got {_show(v)}")
        if ge is not None and not x >= ge:
            raise self.err(where, f"must be >= {ge}, got {_show(v)}")
        return x

    def integer(self, v, where: str, *, ge=None) -> int:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.err(where, f"must be an integer, got {_show(v)}")
        if isinstance(v, float) and not (math.isfinite(v) and v.is_integer()):
            raise self.err(where, f"must be an integer, got {_show(v)}")
        n = int(v)
        if ge is not None and n < ge:
            raise self.err(where, f"must be >= {ge}, got {n}")
        return n

    def boolean(self, v, where: str) -> bool:
        if not isinstance(v, bool):
            raise self.err(where, f"must be true or false, got {_show(v)}")
        return v

    def choice(self, v, where: str, choices) -> str:
        if not isinstance(v, str) or v not in choices:
            raise self.err(where, f"must be one of {', '.join(json.dumps(c) for c in choices)}, got {_show(v)}")
        return v

    def vector(self, v, where: str, n: int) -> np.ndarray:
        if not isinstance(v, list) or len(v) != n:
            raise self.err(where, f"must be a list of {n} numbers, got {_show(v)}")
        return np.array([self.number(x, f"{where}[{i}]") for i, x in enumerate(v)])

    def rgb(self, v, where: str) -> np.ndarray:
        """A number or [r, g, b], each finite and >= 0."""
        if isinstance(v, list):
            a = self.vector(v, where, 3)
            for i, x in enumerate(a):
                if x < 0:
                    raise self.err(f"{where}[{i}]", f"must be >= 0, got {x}")
            return a
        return np.full(3, self.number(v, where, ge=0))

    def file(self, v, where: str, *, must_exist: bool) -> str:
        if not isinstance(v, str) or not v:
            raise self.err(where, f"must be a file name, got {_show(v)}")
        p = os.path.normpath(os.path.join(self.base, v))
        if os.path.isdir(p):
            raise self.err(where, f"is a directory, expected a file: {p}")
        if must_exist and not os.path.exists(p):
            raise self.err(where, f"file not found: {p}")
        return p

    def image_info(self, p: str, where: str) -> dict:
        try:
            return read_image_info(p)
        except (ValueError, OSError) as e:
            raise self.err(where, f"cannot be read: {e}") from None


def _join(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _show(v) -> str:
    s = json.dumps(v) if isinstance(v, (dict, list, str, bool, type(None))) else repr(v)
    return s if len(s) <= 60 else s[:57] + "..."


def _lighting(r: _Reader, v, where: str):
    if v is None:
        return None
    r.obj(v, where, {"envmap", "up", "layout", "encoding", "rotation", "directional"})
    env = None if v.get("envmap") is None else r.file(v["envmap"], f"{where}.envmap", must_exist=True)
    up = None if v.get("up") is None else r.choice(v["up"], f"{where}.up", ("+z", "+y"))
    layout = "latlong" if v.get("layout") is None else r.choice(v["layout"], f"{where}.layout", ("latlong", "angular"))
    if up is None and layout == "angular" and v.get("envmap") is not None:
        raise r.err(f"{where}.up", 'is required for an angular map (`layout` "angular"): its file frame is +y up (x '
                    'right, the centre looking along -z, docs/conventions.md); "+y" turns it into the library\'s +z-up '
                    'frame, "+z" takes the file\'s axes as the world\'s')
    up = "+z" if up is None else up
    enc = None if v.get("encoding") is None else r.choice(v["encoding"], f"{where}.encoding", ENCODINGS)
    if env is not None:
        info = r.image_info(env, f"{where}.envmap")
        if info["float"] and enc == "srgb":
            raise r.err(f"{where}.encoding", f'must be "linear" (or absent) for the float image {env}')
        if not info["float"] and enc is None:
            raise r.err(f"{where}.encoding", f'is required for the {info["bits"]}-bit integer image {env} ("linear" or "srgb")')
        fw, fh = info["width"], info["height"]
        if layout == "latlong" and fw != 2 * fh:
            raise r.err(f"{where}.envmap", f"is a {fw}x{fh} image but a lat-long map (`{where}.layout` \"latlong\") "
                                           f"must be twice as wide as high: {env}")
        if layout == "angular" and fw != fh:
            raise r.err(f"{where}.envmap", f"is a {fw}x{fh} image but an angular map (`{where}.layout` \"angular\") "
                                           f"must be square: {env}")
    if env is not None:
        colours = info["channels"] - int(info["alpha"])
        if colours not in (1, 3):
            raise r.err(f"{where}.envmap", f"has {colours} colour channels{' besides alpha' if info['alpha'] else ''}: "
                                           f"an environment map is grey (1) or RGB (3): {env}")
    elif (k := next((k for k in ("up", "layout", "encoding") if v.get(k) is not None), None)) is not None:
        raise r.err(f"{where}.{k}", "describes an `envmap`; there is none (`directional` sources are given in the world "
                                    "frame, in linear radiance)")
    rot = None
    if v.get("rotation") is not None:
        if env is None:
            raise r.err(f"{where}.rotation", "turns an `envmap` into the world frame; there is none (`directional` "
                                             "sources are given in the world frame)")
        rows = v["rotation"]
        w = f"{where}.rotation"
        if not isinstance(rows, list) or len(rows) != 3 or not all(isinstance(x, list) and len(x) == 3 for x in rows):
            raise r.err(w, f"must be a 3x3 matrix (a list of 3 rows of 3 numbers), got {_show(rows)}")
        rot = np.array([[r.number(x, f"{w}[{i}][{j}]") for j, x in enumerate(row)] for i, row in enumerate(rows)])
        if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-6 or np.linalg.det(rot) < 0:
            raise r.err(w, "must be a rotation (orthonormal within 1e-6, det +1)")
    dirs_raw = v.get("directional")
    dirs = []
    if dirs_raw is not None:
        if not isinstance(dirs_raw, list):
            raise r.err(f"{where}.directional", f"must be a list of sources, got {_show(dirs_raw)}")
        for j, s in enumerate(dirs_raw):
            w = f"{where}.directional[{j}]"
            r.obj(s, w, {"direction", "radiance"}, required=("direction", "radiance"))
            d = r.vector(s["direction"], f"{w}.direction", 3)
            norm = float(np.linalg.norm(d))
            if not norm > 0:
                raise r.err(f"{w}.direction", "must be non-zero")
            dirs.append({"direction": d / norm, "radiance": r.rgb(s["radiance"], f"{w}.radiance")})
    if env is None and not dirs:
        raise ManifestError(f"{r.path}: `{where}` has neither an `envmap` nor `directional` sources")
    return {"envmap": env, "up": up, "layout": layout, "encoding": enc, "rotation": rot, "directional": dirs}


def _camera(r: _Reader, cam, where: str, image_info):
    common = {"model", "width", "height", "cam_to_world"}
    if not isinstance(cam, dict):
        raise r.err(where, f"must be an object, got {_show(cam)}")
    model = r.choice(cam.get("model"), f"{where}.model", ("pinhole", "orthographic"))
    c = {"model": model}
    if model == "pinhole":
        r.obj(cam, where, common | {"fx", "fy", "cx", "cy", "pixel_centers"},
              required=("fx", "fy", "cx", "cy", "cam_to_world"))
        c["fx"] = r.number(cam["fx"], f"{where}.fx", gt=0)
        c["fy"] = r.number(cam["fy"], f"{where}.fy", gt=0)
        centers = "half" if cam.get("pixel_centers") is None else \
            r.choice(cam["pixel_centers"], f"{where}.pixel_centers", _PIXEL_CENTERS)
        # jaxsh's pixel (i, j) is centred at (u, v) = (j + 1/2, i + 1/2); OpenCV's ("integer") at (j, i): the same
        # camera has a principal point half a pixel further in jaxsh's coordinates
        shift = 0.5 if centers == "integer" else 0.0
        c["cx"] = r.number(cam["cx"], f"{where}.cx") + shift
        c["cy"] = r.number(cam["cy"], f"{where}.cy") + shift
    else:
        r.obj(cam, where, common | {"scale"}, required=("scale", "cam_to_world"))
        c["scale"] = r.number(cam["scale"], f"{where}.scale", gt=0)
    rows = cam["cam_to_world"]
    w = f"{where}.cam_to_world"
    if not isinstance(rows, list) or len(rows) != 4 or not all(isinstance(x, list) and len(x) == 4 for x in rows):
        raise r.err(w, f"must be a 4x4 matrix (a list of 4 rows of 4 numbers), got {_show(rows)}")
    m = np.array([[r.number(x, f"{w}[{i}][{j}]") for j, x in enumerate(row)] for i, row in enumerate(rows)])
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9:
        raise r.err(w, f"must have the last row [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-6 or np.linalg.det(rot) < 0:
        raise r.err(w, "must hold a rotation (orthonormal within 1e-6, det +1) in its upper-left 3x3 block")
    c["cam_to_world"] = m
    wd = None if cam.get("width") is None else r.integer(cam["width"], f"{where}.width", ge=1)
    ht = None if cam.get("height") is None else r.integer(cam["height"], f"{where}.height", ge=1)
    if (wd is None or ht is None) and image_info is not None:
        wd = image_info["width"] if wd is None else wd
        ht = image_info["height"] if ht is None else ht
    if wd is None or ht is None:
        view = where.rsplit(".", 1)[0]
        raise ManifestError(f"{r.path}: `{where}.width`/`height` are needed (or an existing `{view}.image`)")
    c["width"], c["height"] = wd, ht
    return c


def _normal_map_shape(r: _Reader, p: str, where: str):
    if p.lower().endswith(".npy"):
        try:
            a = np.load(p, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError) as e:
            raise r.err(where, f"cannot be read: {e}") from None
        shape = tuple(a.shape)
    else:
        info = r.image_info(p, where)
        if not info["float"]:
            raise r.err(where, f"must be a float image (EXR, PFM) or .npy, got a {info['bits']}-bit integer image {p}")
        shape = (info["height"], info["width"], info["channels"])
    if len(shape) != 3 or shape[2] != 3:
        raise r.err(where, f"must hold (H, W, 3) normals, got shape {shape} in {p}")
    return shape[:2]


def _read_json(path: str):
    try:
        with open(path, "rb") as f:
            data = f.read()
    except IsADirectoryError:
        raise ManifestError(f"{path}: is a directory, expected a manifest file") from None
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ManifestError(f"{path}: not UTF-8 text (byte {e.start}: {e.reason})") from None

    def no_duplicates(pairs):
        d = {}
        for k, v in pairs:
            if k in d:
                raise ManifestError(f"{path}: field `{k}` appears twice in one object")
            d[k] = v
        return d

    try:
        return json.loads(text, object_pairs_hook=no_duplicates)
    except json.JSONDecodeError as e:
        raise ManifestError(f"{path}: not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}") from None
    except RecursionError:
        raise ManifestError(f"{path}: not valid JSON: nested too deeply") from None


def read_manifest(path) -> dict:
    """Read and validate a capture manifest completely (docs/manifest.md lists every field).

    Everything is checked before any work: JSON syntax (with line and
    column), UTF-8, types (integers for sizes, finite numbers), ranges,
    unknown fields (an error, with a "did you mean"), file references
    (existing files, not directories), camera matrices (a rotation and
    the last row [0, 0, 0, 1]), declared image encodings (read from the
    image headers). Paths are resolved relative to the manifest. Keys
    starting with `_` are comments and are skipped.

    **Returns:** a plain dict:

    - `geometry`: `{"sphere": {"center": (3,), "radius"}}`, `{"mesh": abs_path, "normals": "smooth" | "faces"}`,
      `{"normal_map": abs_path}`, or `{}` (every view has its own `normal_map`);
    - `views`: list of `{"image", "mask", "normal_map": abs_path | None, "camera": {...},
      "encoding": "linear" | "srgb" | None, "exposure": float, "saturation": float | None,
      "alpha": "ignore" | "mask" | None, "lighting": None | a lighting dict}`; the camera has its
      `model` ("pinhole" or "orthographic"), intrinsics, `width`, `height` (from the camera
      block, else from the image header) and `cam_to_world` `(4, 4)`; a pinhole camera's `cx`, `cy`
      are in jaxsh's pixel coordinates (pixel (i, j) centred at (j + ½, i + ½)) whatever its declared
      `pixel_centers` (`"integer"` adds ½ to both). The encoding is "linear" for float images;
      `saturation` defaults to the image's maximum code value for integer images; `alpha` (the
      view's, else the top-level one) is required when the image has an alpha channel;
    - `lighting`: None (unknown) or `{"envmap": abs_path | None, "up", "layout", "encoding",
      "rotation": (3, 3) | None, "directional": [{"direction": (3,) unit, "radiance": (3,)}]}`;
    - `brdf`: None (unknown), `{"model": "torrance_sparrow", "kd", "ks", "mu": float | None, "sigma",
      "files": {"kd"?: abs_path, "ks"?: abs_path}}` with `kd`, `ks` each `(3,)` or a texture map
      `(H, W, 3)` read from the file the manifest names (`read_texture`; the views' pixel grid), or `{"model": "rbf", "file": abs_path, "spatial": bool,
      "rbf": read_rbf(file)}`;
    - `solve`: `{"lighting_lmax", "render_lmax", "fresnel", "saturation", "brdf_model", "textured",
      "n_centers", "m_w", "m_xy", "tol", "min_cos", "max_samples"}` with defaults (docs/manifest.md);
    - `encoding`: the top-level default encoding or None; `path`: the manifest's absolute path;
    - `given`: `{"solve": [...], "views": [[...], ...]}`, the keys the file gives (not null) in `solve` and in
      each view, for the commands' checks of fields they do not use.

    Every problem raises `ManifestError` (a `ValueError`) naming the file and
    the field path (e.g. `views[2].camera.fx`); a missing manifest raises an
    error that is both a `ManifestError` and a `FileNotFoundError`.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise _ManifestNotFound(f"manifest not found: {path}")
    raw = _read_json(path)
    r = _Reader(path)
    if not isinstance(raw, dict):
        raise ManifestError(f"{path}: the manifest must be a JSON object, got {_show(raw)}")
    r.obj(raw, "", {"$schema", "geometry", "views", "lighting", "brdf", "solve", "encoding", "alpha"},
          required=("views",))
    default_enc = None if raw.get("encoding") is None else r.choice(raw["encoding"], "encoding", ENCODINGS)
    default_alpha = None if raw.get("alpha") is None else r.choice(raw["alpha"], "alpha", ALPHA_MODES)

    # views first: whether `geometry` may be absent depends on them
    views_raw = raw["views"]
    if not isinstance(views_raw, list) or not views_raw:
        raise r.err("views", f"must be a non-empty list, got {_show(views_raw)}")
    views = []
    allowed_view = {"image", "mask", "camera", "encoding", "exposure", "saturation", "lighting", "normal_map", "alpha"}
    for k, v in enumerate(views_raw):
        where = f"views[{k}]"
        r.obj(v, where, allowed_view, required=("camera",))
        image = None if v.get("image") is None else r.file(v["image"], f"{where}.image", must_exist=False)
        mask = None if v.get("mask") is None else r.file(v["mask"], f"{where}.mask", must_exist=False)
        info = r.image_info(image, f"{where}.image") if image is not None and os.path.exists(image) else None
        cam = _camera(r, v["camera"], f"{where}.camera", info)
        if info is not None and (info["width"], info["height"]) != (cam["width"], cam["height"]):
            raise r.err(f"{where}.image", f"is {info['width']}x{info['height']} but `{where}.camera` is "
                                          f"{cam['width']}x{cam['height']}: {image}")
        enc = default_enc if v.get("encoding") is None else r.choice(v["encoding"], f"{where}.encoding", ENCODINGS)
        saturation = None if v.get("saturation") is None else r.number(v["saturation"], f"{where}.saturation", gt=0)
        if info is not None:
            if info["float"]:
                if enc == "srgb" and v.get("encoding") is None:  # the top-level default: say so
                    raise r.err("encoding", f'"srgb" is the default of `{where}.encoding`, but the float image {image} '
                                            f'holds linear values (EXR/HDR/PFM): give `{where}.encoding` "linear"')
                if enc == "srgb":
                    raise r.err(f"{where}.encoding", f'must be "linear" for the float image {image} '
                                                     "(EXR/HDR/PFM hold linear values)")
                enc = "linear"
            else:
                if enc is None:
                    raise r.err(f"{where}.encoding", f"is required for the {info['bits']}-bit integer image {image} "
                                                     '("linear" or "srgb"; a top-level `encoding` sets a default)')
                if saturation is None:
                    saturation = float(info["max_code"])
        alpha = default_alpha if v.get("alpha") is None else r.choice(v["alpha"], f"{where}.alpha", ALPHA_MODES)
        if info is not None and info["alpha"] and alpha is None:
            raise r.err(f"{where}.alpha", f"is required: the image {image} has an alpha channel; declare \"ignore\" "
                                          "(drop it) or \"mask\" (also drop the pixels whose alpha is at most half of "
                                          "full scale); it is never guessed (a top-level `alpha` sets a default)")
        exposure = 1.0 if v.get("exposure") is None else r.number(v["exposure"], f"{where}.exposure", gt=0)
        nmap = None if v.get("normal_map") is None else r.file(v["normal_map"], f"{where}.normal_map", must_exist=True)
        if nmap is not None:
            hw = _normal_map_shape(r, nmap, f"{where}.normal_map")
            if hw != (cam["height"], cam["width"]):
                raise r.err(f"{where}.normal_map", f"is {hw[1]}x{hw[0]} but `{where}.camera` is "
                                                   f"{cam['width']}x{cam['height']}: {nmap}")
        lighting_v = _lighting(r, v.get("lighting"), f"{where}.lighting")
        views.append({"image": image, "mask": mask, "normal_map": nmap, "camera": cam, "encoding": enc,
                      "exposure": exposure, "saturation": saturation, "alpha": alpha, "lighting": lighting_v})

    per_view_normals = [v["normal_map"] is not None for v in views]
    geo = raw.get("geometry")
    if geo is None:
        if not all(per_view_normals):
            raise ManifestError(f"{path}: missing field `geometry` (it may be left out only when every view has a `normal_map`)")
        geometry = {}
    else:
        r.obj(geo, "geometry", {"mesh", "sphere", "normal_map", "normals"})
        if geo.get("normals") is not None and geo.get("mesh") is None:
            raise r.err("geometry.normals", "is only for a `geometry.mesh` (a sphere's normals are exact; a normal map "
                                            "holds its own)")
        if len([key for key in ("mesh", "sphere", "normal_map") if geo.get(key) is not None]) != 1:
            raise ManifestError(f'{path}: `geometry` must have exactly one of "mesh", "sphere" or "normal_map"')
        if any(per_view_normals) and geo.get("normal_map") is None:
            k = per_view_normals.index(True)
            raise r.err(f"views[{k}].normal_map", "cannot be combined with a `geometry` mesh or sphere "
                                                  "(give normal maps per view, or a `geometry.normal_map`)")
        if geo.get("sphere") is not None:
            sph = r.obj(geo["sphere"], "geometry.sphere", {"center", "radius"}, required=("center", "radius"))
            geometry = {"sphere": {"center": r.vector(sph["center"], "geometry.sphere.center", 3),
                                   "radius": r.number(sph["radius"], "geometry.sphere.radius", gt=0)}}
        elif geo.get("mesh") is not None:
            geometry = {"mesh": r.file(geo["mesh"], "geometry.mesh", must_exist=True),
                        "normals": "smooth" if geo.get("normals") is None else
                        r.choice(geo["normals"], "geometry.normals", _MESH_NORMALS)}
        else:
            nmap = r.file(geo["normal_map"], "geometry.normal_map", must_exist=True)
            hw = _normal_map_shape(r, nmap, "geometry.normal_map")
            for k, v in enumerate(views):
                c = v["camera"]
                if hw != (c["height"], c["width"]):
                    raise r.err("geometry.normal_map", f"is {hw[1]}x{hw[0]} but `views[{k}].camera` is "
                                                       f"{c['width']}x{c['height']}: {nmap}")
                if v["normal_map"] is None and not _same_camera(c, views[0]["camera"]):
                    raise r.err(f"views[{k}].camera", "differs from `views[0].camera`: a `geometry.normal_map` is in "
                                                      "the pixel grid of one camera shared by all views "
                                                      "(give `views[k].normal_map` per view instead)")
            geometry = {"normal_map": nmap}

    lighting = _lighting(r, raw.get("lighting"), "lighting")

    brdf = _brdf_block(r, raw.get("brdf"), views)

    s = {} if raw.get("solve") is None else r.obj(raw["solve"], "solve", set(_SOLVE_DEFAULTS))
    solve = dict(_SOLVE_DEFAULTS)
    if s.get("lighting_lmax") is not None:
        solve["lighting_lmax"] = r.integer(s["lighting_lmax"], "solve.lighting_lmax", ge=0)
    if s.get("render_lmax") is not None:
        solve["render_lmax"] = r.integer(s["render_lmax"], "solve.render_lmax", ge=0)
    if s.get("fresnel") is not None:
        solve["fresnel"] = r.boolean(s["fresnel"], "solve.fresnel")
    if s.get("saturation") is not None:
        solve["saturation"] = r.number(s["saturation"], "solve.saturation", gt=0)
    if s.get("brdf_model") is not None:
        solve["brdf_model"] = r.choice(s["brdf_model"], "solve.brdf_model", _BRDF_MODELS)
    if s.get("textured") is not None:
        solve["textured"] = r.choice(s["textured"], "solve.textured", ("kd", "kd_ks"))
    for key in ("n_centers", "max_samples"):
        if s.get(key) is not None:
            solve[key] = r.integer(s[key], f"solve.{key}", ge=1)
    for key in ("m_w", "m_xy", "tol"):
        if s.get(key) is not None:
            solve[key] = r.number(s[key], f"solve.{key}", gt=0)
    if s.get("min_cos") is not None:
        solve["min_cos"] = r.number(s["min_cos"], "solve.min_cos", ge=0)
        if solve["min_cos"] >= 1:
            raise r.err("solve.min_cos", f"must be < 1, got {solve['min_cos']}")
    if solve["textured"] is not None and solve["brdf_model"] != "torrance_sparrow":
        raise r.err("solve.textured", f'needs `solve.brdf_model` "torrance_sparrow", got {solve["brdf_model"]!r}')
    given = {"solve": sorted(k for k, x in s.items() if x is not None),
             "views": [sorted(k for k, x in v.items() if x is not None) for v in views_raw]}
    return {"path": os.path.abspath(path), "geometry": geometry, "views": views, "lighting": lighting, "brdf": brdf,
            "solve": solve, "encoding": default_enc, "given": given}


def _brdf_block(r: _Reader, b, views: list):
    """The validated `brdf` block: Torrance-Sparrow (RGB values or texture maps) or an RBF file."""
    if b is None:
        return None
    if not isinstance(b, dict):
        raise r.err("brdf", f"must be an object or null, got {_show(b)}")
    model = r.choice(b.get("model"), "brdf.model", ("torrance_sparrow", "rbf"))
    if model == "rbf":
        r.obj(b, "brdf", {"model", "file", "spatial", "n_centers"}, required=("model", "file"))
        p = r.file(b["file"], "brdf.file", must_exist=True)
        try:
            rbf = read_rbf(p)
        except (ValueError, OSError) as e:
            raise r.err("brdf.file", f"cannot be used: {e}") from None
        if b.get("spatial") is not None and r.boolean(b["spatial"], "brdf.spatial") != rbf["spatial"]:
            raise r.err("brdf.spatial", f"is {b['spatial']} but the file {p} holds a {'5' if rbf['spatial'] else '3'}-D RBF")
        n_c = int(rbf["model"].centers.shape[0])
        if b.get("n_centers") is not None and r.integer(b["n_centers"], "brdf.n_centers", ge=1) != n_c:
            raise r.err("brdf.n_centers", f"is {b['n_centers']} but the file {p} has {n_c} centres")
        if rbf["spatial"]:
            for k, v in enumerate(views):
                c = v["camera"]
                if (c["width"], c["height"]) != (rbf["width"], rbf["height"]):
                    raise r.err(f"views[{k}].camera", f"is {c['width']}x{c['height']} but the spatial RBF {p} has surface "
                                                      f"coordinates in a {rbf['width']}x{rbf['height']} pixel grid")
            _one_pixel_grid(r, views, f"the spatial RBF `brdf.file` {p} takes its surface coordinates from", p,
                            "brdf.file")
        return {"model": "rbf", "file": p, "spatial": rbf["spatial"], "rbf": rbf}
    r.obj(b, "brdf", {"model", "kd", "ks", "mu", "sigma"}, required=("model", "kd", "ks", "sigma"))
    if "mu" not in b:
        raise ManifestError(f"{r.path}: missing field `brdf.mu` (a number >= 1, or null for no Fresnel term)")
    out = {"model": model, "mu": None if b["mu"] is None else r.number(b["mu"], "brdf.mu", ge=1),
           "sigma": r.number(b["sigma"], "brdf.sigma", gt=0), "files": {}}
    for key in ("kd", "ks"):
        v = b[key]
        if not isinstance(v, str):
            out[key] = r.rgb(v, f"brdf.{key}")
            continue
        p = r.file(v, f"brdf.{key}", must_exist=True)
        try:
            tex = read_texture(p)
        except (ValueError, OSError) as e:
            raise r.err(f"brdf.{key}", f"cannot be used: {e}") from None
        for k, view in enumerate(views):
            c = view["camera"]
            if tex.shape[:2] != (c["height"], c["width"]):
                raise r.err(f"brdf.{key}", f"is a {tex.shape[1]}x{tex.shape[0]} map but `views[{k}].camera` is "
                                           f"{c['width']}x{c['height']}: a texture map is in the views' pixel grid ({p})")
        _one_pixel_grid(r, views, f"the texture map `brdf.{key}` {p} is in", p, f"brdf.{key}")
        out[key] = tex
        out["files"][key] = p
    return out


def _one_pixel_grid(r: _Reader, views: list, what: str, path: str, where: str) -> None:
    """Maps in a pixel grid (texture maps, a spatial RBF's surface coordinates) hold values per pixel of one camera:
    the one the file records (`recorded_camera`), else `views[0].camera`'s; every view must have that camera (pose
    and intrinsics), else the values would stick to the image, not the surface."""
    try:
        rec = recorded_camera(path)
    except (ValueError, OSError) as e:
        raise r.err(where, f"cannot be used: {e}") from None
    if rec is not None:
        for k, view in enumerate(views):
            if not _same_camera(view["camera"], rec):
                raise r.err(f"views[{k}].camera", f"is not the camera {what}: the file records the camera it was "
                                                  "made for (the fit's), and the values would stick to the image, "
                                                  "not to the surface; render that camera under new lights")
        return
    for k, view in enumerate(views[1:], 1):
        if not _same_camera(view["camera"], views[0]["camera"]):
            raise r.err(f"views[{k}].camera", f"differs from `views[0].camera`: {what} the pixel grid of one camera, "
                                              "`views[0].camera` (the camera it was made for: the fit's); every view "
                                              "must have that camera (render new lights, not new views)")


def _same_camera(a: dict, b: dict) -> bool:
    if a.keys() != b.keys():
        return False
    return all(np.array_equal(a[k], b[k]) if k == "cam_to_world" else a[k] == b[k] for k in a)


# The header attribute (EXR) / array (RBF .npz) holding the camera of a per-pixel map.
_CAMERA_ATTR = "jaxsh:camera"
_CAMERA_KEYS = {"pinhole": ("fx", "fy", "cx", "cy"), "orthographic": ("scale",)}


def _camera_json(cam: dict) -> str:
    """A camera block of `read_manifest` as JSON (cx, cy in jaxsh's pixel coordinates; floats round-trip exactly)."""
    model = cam.get("model")
    if model not in _CAMERA_KEYS:
        raise ValueError(f'`camera` must be a camera block of read_manifest (model "pinhole" or "orthographic"), '
                         f"got model {model!r}")
    out = {"model": model, **{k: float(cam[k]) for k in _CAMERA_KEYS[model]},
           "width": int(cam["width"]), "height": int(cam["height"]),
           "cam_to_world": np.asarray(cam["cam_to_world"], np.float64).tolist()}
    return json.dumps(out)


def _camera_from_json(text: str, path: str) -> dict:
    try:
        raw = json.loads(text)
        cam = {"model": raw["model"], **{k: float(raw[k]) for k in _CAMERA_KEYS[raw["model"]]},
               "width": int(raw["width"]), "height": int(raw["height"]),
               "cam_to_world": np.asarray(raw["cam_to_world"], np.float64).reshape(4, 4)}
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: its recorded camera (`{_CAMERA_ATTR}`) cannot be read: {e}") from None
    return cam


def recorded_camera(path) -> dict | None:
    """The camera a per-pixel map was made for, if its file records one, else None.

    `jaxsh fit` records it in the texture maps it writes (`kd.exr`, `ks.exr`:
    EXR header attribute `jaxsh:camera`) and in a spatial RBF file
    (`brdf_rbf.npz`, array `camera`). **Returns:** a camera block like
    `read_manifest`'s `views[k]["camera"]` (`model`, intrinsics with `cx`, `cy`
    in jaxsh's pixel coordinates, `width`, `height`, `cam_to_world` `(4, 4)`),
    or None for files without one (maps made elsewhere, `.npy`, PFM).
    """
    path = os.fspath(path)
    _check_readable(path, "map")
    ext = os.path.splitext(path)[1].lower()
    if ext == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                text = str(z["camera"]) if "camera" in z.files else None
        except (ValueError, OSError, EOFError) as e:
            raise ValueError(f"cannot read {path!r}: {e}") from None
    elif ext == ".exr":
        inp = _open(path)
        try:
            text = inp.spec().get_string_attribute(_CAMERA_ATTR, "") or None
        finally:
            inp.close()
    else:
        return None
    return None if text is None else _camera_from_json(text, path)


def read_mesh(path):
    """Load a triangle mesh (OBJ, PLY, STL, ...) with trimesh, positions only, merged vertices.

    A vertex that is not finite is an error (`ValueError` naming the file), never dropped with its triangles."""
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
    vertices = np.asarray(loaded.vertices)
    bad = ~np.all(np.isfinite(vertices), axis=-1)
    if np.any(bad):  # trimesh's processing would drop them and their triangles without a word
        raise ValueError(f"mesh {path!r}: {int(bad.sum())} vertices are not finite (NaN/inf), e.g. vertex "
                         f"{int(np.argmax(bad))} (0-based)")
    mesh = trimesh.Trimesh(vertices=vertices, faces=np.asarray(loaded.faces), process=True)
    return mesh
