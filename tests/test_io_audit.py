"""Writers and readers of `jaxsh.io` at their edges: formats and channel counts `write_image` cannot store, PNG alpha,
errors that name the target file, option validation, envmap resampling against closed-form directions.

Independent references: OpenImageIO reading the stored codes directly (told not to premultiply), the IEC 61966-2-1
encoding written out here, and directions from the formulas of docs/conventions.md written out here."""

import json
import os
import re
import warnings

import jax
import numpy as np
import pytest

import jaxsh.io as jio


def _srgb_encode_reference(x):
    """IEC 61966-2-1 encoding, written independently of jaxsh: 12.92 x below 0.0031308, else 1.055 x^(1/2.4) - 0.055."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.abs(x) ** (1 / 2.4) - 0.055)


def _stored_codes(path):
    """The 8-bit codes as stored in the file (OpenImageIO told that alpha is unassociated: nothing is rescaled)."""
    import OpenImageIO as oiio

    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    try:
        codes = np.asarray(inp.read_image("uint8"))
    finally:
        inp.close()
    return codes.astype(np.int64)


@pytest.mark.parametrize("channels", [2, 4])
def test_png_alpha_is_stored_as_given(tmp_path, channels):
    """PNG's last channel of 2 or 4 is its alpha: stored linearly (round(255 a)), not sRGB-encoded, not scaled by
    `exposure`; the colour is sRGB-encoded and never divided by alpha. Before: OpenImageIO divided the colour by
    alpha (0.2 at alpha 0.25 was stored as the code of 0.8) and the alpha was sRGB-encoded (0.5 -> 188)."""
    colour = np.array([0.2, 0.4, 0.1])[: channels - 1]
    a = np.zeros((1, 4, channels), np.float32)
    a[..., :-1] = colour
    a[0, :, -1] = [1.0, 0.5, 0.25, 0.0]
    p = tmp_path / "a.png"
    jio.write_image(p, a, exposure=1.0)
    codes = _stored_codes(p)
    want_colour = np.round(255 * _srgb_encode_reference(np.clip(2.0 * colour, 0, 1)))
    np.testing.assert_array_equal(codes[0, :, :-1], np.broadcast_to(want_colour, (4, channels - 1)))
    np.testing.assert_array_equal(codes[0, :, -1], [255, 128, 64, 0])
    info = jio.read_image_info(p)
    assert info["alpha"] and info["channels"] == channels
    back = jio.read_image(p, "srgb")  # jaxsh's reader: colour decoded, alpha linear
    np.testing.assert_allclose(back[0, :, -1], np.round(255 * a[0, :, -1]) / 255, rtol=0, atol=1e-7)
    np.testing.assert_allclose(back[0, :, :-1], np.broadcast_to(2.0 * colour, (4, channels - 1)), rtol=0.02)


def test_write_refuses_what_it_cannot_store(tmp_path):
    """Extensions other than EXR/PFM/TIFF/HDR/PNG/JPEG, and channel counts a format does not hold, are errors
    naming the target (not the temporary file); nothing is left in the folder. Before: BMP/TGA were written as
    8-bit codes without the sRGB curve (0.5 -> 128), WebP lossily, a 2-channel JPEG got a made-up third channel, a
    4-channel JPEG lost its alpha, and OpenImageIO's refusals named `.a.hdr.xxxx.tmp.hdr`."""
    img3 = np.full((2, 2, 3), 0.5, np.float32)
    for name in ("a.bmp", "a.tga", "a.webp", "a.ppm", "a.gif", "noext"):
        with pytest.raises(ValueError, match=rf"{name}: cannot write") as e:
            jio.write_image(tmp_path / name, img3)
        assert ".tmp" not in str(e.value)
    for name, c in (("g.hdr", 1), ("ga.hdr", 2), ("rgba.hdr", 4), ("ga.pfm", 2), ("rgba.pfm", 4), ("ga.jpg", 2),
                    ("rgba.jpeg", 4), ("five.png", 5)):
        with pytest.raises(ValueError, match=rf"{name}: a \.\w+ file holds .* channels, got an array of {c}") as e:
            jio.write_image(tmp_path / name, np.full((2, 2, c), 0.5))
        assert ".tmp" not in str(e.value)
    assert os.listdir(tmp_path) == []
    for name, c in (("g.pfm", 1), ("rgb.hdr", 3), ("g.jpg", 1), ("ga.png", 2), ("x.exr", 5), ("x.tiff", 2)):
        jio.write_image(tmp_path / name, np.full((2, 2, c), 0.5))  # what the formats hold is written


