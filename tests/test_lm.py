"""`solvers._lm`: Levenberg-Marquardt that accepts a step whose loss changed only by rounding.

References: the trust region's acceptance rule on hand-made losses (one ulp above, well above, below the last
accepted one) against `optimistix.ClassicalTrustRegion`'s; the damped step against `numpy.linalg.lstsq` of the
stacked system; the solution against `scipy.optimize.least_squares` and against a linear problem's closed form;
the compiled program against the LAPACK call that races (`dormqr`)."""

import re

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest
import scipy.optimize

from solvers._lm import _FLAT, FactoredDampedNewtonDescent, LevenbergMarquardt, RoundingTrustRegion


def _info(residual, jac):
    return optx.FunctionInfo.ResidualJac(jnp.asarray(residual), lx.MatrixLinearOperator(jnp.asarray(jac)))


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_trust_region_accepts_a_loss_changed_by_rounding_only(dtype):
    """A step whose loss is one ulp above the last accepted loss, predicted to fall by far less than that, is
    rejected by optimistix's trust region (which shrinks by 1/4) and accepted here with the size kept; a loss
    clearly above is rejected by both, alike; a loss that falls as predicted is accepted by both, alike."""
    jac = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    r0 = np.array([3.0, -4.0, 2.0])
    y = jnp.zeros(2, dtype)
    # a tiny step down the gradient J^T r0 = (5, -2): a predicted decrease (29 eps^2-ish) far below the loss's ulp
    y_eval = jnp.asarray(-(1e-18 if dtype == jnp.float64 else 1e-10) * np.array([5.0, -2.0]), dtype)
    f0 = _info(r0.astype(dtype), jac.astype(dtype))
    loss0 = float(f0.as_min())
    ulp = float(np.spacing(np.asarray(loss0, dtype)))

    def with_loss(target):
        # the last residual moved until 0.5 |r|^2, as the solver computes it, first reaches `target`
        r = r0.astype(dtype)
        while float(_info(r, jac.astype(dtype)).as_min()) < target:
            r = r.copy()
            r[2] = np.nextafter(r[2], dtype(np.inf))
        return _info(r, jac.astype(dtype)), float(_info(r, jac.astype(dtype)).as_min())

    ours, theirs = RoundingTrustRegion(), optx.ClassicalTrustRegion()
    state = ours.init(y, None)
    first = jnp.asarray(False)
    up_one, loss_up = with_loss(loss0 + ulp)
    assert loss0 < loss_up <= loss0 + 2 * ulp
    size_o, acc_o, _, st_o = ours.step(first, y, y_eval, f0, up_one, state)
    size_t, acc_t, _, _ = theirs.step(first, y, y_eval, f0, up_one, theirs.init(y, None))
    assert not bool(acc_t) and float(size_t) == 0.25  # optimistix: rejected, the region shrunk
    assert bool(acc_o) and float(size_o) == 1.0 and float(st_o.step_size) == 1.0
    # well above rounding: both reject and shrink alike
    up, _ = with_loss(loss0 * (1 + 4 * _FLAT * np.finfo(dtype).eps))
    (s1, a1, _, _), (s2, a2, _, _) = (ours.step(first, y, y_eval, f0, up, state),
                                      theirs.step(first, y, y_eval, f0, up, theirs.init(y, None)))
    assert not bool(a1) and not bool(a2) and float(s1) == float(s2) == 0.25
    # a real decrease (a full Gauss-Newton step of this linear model): both accept and grow alike
    y_gn = -jnp.linalg.lstsq(jac.astype(dtype), r0.astype(dtype))[0]
    down = _info((r0 + jac @ np.asarray(y_gn, np.float64)).astype(dtype), jac.astype(dtype))
    (s1, a1, _, _), (s2, a2, _, _) = (ours.step(first, y, y_gn, f0, down, state),
                                      theirs.step(first, y, y_gn, f0, down, theirs.init(y, None)))
    assert bool(a1) and bool(a2) and float(s1) == float(s2) == 3.5


