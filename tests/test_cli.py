"""The `jaxsh` command line."""

import json

import jax
import pytest

from solvers.cli import main


@pytest.mark.slow  # the largest test (~7 % of the suite's CPU); `make demo` runs the demo end to end (make test-all)
def test_demo_runs_small_and_writes_report(tmp_path):
    x64_before = jax.config.jax_enable_x64
    out = tmp_path / "out"
    report = tmp_path / "r.json"
    rc = main(["demo", "--size", "24", "--materials", "1", "--lmax", "6", "--out", str(out), "--json", str(report)])
    assert rc == 0
    data = json.loads(report.read_text())
    mat = data["materials"][0]
    assert mat["name"] == "teflon" and mat["truth"]["sigma"] == 0.12
    assert mat["known_lighting"]["status"] == "converged" and mat["unknown_lighting"]["status"] == "converged"
    assert abs(mat["known_lighting"]["brdf"]["sigma"] - 0.12) < 0.02
    assert len(mat["unknown_lighting"]["lighting"]["coeffs"]) == 49
    assert (out / "teflon_input_view0.exr").exists() and (out / "teflon_lighting_recovered.png").exists()
    assert jax.config.jax_enable_x64 == x64_before  # the demo's float64 is scoped


# ----------------------------------------------------------------------------- manifests and `jaxsh render`

import numpy as np  # noqa: E402

import jaxsh  # noqa: E402
import jaxsh.io as jio  # noqa: E402
import solvers  # noqa: E402


def _write_manifest(tmp_path, geometry=None, **over):
    env = np.asarray(jaxsh.synthesize_latlong(np.random.default_rng(0).normal(size=(9, 3)) * 0.2 + np.array([[1.0, 1, 1]] + [[0, 0, 0]] * 8), 16, 32))
    jio.write_image(tmp_path / "probe.exr", np.maximum(env, 0))
    cam = np.asarray(jaxsh.look_at(np.array([0, 0, 5.0]), np.zeros(3), np.array([0, 1.0, 0])))
    m = {
        "geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}} if geometry is None else geometry,
        "views": [{"camera": {"model": "orthographic", "scale": 0.05, "width": 48, "height": 40, "cam_to_world": cam.tolist()}}],
        "lighting": {"envmap": "probe.exr", "up": "+z", "layout": "latlong", "directional": [{"direction": [0.3, 0.4, 0.87], "radiance": [2, 2, 2]}]},
        "brdf": {"model": "torrance_sparrow", "kd": [0.3, 0.2, 0.1], "ks": 0.4, "mu": 1.5, "sigma": 0.2},
        "solve": {},
    }
    m.update(over)
    p = tmp_path / "capture.json"
    p.write_text(json.dumps(m))
    return p, m


def test_render_manifest_sphere(tmp_path):
    p, m = _write_manifest(tmp_path)
    out = tmp_path / "out"
    assert main(["render", str(p), "--out", str(out)]) == 0
    img = jio.read_image(out / "view_000.exr")
    assert img.shape == (40, 48, 3) and (out / "view_000.png").exists()
    # the same render done by hand with the library
    man = jio.read_manifest(p)
    cam = jaxsh.OrthographicCamera(0.05, 48, 40, np.asarray(m["views"][0]["camera"]["cam_to_world"]))
    g = jaxsh.sphere_gbuffer(cam, np.zeros(3), 1.0)
    slow = jaxsh.project_latlong(jio.read_envmap(tmp_path / "probe.exr").astype(np.float64), 7)
    d = np.array([0.3, 0.4, 0.87]) / np.linalg.norm([0.3, 0.4, 0.87])
    want = jaxsh.render_practical(g.normal, g.view, [0.3, 0.2, 0.1], 0.4, 1.5, 0.2, slow_sh=slow, fast_directions=d[None], fast_energy=np.full((1, 3), 2.0), mask=g.mask).total
    np.testing.assert_allclose(img, np.asarray(want, np.float32), rtol=1e-6, atol=1e-6)
    assert man["brdf"]["ks"].shape == (3,)


