"""Manifest fields that declare how inputs are read: `geometry.normals`, `camera.pixel_centers`, `views[k].alpha`;
textured BRDFs bound to one camera; errors from the files the manifest names (manifest path, field, file).

Expected values are computed here by hand (NumPy): pixel-centre coordinates, an OpenCV projection, a
Lambertian shading n·l, the pixels a sphere covers.
"""

import json

import numpy as np
import pytest

import jaxsh
from jaxsh import io as jio
from solvers._fit_manifest import fit_manifest
from solvers._render_manifest import camera_from_manifest, render_manifest

N = 16
C2W = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10], [0, 0, 0, 1]]  # looks down -z from z = 10; image up = +y
ORTHO = {"model": "orthographic", "scale": 2.4 / N, "width": N, "height": N, "cam_to_world": C2W}
SPHERE = {"sphere": {"center": [0, 0, 0], "radius": 1}}
UP = {"directional": [{"direction": [0, 0, 1], "radiance": 1.0}]}  # light from +z, irradiance 1


def _write(tmp_path, m, name="m.json"):
    p = tmp_path / name
    p.write_text(json.dumps(m))
    return str(p)


def _schema_ok(m):
    from tests.test_manifest import _validator

    _validator().validate(m)


def _world_xy(n, scale):
    """World (x, y) of the pixel centres of `ORTHO`-like cameras: column j -> x, row i -> -y (hand formula)."""
    c = (np.arange(n) + 0.5 - n / 2) * scale
    x, y = np.meshgrid(c, -c)
    return x, y


def _write_oiio(path, arr, fmt, **attrs):
    """Write `arr` (H, W, C) exactly as given (no premultiplication: "oiio:UnassociatedAlpha" = 1)."""
    import OpenImageIO as oiio

    arr = np.ascontiguousarray(arr)
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    for k, v in attrs.items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(arr), out.geterror()
    out.close()


# ----------------------------------------------------------------------------- geometry.normals


def _cube(tmp_path):
    import trimesh

    trimesh.creation.box(extents=(1, 1, 1)).export(tmp_path / "cube.ply")


@pytest.mark.parametrize("normals", ["faces", "smooth", None])
def test_mesh_normals_faces_shade_a_cube_flat(tmp_path, normals):
    """A unit cube seen from above, lit from +z, Lambertian kd = 1: n·l = 1 on the whole top face with face
    normals; the smoothed vertex normals (the default) tilt towards the corners and render less."""
    _cube(tmp_path)
    n, scale = 20, 0.08  # pixel centres at ±0.04, ..., ±0.52: none on the cube's edges (±0.5)
    cam = {"model": "orthographic", "scale": scale, "width": n, "height": n, "cam_to_world": C2W}
    geo = {"mesh": "cube.ply"} if normals is None else {"mesh": "cube.ply", "normals": normals}
    m = {"geometry": geo, "views": [{"camera": cam}], "lighting": UP,
         "brdf": {"model": "torrance_sparrow", "kd": 1.0, "ks": 0.0, "mu": None, "sigma": 0.2}}
    _schema_ok(m)
    render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)
    img = np.asarray(jio.read_image(tmp_path / "out" / "view_000.exr"))[..., 0]
    x, y = _world_xy(n, scale)
    top = (np.abs(x) < 0.5) & (np.abs(y) < 0.5)
    assert top.sum() == 144
    np.testing.assert_array_equal(img[~top], 0.0)
    if normals == "faces":
        np.testing.assert_allclose(img[top], 1.0, atol=1e-9)
    else:  # the default is "smooth": interpolated corner normals (±1, ±1, 1)/√3 at the corners
        assert img[top].min() < 0.8 and img[top].max() <= 1.0 + 1e-9


@pytest.mark.parametrize("geo", [{**SPHERE, "normals": "faces"}, {"normal_map": "n.npy", "normals": "smooth"}])
def test_mesh_normals_only_with_a_mesh(tmp_path, geo):
    np.save(tmp_path / "n.npy", np.zeros((N, N, 3)))
    m = {"geometry": geo, "views": [{"camera": ORTHO}]}
    with pytest.raises(jio.ManifestError, match=r"m\.json: `geometry\.normals` is only for a `geometry\.mesh`"):
        jio.read_manifest(_write(tmp_path, m))
    from tests.test_manifest import _validator

    assert list(_validator().iter_errors(m))


def test_mesh_normals_value_is_checked(tmp_path):
    _cube(tmp_path)
    m = {"geometry": {"mesh": "cube.ply", "normals": "flat"}, "views": [{"camera": ORTHO}]}
    with pytest.raises(jio.ManifestError, match=r"`geometry\.normals` must be one of \"smooth\", \"faces\""):
        jio.read_manifest(_write(tmp_path, m))
    r = jio.read_manifest(_write(tmp_path, {**m, "geometry": {"mesh": "cube.ply"}}))
    assert r["geometry"] == {"mesh": str(tmp_path / "cube.ply"), "normals": "smooth"}


# ----------------------------------------------------------------------------- camera.pixel_centers

W, H, F = 32, 24, 40.0
CX_CV, CY_CV = (W - 1) / 2, (H - 1) / 2  # an OpenCV calibration of a centred lens


def _pinhole(**kw):
    c2w = np.asarray(jaxsh.look_at([0.3, -4, 1], [0, 0, 0]))
    return {"model": "pinhole", "fx": F, "fy": F, "width": W, "height": H, "cam_to_world": c2w.tolist(), **kw}


def _ray_distance(cam_block, point, row, col):
    o, d = map(np.asarray, jaxsh.camera_rays(camera_from_manifest(cam_block)))
    v = point - o[row, col]
    return float(np.linalg.norm(v - (v @ d[row, col]) * d[row, col]))


