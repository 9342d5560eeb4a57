"""The command line's persistent compilation cache (issue 13: a second run reuses the compiled programs)."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

import jaxsh.io
from solvers import cli

C2W = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10], [0, 0, 0, 1]]


def _manifest(tmp_path):
    m = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}},
         "views": [{"camera": {"model": "orthographic", "scale": 0.15, "width": 16, "height": 16, "cam_to_world": C2W}}],
         "lighting": {"directional": [{"direction": [0.3, 0.2, 0.93], "radiance": 1.5}]},
         "brdf": {"model": "torrance_sparrow", "kd": [0.5, 0.4, 0.3], "ks": 0.2, "mu": 1.5, "sigma": 0.2}}
    p = tmp_path / "render.json"
    p.write_text(json.dumps(m))
    return p


def _run(args, env):
    code = "import sys; from solvers.cli import main; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, timeout=600)


def test_command_line_fills_and_reuses_its_cache(tmp_path):
    p = _manifest(tmp_path)
    env = {**os.environ, "JAXSH_CACHE_DIR": str(tmp_path / "xla")}
    env.pop("JAXSH_NO_CACHE", None)
    env.pop("EQX_ON_ERROR", None)
    r1 = _run(["render", str(p), "--out", str(tmp_path / "a")], env)
    assert r1.returncode == 0, r1.stderr
    entries = set(os.listdir(tmp_path / "xla"))
    # the G-buffer's and the renderer's programs are cached (the renderer: `_render_practical`, or its
    # per-pixel and combining programs)
    assert any("sphere_gbuffer" in e for e in entries), sorted(entries)[:10]
    assert any("render" in e or "combine" in e for e in entries), sorted(entries)[:10]
    r2 = _run(["render", str(p), "--out", str(tmp_path / "b")], env)
    assert r2.returncode == 0, r2.stderr
    a = jaxsh.io.read_image(tmp_path / "a" / "view_000.exr")
    b = jaxsh.io.read_image(tmp_path / "b" / "view_000.exr")
    np.testing.assert_array_equal(a, b)
    assert a.max() > 0.05


@pytest.mark.slow  # the cache itself is tested by test_command_line_fills_and_reuses_its_cache (make test-all)
def test_cache_can_be_turned_off(tmp_path):
    p = _manifest(tmp_path)
    env = {**os.environ, "JAXSH_CACHE_DIR": str(tmp_path / "xla"), "JAXSH_NO_CACHE": "1"}
    r = _run(["render", str(p), "--out", str(tmp_path / "a")], env)
    assert r.returncode == 0, r.stderr
    assert not (tmp_path / "xla").exists()


def test_main_with_argv_leaves_the_callers_jax_config_alone(tmp_path, monkeypatch):
    """Called from Python (tests, notebooks) the command line does not change `jax.config` of that process."""
    monkeypatch.setenv("JAXSH_CACHE_DIR", str(tmp_path / "xla"))
    before = jax.config.jax_compilation_cache_dir
    assert cli.main(["render", str(_manifest(tmp_path)), "--out", str(tmp_path / "o")]) == 0
    assert jax.config.jax_compilation_cache_dir == before
    assert not (tmp_path / "xla").exists()


def test_cache_dir_locations(monkeypatch, tmp_path):
    monkeypatch.delenv("JAXSH_NO_CACHE", raising=False)
    monkeypatch.setenv("JAXSH_CACHE_DIR", str(tmp_path / "c"))
    assert cli.cache_dir() == str(tmp_path / "c")
    monkeypatch.delenv("JAXSH_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "x"))
    assert cli.cache_dir() == os.path.join(str(tmp_path / "x"), "jaxsh", "xla")
    monkeypatch.setenv("JAXSH_NO_CACHE", "1")
    assert cli.cache_dir() is None
