"""Degenerate data (issue 12): every solver returns a `Status` and a finite `rel_rms`, never an exception.

Too few samples, duplicate or affinely degenerate points for the RBF fits
(`fit_sharing` and the reflectance-sharing models through it), all-zero
lighting for `fit_brdf` / `fit_brdf_sh` (`no_signal`), an all-zero BRDF for
inverse lighting (`no_signal`) and a Lambertian BRDF ($K_s = 0$) for the dual
method (`ill_conditioned`, the $l \\le 2$ fallback). Expected values are closed
forms (an affine function, the mean of duplicate samples) or the known
lighting that rendered the images. Bad shapes and options (a `ValueError`)
are in tests/test_bad_input_solvers.py.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers

from .helpers import hemisphere_normals as _hemisphere


def _ok(res, expected=None):
    """The result carries a `Status`, finite `rms` and `rel_rms`; returns the status name."""
    assert isinstance(res.status, solvers.Status)
    name = res.status_name
    if expected is not None:
        assert name == expected, name
    assert np.isfinite(float(res.rms)) and np.isfinite(float(res.rel_rms)), (name, res.rms, res.rel_rms)
    return name


def _affine(p):
    return 0.7 + p @ np.array([0.5, -0.2, 0.3])[: p.shape[1]]


# --------------------------------------------------------------------------- fit_sharing


@pytest.mark.parametrize("n", [1, 2, 3])
def test_fit_sharing_too_few_samples(n):
    """N < d + 1: the minimum-norm affine fit, exact at the samples (an affine function through <= d + 1 points)."""
    p = np.random.default_rng(n).uniform(size=(n, 3))
    y = _affine(p) + np.random.default_rng(9).normal(size=n)  # any values: n <= d + 1 points are interpolated
    fit = solvers.fit_sharing(p, y, 4)
    _ok(fit, "ill_conditioned")
    np.testing.assert_allclose(np.asarray(fit(p)), y, atol=1e-12)
    assert float(fit.rms) < 1e-12
    with pytest.raises(solvers.SolveError, match="ill_conditioned"):
        solvers.fit_sharing(p, y, 4, throw=True)


def test_fit_sharing_one_sample_is_a_constant():
    p = np.array([[0.2, 0.4, 0.6]])
    fit = solvers.fit_sharing(p, np.array([[1.5, -2.0]]), 4)
    _ok(fit, "ill_conditioned")
    q = np.random.default_rng(0).uniform(size=(5, 3))
    np.testing.assert_allclose(np.asarray(fit(q)), np.tile([1.5, -2.0], (5, 1)), atol=1e-12)


@pytest.mark.parametrize("kind", ["constant_w", "coplanar"])
def test_fit_sharing_affinely_degenerate(kind):
    """A constant coordinate (one image) or coplanar points: the affine LSQ fit reproduces an affine function."""
    rng = np.random.default_rng(1)
    p = rng.uniform(size=(30, 3))
    if kind == "constant_w":
        p[:, 2] = 0.5
    else:
        p[:, 2] = 0.3 * p[:, 0] - 0.2 * p[:, 1]
    y = _affine(p)
    fit = solvers.fit_sharing(p, y, 30)
    _ok(fit, "ill_conditioned")
    assert float(fit.rel_rms) < 1e-12
    q = rng.uniform(size=(6, 3))
    q[:, 2] = 0.5 if kind == "constant_w" else 0.3 * q[:, 0] - 0.2 * q[:, 1]  # on the samples' hull
    np.testing.assert_allclose(np.asarray(fit(q)), _affine(q), atol=1e-12)
    _ok(solvers.fit_sharing(p, y, 10), "ill_conditioned")  # greedy budget: the same fallback


@pytest.mark.parametrize("weighted", [False, True])
def test_fit_sharing_duplicates_are_merged(weighted):
    """Repeated points: their (weighted) mean is interpolated; rms is measured on the samples as given."""
    rng = np.random.default_rng(2)
    p = rng.uniform(size=(20, 3))
    y = np.sin(3 * p[:, 0]) + p[:, 1]
    dup = np.concatenate([p, p[:2]])
    yd = np.concatenate([y, y[:2] + np.array([0.2, -0.4])])
    w = np.concatenate([np.full(20, 1.0), [3.0, 1.0]]) if weighted else np.ones(22)
    fit = solvers.fit_sharing(dup, yd, 22, weights=w if weighted else None)
    _ok(fit, "ill_conditioned")
    assert int(fit.stats["n_merged"]) == 2
    # closed form: the merged value at a repeated point is the weighted mean of its samples
    want = (w[:2] * y[:2] + w[20:] * yd[20:]) / (w[:2] + w[20:])
    np.testing.assert_allclose(np.asarray(fit(p[:2])), want, atol=1e-9)
    np.testing.assert_allclose(np.asarray(fit(p[2:])), y[2:], atol=1e-9)  # the others are interpolated
    r = (yd - np.concatenate([np.asarray(fit(p)), want])) * w
    np.testing.assert_allclose(float(fit.rms), np.sqrt(np.sum(r * r) / 22), rtol=1e-9)
    assert np.all(np.asarray(fit.center_index) < 22)


def test_fit_sharing_all_points_equal():
    p = np.tile([[0.1, 0.2, 0.3]], (6, 1))
    v = np.arange(6.0)
    fit = solvers.fit_sharing(p, v, 4)
    _ok(fit, "ill_conditioned")
    np.testing.assert_allclose(float(fit(p[0])), v.mean(), atol=1e-12)


def test_sharing_models_on_degenerate_samples():
    """One image (constant w), a few pixels: a status from every model, never an exception."""
    normal, mask = _hemisphere()
    img = np.ones((1,) + mask.shape + (3,))
    one = solvers.reflectance_samples(img, normal, [0.0, 0.0, 1.0], [[0.0, 0.0, 1.0]], mask=mask)
    assert _ok(solvers.fit_homogeneous(one, 8)) == "ill_conditioned"
    xy = np.stack(np.meshgrid(np.linspace(0, 1, 8), np.linspace(0, 1, 8)), -1)
    one_xy = solvers.reflectance_samples(img, normal, [0.0, 0.0, 1.0], [[0.0, 0.0, 1.0]], mask=mask, xy=xy)
    assert _ok(solvers.fit_sbrdf(one_xy, 8)) == "ill_conditioned"
    few = np.zeros_like(mask)
    few[3, 3:5] = True  # two pixels
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])
    imgs = np.ones((3,) + mask.shape + (3,))
    res = solvers.fit_dichromatic(imgs, imgs, np.ones((3, 3)), normal, [0.0, 0.0, 1.0], lights, xy, 6, 6, mask=few)
    _ok(res, "ill_conditioned")
    res = solvers.fit_one_image(imgs[0], imgs[0], np.ones(3), normal, [0.0, 0.0, 1.0], lights[1], xy, 6, mask=few)
    _ok(res, "ill_conditioned")


def test_reflectance_samples_without_samples_is_a_named_error():
    """A data builder, not a solver: no usable sample is a ValueError saying why (documented)."""
    normal, mask = _hemisphere()
    imgs = np.ones((1,) + mask.shape)
    with pytest.raises(ValueError, match="no usable samples"):
        solvers.reflectance_samples(imgs, normal, [0.0, 0.0, 1.0], [[0.0, 0.0, -1.0]], mask=mask)  # light behind


# --------------------------------------------------------------------------- zero lighting, zero BRDF, Lambertian


@pytest.fixture(scope="module")
def gbs():
    cams = solvers.view_cameras(2, 8)
    return [jaxsh.sphere_gbuffer(c, jnp.zeros(3), jnp.asarray(1.0)) for c in cams]


@pytest.fixture(scope="module")
def ones_obs(gbs):
    return solvers.observations(gbs, [np.ones(np.asarray(g.mask).shape + (3,)) for g in gbs])


def test_fit_brdf_zero_lighting_is_no_signal(ones_obs):
    _ok(solvers.fit_brdf(ones_obs, jaxsh.Lighting(np.zeros((9, 3))), max_steps=10), "no_signal")
    one_dark = np.eye(9, 3) * [1.0, 1.0, 0.0]  # channel 2 unlit
    _ok(solvers.fit_brdf(ones_obs, jaxsh.Lighting(one_dark), max_steps=10), "no_signal")


def test_fit_brdf_sh_overflowing_float32_data_is_not_converged(gbs):
    """float32 images of 1e20: the residual's sum of squares overflows (docs/conventions.md, the float32 range);
    the status was `converged` with rms inf and rel_rms NaN, and is `nonfinite` now. The same data at 1 converge."""
    for scale, want in ((1.0, "converged"), (1e20, "nonfinite")):
        imgs = [np.full(np.asarray(g.mask).shape + (3,), scale, np.float32) for g in gbs]
        obs = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a,
                                     solvers.observations(gbs, imgs))
        res = solvers.fit_brdf_sh(obs, np.eye(9, 3, dtype=np.float32) + 1, 2)
        assert res.status_name == want, (scale, res.status_name, res.rms)


def test_fit_brdf_sh_zero_lighting_is_no_signal(ones_obs):
    _ok(solvers.fit_brdf_sh(ones_obs, np.zeros((9, 3)), 2), "no_signal")
    _ok(solvers.fit_brdf_sh(ones_obs, jaxsh.Lighting(np.zeros((9, 3))), 2), "no_signal")


@pytest.mark.parametrize("solver", ["inverse_lighting", "inverse_lighting_dual"])
def test_inverse_lighting_zero_brdf_is_no_signal(ones_obs, solver):
    zero = solvers.TorranceSparrow(np.zeros(3), np.zeros(3), 1.5, 0.2)
    res = solvers.inverse_lighting(ones_obs, zero, 2) if solver == "inverse_lighting" else \
        solvers.inverse_lighting_dual(ones_obs, zero, 8, maxiter=10)
    _ok(res, "no_signal")


@pytest.fixture(scope="module")
def lambertian_capture(gbs):
    rng = np.random.default_rng(3)
    sh = rng.normal(size=(9, 3)) * 0.2
    sh[0] = 1.0
    brdf = solvers.TorranceSparrow(np.array([0.6, 0.45, 0.3]), np.zeros(3), 1.6, 0.2)
    imgs = [solvers.predict(brdf, jaxsh.Lighting(sh), g.normal, g.view, mask=g.mask) for g in gbs]
    return solvers.observations(gbs, imgs), brdf, sh


def test_inverse_lighting_dual_lambertian(lambertian_capture):
    """K_s = 0: no exception; `coeffs9` is the l <= 2 lighting that rendered the images, status ill_conditioned."""
    obs, brdf, sh = lambertian_capture
    res = solvers.inverse_lighting_dual(obs, brdf, 8, nonneg=False)
    _ok(res, "ill_conditioned")
    np.testing.assert_allclose(np.asarray(res.coeffs9), sh, atol=1e-9)
    assert not np.asarray(res.covered).any()
    # the image is the l <= 2 field of coeffs9 (independently: SH synthesis at the texel directions)
    dirs = jaxsh.latlong_directions(8, 16).reshape(-1, 3)
    field = np.asarray(jaxsh.real_sh(dirs, 2)) @ sh
    np.testing.assert_allclose(np.asarray(res.image).reshape(-1, 3), field, atol=1e-9)
    with pytest.raises(solvers.SolveError, match="ill_conditioned"):
        solvers.inverse_lighting_dual(obs, brdf, 8, nonneg=False, throw=True)


def test_inverse_lighting_dual_one_lambertian_channel(lambertian_capture, gbs):
    """K_s = 0 in one channel only: that channel takes the diffuse fallback, the others the dual method."""
    _, _, sh = lambertian_capture
    brdf = solvers.TorranceSparrow(np.array([0.6, 0.45, 0.3]), np.array([0.3, 0.0, 0.3]), 1.6, 0.2)
    imgs = [solvers.predict(brdf, jaxsh.Lighting(sh), g.normal, g.view, mask=g.mask) for g in gbs]
    obs = solvers.observations(gbs, imgs)
    res = solvers.inverse_lighting_dual(obs, brdf, 8, nonneg=False)
    _ok(res, "ill_conditioned")
    np.testing.assert_allclose(np.asarray(res.coeffs9)[:, 1], sh[:, 1], atol=1e-9)
    assert np.asarray(res.covered).any()
    assert np.all(np.isfinite(np.asarray(res.image)))


def test_min_norm_two_by_two_solve_against_numpy_pinv(rng):
    # fit_brdf's homogeneous inner (K_d, K_s) solve: Cramer where regular, A^+ r = A r / tr(A)^2 where singular
    from solvers._normal_equations import solve_sym2_min_norm

    u = rng.normal(size=(5, 2))
    cases = [np.outer(x, x) * s for x, s in zip(u, [1.0, 3.0, 0.2, 1.0, 1.0])]  # rank 1
    cases += [np.diag([2.0, 0.0]), np.zeros((2, 2)), np.array([[2.0, 0.5], [0.5, 1.0]])]  # one-sided, zero, regular
    a = np.stack(cases)
    r = rng.normal(size=(len(cases), 2))
    x1, x2, bad = solve_sym2_min_norm(*(jnp.asarray(v) for v in (a[:, 0, 0], a[:, 0, 1], a[:, 1, 1], r[:, 0], r[:, 1])))
    want = np.stack([np.linalg.pinv(m) @ v for m, v in zip(a, r)])
    np.testing.assert_allclose(np.stack([x1, x2], 1), want, rtol=1e-9, atol=1e-12)
    assert np.asarray(bad).tolist() == [True] * 7 + [False]


def test_two_by_two_solve_does_not_depend_on_the_units_of_the_weights(rng):
    """`solve_sym2` in its Jacobi-scaled form: systems scaled by 1e-200 .. 1e200 (float64) give the same solution as
    NumPy's solve of the unscaled system; the plain Cramer determinant under- or overflowed there (NaN kd)."""
    from solvers._normal_equations import solve_sym2, solve_sym2_min_norm

    a = np.array([[2.0, 0.5], [0.5, 1.0]])
    r = rng.normal(size=2)
    want = np.linalg.solve(a, r)
    for s in (1e-200, 1e-100, 1.0, 1e100, 1e200):
        for f in (solve_sym2, solve_sym2_min_norm):
            x1, x2, bad = f(*(jnp.asarray(v) for v in (s * a[0, 0], s * a[0, 1], s * a[1, 1], s * r[0], s * r[1])))
            np.testing.assert_allclose([float(x1), float(x2)], want, rtol=1e-12)
            assert not bool(bad)
    u = rng.normal(size=2)  # rank 1: the minimum-norm solution, also at extreme scales
    for s in (1e-200, 1.0, 1e200):
        m = np.outer(u, u) * s
        x1, x2, _ = solve_sym2_min_norm(*(jnp.asarray(v) for v in (m[0, 0], m[0, 1], m[1, 1], s * r[0], s * r[1])))
        np.testing.assert_allclose([float(x1), float(x2)], np.linalg.pinv(np.outer(u, u)) @ r, rtol=1e-10)