def test_pixel_centers_integer_reads_opencv_intrinsics(tmp_path):
    """A point OpenCV images at the centre of pixel (row 7, column 22) — u = 22, v = 7 by OpenCV's pinhole formula —
    lies on jaxsh's ray through that pixel when the camera declares `"pixel_centers": "integer"`."""
    c2w = np.asarray(_pinhole()["cam_to_world"])
    row, col = 7, 22
    xc = np.array([(col - CX_CV) / F, (row - CY_CV) / F, 1.0]) * 3.7  # camera frame, depth 3.7
    xw = c2w[:3, :3] @ xc + c2w[:3, 3]
    # OpenCV's projection of the world point, by hand: x_cam = R^T (X - t); u = fx x/z + cx, v = fy y/z + cy
    p = c2w[:3, :3].T @ (xw - c2w[:3, 3])
    np.testing.assert_allclose([F * p[0] / p[2] + CX_CV, F * p[1] / p[2] + CY_CV], [col, row], atol=1e-12)
    views = [{"camera": _pinhole(cx=CX_CV, cy=CY_CV, pixel_centers="integer")},
             {"camera": _pinhole(cx=CX_CV + 0.5, cy=CY_CV + 0.5)},  # the default "half", shifted by hand
             {"camera": _pinhole(cx=CX_CV + 0.5, cy=CY_CV + 0.5, pixel_centers="half")},
             {"camera": _pinhole(cx=CX_CV, cy=CY_CV)}]  # OpenCV's K copied verbatim: half a pixel off
    m = {"geometry": SPHERE, "views": views}
    _schema_ok(m)
    cams = [v["camera"] for v in jio.read_manifest(_write(tmp_path, m))["views"]]
    for c in cams[:3]:
        assert _ray_distance(c, xw, row, col) < 1e-9
    assert _ray_distance(cams[3], xw, row, col) > 1e-2  # the verbatim K misses the point
    # the same camera, whichever way it is written: equal blocks, equal rays
    assert jio._same_camera(cams[0], cams[1]) and jio._same_camera(cams[0], cams[2])
    assert not jio._same_camera(cams[0], cams[3])
    rays = [np.asarray(jaxsh.camera_rays(camera_from_manifest(c))[1]) for c in cams[:2]]
    np.testing.assert_array_equal(rays[0], rays[1])


def test_pixel_centers_errors(tmp_path):
    m = {"geometry": SPHERE, "views": [{"camera": _pinhole(cx=16, cy=12, pixel_centers="corner")}]}
    with pytest.raises(jio.ManifestError, match=r"m\.json: `views\[0\]\.camera\.pixel_centers` must be one of"):
        jio.read_manifest(_write(tmp_path, m))
    from tests.test_manifest import _validator

    assert list(_validator().iter_errors(m))
    m = {"geometry": SPHERE, "views": [{"camera": {**ORTHO, "pixel_centers": "half"}}]}  # pinhole only
    with pytest.raises(jio.ManifestError, match=r"unknown field `views\[0\]\.camera\.pixel_centers`"):
        jio.read_manifest(_write(tmp_path, m))


def test_pixel_centers_views_compare_equal_for_a_shared_normal_map(tmp_path):
    """`geometry.normal_map` needs one camera for all views: "integer" and its "half" equivalent are that camera."""
    np.save(tmp_path / "n.npy", np.zeros((H, W, 3)))
    views = [{"camera": _pinhole(cx=CX_CV, cy=CY_CV, pixel_centers="integer")},
             {"camera": _pinhole(cx=CX_CV + 0.5, cy=CY_CV + 0.5)}]
    jio.read_manifest(_write(tmp_path, {"geometry": {"normal_map": "n.npy"}, "views": views}))
    views[1]["camera"]["cx"] = CX_CV
    with pytest.raises(jio.ManifestError, match=r"`views\[1\]\.camera` differs from `views\[0\]\.camera`"):
        jio.read_manifest(_write(tmp_path, {"geometry": {"normal_map": "n.npy"}, "views": views}))


# ----------------------------------------------------------------------------- pixel-grid BRDFs need one camera


def _kd_map():
    kd = np.full((N, N, 3), 0.2)
    kd[:, N // 2:] = 0.8  # left half 0.2, right half 0.8
    return kd


def test_texture_map_render_needs_the_camera_it_was_made_for(tmp_path):
    np.save(tmp_path / "kd.npy", _kd_map())
    np.save(tmp_path / "ks.npy", np.zeros((N, N, 3)))
    side = {**ORTHO, "cam_to_world": np.asarray(jaxsh.look_at([5, 0, 0], [0, 0, 0])).tolist()}  # same size
    brdf = {"model": "torrance_sparrow", "kd": "kd.npy", "ks": "ks.npy", "mu": None, "sigma": 0.2}
    m = {"geometry": SPHERE, "views": [{"camera": ORTHO}, {"camera": side}], "lighting": UP, "brdf": brdf}
    p = _write(tmp_path, m)
    with pytest.raises(jio.ManifestError,
                       match=r"m\.json: `views\[1\]\.camera` differs from `views\[0\]\.camera`: the texture map "
                             r"`brdf\.kd` .*kd\.npy is in the pixel grid of one camera") as e:
        render_manifest(p, tmp_path / "out", progress=False)
    assert str(e.value).startswith(p)
    assert not (tmp_path / "out").exists()
    # the same camera renders: kd(i, j) * E * n_z on the sphere (n_z from the pixel centre, by hand)
    m["views"] = [{"camera": ORTHO}, {"camera": ORTHO, "lighting": {"directional": [{"direction": [0, 0, 1],
                                                                                      "radiance": 2.0}]}}]
    _schema_ok(m)
    render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)
    x, y = _world_xy(N, 2.4 / N)
    r2 = x ** 2 + y ** 2
    nz = np.sqrt(np.clip(1 - r2, 0, None)) * (r2 < 1)
    for k, e_ in enumerate((1.0, 2.0)):
        got = np.asarray(jio.read_image(tmp_path / "out" / f"view_{k:03d}.exr"))
        np.testing.assert_allclose(got, _kd_map() * e_ * nz[..., None], atol=1e-6)


def test_spatial_rbf_render_needs_the_camera_it_was_fitted_in(tmp_path):
    rng = np.random.default_rng(0)
    model = jaxsh.RBFModel(rng.normal(size=(6, 5)), np.zeros((6, 3)), np.full((6, 3), 0.1), [0.3, 0.3, 1, 1, 0.5])
    jio.write_rbf(tmp_path / "s.npz", model, spatial=True, width=N, height=N)
    side = {**ORTHO, "cam_to_world": np.asarray(jaxsh.look_at([0, 5, 0], [0, 0, 0])).tolist()}
    m = {"geometry": SPHERE, "views": [{"camera": ORTHO}, {"camera": side}], "lighting": UP,
         "brdf": {"model": "rbf", "file": "s.npz"}}
    with pytest.raises(jio.ManifestError, match=r"m\.json: `views\[1\]\.camera` differs from `views\[0\]\.camera`: "
                                                r"the spatial RBF `brdf\.file` .*s\.npz"):
        render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)
    m["views"][1]["camera"] = ORTHO
    assert len(render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)) == 4


# ----------------------------------------------------------------------------- errors from the files