def test_write_errors_name_the_target(tmp_path):
    """A missing folder, an empty array, float64 values beyond float32 and NumPy scalars in JSON: errors that name
    the file (and say what is wrong), never the temporary file."""
    with pytest.raises(FileNotFoundError, match=r"nodir") as e:
        jio.write_image(tmp_path / "nodir" / "a.exr", np.ones((2, 2, 3)))
    assert e.value.filename == str(tmp_path / "nodir" / "a.exr") and ".tmp" not in str(e.value)
    with pytest.raises(FileNotFoundError) as e:
        jio.write_json(tmp_path / "nodir" / "r.json", {"a": 1})
    assert e.value.filename == str(tmp_path / "nodir" / "r.json")
    for shape in ((0, 4, 3), (2, 2, 0)):
        with pytest.raises(ValueError, match=r"`array` must have at least one row, column and channel.*empty\.exr"):
            jio.write_image(tmp_path / "empty.exr", np.zeros(shape))
    with pytest.raises(ValueError, match=r"big\.exr: refusing to write 1 values beyond the float32 range"):
        jio.write_image(tmp_path / "big.exr", np.array([[1.0, 1e300]]))
    with pytest.raises(TypeError, match=r"r\.json.*float32"):
        jio.write_json(tmp_path / "r.json", {"x": np.float32(1.5)})
    assert os.listdir(tmp_path) == []


def test_write_image_options_are_validated(tmp_path):
    """`exposure` must be finite (NaN wrote a black PNG) and is for PNG/JPEG only (an EXR ignored it); integer
    arrays are refused (uint8 codes were written as values: a white PNG); bool arrays are 0 and 1."""
    img = np.full((2, 2, 3), 0.5)
    for bad in (float("nan"), float("inf"), "2", None, True):
        with pytest.raises(ValueError, match=r"`exposure` must be a finite number"):
            jio.write_image(tmp_path / "a.png", img, exposure=bad)
    with pytest.raises(ValueError, match=r"a\.exr: `exposure` scales PNG/JPEG"):
        jio.write_image(tmp_path / "a.exr", img, exposure=1.0)
    with pytest.raises(ValueError, match=r"`array` must hold float values.*uint8"):
        jio.write_image(tmp_path / "u.png", np.full((2, 2, 3), 128, np.uint8))
    assert os.listdir(tmp_path) == []
    jio.write_image(tmp_path / "a.exr", img, exposure=0)
    np.testing.assert_array_equal(jio.read_image(tmp_path / "a.exr"), 0.5)
    jio.write_image(tmp_path / "b.exr", np.array([[True, False]]))
    np.testing.assert_array_equal(jio.read_image(tmp_path / "b.exr")[..., 0], [[1.0, 0.0]])


