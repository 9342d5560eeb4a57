"""Capture manifests: complete validation, named errors, the JSON Schema (issues 11 and 12)."""

import copy
import glob
import json
import os
import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jaxsh.io as jio

ROOT = os.path.join(os.path.dirname(__file__), "..")
SCHEMA = os.path.join(ROOT, "docs", "manifest.schema.json")
CAM = [[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 5.0], [0, 0, 0, 1.0]]


def base_manifest():
    return {
        "geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}},
        "views": [{"camera": {"model": "orthographic", "scale": 0.15, "width": 16, "height": 16, "cam_to_world": CAM}},
                  {"camera": {"model": "pinhole", "fx": 20, "fy": 20, "cx": 8, "cy": 8, "width": 16, "height": 16,
                              "cam_to_world": CAM}}],
        "lighting": {"directional": [{"direction": [0, 0, 2.0], "radiance": [1, 1, 1]}]},
        "brdf": {"model": "torrance_sparrow", "kd": [0.3, 0.2, 0.1], "ks": 0.4, "mu": 1.5, "sigma": 0.2},
        "solve": {"lighting_lmax": 4},
    }


def write(tmp_path, m, name="capture.json"):
    p = tmp_path / name
    p.write_text(json.dumps(m))
    return p


def set_path(m, path, value):
    """Set `m` at a field path like `views[1].camera.fx` (the same syntax the errors use)."""
    keys = [int(k) if k.isdigit() else k for k in re.findall(r"[^.\[\]]+", path)]
    d = m
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value
    return m


def expect_error(tmp_path, m, field, message=""):
    p = write(tmp_path, m)
    with pytest.raises(jio.ManifestError) as e:
        jio.read_manifest(p)
    text = str(e.value)
    assert text.startswith(str(p)), text
    assert f"`{field}`" in text, text
    assert message in text, text
    assert "\n" not in text
    return text


def _codes(path, value, dtype, shape=(16, 16, 3)):
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(shape[1], shape[0], shape[2], "uint8" if dtype == np.uint8 else "uint16"))
    assert out.write_image(np.full(shape, value, dtype))
    out.close()


def test_valid_manifest_round_trip(tmp_path):
    m = jio.read_manifest(write(tmp_path, base_manifest()))
    assert m["views"][1]["camera"]["fx"] == 20.0 and m["views"][0]["camera"]["width"] == 16
    np.testing.assert_allclose(m["lighting"]["directional"][0]["direction"], [0, 0, 1])
    assert m["solve"] == {"lighting_lmax": 4, "render_lmax": None, "fresnel": True, "saturation": None,
                          "brdf_model": "torrance_sparrow", "textured": None, "n_centers": 400, "m_w": 0.3, "m_xy": 0.3,
                          "tol": None, "min_cos": 0.1, "max_samples": 200000}
    assert m["views"][0]["exposure"] == 1.0 and m["views"][0]["lighting"] is None and m["encoding"] is None


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("views[0].camera.width", 16.7, "integer"),
        ("views[0].camera.width", 1e400, "integer"),  # json.dumps writes Infinity
        ("views[0].camera.height", 0, ">= 1"),
        ("views[0].camera.width", "16", "integer"),
        ("views[0].camera.width", True, "integer"),
        ("views[1].camera.fx", -1, "> 0"),
        ("views[1].camera.fy", float("nan"), "finite"),
        ("views[1].camera.cx", float("inf"), "finite"),
        ("views[0].camera.scale", 0, "> 0"),
        ("views[0].camera.model", "fisheye", "pinhole"),
        ("brdf.sigma", 0.0, "> 0"),
        ("brdf.sigma", float("nan"), "finite"),
        ("brdf.mu", 0.9, ">= 1"),
        ("brdf.kd", -0.1, ">= 0"),
        ("brdf.kd[1]", -0.1, ">= 0"),
        ("brdf.kd", [0.1, 0.2], "3 numbers"),
        ("brdf.model", "phong", "torrance_sparrow"),
        ("geometry.sphere.radius", -1, "> 0"),
        ("geometry.sphere.center", [0, 0], "3 numbers"),
        ("lighting.directional", 5, "list"),
        ("lighting.directional[0].direction", [0, 0, 0], "non-zero"),
        ("lighting.directional[0].radiance", -2, ">= 0"),
        ("lighting.directional[0].direction[2]", "up", "number"),
        ("lighting.up", "y", "+z"),
        ("solve.lighting_lmax", 2.5, "integer"),
        ("solve.fresnel", "yes", "true or false"),
        ("solve.brdf_model", "phong", "sharing"),
        ("views[0].exposure", 0, "> 0"),
        ("views[0].saturation", -3, "> 0"),
        ("views[0].encoding", "gamma", "srgb"),
        ("encoding", "log", "linear"),
        ("views[0].camera.cam_to_world", [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "4x4"),
        ("views", [], "non-empty"),
        ("views[0].camera", "cam", "object"),
    ],
)
def test_bad_values_name_the_field(tmp_path, field, value, message):
    expect_error(tmp_path, set_path(base_manifest(), field, value), field, message)


