"""Image and environment-map I/O (OpenImageIO)."""

import json
import os

import numpy as np
import pytest

import jaxsh
import jaxsh.io as jio

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "envmaps")


def test_exr_round_trip_is_exact(tmp_path, rng):
    img = rng.random((5, 7, 3)).astype(np.float32) * 100
    p = tmp_path / "a.exr"
    jio.write_image(p, img)
    np.testing.assert_array_equal(jio.read_image(p), img)


def test_pfm_and_hdr_round_trip(tmp_path, rng):
    img = (rng.random((4, 6, 3)) * 50 + 0.01).astype(np.float32)
    jio.write_image(tmp_path / "a.pfm", img)
    np.testing.assert_array_equal(jio.read_image(tmp_path / "a.pfm"), img)
    jio.write_image(tmp_path / "a.hdr", img)
    back = jio.read_image(tmp_path / "a.hdr")
    # RGBE: 8-bit mantissa shared exponent -> relative error <= 2^-8 of the largest channel
    assert np.all(np.abs(back - img) <= 2.0**-7 * img.max(axis=-1, keepdims=True))


def test_pfm_follows_the_format_spec(tmp_path):
    """A hand-written PFM (scanlines bottom to top) reads with its top row first."""
    img = np.zeros((2, 3, 3), np.float32)
    img[0] = 1.0
    p = tmp_path / "h.pfm"
    with open(p, "wb") as f:
        f.write(b"PF\n3 2\n-1.0\n")
        f.write(img[::-1].astype("<f4").tobytes())
    np.testing.assert_array_equal(jio.read_image(p), img)


def test_png_is_srgb_encoded(tmp_path):
    img = np.full((2, 2, 3), 0.2, np.float32)
    jio.write_image(tmp_path / "a.png", img)
    back = jio.read_image(tmp_path / "a.png", encoding="srgb")
    np.testing.assert_allclose(back, 0.2, atol=0.004)  # decoded to linear within 8-bit quantization
    import OpenImageIO as oiio

    raw = oiio.ImageInput.open(str(tmp_path / "a.png")).read_image("uint8")
    assert abs(int(raw[0, 0, 0]) - round(255 * (1.055 * 0.2 ** (1 / 2.4) - 0.055))) <= 1


def test_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.exr"):
        jio.read_image(tmp_path / "nope.exr")
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an image at all")
    with pytest.raises(ValueError, match="bad.exr"):
        jio.read_image(bad)
    with pytest.raises(ValueError, match="x.exr"):
        jio.write_image(tmp_path / "x.exr", np.full((2, 2), np.nan))
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        jio.write_image(tmp_path / "y.exr", np.zeros(3))


def _plus_y_file_with_spot(h, w, u, v_row):
    img = np.zeros((h, w, 3), np.float32)
    img[v_row, u] = 1.0
    return img