def _sphere_image():
    """Lambertian sphere (kd = (0.6, 0.5, 0.4)) under `UP`, by hand: kd n_z, 0 off the sphere; and the sphere mask."""
    x, y = _world_xy(N, 2.4 / N)
    r2 = x ** 2 + y ** 2
    inside = r2 < 1
    nz = np.sqrt(np.clip(1 - r2, 0, None)) * inside
    return nz[..., None] * np.array([0.6, 0.5, 0.4]), inside


def _fit_manifest_file(tmp_path, image, **view):
    m = {"geometry": SPHERE, "views": [{"image": image, "camera": ORTHO, **view}], "lighting": UP, "brdf": None}
    _schema_ok(m)
    return _write(tmp_path, m)


def test_nan_pixel_names_the_view_and_what_the_manifest_can_do(tmp_path):
    img, inside = _sphere_image()
    img = img.astype(np.float32)
    img[N // 2, N // 2, 1] = np.nan  # on the sphere
    _write_oiio(tmp_path / "img.exr", img, "float")  # jaxsh.io.write_image refuses NaN
    p = _fit_manifest_file(tmp_path, "img.exr")
    with pytest.raises(jio.ManifestError) as e:
        fit_manifest(p, tmp_path / "out", progress=False)
    msg = str(e.value)
    assert msg.startswith(f"{p}: `views[0].image` has 1 non-finite")
    assert f"(row {N // 2}, column {N // 2})" in msg and str(tmp_path / "img.exr") in msg
    assert "`views[0].mask`" in msg and "invalid=" not in msg
    # excluding the pixel with `views[0].mask` is what the message says: the fit then runs
    mask = np.full((N, N, 1), 255, np.uint8)
    mask[N // 2, N // 2] = 0
    _write_oiio(tmp_path / "mask.png", mask, "uint8")
    res = fit_manifest(_fit_manifest_file(tmp_path, "img.exr", mask="mask.png"), tmp_path / "out", progress=False)
    assert res["samples"]["valid"] == int(inside.sum()) - 1


@pytest.mark.parametrize("per_view", [False, True])
def test_nan_envmap_names_the_lighting_field(tmp_path, per_view):
    env = np.ones((16, 32, 3), np.float32)
    env[3, 7, 0] = np.nan
    _write_oiio(tmp_path / "env.exr", env, "float")
    lit = {"envmap": "env.exr"}
    m = {"geometry": SPHERE, "views": [{"camera": ORTHO}, {"camera": ORTHO, **({"lighting": lit} if per_view else {})}],
         "lighting": lit if not per_view else UP,
         "brdf": {"model": "torrance_sparrow", "kd": 0.5, "ks": 0.1, "mu": 1.5, "sigma": 0.2}}
    p = _write(tmp_path, m)
    field = r"views\[1\]\.lighting\.envmap" if per_view else r"lighting\.envmap"
    with pytest.raises(jio.ManifestError, match=rf"^{p}: `{field}` has 1 non-finite .*\(row 3, column 7\).*env\.exr"):
        render_manifest(p, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()  # refused before any output


@pytest.mark.parametrize("layout, shape, what", [("latlong", (8, 24), "twice as wide as high"),
                                                 ("angular", (8, 16), "must be square")])
def test_envmap_shape_names_the_manifest_and_field(tmp_path, layout, shape, what):
    jio.write_image(tmp_path / "env.exr", np.ones(shape + (3,), np.float32))
    m = {"geometry": SPHERE, "views": [{"camera": ORTHO}], "lighting": {"envmap": "env.exr", "layout": layout,
                                                                         "up": "+y"}}
    p = _write(tmp_path, m)
    with pytest.raises(jio.ManifestError, match=rf"^{p}: `lighting\.envmap` is a {shape[1]}x{shape[0]} image .*{what}: "
                                                rf".*env\.exr$"):
        jio.read_manifest(p)


def test_an_angular_map_needs_a_declared_up_axis(tmp_path):
    """An angular map's file frame is +y up; with `up` left at the lat-long default "+z" it was read turned by 90
    degrees, silently (a render 37 % off the equivalent lat-long probe). Now `up` is required for it, in the manifest
    (reader and schema) and in `read_envmap`; lat-long maps keep their default."""
    jio.write_image(tmp_path / "env.exr", np.ones((16, 16, 3), np.float32))
    m = {"geometry": SPHERE, "views": [{"camera": ORTHO}], "lighting": {"envmap": "env.exr", "layout": "angular"}}
    p = _write(tmp_path, m)
    with pytest.raises(jio.ManifestError, match=rf"^{p}: `lighting\.up` is required for an angular map"):
        jio.read_manifest(p)
    from jsonschema import ValidationError

    with pytest.raises(ValidationError):  # the schema's if/then on `layout` requires `up`
        _schema_ok(m)
    with pytest.raises(ValueError, match="`up` is required for an angular map"):
        jio.read_envmap(tmp_path / "env.exr", layout="angular")
    for up in ("+y", "+z"):
        m["lighting"]["up"] = up
        _schema_ok(m)
        assert jio.read_manifest(_write(tmp_path, m))["lighting"]["up"] == up
        assert jio.read_envmap(tmp_path / "env.exr", up=up, layout="angular").shape == (8, 16, 3)
    m["lighting"] = {"envmap": "env.exr"}  # lat-long: "+z" by default
    jio.write_image(tmp_path / "env.exr", np.ones((8, 16, 3), np.float32))
    assert jio.read_manifest(_write(tmp_path, m))["lighting"]["up"] == "+z"


@pytest.mark.parametrize("per_view", [False, True])
def test_non_unit_normal_map_names_the_field(tmp_path, per_view):
    _, inside = _sphere_image()
    nmap = np.zeros((N, N, 3), np.float32)
    nmap[inside] = [0.0, 0.0, 0.9]  # not unit length
    jio.write_image(tmp_path / "n.exr", nmap)
    view = {"camera": ORTHO, **({"normal_map": "n.exr"} if per_view else {})}
    m = {"views": [view], "lighting": UP, "brdf": {"model": "torrance_sparrow", "kd": 0.5, "ks": 0.1, "mu": 1.5,
                                                    "sigma": 0.2}}
    if not per_view:
        m["geometry"] = {"normal_map": "n.exr"}
    p = _write(tmp_path, m)
    field = r"views\[0\]\.normal_map" if per_view else r"geometry\.normal_map"
    with pytest.raises(jio.ManifestError, match=rf"^{p}: `{field}` cannot be used: .*n\.exr.*unit vectors"):
        render_manifest(p, tmp_path / "out", progress=False)


@pytest.mark.parametrize("channels, alpha", [(1, None), (2, "ignore")])
def test_image_channels_error_starts_with_the_manifest(tmp_path, channels, alpha):
    img, _ = _sphere_image()
    codes = np.round(img[..., :1] * 255)
    if channels == 2:
        codes = np.concatenate([codes, np.full_like(codes, 255)], -1)  # grey + alpha
    _write_oiio(tmp_path / "img.png", codes.astype(np.uint8), "uint8")
    p = _fit_manifest_file(tmp_path, "img.png", encoding="linear", **({"alpha": alpha} if alpha else {}))
    with pytest.raises(jio.ManifestError, match=rf"^{p}: `views\[0\]\.image` must have 3 colour channels \(RGB\), got 1 "
                                                r"\(alpha not counted\): .*img\.png$"):
        fit_manifest(p, tmp_path / "out", progress=False)


# ----------------------------------------------------------------------------- views[k].alpha


def _rgba_capture(tmp_path):
    """A 16-bit linear capture as RGB and as RGBA PNG (the same colour codes), alpha 0 on the left 5 columns."""
    img, inside = _sphere_image()
    codes = np.round(img * 65535).astype(np.uint16)
    assert codes.max() < 65535  # nothing saturates
    alpha = np.full((N, N, 1), 65535, np.uint16)
    alpha[:, :5] = 0
    alpha[:, 5] = 32768  # just above half of full scale: kept
    _write_oiio(tmp_path / "rgb.png", codes, "uint16")
    _write_oiio(tmp_path / "rgba.png", np.concatenate([codes, alpha], -1), "uint16")
    return inside, alpha[..., 0]


def test_alpha_must_be_declared(tmp_path):
    _rgba_capture(tmp_path)
    p = _fit_manifest_file(tmp_path, "rgba.png", encoding="linear")
    with pytest.raises(jio.ManifestError, match=rf"^{p}: `views\[0\]\.alpha` is required: the image .*rgba\.png has an "
                                                "alpha channel"):
        jio.read_manifest(p)
    m = json.loads(open(p).read())
    m["views"][0]["alpha"] = "premultiplied"
    with pytest.raises(jio.ManifestError, match=r"`views\[0\]\.alpha` must be one of \"ignore\", \"mask\""):
        jio.read_manifest(_write(tmp_path, m))
    from tests.test_manifest import _validator

    assert list(_validator().iter_errors(m))


def test_alpha_ignore_and_mask(tmp_path):
    inside, alpha = _rgba_capture(tmp_path)
    rgb = fit_manifest(_fit_manifest_file(tmp_path, "rgb.png", encoding="linear"), tmp_path / "rgb", progress=False)
    ign = fit_manifest(_fit_manifest_file(tmp_path, "rgba.png", encoding="linear", alpha="ignore"), tmp_path / "ign",
                       progress=False)
    assert ign["samples"] == rgb["samples"] and rgb["samples"]["valid"] == int(inside.sum())
    assert ign["brdf"] == rgb["brdf"]
    # "mask": the pixels with alpha 0 (the left 5 columns) are not samples; alpha 32768 > 65535 / 2 is kept
    m = {"geometry": SPHERE, "encoding": "linear", "alpha": "mask",  # the top-level default
         "views": [{"image": "rgba.png", "camera": ORTHO}], "lighting": UP, "brdf": None}
    _schema_ok(m)
    msk = fit_manifest(_write(tmp_path, m), tmp_path / "msk", progress=False)
    want = int((inside & (alpha > 65535 / 2)).sum())
    assert msk["samples"]["valid"] == want and want < int(inside.sum()) - 10
    # the RGB file with "mask" declared: no alpha channel, nothing dropped
    res = fit_manifest(_fit_manifest_file(tmp_path, "rgb.png", encoding="linear", alpha="mask"), tmp_path / "rgbm",
                       progress=False)
    assert res["samples"]["valid"] == int(inside.sum())


def test_mask_file_with_transparent_alpha_names_the_field(tmp_path):
    img, _ = _sphere_image()
    jio.write_image(tmp_path / "img.exr", img.astype(np.float32))
    mask = np.full((N, N, 2), 255, np.uint8)
    mask[0, 0, 1] = 0  # grey + alpha, not opaque: which channel is the mask?
    _write_oiio(tmp_path / "mask.png", mask, "uint8")
    p = _fit_manifest_file(tmp_path, "img.exr", mask="mask.png")
    with pytest.raises(jio.ManifestError, match=rf"^{p}: `views\[0\]\.mask` cannot be used: .*mask\.png"):
        fit_manifest(p, tmp_path / "out", progress=False)


def test_recorded_camera_round_trips_exactly(tmp_path):
    """`write_image(camera=)` / `write_rbf(camera=)` record a manifest camera; `recorded_camera` gives it back
    exactly (the JSON of float64 values round-trips), and files without one give None."""
    cam = {"model": "pinhole", "fx": 801.25, "fy": 799.5, "cx": 320.1 + 0.5, "cy": 0.1 + 0.2, "width": 4, "height": 3,
           "cam_to_world": np.asarray(jaxsh.look_at([0.3, -2.0, 1.1], [0, 0, 0]), np.float64)}
    jio.write_image(tmp_path / "k.exr", np.ones((3, 4, 3)), camera=cam)
    back = jio.recorded_camera(tmp_path / "k.exr")
    assert jio._same_camera(back, cam)
    np.testing.assert_array_equal(jio.read_texture(tmp_path / "k.exr"), np.ones((3, 4, 3)))
    jio.write_image(tmp_path / "plain.exr", np.ones((3, 4, 3)))
    assert jio.recorded_camera(tmp_path / "plain.exr") is None
    np.save(tmp_path / "k.npy", np.ones((3, 4, 3)))
    assert jio.recorded_camera(tmp_path / "k.npy") is None
    with pytest.raises(ValueError, match=r"k\.pfm: a `camera` is recorded in EXR headers only"):
        jio.write_image(tmp_path / "k.pfm", np.ones((3, 4, 3)), camera=cam)
    with pytest.raises(ValueError, match=r"`camera` is 4x3 but the map 5x3"):
        jio.write_image(tmp_path / "k5.exr", np.ones((3, 5, 3)), camera=cam)
    model = jaxsh.RBFModel(np.zeros((2, 5)), np.zeros((2, 3)), np.zeros((6, 3)), np.ones(5))
    jio.write_rbf(tmp_path / "s.npz", model, spatial=True, width=4, height=3, camera=cam)
    assert jio._same_camera(jio.recorded_camera(tmp_path / "s.npz"), cam)
    assert jio.read_rbf(tmp_path / "s.npz")["spatial"]
    jio.write_rbf(tmp_path / "s0.npz", model, spatial=True, width=4, height=3)
    assert jio.recorded_camera(tmp_path / "s0.npz") is None
    with pytest.raises(ValueError, match="spatial RBF only, of its `width` x `height`"):
        jio.write_rbf(tmp_path / "s1.npz", model, spatial=True, width=5, height=3, camera=cam)


def test_texture_map_with_a_recorded_camera_needs_that_camera(tmp_path):
    """A map that records its camera refuses every other camera, views[0] included; its own camera renders."""
    cam = jio.read_manifest(_write(tmp_path, {"geometry": SPHERE, "views": [{"camera": ORTHO}], "lighting": UP,
                                                "brdf": None}))["views"][0]["camera"]
    jio.write_image(tmp_path / "kd.exr", _kd_map(), camera=cam)
    np.save(tmp_path / "ks.npy", np.zeros((N, N, 3)))
    brdf = {"model": "torrance_sparrow", "kd": "kd.exr", "ks": "ks.npy", "mu": None, "sigma": 0.2}
    side = {**ORTHO, "cam_to_world": np.asarray(jaxsh.look_at([5, 0, 0], [0, 0, 0])).tolist()}
    m = {"geometry": SPHERE, "views": [{"camera": side}], "lighting": UP, "brdf": brdf}
    with pytest.raises(jio.ManifestError, match=r"m\.json: `views\[0\]\.camera` is not the camera the texture map "
                                                r"`brdf\.kd` .*kd\.exr is in"):
        jio.read_manifest(_write(tmp_path, m))
    m["views"] = [{"camera": ORTHO}]
    assert jio.read_manifest(_write(tmp_path, m))["brdf"]["kd"].shape == (N, N, 3)


# ----------------------------------------------------------------------------- lighting.rotation


def test_envmap_rotation_turns_the_map_into_the_world_frame(tmp_path):
    """A probe map holding f(w) = 1 + d.w in the library frame, with `rotation` R, is the world lighting
    1 + (R d).w: its l = 1 coefficients are sqrt(4 pi / 3) (R d)_(y, z, x) and its l = 0 one sqrt(4 pi) (closed
    forms of the orthonormal real basis, conventions.md), on every channel. Also from a "+y"-up file, whose pixels are
    placed by the documented convention (row 0 at +y, u = 0.5 along -z, u = 0.75 along +x). A transposed R would
    put the lobe at R^T d."""
    from solvers._render_manifest import lighting_from_manifest

    h = 16
    d = np.array([0.48, -0.6, 0.64])
    ang = 0.7
    rz = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(0.4), -np.sin(0.4)], [0, np.sin(0.4), np.cos(0.4)]])
    rot = rz @ rx
    lib = np.asarray(jaxsh.latlong_directions(h, 2 * h), np.float64)  # +z file: library directions
    theta = np.pi * (np.arange(h) + 0.5) / h
    alpha = 2 * np.pi * (np.arange(2 * h) + 0.5) / (2 * h)
    st = np.sin(theta)[:, None]
    file_y = np.stack([-st * np.sin(alpha), np.broadcast_to(np.cos(theta)[:, None], (h, 2 * h)),
                       st * np.cos(alpha)], -1)  # file-frame directions of a +y-up lat-long map
    for up, dirs in (("+z", lib), ("+y", file_y @ jio.Y_UP_TO_Z_UP.T)):  # library direction = M v
        jio.write_image(tmp_path / "probe.exr", np.repeat((1.0 + dirs @ d)[..., None], 3, -1))
        lit = {"envmap": "probe.exr", "up": up, "rotation": rot.tolist()}
        m = {"geometry": SPHERE, "views": [{"camera": ORTHO}], "lighting": lit, "brdf": None}
        _schema_ok(m)
        slow, _, _ = lighting_from_manifest(jio.read_manifest(_write(tmp_path, m)), 0.5, 2)
        slow = np.asarray(slow)
        want1 = np.sqrt(4 * np.pi / 3) * (rot @ d)[[1, 2, 0]]
        tol = 1e-6  # the EXR stores float32
        np.testing.assert_allclose(slow[0], np.sqrt(4 * np.pi), atol=tol)
        np.testing.assert_allclose(slow[1:4], np.repeat(want1[:, None], 3, 1), atol=tol)
        np.testing.assert_allclose(slow[4:9], 0.0, atol=tol)
        assert np.abs(slow[1:4, 0] - np.sqrt(4 * np.pi / 3) * (rot.T @ d)[[1, 2, 0]]).max() > 0.1


