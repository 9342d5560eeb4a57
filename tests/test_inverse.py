"""Inverse rendering (R&H 2001 sec. 6): BRDF, lighting, factorization, textures and shadows.

The captures are rendered by `jaxsh.render_reference` (the full Torrance-Sparrow
BRDF integrated over the disk sources by quadrature, the directional source
exactly), not by the practical model the solvers fit, so the recovery
tolerances below include the model error of eq. 24 (~1 % RMS on these spheres).
"""

import dataclasses
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers
from solvers._factorize_dual import _dual_moments, _dual_rss_one
from tests.helpers import quadrature_images

TRUTH = solvers.TorranceSparrow(jnp.array([0.6, 0.45, 0.3]), jnp.array([0.3, 0.3, 0.3]), jnp.asarray(1.6), jnp.asarray(0.1))
SIZE = 64


def _noisy(cap, noise, seed=1):
    rng = np.random.default_rng(seed)
    out = []
    for img, gb in zip(cap.clean, cap.gbuffers):
        m = np.asarray(gb.mask)
        x = img.copy()
        x[m] += noise * np.sqrt(np.mean(img[m] ** 2)) * rng.standard_normal(x[m].shape)
        out.append(x)
    return out


@pytest.fixture(scope="module")
def capture():
    return solvers.sphere_capture(TRUTH, size=SIZE, noise=0.0)


@pytest.fixture(scope="module")
def obs_clean(capture):
    return solvers.observations(capture.gbuffers, capture.clean)


@pytest.fixture(scope="module")
def obs_noisy(capture):
    return solvers.observations(capture.gbuffers, _noisy(capture, 0.01))


def _rel(a, b):
    return abs(float(a) - float(b)) / abs(float(b))


# --------------------------------------------------------------------------- the factored model


def test_practical_terms_equal_render_practical(rng):
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(500, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    sh = rng.normal(size=(jaxsh.num_coeffs(8), 3))
    fd = np.array([[0.0, 0.6, 0.8], [0.6, 0.0, 0.8]])
    fe = rng.uniform(size=(2, 3))
    vis = dict(transfer=rng.normal(size=(500, 9)), fast_visibility=rng.uniform(size=(500, 2)),
               reflected_visibility=rng.uniform(size=500))
    kd = rng.uniform(size=(500, 3))  # a texture
    ks = np.array([0.2, 0.3, 0.1])
    for kw in ({}, vis):
        terms = jaxsh.practical_terms(n, v, slow_sh=sh, fast_directions=fd, fast_energy=fe, **kw)
        a = terms(kd, ks, 1.5, 0.12)
        b = jaxsh.render_practical(n, v, kd, ks, 1.5, 0.12, slow_sh=sh, fast_directions=fd, fast_energy=fe, **kw).total
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="transfer"):
        jaxsh.practical_terms(n, v, slow_sh=sh, transfer=np.zeros((3, 9)))


# --------------------------------------------------------------------------- inverse BRDF (sec. 6.1)


def _check_brdf(res, truth, tol):
    kd, ks = np.asarray(res.brdf.kd), np.asarray(res.brdf.ks)
    np.testing.assert_allclose(kd, np.asarray(truth.kd), rtol=tol["kd"])
    np.testing.assert_allclose(ks, np.asarray(truth.ks), rtol=tol["ks"])
    assert _rel(res.brdf.sigma, truth.sigma) < tol["sigma"]
    assert _rel(res.brdf.mu, truth.mu) < tol["mu"]


TOL = {"kd": 0.02, "ks": 0.02, "sigma": 0.05, "mu": 0.10}


def test_fit_brdf_known_lighting_noise_free(capture, obs_clean):
    res = solvers.fit_brdf(obs_clean, capture.lighting)
    assert solvers.status_name(res.status) == "converged"
    _check_brdf(res, TRUTH, TOL)
    assert float(res.rel_rms) < 0.03  # the practical model's error against the reference renderer
    assert np.all(np.isfinite(np.asarray(res.std_errors.kd)))


def test_fit_brdf_known_lighting_one_percent_noise(capture, obs_noisy):
    res = solvers.fit_brdf(obs_noisy, capture.lighting)
    assert solvers.status_name(res.status) == "converged"
    _check_brdf(res, TRUTH, {k: 2 * v for k, v in TOL.items()})
    # noise raises the residual by about the noise level, in quadrature
    assert 0.005 < float(res.rel_rms) < 0.04


def test_fit_brdf_search_on_a_subset_ends_at_the_all_sample_optimum(capture, obs_noisy):
    # The grid and the simplex on 1,500 of the ~8,000 samples, LM on all of them: the same optimum as a search on
    # every sample, to the stopping tolerance (1e-8) -- not the subset's own optimum, which differs by ~1e-3
    full = solvers.fit_brdf(obs_noisy, capture.lighting, search_pixels=None)
    sub = solvers.fit_brdf(obs_noisy, capture.lighting, search_pixels=1500)
    only_sub = solvers.fit_brdf(obs_noisy, capture.lighting, search_pixels=1500, refine=False)
    n_pos = int(np.sum(np.asarray(obs_noisy.weights) > 0))
    assert int(full.stats["search_pixels"]) == n_pos and int(sub.stats["search_pixels"]) == 1500
    assert int(only_sub.stats["search_pixels"]) == n_pos  # without the LM over all samples: no subset
    assert solvers.status_name(sub.status) == solvers.status_name(full.status) == "converged"
    for a, b in ((sub.brdf.kd, full.brdf.kd), (sub.brdf.ks, full.brdf.ks), (sub.brdf.mu, full.brdf.mu),
                 (sub.brdf.sigma, full.brdf.sigma), (sub.std_errors.sigma, full.std_errors.sigma)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6)
    # the subset's own simplex optimum is measurably elsewhere: the check above can fail
    pos = np.flatnonzero(np.asarray(obs_noisy.weights) > 0)
    small = obs_noisy.subset(pos[np.round(np.linspace(0, pos.size - 1, 1500)).astype(int)])
    alone = solvers.fit_brdf(small, capture.lighting, refine=False)
    assert abs(float(alone.brdf.sigma) - float(full.brdf.sigma)) > 1e-5


def test_fit_brdf_refines_only_after_a_search_on_a_subset(capture, obs_clean):
    """`refine=None` (default) runs Levenberg-Marquardt only when the grid and the simplex used a subset: with every
    sample (~8,000 < `search_pixels`) the simplex has minimized the very objective LM would, and the estimate equals
    the refined one to the simplex's tolerance (1e-8 on the parameters). `True` forces the refinement."""
    auto = solvers.fit_brdf(obs_clean, capture.lighting)
    forced = solvers.fit_brdf(obs_clean, capture.lighting, refine=True)
    sub = solvers.fit_brdf(obs_clean, capture.lighting, search_pixels=1500)
    assert int(auto.stats["num_steps_lm"]) == 0 and int(auto.iterations) == int(auto.stats["num_steps_simplex"])
    assert int(forced.stats["num_steps_lm"]) > 0 and int(sub.stats["num_steps_lm"]) > 0
    assert int(sub.stats["search_pixels"]) == 1500
    for r in (auto, forced, sub):
        assert solvers.status_name(r.status) == "converged"
    for a, b in ((auto.brdf.kd, forced.brdf.kd), (auto.brdf.ks, forced.brdf.ks), (auto.brdf.mu, forced.brdf.mu),
                 (auto.brdf.sigma, forced.brdf.sigma), (auto.std_errors.sigma, forced.std_errors.sigma)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6)
    for bad in ("yes", 1, 0.5):
        with pytest.raises(ValueError, match="`refine`"):
            solvers.fit_brdf(obs_clean, capture.lighting, refine=bad)


def test_fit_brdf_fitted_is_eq24_at_the_estimate(capture, obs_noisy):
    """`fitted` is the practical model at the returned estimate, sample by sample: it equals the renderer's images
    (`solvers.predict` with the exact SH sums, another program) at the object's pixels, and its weighted residual
    is `rms`."""
    res = solvers.fit_brdf(obs_noisy, capture.lighting)
    f = np.asarray(res.fitted)
    assert f.shape == obs_noisy.values.shape and f.dtype == np.float64
    for img, gb in zip(obs_noisy.to_images(f), capture.gbuffers):
        # method="exact": the SH sums, as the fit's terms (the default table interpolation is within ~1e-7)
        ref = np.asarray(solvers.predict(res.brdf, capture.lighting, gb.normal, gb.view, mask=gb.mask, method="exact"))
        m = np.asarray(gb.mask)
        np.testing.assert_allclose(img[m], ref[m], rtol=1e-10, atol=1e-13)
    w, b = np.asarray(obs_noisy.weights), np.asarray(obs_noisy.values)
    rms = np.sqrt(np.sum(w[:, None] * (f - b) ** 2) / (np.count_nonzero(w > 0) * b.shape[1]))
    np.testing.assert_allclose(rms, float(res.rms), rtol=1e-10)
    assert rms > 0.005 * np.sqrt(np.mean(b**2))  # the 1 % noise is in the residual: `fitted` is not the data


def test_fit_brdf_float32(capture, obs_clean):
    obs32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, obs_clean)
    light32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), capture.lighting)
    res = solvers.fit_brdf(obs32, light32)
    assert res.brdf.kd.dtype == jnp.float32 and res.brdf.sigma.dtype == jnp.float32
    _check_brdf(res, TRUTH, TOL)


def test_fit_brdf_float32_standard_errors_do_not_depend_on_the_image_units(capture, obs_noisy):
    """Images 1000x brighter under the same lighting: Kd, Ks and their errors scale by 1000, mu and sigma and
    theirs do not. In float32 every standard error was inf there (the unscaled J^T J's condition number grew like
    the square of the factor, `covariance_from_jacobian`)."""
    light32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), capture.lighting)
    fits = {}
    for s in (1.0, 1000.0):
        obs = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, obs_noisy)
        obs = eqx.tree_at(lambda o: o.values, obs, obs.values * jnp.float32(s))
        fits[s] = solvers.fit_brdf(obs, light32)
    one, big = fits[1.0], fits[1000.0]
    assert not any(big.stats["undetermined"].values())
    for name, f in (("kd", 1000.0), ("ks", 1000.0), ("mu", 1.0), ("sigma", 1.0)):
        a, b = np.asarray(getattr(one.std_errors, name)), np.asarray(getattr(big.std_errors, name))
        assert np.all(np.isfinite(b)), name
        np.testing.assert_allclose(b, f * a, rtol=2e-2, err_msg=name)  # float32 fits stop at ~1e-5 in log mu, sigma