def test_nonnegative_two_by_two_against_scipy_nnls(rng):
    """`nonneg_sym2` (fit_brdf's kd, ks >= 0) equals `scipy.optimize.nnls` on random design matrices, many of
    whose unconstrained solutions have a negative component."""
    from scipy.optimize import nnls

    from solvers._normal_equations import nonneg_sym2, solve_sym2_min_norm

    n_neg = 0
    for _ in range(200):
        m = rng.normal(size=(6, 2))
        b = rng.normal(size=6)
        a = m.T @ m
        r = m.T @ b
        x1, x2, _ = solve_sym2_min_norm(*(jnp.asarray(v) for v in (a[0, 0], a[0, 1], a[1, 1], r[0], r[1])))
        n_neg += bool(x1 < 0) | bool(x2 < 0)
        y1, y2 = nonneg_sym2(x1, x2, *(jnp.asarray(v) for v in (a[0, 0], a[1, 1], r[0], r[1])))
        np.testing.assert_allclose([float(y1), float(y2)], nnls(m, b)[0], atol=1e-12)
    assert n_neg > 50


def test_fit_brdf_never_returns_a_negative_albedo(gbs, lambertian_capture):
    """Negated or offset images: the unconstrained inner solve gave kd, ks < 0 with status `converged` (a
    `TorranceSparrow` its own constructor refuses). The fit is now the best nonnegative one: negated images give
    kd = ks = 0 (relative RMS 1); an offset makes the fit worse, never negative."""
    obs, _, sh = lambertian_capture
    neg = eqx.tree_at(lambda o: o.values, obs, -obs.values)
    res = solvers.fit_brdf(neg, jaxsh.Lighting(sh))
    _ok(res)
    assert np.all(np.asarray(res.brdf.kd) == 0) and np.all(np.asarray(res.brdf.ks) == 0)
    np.testing.assert_allclose(float(res.rel_rms), 1.0, rtol=1e-12)
    off = eqx.tree_at(lambda o: o.values, obs, obs.values - 0.5 * jnp.max(obs.values))
    res = solvers.fit_brdf(off, jaxsh.Lighting(sh))
    _ok(res)
    assert np.all(np.asarray(res.brdf.kd) >= 0) and np.all(np.asarray(res.brdf.ks) >= 0)
    solvers.TorranceSparrow(res.brdf.kd, res.brdf.ks, res.brdf.mu, res.brdf.sigma)  # a valid BRDF