def _f(v):
    """A smooth function of a direction, asymmetric in every axis."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([2 + x + 0.3 * y * z, 2 + y + 0.2 * x, 2 + z - 0.4 * x * y], -1)


def _latlong_reference(h, w):
    """Library directions of a lat-long grid, from docs/conventions.md: theta = pi (i + 1/2)/H, phi = 2 pi (j + 1/2)/W."""
    t, p = np.meshgrid(np.pi * (np.arange(h) + 0.5) / h, 2 * np.pi * (np.arange(w) + 0.5) / w, indexing="ij")
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def test_read_envmap_resamples_by_the_documented_directions_without_warnings(tmp_path):
    """Every resampling path (+z and +y lat-long to another height, +y with a width not divisible by 4, angular)
    gives f(direction) of the documented directions within the bilinear error, and emits no warning (it emitted
    JAX's "float64 ... truncated to float32" UserWarning without x64)."""
    m = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # file (x, y, z) -> library (x, -z, y), conventions.md

    def ydirs(h, w):  # a +y-up lat-long file: u = 0.5 along -z, u = 0.75 along +x, row 0 at +y
        t, u = np.meshgrid(np.pi * (np.arange(h) + 0.5) / h, 2 * np.pi * (np.arange(w) + 0.5) / w, indexing="ij")
        return np.stack([-np.sin(t) * np.sin(u), np.cos(t), np.sin(t) * np.cos(u)], -1)

    s = 128
    jj, ii = np.meshgrid(np.arange(s), np.arange(s))
    u, v = 2 * (jj + 0.5) / s - 1, 1 - 2 * (ii + 0.5) / s
    r = np.hypot(u, v)
    angular = np.stack([np.sin(np.pi * r) * u / r, np.sin(np.pi * r) * v / r, -np.cos(np.pi * r)], -1)
    cases = [(_f(_latlong_reference(32, 64)), {"height": 24}, 3e-3),
             (_f(ydirs(32, 64) @ m.T), {"up": "+y", "height": 24}, 3e-3),
             (_f(ydirs(33, 66) @ m.T), {"up": "+y"}, 2e-3),
             (np.where((r <= 1)[..., None], _f(angular @ m.T), 0.0), {"up": "+y", "layout": "angular", "height": 16},
              2e-3)]
    for k, (img, kw, tol) in enumerate(cases):
        p = tmp_path / f"e{k}.exr"
        jio.write_image(p, img.astype(np.float32))
        with jax.enable_x64(False), warnings.catch_warnings():  # the default configuration of a user
            warnings.simplefilter("error")
            env = jio.read_envmap(p, **kw)
        want = _f(_latlong_reference(*env.shape[:2]))
        err = np.abs(env - want).max()
        assert err < tol, (kw, err)


def test_read_envmap_height_is_validated(tmp_path):
    """`height` is a positive integer (2.7 was truncated to 2, "8" and True accepted)."""
    p = tmp_path / "e.exr"
    jio.write_image(p, np.ones((8, 16, 3)))
    for bad in (2.7, "8", True, 0, -2, float("nan")):
        with pytest.raises(ValueError, match=r"`height` must be a positive integer or None.*e\.exr"):
            jio.read_envmap(p, height=bad)
    assert jio.read_envmap(p, height=4).shape == (4, 8, 3)
    q = tmp_path / "one.exr"
    jio.write_image(q, np.ones((1, 1, 3)))
    with pytest.raises(ValueError, match=r"one\.exr.*1x1.*too small"):
        jio.read_envmap(q, up="+y", layout="angular")


def test_float_maps_refuse_integer_arrays_and_extra_channels(tmp_path):
    """Texture and normal maps are float storage only, `.npy` included (uint8 codes 200 were read as kd = 200),
    and a texture has exactly its channels (an RGBA EXR was cut to RGB, its alpha ignored)."""
    np.save(tmp_path / "kd.npy", np.full((2, 2, 3), 200, np.uint8))
    with pytest.raises(ValueError, match=r"kd\.npy.*dtype must be float, got uint8"):
        jio.read_texture(tmp_path / "kd.npy")
    np.save(tmp_path / "n.npy", np.tile(np.array([0, 0, 1], np.int8), (2, 2, 1)))
    with pytest.raises(ValueError, match=r"n\.npy.*dtype must be float, got int8"):
        jio.read_normal_map(tmp_path / "n.npy")
    a = np.full((2, 2, 4), 0.5)
    jio.write_image(tmp_path / "kd4.exr", a)
    with pytest.raises(ValueError, match=r"kd4\.exr.*\(H, W, 3\), got \(2, 2, 4\)"):
        jio.read_texture(tmp_path / "kd4.exr")
    np.save(tmp_path / "ok.npy", np.full((2, 2, 3), 0.25, np.float32))
    np.testing.assert_array_equal(jio.read_texture(tmp_path / "ok.npy"), 0.25)


def test_read_radiance_saturation_type(tmp_path):
    """A `saturation` that is not a number is a ValueError naming it (was a bare TypeError)."""
    jio.write_image(tmp_path / "f.exr", np.ones((2, 2, 3)))
    for bad in ("2", [2], {"a": 1}):
        with pytest.raises(ValueError, match=r"`saturation` must be a positive finite number"):
            jio.read_radiance(tmp_path / "f.exr", saturation=bad)


def test_unreadable_recorded_camera_names_the_manifest_field(tmp_path):
    """A texture map whose `jaxsh:camera` header cannot be read: the error names the manifest, `brdf.kd` and the
    file (was the manifest and the file only)."""
    import OpenImageIO as oiio

    n = 4
    spec = oiio.ImageSpec(n, n, 3, "float")
    spec.attribute("jaxsh:camera", "{not json")
    out = oiio.ImageOutput.create(str(tmp_path / "kd.exr"))
    assert out.open(str(tmp_path / "kd.exr"), spec)
    assert out.write_image(np.full((n, n, 3), 0.5, np.float32))
    out.close()
    cam = {"model": "orthographic", "scale": 0.5, "width": n, "height": n,
           "cam_to_world": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10], [0, 0, 0, 1]]}
    m = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "views": [{"camera": cam}],
         "lighting": {"directional": [{"direction": [0, 0, 1], "radiance": 1.0}]},
         "brdf": {"model": "torrance_sparrow", "kd": "kd.exr", "ks": 0.1, "mu": None, "sigma": 0.2}}
    (tmp_path / "m.json").write_text(json.dumps(m))
    with pytest.raises(jio.ManifestError, match=r"m\.json: `brdf\.kd` cannot be used: .*kd\.exr.*jaxsh:camera"):
        jio.read_manifest(tmp_path / "m.json")


