"""The command line never overwrites an input, checks --out before the solve, writes atomically (issue 12)."""

import json
import os

import numpy as np
import pytest

import jaxsh.io as jio
import solvers._fit_manifest as fm
from solvers.cli import main

CAM = [[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 5.0], [0, 0, 0, 1.0]]


def manifest(tmp_path, *, fit=False, image="img.exr", name="capture.json", folder=None):
    """A 16x16 sphere manifest; with `fit`, an EXR image and unknown BRDF."""
    folder = tmp_path if folder is None else folder
    folder.mkdir(parents=True, exist_ok=True)
    view = {"camera": {"model": "orthographic", "scale": 0.15, "width": 16, "height": 16, "cam_to_world": CAM}}
    if fit:
        jio.write_image(folder / image, np.random.default_rng(0).random((16, 16, 3)))
        view["image"] = image
    m = {
        "geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}},
        "views": [view],
        "lighting": {"directional": [{"direction": [0.3, 0.4, 0.87], "radiance": [2, 2, 2]}]},
        "brdf": None if fit else {"model": "torrance_sparrow", "kd": 0.3, "ks": 0.2, "mu": 1.5, "sigma": 0.2},
    }
    p = folder / name
    p.write_text(json.dumps(m))
    return p


@pytest.fixture
def no_solve(monkeypatch):
    """Fail loudly if a command reaches the solve or the rendering."""

    def reached(*a, **k):
        raise AssertionError("the solve was reached")

    monkeypatch.setattr(fm, "fit_brdf", reached)
    monkeypatch.setattr("solvers._render_manifest.jaxsh.render_practical", reached)


def one_line_error(capsys, *words):
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    err = err.splitlines()[-1]  # progress lines may come before it
    assert err.startswith("jaxsh "), err
    for w in words:
        assert w in err, err
    return err


def snapshot(*paths):
    return {str(p): (p.read_bytes(), os.stat(p).st_ino) for p in paths}


@pytest.mark.parametrize("command", ["fit", "render"])
def test_out_that_is_a_file_fails_before_the_solve(tmp_path, capsys, no_solve, command):
    p = manifest(tmp_path, fit=command == "fit")
    (tmp_path / "out").write_text("not a folder")
    assert main([command, str(p), "--out", str(tmp_path / "out")]) == 2
    one_line_error(capsys, "--out", "out", "not a directory")
    assert (tmp_path / "out").read_text() == "not a folder"


def test_out_dot_never_overwrites_an_input(tmp_path, capsys, monkeypatch, no_solve):
    p = manifest(tmp_path, fit=True, image="view_000.exr")  # an input named like an output
    before = snapshot(p, tmp_path / "view_000.exr")
    monkeypatch.chdir(tmp_path)
    assert main(["fit", "capture.json", "--out", "."]) == 2
    one_line_error(capsys, "refusing to overwrite the input", "view_000.exr")
    assert snapshot(p, tmp_path / "view_000.exr") == before
    assert sorted(os.listdir(tmp_path)) == ["capture.json", "view_000.exr"]


def test_manifest_inside_the_output_folder(tmp_path, capsys, no_solve):
    p = manifest(tmp_path, fit=True, name="result.json")
    before = snapshot(p)
    assert main(["fit", str(p), "--out", str(tmp_path)]) == 2
    one_line_error(capsys, "result.json", "refusing")
    assert snapshot(p) == before


def test_symlinked_output_to_an_input(tmp_path, capsys, no_solve):
    p = manifest(tmp_path / "cap", fit=True)
    out = tmp_path / "out"
    out.mkdir()
    os.symlink(tmp_path / "cap" / "img.exr", out / "view_000.exr")
    before = snapshot(tmp_path / "cap" / "img.exr")
    assert main(["fit", str(p), "--out", str(out)]) == 2
    one_line_error(capsys, "img.exr", "refusing to overwrite")
    assert snapshot(tmp_path / "cap" / "img.exr") == before
    # an output folder that is a symlink to the inputs' folder
    os.symlink(tmp_path / "cap", tmp_path / "alias")
    (tmp_path / "cap" / "img.exr").rename(tmp_path / "cap" / "view_000.exr")
    p.write_text(p.read_text().replace("img.exr", "view_000.exr"))
    assert main(["fit", str(p), "--out", str(tmp_path / "alias")]) == 2
    one_line_error(capsys, "view_000.exr", "refusing")