def test_envmap_rotation_errors(tmp_path):
    jio.write_image(tmp_path / "probe.exr", np.ones((8, 16, 3)))
    base = {"geometry": SPHERE, "views": [{"camera": ORTHO}], "brdf": None}
    cases = [({"envmap": "probe.exr", "rotation": [[1, 0, 0], [0, 1, 0]]}, r"`lighting\.rotation` must be a 3x3"),
             ({"envmap": "probe.exr", "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]},
              r"`lighting\.rotation` must be a rotation"),
             ({"envmap": "probe.exr", "rotation": [[1, 0, 0], [0, 1, 0.1], [0, 0, 1]]},
              r"`lighting\.rotation` must be a rotation"),
             ({**UP, "rotation": np.eye(3).tolist()}, r"`lighting\.rotation` turns an `envmap`.*there is none")]
    for lit, msg in cases:
        with pytest.raises(jio.ManifestError, match=r"m\.json: " + msg):
            jio.read_manifest(_write(tmp_path, {**base, "lighting": lit}))


# ----------------------------------------------------------------------------- normals facing the camera


def _sphere_normals(n=N, scale=2.4 / N):
    """World normals of the unit sphere under `ORTHO` (by hand; zero off the sphere)."""
    x, y = _world_xy(n, scale)
    r2 = x ** 2 + y ** 2
    inside = r2 < 1
    return np.stack([x, y, np.sqrt(np.clip(1 - r2, 0, None))], -1) * inside[..., None]


@pytest.mark.parametrize("command", ["render", "fit"])
def test_normal_map_facing_away_is_an_error(tmp_path, command):
    """A normal map in another axis convention (here y and z flipped, as a +y-up, +z-towards-the-viewer camera map
    read as world normals under an OpenCV camera) faces away from the camera: an error naming the field and file, for
    both commands, instead of a `no_signal` fit and a black render. The right map passes."""
    good = _sphere_normals()
    np.save(tmp_path / "n_bad.npy", good * np.array([1.0, -1.0, -1.0]))
    np.save(tmp_path / "n.npy", good)
    img = (np.clip(good[..., 2], 0, None)[..., None] * np.array([0.6, 0.5, 0.4])).astype(np.float32)
    jio.write_image(tmp_path / "img.exr", img)
    for nmap, ok in (("n_bad.npy", False), ("n.npy", True)):
        view = {"camera": ORTHO, **({"image": "img.exr"} if command == "fit" else {})}
        brdf = None if command == "fit" else {"model": "torrance_sparrow", "kd": 0.5, "ks": 0.0, "mu": None,
                                               "sigma": 0.2}
        m = {"geometry": {"normal_map": nmap}, "views": [view], "lighting": UP, "brdf": brdf}
        p = _write(tmp_path, m)
        run = (lambda: render_manifest(p, tmp_path / "out", progress=False)) if command == "render" else \
            (lambda: fit_manifest(p, tmp_path / "fit", progress=False))
        if ok:
            run()
            continue
        n_obj = int(np.count_nonzero(good.any(-1)))  # every object pixel faces away
        with pytest.raises(jio.ManifestError, match=rf"m\.json: `geometry\.normal_map`: {n_obj} of the {n_obj} object "
                                                    r"pixels of `views\[0\]` have normals facing away .*world frame"
                                                    r".*n_bad\.npy"):
            run()


def test_render_refuses_a_later_view_before_writing_any(tmp_path):
    """`jaxsh render` checks every view's normals before it writes: a second view whose map faces away leaves no
    output at all (before, `view_000` was written and then the command failed)."""
    good = _sphere_normals()
    np.save(tmp_path / "n.npy", good)
    np.save(tmp_path / "n_bad.npy", good * np.array([1.0, -1.0, -1.0]))
    brdf = {"model": "torrance_sparrow", "kd": 0.5, "ks": 0.0, "mu": None, "sigma": 0.2}
    m = {"geometry": {"normal_map": "n.npy"}, "views": [{"camera": ORTHO}, {"camera": ORTHO, "normal_map": "n_bad.npy"}],
         "lighting": UP, "brdf": brdf}
    with pytest.raises(jio.ManifestError, match=r"`views\[1\]\.normal_map`: .* of `views\[1\]` have normals facing away"):
        render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_mesh_wound_inside_out_is_an_error(tmp_path):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2)
    sphere.export(tmp_path / "ball.ply")
    inv = sphere.copy()
    inv.invert()
    inv.export(tmp_path / "inside_out.ply")
    brdf = {"model": "torrance_sparrow", "kd": 0.5, "ks": 0.0, "mu": None, "sigma": 0.2}
    m = {"geometry": {"mesh": "inside_out.ply"}, "views": [{"camera": ORTHO}], "lighting": UP, "brdf": brdf}
    with pytest.raises(jio.ManifestError, match=r"m\.json: `geometry\.mesh`: \d+ of the \d+ object pixels of "
                                                r"`views\[0\]` have normals facing away .*wound inside out.*inside_out"):
        render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)
    m["geometry"] = {"mesh": "ball.ply"}
    assert len(render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)) == 2