def test_read_envmap_plus_y_orientation(tmp_path):
    """In a +y-up file, u = 0.75 looks along +x, u = 0.5 along -z, row 0 is +y (up)."""
    h, w = 16, 32
    img = np.zeros((h, w, 3), np.float32)
    img[h // 2, int(0.75 * w)] = [1, 0, 0]  # horizon, looking +x (file)
    img[h // 2, int(0.5 * w)] = [0, 1, 0]  # horizon, looking -z (file)
    img[0, :] = [0, 0, 1]  # top row: file +y
    p = tmp_path / "env.exr"
    jio.write_image(p, img)
    env = jio.read_envmap(p, up="+y")
    d = np.asarray(jaxsh.latlong_directions(h, w))
    red = d[env[..., 0] > 0.5].mean(0)
    green = d[env[..., 1] > 0.5].mean(0)
    blue = d[env[..., 2] > 0.5].mean(0)
    assert red[0] > 0.95  # file +x -> library +x
    assert green[1] > 0.95  # file -z -> library +y (Y_UP_TO_Z_UP)
    assert blue[2] > 0.95  # file up -> library +z
    np.testing.assert_allclose(jio.Y_UP_TO_Z_UP @ [0, 1, 0], [0, 0, 1])
    assert np.linalg.det(jio.Y_UP_TO_Z_UP) == pytest.approx(1.0)


def test_read_envmap_exact_remap_matches_resampling(tmp_path):
    """The exact column permutation and the bilinear path agree on a smooth map."""
    h, w = 32, 64
    d = np.asarray(jaxsh.latlong_directions(h, w))  # pretend these are file-frame directions (+y up)
    fd = d @ jio.Y_UP_TO_Z_UP  # not used for content; content is a smooth function of the pixel grid
    del fd
    rng = np.random.default_rng(0)
    c = rng.normal(size=(16, 3))
    img = np.asarray(jaxsh.synthesize_latlong(c, h, w), np.float32)
    p = tmp_path / "smooth.exr"
    jio.write_image(p, img)
    exact = jio.read_envmap(p, up="+y")
    resampled = jio.read_envmap(p, up="+y", height=h + 2)
    ce = np.asarray(jaxsh.project_latlong(exact.astype(np.float64), 3))
    cr = np.asarray(jaxsh.project_latlong(resampled.astype(np.float64), 3))
    assert np.abs(ce - cr).max() < 2e-2 * np.abs(ce).max()


def test_plus_y_conversion_rotates_coefficients(tmp_path):
    """Reading with up="+y" equals rotating the file-frame expansion by Y_UP_TO_Z_UP."""
    h, w = 32, 64
    rng = np.random.default_rng(1)
    c_file = rng.normal(size=(16, 3))
    # Build the file: pixel (i, j) of a +y-up file looks along the file direction fd(i, j).
    theta = np.pi * (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    psi = 2 * np.pi * u
    st = np.sin(theta)[:, None]
    fd = np.stack(np.broadcast_arrays(-st * np.sin(psi), np.cos(theta)[:, None], st * np.cos(psi)), -1)
    img = np.einsum("hwn,nc->hwc", np.asarray(jaxsh.real_sh(fd, 3)), c_file).astype(np.float32)
    p = tmp_path / "f.exr"
    jio.write_image(p, img)
    env = jio.read_envmap(p, up="+y").astype(np.float64)
    got = np.asarray(jaxsh.project_latlong(env, 3))
    want = np.asarray(jaxsh.rotate_sh(c_file, jio.Y_UP_TO_Z_UP))
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_read_envmap_angular(tmp_path):
    s = 64
    dirs, _, inside = jaxsh.angular_map_directions(s)
    dirs = np.asarray(dirs)
    img = np.where(np.asarray(inside)[..., None], (dirs[..., 1:2] > 0.8) * np.ones(3), 0).astype(np.float32)  # file +y cap
    p = tmp_path / "ang.exr"
    jio.write_image(p, img)
    env = jio.read_envmap(p, up="+y", layout="angular")
    assert env.shape == (32, 64, 3)
    d = np.asarray(jaxsh.latlong_directions(32, 64))
    bright = d[env[..., 0] > 0.5]
    assert bright[:, 2].min() > 0.7  # the +y cap of the file is the +z cap of the world


def test_read_envmap_option_errors(tmp_path):
    p = tmp_path / "e.exr"
    jio.write_image(p, np.zeros((4, 6, 3)))
    with pytest.raises(ValueError, match="up"):
        jio.read_envmap(p, up="y")
    with pytest.raises(ValueError, match="layout"):
        jio.read_envmap(p, layout="cube")
    with pytest.raises(ValueError, match="e.exr"):
        jio.read_envmap(p)  # not 2:1


@pytest.mark.skipif(not os.path.isdir(DATA), reason="shared data not present")
def test_real_probe_loads():
    env = jio.read_envmap(os.path.join(DATA, "grace.hdr"), up="+y")
    assert env.shape == (128, 256, 3) and np.all(np.isfinite(env)) and env.max() > 100


@pytest.mark.parametrize("ext", ["obj", "ply", "stl"])
def test_read_mesh_formats(tmp_path, ext):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    p = tmp_path / f"m.{ext}"
    m.export(p)
    got = jio.read_mesh(p)
    assert len(got.faces) == len(m.faces)
    np.testing.assert_allclose(np.sort(np.linalg.norm(got.vertices, axis=1)), 1.0, atol=1e-5)


def test_read_mesh_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        jio.read_mesh(tmp_path / "nope.ply")
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match="bad.obj"):
        jio.read_mesh(bad)


# ----------------------------------------------------------------------------- declared encodings (issue 11)


def _write_codes(path, codes):
    """Write integer code values as they are (uint8 / uint16), bypassing jaxsh."""
    import OpenImageIO as oiio

    codes = np.asarray(codes)
    h, w, c = codes.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, "uint8" if codes.dtype == np.uint8 else "uint16"))
    assert out.write_image(np.ascontiguousarray(codes))
    out.close()


