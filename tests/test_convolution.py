"""Spectra and reflection as convolution: closed forms, quadrature, brute force, identities."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, strategies as st
from scipy.special import eval_legendre, gammaln, gammasgn, roots_jacobi

import jaxsh

from .helpers import random_dirs, random_rotation

# ---------------------------------------------------------------- test BRDFs (vector and angle forms)


def lambert_brdf(kd=1.0):
    def f(wi, wo, n):
        return jnp.where(jnp.sum(wi * n, -1) > 0, kd, 0.0) * jnp.ones(jnp.broadcast_shapes(wi.shape, wo.shape, n.shape)[:-1])

    return f


def smooth_brdf(wi, wo, n):
    """A smooth isotropic, non-radially-symmetric BRDF: 1 + 0.5 (wi_t . wo_t) + 0.3 cos(theta_o) (not reciprocal)."""
    ci = jnp.sum(wi * n, -1)
    co = jnp.sum(wo * n, -1)
    tt = jnp.sum(wi * wo, -1) - ci * co
    return jnp.where((ci > 0) & (co > 0), 1.0 + 0.5 * tt + 0.3 * co, 0.0)


def smooth_transfer(ti, to, dphi):
    return jnp.cos(ti) * (1 + 0.5 * jnp.sin(ti) * jnp.sin(to) * jnp.cos(dphi) + 0.3 * jnp.cos(to))


def glossy_transfer_reciprocal(sigma=0.35, kd=0.3, ks=0.6):
    """rho~ = rho cos(ti) cos(to) of kd + ks S(theta_h)/(4 cos ti cos to): reciprocal by construction."""

    def f(ti, to, dphi):
        ti, to, dphi = jnp.broadcast_arrays(ti, to, dphi)
        wi = jnp.stack([jnp.sin(ti), jnp.zeros_like(ti), jnp.cos(ti)], -1)
        wo = jnp.stack([jnp.sin(to) * jnp.cos(dphi), jnp.sin(to) * jnp.sin(dphi), jnp.cos(to)], -1)
        h = wi + wo
        h = h / jnp.linalg.norm(h, axis=-1, keepdims=True)
        th = jnp.arccos(jnp.clip(h[..., 2], -1, 1))
        s = jnp.exp(-((th / sigma) ** 2)) / (jnp.pi * sigma**2)
        return kd * jnp.cos(ti) * jnp.cos(to) + ks * s / 4

    return f


def _band_limited_lighting(rng, lmax, channels=None):
    shape = (jaxsh.num_coeffs(lmax),) + ((channels,) if channels else ())
    c = rng.normal(size=shape) / (1 + np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1))[(...,) + (None,) * (len(shape) - 1)]
    return c


# ---------------------------------------------------------------- Lambertian


def test_lambertian_printed_values():
    """R&H 2001 eq. 16 and thesis eq. 3.33 (printed to 2-3 decimals)."""
    a = np.asarray(jaxsh.lambertian_spectrum(6))
    np.testing.assert_allclose(a[:5], [3.14, 2.09, 0.79, 0.0, -0.13], atol=6e-3)
    np.testing.assert_allclose(a, [3.142, 2.094, 0.785, 0, -0.131, 0, 0.049], atol=6e-4)
    np.testing.assert_allclose(a[:3], [np.pi, 2 * np.pi / 3, np.pi / 4], rtol=1e-15)


def test_lambertian_closed_form_vs_quadrature():
    lmax = 40
    a = np.asarray(jaxsh.lambertian_spectrum(lmax))
    x, w = np.polynomial.legendre.leggauss(64)  # exact for u P_l(u) on [0, 1]
    u, w = (x + 1) / 2, w / 2
    num = [2 * np.pi * np.sum(w * u * eval_legendre(l, u)) for l in range(lmax + 1)]
    np.testing.assert_allclose(a, num, atol=1e-12)
    # odd l > 1 vanish; even terms fall off as l^{-5/2} (thesis sec. 3.2.4)
    assert np.all(a[3::2] == 0)
    ratio = a[40] / a[20]
    assert abs(abs(ratio) - 2.0 ** -2.5) < 0.02


# ---------------------------------------------------------------- Phong


@given(st.floats(-0.9, 300.0), st.integers(0, 2**32 - 1))
def test_phong_exact_vs_quadrature(s, seed):
    lmax = 12
    a = np.asarray(jaxsh.phong_spectrum(jnp.asarray(s), lmax))
    # Gauss-Jacobi with weight (1+x)^s is exact for u^s P_l(u), u = (1+x)/2 (scipy's nodes).
    x, w = roots_jacobi(40, 0.0, s)
    u = (x + 1) / 2
    num = [(s + 1) * 2.0 ** (-s - 1) * np.sum(w * eval_legendre(l, u)) for l in range(lmax + 1)]
    np.testing.assert_allclose(a, num, atol=5e-9, rtol=1e-7)


@pytest.mark.parametrize("s", [1, 2, 3, 8, 15])
def test_phong_integer_products_eq_3_37(s):
    """Thesis eq. 3.37 (MacRobert's products) for integer s."""
    lmax = 10
    a = np.asarray(jaxsh.phong_spectrum(jnp.asarray(float(s)), lmax))
    for l in range(lmax + 1):
        if l % 2:
            num = np.prod([s + 1] + [s - k for k in range(1, l - 1, 2)])
            den = np.prod([s + k for k in range(2, l + 2, 2)])
        else:
            num = np.prod([s - k for k in range(0, l, 2)]) if l > 0 else 1.0
            den = np.prod([s + k for k in range(3, l + 2, 2)]) if l > 0 else 1.0
        assert a[l] == pytest.approx(num / den, abs=1e-13)


def test_phong_s1_is_lambertian_over_pi():
    np.testing.assert_allclose(jaxsh.phong_spectrum(jnp.asarray(1.0), 20), np.asarray(jaxsh.lambertian_spectrum(20)) / np.pi, atol=1e-14)


def test_phong_large_s_stable_and_gaussian_limit():
    """s = 1e4, l <= 100: finite; log A = -l^2 (1/2s - 1/2s^2) + O(l^4/s^2) (thesis eq. 3.39)."""
    s = 1e4
    a = np.asarray(jaxsh.phong_spectrum(jnp.asarray(s), 100))
    assert np.all(np.isfinite(a)) and np.all(a > 0)
    l = np.arange(101)
    np.testing.assert_allclose(np.log(a), -(l**2) * (1 / (2 * s) - 1 / (2 * s * s)), atol=2 * (l**4 / s**2).max() + 1e-9)
    g = np.asarray(jaxsh.phong_spectrum_gaussian(jnp.asarray(s), 100))
    assert np.abs(a - g).max() < 1e-2


def test_phong_gaussian_approximation_accuracy():
    """Eq. 19 holds where the paper says: large s, l << s."""
    for s in (50.0, 200.0, 1000.0):
        lmax = int(np.sqrt(s))
        a = np.asarray(jaxsh.phong_spectrum(jnp.asarray(s), lmax))
        g = np.asarray(jaxsh.phong_spectrum_gaussian(jnp.asarray(s), lmax))
        assert np.abs(a - g).max() < 3.0 / s ** 0.5  # error O(l^2/s^2 + l/s) at l ~ sqrt(s)


def test_phong_zero_for_l_greater_than_s_same_parity():
    a = np.asarray(jaxsh.phong_spectrum(jnp.asarray(4.0), 12))
    assert np.all(a[6::2] == 0)
    assert np.all(a[5::2] != 0)


@pytest.mark.parametrize("s", [0.5, 7.25, 50.0, 1e3, 1e4])
def test_phong_float32_against_the_gamma_form(s):
    """float32 to 1e-6 (measured 1.2e-7; the log-Gamma evaluation lost 1.2e-5 at s = 50 and 8e-3 at s = 1e4),
    against the Gamma form of R&H eq. 18 in float64 (scipy: gammaln and gammasgn, negative arguments included)."""
    lmax = 40
    l = np.arange(lmax + 1)
    a1, a2 = 1 + (s - l) / 2, (s + l + 3) / 2
    logc = np.log(s + 1) + 0.5 * np.log(np.pi) + gammaln(s + 1) - (s + 1) * np.log(2.0)
    want = gammasgn(a1) * np.exp(logc - gammaln(a1) - gammaln(a2))
    got = jaxsh.phong_spectrum(np.float32(s), lmax)
    assert got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got, np.float64), want, atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.asarray(jaxsh.phong_spectrum(np.float64(s), lmax)), want, atol=1e-12 * max(1.0, s), rtol=0)


