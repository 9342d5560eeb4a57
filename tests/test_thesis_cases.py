"""Special cases of Ramamoorthi's thesis ch. 3, checked against the library (issue 14).

- (3.26) the f(l) ambiguity of the mirror BRDF: lighting L_lm f(l) seen in a BRDF with spectrum
  rho_l / f(l) gives the same images as L_lm in rho_l, so factorization cannot find f(l);
- (3.18-3.22) uniform lighting: an isotropic BRDF is seen only through its l = 0 term (its albedo);
  a mirror and a Lambertian surface look the same, and the roughness is undetermined;
- (3.52-3.53) non-normal exitance: the size of the corrections to R&H eq. 20 / thesis eq. 3.51.

References are closed forms, scipy's spherical harmonics and Legendre polynomials, or numpy
quadrature written here, never the code under test alone.
"""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special as sp

import jaxsh
import solvers

from .helpers import scipy_real_sh


def _sphere_views(n_views=3, size=24):
    gbs = [jaxsh.sphere_gbuffer(c, np.zeros(3), 1.0) for c in solvers.view_cameras(n_views, size)]
    ns = [np.asarray(g.normal)[np.asarray(g.mask)] for g in gbs]
    vs = [np.asarray(g.view)[np.asarray(g.mask)] for g in gbs]
    return gbs, ns, vs


def _reflect(v, n):
    return 2 * np.sum(n * v, -1, keepdims=True) * n - v


def _deg(lmax):
    return np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1)


# --------------------------------------------------------------------------- (a) thesis eq. 3.26


def test_mirror_f_of_l_ambiguity_identical_images():
    """Eq. 3.26: a 'mirror' BRDF with spectrum f(l) reflects sum_l f(l) L_lm Y_lm(R). The microfacet
    lobe of R&H eq. 20 is one such f(l) = exp(-(sigma l)^2): lighting L in a sigma_1 lobe and lighting
    L exp(-(sigma_1 l)^2) / exp(-(sigma_2 l)^2) in a sigma_2 lobe give the same image, and both are the
    closed form computed with scipy's harmonics."""
    lmax, s1, s2 = 8, 0.12, 0.05
    rng = np.random.default_rng(0)
    L = rng.normal(size=((lmax + 1) ** 2, 3))
    deg = _deg(lmax)
    f1, f2 = np.exp(-((s1 * deg) ** 2)), np.exp(-((s2 * deg) ** 2))
    _, ns, vs = _sphere_views(1, 24)
    n, v = ns[0], vs[0]
    want = scipy_real_sh(_reflect(v, n), lmax) @ (f1[:, None] * L)  # thesis eq. 3.26 with f = f1
    a = np.asarray(jaxsh.render_practical(n, v, 0.0, 1.0, None, s1, slow_sh=L).total)
    b = np.asarray(jaxsh.render_practical(n, v, 0.0, 1.0, None, s2, slow_sh=L * (f1 / f2)[:, None]).total)
    np.testing.assert_allclose(a, want, atol=1e-10 * np.abs(want).max())
    np.testing.assert_allclose(b, a, atol=1e-10 * np.abs(want).max())


def test_mirror_f_of_l_ambiguity_factorization_cannot_resolve_it():
    """The images determine only the product f(l) L_lm: inverse lighting under any assumed f(l)
    (here the lobe filters of two roughnesses, `deconvolve=True`) fits the data equally well, with the
    lighting rescaled band by band by the ratio of the filters. So the per-band scale f(l) (and with it
    sigma) cannot come from the images: `factorize` takes sigma from an assumed directional source
    (R&H eq. 26), an extra assumption, exactly as the thesis says."""
    lmax = 6
    rng = np.random.default_rng(1)
    L = rng.normal(size=((lmax + 1) ** 2, 3))
    L[0] += 4.0
    deg = _deg(lmax)
    s_true = 0.1
    gbs, ns, vs = _sphere_views(3, 24)
    imgs = []
    for g, n, v in zip(gbs, ns, vs):
        img = np.zeros(np.asarray(g.mask).shape + (3,))
        img[np.asarray(g.mask)] = scipy_real_sh(_reflect(v, n), lmax) @ (np.exp(-((s_true * deg) ** 2))[:, None] * L)
        imgs.append(img)
    obs = solvers.observations(gbs, imgs)
    fits = {}
    for s in (0.02, 0.1, 0.25):
        brdf = solvers.TorranceSparrow(jnp.zeros(3), jnp.ones(3), None, jnp.asarray(s))
        fits[s] = solvers.inverse_lighting(obs, brdf, lmax, deconvolve=True)
    for s, r in fits.items():
        assert float(r.rel_rms) < 1e-6  # every assumed f(l) explains the images (floor sqrt(eps), module test_inverse)
        ratio = np.exp(-((s_true * deg) ** 2)) / np.exp(-((s * deg) ** 2))
        np.testing.assert_allclose(np.asarray(r.coeffs), L * ratio[:, None], rtol=1e-7, atol=1e-7 * np.abs(L).max())
    # the mirror (no deconvolution) reads the filtered lighting f(l) L directly
    mirror = solvers.inverse_lighting(obs, solvers.TorranceSparrow(jnp.zeros(3), jnp.ones(3), None, jnp.asarray(0.1)), lmax)
    np.testing.assert_allclose(np.asarray(mirror.coeffs), L * np.exp(-((s_true * deg) ** 2))[:, None], atol=1e-7 * np.abs(L).max())