def test_fit_brdf_without_fresnel_and_from_an_initial_guess(capture, obs_clean):
    res = solvers.fit_brdf(obs_clean, capture.lighting, fresnel=False, init=(1.5, 0.2))
    assert res.brdf.mu is None and res.std_errors.mu is None
    assert _rel(res.brdf.sigma, TRUTH.sigma) < 0.1  # F = 1 is a model error here (true mu = 1.6)


def test_sigma_is_ill_conditioned_under_low_frequency_lighting():
    """R&H sec. 3 / 6.3: with only an area source, blurring the lighting and sharpening the lobe
    barely change the images, so sigma's standard error grows sharply; a directional source fixes it."""
    disks, directional = solvers.default_sources()
    errs = {}
    for name, src in (("area+directional", (disks, directional)), ("area only", (disks, None))):
        cap = solvers.sphere_capture(TRUTH, size=32, noise=0.01, sources=src, disk_nodes=(32, 64))
        res = solvers.fit_brdf(solvers.observations(cap.gbuffers, cap.images), cap.lighting)
        errs[name] = float(res.std_errors.sigma) / float(res.brdf.sigma)
    assert errs["area only"] > 10 * errs["area+directional"], errs


# --------------------------------------------------------------------------- inverse lighting (sec. 6.2)


def test_inverse_lighting_is_exact_for_data_of_its_own_model(rng):
    """Eq. 25 (with the filter, deconvolve=True) recovers band-limited lighting to round-off, with shadows."""
    cap_cams = solvers.view_cameras(3, 24)
    gbs = [jaxsh.sphere_gbuffer(c, np.zeros(3), 1.0) for c in cap_cams]
    truth_sh = rng.normal(size=(jaxsh.num_coeffs(6), 3))
    per_view = []
    for gb in gbs:
        m = np.asarray(gb.mask)
        extra = dict(transfer=rng.normal(size=m.shape + (9,)), reflected_visibility=rng.uniform(0.5, 1.0, size=m.shape))
        img = np.asarray(jaxsh.render_practical(gb.normal, gb.view, TRUTH.kd, TRUTH.ks, TRUTH.mu, TRUTH.sigma,
                                                slow_sh=truth_sh, mask=gb.mask, **extra).total)
        per_view.append((img, extra))
    obs = solvers.observations(gbs, [p[0] for p in per_view], transfer=[p[1]["transfer"] for p in per_view],
                               reflected_visibility=[p[1]["reflected_visibility"] for p in per_view])
    res = solvers.inverse_lighting(obs, TRUTH, 6, deconvolve=True)
    np.testing.assert_allclose(res.coeffs, truth_sh, atol=1e-8 * np.abs(truth_sh).max())
    # the RSS comes from the normal equations (b'b - x'A'b), so its floor is sqrt(eps) ~ 1e-8, not eps
    assert float(res.rel_rms) < 1e-6
    assert np.all(np.asarray(res.supported_lmax) == 6)
    assert solvers.status_name(res.status) == "converged"


def test_inverse_lighting_from_reference_images(capture, obs_noisy):
    res = solvers.inverse_lighting(obs_noisy, TRUTH, 12)
    truth = np.asarray(jaxsh.filter_lighting_microfacet(capture.lighting.total_sh(12), TRUTH.sigma))
    rec = np.asarray(res.coeffs)
    for c in range(3):
        assert np.corrcoef(rec[:9, c], truth[:9, c])[0, 1] > 0.99
    # the whole l <= 12 filtered lighting, to the accuracy the band limit allows
    assert np.linalg.norm(rec - truth) / np.linalg.norm(truth) < 0.2
    assert np.all(np.asarray(res.supported_lmax) == 12)
    snr = np.asarray(res.band_snr)
    assert snr[0, 0] > snr[12, 0]  # higher bands are noisier


def test_inverse_lighting_lambertian_determines_only_l_le_2(obs_noisy):
    """R&H sec. 3: a Lambertian object is a low-pass filter; inverse lighting recovers l <= 2 only."""
    lamb = solvers.TorranceSparrow(TRUTH.kd, jnp.zeros(3), TRUTH.mu, TRUTH.sigma)
    res = solvers.inverse_lighting(obs_noisy, lamb, 6)
    assert np.all(np.asarray(res.supported_lmax) == 2)
    assert np.all(np.isfinite(np.asarray(res.std_errors[:9])))
    assert np.all(np.isinf(np.asarray(res.std_errors[9:])))
    assert not np.any(np.asarray(res.determined[9:]))
    assert solvers.status_name(res.status) == "ill_conditioned"
    sv = np.asarray(res.singular_values)
    assert np.all(sv[:, 9:] < 1e-6 * sv[:, :1])


# --------------------------------------------------------------------------- eq. 26 and factorization (sec. 6.3)


@pytest.mark.parametrize("sigma", [0.08, 0.15])
def test_find_source_recovers_sigma_of_a_filtered_delta(sigma):
    """A delta source filtered by exp(-(sigma l)^2) and truncated at l*=24, plus a smooth background:
    find_source locates it and eq. 26 (band-limit corrected) returns sigma."""
    d = np.array([0.3, -0.4, 0.866])
    d /= np.linalg.norm(d)
    lmax = 24
    c = jaxsh.filter_lighting_microfacet(jaxsh.directional_light_sh(d[None], np.array([[2.0, 1.0, 0.5]]), lmax), sigma)
    c = c + jaxsh.disk_light_sh(np.array([0.0, 0.0, -1.0]), 1.0, np.array([0.1, 0.1, 0.1]), lmax)
    src = solvers.find_source(c)
    assert np.arccos(np.clip(np.dot(np.asarray(src.direction), d), -1, 1)) < 0.01
    assert _rel(src.sigma, sigma) < 0.03
    np.testing.assert_allclose(np.asarray(src.energy), [2.0, 1.0, 0.5], rtol=0.1)
    # a user region (fig. 10's box) that contains the source gives the same answer
    src2 = solvers.find_source(c, region=(d + 0.05, 0.6))
    assert _rel(src2.sigma, sigma) < 0.05


def test_find_source_direction_follows_the_scene_not_the_grid():
    """The source direction of a filtered delta (l* = 12, factorize's default) plus a background: within 0.15 deg of
    the true one at 12 random directions of the upper hemisphere (the texel centroid alone: up to 0.6 deg; near the
    background disk its slope shifts the peak itself, 0.24 deg in one case), and rotating the lighting by R
    (`rotate_sh`) rotates the found direction by R to 0.01 deg (before, it moved with the lat-long grid)."""
    rng = np.random.default_rng(3)
    lmax = 12
    for _ in range(12):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        d[2] = abs(d[2])  # away from the background disk (at -z): its slope under the peak would shift it
        c = jaxsh.filter_lighting_microfacet(jaxsh.directional_light_sh(d[None], np.array([[2.0, 1.0, 0.5]]), lmax),
                                             0.15)
        c = c + jaxsh.disk_light_sh(np.array([0.0, 0.0, -1.0]), 1.0, np.array([0.1, 0.1, 0.1]), lmax)
        src = np.asarray(solvers.find_source(c).direction)
        assert np.degrees(np.arccos(np.clip(src @ d, -1, 1))) < 0.15
        R = np.asarray(jaxsh.rotation_from_euler_zyz(*rng.uniform(-np.pi, np.pi, 3)))
        src_r = np.asarray(solvers.find_source(jaxsh.rotate_sh(c, R, channels=True)).direction)
        assert np.degrees(np.arccos(np.clip(src_r @ (R @ src), -1, 1))) < 0.01


def test_eq26_model_functionals_against_legendre_quadrature(rng):
    """eq. 26's model ratio needs three linear functionals of the band-limited filtered delta
    $f_\\sigma(\\theta) = \\sum_l (2l+1)/(4\\pi) e^{-(\\sigma l)^2} P_l(\\cos\\theta)$; the bisection evaluates
    them from a precomputed (K, l* + 1) table (`_delta_moments`). Reference: f evaluated with
    `scipy.special.eval_legendre` on the grid and summed against the same weights; and the unit source's
    integral over the whole sphere is 1 (l = 0 only) whatever sigma."""
    from scipy.special import eval_legendre

    from solvers import _factorize as F

    lmax = 12
    th = np.linspace(0.0, 0.9, 3001)
    m = rng.uniform(0, 1, (3, th.size))
    l = np.arange(lmax + 1)
    fm = F._delta_moments(lmax)(jnp.asarray(m), jnp.asarray(th))
    for sigma in (0.05, 0.12, 0.6):
        f = eval_legendre(l[None, :], np.cos(th)[:, None]) @ ((2 * l + 1) / (4 * np.pi) * np.exp(-((sigma * l) ** 2)))
        np.testing.assert_allclose(np.asarray(fm(jnp.asarray(sigma))), m @ f, rtol=1e-12)
    # the whole sphere by Gauss-Legendre in cos(theta): only l = 0 survives, 4 pi * 1/(4 pi) = 1
    x, w = np.polynomial.legendre.leggauss(2 * lmax)
    full = F._delta_moments(lmax)(jnp.asarray(2 * np.pi * w[None, :]), jnp.asarray(np.arccos(x)))
    for sigma in (0.05, 0.3):
        np.testing.assert_allclose(np.asarray(full(jnp.asarray(sigma))), [1.0], rtol=1e-12)
    # the unbanded lobe (dual path): m @ exp(-theta^2 / (4 sigma^2)) / (4 pi sigma^2)
    lobe = F._lobe_moments(jnp.asarray(m), jnp.asarray(th))(jnp.asarray(0.1))
    np.testing.assert_allclose(np.asarray(lobe), m @ (np.exp(-(th**2) / 0.04) / (4 * np.pi * 0.01)), rtol=1e-12)


@pytest.fixture(scope="module")
def factorization(obs_noisy):
    return solvers.factorize(obs_noisy, 12)


