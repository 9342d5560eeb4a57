"""`jaxsh.jit` / `jaxsh.compile_options`: jaxsh's programs compiled with their own XLA options.

What is promised (jaxsh/_compile.py): the option is used only where this jaxlib accepts it and the
user's `XLA_FLAGS` do not name it; a program compiled with it computes what the plain `jax.jit`
computes; a jaxsh program called inside the caller's own `jit`, `grad`, `vmap` or `lax.map` is staged
into the caller's program (JAX refuses compile options on a nested jit). The speed is measured in
`benchmarks/` (docs/performance.md), not here.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

import jaxsh
from jaxsh import _compile


@pytest.fixture
def fresh_probe(monkeypatch):
    """Forget the per-process probe before and after the test."""
    _compile._probed_options.cache_clear()
    yield monkeypatch
    _compile._probed_options.cache_clear()


def _accepts(name, value):
    try:
        jax.jit(lambda x: x * 2, compiler_options={name: value}).lower(np.float32(1)).compile()
        return True
    except Exception:  # noqa: BLE001
        return False


def test_options_are_the_accepted_ones(fresh_probe):
    fresh_probe.delenv("XLA_FLAGS", raising=False)
    opts = jaxsh.compile_options()
    want = {k: v for k, v in _compile._WANTED.items() if _accepts(k, v)}
    assert opts == want
    opts["xla_cpu_use_fusion_emitters"] = True  # a copy: the caller cannot change jaxsh's options
    assert jaxsh.compile_options() == want


def test_rejected_option_is_left_out(fresh_probe):
    fresh_probe.delenv("XLA_FLAGS", raising=False)
    fresh_probe.setattr(_compile, "_WANTED", {"xla_no_such_option_for_jaxsh": True, **_compile._WANTED})
    assert "xla_no_such_option_for_jaxsh" not in jaxsh.compile_options()
    # and a program still compiles and runs
    f = jaxsh.jit(lambda x: jnp.sin(x) + 1.0)
    np.testing.assert_allclose(f(jnp.asarray([0.5, 1.5])), np.sin([0.5, 1.5]) + 1.0, rtol=1e-15)


def test_unoptimized_options(fresh_probe, monkeypatch):
    """`optimize=False` adds XLA's backend optimization level 0 to the options (where accepted and not named
    by `XLA_FLAGS`), reaches the compilation of a `jaxsh.jit(..., optimize=False)` program, and the program
    computes what the optimized one does."""
    fresh_probe.delenv("XLA_FLAGS", raising=False)
    want = {k: v for k, v in {**_compile._WANTED, **_compile._UNOPTIMIZED}.items() if _accepts(k, v)}
    assert want.get("xla_backend_optimization_level") == 0  # this jaxlib has it: the rest of the test means something
    assert jaxsh.compile_options(optimize=False) == want
    assert "xla_backend_optimization_level" not in jaxsh.compile_options()
    with pytest.raises(ValueError, match="optimize"):
        jaxsh.compile_options(optimize=0)
    with pytest.raises(ValueError, match="optimize"):
        jaxsh.jit(lambda x: x, optimize="no")
    seen = []
    real = eqx.filter_jit

    def spy(fun, **kw):
        seen.append(kw.get("compiler_options"))
        return real(fun, **kw)

    monkeypatch.setattr(_compile.eqx, "filter_jit", spy)
    d = jnp.asarray(np.random.default_rng(5).normal(size=(65, 3)))
    slow = jaxsh.jit(lambda v: jaxsh.real_sh(v, 5), optimize=False)
    fast = jaxsh.jit(lambda v: jaxsh.real_sh(v, 5))
    got = np.asarray(slow(d))
    np.testing.assert_allclose(got, np.asarray(fast(d)), atol=1e-14, rtol=0)
    u = np.asarray(d) / np.linalg.norm(np.asarray(d), axis=1, keepdims=True)
    ref = scipy.special.sph_harm_y(4, 0, np.arccos(u[:, 2]), np.arctan2(u[:, 1], u[:, 0])).real  # Y_{4,0}: real
    np.testing.assert_allclose(got[:, 20], ref, atol=1e-13)
    assert want in seen  # the level-0 options were handed to the compilation
    fresh_probe.setenv("XLA_FLAGS", "--xla_backend_optimization_level=2")
    _compile._probed_options.cache_clear()
    assert "xla_backend_optimization_level" not in jaxsh.compile_options(optimize=False)


def test_xla_flags_naming_the_option_win(fresh_probe):
    fresh_probe.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert "xla_cpu_use_fusion_emitters" not in jaxsh.compile_options()


def test_tuned_program_computes_what_plain_jit_does():
    # a fused elementwise chain, a reduction and a loop, in both dtypes, against scipy where it can
    rng = np.random.default_rng(3)
    d = rng.normal(size=(257, 3))
    for dt, tol in ((np.float64, 1e-13), (np.float32, 2e-6)):
        x = jnp.asarray(d, dt)
        ours = jaxsh.real_sh(x, 6)
        plain = eqx.filter_jit(lambda v: jaxsh.real_sh(v, 6))(x)
        assert ours.dtype == dt
        np.testing.assert_allclose(np.asarray(ours), np.asarray(plain), atol=tol, rtol=0)
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    theta, phi = np.arccos(u[:, 2]), np.arctan2(u[:, 1], u[:, 0])
    ref = scipy.special.sph_harm_y(4, 0, theta, phi).real  # Y_{4,0} is real
    np.testing.assert_allclose(np.asarray(jaxsh.real_sh(jnp.asarray(d), 4))[:, 20], ref, atol=1e-13)


def test_nested_in_callers_transformations():
    d = np.random.default_rng(0).normal(size=(5, 3))
    direct = np.asarray(jaxsh.real_sh(d, 3))
    # traced argument inside the caller's jit
    np.testing.assert_allclose(jax.jit(lambda v: jaxsh.real_sh(v, 3))(d), direct, rtol=1e-14)
    # constant argument inside the caller's jit (no tracer among the arguments)
    np.testing.assert_allclose(jax.jit(lambda s: jaxsh.real_sh(d, 3) * s)(2.0), 2 * direct, rtol=1e-14)
    np.testing.assert_allclose(jax.vmap(lambda v: jaxsh.real_sh(v, 3))(d[None])[0], direct, rtol=1e-14)
    np.testing.assert_allclose(jax.lax.map(lambda v: jaxsh.real_sh(v, 3), d), direct, rtol=1e-14)
    # gradient of sum(Y_{1,0}) = sum(c z/|d|) against the closed form c (e_z - z d/|d|^2)/|d|
    c = np.sqrt(3 / (4 * np.pi))
    g = jax.grad(lambda v: jaxsh.real_sh(v, 1)[:, 2].sum())(jnp.asarray(d))
    r = np.linalg.norm(d, axis=1, keepdims=True)
    want = c * (np.array([0, 0, 1.0]) - d[:, 2:3] * d / r**2) / r
    np.testing.assert_allclose(g, want, rtol=1e-12)


def test_jit_decorator_forms():
    @jaxsh.jit
    def f(x, n):
        return x**n

    g = jaxsh.jit(donate="none")(lambda x: x + 1)
    assert float(f(jnp.asarray(3.0), 2)) == 9.0  # `n`: a Python int, static (filter_jit's rule)
    assert float(g(jnp.asarray(1.0))) == 2.0
    assert f.__name__ == "f"
    low = f.lower(jnp.asarray(3.0), 3)
    assert float(low.compile()(jnp.asarray(2.0), 3)) == 8.0


def test_importing_the_packages_leaves_jax_config_alone():
    """`import jaxsh, solvers, solvers.cli, jaxsh.io` in a fresh process changes no `jax.config` value
    (x64, caches, device count, ...): global flags are the user's; only the command line's `main()` sets its
    own (tests/test_cli_cache.py)."""
    import subprocess
    import sys

    code = (
        "import jax, json\n"
        "names = sorted(k for k in jax.config.values if isinstance(jax.config.values[k], (bool, int, float, str, type(None))))\n"
        "before = {k: jax.config.values[k] for k in names}\n"
        "import jaxsh, jaxsh.io, solvers, solvers.cli\n"
        "after = {k: jax.config.values[k] for k in names}\n"
        "print(json.dumps({k: [before[k], after[k]] for k in names if before[k] != after[k]}))\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "{}", p.stdout


def test_the_suite_compiles_into_its_shared_cache():
    """tests/conftest.py: the run's compiled programs go to one temporary folder, from which the later modules (the
    caches in memory are dropped after every module) and xdist's other worker read them back: a program compiled
    here is written there."""
    import os

    folder = os.environ.get("JAXSH_TEST_XLA_CACHE")
    if folder == "off":
        pytest.skip("run with JAXSH_TEST_XLA_CACHE=off")
    assert folder and os.path.isdir(folder), folder
    assert jax.config.jax_compilation_cache_dir == folder
    before = set(os.listdir(folder))
    salt = float(int.from_bytes(os.urandom(4), "little"))  # a program no earlier run or test has compiled
    assert float(jax.jit(lambda x: x * 3.0 + salt)(np.float64(2.0))) == 6.0 + salt
    assert set(os.listdir(folder)) - before


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.2
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _rotation(rng):
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _lighting(rng):
    sh = 0.1 * rng.normal(size=(49, 3))
    sh[0] = 1.0
    return jaxsh.Lighting(slow_sh=sh, fast_directions=_unit(rng, 1), fast_energy=rng.uniform(1, 2, (1, 3)))


def _brdf(rng):
    return jaxsh.TorranceSparrow(rng.uniform(0.2, 0.5, 3), rng.uniform(0.1, 0.3, 3), rng.uniform(1.3, 1.8), rng.uniform(0.1, 0.3))


# Public functions and argument makers: each call of a maker gives new values of the same shapes.
_N = 64
_CALLS = {
    "real_sh": lambda r: (_unit(r, _N), 12),
    "directional_light_sh": lambda r: (_unit(r, 2), r.uniform(0.5, 2, (2, 3)), 16),
    "disk_light_sh": lambda r: (_unit(r, 1)[0], r.uniform(0.05, 0.3), r.uniform(0.5, 2, 3), 16),
    "split_disk_sources": lambda r: (_unit(r, 3), r.uniform(0.01, 0.3, 3), r.uniform(0.5, 2, (3, 3)), r.uniform(0.1, 0.3), 8),
    "irradiance": lambda r: (r.normal(size=(9, 3)), _unit(r, _N)),
    "convolve": lambda r: (r.normal(size=(81, 3)), r.uniform(size=9)),
    "rotate_sh": lambda r: (r.normal(size=(81, 3)), _rotation(r)),
    "filter_lighting_microfacet": lambda r: (r.normal(size=(81, 3)), r.uniform(0.05, 0.3)),
    "microfacet_spectrum": lambda r: (r.uniform(0.05, 0.3), 16),
    "legendre_p": lambda r: (r.uniform(-1, 1, _N), 12),
    "project_latlong": lambda r: (r.uniform(size=(16, 32, 3)), 6),
    "synthesize_latlong": lambda r: (r.normal(size=(49, 3)), 16, 32),
    "fit_sh": lambda r: (_unit(r, _N), r.normal(size=(_N, 3)), 4),
    "torrance_sparrow": lambda r: (_unit(r, _N), _unit(r, _N), _unit(r, _N), 0.5, 0.3, r.uniform(1.3, 1.8), r.uniform(0.1, 0.3)),
    "cook_torrance": lambda r: (_unit(r, _N), _unit(r, _N), _unit(r, _N), 0.5, 0.3, r.uniform(0.1, 0.3), 1.5),
    "sbrdf_points": lambda r: (_unit(r, _N), _unit(r, _N), _unit(r, _N), r.uniform(size=(_N, 2))),
    "rbf_evaluate": lambda r: (r.uniform(size=(20, 5)), r.uniform(size=(20, 3)), r.uniform(size=(6, 3)), r.uniform(size=(30, 5))),
    "render_practical": lambda r: (_unit(r, _N), _unit(r, _N), _brdf(r), _lighting(r)),
    "render_reference": lambda r: (_unit(r, _N), _unit(r, _N), _brdf(r), jaxsh.Lighting(
        fast_directions=_unit(r, 1), fast_energy=r.uniform(1, 2, (1, 3)), disk_directions=_unit(r, 1),
        disk_radius=r.uniform(0.05, 0.2, 1), disk_radiance=r.uniform(0.5, 1.5, (1, 3)))),
}


@pytest.mark.parametrize("name", sorted(_CALLS))
def test_a_second_call_with_new_values_compiles_nothing(name):
    """Values are traced, shapes and band limits static: a second call with new values of the same shapes runs the
    programs of the first. (`disk_light_sh` and `directional_light_sh` ran their loop over l eagerly, which traced
    and compiled it again at every call, 0.13-0.17 s; `split_disk_sources` compiled small programs for each new
    count of fast sources.)"""
    from .helpers import Compiles

    rng = np.random.default_rng(7)
    fun = getattr(jaxsh, name)
    first, second = _CALLS[name](rng), _CALLS[name](rng)
    jax.block_until_ready(fun(*first))
    with Compiles() as c:
        out = fun(*second)
        jax.block_until_ready(out)
    assert c.names == [], c.names


def _dot_precisions(text):
    """The `precision = [...]` of every `stablehlo.dot_general` in a lowered program's text."""
    out = []
    for line in text.splitlines():
        if "stablehlo.dot_general" in line:
            out.append(line.split("precision = [")[1].split("]")[0] if "precision = [" in line else "none")
    return out