# ----------------------------------------------------------------------------- a mesh in `jaxsh fit`


def test_fit_with_a_mesh_recovers_its_render(tmp_path):
    """`jaxsh fit` with `geometry.mesh` and a Torrance-Sparrow BRDF (the path of howto_multiview_hdr.md sec. 2).
    `fit_manifest`'s local trimesh shadowed its `mesh` (device-mesh) argument, so this crashed in
    `shard_observations` ("`mesh` must be a jax.sharding.Mesh ..., got Trimesh"). A plumbing check: the images are
    `jaxsh render`s of the same manifest, so the fit must give back the BRDF they were made with."""
    import trimesh

    trimesh.creation.icosphere(subdivisions=3).export(tmp_path / "ball.ply")
    n = 24
    cam = {"model": "orthographic", "scale": 2.4 / n, "width": n, "height": n, "cam_to_world": C2W}
    dirs = [[0.3, 0.2, 0.93], [-0.5, 0.3, 0.81], [0.1, -0.6, 0.79]]
    truth = {"model": "torrance_sparrow", "kd": [0.5, 0.4, 0.3], "ks": [0.3, 0.3, 0.3], "mu": None, "sigma": 0.25}
    views = [{"camera": cam, "lighting": {"directional": [{"direction": d, "radiance": 2.0}]}} for d in dirs]
    render_manifest(_write(tmp_path, {"geometry": {"mesh": "ball.ply"}, "views": views, "brdf": truth},
                           "render.json"), tmp_path / "imgs", progress=False)
    fit_views = [{**v, "image": f"imgs/view_{k:03d}.exr"} for k, v in enumerate(views)]
    m = {"geometry": {"mesh": "ball.ply"}, "views": fit_views, "brdf": None, "solve": {"fresnel": False}}
    _schema_ok(m)
    res = fit_manifest(_write(tmp_path, m), tmp_path / "fit", progress=False)
    assert res["status"] == "converged"
    np.testing.assert_allclose(res["brdf"]["kd"], truth["kd"], rtol=1e-4)
    np.testing.assert_allclose(res["brdf"]["ks"], truth["ks"], rtol=1e-4)
    assert res["brdf"]["sigma"] == pytest.approx(truth["sigma"], rel=1e-4)