def test_hard_linked_output_to_an_input(tmp_path, capsys, no_solve):
    p = manifest(tmp_path / "cap", fit=True)
    out = tmp_path / "out"
    out.mkdir()
    os.link(tmp_path / "cap" / "img.exr", out / "view_000.png")
    before = snapshot(tmp_path / "cap" / "img.exr")
    assert main(["fit", str(p), "--out", str(out)]) == 2
    one_line_error(capsys, "img.exr", "the same file")
    assert snapshot(tmp_path / "cap" / "img.exr") == before


def test_out_is_an_inputs_folder(tmp_path, capsys, no_solve):
    """Typical: render into renders/, fit those images with --out renders."""
    folder = tmp_path / "renders"
    folder.mkdir()
    p = manifest(tmp_path, fit=True, image="renders/view_000.exr")
    before = snapshot(folder / "view_000.exr")
    assert main(["fit", str(p), "--out", str(folder)]) == 2
    one_line_error(capsys, "renders/view_000.exr")
    assert snapshot(folder / "view_000.exr") == before


def test_render_into_the_manifests_folder_without_collision(tmp_path):
    """The inputs' folder is a fine output folder when no name collides."""
    p = manifest(tmp_path)
    before = snapshot(p)
    assert main(["render", str(p), "--out", str(tmp_path)]) == 0
    assert snapshot(p) == before
    assert sorted(os.listdir(tmp_path)) == ["capture.json", "view_000.exr", "view_000.png"]


