"""Textured (per-texel) `fit_brdf` against an independent NumPy renderer of R&H's Torrance-Sparrow (sec. 5.2).

The images are drawn here from docs/conventions.md (BRDFs, directional lighting, orthographic cameras: row 0 is
the top of the image, world +y), not with jaxsh's renderer: under directional light eq. 24 is the BRDF itself, so
a fit recovers the texture to rounding. The last four tests pin defects the textured audit fixed: a negative
Kd from textured='kd', singular per-texel systems set to 0, standard errors that counted unobserved texels, and the
shared Ks's NaN standard error.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers

N = 16
C2W = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10], [0, 0, 0, 1]], float)
KS = np.array([0.3, 0.35, 0.4])
MU, SIGMA, E = 1.5, 0.2, 0.8


def _sphere():
    i, j = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    x, y = (j + 0.5 - N / 2) * 2.2 / N, -(i + 0.5 - N / 2) * 2.2 / N  # row 0 at the top (+y)
    mask = x * x + y * y < 1
    n = np.stack([x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, None))], -1) * mask[..., None]
    return mask, n, np.broadcast_to([0.0, 0.0, 1.0], n.shape).copy()


def _fresnel(c, mu):  # exact unpolarized dielectric reflectance (textbook form)
    g = np.sqrt(mu * mu - 1 + c * c)
    return 0.5 * ((g - c) / (g + c)) ** 2 * (1 + ((c * (g + c) - 1) / (c * (g - c) + 1)) ** 2)


def _render(n, v, kd, ks, mu, sigma, d):
    """R&H Torrance-Sparrow under one directional source d of irradiance E: rho cos(theta_i) E."""
    ci, co = n @ d, np.sum(n * v, -1)
    h = (d + v) / np.linalg.norm(d + v, axis=-1, keepdims=True)
    th = np.arccos(np.clip(np.sum(h * n, -1), -1, 1))
    f = 1.0 if mu is None else _fresnel(np.clip(co, 1e-12, 1), mu) / ((mu - 1) / (mu + 1)) ** 2
    spec = f * np.exp(-(th / sigma) ** 2) / (np.pi * sigma**2) / (4 * np.where(co > 0, co, 1))
    lit = ((ci > 0) & (co > 0))[..., None]
    return np.where(lit, kd * ci[..., None] * E + ks * spec[..., None] * E, 0.0)


def _dirs(k):
    az, el = np.arange(k) * 2 * np.pi / k, np.deg2rad(np.linspace(15, 60, k))
    return np.stack([np.sin(el) * np.cos(az), np.sin(el) * np.sin(az), np.cos(el)], 1)


def _texture():
    j, i = np.meshgrid((np.arange(N) + 0.5) / N, (np.arange(N) + 0.5) / N)
    chk = ((np.arange(N)[:, None] // 4 + np.arange(N)[None, :] // 4) % 2).astype(float)  # a flip or transpose shows
    return np.stack([0.2 + 0.5 * j, 0.55 - 0.3 * i, 0.15 + 0.2 * chk + 0.1 * i * j], -1)


def _capture(tex, sigma=SIGMA, k=6, noise=0.0, seed=0, n_texels=N * N):
    mask, n, v = _sphere()
    g = jaxsh.GBuffer(jnp.asarray(mask), jnp.asarray(n), jnp.asarray(n), jnp.asarray(v), jnp.asarray(10 - n[..., 2]))
    rng = np.random.default_rng(seed)
    dirs = _dirs(k)
    imgs = [(_render(n, v, tex, KS, MU, sigma, d) + noise * rng.normal(size=(N, N, 3))) * mask[..., None] for d in dirs]
    texel = np.arange(N * N, dtype=np.int32).reshape(N, N)
    obs = solvers.observations([g] * k, imgs, texel=[texel] * k, n_texels=n_texels)
    lights = [solvers.Lighting(None, jnp.asarray(d[None]), jnp.full((1, 3), E)) for d in dirs]
    return obs, lights, mask, n, v


def test_textured_kd_recovers_the_texture_in_the_pixel_grid():
    """Kd per pixel (row i, column j of the images, row 0 at the top), one Ks, mu, sigma: all to rounding; texels
    no sample sees are 0 with an infinite standard error and a zero count."""
    tex = _texture()
    obs, lights, mask, _, _ = _capture(tex)
    r = solvers.fit_brdf(obs, lights, textured="kd")
    assert r.status == solvers.Status.converged
    kd = np.asarray(r.brdf.kd).reshape(N, N, 3)
    np.testing.assert_allclose(kd[mask], tex[mask], atol=1e-7)
    np.testing.assert_allclose(np.asarray(r.brdf.ks)[0], KS, atol=1e-7)
    assert abs(float(r.brdf.sigma) - SIGMA) < 1e-7 and abs(float(r.brdf.mu) - MU) < 1e-5
    count = np.asarray(r.texel_count).reshape(N, N)
    assert np.all(count[mask] == 6) and np.all(count[~mask] == 0)
    assert np.all(kd[~mask] == 0) and np.all(np.isinf(np.asarray(r.std_errors.kd).reshape(N, N, 3)[~mask]))


def test_textured_kd_ks_without_fresnel_folds_the_fresnel_factor_into_each_texel():
    """One camera: theta_o is fixed per texel, so `kd_ks` with F = 1 fits Ks(x) F(mu, theta_o)/F(mu, 0) exactly
    (the factor computed here from the exact dielectric formula), and Kd(x) to rounding."""
    tex = _texture()
    obs, lights, mask, n, v = _capture(tex)
    r = solvers.fit_brdf(obs, lights, textured="kd_ks", fresnel=False)
    assert r.status == solvers.Status.converged and r.brdf.mu is None
    kd = np.asarray(r.brdf.kd).reshape(N, N, 3)
    ks = np.asarray(r.brdf.ks).reshape(N, N, 3)
    co = n[..., 2]
    want = KS * (_fresnel(np.clip(co, 1e-12, 1), MU) / ((MU - 1) / (MU + 1)) ** 2)[..., None]
    np.testing.assert_allclose(kd[mask], tex[mask], atol=1e-7)
    # where some view carries a specular signal (elsewhere Ks is determined only to rounding / S)
    spec = np.max([_render(n, v, np.zeros(3), np.ones(3), None, SIGMA, d)[..., 0] for d in _dirs(6)], 0)
    sel = mask & (spec > 1e-3 * spec.max())
    assert sel.sum() > 0.5 * mask.sum()
    np.testing.assert_allclose(ks[sel], want[sel], rtol=1e-6)
    assert abs(float(r.brdf.sigma) - SIGMA) < 1e-7


def test_textured_kd_is_nonnegative_and_usable():
    """A black region plus noise: the unconstrained per-texel Kd goes negative. The fit must return Kd >= 0 (as the
    docstring promises and `TorranceSparrow`, `predict` and `jaxsh render` require), no worse than clipping."""
    tex = _texture()
    tex[:, : N // 2] = 0.0
    obs, lights, mask, _, _ = _capture(tex, noise=0.005, seed=1)
    r = solvers.fit_brdf(obs, lights, textured="kd")
    kd = np.asarray(r.brdf.kd)
    assert r.status == solvers.Status.converged
    assert kd.min() >= 0 and np.asarray(r.brdf.ks).min() >= 0
    solvers.predict(r.brdf, lights[0], obs.normals, obs.views, texel=np.asarray(obs.texel))  # no ValueError


def test_textured_kd_ks_texels_without_specular_signal_keep_their_kd():
    """sigma = 0.02: far from the highlights the specular image underflows to exactly 0, so those texels'
    (Kd, Ks) systems are singular. Their Kd is still determined by the diffuse samples; it must be returned
    (not 0), and sigma must not be pulled to where no specular term underflows (before: 0.067)."""
    tex = _texture()
    obs, lights, mask, _, _ = _capture(tex, sigma=0.02)
    r = solvers.fit_brdf(obs, lights, textured="kd_ks", fresnel=False)
    assert abs(float(r.brdf.sigma) - 0.02) < 1e-4
    np.testing.assert_allclose(np.asarray(r.brdf.kd).reshape(N, N, 3)[mask], tex[mask], atol=1e-4)


def test_textured_std_errors_do_not_depend_on_unobserved_texels():
    """Texels no sample sees carry no parameter of the residual: declaring more of them (n_texels) must not change
    any standard error. (Before: with 4 N^2 texels, 2 x 3 x T > the samples, n - p <= 0 and s2 = RSS: sigma's error
    0.71 against a Monte Carlo spread of 0.006.)"""
    tex = _texture()
    out = []
    for n_texels in (N * N, 4 * N * N):
        obs, lights, mask, _, _ = _capture(tex, k=6, noise=0.01, seed=2, n_texels=n_texels)
        r = solvers.fit_brdf(obs, lights, textured="kd_ks", fresnel=False)
        out.append((float(r.std_errors.sigma), np.asarray(r.std_errors.kd)[: N * N]))
    assert out[0][0] == pytest.approx(out[1][0], rel=1e-9)
    np.testing.assert_allclose(out[0][1], out[1][1], rtol=1e-9)


def test_textured_kd_shared_ks_standard_error_is_the_linear_least_squares_one():
    """Given mu and sigma the model is linear in (Kd per texel, Ks): the shared Ks's standard error is
    sqrt(s2 [(A^T A)^-1]_{ks,ks}) of that design matrix, built here from the NumPy renderer at the fitted sigma."""
    tex = _texture()
    obs, lights, mask, n, v = _capture(tex, noise=0.01, seed=3)
    r = solvers.fit_brdf(obs, lights, textured="kd", fresnel=False)
    sigma = float(r.brdf.sigma)
    dirs = _dirs(6)
    idx = np.flatnonzero(mask.ravel())
    T = idx.size
    c = 0  # one channel suffices (the same design in each)
    rows, ys = [], []
    obs_vals = np.asarray(obs.values)[:, c]
    for k, d in enumerate(dirs):
        dk = _render(n, v, np.ones(3), np.zeros(3), None, sigma, d)[..., c].ravel()[idx]
        sk = _render(n, v, np.zeros(3), np.ones(3), None, sigma, d)[..., c].ravel()[idx]
        a = np.zeros((T, T + 1))
        a[np.arange(T), np.arange(T)] = dk
        a[:, T] = sk
        rows.append(a)
    A = np.concatenate(rows)
    y = obs_vals  # samples in view order, each view's object pixels in raster order (as `observations` stores them)
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    rss_all = float(np.sum((np.asarray(r.fitted) - np.asarray(obs.values)) ** 2))
    nobs, npar = 3 * A.shape[0], 3 * T + 3 + 1
    s2 = rss_all / (nobs - npar)
    want = np.sqrt(s2 * np.linalg.inv(A.T @ A)[T, T])
    assert np.isfinite(float(r.std_errors.ks[0, c]))
    assert float(r.std_errors.ks[0, c]) == pytest.approx(want, rel=1e-6)


def test_textured_kd_ks_flags_the_texels_whose_ks_the_images_do_not_determine():
    """sigma = 0.2, noise 0.005: far from every highlight the specular image nearly vanishes and the least-squares
    Ks is noise over it (values beyond 1e6, status converged). `stats["undetermined"]["ks"]` must flag a texel
    exactly when its Ks's one-sigma error is not below the texture's level. The error is computed here from the
    NumPy renderer's unit images and the known noise, sqrt(noise^2 [(A^T A)^-1]_ss) per texel, and the level from
    the true texture. Borderline texels (within 2x of the level) may fall either way. Unflagged texels must be within
    5 of those errors of the truth. Lighting 1000x dimmer (every estimate and error 1000x larger) must give the
    same flags."""
    tex = _texture()
    noise = 0.005
    obs, lights, mask, n, v = _capture(tex, noise=noise, seed=2)
    r = solvers.fit_brdf(obs, lights, textured="kd_ks", fresnel=False)
    und = np.asarray(r.stats["undetermined"]["ks"]).reshape(N, N, 3)
    ks = np.asarray(r.brdf.ks).reshape(N, N, 3)
    dirs = _dirs(6)
    unit_d = np.stack([_render(n, v, np.ones(3), np.zeros(3), None, SIGMA, d)[..., 0] for d in dirs])
    unit_s = np.stack([_render(n, v, np.zeros(3), np.ones(3), None, SIGMA, d)[..., 0] for d in dirs])
    dd, ds, ss = (unit_d * unit_d).sum(0), (unit_d * unit_s).sum(0), (unit_s * unit_s).sum(0)
    det = dd * ss - ds * ds
    se_true = np.where(det > 0, noise * np.sqrt(dd / np.where(det > 0, det, 1.0)), np.inf)[..., None]
    level = np.maximum(tex.max(-1), np.median(tex[mask].max(-1)))[..., None]
    clear_bad = np.broadcast_to(mask[..., None] & (se_true > 2 * level), ks.shape)
    clear_good = np.broadcast_to(mask[..., None] & (se_true < level / 2), ks.shape)
    assert clear_bad[..., 0].sum() > 50 and clear_good[..., 0].sum() > 50  # both kinds in this capture (of 164 texels)
    assert np.all(und[clear_bad]) and not np.any(und[clear_good])
    assert np.all(und[~mask])  # unobserved texels
    assert np.abs(ks[mask]).max() > 1e6  # the values themselves are returned as the least squares give them
    co = n[..., 2]
    want = KS * (_fresnel(np.clip(co, 1e-12, 1), MU) / ((MU - 1) / (MU + 1)) ** 2)[..., None]
    ok = mask[..., None] & ~und
    assert np.all(np.abs(ks - want)[ok] < 5 * np.broadcast_to(se_true, ks.shape)[ok])
    dim = [solvers.Lighting(None, lt.fast_directions, lt.fast_energy * 1e-3) for lt in lights]
    r2 = solvers.fit_brdf(obs, dim, textured="kd_ks", fresnel=False)
    np.testing.assert_allclose(np.asarray(r2.brdf.kd), 1e3 * np.asarray(r.brdf.kd), rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(r2.stats["undetermined"]["ks"]), np.asarray(r.stats["undetermined"]["ks"]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lambertian_data_leave_mu_and_sigma_undetermined(seed):
    """K_s = 0 (a matte object), 6 lights, 0.5 % noise: mu and sigma act only through K_s S, so the images do not
    determine them. Before, the Jacobian's unit-scaled columns made them look determined: sigma 0.018 +- 0.016 in one
    noise draw and 0.675 +- 0.200 in another, `undetermined` False, and noise-free data ended at
    `max_steps_reached`. Now both are undetermined with infinite errors and status converged; Kd is recovered.
    A weak but real specular term (K_s 0.03, 10 standard errors) keeps sigma determined and within 3 errors."""
    mask, n, v = _sphere()
    g = jaxsh.GBuffer(jnp.asarray(mask), jnp.asarray(n), jnp.asarray(n), jnp.asarray(v), jnp.asarray(10 - n[..., 2]))
    dirs = _dirs(6)
    lights = [solvers.Lighting(None, jnp.asarray(d[None]), jnp.full((1, 3), E)) for d in dirs]
    kd = np.array([0.5, 0.4, 0.3])
    rng = np.random.default_rng(seed)
    for ks, noise in ((np.zeros(3), 0.005), (np.zeros(3), 0.0), (np.full(3, 0.03), 0.0005)):
        imgs = [(_render(n, v, kd, ks, MU, SIGMA, d) + noise * rng.normal(size=(N, N, 3))) * mask[..., None]
                for d in dirs]
        obs = solvers.observations([g] * 6, imgs)
        r = solvers.fit_brdf(obs, lights)
        assert solvers.status_name(r.status) == "converged"
        np.testing.assert_allclose(np.asarray(r.brdf.kd), kd, atol=5 * noise + 1e-6)
        und = {k: bool(x) for k, x in r.stats["undetermined"].items()}
        if ks[0] == 0:
            assert und == {"mu": True, "sigma": True}
            assert np.isinf(float(r.std_errors.sigma)) and np.isinf(float(r.std_errors.mu))
        else:
            assert not und["sigma"] and abs(float(r.brdf.sigma) - SIGMA) < 3 * float(r.std_errors.sigma)