def test_fit_rerenders_every_object_pixel_and_counts_them(tmp_path):
    """The re-renders of `jaxsh fit` are the model at every object pixel, clipped and masked ones included (they
    were 0 there: `observations` dropped the weight-0 samples), and `samples.total` counts every object pixel while
    `samples.valid` counts the used ones (docs/results.md). The images are `jaxsh render`s of the same manifest;
    clipping them at `solve.saturation` removes the brightest pixels, which the re-render must give back."""
    n = 24
    cam = {"model": "orthographic", "scale": 2.4 / n, "width": n, "height": n, "cam_to_world": C2W}
    dirs = [[0.3, 0.2, 0.93], [-0.5, 0.3, 0.81], [0.1, -0.6, 0.79]]
    truth = {"model": "torrance_sparrow", "kd": [0.5, 0.4, 0.3], "ks": [0.3, 0.3, 0.3], "mu": None, "sigma": 0.25}
    views = [{"camera": cam, "lighting": {"directional": [{"direction": d, "radiance": 2.0}]}} for d in dirs]
    render_manifest(_write(tmp_path, {"geometry": SPHERE, "views": views, "brdf": truth}, "render.json"),
                    tmp_path / "imgs", progress=False)
    imgs = [np.asarray(jio.read_image(tmp_path / "imgs" / f"view_{k:03d}.exr")) for k in range(3)]
    x, y = _world_xy(n, 2.4 / n)
    obj = x ** 2 + y ** 2 < 1  # the sphere's pixels, by hand
    sat = 0.9
    clipped = [obj & np.any(im >= sat, -1) for im in imgs]
    assert all(c.sum() >= 5 for c in clipped)
    left = np.zeros((n, n), bool)
    left[:, : n // 2] = True
    jio.write_image(tmp_path / "left.exr", left.astype(np.float32))  # a mask for view 0: the left half only
    fit_views = [{**v, "image": f"imgs/view_{k:03d}.exr"} for k, v in enumerate(views)]
    fit_views[0]["mask"] = "left.exr"
    m = {"geometry": SPHERE, "views": fit_views, "brdf": None, "solve": {"fresnel": False, "saturation": sat}}
    res = fit_manifest(_write(tmp_path, m), tmp_path / "fit", progress=False)
    assert res["status"] == "converged"
    used = [obj & ~c for c in clipped]
    used[0] &= left
    assert res["samples"]["total"] == 3 * int(obj.sum())
    assert res["samples"]["valid"] == sum(int(u.sum()) for u in used)
    for k, im in enumerate(imgs):
        got = np.asarray(jio.read_image(tmp_path / "fit" / f"view_{k:03d}.exr"))
        np.testing.assert_allclose(got[obj], im[obj], rtol=1e-4, atol=1e-6)  # clipped and masked pixels too
        np.testing.assert_array_equal(got[~obj], 0.0)


def test_sharing_honours_solve_saturation(tmp_path):
    """`solve.saturation` (an extra threshold for all views, manifest.md) drops the clipped pixels from the
    reflectance samples of `"sharing"` too; it was silently ignored there. Expected counts by hand: object pixels
    with cos(theta_i) and cos(theta_o) above `min_cos` (0.1) and no channel at or above the threshold."""
    n = 24
    cam = {"model": "orthographic", "scale": 2.4 / n, "width": n, "height": n, "cam_to_world": C2W}
    dirs = np.array([[0.3, 0.2, 0.93], [-0.5, 0.3, 0.81], [0.1, -0.6, 0.79]])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    truth = {"model": "torrance_sparrow", "kd": [0.5, 0.4, 0.3], "ks": [0.3, 0.3, 0.3], "mu": None, "sigma": 0.25}
    views = [{"camera": cam, "lighting": {"directional": [{"direction": d.tolist(), "radiance": 2.0}]}} for d in dirs]
    render_manifest(_write(tmp_path, {"geometry": SPHERE, "views": views, "brdf": truth}, "render.json"),
                    tmp_path / "imgs", progress=False)
    imgs = [np.asarray(jio.read_image(tmp_path / "imgs" / f"view_{k:03d}.exr")) for k in range(3)]
    nrm = _sphere_normals(n, 2.4 / n)
    obj = nrm.any(-1)
    sat = 0.9
    fit_views = [{**v, "image": f"imgs/view_{k:03d}.exr"} for k, v in enumerate(views)]
    counts = {}
    for s in (None, sat):
        solve = {"brdf_model": "sharing", "n_centers": 20, **({} if s is None else {"saturation": s})}
        m = {"geometry": SPHERE, "views": fit_views, "brdf": None, "solve": solve}
        counts[s] = fit_manifest(_write(tmp_path, m), tmp_path / f"fit{s}", progress=False)["sharing"]["samples_per_view"]
    for k, (d, im) in enumerate(zip(dirs, imgs)):
        lit = obj & (nrm @ d > 0.1) & (nrm[..., 2] > 0.1)
        assert counts[None][k] == int(lit.sum())
        assert counts[sat][k] == int((lit & ~np.any(im >= sat, -1)).sum()) < counts[None][k]


@pytest.mark.parametrize("field,value,msg", [
    ("mask", "m.png", r"`views\[0\]\.mask` describes a captured image, which `jaxsh render` does not read"),
    ("exposure", 0.5, r"`views\[0\]\.exposure` describes a captured image"),
    ("saturation", 0.5, r"`views\[0\]\.saturation` describes a captured image"),
    ("solve.fresnel", False, r"`solve\.fresnel` is a setting of `jaxsh fit`; `jaxsh render` uses only "
                             r"`solve\.render_lmax`"),
    ("solve.brdf_model", "sharing", r"`solve\.brdf_model` is a setting of `jaxsh fit`")])
def test_render_refuses_fields_it_does_not_use(tmp_path, field, value, msg):
    """`jaxsh render` reads no captured image: a mask, exposure or saturation (or a fit setting) would have been
    silently ignored (the render was byte-identical); it is an error before any output, naming the field."""
    jio.write_image(tmp_path / "m.png", np.ones((N, N, 3)))
    brdf = {"model": "torrance_sparrow", "kd": 0.5, "ks": 0.0, "mu": None, "sigma": 0.2}
    view = {"camera": ORTHO}
    m = {"geometry": SPHERE, "views": [view], "lighting": UP, "brdf": brdf}
    if field.startswith("solve."):
        m["solve"] = {field[6:]: value, "render_lmax": 4}
    else:
        view[field] = value
    with pytest.raises(jio.ManifestError, match=r"m\.json: " + msg):
        render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()
    m["solve"] = {"render_lmax": 4}
    view.pop(field, None)
    assert len(render_manifest(_write(tmp_path, m), tmp_path / "out", progress=False)) == 2


# ----------------------------------------------------------------------------- null equals absent


def _same(a, b):
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b))
    if isinstance(a, jaxsh.RBFModel):
        return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("centers", "weights", "poly", "scale"))
    return a == b