def test_top_level_srgb_default_on_a_float_image_names_the_top_level_field(tmp_path):
    """A top-level `encoding` "srgb" (for a capture's PNGs) reaching an EXR view: the error names the top-level
    `encoding` it came from and the view's field that overrides it (it named only `views[1].encoding`, which the
    manifest does not have). With that override the manifest reads, the EXR as linear."""
    jio.write_image(tmp_path / "v0.png", np.full((4, 4, 3), 0.5))
    jio.write_image(tmp_path / "v1.exr", np.full((4, 4, 3), 0.5))
    cam = {"model": "orthographic", "scale": 0.5,
           "cam_to_world": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10], [0, 0, 0, 1]]}
    m = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "encoding": "srgb",
         "views": [{"image": "v0.png", "camera": cam}, {"image": "v1.exr", "camera": cam}],
         "lighting": {"directional": [{"direction": [0, 0, 1], "radiance": 1.0}]}}
    (tmp_path / "m.json").write_text(json.dumps(m))
    with pytest.raises(jio.ManifestError, match=r"m\.json: `encoding` \"srgb\" is the default of `views\[1\]\.encoding`"
                                                r", but the float image .*v1\.exr .*give `views\[1\]\.encoding` \"linear\""):
        jio.read_manifest(tmp_path / "m.json")
    m["views"][1]["encoding"] = "linear"
    (tmp_path / "m.json").write_text(json.dumps(m))
    assert [v["encoding"] for v in jio.read_manifest(tmp_path / "m.json")["views"]] == ["srgb", "linear"]


def test_read_mesh_refuses_non_finite_vertices(tmp_path):
    """A NaN vertex is an error naming the file (trimesh's processing dropped it and its triangle: 2 faces read as
    1); the finite triangle alone reads, with its 3 vertices."""
    p = tmp_path / "nan.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 1\nf 1 2 3\nf 1 2 4\n")
    with pytest.raises(ValueError, match=r"nan\.obj.*1 vertices are not finite.*vertex 3"):
        jio.read_mesh(p)
    q = tmp_path / "ok.obj"
    q.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    m = jio.read_mesh(q)
    assert len(m.faces) == 1 and np.array_equal(np.sort(m.vertices, axis=0), [[0, 0, 0], [0, 0, 0], [1, 1, 0]])


