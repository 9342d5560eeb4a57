"""Derivatives of the practical model's specular image in σ and μ, and the fit's covariance from them.

`PracticalTerms.specular_unit` contracts the band table with the filter of R&H eq. 20 through a custom JVP rule
(`jaxsh._practical._filtered_bands`: the σ-derivative made from the primal values, scaled by the tangent), and
`solvers.fit_brdf` sums $J^TJ$ from the two derivatives instead of forming the Jacobian (`_gram_homogeneous`).
The references here are NumPy closed forms of eqs. 20, 22 and 23 differentiated by hand, the textbook
(unnormalized-ratio) Fresnel formula differenced centrally, and a central-difference Jacobian of the whole
residual in NumPy.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers
from solvers._brdf import _gram_homogeneous


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@pytest.fixture(scope="module")
def terms():
    rng = np.random.default_rng(21)
    n = _unit(rng.normal(size=(400, 3)) + [0.0, 0.0, 1.5])
    v = _unit(rng.normal(size=(400, 3)) + [0.0, 0.0, 2.0])
    sh = rng.normal(size=(jaxsh.num_coeffs(12), 3)) * 0.3
    sh[0] += 2.0
    fd = _unit(np.array([[0.3, 0.2, 0.9]]))
    fe = np.array([[1.5, 1.2, 0.9]])
    return jaxsh.practical_terms(n, v, slow_sh=sh, fast_directions=fd, fast_energy=fe)


def _np_fresnel(c, mu):
    """F(mu, theta)/F(mu, 0) from the textbook unpolarized dielectric formula (not jaxsh's cancellation-free form)."""
    g = np.sqrt(mu * mu + c * c - 1.0)
    f = 0.5 * (g - c) ** 2 / (g + c) ** 2 * (1.0 + ((c * (g + c) - 1.0) / (c * (g - c) + 1.0)) ** 2)
    return f / ((mu - 1.0) / (mu + 1.0)) ** 2


def _np_parts(t, sigma):
    """The bracket of eq. 24 (slow + fast, without F) and its first two σ-derivatives, NumPy, `(N, C)` each."""
    bands, th = np.asarray(t.bands), np.asarray(t.theta_h)
    fw, fe, co = np.asarray(t.fast_weight), np.asarray(t.fast_energy), np.asarray(t.cos_o)
    l = np.arange(bands.shape[-1], dtype=np.float64)
    f = np.exp(-((sigma * l) ** 2))
    slow = bands @ f
    d_slow = bands @ (-2.0 * sigma * l**2 * f)
    dd_slow = bands @ ((4.0 * sigma**2 * l**4 - 2.0 * l**2) * f)
    e = np.exp(-((th / sigma) ** 2)) / (np.pi * sigma**2) * fw  # eq. 23
    a = 2.0 * th**2 / sigma**3 - 2.0 / sigma  # d log e / d sigma
    da = -6.0 * th**2 / sigma**4 + 2.0 / sigma**2
    inv = 1.0 / (4.0 * co)[:, None]
    fast, d_fast, dd_fast = (e @ fe) * inv, ((e * a) @ fe) * inv, ((e * (a * a + da)) @ fe) * inv
    vis = np.asarray(t.visible)[:, None]
    return [np.where(vis, x, 0.0) for x in (slow + fast, d_slow + d_fast, dd_slow + dd_fast)]


MU, SIGMA = 1.7, 0.13


def test_specular_unit_sigma_derivatives_match_the_closed_form(terms):
    br, d_br, dd_br = _np_parts(terms, SIGMA)
    f = _np_fresnel(np.asarray(terms.cos_o), MU)[:, None]
    want, d_want, dd_want = f * br, f * d_br, f * dd_br
    assert np.abs(d_want).max() > 1.0  # the derivative the checks below see is not negligible

    def spec(m, s):
        return terms.specular_unit(m, s, check=False)

    val, jv = jax.jvp(lambda s: spec(MU, s), (SIGMA,), (1.0,))
    np.testing.assert_allclose(np.asarray(val), want, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(jv), d_want, rtol=1e-9, atol=1e-10)
    # reverse mode (the transpose of the rule's tangent), and the checked path
    wts = np.random.default_rng(3).normal(size=want.shape)
    g = jax.grad(lambda s: jnp.sum(wts * terms.specular_unit(MU, s)))(SIGMA)
    assert float(g) == pytest.approx(float(np.sum(wts * d_want)), rel=1e-9)
    # second derivative: the rule is itself differentiable
    h = jax.grad(jax.grad(lambda s: jnp.sum(wts * spec(MU, s))))(SIGMA)
    assert float(h) == pytest.approx(float(np.sum(wts * dd_want)), rel=1e-8)
    # several tangents at once (vmap of jvp: the fits' Jacobians), mu and sigma; the mu column against the
    # textbook Fresnel differenced centrally
    eye = jnp.eye(2)
    _, tang = jax.vmap(lambda e: jax.jvp(spec, (MU, SIGMA), (e[0], e[1])), out_axes=(None, 0))(eye)
    hmu = 1e-6
    d_mu = (_np_fresnel(np.asarray(terms.cos_o), MU + hmu) - _np_fresnel(np.asarray(terms.cos_o), MU - hmu)) / (2 * hmu)
    np.testing.assert_allclose(np.asarray(tang[0]), d_mu[:, None] * br, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(np.asarray(tang[1]), d_want, rtol=1e-9, atol=1e-10)
    # batched over sigma (a vmap of the primal and of its derivative)
    sig2 = jnp.asarray([SIGMA, 2 * SIGMA])
    vals = jax.vmap(lambda s: spec(MU, s))(sig2)
    ders = jax.vmap(jax.jacfwd(lambda s: spec(MU, s)))(sig2)
    for k, s in enumerate((SIGMA, 2 * SIGMA)):
        b2, db2, _ = _np_parts(terms, s)
        np.testing.assert_allclose(np.asarray(vals[k]), f * b2, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(np.asarray(ders[k]), f * db2, rtol=1e-9, atol=1e-10)


def test_specular_unit_derivative_through_the_band_table(terms):
    """A tangent of the lighting reaches the bands (a derivative through `practical_terms`), which the rule
    contracts with the filter: by linearity it is the slow term of the terms made with the tangent as lighting."""
    rng = np.random.default_rng(5)
    n = _unit(rng.normal(size=(200, 3)) + [0.0, 0.0, 1.5])
    v = _unit(rng.normal(size=(200, 3)) + [0.0, 0.0, 2.0])
    sh = rng.normal(size=(jaxsh.num_coeffs(10), 3))
    dsh = rng.normal(size=sh.shape)

    def spec(c, s):
        return jaxsh.practical_terms(n, v, slow_sh=c).specular_unit(MU, s, check=False)

    _, t_sh = jax.jvp(lambda c: spec(c, SIGMA), (jnp.asarray(sh),), (jnp.asarray(dsh),))
    np.testing.assert_allclose(np.asarray(t_sh), np.asarray(spec(jnp.asarray(dsh), SIGMA)), rtol=1e-10, atol=1e-12)
    # both tangents at once: the sum of the two (the rule adds the table's part to the sigma part)
    _, t_both = jax.jvp(spec, (jnp.asarray(sh), SIGMA), (jnp.asarray(dsh), 0.5))
    _, t_sig = jax.jvp(lambda s: spec(jnp.asarray(sh), s), (SIGMA,), (0.5,))
    np.testing.assert_allclose(np.asarray(t_both), np.asarray(t_sh + t_sig), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("fresnel", [True, False])
def test_fit_gram_matches_a_numpy_jacobian(terms, fresnel):
    """`_gram_homogeneous` against $J^TJ$ of a NumPy Jacobian of $\\sqrt{w}(K_d D + K_s S - b)$ in
    $(K_d, K_s, \\mu, \\sigma)$: columns D, S, and $K_s\\,\\partial S$ from the closed forms above."""
    rng = np.random.default_rng(9)
    w = rng.uniform(0.5, 2.0, size=terms.cos_o.shape[0])
    ks = np.array([0.3, 0.5, 0.2])
    D = np.asarray(terms.diffuse_unit())
    br, d_br, _ = _np_parts(terms, SIGMA)
    co = np.asarray(terms.cos_o)
    f = _np_fresnel(co, MU)[:, None] if fresnel else np.ones_like(co)[:, None]
    S = f * br
    h = 1e-6
    dmu = ((_np_fresnel(co, MU + h) - _np_fresnel(co, MU - h)) / (2 * h))[:, None] * br if fresnel else 0 * br
    n, c = D.shape
    J = np.zeros((n, c, 2 * c + 2))
    for k in range(c):
        J[:, k, k] = D[:, k]
        J[:, k, c + k] = S[:, k]
    J[:, :, 2 * c] = ks * dmu
    J[:, :, 2 * c + 1] = ks * f * d_br
    J *= np.sqrt(w)[:, None, None]
    J = J.reshape(n * c, -1)
    g = _gram_homogeneous(terms, jnp.asarray(D), jnp.asarray(S), jnp.asarray(ks), jnp.asarray(w),
                          jnp.asarray(MU) if fresnel else None, jnp.asarray(SIGMA), fresnel)
    want = J.T @ J
    scale = np.sqrt(np.outer(np.diag(want), np.diag(want))) + 1e-300
    assert np.abs((np.asarray(g) - want) / scale).max() < 1e-7
    if not fresnel:
        assert np.all(np.asarray(g)[2 * c] == 0) and np.all(np.asarray(g)[:, 2 * c] == 0)


def test_fit_brdf_standard_errors_match_a_finite_difference_covariance():
    """`fit_brdf`'s standard errors, $s^2 (J^TJ)^{-1}$ at its estimate, against the same formula with a central-
    difference Jacobian of the whole residual in NumPy (the model of eq. 24 from the terms' arrays, the textbook
    Fresnel), on a small noisy capture rendered by the reference renderer."""
    truth = solvers.TorranceSparrow(jnp.array([0.5, 0.4, 0.3]), jnp.array([0.3, 0.3, 0.3]), jnp.asarray(1.6),
                                    jnp.asarray(0.12))
    cap = solvers.sphere_capture(truth, size=24, noise=0.01, seed=4)
    obs = solvers.observations(cap.gbuffers, cap.images)
    res = solvers.fit_brdf(obs, cap.lighting)
    assert solvers.status_name(res.status) == "converged"
    t = solvers.practical_terms_for(obs, cap.lighting)
    b, w = np.asarray(obs.values), np.asarray(obs.weights)
    D, co = np.asarray(t.diffuse_unit()), np.asarray(t.cos_o)

    def resid(p):
        br = _np_parts(t, p[7])[0]
        return (np.sqrt(w)[:, None] * (p[:3] * D + p[3:6] * _np_fresnel(co, p[6])[:, None] * br - b)).ravel()

    p0 = np.concatenate([np.asarray(res.brdf.kd), np.asarray(res.brdf.ks),
                         [float(res.brdf.mu), float(res.brdf.sigma)]])
    J = np.empty((resid(p0).size, 8))
    for k in range(8):
        h = 1e-6 * max(abs(p0[k]), 1e-3)
        e = np.zeros(8)
        e[k] = h
        J[:, k] = (resid(p0 + e) - resid(p0 - e)) / (2 * h)
    r = resid(p0)
    nobs = float(np.sum(w > 0) * 3)
    cov = np.linalg.inv(J.T @ J) * float(r @ r) / (nobs - 8)
    se = np.sqrt(np.diag(cov))
    got = np.concatenate([np.asarray(res.std_errors.kd), np.asarray(res.std_errors.ks),
                          [float(res.std_errors.mu), float(res.std_errors.sigma)]])
    np.testing.assert_allclose(got, se, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(res.covariance)[6, 7], cov[6, 7], rtol=1e-4)