def test_phong_gradient_in_s():
    f = lambda s: jaxsh.phong_spectrum(s, 6)
    s0 = jnp.asarray(7.3)
    g = jax.jacfwd(f)(s0)
    h = 1e-6
    np.testing.assert_allclose(g, (f(s0 + h) - f(s0 - h)) / (2 * h), atol=1e-8)


def test_phong_bad_s():
    with pytest.raises(Exception, match="> -1"):
        jaxsh.phong_spectrum(jnp.asarray(-1.5), 3).block_until_ready()


# ---------------------------------------------------------------- microfacet


@pytest.mark.parametrize("sigma", [0.05, 0.1, 0.2])
def test_microfacet_gaussian_approximation(sigma):
    """Eq. 20 vs the numerically projected lobe at normal exitance.

    The appendix's approximation drops O(sigma) terms; measured deviation 0.44-0.46 sigma
    for l <= 1/sigma, so the bound asserted is 0.5 sigma.
    """
    lmax = int(1 / sigma)
    a = np.asarray(jaxsh.torrance_sparrow_spectrum(jnp.asarray(sigma), lmax))
    g = np.asarray(jaxsh.microfacet_spectrum(jnp.asarray(sigma), lmax))
    assert np.abs(a - g).max() < 0.5 * sigma
    # A_0 = (1/2 sigma^2) int exp(-theta^2/4 sigma^2) sin(theta) dtheta = 1 - 2 sigma^2/3 + 4 sigma^4/15 - ...
    assert abs(a[0] - (1 - 2 * sigma**2 / 3 + 4 * sigma**4 / 15)) < sigma**6