def _radiance_file(path, header: bytes, rgbe=(128, 128, 128, 129)):
    """A 1x2 Radiance RGBE file written byte by byte (flat scanlines): stored value 1.0 in every channel."""
    with open(path, "wb") as f:
        f.write(b"#?RADIANCE\n" + header + b"FORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 2\n")
        f.write(bytes(rgbe) * 2)


def test_radiance_exposure_and_colorcorr_are_divided_out(tmp_path):
    # Radiance's file format: EXPOSURE and COLORCORR lines are cumulative multipliers applied to the pixels; the
    # radiance is the stored value divided by their product (OpenImageIO reports only the last EXPOSURE line).
    # The stored value 1.0 is the RGBE quadruple (128, 128, 128, 129): 128/256 * 2^(129-128).
    cases = [(b"", [1.0, 1.0, 1.0]), (b"EXPOSURE=          1.0000000000000\n", [1.0, 1.0, 1.0]),
             (b"EXPOSURE=4\n", [0.25, 0.25, 0.25]), (b"EXPOSURE=2\nEXPOSURE=2\n", [0.25, 0.25, 0.25]),
             (b"COLORCORR=1 2 0.5\n", [1.0, 0.5, 2.0]), (b"EXPOSURE=2\nCOLORCORR=1 2 0.5\nGAMMA=1\n", [0.5, 0.25, 1.0])]
    for k, (header, want) in enumerate(cases):
        p = tmp_path / f"r{k}.hdr"
        _radiance_file(p, header)
        got = jio.read_image(p)
        assert got.shape == (1, 2, 3)
        np.testing.assert_array_equal(got[0, 0], np.asarray(want, np.float32), err_msg=repr(header))


def test_radiance_gamma_and_xyz_are_errors(tmp_path):
    p = tmp_path / "g.hdr"
    _radiance_file(p, b"GAMMA=2.2\n")
    with pytest.raises(ValueError, match="GAMMA=2.2"):
        jio.read_image(p)
    q = tmp_path / "x.hdr"
    with open(q, "wb") as f:
        f.write(b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 1 +X 2\n" + bytes((128, 128, 128, 129)) * 2)
    with pytest.raises(ValueError, match=r"x\.hdr"):  # OpenImageIO refuses XYZE itself ("no FORMAT specifier")
        jio.read_image(q)


def test_hdr_written_by_write_image_reads_back(tmp_path):
    img = np.array([[[0.25, 1.0, 3.0], [0.5, 0.125, 8.0]]], np.float32)  # exact in RGBE (powers of two)
    jio.write_image(tmp_path / "w.hdr", img)
    np.testing.assert_array_equal(jio.read_image(tmp_path / "w.hdr"), img)


@pytest.mark.parametrize("ext", ["tif", "exr"])
def test_files_of_several_subimages_are_errors(tmp_path, ext):
    oiio = pytest.importorskip("OpenImageIO")
    p = str(tmp_path / f"two.{ext}")
    specs = [oiio.ImageSpec(2, 2, 3, "float"), oiio.ImageSpec(2, 2, 3, "float")]
    specs[0].attribute("oiio:subimagename", "a")
    specs[1].attribute("oiio:subimagename", "b")
    out = oiio.ImageOutput.create(p)
    assert out.open(p, specs)
    out.write_image(np.full((2, 2, 3), 1.0, np.float32))
    assert out.open(p, specs[1], "AppendSubimage")
    out.write_image(np.full((2, 2, 3), 2.0, np.float32))
    out.close()
    for read in (jio.read_image, jio.read_image_info):
        with pytest.raises(ValueError, match=r"two\.%s.*2 subimages" % ext):
            read(p)


def _write_raw(path, arr, channel_names=None):
    """A float EXR written through OpenImageIO directly (channel names given, so no channel is taken as alpha)."""
    import OpenImageIO as oiio

    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, "float")
    if channel_names is not None:
        spec.channelnames = tuple(channel_names)
        spec.alpha_channel = -1
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(arr, np.float32))
    out.close()