# --------------------------------------------------------------------------- (b) uniform lighting, 3.18-3.22


def test_uniform_lighting_every_brdf_looks_alike():
    """Eq. 3.22: under uniform lighting L the radiance is L times the albedo (the l = 0 term of the
    BRDF): the specular lobe's width is invisible, and a mirror (K_s = 1, F = 1) looks exactly like a
    Lambertian surface of albedo 1 (K_d = 1/pi in R&H's convention)."""
    lmax, lum = 12, 0.7
    sh = np.zeros(((lmax + 1) ** 2, 1))
    sh[0, 0] = lum * 2 * np.sqrt(np.pi)  # L(omega) = lum everywhere (Y_00 = 1 / (2 sqrt(pi)))
    _, ns, vs = _sphere_views(1, 24)
    n, v = ns[0], vs[0]
    imgs = {s: np.asarray(jaxsh.render_practical(n, v, 0.0, 1.0, None, s, slow_sh=sh).total) for s in (0.02, 0.1, 0.5)}
    for img in imgs.values():
        np.testing.assert_allclose(img, lum, rtol=1e-12)
    lamb = np.asarray(jaxsh.render_practical(n, v, 1 / np.pi, 0.0, None, 0.1, slow_sh=sh).total)
    np.testing.assert_allclose(lamb, lum, rtol=1e-12)
    # the reference renderer (quadrature, no SH), uniform environment: the Lambertian surface of albedo 1 is lum
    env = np.full((32, 64, 1), lum)
    ref = np.asarray(jaxsh.render_reference(n, v, 1 / np.pi, 0.0, None, 0.1, envmap=env))
    np.testing.assert_allclose(ref, lum, rtol=1e-3)


def test_uniform_lighting_roughness_is_undetermined():
    """Thesis sec. 3.2.2: under uniform lighting BRDF estimation is ill-posed, only the lowest-frequency
    term is found: fitting K_d, K_s, sigma (F = 1) to images of a glossy sphere, the fit reproduces the
    images but cannot tell sigma nor separate K_d from K_s (one albedo pi K_d + K_s)."""
    lmax, lum = 12, 1.0
    sh = np.zeros(((lmax + 1) ** 2, 3))
    sh[0] = lum * 2 * np.sqrt(np.pi)
    gbs, ns, vs = _sphere_views(3, 24)
    kd, ks, sigma = 0.15, 0.4, 0.1
    imgs = []
    for g, n, v in zip(gbs, ns, vs):
        img = np.zeros(np.asarray(g.mask).shape + (3,))
        img[np.asarray(g.mask)] = np.pi * kd + ks  # eq. 3.22, closed form: lum * albedo
        imgs.append(img)
    obs = solvers.observations(gbs, imgs)
    res = solvers.fit_brdf(obs, solvers.Lighting(jnp.asarray(sh), None, None), fresnel=False)
    assert float(res.rel_rms) < 1e-8
    albedo = np.pi * np.asarray(res.brdf.kd) + np.asarray(res.brdf.ks)
    np.testing.assert_allclose(albedo, np.pi * kd + ks, rtol=1e-8)
    # sigma and the Kd/Ks split are not determined by these images
    assert solvers.status_name(res.status) == "ill_conditioned"
    assert not np.isfinite(float(res.std_errors.sigma)) and not np.any(np.isfinite(np.asarray(res.std_errors.kd)))
    print("uniform lighting fit:", solvers.status_name(res.status), np.asarray(res.brdf.kd), np.asarray(res.brdf.ks),
          float(res.brdf.sigma), np.asarray(res.std_errors.kd), float(res.std_errors.sigma))


# --------------------------------------------------------------------------- (c) non-normal exitance, 3.52-3.53


