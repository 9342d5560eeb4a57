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