def _srgb_decode_reference(x):
    """IEC 61966-2-1, written out independently of jaxsh: linear toe below 0.04045, 2.4 power above."""
    out = np.empty_like(x, dtype=np.float64)
    for idx, v in np.ndenumerate(np.asarray(x, np.float64)):
        out[idx] = v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4
    return out


def test_srgb_decoding_is_the_standard_transfer_function(tmp_path):
    codes8 = np.arange(256, dtype=np.uint8).reshape(16, 16, 1).repeat(3, -1)
    _write_codes(tmp_path / "s8.png", codes8)
    got = jio.read_image(tmp_path / "s8.png", encoding="srgb")
    want = _srgb_decode_reference(codes8 / 255.0)
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-9)
    assert got[0, 10, 0] == pytest.approx(10 / 255 / 12.92, rel=1e-6)  # code 10 is in the linear toe
    codes16 = (np.arange(256, dtype=np.uint16) * 257 + 3).reshape(16, 16, 1).repeat(3, -1)
    _write_codes(tmp_path / "s16.png", codes16)
    got16 = jio.read_image(tmp_path / "s16.png", encoding="srgb")
    np.testing.assert_allclose(got16, _srgb_decode_reference(codes16 / 65535.0), rtol=2e-6, atol=1e-9)


@pytest.mark.parametrize("ext, dtype", [("png", np.uint8), ("png", np.uint16), ("tif", np.uint16), ("tif", np.uint8)])
def test_linear_integer_images_scale_by_the_maximum_code(tmp_path, ext, dtype):
    top = np.iinfo(dtype).max
    codes = np.random.default_rng(3).integers(0, top + 1, size=(16, 16, 3)).astype(dtype)
    p = tmp_path / f"lin.{ext}"
    _write_codes(p, codes)
    np.testing.assert_allclose(jio.read_image(p, encoding="linear"), codes / float(top), rtol=1e-6)
    info = jio.read_image_info(p)
    assert info["max_code"] == top and not info["float"] and (info["width"], info["height"]) == (16, 16)


def test_integer_image_without_encoding_is_an_error(tmp_path):
    _write_codes(tmp_path / "a16.png", np.full((4, 4, 3), 1000, np.uint16))
    with pytest.raises(ValueError, match=r"a16\.png.*16-bit.*`encoding`"):
        jio.read_image(tmp_path / "a16.png")
    with pytest.raises(ValueError, match="encoding"):
        jio.read_image(tmp_path / "a16.png", encoding="gamma22")
    jio.write_image(tmp_path / "f.exr", np.ones((4, 4, 3)))
    with pytest.raises(ValueError, match=r"f\.exr.*srgb"):
        jio.read_image(tmp_path / "f.exr", encoding="srgb")
    np.testing.assert_array_equal(jio.read_image(tmp_path / "f.exr", encoding="linear"), 1.0)
    with pytest.raises(IsADirectoryError, match="directory"):
        jio.read_image(tmp_path)


def test_jpeg_reads_with_declared_srgb(tmp_path):
    _write_codes(tmp_path / "a.jpg", np.full((16, 16, 3), 128, np.uint8))
    got = jio.read_image(tmp_path / "a.jpg", encoding="srgb")
    assert np.abs(got - _srgb_decode_reference(np.array(128 / 255.0))).max() < 0.01  # JPEG is lossy
    with pytest.raises(ValueError, match="a.jpg"):
        jio.read_image(tmp_path / "a.jpg")


