"""Audit of `inverse_lighting` and `fit_brdf_sh` (the reported statistics against a NumPy design matrix), and of
`factorize`'s status on too few pixels and its option checks.

The estimates were right; their statistics were not. `eig_solve` formed the RSS from the normal equations,
$b^Tb - 2x^TA^Tb + x^TA^TAx$, whose rounding is about $\\epsilon\\,b^Tb$. In float32 that made `rms`, every
standard error and the band SNRs wrong: 1.37× at 0.1 % noise, about 1000× on exact data. In float64 exact data
gave an RSS of 0, standard errors of 0 and infinite band SNRs. As many samples as unknowns gave finite standard
errors from $s^2 = 0/1$. References here: a design matrix written in NumPy from the paper's eq. 25 (harmonics from
`scipy.special`, Lambert's $A_l$ in closed form), and least squares on it in float64.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers
from solvers._results import rms_pair

from .helpers import scipy_real_sh

LMAX = 4
A_L = np.array([np.pi, 2 * np.pi / 3, np.pi / 4])  # Lambert's clamped-cosine coefficients, l <= 2 (R&H eq. 21)
KD, KS = np.array([0.5, 0.4, 0.3]), np.array([0.3, 0.35, 0.4])


def _obs(noise, dtype, seed=0, size=24):
    brdf = solvers.TorranceSparrow(KD, KS, None, 0.2)  # mu None: F = 1, so the rows need no Fresnel factor
    rng = np.random.default_rng(seed)
    sh = rng.normal(size=(jaxsh.num_coeffs(LMAX), 3)) * 0.1
    sh[0] = [1.0, 0.9, 0.8]
    light = solvers.Lighting(jnp.asarray(sh))
    gbs = [jaxsh.sphere_gbuffer(c, jnp.zeros(3), jnp.asarray(1.0)) for c in solvers.view_cameras(3, size)]
    imgs = []
    for g in gbs:
        img = np.asarray(solvers.predict(brdf, light, g.normal, g.view, mask=g.mask))
        imgs.append(img + noise * np.abs(img).max() * rng.standard_normal(img.shape) * np.asarray(g.mask)[..., None])
    obs = solvers.observations(gbs, imgs)
    obs = jax.tree_util.tree_map(lambda a: a.astype(dtype) if a.dtype == jnp.float64 else a, obs)
    return obs, brdf


def _design(obs, c):
    """Eq. 25's rows for channel c in NumPy: K_d A_l Y_lm(n) (l <= 2) + K_s Y_lm(R), zero where n . v <= 0."""
    n, v = np.asarray(obs.normals, np.float64), np.asarray(obs.views, np.float64)
    cos_o = np.sum(n * v, -1)
    r = 2 * cos_o[:, None] * n - v
    deg = np.repeat(np.arange(LMAX + 1), 2 * np.arange(LMAX + 1) + 1)
    diffuse = scipy_real_sh(n, LMAX) * np.where(deg <= 2, A_L[np.minimum(deg, 2)], 0.0)
    a = KD[c] * diffuse + KS[c] * scipy_real_sh(r, LMAX)
    return np.where((cos_o > 0)[:, None], a, 0.0)


def _reference(obs, res):
    """Per channel: the rms of the returned estimate's residual, and the least-squares standard errors with s^2 from
    it (both in float64 NumPy)."""
    b = np.asarray(obs.values, np.float64)
    w = np.asarray(obs.weights, np.float64)
    x = np.asarray(res.coeffs, np.float64)
    rss, se = 0.0, []
    for c in range(3):
        a = _design(obs, c) * np.sqrt(w)[:, None]
        r = a @ x[:, c] - np.sqrt(w) * b[:, c]
        rss_c = float(r @ r)
        rss += rss_c
        dof = np.count_nonzero(w > 0) - a.shape[1]
        se.append(np.sqrt(rss_c / dof * np.diag(np.linalg.inv(a.T @ a))))
    nobs = 3 * np.count_nonzero(w > 0)
    return np.sqrt(rss / nobs), np.stack(se, 1)


@pytest.mark.parametrize("noise, dtype, rtol", [(1e-3, jnp.float32, 0.01), (0.0, jnp.float32, 0.1),
                                                (1e-3, jnp.float64, 1e-6), (0.0, jnp.float64, 1e-3)])
def test_inverse_lighting_rms_and_standard_errors_are_those_of_its_residual(noise, dtype, rtol):
    """`rms` and `std_errors` of `inverse_lighting` against the NumPy residual of the estimate it returns (float32:
    the estimate rounded to float32, so its residual on exact data is ~1e-6 of the data, which is what must be
    reported). Tolerances: 1 % with noise, 10 % on exact data in float32 (the residual pass itself sums in
    float32), 1e-6 / 1e-3 in float64."""
    obs, brdf = _obs(noise, dtype)
    res = solvers.inverse_lighting(obs, brdf, LMAX)
    assert res.coeffs.dtype == dtype and solvers.status_name(res.status) == "converged"
    rms, se = _reference(obs, res)
    assert rms > 0
    assert float(res.rms) == pytest.approx(rms, rel=rtol)
    np.testing.assert_allclose(np.asarray(res.std_errors, np.float64), se, rtol=rtol)
    assert np.all(np.isfinite(np.asarray(res.band_snr)))