_CAM = {"model": "orthographic", "scale": 0.5, "width": 4, "height": 4,
        "cam_to_world": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10], [0, 0, 0, 1]]}


def _render_manifest(tmp_path, lighting, **solve):
    m = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "views": [{"camera": _CAM}], "lighting": lighting,
         "brdf": {"model": "torrance_sparrow", "kd": 0.5, "ks": 0.1, "mu": None, "sigma": 0.2},
         **({"solve": solve} if solve else {})}
    (tmp_path / "m.json").write_text(json.dumps(m))
    return tmp_path / "m.json"


@pytest.mark.parametrize("names", [("R", "G"), ("R", "G", "B", "X"), ("R", "G", "B", "X", "Y")])
def test_envmap_colour_channels_must_be_grey_or_rgb(tmp_path, names):
    """An environment map of 2, 4 or 5 colour channels (no alpha): the manifest reader and `read_envmap` refuse it,
    naming the file and `lighting.envmap`. (Before: R, G gave a channel-mismatch error naming nothing, and extra
    channels were dropped without a word.)"""
    _write_raw(tmp_path / "env.exr", np.full((4, 8, len(names)), 0.5), names)
    with pytest.raises(ValueError, match=rf"env\.exr.* has {len(names)} colour channels"):
        jio.read_envmap(tmp_path / "env.exr")
    p = _render_manifest(tmp_path, {"envmap": "env.exr"})
    with pytest.raises(jio.ManifestError, match=rf"m\.json: `lighting\.envmap` has {len(names)} colour channels.*env\.exr"):
        jio.read_manifest(p)


@pytest.mark.parametrize("field, value", [("up", "+y"), ("layout", "angular"), ("encoding", "srgb")])
def test_envmap_fields_without_an_envmap_are_errors(tmp_path, field, value):
    """`up`, `layout`, `encoding` describe an envmap: given with `directional` sources only they were ignored (a user
    writing up "+y" for their source directions got them unconverted); now an error naming the field, as `rotation`."""
    p = _render_manifest(tmp_path, {"directional": [{"direction": [0, 0, 1], "radiance": 1.0}], field: value})
    with pytest.raises(jio.ManifestError, match=rf"m\.json: `lighting\.{field}` describes an `envmap`; there is none"):
        jio.read_manifest(p)


def test_render_of_a_map_too_small_for_the_default_cut_off_names_the_field(tmp_path, capsys):
    """A 2 x 1 lat-long map: the default cut-off min(ceil(4/sigma), H/2 - 1) is -1. `jaxsh render` stops with an
    error naming the manifest, `lighting.envmap` and `solve.render_lmax` (was "`lmax` must be a non-negative int,
    got -1"); with `render_lmax` 0 the map renders, a pixel facing it at least pi * mean * kd (closed form: the
    irradiance of a constant map, plus a non-negative specular term)."""
    from solvers.cli import main

    _write_raw(tmp_path / "env.exr", np.full((1, 2, 3), 0.25))
    p = _render_manifest(tmp_path, {"envmap": "env.exr"})
    assert main(["render", str(p), "--out", str(tmp_path / "out")]) == 2
    assert re.search(r"m\.json: `lighting\.envmap` is 1 row high .*`solve\.render_lmax`", capsys.readouterr().err)
    p = _render_manifest(tmp_path, {"envmap": "env.exr"}, render_lmax=0)
    assert main(["render", str(p), "--out", str(tmp_path / "out0")]) == 0
    img = np.asarray(jio.read_image(tmp_path / "out0" / "view_000.exr"))
    assert img[1:3, 1:3, 0].min() > np.pi * 0.25 * 0.5 * 0.999