def test_read_radiance_saturation_in_file_units(tmp_path):
    codes = np.full((16, 16, 3), 30000, np.uint16)
    codes[0, 0, 1] = 65535  # clipped at the format's maximum
    codes[1, 1, 2] = 60000  # above a user threshold of 50000
    _write_codes(tmp_path / "c.png", codes)
    img, valid = jio.read_radiance(tmp_path / "c.png", "linear", exposure=4.0)
    assert not valid[0, 0] and valid[1, 1] and valid.sum() == 255  # default: the maximum code value
    np.testing.assert_allclose(img[5, 5], 4.0 * 30000 / 65535, rtol=1e-6)  # exposure after decoding
    _, valid = jio.read_radiance(tmp_path / "c.png", "linear", exposure=4.0, saturation=50000)
    assert not valid[0, 0] and not valid[1, 1] and valid.sum() == 254  # in codes, not in scaled radiance
    _, valid = jio.read_radiance(tmp_path / "c.png", "srgb", saturation=30000)
    assert valid.sum() == 0  # >=: a pixel at the threshold is dropped
    f = np.full((16, 16, 3), 2.0, np.float32)
    f[3, 4] = 9.0
    jio.write_image(tmp_path / "f.exr", f)
    _, valid = jio.read_radiance(tmp_path / "f.exr")
    assert valid.all()  # float files: no default threshold
    img, valid = jio.read_radiance(tmp_path / "f.exr", saturation=8.0, exposure=0.5)
    assert valid.sum() == 255 and not valid[3, 4] and img[0, 0, 0] == 1.0
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="exposure"):
            jio.read_radiance(tmp_path / "f.exr", exposure=bad)
        with pytest.raises(ValueError, match="saturation"):
            jio.read_radiance(tmp_path / "f.exr", saturation=bad)


# ----------------------------------------------------------------------------- normal maps


def _sphere_normals(n=16):
    y, x = (np.mgrid[:n, :n] + 0.5) / n * 2 - 1
    r2 = x**2 + y**2
    nz = np.sqrt(np.clip(1 - r2, 0, None))
    nm = np.stack([x, -y, nz], -1)
    nm[r2 >= 1] = 0.0
    return nm


@pytest.mark.parametrize("ext", ["exr", "pfm", "npy"])
def test_read_normal_map_formats(tmp_path, ext):
    nm = _sphere_normals()
    p = tmp_path / f"n.{ext}"
    if ext == "npy":
        np.save(p, nm)
    else:
        jio.write_image(p, nm)
    got = jio.read_normal_map(p)
    assert got.shape == (16, 16, 3) and got.dtype == np.float64
    np.testing.assert_array_equal(np.any(got != 0, -1), np.any(nm != 0, -1))
    np.testing.assert_allclose(got, nm, atol=1e-6)
    on = np.any(got != 0, -1)
    np.testing.assert_allclose(np.linalg.norm(got[on], axis=-1), 1.0, atol=1e-12)


def test_read_normal_map_errors(tmp_path):
    nm = _sphere_normals()
    bad = nm.copy()
    bad[8, 8] *= 1.01
    np.save(tmp_path / "long.npy", bad)
    with pytest.raises(ValueError, match=r"long\.npy.*1 pixels.*row 8, column 8"):
        jio.read_normal_map(tmp_path / "long.npy")
    bad = nm.copy()
    bad[2, 3, 0] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(ValueError, match=r"nan\.npy.*not finite"):
        jio.read_normal_map(tmp_path / "nan.npy")
    np.save(tmp_path / "flat.npy", nm[..., :2])
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        jio.read_normal_map(tmp_path / "flat.npy")
    _write_codes(tmp_path / "n.png", np.full((4, 4, 3), 128, np.uint8))
    with pytest.raises(ValueError, match="integer"):
        jio.read_normal_map(tmp_path / "n.png")
    with pytest.raises(FileNotFoundError, match="nope.exr"):
        jio.read_normal_map(tmp_path / "nope.exr")