def test_camera_matrix_checks(tmp_path):
    m = base_manifest()
    m["views"][0]["camera"]["cam_to_world"] = np.diag([1.0, 1.0, 2.0, 1.0]).tolist()
    expect_error(tmp_path, m, "views[0].camera.cam_to_world", "rotation")
    m["views"][0]["camera"]["cam_to_world"] = np.diag([1.0, 1.0, -1.0, 1.0]).tolist()  # a reflection
    expect_error(tmp_path, m, "views[0].camera.cam_to_world", "det +1")
    bad = copy.deepcopy(CAM)
    bad[3] = [0, 0, 1, 1]
    m["views"][0]["camera"]["cam_to_world"] = bad
    expect_error(tmp_path, m, "views[0].camera.cam_to_world", "last row")
    m["views"][0]["camera"]["cam_to_world"] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, float("nan")]]
    expect_error(tmp_path, m, "views[0].camera.cam_to_world[3][3]", "finite")


def test_unknown_fields_are_errors_with_a_suggestion(tmp_path):
    m = base_manifest()
    m["views"][1]["exposre"] = 2.0
    assert "did you mean \"exposure\"" in expect_error(tmp_path, m, "views[1].exposre", "unknown field")
    m = base_manifest()
    m["views"][0]["camera"]["fx"] = 100  # a pinhole parameter on an orthographic camera
    expect_error(tmp_path, m, "views[0].camera.fx", "unknown field")
    m = base_manifest()
    m["ligthing"] = m.pop("lighting")
    assert "did you mean \"lighting\"" in expect_error(tmp_path, m, "ligthing")
    m = base_manifest()
    m["_note"] = "comments start with an underscore"
    m["views"][0]["_why"] = "skipped"
    m["$schema"] = "docs/manifest.schema.json"
    jio.read_manifest(write(tmp_path, m))


def test_missing_fields(tmp_path):
    m = base_manifest()
    del m["brdf"]["sigma"]
    expect_error(tmp_path, m, "brdf.sigma", "missing field")
    m = base_manifest()
    del m["views"][1]["camera"]["cy"]
    expect_error(tmp_path, m, "views[1].camera.cy", "missing field")
    m = base_manifest()
    del m["geometry"]
    expect_error(tmp_path, m, "geometry", "missing field")
    m = base_manifest()
    m["geometry"] = {"sphere": {"center": [0, 0, 0], "radius": 1}, "mesh": "x.ply"}
    p = write(tmp_path, m)
    with pytest.raises(jio.ManifestError, match="exactly one"):
        jio.read_manifest(p)


