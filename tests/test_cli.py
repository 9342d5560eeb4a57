"""The `jaxsh` command line."""

import json

import jax

from solvers.cli import main


def test_demo_runs_small_and_writes_report(tmp_path):
    x64_before = jax.config.jax_enable_x64
    out = tmp_path / "out"
    report = tmp_path / "r.json"
    rc = main(["demo", "--height", "32", "--lmax", "2", "6", "--out", str(out), "--json", str(report)])
    assert rc == 0
    data = json.loads(report.read_text())
    assert [p["lmax"] for p in data["projection"]] == [2, 6]
    assert all(p["round_trip_max_abs"] < 1e-9 for p in data["projection"])
    assert data["convolution"]["lstar_lambertian"] == 2
    assert (out / "sky.exr").exists() and (out / "sky.png").exists()
    assert jax.config.jax_enable_x64 == x64_before  # the demo's float64 is scoped


def test_fit_and_render_say_not_implemented(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "m.json")]) == 2
    assert "not implemented yet" in capsys.readouterr().err
    assert main(["render", str(tmp_path / "m.json")]) == 2