# ----------------------------------------------------------------------------- lossy / impossible writes, atomic writes (issue 12)


def test_impossible_writes_are_errors(tmp_path):
    with pytest.raises(ValueError, match=r"neg\.hdr.*negative.*1 values"):
        jio.write_image(tmp_path / "neg.hdr", np.array([[1.0, -0.5]]))
    with pytest.raises(ValueError, match=r"c\.exr.*complex"):
        jio.write_image(tmp_path / "c.exr", np.ones((2, 2)) * (1 + 1j))
    img = np.ones((4, 4, 3))
    img[0, 0] = [np.nan, np.inf, 1.0]
    with pytest.raises(ValueError, match=r"nf\.exr.*2 of 48"):
        jio.write_image(tmp_path / "nf.exr", img)
    with pytest.raises(ValueError, match="dtype"):
        jio.write_image(tmp_path / "o.exr", np.array([["a", "b"]]))
    assert sorted(os.listdir(tmp_path)) == []  # nothing written, no temporary files
    with pytest.raises(ValueError, match=r"r\.json"):
        jio.write_json(tmp_path / "r.json", {"rms": float("nan")})
    (tmp_path / "d.exr").mkdir()
    with pytest.raises(IsADirectoryError, match="d.exr"):
        jio.write_image(tmp_path / "d.exr", np.ones((2, 2)))


def test_writes_are_atomic(tmp_path, monkeypatch):
    p = tmp_path / "a.exr"
    old_umask = os.umask(0o022)
    try:
        jio.write_image(p, np.full((4, 4, 3), 1.0))
    finally:
        os.umask(old_umask)
    assert os.stat(p).st_mode & 0o777 == 0o644  # ordinary permissions, not the temporary file's 0600

    def broken(path, spec, data):
        with open(path, "wb") as f:
            f.write(b"\x76\x2f\x31\x01 half an EXR")
        raise OSError("No space left on device")

    monkeypatch.setattr(jio, "_write_pixels", broken)
    with pytest.raises(OSError, match="No space"):
        jio.write_image(p, np.full((4, 4, 3), 2.0))
    with pytest.raises(OSError, match="No space"):
        jio.write_image(tmp_path / "new.exr", np.full((4, 4, 3), 2.0))
    monkeypatch.undo()
    assert sorted(os.listdir(tmp_path)) == ["a.exr"]  # the old file intact, no partial file
    np.testing.assert_array_equal(jio.read_image(p), 1.0)
    jio.write_json(tmp_path / "r.json", {"a": 1})

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(jio.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        jio.write_json(tmp_path / "r.json", {"a": 2})
    monkeypatch.undo()
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "r.json"]
    assert json.loads((tmp_path / "r.json").read_text()) == {"a": 1}


# ----------------------------------------------------------------------------- alpha, orientation, windows


def _write_stored(path, codes, fmt, **attrs):
    """Write integer codes exactly as given (OpenImageIO told that alpha is unassociated, so nothing is scaled)."""
    import OpenImageIO as oiio

    h, w, c = codes.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    if c in (2, 4):
        spec.alpha_channel = c - 1
    for k, v in attrs.items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec), oiio.geterror()
    out.write_image(codes)
    out.close()


