"""Image and environment-map I/O (OpenImageIO)."""

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