def test_render_manifest_mesh_has_shadows(tmp_path):
    import trimesh

    box = trimesh.creation.box(extents=[2.0, 2.0, 0.2])
    wall = trimesh.creation.box(extents=[0.2, 2.0, 1.0])
    wall.apply_translation([0.0, 0.0, 0.6])
    trimesh.util.concatenate([box, wall]).export(tmp_path / "scene.ply")
    p, _ = _write_manifest(
        tmp_path, geometry={"mesh": "scene.ply"},
        lighting={"envmap": None, "directional": [{"direction": [1.0, 0.0, 0.6], "radiance": [3, 3, 3]}]},
    )
    out = tmp_path / "out"
    assert main(["render", str(p), "--out", str(out)]) == 0
    img = jio.read_image(out / "view_000.exr")[..., 0]
    # Camera +x is world +x. The sun (the only light) is at +x, 31 deg up; the 1.0-high wall at x = 0
    # shadows the whole floor at x < -0.1 (shadow length 1.67): black there, lit on the right.
    cols = img.shape[1]
    left, right = img[6:-6, 6 : cols // 2 - 4], img[6:-6, cols // 2 + 4 : -6]  # inside the 2x2 floor
    assert left.max() == 0.0
    assert right.min() > 0.0


@pytest.mark.parametrize(
    "change, message",
    [
        ({"geometry": {}}, "exactly one"),
        ({"views": []}, "views"),
        ({"brdf": {"model": "phong", "kd": 1, "ks": 1, "mu": 1.5, "sigma": 0.1}}, "brdf.model"),
        ({"brdf": {"model": "torrance_sparrow", "kd": 1, "ks": 1, "mu": 1.5}}, "brdf.sigma"),
        ({"lighting": {"envmap": "missing.exr"}}, "missing.exr"),
        ({"lighting": {"envmap": "probe.exr", "up": "y"}}, "lighting.up"),
    ],
)
def test_manifest_errors_name_file_and_field(tmp_path, change, message):
    p, _ = _write_manifest(tmp_path, **change)
    with pytest.raises(jio.ManifestError, match=message) as e:
        jio.read_manifest(p)
    assert "capture.json" in str(e.value)


def test_manifest_camera_errors(tmp_path):
    p, m = _write_manifest(tmp_path)
    m["views"][0]["camera"]["cam_to_world"] = np.diag([1.0, 1.0, 2.0, 1.0]).tolist()
    p.write_text(json.dumps(m))
    with pytest.raises(jio.ManifestError, match=r"views\[0\]\.camera\.cam_to_world"):
        jio.read_manifest(p)
    m["views"][0]["camera"] = {"model": "pinhole", "fx": 100, "fy": 100, "cx": 20, "cy": 20, "cam_to_world": np.eye(4).tolist()}
    p.write_text(json.dumps(m))
    with pytest.raises(jio.ManifestError, match="width"):
        jio.read_manifest(p)
    p.write_text("{not json")
    with pytest.raises(jio.ManifestError, match="capture.json.*JSON"):
        jio.read_manifest(p)
    with pytest.raises(FileNotFoundError, match="nope.json"):
        jio.read_manifest(tmp_path / "nope.json")


def test_render_cli_reports_errors(tmp_path, capsys):
    p, _ = _write_manifest(tmp_path, brdf=None)
    assert main(["render", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "needs both" in capsys.readouterr().err


# ----------------------------------------------------------------------------- `jaxsh fit`


def _fit_capture(tmp_path, n_views=2, size=40, sigma=0.2, radius=1.0):
    """Render views of a manifest with `jaxsh render` (practical model), then blank lighting/BRDF for fitting."""
    p, m = _write_manifest(tmp_path, geometry={"sphere": {"center": [0, 0, 0], "radius": radius}})
    m["brdf"]["sigma"] = sigma
    # a structured probe: the demo's area source and ground bounce (R&H's projection screen)
    disks, _ = solvers.default_sources()
    sh = sum(jaxsh.disk_light_sh(disks[0][k], disks[1][k], disks[2][k], 15) for k in range(2))
    jio.write_image(tmp_path / "probe.exr", np.maximum(np.asarray(jaxsh.synthesize_latlong(sh, 32, 64)), 0))
    eyes = [np.array([0.5, -4.0, 3.0]), np.array([3.0, 1.0, 4.0]), np.array([-2.0, 3.0, 3.5])][:n_views]
    views = []
    for k, eye in enumerate(eyes):
        cam = np.asarray(jaxsh.look_at(eye, np.zeros(3), np.array([0, 0, 1.0])))
        views.append({"camera": {"model": "orthographic", "scale": 2.4 / size, "width": size, "height": size,
                                 "cam_to_world": cam.tolist()}})
    m["views"] = views
    p.write_text(json.dumps(m))
    assert main(["render", str(p), "--out", str(tmp_path / "renders")]) == 0
    for k, v in enumerate(views):
        v["image"] = f"renders/view_{k:03d}.exr"
    p.write_text(json.dumps(m))
    return p, m


def test_fit_recovers_brdf_with_known_lighting(tmp_path):
    p, m = _fit_capture(tmp_path)
    m["brdf"] = None
    p.write_text(json.dumps(m))
    out = tmp_path / "fit"
    assert main(["fit", str(p), "--out", str(out)]) == 0
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "converged"
    # the images come from the same (practical) model: exact recovery up to float32 EXR rounding
    np.testing.assert_allclose(r["brdf"]["kd"], [0.3, 0.2, 0.1], rtol=1e-3)
    np.testing.assert_allclose(r["brdf"]["ks"], [0.4, 0.4, 0.4], rtol=1e-3)
    assert abs(r["brdf"]["mu"] - 1.5) < 1e-2 and abs(r["brdf"]["sigma"] - 0.2) < 1e-3
    assert set(r["std_errors"]) == {"kd", "ks", "mu", "sigma"}
    assert r["lighting"]["frame"] == "world, +z up" and len(r["lighting"]["coeffs"]) == 169
    for name in ("lighting.exr", "lighting.png", "view_000.exr", "view_001.png"):
        assert (out / name).exists()
    re = jio.read_image(out / "view_001.exr")
    src = jio.read_image(tmp_path / "renders" / "view_001.exr")
    assert np.abs(re - src).max() < 1e-3 * np.abs(src).max()


def test_fits_of_captures_in_one_size_bucket_compile_nothing_new(tmp_path):
    """`jaxsh fit` pads the samples to a size bucket: a second object whose pixel count falls in the same bucket
    reuses every compiled program of the first fit (in one process here; across runs, the compilation cache)."""
    from solvers._scale import _size_bucket

    from .helpers import Compiles

    counts, results = [], []
    # 48 x 48 views: a bucket (2,560 samples) that no other fit of this file uses, so the first fit compiles
    for k, radius in enumerate((1.0, 0.98)):
        d = tmp_path / f"c{k}"
        d.mkdir()
        p, m = _fit_capture(d, size=48, radius=radius)
        m["brdf"] = None
        p.write_text(json.dumps(m))
        with Compiles() as c:
            assert main(["fit", str(p), "--out", str(d / "fit")]) == 0
        counts.append(c.names)
        results.append(json.loads((d / "fit" / "result.json").read_text()))
    n = [int(r["samples"]["total"]) for r in results]
    assert n[0] != n[1] and _size_bucket(n[0]) == _size_bucket(n[1]) == 2560, n
    assert any("_fit_brdf" in name for name in counts[0]) and counts[1] == [], counts[1]
    for r in results:  # both fits recover the rendered material
        assert r["status"] == "converged"
        np.testing.assert_allclose(r["brdf"]["kd"], [0.3, 0.2, 0.1], rtol=1e-3)
        assert abs(r["brdf"]["sigma"] - 0.2) < 1e-3


def test_fit_factorizes_unknown_lighting_and_brdf(tmp_path):
    # a glossy object (sigma 0.1): the directional source's highlight separates K_s from K_d (R&H sec. 6.3)
    p, m = _fit_capture(tmp_path, n_views=3, sigma=0.1)
    m["brdf"] = None
    m["lighting"] = None
    m["solve"] = {"lighting_lmax": 15}  # the band limit of the rendered probe (a 32x64 map)
    p.write_text(json.dumps(m))
    out = tmp_path / "fit"
    assert main(["fit", str(p), "--out", str(out)]) == 0
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "converged"
    kd, ks = np.array([0.3, 0.2, 0.1]), np.array([0.4, 0.4, 0.4])
    np.testing.assert_allclose(r["brdf"]["ks"], ks / (kd + ks), atol=0.03)
    np.testing.assert_allclose(np.add(r["brdf"]["kd"], r["brdf"]["ks"]), 1.0, atol=1e-9)
    assert len(r["lighting"]["coeffs"]) == 256 and len(r["lighting"]["directional"]) == 1
    assert r["at_bound"] == {"mu": False, "sigma": False}  # results.md: written for a factorization too


def test_fit_inverse_lighting_with_known_brdf(tmp_path):
    p, m = _fit_capture(tmp_path)
    m["lighting"] = None
    m["solve"] = {"lighting_lmax": 6}
    p.write_text(json.dumps(m))
    out = tmp_path / "fit"
    assert main(["fit", str(p), "--out", str(out)]) == 0
    r = json.loads((out / "result.json").read_text())
    rec = np.array(r["lighting"]["coeffs"])
    env = jio.read_envmap(tmp_path / "probe.exr").astype(np.float64)
    d = np.array([[0.3, 0.4, 0.87]]) / np.linalg.norm([0.3, 0.4, 0.87])
    truth = np.asarray(jaxsh.project_latlong(env, 6)) + np.asarray(jaxsh.directional_light_sh(d, np.full((1, 3), 2.0), 6))
    for c in range(3):
        assert np.corrcoef(rec[:9, c], truth[:9, c])[0, 1] > 0.99
    assert r["brdf"]["sigma"] == 0.2
    sup = r["lighting"]["supported_lmax"]  # results.md: [int, int, int] (they were written as 12.0)
    assert len(sup) == 3 and all(type(x) is int and 0 <= x <= 6 for x in sup)


def test_fit_errors(tmp_path, capsys):
    p, m = _fit_capture(tmp_path, n_views=1, size=24)
    assert main(["fit", str(p), "--out", str(tmp_path / "f")]) == 2  # both given
    assert "nothing to recover" in capsys.readouterr().err
    m["brdf"] = None
    m["views"][0]["image"] = "missing.exr"
    p.write_text(json.dumps(m))
    assert main(["fit", str(p), "--out", str(tmp_path / "f")]) == 2
    assert "missing.exr" in capsys.readouterr().err


def _write_codes16(path, codes):
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(codes.shape[1], codes.shape[0], codes.shape[2], "uint16"))
    assert out.write_image(np.ascontiguousarray(codes.astype(np.uint16)))
    out.close()


def test_fit_from_16_bit_pngs_with_encoding_exposure_and_saturation(tmp_path):
    """View 0: 16-bit linear PNG; view 1: 16-bit sRGB PNG. Clipped pixels carry wrong values and must be dropped."""
    p, m = _fit_capture(tmp_path)
    m["brdf"] = None
    rng = np.random.default_rng(7)
    for k, v in enumerate(m["views"]):
        img = jio.read_image(tmp_path / v["image"]).astype(np.float64)
        exposure = 1.25 * img.max()
        x = img / exposure
        if k == 1:  # sRGB encoding, IEC 61966-2-1
            x = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
        codes = np.round(x * 65535)
        lit = np.argwhere(img[..., 0] > 0.05 * img.max())
        hit = lit[rng.choice(len(lit), 60, replace=False)]
        # view 0: clipped at the format's maximum (the default threshold); view 1: above a declared 60000
        codes[hit[:, 0], hit[:, 1], 1] = 65535 if k == 0 else 60001
        _write_codes16(tmp_path / f"v{k}.png", codes)
        v.update(image=f"v{k}.png", encoding="linear" if k == 0 else "srgb", exposure=exposure)
        if k == 1:
            v["saturation"] = 60000
        assert codes.max() <= 65535 and (k == 1 or np.sum(codes == 65535) == 60)
    p.write_text(json.dumps(m))
    out = tmp_path / "fit"
    assert main(["fit", str(p), "--out", str(out)]) == 0
    r = json.loads((out / "result.json").read_text())
    assert r["status"] == "converged"
    # 16-bit quantization of images from the same (practical) model: recovery to a few 1e-4
    np.testing.assert_allclose(r["brdf"]["kd"], [0.3, 0.2, 0.1], rtol=2e-3)
    np.testing.assert_allclose(r["brdf"]["ks"], [0.4, 0.4, 0.4], rtol=2e-3)
    assert abs(r["brdf"]["sigma"] - 0.2) < 2e-3