def test_fit_brdf_does_not_depend_on_the_units_of_the_weights(lambertian_capture):
    """Uniform weights of 1e-200 or 1e200 (float64) give the fit of unit weights; they gave NaN kd before."""
    obs, brdf, sh = lambertian_capture
    ref = solvers.fit_brdf(obs, jaxsh.Lighting(sh))
    for s in (1e-200, 1e200):
        res = solvers.fit_brdf(eqx.tree_at(lambda o: o.weights, obs, obs.weights * s), jaxsh.Lighting(sh))
        _ok(res, ref.status_name)
        np.testing.assert_allclose(np.asarray(res.brdf.kd), np.asarray(ref.brdf.kd), rtol=1e-9)
        np.testing.assert_allclose(float(res.rel_rms), float(ref.rel_rms), rtol=1e-6, atol=1e-12)


def test_fit_brdf_status_does_not_depend_on_the_radiometric_units(lambertian_capture):
    """Noise-free images (sky and sun) in units 1e-30 .. 1e30 (float64): the same status and estimate (the
    simplex's path may differ by rounding). Its absolute tolerance was applied to the RSS in the data's units, so at 1e30 it
    stopped at `max_steps_reached`."""
    _, _, sh = lambertian_capture
    d, e = np.array([[0.3, 0.4, 0.87]]) / np.linalg.norm([0.3, 0.4, 0.87]), np.full((1, 3), 2.0)
    brdf = solvers.TorranceSparrow(np.array([0.6, 0.45, 0.3]), np.full(3, 0.3), 1.6, 0.2)
    gbs = [jaxsh.sphere_gbuffer(c, jnp.zeros(3), jnp.asarray(1.0)) for c in solvers.view_cameras(2, 16)]
    light = lambda s: jaxsh.Lighting(sh * s, d, e * s)  # noqa: E731
    obs = solvers.observations(gbs, [solvers.predict(brdf, light(1.0), g.normal, g.view, mask=g.mask) for g in gbs])
    ref = solvers.fit_brdf(obs, light(1.0))
    assert ref.status_name == "converged" and abs(float(ref.brdf.sigma) - 0.2) < 1e-6
    for s in (1e-30, 1e30):
        res = solvers.fit_brdf(eqx.tree_at(lambda o: o.values, obs, obs.values * s), light(s))
        _ok(res, ref.status_name)
        assert int(res.iterations) < 200
        np.testing.assert_allclose(np.asarray(res.brdf.kd), np.asarray(ref.brdf.kd), rtol=1e-9)
        np.testing.assert_allclose(float(res.brdf.sigma), float(ref.brdf.sigma), rtol=1e-9)