def test_file_level_errors(tmp_path):
    p = tmp_path / "capture.json"
    p.write_text('{\n  "views": [\n    {"camera": 1,}\n  ]\n}\n')
    with pytest.raises(jio.ManifestError, match=r"capture\.json: not valid JSON.*line 3, column"):
        jio.read_manifest(p)
    p.write_bytes(b'{"views": "\xff\xfe"}')
    with pytest.raises(jio.ManifestError, match=r"capture\.json: not UTF-8"):
        jio.read_manifest(p)
    p.write_text('{"views": [], "views": []}')
    with pytest.raises(jio.ManifestError, match="`views` appears twice"):
        jio.read_manifest(p)
    p.write_text("[1, 2]")
    with pytest.raises(jio.ManifestError, match="JSON object"):
        jio.read_manifest(p)
    (tmp_path / "dir.json").mkdir()
    with pytest.raises(jio.ManifestError, match=r"dir\.json: is a directory"):
        jio.read_manifest(tmp_path / "dir.json")
    with pytest.raises(FileNotFoundError, match="nope.json"):
        jio.read_manifest(tmp_path / "nope.json")
    with pytest.raises(jio.ManifestError, match="nope.json"):
        jio.read_manifest(tmp_path / "nope.json")
    # a directory where a referenced file is expected
    (tmp_path / "probe.exr").mkdir()
    m = base_manifest()
    m["lighting"] = {"envmap": "probe.exr"}
    expect_error(tmp_path, m, "lighting.envmap", "is a directory")
    m["lighting"] = {"envmap": "missing.exr"}
    expect_error(tmp_path, m, "lighting.envmap", "missing.exr")


def test_encodings(tmp_path):
    _codes(tmp_path / "v16.png", 1000, np.uint16)
    _codes(tmp_path / "v8.png", 100, np.uint8)
    jio.write_image(tmp_path / "v.exr", np.ones((16, 16, 3)))
    m = base_manifest()
    m["views"][1]["image"] = "v16.png"
    text = expect_error(tmp_path, m, "views[1].encoding", "required")
    assert "v16.png" in text and "16-bit" in text
    m["encoding"] = "linear"  # the top-level default
    v = jio.read_manifest(write(tmp_path, m))["views"][1]
    assert v["encoding"] == "linear" and v["saturation"] == 65535.0
    m["views"][0]["image"] = "v8.png"
    m["views"][0]["encoding"] = "srgb"
    m["views"][0]["saturation"] = 250
    views = jio.read_manifest(write(tmp_path, m))["views"]
    assert views[0]["encoding"] == "srgb" and views[0]["saturation"] == 250.0
    m["views"][0]["image"] = "v.exr"
    expect_error(tmp_path, m, "views[0].encoding", "float image")
    del m["views"][0]["encoding"], m["views"][0]["saturation"]
    views = jio.read_manifest(write(tmp_path, m))["views"]
    assert views[0]["encoding"] == "linear" and views[0]["saturation"] is None  # float: linear, no threshold
    m["views"][0]["camera"]["width"] = 17
    expect_error(tmp_path, m, "views[0].image", "16x16")