def _ts_zonal_reference(sigma, lmax, theta_o, nt=400, npf=800):
    """A_l(theta_o) = int S(theta_h) / (4 cos theta_o) P_l(omega_i . R) d omega_i over the upper hemisphere
    (the Torrance-Sparrow lobe, F = 1), by Gauss-Legendre in cos(theta_i) x midpoint azimuth in the normal
    frame, with scipy's Legendre polynomials."""
    x, wx = np.polynomial.legendre.leggauss(nt)
    ct, w = 0.5 * (x + 1), 0.5 * wx
    phi = (np.arange(npf) + 0.5) * 2 * np.pi / npf
    st = np.sqrt(1 - ct**2)
    wi = np.stack([st[:, None] * np.cos(phi)[None], st[:, None] * np.sin(phi)[None], np.broadcast_to(ct[:, None], (nt, npf))], -1)
    wo = np.array([np.sin(theta_o), 0.0, np.cos(theta_o)])
    r = np.array([-np.sin(theta_o), 0.0, np.cos(theta_o)])
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    th = np.arccos(np.clip(h[..., 2], -1, 1))
    f = np.exp(-((th / sigma) ** 2)) / (np.pi * sigma**2) / (4 * np.cos(theta_o))
    u = wi @ r
    p = np.stack([sp.eval_legendre(l, u) for l in range(lmax + 1)], -1)
    return np.einsum("ij,ijl->l", f * w[:, None] * (2 * np.pi / npf), p)


def test_half_angle_first_order_eq_3_52():
    """Eq. 3.52: with theta_i', phi_i' the polar coordinates of omega_i about R (phi_i' = 0 in the plane of
    n and R), theta_h^2 = (theta_i'/2)^2 (1 + sin^2 phi_i' tan^2 theta_o) to leading order in theta_i'."""
    for theta_o in (0.0, 0.3, 0.6, 1.0):
        wo = np.array([np.sin(theta_o), 0.0, np.cos(theta_o)])
        r = np.array([-np.sin(theta_o), 0.0, np.cos(theta_o)])
        e1 = np.array([np.cos(theta_o), 0.0, np.sin(theta_o)])
        e2 = np.array([0.0, 1.0, 0.0])
        for phi in np.linspace(0, 2 * np.pi, 9):
            ti = 1e-3
            wi = np.cos(ti) * r + np.sin(ti) * (np.cos(phi) * e1 + np.sin(phi) * e2)
            h = (wi + wo) / np.linalg.norm(wi + wo)
            th2 = np.arccos(np.clip(h[2], -1, 1)) ** 2
            pred = (ti / 2) ** 2 * (1 + np.sin(phi) ** 2 * np.tan(theta_o) ** 2)
            assert th2 == pytest.approx(pred, rel=1e-2), (theta_o, phi)


def test_non_normal_exitance_corrections_eq_3_53():
    """Eq. 3.53 and the text after it: at non-normal exitance the zonal coefficients of the lobe about R
    differ from their normal-exitance values by O(theta_o^2 (sigma l)^2), none at l = 0 (the lobe normalised
    by cos theta_o keeps its area). Measured by quadrature: the relative correction is
    c theta_o^2 (sigma l)^2 with c in [0.50, 0.75] for theta_o <= 0.6, sigma = 0.05, 0.1, l <= 12.

    The library: `jaxsh.torrance_sparrow_spectrum(sigma, lmax, theta_o)` gives these A_l(theta_o)
    (checked here against the quadrature); the practical model (R&H eq. 24) and the solvers use
    exp(-(sigma l)^2) at every theta_o, i.e. they do *not* apply the corrections (their size, ~0.6 theta_o^2
    (sigma l)^2: 0.4 % at theta_o = 0.2, sigma l = 0.4; 13 % at theta_o = 0.4, sigma l = 1.2)."""
    lmax = 12
    ls = np.arange(2, lmax + 1, 2)
    for sigma in (0.05, 0.1):
        a0 = _ts_zonal_reference(sigma, lmax, 0.0)
        for theta_o in (0.1, 0.2, 0.4):
            a = _ts_zonal_reference(sigma, lmax, theta_o)
            np.testing.assert_allclose(np.asarray(jaxsh.torrance_sparrow_spectrum(sigma, lmax, theta_o)), a, rtol=1e-5, atol=1e-7)
            assert a[0] == pytest.approx(a0[0], rel=1e-6)  # no correction at l = 0
            c = (a[ls] / a0[ls] - 1) / (theta_o**2 * (sigma * ls) ** 2)
            assert np.all((c > 0.5) & (c < 0.8)), (sigma, theta_o, c)
