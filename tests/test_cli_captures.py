"""Real captures through the command line (issue 11): `jaxsh fit` -> `result.json` -> `jaxsh render` of held-out lights.

Photometric-stereo captures are written to disk in the formats users have (16-bit linear PNG, 8-bit sRGB PNG,
EXR normal maps from the analytic sphere and from a mesh), one directional light per image, by the reference
renderer (`jaxsh.render_reference`). Each model the manifest offers (`torrance_sparrow`, textured Kd,
`sharing`, `sharing_spatial`) predicts images under lights it never saw, compared with the reference renderer.
"""

import json

import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import jaxsh.io
import solvers
from solvers.cli import main

from .helpers import write_png16

N = 32  # image size: the sphere covers ~650 pixels
C2W = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10], [0, 0, 0, 1]], float)  # looks down -z
CAM = {"model": "orthographic", "scale": 2.2 / N, "width": N, "height": N, "cam_to_world": C2W.tolist()}
TRUE = jaxsh.TorranceSparrow(jnp.asarray([0.5, 0.4, 0.3]), jnp.asarray([0.3, 0.35, 0.4]), 1.5, 0.2)
E = 0.5  # irradiance of every light


def _lights(k=12):
    az = np.arange(k) * 2 * np.pi / k
    el = np.deg2rad(np.linspace(15, 60, k))
    return np.stack([np.sin(el) * np.cos(az), np.sin(el) * np.sin(az), np.cos(el)], 1)


DIRS = _lights()
HELD = DIRS[[3, 8]]  # never seen by the fits
FIT = np.delete(DIRS, [3, 8], axis=0)


def _gbuffer():
    cam = jaxsh.OrthographicCamera(2.2 / N, N, N, C2W)
    return jaxsh.sphere_gbuffer(cam, np.zeros(3), 1.0)


def _texture():
    """A Kd texture over the pixel grid (x = column, y = row, in [0, 1]): smooth, different per channel."""
    j, i = np.meshgrid((np.arange(N) + 0.5) / N, (np.arange(N) + 0.5) / N)
    return np.stack([0.2 + 0.5 * j, 0.55 - 0.3 * i, 0.25 + 0.3 * j * i], -1)


def _reference(g, d, kd=None):
    """The reference renderer's image under one directional light of irradiance E, 0 off the object."""
    brdf = TRUE if kd is None else jaxsh.TorranceSparrow(jnp.asarray(kd), TRUE.ks, TRUE.mu, TRUE.sigma)
    lit = solvers.Lighting(None, jnp.asarray(d[None]), jnp.full((1, 3), E))
    return np.asarray(jaxsh.render_reference(g.normal, g.view, brdf, lit)) * np.asarray(g.mask)[..., None]


def _rel(got, want, mask):
    return float(np.sqrt(np.mean((got[mask] - want[mask]) ** 2) / np.mean(want[mask] ** 2)))