def test_per_view_lighting_normal_maps_and_brdf_model_are_parsed(tmp_path):
    y, x = (np.mgrid[:16, :16] + 0.5) / 8 - 1
    nz = np.sqrt(np.clip(1 - x**2 - y**2, 0, None))
    nm = np.where((x**2 + y**2 < 1)[..., None], np.stack([x, -y, nz], -1), 0.0)
    np.save(tmp_path / "n.npy", nm)
    jio.write_image(tmp_path / "n.exr", nm)
    m = base_manifest()
    m["geometry"] = {"normal_map": "n.exr"}
    m["views"][1]["camera"] = copy.deepcopy(m["views"][0]["camera"])
    m["views"][1]["lighting"] = {"directional": [{"direction": [1, 0, 0], "radiance": 3}]}
    m["solve"]["brdf_model"] = "sharing_spatial"
    r = jio.read_manifest(write(tmp_path, m))
    assert r["geometry"] == {"normal_map": str(tmp_path / "n.exr")}
    np.testing.assert_allclose(r["views"][1]["lighting"]["directional"][0]["radiance"], [3, 3, 3])
    assert r["views"][0]["lighting"] is None and r["solve"]["brdf_model"] == "sharing_spatial"
    m["views"][1]["lighting"]["directional"][0]["direction"] = "x"
    expect_error(tmp_path, m, "views[1].lighting.directional[0].direction", "list of 3")
    m["views"][1]["lighting"] = {"envmap": None}
    expect_error(tmp_path, m, "views[1].lighting", "neither")
    m["views"][1]["lighting"] = None
    m["views"][1]["camera"]["scale"] = 0.2  # not the normal map's camera
    expect_error(tmp_path, m, "views[1].camera", "differs")
    # per-view normal maps, no geometry
    m = base_manifest()
    del m["geometry"]
    for v in m["views"]:
        v["normal_map"] = "n.npy"
    r = jio.read_manifest(write(tmp_path, m))
    assert r["geometry"] == {} and r["views"][1]["normal_map"] == str(tmp_path / "n.npy")
    m["views"][0]["camera"]["width"] = 20
    expect_error(tmp_path, m, "views[0].normal_map", "16x16")
    m = base_manifest()
    m["views"][0]["normal_map"] = "n.npy"
    expect_error(tmp_path, m, "views[0].normal_map", "cannot be combined")
    m["views"][0]["normal_map"] = "missing.npy"
    expect_error(tmp_path, m, "views[0].normal_map", "not found")
    np.save(tmp_path / "bad.npy", np.zeros((16, 16)))
    m["geometry"] = {"normal_map": "bad.npy"}
    del m["views"][0]["normal_map"]
    expect_error(tmp_path, m, "geometry.normal_map", "(H, W, 3)")


# numbers that must be rejected in every range-checked field
_bad_numbers = st.one_of(
    st.just(float("nan")), st.just(float("inf")), st.just(float("-inf")), st.floats(max_value=-1e-9, min_value=-1e6),
    st.text(max_size=3), st.booleans(), st.lists(st.integers(), max_size=2),
)
_positive_fields = ["views[0].camera.scale", "views[1].camera.fx", "views[1].camera.fy", "brdf.sigma",
                    "geometry.sphere.radius", "views[0].exposure", "views[1].saturation"]
_nonneg_fields = ["brdf.ks", "brdf.kd[2]", "lighting.directional[0].radiance"]


@given(field=st.sampled_from(_positive_fields + _nonneg_fields + ["brdf.mu"]), value=_bad_numbers)
def test_hypothesis_bad_numbers_are_named(tmp_path_factory, field, value):
    tmp = tmp_path_factory.mktemp("m")
    m = set_path(base_manifest(), field, value)
    p = write(tmp, m)
    with pytest.raises(jio.ManifestError) as e:
        jio.read_manifest(p)
    assert str(e.value).startswith(str(p)) and f"`{field}" in str(e.value)


@given(width=st.one_of(st.floats(allow_nan=True, allow_infinity=True).filter(lambda w: not float(w).is_integer()),
                       st.integers(max_value=0)))
def test_hypothesis_sizes_are_positive_integers(tmp_path_factory, width):
    tmp = tmp_path_factory.mktemp("m")
    p = write(tmp, set_path(base_manifest(), "views[1].camera.width", width))
    with pytest.raises(jio.ManifestError, match=r"views\[1\]\.camera\.width"):
        jio.read_manifest(p)