def test_factorize_hessian_of_the_profiled_rss_against_autodiff(obs_noisy, factorization):
    # The standard errors of (K_s, sigma) come from a 9-point central-difference Hessian (`_profiled_hessian`);
    # the reference is the exact second derivative by autodiff through the same RSS (jax.hessian)
    from solvers import _factorize as F

    fac = factorization
    mu, ks, sigma = fac.brdf.mu, fac.brdf.ks, fac.brdf.sigma
    d = fac.lighting.fast_directions[0]
    jt = F._joint_jit(obs_noisy, None, mu, 12, 4096, 1e-12, None)
    sp = F._source_parts(jt, mu, d)
    c = ks.shape[0]
    theta = jnp.concatenate([ks, sigma[None]])
    exact = np.asarray(jax.jit(jax.hessian(lambda th: jnp.sum(F._joint_rss(jt, sp, th[:c], th[c], 12)[0])))(theta))
    fd = np.asarray(jax.jit(lambda: F._profiled_hessian(jt, sp, ks, sigma, 12)[0])())
    assert np.max(np.abs(fd - exact)) < 1e-5 * np.max(np.abs(exact))  # measured 9e-7 on a 3-view 48^2 sphere
    assert np.all(exact[:c, :c][~np.eye(c, dtype=bool)] == 0)  # the K_s block is diagonal: channels decouple
    np.testing.assert_allclose(np.diag(np.linalg.inv(fd)), np.diag(np.linalg.inv(exact)), rtol=1e-5)