def test_float32_products_are_traced_at_full_precision():
    """float32 matrix products ask for full precision, so an accelerator does not round them to TF32.

    On an H200 (docs/performance.md, "Seventeenth round") JAX's default precision let the float32 RBF
    evaluation, the float32 sharing fit and the float32 pairwise reference renderer miss their documented
    accuracy by 10-100x. Checked here on the lowered programs (the CPU computes the same numbers at any
    precision): a jaxsh program alone, staged into the caller's `jit`, and a solver's program; and a
    precision the user set is kept.
    """
    rng = np.random.default_rng(0)
    c = jnp.asarray(rng.uniform(-1, 1, size=(50, 5)), jnp.float32)
    model = jaxsh.RBFModel(c, jnp.asarray(rng.normal(size=(50, 3)), jnp.float32),
                           jnp.asarray(rng.normal(size=(6, 3)), jnp.float32))
    x = jnp.asarray(rng.uniform(-1, 1, size=(40, 5)), jnp.float32)
    inside = _dot_precisions(jax.jit(lambda m, x: m(x)).lower(model, x).as_text())
    assert inside and all(p == "HIGHEST, HIGHEST" for p in inside), inside

    @jaxsh.jit
    def gram(a):
        return a.T @ a, jnp.einsum("ij,ik->jk", a, a)

    alone = _dot_precisions(gram.lower(x).as_text())
    assert len(alone) == 2 and all(p == "HIGHEST, HIGHEST" for p in alone), alone
    d = jnp.asarray(rng.normal(size=(30, 3)), jnp.float32)
    fit = _dot_precisions(jax.jit(lambda d, v: jaxsh.fit_sh(d, v, 4)).lower(d, d[:, 0]).as_text())
    assert fit and all(p == "HIGHEST, HIGHEST" for p in fit), fit
    with jax.default_matmul_precision("bfloat16"):  # the user's choice wins
        theirs = _dot_precisions(gram.lower(x).as_text())
    assert len(theirs) == 2 and all(p != "HIGHEST, HIGHEST" for p in theirs), theirs
    np.testing.assert_allclose(np.asarray(gram(x)[0]), np.asarray(x, np.float64).T @ np.asarray(x, np.float64),
                               rtol=2e-6)