def test_null_equals_absent_for_every_optional_field(tmp_path):
    """manifest.md: `null` equals absent for every optional field. Each optional field of each block, set to null,
    gives the same `read_manifest` result as the field left out, and the schema accepts both (`up` and `layout`
    were refused by the reader; `geometry.mesh`/`sphere`/`normal_map`, a null `geometry` and the RBF's `spatial`,
    `n_centers` by the schema)."""
    jio.write_image(tmp_path / "probe.exr", np.ones((8, 16, 3)))
    jio.write_image(tmp_path / "img.exr", np.ones((N, N, 3)))
    np.save(tmp_path / "n.npy", _sphere_normals())
    import trimesh

    trimesh.creation.icosphere(subdivisions=1).export(tmp_path / "ball.ply")
    model = jaxsh.RBFModel(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((4, 3)), np.ones(3))
    jio.write_rbf(tmp_path / "r.npz", model, spatial=False)
    env = {"envmap": "probe.exr", "directional": [{"direction": [0, 0, 1], "radiance": 1.0}]}
    ts = {"model": "torrance_sparrow", "kd": 0.5, "ks": 0.1, "mu": 1.5, "sigma": 0.2}
    pin = {"model": "pinhole", "fx": 20.0, "fy": 20.0, "cx": 8.0, "cy": 8.0, "width": N, "height": N,
           "cam_to_world": C2W}
    bases = {
        "sphere": {"geometry": SPHERE, "views": [{"camera": ORTHO, "image": "img.exr"}], "lighting": env,
                   "brdf": ts, "solve": {"lighting_lmax": 4}},
        "mesh": {"geometry": {"mesh": "ball.ply"}, "views": [{"camera": pin}], "lighting": UP, "brdf": ts},
        "views_nmap": {"views": [{"camera": ORTHO, "normal_map": "n.npy"}], "lighting": UP,
                       "brdf": {"model": "rbf", "file": "r.npz"}},
    }
    optional = {  # (base, path to the block, key)
        "sphere": [((), k) for k in ("lighting", "brdf", "solve", "encoding", "alpha")]
        + [(("views", 0), k) for k in ("image", "mask", "encoding", "exposure", "saturation", "lighting",
                                       "normal_map", "alpha")]
        + [(("views", 0, "camera"), k) for k in ("width", "height")]
        + [(("lighting",), k) for k in ("up", "layout", "encoding", "rotation", "directional")]
        + [(("geometry",), k) for k in ("mesh", "normal_map")]
        + [(("solve",), k) for k in ("lighting_lmax", "render_lmax", "fresnel", "saturation", "brdf_model",
                                     "textured", "n_centers", "m_w", "m_xy", "tol", "min_cos", "max_samples")],
        "mesh": [(("geometry",), k) for k in ("sphere", "normal_map", "normals")]
        + [(("views", 0, "camera"), "pixel_centers")],
        "views_nmap": [((), "geometry"), (("brdf",), "spatial"), (("brdf",), "n_centers")],
    }
    validator = _validator_or_none()
    checked = 0
    for name, base in bases.items():
        for path, key in optional[name]:
            absent = json.loads(json.dumps(base))
            block = absent
            for p in path:
                block = block[p]
            block.pop(key, None)
            null = json.loads(json.dumps(absent))
            block = null
            for p in path:
                block = block[p]
            block[key] = None
            where = ".".join(str(p) for p in path + (key,))
            a = jio.read_manifest(_write(tmp_path, absent, "a.json"))
            b = jio.read_manifest(_write(tmp_path, null, "a.json"))
            assert _same(a, b), where
            if validator is not None:
                assert not list(validator.iter_errors(absent)), where
                assert not list(validator.iter_errors(null)), where
            checked += 1
    assert checked == 41