def test_inverse_lighting_with_no_degree_of_freedom_has_infinite_standard_errors():
    """As many samples as unknowns (25 at l* = 4): the data fix the coefficients exactly but say nothing about the
    noise (s^2 = 0/0). Every standard error is inf and every band SNR 0 (were ~1e-7 and 4e6); one sample more,
    and they equal the least-squares ones."""
    obs, brdf = _obs(1e-2, jnp.float64, seed=1)
    n = jaxsh.num_coeffs(LMAX)
    idx = np.flatnonzero(np.sum(np.asarray(obs.normals) * np.asarray(obs.views), -1) > 0.2)
    idx = np.random.default_rng(2).choice(idx, n + 1, replace=False)
    exact = solvers.inverse_lighting(obs.subset(np.sort(idx[:n])), brdf, LMAX)
    assert np.all(np.asarray(exact.determined)) and np.all(np.isinf(np.asarray(exact.std_errors)))
    assert np.all(np.asarray(exact.band_snr) == 0)
    one_more = obs.subset(np.sort(idx))
    res = solvers.inverse_lighting(one_more, brdf, LMAX)
    np.testing.assert_allclose(np.asarray(res.std_errors), _reference(one_more, res)[1], rtol=1e-6)


def test_fit_brdf_sh_checks_rcond_and_accepts_disks_per_view():
    """`rcond` NaN or inf gave rank 0, rho all 0 and `converged`; a string a bare conversion error. Now a ValueError
    naming `rcond`. A disk source was accepted in one `Lighting` (as `total_sh`) but refused in the per-view list,
    asking to split it by a sigma this solver does not have: both forms now give the same fit. With fewer samples
    than unknowns the singular values keep their documented shape (C, n_unknowns), zero-padded."""
    gbs = [jaxsh.sphere_gbuffer(c, jnp.zeros(3), jnp.asarray(1.0)) for c in solvers.view_cameras(2, 12)]
    d = np.array([[0.0, 0.3, 1.0]]) / np.linalg.norm([0.0, 0.3, 1.0])
    lit = solvers.Lighting(jnp.asarray(np.r_[[[1.0, 1.0, 1.0]], np.zeros((8, 3))]), disk_directions=jnp.asarray(d),
                           disk_radius=jnp.asarray([0.3]), disk_radiance=jnp.asarray([[2.0, 2.0, 2.0]]))
    brdf = solvers.TorranceSparrow(KD, KS, None, 0.3)
    imgs = [np.asarray(solvers.predict(brdf, lit.split_disks(0.3, 8), g.normal, g.view, mask=g.mask)) for g in gbs]
    obs = solvers.observations(gbs, imgs)
    for bad in (np.nan, np.inf, -1.0, "x"):
        with pytest.raises(ValueError, match="rcond"):
            solvers.fit_brdf_sh(obs, lit, 2, rcond=bad)
    one = solvers.fit_brdf_sh(obs, lit, 2)
    per_view = solvers.fit_brdf_sh(obs, [lit, lit], 2)
    np.testing.assert_allclose(np.asarray(per_view.rho), np.asarray(one.rho), atol=1e-10)
    few = solvers.fit_brdf_sh(obs.subset(np.arange(6)), lit, 2)
    assert np.asarray(few.stats["singular_values"]).shape == (3, few.n_unknowns)
    assert np.all(np.asarray(few.stats["singular_values"])[:, 6:] == 0)


def test_rms_pair_is_nan_when_the_residual_or_the_data_are():
    """A NaN residual is no perfect fit: `rel_rms` was 0 when `rms` was NaN (the docs: never NaN unless the
    residual itself is)."""
    for rss, data_ss in ((np.nan, 1.0), (1.0, np.nan), (np.nan, np.nan)):
        rms, rel = rms_pair(jnp.asarray(rss), jnp.asarray(data_ss), jnp.asarray(3.0))
        assert np.isnan(float(rel))
    rms, rel = rms_pair(jnp.asarray(0.0), jnp.asarray(0.0), jnp.asarray(3.0))
    assert float(rms) == 0 and float(rel) == 0


@pytest.fixture(scope="module")
def small_obs():
    brdf = solvers.TorranceSparrow(jnp.array([0.6, 0.45, 0.3]), jnp.array([0.3, 0.3, 0.3]), jnp.asarray(1.6),
                                   jnp.asarray(0.12))
    cap = solvers.sphere_capture(brdf, size=24, n_views=2, noise=0.01)
    return solvers.observations(cap.gbuffers, cap.images)


def test_factorize_keeps_stage_one_status_on_too_few_pixels(small_obs):
    """Six valid pixels for 49 lighting coefficients: stage 1 says `ill_conditioned`, and the refinement, which
    solves for the same lighting plus the source, used to report `converged` with rms 0 and zero standard errors."""
    w = np.zeros(small_obs.n_samples)
    w[np.linspace(0, small_obs.n_samples - 1, 6).astype(int)] = 1.0
    obs = eqx.tree_at(lambda o: o.weights, small_obs, jnp.asarray(w))
    r = solvers.factorize(obs, 6)
    assert solvers.status_name(r.status) != "converged"


@pytest.mark.parametrize("kw, name", [
    (dict(search_pixels=5), "search_pixels"), (dict(region=(1, 2)), "region"), (dict(region="up"), "region"),
    (dict(region=([0.0, 0.0, 1.0], -1.0)), "region"), (dict(region=([0.0, 0.0, 0.0], 0.5)), "region"),
    (dict(rtol=-1.0), "rtol"), (dict(atol=np.nan), "atol"), (dict(key=5), "key"),
])
def test_factorize_bad_options_are_named_errors(small_obs, kw, name):
    """Options that were accepted and gave garbage marked converged (`search_pixels=5`: K_s 0.94 for 0.3), a
    `max_steps_reached`/`nonfinite` status (`rtol=-1`, `atol=nan`), nothing (`key=5`, a negative region radius),
    or an error from inside a matrix product (`region=(1, 2)`)."""
    with pytest.raises(ValueError, match=rf"`{name}"):
        solvers.factorize(small_obs, 6, **kw)