@pytest.mark.parametrize("ext,fmt,cmax", [("png", "uint8", 255), ("png", "uint16", 65535), ("tif", "uint16", 65535)])
def test_alpha_is_read_as_stored_and_must_be_declared(tmp_path, ext, fmt, cmax):
    """Colour codes are never multiplied by alpha; alpha is never sRGB-decoded; radiance needs `alpha` declared.
    (OpenImageIO's default read premultiplied: code 200 with alpha 128 read as 0.392 instead of 0.784.)"""
    dt = np.uint8 if cmax == 255 else np.uint16
    col = np.array([[[200, 100, 50], [255, 10, 0], [30, 30, 30]]], np.float64) * (cmax / 255)
    alpha = np.array([[cmax // 2 + 1, cmax, cmax // 2]], np.float64)  # just above half, opaque, at half
    codes = np.concatenate([np.round(col), alpha[..., None]], -1).astype(dt)
    p = tmp_path / f"rgba.{ext}"
    _write_stored(p, codes, fmt)
    info = jio.read_image_info(p)
    assert info["alpha"] and info["channels"] == 4
    exact = codes.astype(np.float64) / cmax
    np.testing.assert_allclose(jio.read_image(p, "linear"), exact, rtol=0, atol=1e-7)
    srgb = jio.read_image(p, "srgb")
    np.testing.assert_allclose(srgb[..., :3], _srgb_decode_reference(exact[..., :3]), rtol=1e-6, atol=1e-7)  # float32 pow
    np.testing.assert_allclose(srgb[..., 3], exact[..., 3], rtol=0, atol=1e-7)  # alpha: linear
    with pytest.raises(ValueError, match=r"rgba\.%s.*alpha channel.*`alpha`" % ext):
        jio.read_radiance(p, "linear")
    with pytest.raises(ValueError, match="`alpha` must be"):
        jio.read_radiance(p, "linear", alpha="premultiply")
    rad, valid = jio.read_radiance(p, "linear", alpha="ignore")
    assert rad.shape == (1, 3, 3)
    np.testing.assert_allclose(rad, exact[..., :3], rtol=0, atol=1e-7)
    # saturation looks at colour only: the opaque pixel is valid, the one with a full-scale red code is not
    np.testing.assert_array_equal(valid, [[True, False, True]])
    _, valid = jio.read_radiance(p, "linear", alpha="mask")
    np.testing.assert_array_equal(valid, [[True, False, False]])  # alpha at half of full scale: off the object


def test_grey_alpha_image_and_rgb_image_without_alpha(tmp_path):
    """Grey+alpha: one colour channel; a file without alpha needs no declaration and ignores `alpha`."""
    p = tmp_path / "la.png"
    _write_stored(p, np.array([[[128, 0], [128, 255]]], np.uint8), "uint8")
    rad, valid = jio.read_radiance(p, "linear", alpha="mask")
    assert rad.shape == (1, 2, 1)
    np.testing.assert_allclose(rad[..., 0], [[128 / 255, 128 / 255]], atol=1e-7)
    np.testing.assert_array_equal(valid, [[False, True]])
    q = tmp_path / "rgb.png"
    _write_stored(q, np.full((2, 2, 3), 7, np.uint8), "uint8")
    assert not jio.read_image_info(q)["alpha"]
    for a in (None, "ignore", "mask"):
        rad, valid = jio.read_radiance(q, "linear", alpha=a)
        assert rad.shape == (2, 2, 3) and valid.all()


def test_read_mask_rule_and_alpha(tmp_path):
    """Mask: first channel above half of full scale; an alpha channel only if opaque everywhere."""
    p = tmp_path / "m.png"
    _write_stored(p, np.array([[[127], [128], [255], [0]]], np.uint8), "uint8")
    np.testing.assert_array_equal(jio.read_mask(p), [[False, True, True, False]])
    p16 = tmp_path / "m16.png"
    _write_stored(p16, np.array([[[32767], [32768]]], np.uint16), "uint16")
    np.testing.assert_array_equal(jio.read_mask(p16), [[False, True]])
    opaque = tmp_path / "mo.png"
    _write_stored(opaque, np.array([[[255, 255], [0, 255]]], np.uint8), "uint8")
    np.testing.assert_array_equal(jio.read_mask(opaque), [[True, False]])
    cutout = tmp_path / "cut.png"  # grey 255 everywhere, the shape only in alpha: ambiguous
    _write_stored(cutout, np.array([[[255, 255], [255, 0]]], np.uint8), "uint8")
    with pytest.raises(ValueError, match=r"cut\.png.*alpha channel that is not opaque"):
        jio.read_mask(cutout)


def test_envmap_alpha(tmp_path):
    """An opaque alpha channel is dropped from an environment map; a partial one is an error."""
    img = np.ones((2, 4, 4), np.float32)
    p = tmp_path / "env.exr"
    jio.write_image(p, img)  # RGBA, alpha 1
    assert jio.read_image_info(p)["alpha"]
    assert jio.read_envmap(p).shape == (2, 4, 3)
    img[0, 0, 3] = 0.5
    jio.write_image(p, img)
    with pytest.raises(ValueError, match=r"env\.exr.*alpha channel"):
        jio.read_envmap(p)


def _pattern(h=3, w=5):
    """An asymmetric pattern: every pixel different, so any flip or turn shows."""
    return (np.arange(h * w * 3, dtype=np.float32).reshape(h, w, 3) + 1.0)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_orientation_tag_is_applied(tmp_path, orientation):
    """Row 0 is the top of the image as displayed, whatever the TIFF's Orientation tag; the reference is
    OpenImageIO's own `ImageBufAlgo.reorient`, and three tags are also checked by hand."""
    import OpenImageIO as oiio

    stored = _pattern()
    p = tmp_path / f"o{orientation}.tif"
    spec = oiio.ImageSpec(5, 3, 3, "float")
    spec.attribute("Orientation", orientation)
    out = oiio.ImageOutput.create(str(p))
    out.open(str(p), spec)
    out.write_image(stored)
    out.close()
    got = jio.read_image(p)
    ref = oiio.ImageBufAlgo.reorient(oiio.ImageBuf(str(p))).get_pixels(oiio.FLOAT)
    np.testing.assert_array_equal(got, ref)
    by_hand = {1: stored, 3: stored[::-1, ::-1], 4: stored[::-1], 6: np.rot90(stored, -1), 8: np.rot90(stored, 1)}
    if orientation in by_hand:
        np.testing.assert_array_equal(got, by_hand[orientation])
    info = jio.read_image_info(p)
    assert (info["height"], info["width"]) == got.shape[:2] == ((3, 5) if orientation <= 4 else (5, 3))
    assert info["orientation"] == orientation


def test_radiance_hdr_stored_bottom_up(tmp_path):
    """A Radiance file whose header says "+Y H +X W" stores its bottom row first: read top row first."""
    rows = np.array([[1.0, 1.0], [0.0, 0.0], [0.0, 0.0]])  # displayed: top row bright
    def rgbe(v):  # 1.0 -> mantissa 128, exponent 129: 128 * 2^(129 - 136) = 1
        return bytes([128, 128, 128, 129]) if v else bytes(4)
    for header, order in ((b"-Y 3 +X 2", rows), (b"+Y 3 +X 2", rows[::-1])):
        p = tmp_path / "a.hdr"
        with open(p, "wb") as f:
            f.write(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + header + b"\n")
            f.write(b"".join(rgbe(v) for v in order.ravel()))
        np.testing.assert_array_equal(jio.read_image(p)[..., 0], rows)


def test_exr_data_window(tmp_path):
    """An EXR whose data window covers its display window (overscan) is cut to it; one that does not is an
    error naming the file (before: its data were read as if they started at the display window's corner)."""
    import OpenImageIO as oiio

    def write(path, data, x, y, full):
        spec = oiio.ImageSpec(data.shape[1], data.shape[0], 3, "float")
        spec.x, spec.y = x, y
        spec.full_x, spec.full_y, spec.full_width, spec.full_height = full
        out = oiio.ImageOutput.create(str(path))
        out.open(str(path), spec)
        out.write_image(data)
        out.close()

    disp = _pattern(6, 8)
    over = np.zeros((8, 11, 3), np.float32)
    over[1:7, 2:10] = disp  # data window (11 x 8) at (-2, -1), display window 8 x 6 at the origin
    p = tmp_path / "over.exr"
    write(p, over, -2, -1, (0, 0, 8, 6))
    info = jio.read_image_info(p)
    assert (info["width"], info["height"]) == (8, 6)
    np.testing.assert_array_equal(jio.read_image(p), disp)
    q = tmp_path / "shifted.exr"
    write(q, disp, 2, 1, (0, 0, 8, 6))
    with pytest.raises(ValueError, match=r"shifted\.exr.*data window.*does not cover its display window"):
        jio.read_image_info(q)
    with pytest.raises(ValueError, match=r"shifted\.exr.*data window"):
        jio.read_image(q)