def test_files_of_an_earlier_run_are_named_not_deleted(tmp_path, capsys):
    """A second run into the same folder replaces its own outputs and names those of the earlier run that it did not
    write (here the views of a capture with two views, rendered again with one), leaving them in place."""
    p = manifest(tmp_path)
    m = json.loads(p.read_text())
    m["views"] *= 2
    p2 = tmp_path / "two.json"
    p2.write_text(json.dumps(m))
    out = tmp_path / "out"
    assert main(["render", str(p2), "--out", str(out)]) == 0
    assert "earlier run" not in capsys.readouterr().err
    (out / "notes.txt").write_text("mine")  # not an output name: never reported
    assert main(["render", str(p), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "also holds 2 file(s) of an earlier run that this run did not write: view_001.exr, view_001.png" in err
    assert sorted(os.listdir(out)) == ["notes.txt", "view_000.exr", "view_000.png", "view_001.exr", "view_001.png"]
    (out / "view_1000.exr").write_text("x")  # a capture of more than 1,000 views: names keep all digits
    (out / "view_01.exr").write_text("x")  # not an output name (3 digits at least)
    assert main(["render", str(p), "--out", str(out)]) == 0
    assert ("3 file(s) of an earlier run that this run did not write: view_001.exr, view_001.png, view_1000.exr"
            in capsys.readouterr().err)


def test_fit_names_the_files_of_an_earlier_run(tmp_path, capsys):
    p = manifest(tmp_path, fit=True)
    m = json.loads(p.read_text())
    m["views"] *= 2
    p2 = tmp_path / "two.json"
    p2.write_text(json.dumps(m))
    out = tmp_path / "out"
    main(["fit", str(p2), "--out", str(out)])
    capsys.readouterr()
    main(["fit", str(p), "--out", str(out)])
    err = capsys.readouterr().err
    assert "also holds 2 file(s) of an earlier run that this run did not write: view_001.exr, view_001.png" in err


def test_interrupted_render_leaves_no_partial_file(tmp_path, capsys, monkeypatch):
    p = manifest(tmp_path)
    out = tmp_path / "out"
    real = jio._write_pixels
    calls = []

    def dies_on_the_png(path, spec, data):
        calls.append(path)
        if path.endswith(".png"):
            with open(path, "wb") as f:
                f.write(b"\x89PNG\r\n\x1a\n half a PNG")
            raise OSError(28, "No space left on device")
        real(path, spec, data)

    monkeypatch.setattr(jio, "_write_pixels", dies_on_the_png)
    assert main(["render", str(p), "--out", str(out)]) == 2
    one_line_error(capsys, "No space left on device", "view_000.png")
    assert sorted(os.listdir(out)) == ["view_000.exr"]  # complete, and no temporary file
    assert jio.read_image(out / "view_000.exr").shape == (16, 16, 3)
    assert len(calls) == 2 and all(os.path.basename(c).startswith(".view_000.") for c in calls)

    def interrupted(path, spec, data):
        with open(path, "wb") as f:
            f.write(b"v/1\x01 partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(jio, "_write_pixels", interrupted)
    old = snapshot(out / "view_000.exr")
    with pytest.raises(KeyboardInterrupt):
        main(["render", str(p), "--out", str(out)])
    assert sorted(os.listdir(out)) == ["view_000.exr"] and snapshot(out / "view_000.exr") == old


def test_interrupted_result_json(tmp_path, monkeypatch):
    (tmp_path / "result.json").write_text('{"old": true}')

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(jio.os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        jio.write_json(tmp_path / "result.json", {"status": "converged"})
    assert sorted(os.listdir(tmp_path)) == ["result.json"]
    assert json.loads((tmp_path / "result.json").read_text()) == {"old": True}


@pytest.mark.parametrize(
    "change, words",
    [
        (lambda m: m["views"][0].update(lighting={"directional": 5}),  # views[k].lighting is supported: checked
         ["`views[0].lighting.directional` must be a list"]),
        (lambda m: m.update(solve={"brdf_model": "sharing", "textured": "kd"}), ["solve.textured", "torrance_sparrow"]),
        (lambda m: m["views"][0]["camera"].update(fx=3), ["unknown field `views[0].camera.fx`"]),
        (lambda m: m["views"][0]["camera"].update(width=16.7), ["`views[0].camera.width` must be an integer"]),
        (lambda m: m["lighting"].update(directional=5), ["`lighting.directional` must be a list"]),
        (lambda m: m["views"][0].update(image="gone.exr"), ["`views[0].image` file not found", "gone.exr"]),
    ],
)
def test_fit_errors_are_one_line_exit_2(tmp_path, capsys, no_solve, change, words):
    p = manifest(tmp_path, fit=True)
    m = json.loads(p.read_text())
    change(m)
    p.write_text(json.dumps(m))
    assert main(["fit", str(p), "--out", str(tmp_path / "o")]) == 2
    one_line_error(capsys, "capture.json", *words)
    assert not (tmp_path / "o").exists()


def test_missing_encoding_names_file_view_and_field(tmp_path, capsys, no_solve):
    import OpenImageIO as oiio

    p = manifest(tmp_path, fit=True)
    out = oiio.ImageOutput.create(str(tmp_path / "img16.png"))
    out.open(str(tmp_path / "img16.png"), oiio.ImageSpec(16, 16, 3, "uint16"))
    out.write_image(np.full((16, 16, 3), 1000, np.uint16))
    out.close()
    p.write_text(p.read_text().replace("img.exr", "img16.png"))
    for command in ("fit", "render"):
        if command == "render":
            m = json.loads(p.read_text())
            m["brdf"] = {"model": "torrance_sparrow", "kd": 0.3, "ks": 0.2, "mu": 1.5, "sigma": 0.2}
            p.write_text(json.dumps(m))
        assert main([command, str(p), "--out", str(tmp_path / "o")]) == 2
        one_line_error(capsys, "img16.png", "`views[0].encoding`", "required")


def test_unexpected_failures_are_one_line_exit_1(tmp_path, capsys, monkeypatch):
    p = manifest(tmp_path)

    def boom(*a, **k):
        raise RuntimeError("something\nbroke")

    monkeypatch.setattr("solvers._render_manifest.render_manifest", boom)
    assert main(["render", str(p), "--out", str(tmp_path / "o")]) == 1
    one_line_error(capsys, "RuntimeError", "something broke", "JAXSH_TRACEBACK")


@pytest.mark.parametrize("solve, brdf, field", [
    ({"n_centers": 5}, False, "n_centers"), ({"m_w": 0.1}, False, "m_w"), ({"tol": 0.5}, False, "tol"),
    ({"min_cos": 0.9}, False, "min_cos"), ({"max_samples": 3}, False, "max_samples"), ({"m_xy": 0.2}, False, "m_xy"),
    ({"brdf_model": "sharing", "m_xy": 0.2}, False, "m_xy"), ({"fresnel": False}, True, "fresnel"),
    ({"render_lmax": 3}, False, "render_lmax"), ({"render_lmax": 3}, True, "render_lmax"),
])
def test_fit_refuses_solve_fields_its_fit_does_not_use(tmp_path, capsys, no_solve, solve, brdf, field):
    """docs/manifest.md: a field a command cannot use is an error before any work, never silently ignored. `jaxsh fit`
    ran a Torrance-Sparrow fit with sharing settings, an inverse lighting (known `brdf`) with `fresnel` false, and
    a directional-only fit with `render_lmax`, each exiting 0 with the same result as without the field."""
    p = manifest(tmp_path, fit=True)
    m = json.loads(p.read_text())
    m["solve"] = solve
    if brdf:
        m["brdf"] = {"model": "torrance_sparrow", "kd": 0.3, "ks": 0.2, "mu": 1.5, "sigma": 0.2}
        m["lighting"] = None
    p.write_text(json.dumps(m))
    assert main(["fit", str(p), "--out", str(tmp_path / "out")]) == 2
    one_line_error(capsys, f"`solve.{field}`", "does not use it")