def test_radial_spectrum_matches_closed_forms():
    a = jaxsh.radial_spectrum(lambda u: jnp.maximum(u, 0.0), 8, support=(0, 1))
    np.testing.assert_allclose(a, jaxsh.lambertian_spectrum(8), atol=1e-13)
    s = 12.5
    b = jaxsh.radial_spectrum(lambda u: (s + 1) / (2 * np.pi) * u**s, 8, support=(0, 1))
    np.testing.assert_allclose(b, jaxsh.phong_spectrum(jnp.asarray(s), 8), atol=1e-13)
    with pytest.raises(ValueError, match="support"):
        jaxsh.radial_spectrum(lambda u: u, 2, support=(0.5, 0.2))


# ---------------------------------------------------------------- convolution vs brute force


@given(st.integers(0, 2**32 - 1))
def test_lambertian_convolution_equals_brute_force(seed):
    """B = sum_l A_l L_lm Y_lm(n) = int L(w) max(w.n, 0) dw, for band-limited L (l <= 6)."""
    rng = np.random.default_rng(seed)
    lmax = 6
    c = _band_limited_lighting(rng, lmax, 3)
    n = random_dirs(rng, (8,))
    pred = np.asarray(jaxsh.real_sh(n, lmax)) @ np.asarray(jaxsh.convolve(c, jaxsh.lambertian_spectrum(lmax)))
    ref = jaxsh.reflect_quadrature(lambda d: jaxsh.real_sh(d, lmax) @ c, lambert_brdf(), n, n, n_theta=48, n_phi=64)
    np.testing.assert_allclose(pred, ref, atol=1e-11)


@given(st.integers(0, 2**32 - 1), st.floats(1.0, 60.0))
def test_phong_mirror_of_blurred_lighting(seed, s):
    """Associativity (eq. 17, 3.41): the Phong lobe about R applied to L = blurred L seen in a mirror at R."""
    rng = np.random.default_rng(seed)
    lmax = 8
    c = _band_limited_lighting(rng, lmax)
    r = random_dirs(rng, (5,))
    blurred = jaxsh.convolve(c, jaxsh.phong_spectrum(jnp.asarray(s), lmax))
    mirror = np.asarray(jaxsh.real_sh(r, lmax)) @ np.asarray(blurred)

    # brute force: integrate L(w) (s+1)/(2 pi) max(R.w, 0)^s over the hemisphere about R
    def lobe(wi, wo, n):
        return (s + 1) / (2 * np.pi) * jnp.maximum(jnp.sum(wi * n, -1), 0.0) ** (s - 1)  # times cos inside

    ref = jaxsh.reflect_quadrature(lambda d: jaxsh.real_sh(d, lmax) @ c, lobe, r, r, n_theta=96, n_phi=48)
    np.testing.assert_allclose(mirror, ref, atol=1e-9)


