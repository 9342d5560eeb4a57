"""Small linear-algebra kernels at extreme units and in float32 (audit, session 28). References: NumPy inverses."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import solvers
from solvers._normal_equations import covariance_from_jacobian, inverse_sym2_diag


@pytest.mark.parametrize("dt, scales", [(np.float64, (1e-200, 1e-160, 1.0, 1e160, 1e200)),
                                        (np.float32, (1e-20, 1.0, 1e20))])
def test_inverse_sym2_diag_at_extreme_units(dt, scales):
    """$a_{11}a_{22} - a_{12}^2$ under- or overflowed at 1e±160 (float64) and 1e±20 (float32): ok False."""
    a = np.array([[2.0, 0.5], [0.5, 1.0]])
    ref = np.diag(np.linalg.inv(a))
    for s in scales:
        v1, v2, ok = inverse_sym2_diag(*(jnp.asarray(x * s, dt) for x in (a[0, 0], a[0, 1], a[1, 1])))
        assert bool(ok), s
        np.testing.assert_allclose(np.array([float(v1), float(v2)]) * s, ref, rtol=1e-6 if dt == np.float32 else 1e-14)


def test_inverse_sym2_diag_keeps_the_determined_unknown():
    """A zero second row and column: the first unknown is still determined, $v_{11} = 1/a_{11}$."""
    v1, v2, ok = inverse_sym2_diag(jnp.asarray(4.0), jnp.asarray(0.0), jnp.asarray(0.0))
    assert float(v1) == 0.25 and np.isinf(float(v2)) and not bool(ok)


def test_textured_standard_errors_do_not_depend_on_the_weights_units():
    """`fit_brdf(textured="kd_ks")`'s per-texel errors went all-infinite with weights scaled by 1e±170 (and then
    every K_s was undetermined and σ's error infinite); with unit weights they are finite (median 0.0113)."""
    from tests import test_textured_audit as T

    tex = T._texture()
    obs, lights, mask, _, _ = T._capture(tex, k=6, noise=0.01, seed=2)
    ses = []
    for s in (1.0, 1e-170, 1e170):
        o = eqx.tree_at(lambda o: o.weights, obs, obs.weights * s)
        r = solvers.fit_brdf(o, lights, textured="kd_ks", fresnel=False)
        se = np.asarray(r.std_errors.kd).reshape(T.N, T.N, 3)[mask]
        assert np.all(np.isfinite(se)), s
        ses.append((se, float(r.std_errors.sigma)))
    for se, ss in ses[1:]:
        np.testing.assert_allclose(se, ses[0][0], rtol=1e-6)
        assert ss == pytest.approx(ses[0][1], rel=1e-6)


def test_float32_covariance_does_not_flag_correlated_determined_parameters():
    """Beside an exactly dependent pair, float32 flagged the determined but correlated parameters 2 and 3
    undetermined in 38 of 40 draws at correlation 0.995 (an amplitude threshold of 1e-6 below the eigenvectors'
    float32 rounding); float64 never did. The dependent ones must still be flagged."""
    rng = np.random.default_rng(2)
    f = jax.jit(covariance_from_jacobian)
    flagged_det = flagged_dep = 0
    for _ in range(20):
        j = rng.normal(size=(400, 5))
        j[:, 4] = j[:, 0] - 2 * j[:, 1]
        j[:, 3] = j[:, 2] + 0.1 * rng.normal(size=400)
        _, se = f(jnp.asarray(j, jnp.float32), jnp.asarray(1.0, jnp.float32), 400.0, 5)
        se = np.asarray(se)
        flagged_det += bool(np.any(np.isinf(se[2:4])))
        flagged_dep += bool(np.all(np.isinf(se[[0, 1, 4]])))
    assert flagged_det == 0 and flagged_dep == 20


def test_check_float_refuses_bools_and_strings():
    from solvers._results import check_float

    for v in (True, np.bool_(False), "0.5", b"1"):
        with pytest.raises(ValueError, match="`rtol`"):
            check_float(v, "rtol")
    assert check_float(np.float32(0.5), "rtol") == 0.5


@pytest.mark.parametrize("dt, span", [(np.float64, 12.0), (np.float32, 6.0)])
def test_solve_spd_small_at_unknowns_of_very_different_scales(dt, span):
    """A 10x10 SPD system whose diagonal spans 10^±span (an unknown in other units than the rest, as the source's
    energy beside the lighting's coefficients): the jitter was 16 eps times the largest diagonal entry and
    swamped the smallest unknowns' (x off in its first digit); solved Jacobi-scaled it matches NumPy's solve
    to the scaled system's condition. Batched, with an exactly singular (zero) row that stays finite."""
    from solvers._normal_equations import inverse_spd_small, solve_spd_small

    rng = np.random.default_rng(7)
    q = rng.normal(size=(3, 10, 10))
    c = q @ np.swapaxes(q, -1, -2) + 10 * np.eye(10)  # well conditioned in its own units
    d = 10.0 ** np.linspace(-span, span, 10) / 2  # diagonal entries d^2: 10^(-2 span) .. 10^(2 span), over 4
    m = c * d[:, None] * d[None, :]
    x_true = rng.normal(size=(3, 10)) / d
    r = np.einsum("bij,bj->bi", m, x_true)
    x = np.asarray(solve_spd_small(jnp.asarray(m, dt), jnp.asarray(r, dt)))
    tol = 1e-10 if dt == np.float64 else 2e-3
    np.testing.assert_allclose(x * d, x_true * d, rtol=0, atol=tol * np.max(np.abs(x_true * d)))
    inv = np.asarray(inverse_spd_small(jnp.asarray(m[0], dt)))
    ref = np.linalg.inv(m[0])
    np.testing.assert_allclose(inv * d[:, None] * d[None, :], ref * d[:, None] * d[None, :], rtol=0,
                               atol=tol * np.max(np.abs(ref * d[:, None] * d[None, :])))
    sing = m[0].copy()
    sing[4, :] = sing[:, 4] = 0.0
    rs = r[0].copy()
    rs[4] = 0.0
    xs = np.asarray(solve_spd_small(jnp.asarray(sing, dt), jnp.asarray(rs, dt)))
    assert np.all(np.isfinite(xs)) and xs[4] == 0.0