def _view(name, d, **extra):
    return {"image": name, "camera": CAM, "lighting": {"directional": [{"direction": list(map(float, d)), "radiance": E}]},
            **extra}


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Two captures on disk: homogeneous (16-bit linear PNG) and textured Kd (EXR); normal map from the analytic sphere."""
    root = tmp_path_factory.mktemp("capture")
    g = _gbuffer()
    jaxsh.io.write_image(root / "normals.exr", np.asarray(g.normal))
    tex = _texture()
    for k, d in enumerate(FIT):
        img = _reference(g, d)
        assert img.max() < 0.95  # nothing clips in the 16-bit file
        write_png16(root / f"img_{k:03d}.png", img)
        jaxsh.io.write_image(root / f"tex_{k:03d}.exr", _reference(g, d, tex))
    return root, g, tex


def _fit(root, name, views, solve=None, geometry=None, encoding="linear"):
    m = {"geometry": geometry or {"normal_map": "normals.exr"}, "encoding": encoding, "views": views,
         "lighting": None, "brdf": None, "solve": solve or {}}
    (root / f"{name}.json").write_text(json.dumps(m))
    assert main(["fit", str(root / f"{name}.json"), "--out", str(root / name)]) == 0
    return json.loads((root / name / "result.json").read_text())


def _render_held(root, name, brdf):
    """`jaxsh render` of the held-out lights with `brdf` (paths relative to the fit's output folder)."""
    m = {"geometry": {"normal_map": str(root / "normals.exr")}, "views": [_view(None, d) for d in HELD],
         "lighting": None, "brdf": brdf}
    for v in m["views"]:
        del v["image"]
    (root / name / "held.json").write_text(json.dumps(m))
    assert main(["render", str(root / name / "held.json"), "--out", str(root / name / "held")]) == 0
    return [np.asarray(jaxsh.io.read_image(root / name / "held" / f"view_{j:03d}.exr"))[..., :3] for j in range(len(HELD))]


def test_torrance_sparrow_from_a_mesh_normal_map(tmp_path):
    """Geometry from a normal map rendered from a mesh (an icosphere's G-buffer): the fit recovers the BRDF and
    predicts the held-out lights as the reference renderer draws them (directional light: no model error)."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3)
    cam = jaxsh.OrthographicCamera(2.2 / N, N, N, C2W)
    g = jaxsh.mesh_gbuffer(cam, mesh)
    mask = np.asarray(g.mask)
    jaxsh.io.write_image(tmp_path / "normals.exr", np.asarray(g.normal))
    views = []
    for k, d in enumerate(FIT):
        write_png16(tmp_path / f"img_{k:03d}.png", _reference(g, d))
        views.append(_view(f"img_{k:03d}.png", d))
    result = _fit(tmp_path, "fit", views)
    assert result["status"] == "converged"
    np.testing.assert_allclose(result["brdf"]["kd"], np.asarray(TRUE.kd), rtol=2e-3)
    np.testing.assert_allclose(result["brdf"]["ks"], np.asarray(TRUE.ks), rtol=2e-3)
    assert result["brdf"]["sigma"] == pytest.approx(0.2, rel=2e-3)
    m = {"geometry": {"normal_map": "../normals.exr"}, "views": [{"camera": CAM, "lighting": {"directional": [
        {"direction": list(map(float, d)), "radiance": E}]}} for d in HELD], "lighting": None, "brdf": result["brdf"]}
    (tmp_path / "fit" / "held.json").write_text(json.dumps(m))
    assert main(["render", str(tmp_path / "fit" / "held.json"), "--out", str(tmp_path / "held")]) == 0
    for j, d in enumerate(HELD):
        got = np.asarray(jaxsh.io.read_image(tmp_path / "held" / f"view_{j:03d}.exr"))[..., :3]
        assert _rel(got, _reference(g, d), mask) < 1e-3  # 16-bit quantization of the inputs only


def test_textured_kd_writes_maps_that_render(capture):
    """`solve.textured = "kd"`: Kd per pixel of the camera, written as `kd.exr`, referenced from result.json, renders."""
    root, g, tex = capture
    mask = np.asarray(g.mask)
    result = _fit(root, "textured", [_view(f"tex_{k:03d}.exr", d) for k, d in enumerate(FIT)], {"textured": "kd"})
    assert result["status"] == "converged"
    assert result["brdf"]["kd"] == "kd.exr" and result["texels"]["observed"] == int(mask.sum())
    kd = np.asarray(jaxsh.io.read_texture(root / "textured" / "kd.exr"))
    np.testing.assert_allclose(kd[mask], tex[mask], rtol=2e-3, atol=1e-4)
    assert np.all(kd[~mask] == 0)
    np.testing.assert_allclose(result["brdf"]["ks"], np.asarray(TRUE.ks), rtol=2e-3)
    brdf = {**result["brdf"], "kd": str(root / "textured" / "kd.exr")}
    for got, d in zip(_render_held(root, "textured", brdf), HELD):
        assert _rel(got, _reference(g, d, tex), mask) < 1e-3
    # the map records the camera it was fitted in: a single view on another pose is refused by `jaxsh render`
    rec = jaxsh.io.recorded_camera(root / "textured" / "kd.exr")
    np.testing.assert_array_equal(rec["cam_to_world"], np.asarray(CAM["cam_to_world"], float))
    assert (rec["model"], rec["width"], rec["height"]) == (CAM["model"], CAM["width"], CAM["height"])
    moved = {**CAM, "cam_to_world": np.asarray(jaxsh.look_at([5, 0, 0], [0, 0, 0])).tolist()}
    bad = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "views": [{"camera": moved}],
           "lighting": {"directional": [{"direction": [0, 0, 1], "radiance": 1}]}, "brdf": brdf}
    (root / "moved.json").write_text(json.dumps(bad))
    with pytest.raises(jaxsh.io.ManifestError, match=r"moved\.json: `views\[0\]\.camera` is not the camera the "
                                                     r"texture map `brdf\.kd` .*kd\.exr is in"):
        jaxsh.io.read_manifest(root / "moved.json")


def test_textured_kd_ks_writes_undetermined_ks_as_zero(tmp_path):
    """`solve.textured = "kd_ks"` on noisy images (0.5 % of the brightest pixel, sigma 0.2): far from every highlight
    the least-squares Ks is noise over a vanishing specular term, and ks.exr used to hold it (values beyond 1e6).
    Those texels are now 0 in ks.exr and counted in result.json's `undetermined.ks_values`. Where a view sees a
    highlight (specular lobe at least 10 % of its peak, computed here in NumPy), Ks keeps its value,
    K_s F(mu, theta_o)/F(mu, 0) with F = 1 in the fit, and Kd is recovered everywhere."""
    g = _gbuffer()
    mask = np.asarray(g.mask)
    jaxsh.io.write_image(tmp_path / "normals.exr", np.asarray(g.normal))
    tex = _texture()
    rng = np.random.default_rng(5)
    views = []
    for k, d in enumerate(FIT):
        img = _reference(g, d, tex)
        img = (img + 0.005 * img.max() * rng.standard_normal(img.shape)) * mask[..., None]
        jaxsh.io.write_image(tmp_path / f"n_{k:03d}.exr", img)
        views.append(_view(f"n_{k:03d}.exr", d))
    result = _fit(tmp_path, "kdks", views, {"textured": "kd_ks", "fresnel": False})
    ks = np.asarray(jaxsh.io.read_texture(tmp_path / "kdks" / "ks.exr"))
    kd = np.asarray(jaxsh.io.read_texture(tmp_path / "kdks" / "kd.exr"))
    zeros = int(np.count_nonzero(ks[mask] == 0))
    assert 0 < result["undetermined"]["ks_values"] <= zeros
    assert np.all(np.isfinite(ks)) and ks.max() < 50
    n = np.asarray(g.normal)[mask]
    h = (FIT + np.array([0.0, 0.0, 1.0])) / np.linalg.norm(FIT + np.array([0.0, 0.0, 1.0]), axis=1, keepdims=True)
    lobe = np.exp(-((np.arccos(np.clip(n @ h.T, -1, 1)) / 0.2) ** 2)).max(1)  # the view looks down -z
    strong = lobe > 0.1
    assert strong.sum() > 100
    co = n[:, 2]
    mu = 1.5
    gg = np.sqrt(mu * mu - 1 + co * co)  # exact unpolarized dielectric Fresnel, over its value at normal incidence
    f = 0.5 * ((gg - co) / (gg + co)) ** 2 * (1 + ((co * (gg + co) - 1) / (co * (gg - co) + 1)) ** 2)
    want = np.asarray(TRUE.ks)[None, :] * (f / ((mu - 1) / (mu + 1)) ** 2)[:, None]
    assert np.median(np.abs(ks[mask][strong] - want[strong])) < 0.01
    assert np.all(ks[mask][strong] > 0)
    assert np.sqrt(np.mean((kd[mask] - tex[mask]) ** 2)) < 0.01


def _lambertian_error(root, g, kd_fit_images, held_images):
    """Baseline: the best Lambertian BRDF (Kd per channel, least squares over every fit pixel), held-out error."""
    mask = np.asarray(g.mask)
    n = np.asarray(g.normal)[mask]
    shade = [E * np.maximum(n @ d, 0) / np.pi for d in FIT]
    a = np.concatenate(shade)
    b = np.concatenate([im[mask] for im in kd_fit_images])
    kd = (a @ b) / (a @ a)
    errs = [_rel((E * np.maximum(np.asarray(g.normal) @ d, 0) / np.pi)[..., None] * kd * mask[..., None], want, mask)
            for d, want in zip(HELD, held_images)]
    return max(errs)


def test_sharing_predicts_held_out_lights(capture):
    """`solve.brdf_model = "sharing"` (Zickler eq. 12): an RBF file next to result.json; `jaxsh render` of it predicts
    lights it never saw; the same model through the Python API gives the same images."""
    root, g, _ = capture
    mask = np.asarray(g.mask)
    result = _fit(root, "sharing", [_view(f"img_{k:03d}.png", d) for k, d in enumerate(FIT)],
                  {"brdf_model": "sharing", "n_centers": 300})
    assert result["status"] == "converged"
    assert result["brdf"] == {"model": "rbf", "file": "brdf_rbf.npz", "spatial": False, "n_centers": 300}
    assert result["sharing"]["samples"] == sum(result["sharing"]["samples_per_view"]) > 0
    got = _render_held(root, "sharing", {"model": "rbf", "file": "brdf_rbf.npz"})
    want = [_reference(g, d) for d in HELD]
    errs = [_rel(a, b, mask) for a, b in zip(got, want)]
    fit_images = [np.asarray(jaxsh.io.read_image(root / f"img_{k:03d}.png", "linear")) for k in range(len(FIT))]
    lam = _lambertian_error(root, g, fit_images, want)
    # measured 1.0 % / 1.4 %; the best Lambertian BRDF misses the highlights (~25 %)
    assert max(errs) < 0.03 and max(errs) < 0.2 * lam, (errs, lam)
    rbf = jaxsh.io.read_rbf(root / "sharing" / "brdf_rbf.npz")
    api = np.asarray(solvers.render_rbf(rbf["model"], g.normal, g.view, HELD[0], E, mask=g.mask))
    np.testing.assert_allclose(got[0], api, rtol=1e-5, atol=1e-6)


def test_sharing_spatial_predicts_a_textured_object(capture):
    """`solve.brdf_model = "sharing_spatial"` (eq. 13, x, y = the pixel grid): a textured Kd is shared across the
    surface and predicted under held-out lights; the homogeneous eq. 12 cannot represent the texture."""
    root, g, tex = capture
    mask = np.asarray(g.mask)
    views = [_view(f"tex_{k:03d}.exr", d) for k, d in enumerate(FIT)]
    result = _fit(root, "spatial", views, {"brdf_model": "sharing_spatial", "n_centers": 300})
    assert result["status"] == "converged" and result["brdf"]["spatial"] is True
    got = _render_held(root, "spatial", {"model": "rbf", "file": "brdf_rbf.npz", "spatial": True})
    errs = [_rel(a, _reference(g, d, tex), mask) for a, d in zip(got, HELD)]
    assert max(errs) < 0.03, errs
    # a spatial RBF belongs to its pixel grid: another camera size is refused before any work
    bad = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "views": [{"camera": {**CAM, "width": N + 1}}],
           "lighting": {"directional": [{"direction": [0, 0, 1], "radiance": 1}]},
           "brdf": {"model": "rbf", "file": str(root / "spatial" / "brdf_rbf.npz")}}
    (root / "bad_grid.json").write_text(json.dumps(bad))
    with pytest.raises(jaxsh.io.ManifestError, match=r"views\[0\]\.camera.*pixel grid"):
        jaxsh.io.read_manifest(root / "bad_grid.json")
    # and to its camera, which the file records: the same size on another pose is refused too
    bad["views"] = [{"camera": {**CAM, "cam_to_world": np.asarray(jaxsh.look_at([0, 5, 0], [0, 0, 0])).tolist()}}]
    (root / "moved.json").write_text(json.dumps(bad))
    with pytest.raises(jaxsh.io.ManifestError, match=r"`views\[0\]\.camera` is not the camera the spatial RBF"):
        jaxsh.io.read_manifest(root / "moved.json")


def test_8bit_srgb_capture(tmp_path):
    """8-bit sRGB PNGs (as cameras write them) declared `"encoding": "srgb"`: the fit recovers Kd to the 8-bit
    quantization; the same files read as linear would be the issue's silent misread."""
    g = _gbuffer()
    mask = np.asarray(g.mask)
    views = []
    for k, d in enumerate(FIT):
        img = _reference(g, d)
        jaxsh.io.write_image(tmp_path / f"img_{k:03d}.png", img)  # 8-bit, sRGB-encoded
        views.append(_view(f"img_{k:03d}.png", d))
    # the file decodes to the radiance within 8-bit sRGB quantization (half a code step of the curve)
    back = np.asarray(jaxsh.io.read_image(tmp_path / "img_000.png", "srgb"))
    want = _reference(g, FIT[0])
    assert _rel(back[..., :3], want, mask) < 0.01
    assert _rel(np.asarray(jaxsh.io.read_image(tmp_path / "img_000.png", "linear"))[..., :3], want, mask) > 0.5
    result = _fit(tmp_path, "fit", views, geometry={"sphere": {"center": [0, 0, 0], "radius": 1}}, encoding="srgb")
    assert result["status"] == "converged"
    np.testing.assert_allclose(result["brdf"]["kd"], np.asarray(TRUE.kd), rtol=0.03)
    assert result["brdf"]["sigma"] == pytest.approx(0.2, rel=0.03)


def test_jpeg_is_read_with_its_declared_encoding(tmp_path):
    """A JPEG (8-bit, lossy) declared sRGB decodes to the radiance within JPEG error; an undeclared one is refused."""
    g = _gbuffer()
    mask = np.asarray(g.mask)
    img = _reference(g, FIT[0])
    jaxsh.io.write_image(tmp_path / "img.jpg", img)
    back = np.asarray(jaxsh.io.read_image(tmp_path / "img.jpg", "srgb"))[..., :3]
    assert _rel(back, img, mask) < 0.05
    with pytest.raises(ValueError, match="encoding"):
        jaxsh.io.read_image(tmp_path / "img.jpg")


@pytest.mark.parametrize(
    "change, field",
    [
        (lambda m: m["views"][0]["lighting"]["directional"].append({"direction": [0, 1, 1], "radiance": 1}),
         "views[0].lighting"),
        (lambda m: m["views"][1].update(camera={**CAM, "scale": 0.05}), "views[k].camera"),
        (lambda m: m["solve"].update(brdf_model="torrance_sparrow", textured="kd") or
         m["views"][1].update(camera={**CAM, "scale": 0.05}), "solve.textured"),
    ],
)
def test_model_requirements_are_checked_before_any_work(capture, capsys, change, field):
    root, _, _ = capture
    m = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "encoding": "linear",
         "views": [_view(str(root / f"img_{k:03d}.png"), d) for k, d in enumerate(FIT[:2])],
         "lighting": None, "brdf": None, "solve": {"brdf_model": "sharing_spatial"}}
    change(m)
    (root / "bad.json").write_text(json.dumps(m))
    assert main(["fit", str(root / "bad.json"), "--out", str(root / "bad_out")]) == 2
    err = capsys.readouterr().err
    assert field in err and len(err.strip().splitlines()) == 1
    assert not (root / "bad_out").exists()  # nothing was written