@given(st.integers(0, 2**32 - 1))
def test_rotation_equivariance(seed):
    rng = np.random.default_rng(seed)
    c = _band_limited_lighting(rng, 6, 2)
    R = random_rotation(rng)
    a = jaxsh.phong_spectrum(jnp.asarray(rng.uniform(1, 30)), 6)
    np.testing.assert_allclose(jaxsh.convolve(jaxsh.rotate_sh(c, R), a), jaxsh.rotate_sh(jaxsh.convolve(c, a), R), atol=1e-12)


def test_uniform_lighting_only_l0():
    """Uniform lighting: B has only l = 0, and B = A_0 L_00 Y_00 = pi L for Lambertian."""
    c = np.zeros(16)
    c[0] = np.sqrt(4 * np.pi)  # L = 1 everywhere
    b = np.asarray(jaxsh.convolve(c, jaxsh.lambertian_spectrum(3)))
    assert np.all(b[1:] == 0)
    np.testing.assert_allclose(np.asarray(jaxsh.real_sh(np.array([0.3, 0.1, 0.9]), 3)) @ b, np.pi)


def test_convolve_layouts_and_errors(rng):
    c = rng.normal(size=(4, 9, 3))
    a = rng.normal(size=(4, 3))
    out = jaxsh.convolve(c, a)
    np.testing.assert_allclose(out[1, 4:, 2], c[1, 4:, 2] * a[1, 2])
    assert jaxsh.convolve(rng.normal(size=16), np.ones(6)).shape == (16,)
    with pytest.raises(ValueError, match=r"A.*lmax \+ 1 = 4"):
        jaxsh.convolve(rng.normal(size=16), np.ones(3))
    lc = jaxsh.real_to_complex_coeffs(rng.normal(size=9))
    assert jnp.iscomplexobj(jaxsh.convolve(lc, np.ones(3), channels=False))


# ---------------------------------------------------------------- irradiance


def test_irradiance_matches_published_closed_form(rng):
    """Ramamoorthi & Hanrahan 2001 (irradiance maps), eq. 13 with c1..c5 printed to 6 digits."""
    c1, c2, c3, c4, c5 = 0.429043, 0.511664, 0.743125, 0.886227, 0.247708
    L = rng.normal(size=(9, 3))
    n = random_dirs(rng, (50,))
    x, y, z = n.T
    want = np.stack(
        [
            c1 * Lc[8] * (x * x - y * y) + c3 * Lc[6] * z * z + c4 * Lc[0] - c5 * Lc[6]
            + 2 * c1 * (Lc[4] * x * y + Lc[7] * x * z + Lc[5] * y * z)
            + 2 * c2 * (Lc[3] * x + Lc[1] * y + Lc[2] * z)
            for Lc in L.T
        ],
        -1,
    )
    got = np.asarray(jaxsh.irradiance(L, n))
    assert got.shape == (50, 3)
    np.testing.assert_allclose(got, want, atol=5e-6 * np.abs(L).sum())


def test_irradiance_layouts(rng):
    L = rng.normal(size=16)
    n = random_dirs(rng, (2, 3))
    e = jaxsh.irradiance(L, n)
    assert e.shape == (2, 3)
    want = np.asarray(jaxsh.real_sh(n, 2)) @ np.asarray(jaxsh.convolve(L[:9], jaxsh.lambertian_spectrum(2)))
    np.testing.assert_allclose(e, want, atol=1e-13)
    np.testing.assert_allclose(jaxsh.irradiance(L[:4], n), np.asarray(jaxsh.real_sh(n, 1)) @ (L[:4] * np.array([np.pi, 2 * np.pi / 3, 2 * np.pi / 3, 2 * np.pi / 3])), atol=1e-13)
    with pytest.raises(ValueError, match="normals"):
        jaxsh.irradiance(L, np.ones((3, 2)))
    assert jaxsh.irradiance(L.astype(np.float32), n.astype(np.float32)).dtype == jnp.float32