def _validator_or_none():
    try:
        from tests.test_manifest import _validator

        return _validator()
    except pytest.skip.Exception:
        return None


# ----------------------------------------------------------------------------- the cut-off of a known environment map


def test_fit_projects_the_envmap_to_the_fitted_roughness(tmp_path, monkeypatch):
    """`jaxsh fit` with a known environment map cut it off at l = 40 (the cut-off of sigma = 0.1) whatever the
    surface: a smoother surface reflects finer detail of the map, and the fit of a sigma = 0.04 sphere under a small
    bright disk was off (sigma, mu) with status `converged`. Now the map is projected again at the fitted sigma's
    cut-off (ceil(4 / sigma), at most H/2 - 1) and fitted again; `result.json` reports the cut-off used.

    A plumbing test of that choice: the images are rendered by `jaxsh.render_practical`, the fitted model, with the
    map projected to l = ceil(4 / 0.04) = 100 -- what the fit must use to recover the truth."""
    h = 256  # lat-long texel centres (docs/conventions.md), by hand
    theta = (np.arange(h) + 0.5) * np.pi / h
    phi = (np.arange(2 * h) + 0.5) * 2 * np.pi / (2 * h)
    dirs = np.stack([np.sin(theta)[:, None] * np.cos(phi), np.sin(theta)[:, None] * np.sin(phi),
                     np.broadcast_to(np.cos(theta)[:, None], (h, 2 * h))], -1)
    d0 = np.array([0.3, 0.4, 0.87]) / np.linalg.norm([0.3, 0.4, 0.87])
    env = 0.2 + 40.0 * (dirs @ d0 > np.cos(0.08))[..., None] * np.ones(3)
    jio.write_image(tmp_path / "probe.exr", env.astype(np.float32))
    kd, ks, mu, sigma = np.array([0.5, 0.4, 0.3]), 0.3, 1.6, 0.04
    slow = jaxsh.project_latlong(jio.read_envmap(tmp_path / "probe.exr").astype(np.float64), 100)
    cams = [{"model": "orthographic", "scale": 2.4 / 48, "width": 48, "height": 48, "cam_to_world": C2W}]
    views = []
    for k, c in enumerate(cams):
        g = jaxsh.sphere_gbuffer(jaxsh.OrthographicCamera(c["scale"], 48, 48, np.asarray(C2W, float)), np.zeros(3), 1.0)
        img = np.asarray(jaxsh.render_practical(g.normal, g.view, kd, ks, mu, sigma, slow_sh=slow, mask=g.mask).total)
        jio.write_image(tmp_path / f"v{k}.exr", img.astype(np.float32))
        views.append({"camera": c, "image": f"v{k}.exr"})
    m = {"geometry": SPHERE, "views": views, "lighting": {"envmap": "probe.exr"}}
    fit_manifest(_write(tmp_path, m), tmp_path / "fit", progress=False)
    r = json.loads((tmp_path / "fit" / "result.json").read_text())
    assert r["status"] == "converged"
    assert r["lighting"]["envmap_lmax"] >= 95  # ceil(4 / sigma_fit), sigma_fit close to 0.04
    # measured: sigma to 1e-10, rel_rms 2.5e-8; with the map cut off at l = 40: sigma 0.04029, mu 1.6018, rel_rms 5.6e-3
    assert abs(r["brdf"]["sigma"] - sigma) < 1e-4 and abs(r["brdf"]["mu"] - mu) < 1e-3
    assert r["rel_rms"] < 1e-5
    # the automatic cut-off is capped by the size of the fit's per-sample terms (`_TERMS_BYTES`): with no room the
    # map stays at l = 40
    import solvers._fit_manifest as fm

    monkeypatch.setattr(fm, "_TERMS_BYTES", 0)
    fit_manifest(_write(tmp_path, m), tmp_path / "fit_capped", progress=False)
    assert json.loads((tmp_path / "fit_capped" / "result.json").read_text())["lighting"]["envmap_lmax"] == 40