def test_small_spd_solve_against_numpy(rng):
    # the Schur complements' elimination (`solve_spd_small`, plain XLA ops inside the searches), batched, in both
    # dtypes, against LAPACK; a singular system stays finite (the 16 eps diagonal jitter)
    from solvers._normal_equations import inverse_spd_small, solve_spd_small

    for dt, tol in ((np.float64, 1e-10), (np.float32, 2e-3)):
        g = rng.normal(size=(4, 3, 10, 10))
        m = (g @ np.swapaxes(g, -1, -2) + 0.1 * np.eye(10)).astype(dt)
        r = rng.normal(size=(4, 3, 10)).astype(dt)
        x = np.asarray(solve_spd_small(jnp.asarray(m), jnp.asarray(r)))
        assert x.dtype == dt
        want = np.linalg.solve(m.astype(np.float64), r.astype(np.float64)[..., None])[..., 0]
        assert np.max(np.abs(x - want)) <= tol * np.max(np.abs(want))
        np.testing.assert_allclose(np.asarray(inverse_spd_small(jnp.asarray(m[0, 0]))), np.linalg.inv(m[0, 0]),
                                   rtol=tol * 10, atol=tol * np.max(np.abs(np.linalg.inv(m[0, 0]))))
    u = rng.normal(size=(9, 1))
    sing = jnp.asarray(u @ u.T)  # rank 1
    assert np.all(np.isfinite(np.asarray(solve_spd_small(sing, jnp.ones(9)))))