# ---------------------------------------------------------------- recoverability


def test_recoverable_orders_follow_the_theory():
    ok, lstar = jaxsh.recoverable_orders(jaxsh.lambertian_spectrum(20), 0.1)
    assert lstar == 2
    for s in (25.0, 100.0, 400.0):
        _, l = jaxsh.recoverable_orders(jaxsh.phong_spectrum(jnp.asarray(s), 200), 0.05)
        assert abs(l - np.sqrt(2 * s * np.log(20))) <= 1.5
    for sigma in (0.05, 0.1, 0.2):
        _, l = jaxsh.recoverable_orders(jaxsh.microfacet_spectrum(jnp.asarray(sigma), 200), 0.05)
        assert abs(l - np.sqrt(np.log(20)) / sigma) <= 1.0
    with pytest.raises(ValueError, match="noise"):
        jaxsh.recoverable_orders(np.ones(3), 0.0)


# ---------------------------------------------------------------- general isotropic BRDFs (eqs. 8-13)


@given(st.integers(0, 2**32 - 1))
def test_frequency_prediction_equals_brute_force(seed):
    """B(alpha, beta, w_o') from L_lm, D^l(alpha) and rho_lq(w_o') = the reflection integral (eqs. 2, 5, 6, 10)."""
    rng = np.random.default_rng(seed)
    lmax = 5
    c = _band_limited_lighting(rng, lmax)
    lc = jaxsh.real_to_complex_coeffs(c)
    alpha, beta = rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
    theta_o, phi_o = rng.uniform(0, 1.4), rng.uniform(0, 2 * np.pi)
    R = np.asarray(jaxsh.rotation_from_euler_zyz(beta, alpha, 0.0))  # R_{alpha,beta} = Rz(beta) Ry(alpha)
    wo_local = np.array([np.sin(theta_o) * np.cos(phi_o), np.sin(theta_o) * np.sin(phi_o), np.cos(theta_o)])
    rho_i = jaxsh.brdf_incident_coefficients(smooth_transfer, jnp.asarray(theta_o), lmax, n_theta=48, n_phi=32)
    pred = float(jaxsh.reflect_sh(lc, rho_i, alpha, beta, phi_o))
    ref = float(jaxsh.reflect_quadrature(lambda d: jaxsh.real_sh(d, lmax) @ c, smooth_brdf, R[:, 2], R @ wo_local, n_theta=48, n_phi=64))
    assert abs(pred - ref) < 1e-11


def test_light_field_series_converges_to_brute_force(rng):
    """The full 4-D expansion (eqs. 9, 10) with p truncated converges; reciprocal form (eq. 13)."""
    lmax = 4
    c = _band_limited_lighting(rng, lmax)
    lc = np.asarray(jaxsh.real_to_complex_coeffs(c))
    alpha, beta, theta_o, phi_o = 0.7, 2.0, 0.5, 0.3
    R = np.asarray(jaxsh.rotation_from_euler_zyz(beta, alpha, 0.0))
    wo_local = np.array([np.sin(theta_o) * np.cos(phi_o), np.sin(theta_o) * np.sin(phi_o), np.cos(theta_o)])
    ref = float(jaxsh.reflect_quadrature(lambda d: jaxsh.real_sh(d, lmax) @ c, smooth_brdf, R[:, 2], R @ wo_local)) * np.cos(theta_o)
    P = 40
    rho = jaxsh.brdf_sh_coefficients(lambda ti, to, dp: smooth_transfer(ti, to, dp) * jnp.cos(to), P, n_theta=96, n_phi=32)
    lp = np.zeros(jaxsh.num_coeffs(P), complex)
    lp[: len(lc)] = lc
    B = jaxsh.light_field_coefficients(jnp.asarray(lp), rho)
    C = jaxsh.light_field_basis(alpha, beta, jnp.asarray(wo_local), P)
    got = float(jnp.real(jnp.sum(B * C)))
    assert abs(got - ref) < 1e-3 * abs(ref)  # kink at the horizon: O(1/P^2) convergence; measured 5e-4 relative