@pytest.mark.parametrize("n_px", [2000, 4500])  # below one chunk of `_weighted_products`; two chunks and a tail
def test_gram_blocks_at_many_mu_by_quadrature_equal_the_direct_sums(rng, n_px):
    # `grams_at_mus` forms the specular block through the projected point set and an exact Gauss-Legendre rule;
    # the reference is the plain chunked sum over pixels (`accumulate_gram`), with transfer vectors, reflected-ray
    # visibility, zero weights and pixels seen from behind
    from solvers._normal_equations import _PRODUCT_CHUNK, accumulate_gram, grams_at_mus, mirror_table

    assert _PRODUCT_CHUNK == 2048
    lmax = 5
    n = rng.normal(size=(n_px, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(n_px, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    b, w = rng.uniform(size=(n_px, 2)), rng.uniform(size=n_px) * (rng.uniform(size=n_px) > 0.1)
    mus = jnp.asarray([1.05, 1.7, 3.5])
    direct = jax.jit(accumulate_gram, static_argnums=(8, 9))
    table = jax.jit(lambda *a: grams_at_mus(mirror_table(*a, lmax), mus, lmax))
    for transfer, rvis in [(None, None), (rng.normal(size=(n_px, 9)), rng.uniform(size=n_px))]:
        args = [jnp.asarray(a) if a is not None else None for a in (n, v, b, w, transfer, rvis)]
        grams = table(*args)
        for k in range(len(mus)):
            ref = direct(*args, mus[k], None, lmax, 512)
            for field in ("dd", "ds", "ss", "db", "sb", "bb", "count"):
                got, want = np.asarray(getattr(grams, field)[k]), np.asarray(getattr(ref, field))
                assert np.max(np.abs(got - want)) <= 1e-13 * np.max(np.abs(want)), field  # measured <= 2.4e-15


def test_golden_ks_rss_from_fixed_parts_equals_the_dense_least_squares(rng):
    # `_golden_ks` evaluates the eq.-25 RSS from K_s-independent 9x9 parts (`_golden_parts`, `_reduced_rss`);
    # the reference is the dense least-squares problem over all n coefficients, solved by NumPy: the data
    # b_i ~ K_d d_i.L + K_s s_i.(f o L), normal matrix A = M^T G M with M = [K_d I_9 0; K_s diag(f)], RSS =
    # bb - r^T A^-1 r. A general filter f (not ones) and three K_s, two channels; also the old block elimination.
    from solvers import _factorize as F
    from solvers._normal_equations import accumulate_gram, pinv_psd

    n_px, lmax = 3000, 6
    nc = (lmax + 1) ** 2
    n = rng.normal(size=(n_px, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = rng.normal(size=(n_px, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    b, w = rng.uniform(size=(n_px, 2)), rng.uniform(0.5, 1.0, size=n_px)
    g = jax.jit(accumulate_gram, static_argnums=(8, 9))(*(jnp.asarray(a) for a in (n, v, b, w)), None, None,
                                                        jnp.asarray(1.6), None, lmax, 1024)
    bl = F._Blocks(g, pinv_psd(g.ss[9:, 9:], 1e-12, half=True)[1])
    filt = jnp.asarray(np.exp(-((0.15 * jaxsh.sh_degrees(lmax)) ** 2)))
    parts = F._golden_parts(bl, filt)
    gram = np.block([[np.asarray(g.dd), np.asarray(g.ds)], [np.asarray(g.ds).T, np.asarray(g.ss)]])
    rhs = np.concatenate([np.asarray(g.db), np.asarray(g.sb)])  # (9 + n, C)
    assert np.linalg.cond(np.asarray(g.ss)) < 1e8  # well posed: the dense solve is a reference
    for ks in (0.05, 0.4, 0.93):
        kd = 1.0 - ks
        m = np.vstack([kd * np.eye(9, nc), ks * np.diag(np.asarray(filt))])
        a, r = m.T @ gram @ m, m.T @ rhs
        want = np.asarray(g.bb) - np.sum(r * np.linalg.solve(a, r), 0)
        got = np.array([float(F._reduced_rss(jax.tree_util.tree_map(lambda x: x[c], parts), jnp.asarray(ks)))
                         for c in range(2)])
        old = np.asarray(F._schur_rss(bl, jnp.full(2, kd), jnp.full(2, ks), filt)[0])
        scale = np.asarray(g.bb)
        assert np.all(want > 0.01 * scale)  # a residual, not the data: the comparison sees the fit
        assert np.max(np.abs(got - want) / scale) <= 1e-13, (ks, got, want)  # measured <= 2.0e-15
        assert np.max(np.abs(old - want) / scale) <= 1e-13, (ks, old, want)  # measured <= 1.8e-15


def test_factorize_from_the_table_equals_the_direct_sums_end_to_end(obs_noisy, monkeypatch):
    # a capture smaller than `search_pixels`: the table of all pixels serves the mu search, the final stage-1
    # blocks and the refinement's rows; the reference forms them all by direct sums. Stage 1's mu on both paths
    # (`refine_mu=False`: the joint model's mu searches of the two paths differ in their rounding)
    from solvers import _factorize as F

    assert obs_noisy.n_samples < 40000
    monkeypatch.setattr(F, "_TABLE_BYTES", 0)
    ref = solvers.factorize(obs_noisy, 12, refine_mu=False)
    monkeypatch.undo()
    new = solvers.factorize(obs_noisy, 12, refine_mu=False)
    np.testing.assert_allclose(float(new.brdf.mu), float(ref.brdf.mu), rtol=1e-9)
    # K_s: a golden search on a flat minimum whose RSS carries rounding noise ~1e-14 resolves K_s to ~1e-7 only
    # (bitwise equal on a repeat of either path); sigma to the simplex's tolerance. Measured:
    # mu 3.6e-12, K_s 7e-8, sigma 2.1e-8, slow lighting 2.0e-7 (of its largest coefficient), source energy 8e-8
    np.testing.assert_allclose(np.asarray(new.brdf.ks), np.asarray(ref.brdf.ks), rtol=1e-6)
    np.testing.assert_allclose(float(new.brdf.sigma), float(ref.brdf.sigma), rtol=1e-5)
    slow, slow_ref = np.asarray(new.lighting.slow_sh), np.asarray(ref.lighting.slow_sh)
    assert np.max(np.abs(slow - slow_ref)) <= 1e-4 * np.max(np.abs(slow_ref))
    np.testing.assert_allclose(np.asarray(new.lighting.fast_energy), np.asarray(ref.lighting.fast_energy), rtol=1e-4)


def test_factorize_subset_draw_is_numpy_seeded_by_the_key(obs_noisy):
    # `factorize` draws its search subset on the host: NumPy's `default_rng` seeded with the key's data (what
    # `benchmarks/bench_inverse.py`'s scipy baseline draws), the same for a raw and a typed key, different for
    # another key; `Observations.subset` gathers every field at the drawn indices
    from solvers import _factorize as F

    key = jax.random.PRNGKey(7)
    n = obs_noisy.n_samples
    got = F._draw_without_replacement(key, n, 500)
    seed = np.asarray(key).astype(np.uint32).tolist()
    np.testing.assert_array_equal(got, np.random.default_rng(seed).choice(n, 500, replace=False))
    np.testing.assert_array_equal(F._draw_without_replacement(jax.random.wrap_key_data(key), n, 500), got)
    assert not np.array_equal(F._draw_without_replacement(jax.random.PRNGKey(8), n, 500), got)
    assert np.unique(got).size == 500 and got.min() >= 0 and got.max() < n
    idx = np.sort(got)
    sub = obs_noisy.subset(idx)
    for name in ("normals", "views", "values", "weights", "view_index", "pixel_index"):
        np.testing.assert_array_equal(np.asarray(getattr(sub, name)), np.asarray(getattr(obs_noisy, name))[idx])
    assert sub.transfer is None and sub.image_shapes == obs_noisy.image_shapes


def test_factorize_mu_search_from_the_table_equals_the_direct_search(obs_noisy):
    # the stage-1 objective at each mu candidate is the same whether its blocks come from the subset's table
    # (default) or from `accumulate_gram` per candidate (the path above `_TABLE_BYTES`; end to end: the test above)
    from solvers import _factorize as F

    sub = obs_noisy.subset(np.arange(0, obs_noisy.n_samples, 3))
    t = jnp.asarray(np.linspace(np.log(0.05), np.log(2.5), 9))
    via_table = np.asarray(F._golden_batch(F._mu_blocks(F._mirror_table_jit(sub, 12), 1.0 + jnp.exp(t), 12, 1e-12))[0])
    direct = np.asarray(F._mu_candidates(sub, t, 12, 4096, 1e-12))
    np.testing.assert_allclose(via_table, direct, rtol=1e-10)  # measured 1.4e-11
    assert np.ptp(direct) > 0.1 * np.max(direct)  # the candidates differ: the comparison can see a wrong mu


def test_factorize_source_rows_are_those_of_practical_terms(obs_noisy, rng):
    # the refinement's rows for the found source (`_source_parts`) are the practical model's rows of one fast
    # source of unit energy (`jaxsh.practical_terms`, the forward model), shadow included
    from solvers import _factorize as F

    o = obs_noisy
    d = jnp.asarray([0.3, -0.4, 0.866])
    d = d / jnp.linalg.norm(d)
    fvis = jnp.asarray(rng.uniform(size=o.n_samples) > 0.3, o.values.dtype)
    jt = dataclasses.replace(F._joint_jit(o, None, 1.6, 12, 4096, 1e-12, None), fvis=fvis)
    sp = F._source_parts(jt, jnp.asarray(1.6), d)
    sigma = 0.15
    fs = sp.amp * np.exp(-sp.th2 / sigma**2) / (np.pi * sigma**2)
    terms = jaxsh.practical_terms(o.normals, o.views, slow_sh=jnp.zeros((1, 1)), fast_directions=d[None],
                                  fast_energy=jnp.ones((1, 1)), fast_visibility=fvis[:, None])
    np.testing.assert_allclose(np.asarray(sp.fd), np.asarray(terms.irradiance[:, 0]), rtol=1e-12, atol=1e-14)
    spec = terms.components(jnp.zeros(1), jnp.ones(1), 1.6, sigma).specular_fast[:, 0]
    np.testing.assert_allclose(np.asarray(fs), np.asarray(spec), rtol=1e-10, atol=1e-14)
    assert np.sum(np.asarray(fs) > 0) > 100 and np.sum((np.asarray(fvis) == 0) & (np.asarray(sp.fd) == 0)) > 100


def test_factorize_joint_rss_equals_a_dense_weighted_least_squares(obs_noisy):
    # the refinement's profiled RSS (`_joint_rss`: the factored elimination with P = H^T H) against a dense NumPy
    # weighted least-squares solve of the same design (slow SH to l* filtered by exp(-(sigma l)^2), plus the source
    # as one column), per channel: the RSS and the coefficients, and against the (C, m, m) elimination `_schur_rss`
    from solvers import _factorize as F

    o = obs_noisy
    mu, lmax, sigma = jnp.asarray(1.6), 12, 0.13
    ks = jnp.asarray([0.2, 0.35, 0.6])
    d = jnp.asarray([0.3, -0.4, 0.866])
    d = d / jnp.linalg.norm(d)
    jt = F._joint_jit(o, None, mu, lmax, 4096, 1e-12, None)
    sp = F._source_parts(jt, mu, d)
    rss, x1, x2 = (np.asarray(a) for a in jax.jit(lambda: F._joint_rss(jt, sp, ks, sigma, lmax))())
    rows, w, b = np.asarray(jt.rows), np.asarray(jt.w), np.asarray(jt.b)
    filt = np.exp(-((sigma * jaxsh.sh_degrees(lmax)) ** 2))
    fs = np.asarray(sp.amp) * np.exp(-np.asarray(sp.th2) / sigma**2) / (np.pi * sigma**2)
    sw = np.sqrt(w)
    for c in range(3):
        kd_c, ks_c = 1.0 - float(ks[c]), float(ks[c])
        spec = ks_c * rows[9:] * filt[:, None]  # (n, N)
        spec[:9] += kd_c * rows[:9]
        a = np.concatenate([spec, (kd_c * np.asarray(sp.fd) + ks_c * fs)[None]], 0).T * sw[:, None]
        coef, *_ = np.linalg.lstsq(a, b[:, c] * sw, rcond=None)
        ref_rss = np.sum((a @ coef - b[:, c] * sw) ** 2)
        assert abs(rss[c] - ref_rss) <= 1e-12 * np.sum(w * b[:, c] ** 2)  # measured 8e-15
        got = np.concatenate([x1[c, :9], x2[c], x1[c, 9:]])
        np.testing.assert_allclose(got, coef, rtol=0, atol=1e-10 * np.max(np.abs(coef)))  # measured 6e-13
    # the same elimination in the (C, m, m) form of `_schur_rss`
    old = np.asarray(jax.jit(lambda: _schur_joint(F, jt, sp, ks, sigma, lmax))())
    np.testing.assert_allclose(rss, old, rtol=1e-12)  # measured 6e-15


def _schur_joint(F, jt, sp, ks, sigma, lmax):
    """`_joint_rss` through `_schur_rss` (the unfactored elimination), as the refinement ran before."""
    filt = jaxsh.microfacet_spectrum(sigma, lmax)[jaxsh.sh_degrees(lmax)]
    kd = 1.0 - ks
    fs = sp.amp * (jnp.exp(-sp.th2 / sigma**2) / (jnp.pi * sigma**2))
    wfs = jt.w * fs
    rows_fs = jt.rows @ wfs
    dfd, dfs = sp.rows_fd[:9], rows_fs[:9]
    sfd, sfs = sp.rows_fd[9:] * filt, rows_fs[9:] * filt
    a_d = (kd**2)[None, :] * dfd[:, None] + (kd * ks)[None, :] * (dfs[:, None] + sfd[:9, None]) + (ks**2)[None, :] * sfs[:9, None]
    a_s = (ks * kd)[None, :] * sfd[9:, None] + (ks**2)[None, :] * sfs[9:, None]
    a_ss = kd**2 * sp.fd_fd + 2 * kd * ks * jnp.sum(wfs * sp.fd) + ks**2 * jnp.sum(wfs * fs)
    r_s = kd * sp.fd_b + ks * (wfs @ jt.b)
    return F._schur_rss(jt.bl, kd, ks, filt, (a_d, a_s, a_ss, r_s))[0]


def test_factorize_recovers_brdf_under_unknown_lighting(factorization):
    res = factorization
    assert solvers.status_name(res.status) == "converged"
    s = np.asarray(TRUTH.kd + TRUTH.ks)
    np.testing.assert_allclose(np.asarray(res.brdf.ks), np.asarray(TRUTH.ks) / s, atol=0.03)
    np.testing.assert_allclose(np.asarray(res.brdf.kd), np.asarray(TRUTH.kd) / s, atol=0.03)
    np.testing.assert_allclose(np.asarray(res.brdf.kd + res.brdf.ks), 1.0, atol=1e-12)
    assert _rel(res.brdf.sigma, TRUTH.sigma) < 0.15
    assert _rel(res.brdf.mu, TRUTH.mu) < 0.10
    assert np.all(np.isfinite(np.asarray(res.std_errors.ks))) and np.isfinite(float(res.std_errors.sigma))
    assert np.isfinite(float(res.std_errors.mu))


def test_factorize_lighting_correlates_with_truth(capture, factorization):
    rec = np.asarray(factorization.lighting.total_sh(2))
    tru = np.asarray(capture.lighting.total_sh(2))
    for c in range(3):
        assert np.corrcoef(rec[:, c], tru[:, c])[0, 1] > 0.99
    # the found source is the true directional source
    d_true = np.asarray(capture.directional[0][0])
    assert np.arccos(np.clip(np.dot(np.asarray(factorization.source.direction), d_true), -1, 1)) < 0.05


def test_factorize_predicts_a_held_out_view_under_a_new_light(factorization):
    """Re-render a view not used for fitting, under a new directional source, against the reference.

    The absolute scale per channel (lighting colour times albedo) is unrecoverable (R&H sec. 6.3),
    so one least-squares scale per channel is applied before comparing."""
    cam = solvers.view_cameras(1, SIZE, azimuths=[2.4], elevation=0.2)[0]
    gb = jaxsh.sphere_gbuffer(cam, np.zeros(3), 1.0)
    m = np.asarray(gb.mask)
    n, v = np.asarray(gb.normal)[m], np.asarray(gb.view)[m]
    d_new = np.array([[0.6, 0.7, 0.4]]) / np.linalg.norm([0.6, 0.7, 0.4])
    e_new = np.array([[2.0, 2.0, 2.0]])
    ref = np.asarray(jaxsh.render_reference(n, v, TRUTH.kd, TRUTH.ks, TRUTH.mu, TRUTH.sigma, directional=(d_new, e_new)))
    pred = np.asarray(solvers.predict(factorization.brdf, solvers.Lighting(None, jnp.asarray(d_new), jnp.asarray(e_new)), n, v))
    scale = np.sum(pred * ref, 0) / np.sum(pred * pred, 0)
    err = np.sqrt(np.mean((pred * scale - ref) ** 2)) / np.sqrt(np.mean(ref**2))
    assert err < 0.05, err


def _weighted_rms(obs, fitted):
    w, b = np.asarray(obs.weights), np.asarray(obs.values)
    return np.sqrt(np.sum(w[:, None] * (np.asarray(fitted) - b) ** 2) / (np.count_nonzero(w > 0) * b.shape[1]))


def test_factorize_fitted_is_the_model_at_the_estimate(capture, obs_noisy, factorization):
    """After the refinement, `fitted` is eq. 24 with the returned BRDF and lighting (slow SH + the found source):
    it equals the renderer's images (`solvers.predict`, exact SH sums: another program) and its weighted residual
    is the result's `rms`. Without the refinement it is eq. 25 of the first stage, whose residual is that rms."""
    res = factorization
    assert res.fitted.shape == obs_noisy.values.shape
    for img, gb in zip(obs_noisy.to_images(res.fitted), capture.gbuffers):
        ref = np.asarray(solvers.predict(res.brdf, res.lighting, gb.normal, gb.view, mask=gb.mask, method="exact"))
        m = np.asarray(gb.mask)
        np.testing.assert_allclose(img[m], ref[m], rtol=1e-9, atol=1e-12 * np.abs(ref[m]).max())
    np.testing.assert_allclose(_weighted_rms(obs_noisy, res.fitted), float(res.rms), rtol=1e-9)
    assert float(res.rel_rms) > 0.005  # the 1 % noise (and the model's error) is in the residual
    for kw in ({"find_sigma": False, "refine": False}, {"refine": False}, {"fresnel": False, "refine": False}):
        r = solvers.factorize(obs_noisy, 8, **kw)
        assert r.fitted.shape == obs_noisy.values.shape
        np.testing.assert_allclose(_weighted_rms(obs_noisy, r.fitted), float(r.rms), rtol=1e-9)
    # the search on a subset, the final solve (and `fitted`) on every sample
    r = solvers.factorize(obs_noisy, 8, search_pixels=3000)
    assert r.fitted.shape == obs_noisy.values.shape
    np.testing.assert_allclose(_weighted_rms(obs_noisy, r.fitted), float(r.rms), rtol=1e-9)
    # counted over every sample too (stage 1 starts the joint mu search from the subset's blocks, then is redone)
    n_pos = int(np.count_nonzero(np.asarray(obs_noisy.weights) > 0))
    assert n_pos > 3000 and int(r.stats["n_obs"]) == n_pos * obs_noisy.n_channels


def test_factorize_options(obs_noisy):
    r0 = solvers.factorize(obs_noisy, 8, find_sigma=False, refine=False)
    assert bool(jnp.isnan(r0.brdf.sigma)) and r0.source is None
    r1 = solvers.factorize(obs_noisy, 8, fresnel=False, refine=False)
    assert r1.brdf.mu is None and np.isfinite(float(r1.brdf.sigma))
    with pytest.raises(ValueError, match="lmax"):
        solvers.factorize(obs_noisy, 2)
    with pytest.raises(ValueError, match="find_sigma"):
        solvers.factorize(obs_noisy, 8, find_sigma=False, refine=True)
    import equinox as eqx

    textured = eqx.tree_at(lambda o: o.texel, obs_noisy, jnp.zeros(obs_noisy.n_samples, jnp.int32), is_leaf=lambda x: x is None)
    with pytest.raises(ValueError, match="homogeneous"):
        solvers.factorize(textured, 8)


# --------------------------------------------------------------------------- textures and shadows (sec. 6.4)


def _floor_and_wall():
    import trimesh

    box = trimesh.creation.box(extents=[2.0, 2.0, 0.2])
    box.apply_translation([0.0, 0.0, -0.1])
    wall = trimesh.creation.box(extents=[0.2, 2.0, 1.0])
    wall.apply_translation([0.0, 0.0, 0.6])
    return trimesh.util.concatenate([box, wall])


def test_textured_kd_on_a_self_shadowing_mesh():
    """Known lighting, Kd(x) a 4x4 checker texture on a floor shadowed by a wall (R&H sec. 6.4).

    Reference images ray-trace every quadrature direction; the fit uses the practical model with
    transfer vectors, the shadow of the directional source and the reflected-ray visibility."""
    mesh = _floor_and_wall()
    rng = np.random.default_rng(7)
    tex = rng.uniform(0.25, 0.8, size=(17, 3))  # 16 floor cells + the wall
    ks, mu, sigma = np.array([0.25, 0.25, 0.25]), 1.5, 0.2
    d1 = np.array([0.7, 0.2, 0.69]) / np.linalg.norm([0.7, 0.2, 0.69])
    d2 = np.array([-0.6, 0.3, 0.74]) / np.linalg.norm([-0.6, 0.3, 0.74])
    r1, l1, e2 = 0.4, np.array([1.2, 1.1, 1.0]), np.array([2.5, 2.5, 2.5])
    slow = jaxsh.disk_light_sh(d1, r1, l1, 24)
    gbs, imgs, extra = [], [], {"transfer": [], "fast_visibility": [], "reflected_visibility": [], "texel": []}
    eyes = [np.array([0.3, -2.0, 4.0]), np.array([2.0, 1.5, 3.5]), np.array([-2.5, -1.0, 3.0])]
    for eye in eyes:
        cam = jaxsh.OrthographicCamera(0.08, 26, 26, jaxsh.look_at(eye, np.zeros(3), np.array([0, 0, 1.0])))
        g = jaxsh.mesh_gbuffer(cam, mesh, smooth=False)
        m = np.asarray(g.mask)
        pts, nrm, vw = (np.asarray(a)[m] for a in (g.position, g.normal, g.view))
        on_floor = pts[:, 2] < 1e-6
        cell = np.clip(((pts[:, 0] + 1) * 2).astype(int), 0, 3) * 4 + np.clip(((pts[:, 1] + 1) * 2).astype(int), 0, 3)
        tid = np.where(on_floor, cell, 16)
        ref = np.asarray(jaxsh.render_reference(nrm, vw, tex[tid], ks, mu, sigma, disks=(d1[None], np.array([r1]), l1[None]),
                                                directional=(d2[None], e2[None]), disk_nodes=(24, 48), mesh=mesh, points=pts))
        img = np.zeros(m.shape + (3,))
        img[m] = ref
        full = lambda x, tail: (lambda out: (out.__setitem__(m, x), out)[1])(np.zeros(m.shape + tail, x.dtype))  # noqa: E731
        extra["transfer"].append(full(np.asarray(jaxsh.visibility_sh(mesh, pts, nrm, 2, n_dirs=1024)), (9,)))
        extra["fast_visibility"].append(full(np.asarray(jaxsh.directional_visibility(mesh, pts, nrm, d2[None])), (1,)))
        extra["reflected_visibility"].append(full(np.asarray(jaxsh.reflected_visibility(mesh, pts, nrm, vw)), ()))
        extra["texel"].append(full(tid.astype(np.int64), ()))
        gbs.append(g)
        imgs.append(img)
    obs = solvers.observations(gbs, imgs, n_texels=17, **extra)
    light = solvers.Lighting(slow, jnp.asarray(d2[None]), jnp.asarray(e2[None]))
    res = solvers.fit_brdf(obs, light, textured="kd")
    seen = np.asarray(res.texel_count) > 0
    assert seen.sum() >= 14
    kd = np.asarray(res.brdf.kd)
    err = np.sqrt(np.mean((kd[seen] - tex[seen]) ** 2)) / np.sqrt(np.mean(tex[seen] ** 2))
    assert err < 0.03, err
    assert np.all(np.isinf(np.asarray(res.std_errors.kd)[~seen]))
    assert _rel(res.brdf.sigma, sigma) < 0.15
    # `fitted` carries each sample's own texel K_d: its weighted residual is the fit's
    f, b, w = np.asarray(res.fitted), np.asarray(obs.values), np.asarray(obs.weights)
    assert f.shape == b.shape
    np.testing.assert_allclose(np.sqrt(np.sum(w[:, None] * (f - b) ** 2) / (np.count_nonzero(w > 0) * b.shape[1])),
                               float(res.rms), rtol=1e-10)


# --------------------------------------------------------------------------- bad input


def test_observations_reject_bad_input(capture):
    gbs, imgs = capture.gbuffers, capture.clean
    empty = [np.zeros(np.asarray(g.mask).shape, bool) for g in gbs]
    with pytest.raises(ValueError, match="no valid pixel"):
        solvers.observations(gbs, imgs, masks=empty)
    bad = [x.copy() for x in imgs]
    m = np.asarray(gbs[1].mask)
    bad[1][np.argwhere(m)[0][0], np.argwhere(m)[0][1], 0] = np.nan
    with pytest.raises(ValueError, match=r"images\[1\].*non-finite"):
        solvers.observations(gbs, bad)
    dropped = solvers.observations(gbs, bad, invalid="drop")
    full = solvers.observations(gbs, imgs)
    assert dropped.n_samples == full.n_samples - 1
    sat = solvers.observations(gbs, imgs, saturation=float(np.percentile(imgs[0][np.asarray(gbs[0].mask)], 99)))
    assert sat.n_samples < full.n_samples and np.all(np.isfinite(np.asarray(sat.values)))
    with pytest.raises(ValueError, match="one image per G-buffer"):
        solvers.observations(gbs, imgs[:2])
    with pytest.raises(ValueError, match=r"images\[0\]"):
        solvers.observations(gbs, [imgs[0][:-1]] + imgs[1:])
    with pytest.raises(ValueError, match="invalid"):
        solvers.observations(gbs, imgs, invalid="ignore")
    # to_images round trip
    back = full.to_images(full.values)
    for k in range(3):
        np.testing.assert_array_equal(back[k][np.asarray(gbs[k].mask)], imgs[k][np.asarray(gbs[k].mask)])


def test_solvers_report_failures(capture, obs_clean):
    res = solvers.fit_brdf(obs_clean, capture.lighting, max_steps=2, refine=False)
    assert solvers.status_name(res.status) == "max_steps_reached"
    with pytest.raises(ValueError, match="texel"):
        solvers.fit_brdf(obs_clean, capture.lighting, textured="kd")
    with pytest.raises(ValueError, match="textured"):
        solvers.fit_brdf(obs_clean, capture.lighting, textured="ks")
    tex = solvers.TorranceSparrow(jnp.ones((4, 3)), jnp.ones((4, 3)), TRUTH.mu, TRUTH.sigma)
    with pytest.raises(ValueError, match="homogeneous"):
        solvers.inverse_lighting(obs_clean, tex, 4)
    with pytest.raises(ValueError, match="Lighting needs"):
        solvers.Lighting()
    with pytest.raises(ValueError, match="Observations"):
        solvers.fit_brdf(capture.clean, capture.lighting)


# --------------------------------------------------------------------------- dual angular / frequency lighting


def test_inverse_lighting_dual_recovers_the_filtered_lighting():
    """R&H fig. 8 on images of the slow-lighting model (B_s,fast = 0, the method's assumption).

    The image is compared with the true filtered lighting on texels a mirror direction reaches; the
    residual error (~3 %) comes from binning the mirror directions into 32x64 texels and from the
    paper's consistency condition using the filtered lighting's l <= 2 part for the diffuse term."""
    disks, _ = solvers.default_sources()
    gbs = [jaxsh.sphere_gbuffer(c, np.zeros(3), 1.0) for c in solvers.view_cameras(3, 80)]
    slow = sum(jaxsh.disk_light_sh(disks[0][k], disks[1][k], disks[2][k], 40) for k in range(2))
    imgs = [np.asarray(jaxsh.render_practical(g.normal, g.view, TRUTH.kd, TRUTH.ks, TRUTH.mu, TRUTH.sigma,
                                              slow_sh=slow, mask=g.mask).total) for g in gbs]
    obs = solvers.observations(gbs, imgs)
    truth_map = np.asarray(jaxsh.synthesize_latlong(jaxsh.filter_lighting_microfacet(slow, TRUTH.sigma), 32, 64))
    for nonneg in (False, True):
        r = solvers.inverse_lighting_dual(obs, TRUTH, 32, nonneg=nonneg, maxiter=100)
        cov = np.asarray(r.covered)
        img = np.asarray(r.image)
        assert cov.mean() > 0.9
        err = np.sqrt(np.mean((img[cov] - truth_map[cov]) ** 2) / np.mean(truth_map[cov] ** 2))
        assert err < 0.05, err
        np.testing.assert_allclose(np.asarray(r.coeffs9), np.asarray(slow[:9]), atol=0.05 * np.abs(np.asarray(slow[:9])).max())
        assert np.all(np.asarray(r.consistency) < 1e-10)  # L1 = L2 (the 9 equations)
        if nonneg:
            assert img.min() >= 0.0
    # K_s = 0 (Lambertian): a status and the l <= 2 diffuse fallback, not an exception (tests/test_degenerate.py)
    lam = solvers.inverse_lighting_dual(obs, solvers.TorranceSparrow(TRUTH.kd, jnp.zeros(3), TRUTH.mu, TRUTH.sigma), 32,
                                        nonneg=False)
    assert lam.status_name == "ill_conditioned" and np.isfinite(float(lam.rel_rms))


# --------------------------------------------------------------------------- SH BRDF coefficients (sec. 6.1)


def test_fit_brdf_sh_solves_the_linear_system_of_eqs_9_10(rng):
    """Images of a known BRDF under random band-limited lighting, rendered by brute-force quadrature of the
    reflection equation (`helpers.quadrature_images`: no SH BRDF coefficients, no local frames of eqs. 9, 10): the
    solve reproduces them and held-out pixels of the same views to rounding.

    The BRDF rho = 0.3/pi + 0.2 (w_i . w_o)^2 is a polynomial of degree 2 in each direction, and the lighting is
    band-limited to lmax 4, so the images are exactly representable by eqs. 9, 10 at lmax 4 (the hemispherical
    projections of `jaxsh.brdf_sh_coefficients` are not that representation: they converge as O(1/P^2), see
    `test_convolution.py`). With three views at one elevation the system has
    rank 52 of 55 (measured): three combinations of coefficients are not excited by these views, so a view from
    elsewhere is not determined -- the solver says so through `rank` instead of inventing values (minimum-norm)."""
    lmax = 4

    scale = np.array([1.0, 0.5, 2.0])  # the BRDF of channel c is scale[c] rho

    def brdf(wi, wo, n):  # the same BRDF in world directions
        return 0.3 / np.pi + 0.2 * jnp.sum(wi * wo, -1) ** 2

    L = rng.normal(size=(jaxsh.num_coeffs(lmax), 3))
    L[0] += 3.0
    gbs = [jaxsh.sphere_gbuffer(c, np.zeros(3), 1.0) for c in solvers.view_cameras(3, 24)]
    imgs = quadrature_images(gbs, brdf, [L * scale] * 3, lmax)  # B is linear in (BRDF scale) x (lighting)
    masks = [rng.uniform(size=np.asarray(g.mask).shape) < 0.8 for g in gbs]
    res = solvers.fit_brdf_sh(solvers.observations(gbs, imgs, masks=masks), L, lmax)
    assert float(res.rel_rms) < 1e-10 and solvers.status_name(res.status) == "converged"
    assert res.n_unknowns == 55 and np.all(np.asarray(res.rank) == 52)
    for g, img, m_fit in zip(gbs, imgs, masks):
        held = np.asarray(g.mask) & ~m_fit
        pred = np.asarray(solvers.predict_brdf_sh(res.rho, L, np.asarray(g.normal)[held], np.asarray(g.view)[held]))
        np.testing.assert_allclose(pred, img[held], atol=1e-9 * np.abs(img).max())
    with pytest.raises(ValueError, match="lighting_sh"):
        solvers.fit_brdf_sh(solvers.observations(gbs, imgs), L[:4], lmax)


@pytest.mark.parametrize("path", ["table", "direct"])
def test_factorize_searches_mu_again_on_the_joint_model(path, monkeypatch):
    """A sphere under smooth lighting plus a sun, noise-free images of the factorization's own model (slow SH to
    l = 6 plus a directional source), grazing pixels masked. Stage 1 models the lighting as SH only, and the sun's
    misfit moves its mu: without `refine_mu` (R&H's algorithm) mu 1.49 for 1.6, K_s 5-7 % low, and a standard error
    of mu (0.0008) 140 times smaller than its error. With it (the default) the joint model's mu: K_s, mu, sigma
    within 0.3 %, 0.2 %, 0.5 % (measured). The remaining error comes from the source direction of eq. 26, which
    the refinement holds fixed; mu's standard error is conditional on it and, on noise-free images, far smaller
    than that error (2.6e-4 against 2.4e-3: the former check "truth within 3 standard errors" held only while the
    error was sqrt(data energy) times too large). On both paths: the search subset's `MirrorTable`, and direct
    sums (a subset too large for a table; forced here by a zero table budget), which used to keep stage 1's mu."""
    from solvers import _factorize as F

    if path == "direct":
        monkeypatch.setattr(F, "_TABLE_BYTES", 0)
    rng = np.random.default_rng(1)
    sh = rng.normal(size=(jaxsh.num_coeffs(6), 3)) * 0.08
    sh[0] = [1.2, 1.1, 1.0]
    d = np.array([[0.5, -0.3, 0.8]]) / np.linalg.norm([0.5, -0.3, 0.8])
    light = solvers.Lighting(jnp.asarray(sh), jnp.asarray(d), jnp.asarray([[3.0, 2.8, 2.5]]))
    brdf = solvers.TorranceSparrow(np.array([0.5, 0.4, 0.3]), np.full(3, 0.3), 1.6, 0.2)
    gbs = [jaxsh.sphere_gbuffer(c, jnp.zeros(3), jnp.asarray(1.0)) for c in solvers.view_cameras(4, 48)]
    imgs = [np.asarray(solvers.predict(brdf, light, g.normal, g.view, mask=g.mask)) for g in gbs]
    masks = [np.asarray(g.mask) & (np.sum(np.asarray(g.normal) * np.asarray(g.view), -1) > 0.3) for g in gbs]
    obs = solvers.observations(gbs, imgs, masks=masks)
    ks_true = 0.3 / np.array([0.8, 0.7, 0.6])  # kd + ks = 1: the lighting carries the scale
    res = solvers.factorize(obs, 12)
    assert res.status_name == "converged"
    np.testing.assert_allclose(np.asarray(res.brdf.ks), ks_true, rtol=0.01)
    assert abs(float(res.brdf.mu) - 1.6) < 0.01 and abs(float(res.brdf.sigma) - 0.2) < 0.003
    assert 0 < float(res.std_errors.mu) < 0.01
    old = solvers.factorize(obs, 12, refine_mu=False)
    assert abs(float(old.brdf.mu) - 1.6) > 0.05 and np.all(np.asarray(old.brdf.ks) < 0.97 * ks_true)


def test_factorize_mu_standard_error_has_the_units_of_mu():
    """`std_errors.mu` of the joint mu search (`refine_mu`, the default) took the profile's curvature of RSS / data
    energy for one of RSS: it scaled with the images (x100 images, x100 error) and was 126 times a Monte Carlo
    spread over noise draws (0.127 against 1.0e-3; now 8.6e-4 against 7.5e-4, 3 x 48^2 views). It must not change
    when the images are scaled, nor when weight-0 samples are added (`pad_observations`; they were counted), and
    must agree with the spread of mu over noise draws within a factor 2 (5 draws)."""
    brdf = solvers.TorranceSparrow(jnp.array([0.6, 0.45, 0.3]), jnp.array([0.3, 0.3, 0.3]), jnp.asarray(1.6),
                                   jnp.asarray(0.1))
    cap = solvers.sphere_capture(brdf, size=32, n_views=3, noise=0.0)
    mus, ses = [], []
    for seed in range(5):
        rng = np.random.default_rng(seed)
        imgs = [c + 0.01 * np.sqrt(np.mean(c[np.asarray(g.mask)] ** 2)) * rng.standard_normal(c.shape)
                * np.asarray(g.mask)[..., None] for c, g in zip(cap.clean, cap.gbuffers)]
        obs = solvers.observations(cap.gbuffers, imgs)
        r = solvers.factorize(obs, 12)
        mus.append(float(r.brdf.mu))
        ses.append(float(r.std_errors.mu))
        if seed == 0:
            bright = solvers.factorize(eqx.tree_at(lambda o: o.values, obs, obs.values * 100.0), 12)
            assert float(bright.std_errors.mu) == pytest.approx(ses[0], rel=1e-6)
            padded = solvers.factorize(solvers.pad_observations(obs, bucket=True), 12)
            assert padded.stats["n_obs"] == r.stats["n_obs"]
            assert float(padded.std_errors.mu) == pytest.approx(ses[0], rel=1e-3)
    spread = np.std(mus, ddof=1)
    assert 0.5 < np.mean(ses) / spread < 2.0, (np.mean(ses), spread)


@pytest.mark.parametrize("mu_true, end", [(8.0, 3.5), (1.02, 1.05)])
def test_factorize_flags_mu_at_an_end_of_its_range(mu_true, end):
    """A Fresnel index outside the factorization's range ($\\mu \\in [1.05, 3.5]$) stops at its end. That used to
    come back as a plain `converged` estimate whose only sign was an infinite `std_errors.mu`; `stats["at_bound"]`
    now says it, as `fit_brdf`'s does, and neither the search nor σ's flag moves. Checked on images rendered by
    `render_reference` (not the fitted model), both with the joint μ search (the default) and without it."""
    brdf = solvers.TorranceSparrow(jnp.array([0.6, 0.45, 0.3]), jnp.array([0.3, 0.3, 0.3]), jnp.asarray(mu_true),
                                   jnp.asarray(0.1))
    cap = solvers.sphere_capture(brdf, size=32, n_views=3, noise=0.0)
    obs = solvers.observations(cap.gbuffers, cap.clean)
    for refine_mu in (True, False):
        r = solvers.factorize(obs, 12, refine_mu=refine_mu)
        assert float(r.brdf.mu) == pytest.approx(end, rel=1e-12)
        assert {k: bool(v) for k, v in r.stats["at_bound"].items()} == {"mu": True, "sigma": False}
        assert np.isinf(float(r.std_errors.mu)) and np.isfinite(float(r.std_errors.sigma))
        assert float(r.brdf.sigma) == pytest.approx(0.1, rel=0.15)


def test_factorize_at_bound_is_false_inside_the_ranges(factorization):
    """On the fixture's capture (μ 1.6, σ 0.1) neither flag is set and both errors are finite. The rule itself on
    given values: μ's flag at the exact ends of its grid's range (the searches reach them exactly), σ's within 0.1 %
    in log σ of an end (its grids approach an end by their spacing), none without Fresnel or σ."""
    assert {k: bool(v) for k, v in factorization.stats["at_bound"].items()} == {"mu": False, "sigma": False}
    assert np.isfinite(float(factorization.std_errors.mu)) and np.isfinite(float(factorization.std_errors.sigma))
    from solvers import _factorize as F

    assert not any(F._at_bound(None, None).values())
    assert F._at_bound(F._MU_T_RANGE[0], 0.5) == {"mu": True, "sigma": False}
    assert F._at_bound(0.0, 2.0 * (1 - 1e-4)) == {"mu": False, "sigma": True}
    assert F._at_bound(0.0, 1e-3 * (1 + 2e-3)) == {"mu": False, "sigma": False}


def test_inverse_lighting_and_factorize_accept_float32(obs_noisy, factorization):
    obs32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, obs_noisy)
    t32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), TRUTH)
    il32 = solvers.inverse_lighting(obs32, t32, 8)
    il64 = solvers.inverse_lighting(obs_noisy, TRUTH, 8)
    assert il32.coeffs.dtype == jnp.float32
    np.testing.assert_allclose(il32.coeffs, il64.coeffs, atol=1e-4 * float(jnp.abs(il64.coeffs).max()))
    f32 = solvers.factorize(obs32, 12)  # solved in float64 internally (documented), returned in float32
    assert f32.brdf.ks.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(f32.brdf.ks), np.asarray(factorization.brdf.ks), atol=1e-3)

# --------------------------------------------------------------------------- the dual lighting inside factorize (sec. 6.3)
# R&H factor their spheres "with the dual angular and frequency-space algorithm for inverse lighting"
# (figs. 8-9, 11). The data are reference-rendered with a directional source, which violates the dual
# model's assumption B_s,fast = 0: the tolerances include that model error. 64^2 x 3 views: 7,980
# samples, so the default search grid is 15 x 30 (16 samples per texel).


@pytest.fixture(scope="module")
def dual_factorization(obs_noisy):
    return solvers.factorize(obs_noisy, 12, lighting_method="dual", refine=False)


def test_closed_form_objective_equals_inverse_lighting_dual(obs_noisy):
    """The search's RSS (moments formed once per mu) equals the RSS of `inverse_lighting_dual`'s own solve."""
    for ks, mu in [(0.2, 1.4), (0.5, 2.5), (0.9, None)]:
        mo = _dual_moments(obs_noisy, None if mu is None else jnp.asarray(mu), 24)
        brdf = solvers.TorranceSparrow(jnp.full(3, 1 - ks), jnp.full(3, ks), None if mu is None else jnp.asarray(mu),
                                       jnp.asarray(0.1))
        ref = solvers.inverse_lighting_dual(obs_noisy, brdf, 24, nonneg=False)
        rss_ref = float(ref.rms) ** 2 * float(ref.stats["n_obs"])
        rss = sum(float(_dual_rss_one(mo, c, jnp.asarray(ks))[0]) for c in range(3))
        assert abs(rss - rss_ref) <= 1e-8 * rss_ref, (ks, mu, rss, rss_ref)
        l1 = np.stack([np.asarray(_dual_rss_one(mo, c, jnp.asarray(ks))[1]) for c in range(3)], 1)
        np.testing.assert_allclose(l1, np.asarray(ref.coeffs9), rtol=1e-7, atol=1e-9 * np.abs(l1).max())


def test_dual_factorization_recovers_the_brdf(capture, obs_noisy, dual_factorization):
    """R&H fig. 11 under unknown lighting: accurate, with K_s and mu somewhat low (the paper: teflon
    K_s 0.13 for 0.11, mu 1.48 for 1.78). Measured here: K_s 0.312 / 0.370 / 0.460 for 0.333 / 0.4 / 0.5,
    mu 1.47 for 1.6, sigma 0.088 for 0.1 (eq. 26 on the image, no refinement; eq. 26 holds at normal
    exitance, and the views see the sun's lobe obliquely). The SH method on the same data: K_s
    0.343 / 0.408 / 0.505, mu 1.63, sigma 0.093."""
    res = dual_factorization
    print(f"dual factorization: ks {np.round(np.asarray(res.brdf.ks), 3)}, mu {float(res.brdf.mu):.3f}, "
          f"sigma {float(res.brdf.sigma):.4f}, peak {np.round(np.asarray(res.source.peak), 2)}")
    assert res.status_name == "converged"
    assert res.dual.image.shape == (30, 60, 3)  # twice the search grid
    s = np.asarray(TRUTH.kd + TRUTH.ks)
    np.testing.assert_allclose(np.asarray(res.brdf.ks), np.asarray(TRUTH.ks) / s, atol=0.05)
    np.testing.assert_allclose(np.asarray(res.brdf.kd + res.brdf.ks), 1.0, atol=1e-12)
    assert abs(float(res.brdf.mu) - 1.6) / 1.6 < 0.15
    assert abs(float(res.brdf.sigma) - 0.1) / 0.1 < 0.15
    d_true = np.asarray(capture.directional[0][0])
    # the texels of the returned 30 x 60 image are 0.105 rad: measured 0.028
    assert np.arccos(np.clip(np.dot(np.asarray(res.source.direction), d_true), -1, 1)) < 0.06
    # the returned image is inverse_lighting_dual's at the stage-1 BRDF
    again = solvers.inverse_lighting_dual(obs_noisy, solvers.TorranceSparrow(res.brdf.kd, res.brdf.ks, res.brdf.mu, jnp.asarray(0.1)),
                                          30, nonneg=False)
    np.testing.assert_allclose(np.asarray(res.dual.image), np.asarray(again.image), rtol=1e-9, atol=1e-12)
    assert res.filtered_sh.shape == (jaxsh.num_coeffs(12), 3)


def test_dual_image_is_sharper_than_the_sh_lighting(obs_noisy, dual_factorization, factorization):
    """Fig. 9: the dual method's source is sharper than the l* = 12 SH recovery (which is cut by its band
    limit): measured peak 1.49x on the 30 x 60 grid."""
    sh = factorization  # its `source` is the first stage's (find_source on the l* = 12 SH lighting)
    assert float(jnp.mean(dual_factorization.source.peak)) > 1.3 * float(jnp.mean(sh.source.peak))
    # both see about the same source energy (eq. 26's L_tot): measured 19 % more in the dual image
    np.testing.assert_allclose(np.asarray(dual_factorization.source.energy), np.asarray(sh.source.energy), rtol=0.3)


def test_dual_then_refine(capture, obs_noisy):
    """The joint refinement (slow SH + the found source, sec. 6.3) from the dual first stage, with μ searched again
    on the joint model (`refine_mu`, the default) and the source's direction from the dual image's SH projection
    (`_dual_source`). Measured: K_s/(K_d+K_s) 0.330 / 0.398 / 0.498 for 0.333 / 0.4 / 0.5, μ 1.628, σ 0.1000, the
    direction 2e-4 rad off, rel_rms 0.020. The dual path used to keep stage 1's μ and the direction of the dual
    image's brightest texels: μ 2.57, σ 0.109, K_s 0.353 / 0.421 / 0.523, 0.041 rad, rel_rms 0.127."""
    res = solvers.factorize(obs_noisy, 8, lighting_method="dual", search_pixels=3000)
    assert res.status_name == "converged"
    assert res.dual is not None and res.stats["num_sigma_candidates"] > 0
    assert abs(float(res.brdf.sigma) - 0.1) / 0.1 < 0.02
    assert abs(float(res.brdf.mu) - 1.6) / 1.6 < 0.04
    s = np.asarray(TRUTH.kd + TRUTH.ks)
    np.testing.assert_allclose(np.asarray(res.brdf.ks), np.asarray(TRUTH.ks) / s, atol=0.01)
    d_true = np.asarray(capture.directional[0][0])
    assert np.arccos(np.clip(np.dot(np.asarray(res.source.direction), d_true), -1, 1)) < 0.01
    assert float(res.rel_rms) < 0.03
    # mu's error from the joint model's profile (the search above): finite
    assert 0 < float(res.std_errors.mu) < 0.01


def test_dual_joint_mu_search_by_table_equals_direct_sums(obs_noisy, monkeypatch):
    """The dual path's joint μ search takes the subset's rows from a `MirrorTable`; without one (a subset too large
    for it, here forced) it forms them by direct sums: the same estimate."""
    import solvers._factorize as fac

    kw = dict(lighting_method="dual", search_pixels=1500)
    by_table = solvers.factorize(obs_noisy, 6, **kw)
    monkeypatch.setattr(fac, "_TABLE_BYTES", 0)
    direct = solvers.factorize(obs_noisy, 6, **kw)
    assert by_table.status_name == direct.status_name == "converged"
    # measured: mu 9e-14, sigma 9e-11, rms 1e-8, K_s 3e-7 (a golden search on a flat minimum whose RSS carries
    # rounding noise, as in `test_factorize_from_the_table_equals_the_direct_sums_end_to_end`)
    np.testing.assert_allclose(float(by_table.brdf.mu), float(direct.brdf.mu), rtol=1e-9)
    np.testing.assert_allclose(float(by_table.brdf.sigma), float(direct.brdf.sigma), rtol=1e-7)
    np.testing.assert_allclose(float(by_table.rms), float(direct.rms), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(by_table.brdf.ks), np.asarray(direct.brdf.ks), rtol=1e-6)


def test_dual_options(obs_noisy):
    with pytest.raises(ValueError, match="lighting_method"):
        solvers.factorize(obs_noisy, 8, lighting_method="angular")
    with pytest.raises(ValueError, match="dual_height"):
        solvers.factorize(obs_noisy, 8, lighting_method="dual", dual_height=2)
    import equinox as eqx

    concave = eqx.tree_at(lambda o: o.transfer, obs_noisy, jnp.ones((obs_noisy.n_samples, 9)), is_leaf=lambda x: x is None)
    with pytest.raises(ValueError, match="concave"):
        solvers.factorize(concave, 8, lighting_method="dual")


def test_factorize_joint_rows_from_the_table_equal_those_of_eq25(obs_noisy):
    # the refinement's rows on the search subset come from its MirrorTable; the reference is `eq25_rows`
    from solvers import _factorize as F

    sub = obs_noisy.subset(np.arange(0, obs_noisy.n_samples, 2))
    mu = jnp.asarray(1.7)
    direct = F._joint_jit(sub, None, mu, 12, 4096, 1e-12, None)
    tab = F._mirror_table_jit(sub, 12)
    via = F._joint_from_table(sub, tab, direct.bl, mu, 12, F._K0())
    assert via.rows.shape == direct.rows.shape == (9 + 169, sub.n_samples)
    np.testing.assert_allclose(np.asarray(via.rows), np.asarray(direct.rows), rtol=1e-12, atol=1e-13)


def test_factorize_refinement_reaches_the_minimum_of_the_joint_rss(obs_noisy, factorization):
    # The refinement profiles K_s per channel inside zooming grids in log sigma (`_refine_search`); the reference
    # is scipy's BFGS over all four parameters of the same joint RSS (`_joint_rss`, itself tested against a dense
    # least squares above; its gradient by autodiff), run to tight tolerances from a start away from the answer
    import scipy.optimize

    from solvers import _factorize as F

    fac = factorization
    assert solvers.status_name(fac.status) == "converged"
    mu, d = fac.brdf.mu, fac.lighting.fast_directions[0]
    jt = F._joint_jit(obs_noisy, None, mu, 12, 4096, 1e-12, None)  # 9,600 samples: the search ran on all of them
    sp = F._source_parts(jt, mu, d)
    c = fac.brdf.ks.shape[0]
    obj = jax.jit(jax.value_and_grad(
        lambda x: jnp.sum(F._joint_rss(jt, sp, x[:c], jnp.exp(x[c]), 12)[0]) / jnp.sum(jt.bl.g.bb)))
    ours = np.concatenate([np.asarray(fac.brdf.ks), [np.log(float(fac.brdf.sigma))]])
    ref = scipy.optimize.minimize(lambda x: tuple(np.asarray(v) for v in obj(jnp.asarray(x))),
                                  ours + [0.03, -0.02, 0.02, 0.1], jac=True, method="BFGS", options=dict(gtol=1e-13))
    assert float(obj(jnp.asarray(ours))[0]) <= ref.fun * (1 + 1e-10)  # measured 2.5e-12 above it
    np.testing.assert_allclose(ours, ref.x, atol=1e-6)  # measured 6.9e-8 at most (K_s and log sigma)


def test_refinement_parts_equal_the_joint_rss(obs_noisy, factorization):
    # `_reduced_rss` of `_joint_golden_parts` (the source as a tenth unknown) is `_joint_rss` channel by channel
    from solvers import _factorize as F

    fac = factorization
    mu, d = fac.brdf.mu, fac.lighting.fast_directions[0]
    jt = F._joint_jit(obs_noisy, None, mu, 12, 4096, 1e-12, None)
    sp = F._source_parts(jt, mu, d)
    ks = jnp.asarray([1e-6, 0.3, 0.7, 1.0])

    @jax.jit
    def both(sigma):  # (4 K_s, C): from the parts, and from `_joint_rss` with every channel at that K_s
        parts = F._joint_golden_parts(jt, sp, sigma, 12)
        got = jax.vmap(lambda k: jax.vmap(lambda p: F._reduced_rss(p, k))(parts))(ks)
        want = jax.vmap(lambda k: F._joint_rss(jt, sp, jnp.full((3,), k), sigma, 12)[0])(ks)
        return got, want

    for sigma in (0.05, 0.12, 0.4):
        got, want = both(jnp.asarray(sigma))
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-11)


def test_golden_ks_unit_converges_within_its_steps():
    # optimistix 0.1.0's GoldenSearch starts from a wrong point unless the bracket starts at 0 (optimistix
    # issue #236); `golden_ks_unit` searches [0, 1] and maps it to [1e-6, 1]: on a parabola it converges in ~51
    # steps at tolerance 1e-11 (from the bracket [1e-6, 1] directly it ran to its 100 steps), to the minimum
    from solvers._factorize_dual import golden_ks_unit

    for k0 in (0.05, 0.37, 0.93):
        ks, f, steps = jax.jit(lambda: golden_ks_unit(lambda k, _: (k - k0) ** 2 + 2.0, jnp.float64, 1e-11, 1e-11,
                                                      100))()
        assert int(steps) < 70 and abs(float(ks) - k0) < 1e-6 and float(f) == pytest.approx(2.0, abs=1e-12)
    ks, f, _ = golden_ks_unit(lambda k, _: -k, jnp.float64, 1e-11, 1e-11, 100)  # decreasing: the end point 1
    assert float(ks) == 1.0


def test_inverse_lighting_dual_nonneg_does_not_depend_on_the_image_units(capture, obs_noisy):
    """R&H sec. 6.2's dual method with L >= 0: images x s give the lighting image x s at s = 1e-3 and 1e3. L-BFGS-B
    stops on a projected-gradient norm; the loss was in the images' units squared, so at s = 1e-3 it stopped early
    (0.05 % away from the s = 1 image here, 18 % on a finer grid) and at 1e3 late. Now in units of the data."""
    base = solvers.inverse_lighting_dual(obs_noisy, TRUTH, 8)
    assert solvers.status_name(base.status) == "converged"
    for s in (1e-3, 1e3):
        obs = eqx.tree_at(lambda o: o.values, obs_noisy, obs_noisy.values * s)
        r = solvers.inverse_lighting_dual(obs, TRUTH, 8)
        assert solvers.status_name(r.status) == "converged"
        img, ref = np.asarray(r.image) / s, np.asarray(base.image)
        assert np.linalg.norm(img - ref) / np.linalg.norm(ref) < 1e-6, s
        np.testing.assert_allclose(np.asarray(r.coeffs9) / s, np.asarray(base.coeffs9), rtol=1e-6, atol=1e-9)


def test_dual_default_grid_ignores_weight_zero_padding(obs_noisy):
    """`lighting_method="dual"` took its default search grid from all samples, weight-0 padding included: on 4,607
    samples (height floor(sqrt(4607/32)) = 11) one padding sample (`pad_observations(obs, 2)`, what
    `shard_observations` does on 2 devices) made it 12, and mu 1.454 for 1.561. Padded and unpadded must agree."""
    obs = obs_noisy.subset(np.arange(4607))
    ref = solvers.factorize(obs, 6, lighting_method="dual", refine=False)
    padded = solvers.pad_observations(obs, 2)  # one weight-0 sample (a size bucket's padding is the same case)
    assert padded.n_samples == obs.n_samples + 1
    r = solvers.factorize(padded, 6, lighting_method="dual", refine=False)
    assert r.dual.image.shape == ref.dual.image.shape == (22, 44, 3)
    np.testing.assert_allclose(np.asarray(r.brdf.ks), np.asarray(ref.brdf.ks), rtol=1e-6)
    assert float(r.brdf.mu) == pytest.approx(float(ref.brdf.mu), rel=1e-6)


def test_dual_refined_mu_error_is_not_claimed(obs_noisy):
    """With `"dual"` and stage 1's μ (`refine_mu=False`), μ's search profile is the dual model's RSS, not the
    refined joint model's whose residual scaled its curvature: the error came out 9-12x the spread of μ over noise
    draws. It is inf (not estimated); σ's and K_s's, from the refined model itself, stay finite."""
    r = solvers.factorize(obs_noisy, 8, lighting_method="dual", search_pixels=3000, refine_mu=False)
    assert np.isinf(float(r.std_errors.mu))
    assert np.all(np.isfinite(np.asarray(r.std_errors.ks))) and np.isfinite(float(r.std_errors.sigma))


def test_region_height_and_mesh_arguments_are_checked():
    """`find_source` checked `region` only for containing a texel (a zero direction or NaN radius said "enlarge its
    radius", a 2-vector failed in a matmul, `(d,)` raised IndexError, a radius of 7 passed) and truncated a float
    `height`; `dual_height` 4 gives a grid whose quadrature misses the l <= 2 harmonics by 0.094; `pixel_mesh` took a
    float count (TypeError) and one device twice (a runtime error when sharding)."""
    coeffs = np.zeros((16, 3))
    coeffs[0] = 1.0
    bad = [((np.zeros(3), 0.3), "direction"), ((np.array([0.0, 0, 1]), np.nan), "radius"),
           ((np.array([0.0, 1]), 0.3), "direction"), ((np.array([0.0, 0, 1]),), "region"),
           ((np.array([0.0, 0, 1]), 7.0), "radius")]
    for region, word in bad:
        with pytest.raises(ValueError, match="`region`") as e:
            solvers.find_source(coeffs, region=region)
        assert word in str(e.value) and "enlarge" not in str(e.value), str(e.value)
    with pytest.raises(ValueError, match="`height`"):
        solvers.find_source(coeffs, height=2.7)
    cap = solvers.sphere_capture(TRUTH, size=16, noise=0.0)
    obs = solvers.observations(cap.gbuffers, cap.clean)
    with pytest.raises(ValueError, match="`dual_height`"):
        solvers.factorize(obs, 4, lighting_method="dual", dual_height=4)
    with pytest.raises(ValueError, match="`devices`"):
        solvers.pixel_mesh(2.0)
    with pytest.raises(ValueError, match="more than once"):
        solvers.pixel_mesh([jax.devices()[0]] * 2)