def test_solution_matches_scipy_and_a_closed_form():
    """An exponential decay fitted to noisy samples: the minimizer of scipy's `least_squares` (method "lm",
    MINPACK) to 1e-9, in no more steps than optimistix's own Levenberg-Marquardt takes; a linear problem: its
    least-squares solution (`numpy.linalg.lstsq`) to 1e-12."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 4.0, 20_000)
    data = 2.5 * np.exp(-1.3 * t) + 0.4 + 0.01 * rng.normal(size=t.size)

    def resid(p, _):
        return p[0] * jnp.exp(-p[1] * t) + p[2] - data

    p0 = jnp.asarray([1.0, 0.5, 0.0])
    ours = optx.least_squares(resid, LevenbergMarquardt(rtol=1e-10, atol=1e-10), p0, max_steps=100, throw=False)
    theirs = optx.least_squares(resid, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10), p0, max_steps=100, throw=False)
    ref = scipy.optimize.least_squares(lambda p: np.asarray(resid(p, None)), np.asarray(p0), method="lm",
                                       xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    assert ours.result == optx.RESULTS.successful
    np.testing.assert_allclose(np.asarray(ours.value), ref, rtol=1e-9)
    assert int(ours.stats["num_steps"]) <= int(theirs.stats["num_steps"])

    a = rng.normal(size=(500, 4))
    b = rng.normal(size=500)
    lin = optx.least_squares(lambda p, _: a @ p - b, LevenbergMarquardt(rtol=1e-12, atol=1e-12), jnp.zeros(4),
                             max_steps=50, throw=False)
    np.testing.assert_allclose(np.asarray(lin.value), np.linalg.lstsq(a, b, rcond=None)[0], rtol=1e-12, atol=1e-14)


def test_jit_and_float32():
    """Traced inside `jax.jit`, and in float32 in a process without float64 (a user's default; with float64 on,
    optimistix's own Levenberg-Marquardt fails on float32 parameters too: its damping is float64), where the
    loss's ulp is float32's."""
    with jax.enable_x64(False):
        t = jnp.linspace(0.0, 2.0, 1000)
        data = 1.5 * jnp.exp(-0.7 * t) + 0.01 * jnp.sin(40.0 * t)

        @jax.jit
        def fit(p0):
            sol = optx.least_squares(lambda p, _: p[0] * jnp.exp(-p[1] * t) - data, LevenbergMarquardt(1e-6, 1e-6),
                                     p0, max_steps=100, throw=False)
            return sol.value, sol.result

        p, res = fit(jnp.asarray([1.0, 1.0]))
        assert p.dtype == jnp.float32 and res == optx.RESULTS.successful
    ref = scipy.optimize.least_squares(lambda q: q[0] * np.exp(-q[1] * np.asarray(t, float)) - np.asarray(data, float),
                                       [1.0, 1.0], method="lm", xtol=1e-14, ftol=1e-14).x
    np.testing.assert_allclose(np.asarray(p), ref, rtol=1e-5)


@pytest.mark.parametrize("blocks", [1, 2, 3])
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_damped_step_is_the_stacked_least_squares_solution(dtype, blocks):
    r"""`FactoredDampedNewtonDescent`'s step at several step sizes is $-\delta$, $\delta$ the least-squares solution
    of $[J; \sqrt{\lambda} I]\delta = [r; 0]$, $\lambda = 1/$size (`numpy.linalg.lstsq` in float64 of the stacked
    system: optimistix's step, by another route), for parameters given as a pytree (a dict of a vector and a
    scalar, raveled in `ravel_pytree`'s order), for residuals given as a pytree (a `(m/2, 2)` leaf and a `(2,)`
    leaf, as `fit_brdf`'s samples and wall), in one block and in `blocks` row blocks (TSQR), and for fewer
    residuals than parameters + 1; a step size at or below eps gives a vanishing step (below 1e-30)."""
    rng = np.random.default_rng(7)
    tol = 1e-11 if dtype == jnp.float64 else 2e-4
    y = {"a": jnp.zeros(2, dtype), "b": jnp.zeros((), dtype)}  # ravel_pytree order: a[0], a[1], b
    for m, tree in ((300, False), (302, True), (2, False), (3, False), (4, False)):  # blocks of 1 or 2 rows
        jac = rng.normal(size=(m, 3)) * np.array([1.0, 30.0, 0.2])  # columns of unequal scale
        res = rng.normal(size=m)
        jd = jnp.asarray(jac, dtype)

        def mv(v, jd=jd, tree=tree):
            out = jd @ jnp.concatenate([v["a"], v["b"][None]])
            return (out[:-2].reshape(-1, 2), out[-2:]) if tree else out

        op = lx.FunctionLinearOperator(mv, jax.eval_shape(lambda: y))
        r = jnp.asarray(res, dtype)
        d = FactoredDampedNewtonDescent(blocks)
        info = optx.FunctionInfo.ResidualJac((r[:-2].reshape(-1, 2), r[-2:]) if tree else r, op)
        state = d.query(y, info, d.init(y, None))
        for size in (1e-3, 0.25, 1.0, 40.0, 1e6):
            step, result = d.step(jnp.asarray(size, dtype), state)
            assert result == optx.RESULTS.successful
            got = np.concatenate([np.asarray(step["a"], np.float64), [float(step["b"])]])
            assert step["a"].dtype == dtype and step["b"].shape == ()
            stacked = np.concatenate([jac, np.sqrt(1.0 / size) * np.eye(3)])
            want = -np.linalg.lstsq(stacked, np.concatenate([res, np.zeros(3)]), rcond=None)[0]
            np.testing.assert_allclose(got, want, rtol=tol, atol=tol * np.max(np.abs(want)))
        step, _ = d.step(jnp.asarray(np.finfo(dtype).eps / 2, dtype), state)
        # lambda = the dtype's largest value (optimistix's): a step of the order of its inverse
        assert max(float(jnp.max(jnp.abs(step["a"]))), abs(float(step["b"]))) < 1e-30


def test_program_has_no_ormqr():
    """The compiled Levenberg-Marquardt holds no LAPACK `dormqr` call, the one that races on CPU (module docstring
    of `solvers._lm`: it writes the factor that XLA lets a concurrent slice read); optimistix's own holds one (its
    `lineax.QR`), so the check sees what it looks for."""
    t = jnp.linspace(0.0, 3.0, 64)
    data = 2.0 * jnp.exp(-1.3 * t)

    def text(solver):
        fit = jax.jit(lambda p0: optx.least_squares(lambda p, _: p[0] * jnp.exp(-p[1] * t) - data, solver, p0,
                                                    max_steps=20, throw=False).value)
        return fit.lower(jnp.asarray([1.0, 0.5])).compile().as_text()

    def targets(solver):
        return set(re.findall(r'custom_call_target="(\w+)"', text(solver)))

    assert any("ormqr" in c for c in targets(optx.LevenbergMarquardt(1e-8, 1e-8)))
    ours = targets(LevenbergMarquardt(1e-8, 1e-8))
    assert not any("ormqr" in c for c in ours) and any("geqrf" in c for c in ours), ours