def test_directional_source_identity():
    """Source at +z: L_lm = delta_m0 / Lambda_l, so B_l0pq = rho_lpq (R&H sec. 5.2)."""
    lmax = 6
    lc = jaxsh.real_to_complex_coeffs(jaxsh.real_sh(jnp.array([0.0, 0.0, 1.0]), lmax))
    ms = jaxsh.sh_orders(lmax)
    ls = jaxsh.sh_degrees(lmax)
    np.testing.assert_allclose(lc, np.where(ms == 0, 1 / jaxsh.sh_lambda(lmax)[ls], 0), atol=1e-14)
    rho = jaxsh.brdf_sh_coefficients(glossy_transfer_reciprocal(), lmax, n_theta=48, n_phi=64)
    B = np.asarray(jaxsh.light_field_coefficients(lc, rho))
    for l in range(lmax + 1):
        np.testing.assert_allclose(B[l * l + l, :, lmax:], rho[l], atol=1e-13)
    assert np.abs(B[ms != 0]).max() < 1e-14  # B_lmpq = 0 for m != 0


def test_mirror_light_field_reflects_the_lighting(rng):
    """rho_lpq = (-1)^q delta_lp (eq. 14): B(alpha, beta, w_o') = L(R_{alpha,beta} reflect(w_o'))."""
    lmax = 6
    c = _band_limited_lighting(rng, lmax)
    lc = jaxsh.real_to_complex_coeffs(c)
    B = jaxsh.light_field_coefficients(lc, jaxsh.mirror_brdf_coefficients(lmax))
    alpha, beta, theta_o, phi_o = 1.1, -0.4, 0.6, 2.2
    wo = jnp.array([np.sin(theta_o) * np.cos(phi_o), np.sin(theta_o) * np.sin(phi_o), np.cos(theta_o)])
    got = float(jnp.real(jnp.sum(B * jaxsh.light_field_basis(alpha, beta, wo, lmax))))
    R = np.asarray(jaxsh.rotation_from_euler_zyz(beta, alpha, 0.0))
    refl_local = np.array([-wo[0], -wo[1], wo[2]])  # azimuth + pi
    want = float(np.asarray(jaxsh.real_sh(R @ refl_local, lmax)) @ c)
    assert abs(got - want) < 1e-12


def test_reciprocity_of_rho_tilde():
    rho = np.asarray(jaxsh.brdf_sh_coefficients(glossy_transfer_reciprocal(), 8, n_theta=64, n_phi=64))
    np.testing.assert_allclose(rho, np.transpose(rho, (1, 0, 2)), atol=1e-13)
    # a non-reciprocal transfer breaks it visibly
    nr = np.asarray(jaxsh.brdf_sh_coefficients(lambda ti, to, dp: smooth_transfer(ti, to, dp) * jnp.cos(to), 4, n_theta=32, n_phi=16))
    assert np.abs(nr - np.transpose(nr, (1, 0, 2))).max() > 1e-3


def test_factorization_recovers_lighting_and_brdf(rng):
    """Sec. 5.1: L and rho~ from B~ up to the global scale fixed by L_00 = 1/Lambda_0."""
    lmax = 4
    c = _band_limited_lighting(rng, lmax)
    c[0] = 2.0
    lc = np.asarray(jaxsh.real_to_complex_coeffs(c))
    rho = jaxsh.brdf_sh_coefficients(glossy_transfer_reciprocal(), lmax, n_theta=48, n_phi=64)
    Bt = jaxsh.light_field_coefficients(jnp.asarray(lc), rho)
    L_rec, rho_rec = jaxsh.factorize_light_field(Bt)
    scale = lc[0] / (1 / np.sqrt(4 * np.pi))
    np.testing.assert_allclose(np.asarray(L_rec) * scale, lc, atol=1e-11)
    np.testing.assert_allclose(np.asarray(rho_rec) / scale, rho, atol=1e-11)


