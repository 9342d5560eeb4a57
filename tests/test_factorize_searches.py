"""`factorize`'s 1-D searches finished by Chebyshev interpolation.

Stage 1's search over $t = \\log(\\mu - 1)$: a 9-point grid, then the minimum of the polynomial through 9 Chebyshev
points on the best value's bracket (`_chebyshev_points`, `_interpolant_minimum`, on the host). The refinement's
search over $\\log\\sigma$ (`_refine_search`, jitted): two zooms, 16 Chebyshev points, then one grid of spacing
1/16 of the tolerance around their interpolant's minimum (`_cheb_tables`, `_interpolant_argmin`).

References: closed forms (functions whose minimum and curvature are known), NumPy's Chebyshev module, and, for the
solvers, each profile evaluated on a fine grid around the returned value (a brute-force minimum of the same objective,
found without the search under test)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import solvers
from solvers import _factorize as F


def _capture(mu, sigma, noise, seed, model):
    """3 views of 48^2 of a sphere rendered with `model` (a fuller BRDF than the one fitted) and `noise`."""
    brdf = solvers.TorranceSparrow(jnp.asarray([0.5, 0.4, 0.3]), jnp.asarray([0.3, 0.3, 0.3]), jnp.asarray(mu),
                                   jnp.asarray(sigma))
    cap = solvers.sphere_capture(brdf, size=48, n_views=3, noise=noise, seed=seed, brdf_model=model)
    return solvers.observations(cap.gbuffers, cap.images)


def _in_batches(f, ts, k):
    """`f` at each value of `ts`, `k` per call (the last batch padded with its last value): `(len(ts),)`."""
    out = []
    for i in range(0, len(ts), k):
        part = np.asarray(ts[i : i + k], np.float64)
        out.append(np.asarray(f(np.concatenate([part, np.full(k - len(part), part[-1])])))[: len(part)])
    return np.concatenate(out)


def test_chebyshev_points_are_the_second_kind_on_the_interval():
    x = F._chebyshev_points(-1.25, 0.5)
    ref = -1.25 + 1.75 * (np.cos(np.pi * np.arange(9) / 8)[::-1] + 1) / 2
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-15)
    assert x[0] == -1.25 and x[-1] == 0.5 and np.all(np.diff(x) > 0)
    assert x[4] == pytest.approx(-0.375, abs=1e-15)  # the middle: the first grid's best value when not clipped


@pytest.mark.parametrize("lo, hi, t0", [(-0.5, 0.5, 0.3), (-1.53, -0.55, -0.80384569), (0.0, 1.0, 0.02)])
def test_interpolant_minimum_of_analytic_functions(lo, hi, t0):
    """cosh(t - t0) + 0.2 (t - t0)^3: minimum at t0 (f' = sinh + 0.6 (t - t0)^2 > 0 right of it, < 0 left, near it),
    second derivative 1 there. The old parabola through three points 0.054 apart was off by ~h^2 f'''/(6 f'') ~ 6e-4
    on such a cubic; the 9-point interpolant must land within 1e-9."""
    f = lambda t: np.cosh(t - t0) + 0.2 * (t - t0) ** 3  # noqa: E731
    t = F._chebyshev_points(lo, hi)
    t_min, c2 = F._interpolant_minimum(t, f(t))
    assert abs(t_min - t0) < 1e-9
    assert c2 == pytest.approx(1.0, rel=1e-6)


def test_interpolant_minimum_at_an_end_or_not_convex():
    t = F._chebyshev_points(-1.0, 1.0)
    assert F._interpolant_minimum(t, (t - 2.0) ** 2) == (1.0, None)  # decreasing throughout: the right end
    assert F._interpolant_minimum(t, (t + 3.0) ** 2) == (-1.0, None)
    t_min, c2 = F._interpolant_minimum(t, -(t**2))  # concave: an end, no curvature
    assert t_min in (-1.0, 1.0) and c2 is None
    t_min, c2 = F._interpolant_minimum(t, np.full(9, 2.0))  # flat: no curvature
    assert c2 is None


def test_interpolant_minimum_with_non_finite_values():
    t = F._chebyshev_points(0.0, 1.0)
    v = (t - 0.6) ** 2
    v[3] = np.nan
    t_min, c2 = F._interpolant_minimum(t, v)
    assert t_min == t[int(np.nanargmin(v))] and c2 is None
    t_min, c2 = F._interpolant_minimum(t, np.full(9, np.nan))
    assert t_min == t[4] and c2 is None


def _profile(tab, ts):
    """The profiled relative RSS of stage 1 at each value of `ts` (9 per batch), from the rounds' own programs."""
    return _in_batches(lambda tp: F._golden_batch(F._mu_blocks(tab, jnp.asarray(1.0 + np.exp(tp)), 6, 1e-12))[0], ts, 9)


def test_stage1_mu_is_the_profile_minimum(monkeypatch):
    """Data from a fuller BRDF than the one fitted (Cook-Torrance, 1 % noise): stage 1's profile is not the model's
    own, and its minimum is not at the true mu. The returned t = log(mu - 1) must be the minimum of the profile it
    searched, found by brute force: 41 values 2e-3 apart around it and a quartic fit (the profile's Taylor terms
    past the fourth are ~1e-12 relative over that span). Its curvature there, which gives the standard error of mu,
    must match the search's to 1e-4. The two 7-point zooms and parabola this search replaced were 1.2e-4 off here."""
    obs = _capture(1.2, 0.2, 0.01, 1, "cook_torrance")
    tabs, found = [], []
    table, minimum = F._mirror_table_jit, F._interpolant_minimum
    monkeypatch.setattr(F, "_mirror_table_jit", lambda *a: tabs.append(table(*a)) or tabs[-1])
    monkeypatch.setattr(F, "_interpolant_minimum", lambda *a: found.append(minimum(*a)) or found[-1])
    res = solvers.factorize(obs, 6, find_sigma=False, refine=False, search_pixels=None)
    assert res.status == solvers.Status.converged and len(tabs) == 1 and len(found) == 1
    t_hat = found[0][0]
    assert float(res.brdf.mu) == pytest.approx(1.0 + np.exp(t_hat), rel=1e-15) and found[0][1] is not None
    ts = t_hat + 2e-3 * np.arange(-20, 21)
    c = np.polyfit(ts - t_hat, _profile(tabs[0], ts), 4)
    t_ref = t_hat - c[3] / (2 * c[2])
    assert abs(t_hat - t_ref) < 1e-6
    assert found[0][1] == pytest.approx(2 * c[2], rel=1e-4)


def test_cheb_tables_against_numpy_chebyshev():
    rng = np.random.default_rng(3)
    c = rng.normal(size=16)
    x, coef, dense, d1, d2 = F._cheb_tables(16, 33)
    np.testing.assert_allclose(x, -np.cos(np.pi * np.arange(16) / 15), atol=1e-15)
    vals = np.polynomial.chebyshev.chebval(x, c)
    np.testing.assert_allclose(coef @ vals, c, atol=1e-12)
    np.testing.assert_allclose(dense @ vals, np.polynomial.chebyshev.chebval(np.linspace(-1, 1, 33), c), atol=1e-12)
    np.testing.assert_allclose((d1 @ c)[:15], np.polynomial.chebyshev.chebder(c), atol=1e-11)
    np.testing.assert_allclose((d2 @ c)[:14], np.polynomial.chebyshev.chebder(c, 2), atol=1e-10)
    assert np.all((d1 @ c)[15:] == 0) and np.all((d2 @ c)[14:] == 0)
    for z in (-1.0, -0.3, 0.7, 1.0):
        assert float(F._cheb_values(jnp.asarray(c), jnp.asarray(z))) == pytest.approx(
            np.polynomial.chebyshev.chebval(z, c), abs=1e-12)


@pytest.mark.parametrize("dtype, tol", [(jnp.float64, 1e-10), (jnp.float32, 2e-3)])
def test_interpolant_argmin_of_an_analytic_function(dtype, tol):
    """cosh(2(x - 0.3)) + 0.1 (x - 0.3)^3: minimum 1 at x = 0.3, second derivative 4; a cubic part so that a
    parabola through grid points would miss it."""
    x = F._cheb_tables(16, 2)[0]
    f = lambda z: np.cosh(2 * (z - 0.3)) + 0.1 * (z - 0.3) ** 3  # noqa: E731
    z, inner, val = jax.jit(F._interpolant_argmin, static_argnums=1)(jnp.asarray(f(x), dtype), dtype)
    assert z.dtype == dtype and bool(inner)
    assert abs(float(z) - 0.3) < tol and float(val) == pytest.approx(1.0, abs=tol)


def test_interpolant_argmin_at_an_end():
    x = F._cheb_tables(16, 2)[0]
    z, inner, _ = F._interpolant_argmin(jnp.asarray((x - 2.0) ** 2), jnp.float64)
    assert float(z) == 1.0 and not bool(inner)
    z, inner, _ = F._interpolant_argmin(jnp.asarray(-(x**2)), jnp.float64)  # concave: the best end
    assert abs(float(z)) == 1.0 and not bool(inner)


def test_refine_search_reaches_the_profile_minimum_in_four_grids(monkeypatch):
    """The refinement's search over log sigma on a capture made with a fuller BRDF (Cook-Torrance, 1 % noise): the
    returned sigma is within the tolerance of the brute-force minimum of the profile it searched (41 values 1e-4
    apart, a quartic fit), after 4 grids of 16 values (two zooms, the Chebyshev grid, the fine grid; the 8.5-fold
    zooms alone took 8 here). Stopped after 3 grids, as the joint mu search stops it, the value it returns is the
    profile's minimum to 1e-9 (the interpolant's), where the best point of three zooms was 2.5e-4 above it."""
    obs = _capture(1.6, 0.15, 0.01, 2, "cook_torrance")
    calls = []
    search = F._refine_search
    monkeypatch.setattr(F, "_refine_search", lambda *a: calls.append(a) or search(*a))
    res = solvers.factorize(obs, 6, refine_mu=False, search_pixels=None)
    assert res.status == solvers.Status.converged and len(calls) == 1
    jt, mu, ks0, d, sigma0, lmax = calls[0][:6]
    rtol = atol = 1e-7
    ks, sigma, status, n_values, val = search(jt, mu, ks0, d, sigma0, lmax, *F._limits(200, rtol, atol))
    assert status == solvers.Status.converged and int(n_values) == 64
    assert float(sigma) == float(res.brdf.sigma)
    sp = F._source_parts(jt, mu, d)
    profile = jax.jit(lambda ts: F._profiled_sigmas(jt, sp, ts, lmax)[0])

    t_hat = float(np.log(float(sigma)))
    ts = t_hat + 1e-4 * np.arange(-20, 21)
    vals = _in_batches(lambda tp: profile(jnp.asarray(tp)), ts, 16)
    c = np.polyfit(ts - t_hat, vals, 4)
    t_ref = t_hat - c[3] / (2 * c[2])
    assert abs(t_hat - t_ref) <= atol + rtol * abs(t_ref)
    v_ref = np.polyval(c, t_ref - t_hat)
    assert float(val) == pytest.approx(v_ref, rel=1e-9)
    # stopped after the Chebyshev grid: the interpolant's minimum, not the best point evaluated
    *_, status3, n3, val3 = search(jt, mu, ks0, d, sigma0, lmax, *F._limits(3, rtol, atol))
    assert int(n3) == 48 and float(val3) == pytest.approx(v_ref, rel=1e-9)
    assert status3 == solvers.Status.max_steps_reached  # the fine grid did not run


def test_joint_mu_search_is_the_profile_minimum(monkeypatch):
    """The joint model's search over t = log(mu - 1) (`refine_mu`, the default) on a capture made with a fuller BRDF
    (GGX, 2 % noise): the returned t is the minimum of the profile it searched (each value: the blocks at that mu,
    (K_s, sigma) re-searched), found by brute force: 41 values 2e-3 apart and a quartic fit. The interpolant through
    the 9 Chebyshev points lands within 1e-5; the parabola through the best of 9 evenly spaced values, which it
    replaced, was 1e-3 to 1e-2 off on the captures measured (1.2 to 2.1 standard errors of t)."""
    import dataclasses

    obs = _capture(2.2, 0.1, 0.02, 1, "ggx")
    calls = []
    search = F._joint_mu_search
    monkeypatch.setattr(F, "_joint_mu_search", lambda *a, **k: calls.append((a, search(*a, **k))) or calls[-1][1])
    res = solvers.factorize(obs, 6, search_pixels=None)
    assert res.status == solvers.Status.converged and len(calls) == 1
    (sub, tab, lmax, t1, ks0, d, sigma0, max_steps, rtol, atol, rcond, column), (t_hat, c2, _) = calls[0]
    assert tab is not None and c2 is not None and float(res.brdf.mu) == pytest.approx(1.0 + np.exp(t_hat), rel=1e-12)

    def profile(tp):  # 9 values: their blocks in one batch, then (K_s, sigma) re-searched at each
        bl = F._mu_blocks(tab, jnp.asarray(1.0 + np.exp(tp)), lmax, rcond)
        out = []
        for k, t in enumerate(tp):
            mu = jnp.asarray(1.0 + np.exp(t))
            jt = F._joint_from_table(sub, tab, bl, mu, lmax, jnp.asarray(k, jnp.int32))
            if column is not None:
                jt = dataclasses.replace(jt, fvis=sub.fast_visibility[:, column])
            out.append(float(F._refine_search(jt, mu, ks0, d, sigma0, lmax, *F._limits(max_steps, rtol, atol))[4]))
        return np.asarray(out)

    ts = t_hat + 2e-3 * np.arange(-20, 21)
    c = np.polyfit(ts - t_hat, _in_batches(profile, ts, 9), 4)
    t_ref = t_hat - c[3] / (2 * c[2])
    assert abs(t_hat - t_ref) < 1e-5
    assert c2 == pytest.approx(2 * c[2], rel=1e-3)