@given(width=st.integers(1, 4096), scale=st.floats(1e-6, 1e3), sigma=st.floats(1e-3, 2.0), mu=st.floats(1.0, 5.0))
def test_hypothesis_valid_values_are_kept(tmp_path_factory, width, scale, sigma, mu):
    tmp = tmp_path_factory.mktemp("m")
    m = base_manifest()
    set_path(m, "views[0].camera.width", width)
    set_path(m, "views[0].camera.scale", scale)
    set_path(m, "brdf.sigma", sigma)
    set_path(m, "brdf.mu", mu)
    r = jio.read_manifest(write(tmp, m))
    assert r["views"][0]["camera"]["width"] == width and r["views"][0]["camera"]["scale"] == scale
    assert r["brdf"]["sigma"] == sigma and r["brdf"]["mu"] == mu
    _validator().validate(m)


# ----------------------------------------------------------------------------- the JSON Schema


def _validator():
    jsonschema = pytest.importorskip("jsonschema")
    with open(SCHEMA) as f:
        schema = json.load(f)
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _doc_manifests():
    """Every JSON code block of docs/*.md that is a manifest (has `views`), and docs/**/*.json manifests."""
    found = []
    for md in sorted(glob.glob(os.path.join(ROOT, "docs", "**", "*.md"), recursive=True)):
        with open(md, encoding="utf-8") as f:
            text = f.read()
        for k, block in enumerate(re.findall(r"```json\n(.*?)```", text, flags=re.S)):
            try:
                m = json.loads(block)
            except json.JSONDecodeError:
                continue  # a fragment (e.g. a result.json excerpt), not a manifest
            if isinstance(m, dict) and "views" in m:
                found.append((f"{os.path.relpath(md, ROOT)}#{k}", m))
    for js in sorted(glob.glob(os.path.join(ROOT, "docs", "**", "*.json"), recursive=True)):
        if js.endswith("schema.json"):
            continue
        with open(js, encoding="utf-8") as f:
            m = json.load(f)
        if isinstance(m, dict) and "views" in m:
            found.append((os.path.relpath(js, ROOT), m))
    return found


def test_docs_have_example_manifests():
    names = [n for n, _ in _doc_manifests()]
    assert any(n.startswith(os.path.join("docs", "manifest.md")) for n in names), names


@pytest.mark.parametrize("name, manifest", _doc_manifests(), ids=lambda x: x if isinstance(x, str) else "")
def test_doc_manifests_follow_the_schema(name, manifest):
    errors = sorted(_validator().iter_errors(manifest), key=str)
    assert not errors, f"{name}: {errors[0].message} at {list(errors[0].absolute_path)}"


def test_test_manifests_follow_the_schema(tmp_path):
    """The manifests the tests build (test_cli, test_cli_safety, this file) validate."""
    from tests import test_cli

    v = _validator()
    _, m = test_cli._write_manifest(tmp_path)
    v.validate(m)
    v.validate(base_manifest())
    m["lighting"] = None
    m["brdf"] = None
    m["solve"] = {"lighting_lmax": 15, "fresnel": False, "saturation": 0.99, "brdf_model": "sharing"}
    v.validate(m)
    m2 = base_manifest()
    del m2["geometry"]
    m2["views"][0].update(normal_map="n.npy", encoding="srgb", exposure=2.0, saturation=250,
                          lighting={"envmap": "p.png", "encoding": "srgb", "up": "+y", "layout": "angular"})
    v.validate(m2)


@pytest.mark.parametrize(
    "field, value",
    [("views[0].camera.width", 16.7), ("views[0].camera.scale", 0), ("brdf.mu", 0.5), ("brdf.kd", -1),
     ("lighting.directional", 5), ("views[0].exposre", 1), ("solve.brdf_model", "phong"), ("views", []),
     ("encoding", "gamma"), ("views[1].camera.scale", 1.0)],
)
def test_schema_and_reader_reject_the_same_errors(tmp_path, field, value):
    m = set_path(base_manifest(), field, value)
    assert list(_validator().iter_errors(m)), f"the schema accepts {field} = {value!r}"
    with pytest.raises(jio.ManifestError):
        jio.read_manifest(write(tmp_path, m))