def test_incident_coefficients_equal_sum_over_p(rng):
    """rho_lq(w_o) = sum_p rho_lpq Y_pq(w_o) for the reciprocal glossy transfer (kink-free in the interior)."""
    lmax, P = 3, 36
    f = glossy_transfer_reciprocal()
    rho = np.asarray(jaxsh.brdf_sh_coefficients(f, P, n_theta=96, n_phi=64))
    theta_o = 0.4
    yo = np.asarray(jaxsh.complex_sh(np.array([np.sin(theta_o), 0, np.cos(theta_o)]), P)).real
    ri = np.asarray(jaxsh.brdf_incident_coefficients(f, jnp.asarray(theta_o), lmax, n_theta=96, n_phi=64))
    for l in range(lmax + 1):
        for q in range(l + 1):
            s = sum(rho[l, p, q] * yo[p * p + p + q] for p in range(q, P + 1))
            assert abs(s - ri[l * l + l + q]) < 2e-3 * np.abs(ri).max()


@pytest.mark.parametrize("model", ["torrance_sparrow", "cook_torrance", "oren_nayar"])
def test_library_models_frequency_vs_brute_force(rng, model):
    """The library's own BRDF models through eqs. 5-10 agree with the brute-force integral."""
    lmax = 6
    c = _band_limited_lighting(rng, lmax)
    lc = jaxsh.real_to_complex_coeffs(c)
    params = {
        "torrance_sparrow": dict(kd=0.3, ks=0.5, mu=1.6, sigma=0.35),
        "cook_torrance": dict(kd=0.4, ks=0.6, m=0.4, mu=1.5),
        "oren_nayar": dict(albedo=0.8, sigma=0.5),
    }[model]
    brdf = getattr(jaxsh, model)

    def vec(wi, wo, n):
        return brdf(wi, wo, n, **params)

    def transfer(ti, to, dphi):
        wi, wo = jaxsh.local_directions(*jnp.broadcast_arrays(ti, to, dphi))
        n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), wi.shape)
        return vec(wi, wo, n) * jnp.cos(ti)

    alpha, beta, theta_o, phi_o = 0.8, 1.3, 0.7, 2.0
    R = np.asarray(jaxsh.rotation_from_euler_zyz(beta, alpha, 0.0))
    wo_local = np.array([np.sin(theta_o) * np.cos(phi_o), np.sin(theta_o) * np.sin(phi_o), np.cos(theta_o)])
    rho_i = jaxsh.brdf_incident_coefficients(transfer, jnp.asarray(theta_o), lmax, n_theta=160, n_phi=256)
    pred = float(jaxsh.reflect_sh(lc, rho_i, alpha, beta, phi_o))
    ref = float(jaxsh.reflect_quadrature(lambda d: jaxsh.real_sh(d, lmax) @ c, vec, R[:, 2], R @ wo_local, n_theta=160, n_phi=256))
    # Both sides are quadratures of the same integrand; measured differences: 4e-16 (Torrance-Sparrow),
    # 7e-10 (Cook-Torrance), 1.3e-7 (Oren-Nayar, whose max(0, cos dphi) kink slows the azimuthal rule).
    assert abs(pred - ref) < 1e-5 * (abs(ref) + 1)


def test_spectra_batch_and_float32():
    s = np.array([[2.0, 10.0], [50.0, 0.5]])
    a = jaxsh.phong_spectrum(s, 5)
    assert a.shape == (2, 2, 6)
    np.testing.assert_allclose(a[1, 0], jaxsh.phong_spectrum(jnp.asarray(50.0), 5), atol=1e-15)
    a32 = jaxsh.phong_spectrum(s.astype(np.float32), 5)
    assert a32.dtype == jnp.float32
    assert np.abs(np.asarray(a32, np.float64) - np.asarray(a)).max() < 1e-5
    assert jaxsh.microfacet_spectrum(np.float32(0.1), 4).dtype == jnp.float32
    assert jaxsh.microfacet_spectrum(np.array([0.1, 0.2]), 4).shape == (2, 5)
    assert jaxsh.lambertian_spectrum(4, dtype=jnp.float32).dtype == jnp.float32
    e = jaxsh.irradiance(np.ones((9, 3), np.float32), np.array([[0, 0, 1.0]], np.float32))
    assert e.dtype == jnp.float32 and e.shape == (1, 3)