def test_rbf_brdf_renders_under_directional_sources_only(capture, capsys):
    root, _, _ = capture
    jaxsh.io.write_image(root / "env.exr", np.ones((8, 16, 3), np.float32))
    poly = np.zeros((4, 3))
    poly[0] = 0.1  # f = c0 = 0.1: a constant (Lambertian) reflectance
    rbf = jaxsh.RBFModel(np.random.default_rng(0).normal(size=(8, 3)), np.zeros((8, 3)), poly)
    jaxsh.io.write_rbf(root / "model.npz", rbf, spatial=False)
    m = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "views": [{"camera": CAM}],
         "lighting": {"envmap": "env.exr"}, "brdf": {"model": "rbf", "file": "model.npz"}}
    (root / "env_rbf.json").write_text(json.dumps(m))
    assert main(["render", str(root / "env_rbf.json"), "--out", str(root / "env_out")]) == 2
    assert "lighting.envmap" in capsys.readouterr().err
    # a constant RBF (weights 0, c0 = 0.1) under one light renders 0.1 * E cos(theta_i): the rendering equation
    m["lighting"] = {"directional": [{"direction": [0, 0, 1], "radiance": 2.0}]}
    (root / "dir_rbf.json").write_text(json.dumps(m))
    assert main(["render", str(root / "dir_rbf.json"), "--out", str(root / "dir_out")]) == 0
    g = _gbuffer()
    got = np.asarray(jaxsh.io.read_image(root / "dir_out" / "view_000.exr"))[..., :3]
    want = 0.1 * 2.0 * np.maximum(np.asarray(g.normal)[..., 2], 0)[..., None] * np.asarray(g.mask)[..., None]
    np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=1e-6)
    # a grey (one-channel) model, as a fit of grey images writes it, under an RGB source renders RGB: f L cos(theta_i)
    # (it stopped with "Incompatible types for broadcasting", naming no field)
    grey = jaxsh.RBFModel(np.random.default_rng(0).normal(size=(8, 3)), np.zeros((8, 1)), poly[:, :1])
    jaxsh.io.write_rbf(root / "grey.npz", grey, spatial=False)
    m["brdf"] = {"model": "rbf", "file": "grey.npz"}
    m["lighting"] = {"directional": [{"direction": [0, 0, 1], "radiance": [1.0, 2.0, 0.5]}]}
    (root / "grey_rbf.json").write_text(json.dumps(m))
    assert main(["render", str(root / "grey_rbf.json"), "--out", str(root / "grey_out")]) == 0
    got = np.asarray(jaxsh.io.read_image(root / "grey_out" / "view_000.exr"))[..., :3]
    want = 0.1 * np.array([1.0, 2.0, 0.5]) * (np.maximum(np.asarray(g.normal)[..., 2], 0) * np.asarray(g.mask))[..., None]
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_rbf_file_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(1)
    model = jaxsh.RBFModel(rng.normal(size=(6, 5)), rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), [0.3, 0.3, 1, 1, 0.5])
    jaxsh.io.write_rbf(tmp_path / "m.npz", model, spatial=True, width=7, height=5)
    back = jaxsh.io.read_rbf(tmp_path / "m.npz")
    assert back["spatial"] and (back["width"], back["height"]) == (7, 5)
    q = rng.normal(size=(4, 5))
    np.testing.assert_allclose(np.asarray(back["model"](q)), np.asarray(model(q)), rtol=1e-12)
    with pytest.raises(ValueError, match="width"):
        jaxsh.io.write_rbf(tmp_path / "n.npz", model, spatial=True)
    with pytest.raises(ValueError, match="3-D points for spatial=False"):
        jaxsh.io.write_rbf(tmp_path / "n.npz", model, spatial=False)
    np.savez(tmp_path / "bad.npz", format="jaxsh-rbf-1", centers=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="bad.npz.*missing array `weights`"):
        jaxsh.io.read_rbf(tmp_path / "bad.npz")
    (tmp_path / "text.npz").write_text("not an npz")
    with pytest.raises(ValueError, match="text.npz"):
        jaxsh.io.read_rbf(tmp_path / "text.npz")
