"""BRDF models, Fresnel, half/difference coordinates: closed forms, independent
NumPy references, reciprocity, energy by brute-force quadrature, horizons,
gradients, batching, precision and argument errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special as sp

from jaxsh import _reflectance as rf

from .helpers import random_dirs, random_rotation, tol

Z = np.array([0.0, 0.0, 1.0])


# ---------------------------------------------------------------- references (NumPy)


def np_fresnel_sp(cos_t, mu):
    """Unpolarized Fresnel from Snell's law and the s/p amplitudes (Born & Wolf 1.5.2)."""
    cos_t = np.asarray(cos_t, dtype=np.float64)
    sin_t = np.sqrt(1 - cos_t**2)
    sin_tr = sin_t / mu
    cos_tr = np.sqrt(np.maximum(1 - sin_tr**2, 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = (cos_t - mu * cos_tr) / (cos_t + mu * cos_tr)
        rp = (mu * cos_t - cos_tr) / (mu * cos_t + cos_tr)
    return np.where(sin_tr >= 1, 1.0, 0.5 * (rs**2 + rp**2))


def np_fresnel_ct(c, mu):
    """The textbook (Cook-Torrance) form, g^2 = mu^2 - 1 + c^2."""
    g = np.sqrt(mu**2 - 1 + c**2)
    return 0.5 * (g - c) ** 2 / (g + c) ** 2 * (1 + ((c * (g + c) - 1) / (c * (g - c) + 1)) ** 2)


def np_local(w, n):
    """Local coordinates in an independently built frame (cross products)."""
    a = np.where(np.abs(n[..., :1]) < 0.9, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    t = np.cross(a, n)
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    b = np.cross(n, t)
    return np.stack([np.sum(w * t, -1), np.sum(w * b, -1), np.sum(w * n, -1)], -1)


def np_angles(wi, wo, n):
    li, lo = np_local(wi, n), np_local(wo, n)
    ti, to = np.arccos(np.clip(li[..., 2], -1, 1)), np.arccos(np.clip(lo[..., 2], -1, 1))
    dphi = np.arctan2(lo[..., 1], lo[..., 0]) - np.arctan2(li[..., 1], li[..., 0])
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
    th = np.arccos(np.clip(np.sum(h * n, -1), -1, 1))
    return ti, to, dphi, th, h


def upper_pairs(rng, shape, normal=None):
    """Random (wi, wo, n) with both directions strictly above the horizon."""
    n = random_dirs(rng, shape) if normal is None else np.broadcast_to(normal, tuple(shape) + (3,))
    wi, wo = random_dirs(rng, shape), random_dirs(rng, shape)
    wi = np.where(np.sum(wi * n, -1, keepdims=True) < 0, wi - 2 * np.sum(wi * n, -1, keepdims=True) * n, wi)
    wo = np.where(np.sum(wo * n, -1, keepdims=True) < 0, wo - 2 * np.sum(wo * n, -1, keepdims=True) * n, wo)
    return wi, wo, n


def hemisphere_quadrature(n_theta=400, n_phi=400):
    """Gauss-Legendre in cos(theta) x midpoint in phi over the upper hemisphere."""
    x, w = sp.roots_legendre(n_theta)
    mu, wmu = 0.5 * (x + 1), 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    st = np.sqrt(1 - mu**2)
    d = np.stack(np.broadcast_arrays(st[:, None] * np.cos(phi), st[:, None] * np.sin(phi), mu[:, None]), -1)
    wts = wmu[:, None] * np.full(n_phi, 2 * np.pi / n_phi)
    return d.reshape(-1, 3), wts.reshape(-1)


@pytest.fixture(scope="module")
def quad():
    return hemisphere_quadrature()


# Models with parameters (reciprocal ones first).
MODELS = {
    "lambertian": (rf.lambertian, (0.3,)),
    "phong_transfer": (rf.phong_transfer, (7.5,)),
    "cook_torrance": (rf.cook_torrance, (0.4, 0.6, 0.3, 1.5)),
    "ward_isotropic": (rf.ward_isotropic, (0.4, 0.6, 0.25)),
    "oren_nayar": (rf.oren_nayar, (0.8, 0.6)),
    "lafortune": (rf.lafortune, (0.3, np.array([[-1.0, 0.9, 8.0], [0.7, 0.5, 3.5]]))),
    "torrance_sparrow_nofresnel": (rf.torrance_sparrow, (0.2, 0.8, None, 0.2)),
    "phong": (rf.phong, (7.5,)),
    "torrance_sparrow": (rf.torrance_sparrow, (0.2, 0.8, 1.5, 0.2)),
}
RECIPROCAL = [k for k in MODELS if k not in ("phong", "torrance_sparrow")]


# ---------------------------------------------------------------- geometry


def test_reflect_mirror_half(rng):
    v = random_dirs(rng, (20,))
    n = random_dirs(rng, (20,))
    r = np.asarray(rf.reflect(v, n))
    np.testing.assert_allclose(r, 2 * np.sum(v * n, -1, keepdims=True) * n - v, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(r, axis=-1), 1, atol=1e-14)
    np.testing.assert_allclose(np.sum(r * n, -1), np.sum(v * n, -1), atol=1e-14)
    np.testing.assert_array_equal(np.asarray(rf.mirror_direction(v, n)), r)
    np.testing.assert_allclose(rf.reflect(np.array([1.0, 0, 1]) / np.sqrt(2), Z), [-1 / np.sqrt(2), 0, 1 / np.sqrt(2)], atol=1e-15)
    h = np.asarray(rf.half_vector(v, r))
    np.testing.assert_allclose(np.abs(np.sum(h * n, -1)), 1, atol=1e-12)  # h of a mirror pair is +-n
    # wi = -wo: undefined, reported as zeros with finite gradient
    np.testing.assert_array_equal(rf.half_vector(Z, -Z), np.zeros(3))
    g = jax.grad(lambda a: jnp.sum(rf.half_vector(a, -Z)))(jnp.asarray(Z))
    assert np.all(np.isfinite(g))


def test_tangent_frame(rng):
    n = np.concatenate([random_dirs(rng, (30,)), [Z, -Z, [1.0, 0, 0], [0, -1.0, 0]]])
    t, b = (np.asarray(x) for x in rf.tangent_frame(n))
    for u in (t, b):
        np.testing.assert_allclose(np.linalg.norm(u, axis=-1), 1, atol=1e-14)
        np.testing.assert_allclose(np.sum(u * n, -1), 0, atol=1e-14)
    np.testing.assert_allclose(np.cross(t, b), n, atol=1e-14)
    # A given tangent is orthonormalized and kept in the (t, n) plane.
    t0 = random_dirs(rng, (34,))
    t2, b2 = (np.asarray(x) for x in rf.tangent_frame(n, t0))
    np.testing.assert_allclose(np.cross(t2, b2), n, atol=1e-13)
    proj = t0 - np.sum(t0 * n, -1, keepdims=True) * n
    np.testing.assert_allclose(t2, proj / np.linalg.norm(proj, axis=-1, keepdims=True), atol=1e-12)


def test_rusinkiewicz_known_configurations():
    th, ph, td, pd = (float(x) for x in rf.rusinkiewicz_angles(Z, Z, Z))
    assert th == 0 and td == 0 and ph == 0 and pd == 0
    for a in (0.1, 0.7, 1.4):
        wi = np.array([np.sin(a), 0, np.cos(a)])
        wo = np.array([-np.sin(a), 0, np.cos(a)])  # mirror pair
        th, ph, td, pd = (float(x) for x in rf.rusinkiewicz_angles(wi, wo, Z))
        assert th == pytest.approx(0, abs=1e-15) and td == pytest.approx(a, abs=1e-14)
        assert pd == pytest.approx(0, abs=1e-14)  # wi at azimuth 0 in the tangent frame +x
        # wi = wo: theta_d = 0, theta_h = angle
        th, ph, td, pd = (float(x) for x in rf.rusinkiewicz_angles(wi, wi, Z))
        assert th == pytest.approx(a, abs=1e-14) and td == pytest.approx(0, abs=1e-15)
        assert ph == pytest.approx(0, abs=1e-15)
    # frame with tangent +x at n = +z is the identity frame
    t, b = rf.tangent_frame(Z)
    np.testing.assert_allclose(t, [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(b, [0, 1, 0], atol=1e-15)


def test_rusinkiewicz_independent_and_roundtrip(rng):
    wi, wo, n = upper_pairs(rng, (200,))
    th, ph, td, pd = (np.asarray(x) for x in rf.rusinkiewicz_angles(wi, wo, n))
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.cos(th), np.sum(h * n, -1), atol=1e-12)
    np.testing.assert_allclose(np.cos(td), np.sum(h * wi, -1), atol=1e-12)  # theta_d = angle(wi, h)
    assert np.all((ph >= 0) & (ph < 2 * np.pi) & (pd >= 0) & (pd < 2 * np.pi))
    assert np.all((th <= np.pi / 2) & (td <= np.pi / 2))
    # phi_h is the azimuth of h in the frame
    t, b = (np.asarray(x) for x in rf.tangent_frame(n))
    np.testing.assert_allclose(np.mod(np.arctan2(np.sum(h * b, -1), np.sum(h * t, -1)), 2 * np.pi), ph, atol=1e-10)
    # inverse: reconstruct the local directions
    li = np.stack([np.sum(wi * t, -1), np.sum(wi * b, -1), np.sum(wi * n, -1)], -1)
    lo = np.stack([np.sum(wo * t, -1), np.sum(wo * b, -1), np.sum(wo * n, -1)], -1)
    ri, ro = rf.rusinkiewicz_directions(th, ph, td, pd)
    np.testing.assert_allclose(ri, li, atol=1e-12)
    np.testing.assert_allclose(ro, lo, atol=1e-12)
    # reciprocity: swapping wi and wo maps phi_d -> phi_d + pi
    th2, ph2, td2, pd2 = (np.asarray(x) for x in rf.rusinkiewicz_angles(wo, wi, n))
    np.testing.assert_allclose(th2, th, atol=1e-12)
    np.testing.assert_allclose(td2, td, atol=1e-12)
    np.testing.assert_allclose(np.cos(pd2 - pd), -1, atol=1e-9)
    # phi_d does not depend on the tangent (isotropy); phi_h shifts with it
    t_other = random_dirs(rng, (200,))
    th3, ph3, td3, pd3 = (np.asarray(x) for x in rf.rusinkiewicz_angles(wi, wo, n, t_other))
    np.testing.assert_allclose(th3, th, atol=1e-12)
    np.testing.assert_allclose(td3, td, atol=1e-12)
    np.testing.assert_allclose(np.cos(pd3 - pd), 1, atol=1e-9)


def test_rusinkiewicz_gradients_finite_at_singular_points():
    a = 0.4
    p = np.array([np.sin(a), 0, np.cos(a)])
    q = np.array([-np.sin(a), 0, np.cos(a)])
    # wi = wo = n; mirror pair (theta_h = 0); wi = wo (theta_d = 0); wi = -wo
    wi = np.stack([Z, p, p, Z])
    wo = np.stack([Z, q, p, -Z])
    angles = rf.rusinkiewicz_angles(wi, wo, Z)
    assert all(np.all(np.isfinite(x)) for x in angles)
    total = lambda x, y: jnp.sum(sum(rf.rusinkiewicz_angles(x, y, Z)))  # finite iff every term is
    g = jax.jit(jax.grad(total, argnums=(0, 1)))(wi, wo)
    assert all(np.all(np.isfinite(gi)) for gi in g)


def test_local_directions():
    ti, to, dp = np.array([0.3, 1.0]), np.array([0.5, 0.2]), np.array([2.0, -1.0])
    wi, wo = (np.asarray(x) for x in rf.local_directions(ti, to, dp))
    np.testing.assert_allclose(wi, np.stack([np.sin(ti), 0 * ti, np.cos(ti)], -1), atol=1e-15)
    np.testing.assert_allclose(np.arccos(wo[:, 2]), to, atol=1e-14)
    np.testing.assert_allclose(np.arctan2(wo[:, 1], wo[:, 0]), dp, atol=1e-14)
    # broadcasting of the angles: (3, 1), (4,), ()
    wi, wo = rf.local_directions(np.zeros((3, 1)), np.zeros(4), 0.0)
    assert wi.shape == wo.shape == (3, 4, 3)


# ---------------------------------------------------------------- uvw (Zickler 2006 eq. 7)


def test_uvw_formula(rng):
    th = rng.uniform(0, np.pi / 2, 50)
    pd = rng.uniform(0, 2 * np.pi, 50)
    td = rng.uniform(0, np.pi / 2, 50)
    want = np.stack([np.sin(th) * np.cos(2 * pd), np.sin(th) * np.sin(2 * pd), 2 * td / np.pi], -1)
    np.testing.assert_allclose(rf.uvw(th, pd, td), want, atol=1e-15)
    # phi_d -> phi_d + pi leaves (u, v, w) unchanged (reciprocity), theta_h = 0 is the w axis
    np.testing.assert_allclose(rf.uvw(th, pd + np.pi, td), want, atol=1e-14)
    np.testing.assert_allclose(np.asarray(rf.uvw(0.0, pd, td))[:, :2], 0, atol=1e-15)


def test_uvw_finite_at_theta_d_zero():
    f = lambda th, pd, td: jnp.sum(rf.uvw(th, pd, td) * jnp.array([1.0, 2.0, 3.0]))
    for th in (0.0, 0.3):
        val = rf.uvw(th, 0.7, 0.0)
        assert np.all(np.isfinite(val)) and float(val[2]) == 0
        g = jax.grad(f, argnums=(0, 1, 2))(th, 0.7, 0.0)
        assert all(np.isfinite(gi) for gi in g)
        np.testing.assert_allclose(g[2], 3 * 2 / np.pi, rtol=1e-14)
    # from directions: wi = wo (theta_d = 0) and wi = wo = n
    a = jnp.array([np.sin(0.3), 0.0, np.cos(0.3)])
    for w in (a, jnp.asarray(Z)):
        val = rf.uvw_from_directions(w, w, Z)
        assert np.all(np.isfinite(val)) and float(val[2]) == pytest.approx(0, abs=1e-12)
        g = jax.grad(lambda p, q: jnp.sum(rf.uvw_from_directions(p, q, Z)), argnums=(0, 1))(w, w)
        assert all(np.all(np.isfinite(gi)) for gi in g)


def test_uvw_from_directions(rng):
    wi, wo, n = upper_pairs(rng, (200,))
    q = np.asarray(rf.uvw_from_directions(wi, wo, n))
    th, _, td, pd = rf.rusinkiewicz_angles(wi, wo, n)
    np.testing.assert_allclose(q, rf.uvw(th, pd, td), atol=1e-15)
    np.testing.assert_allclose(rf.uvw_from_directions(wo, wi, n), q, atol=1e-11)  # reciprocal
    # invariant under a common rotation of wi, wo, n (isotropy; independent of the tangent)
    r = random_rotation(rng)
    np.testing.assert_allclose(rf.uvw_from_directions(wi @ r.T, wo @ r.T, n @ r.T), q, atol=1e-10)
    assert np.all(np.abs(q[:, :2]).max(-1) <= 1) and np.all((q[:, 2] >= 0) & (q[:, 2] <= 1))


# ---------------------------------------------------------------- Fresnel


@pytest.mark.parametrize("mu", [1.05, 1.33, 1.5, 2.4, 5.0])
def test_fresnel_against_references(mu):
    c = np.linspace(0.0, 1.0, 101)
    f = np.asarray(rf.fresnel_dielectric(c, mu))
    np.testing.assert_allclose(f, np_fresnel_sp(c, mu), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(f[1:], np_fresnel_ct(c[1:], mu), rtol=1e-12)
    r0 = ((mu - 1) / (mu + 1)) ** 2
    assert f[-1] == pytest.approx(r0, rel=1e-14)  # normal incidence
    assert f[0] == pytest.approx(1.0, rel=1e-14)  # grazing
    assert np.all((f > 0) & (f <= 1 + 1e-14))
    fn = np.asarray(rf.fresnel_normalized(c, mu))
    np.testing.assert_allclose(fn, f / r0, rtol=1e-12)
    assert fn[-1] == pytest.approx(1.0, rel=1e-14)


def test_fresnel_total_internal_reflection_and_mu_one():
    mu = 1 / 1.5
    c = np.linspace(0.0, 1.0, 201)
    np.testing.assert_allclose(rf.fresnel_dielectric(c, mu), np_fresnel_sp(c, mu), atol=1e-12)
    c_crit = np.sqrt(1 - mu**2)
    assert np.all(np.asarray(rf.fresnel_dielectric(c[c < c_crit], mu)) == 1)
    # mu = 1: no reflection; the normalized term has the finite limit (1 + (2c^2-1)^2)/(2c^4)
    c = np.linspace(0.05, 1.0, 20)
    np.testing.assert_allclose(rf.fresnel_dielectric(c, 1.0), 0, atol=1e-30)
    np.testing.assert_allclose(rf.fresnel_normalized(c, 1.0), (1 + (2 * c**2 - 1) ** 2) / (2 * c**4), rtol=1e-13)
    c = c[c > 0.2]  # continuity at mu = 1 (the limit holds for mu - 1 << c^2)
    np.testing.assert_allclose(rf.fresnel_normalized(c, 1 + 1e-6), (1 + (2 * c**2 - 1) ** 2) / (2 * c**4), rtol=1e-4)
    for mu in (1.0, 1.5):
        g = jax.grad(lambda m, c: rf.fresnel_normalized(c, m), argnums=(0, 1))(mu, 0.5)
        assert all(np.isfinite(gi) for gi in g)
    for c0 in (0.0, 1.0):
        g = jax.grad(lambda m, c: rf.fresnel_dielectric(c, m), argnums=(0, 1))(1.5, c0)
        assert all(np.isfinite(gi) for gi in g)
    # gradient in mu against a central difference
    gm = jax.grad(lambda m: rf.fresnel_dielectric(0.3, m))(1.5)
    fd = (np_fresnel_sp(0.3, 1.5 + 1e-6) - np_fresnel_sp(0.3, 1.5 - 1e-6)) / 2e-6
    assert float(gm) == pytest.approx(float(fd), rel=1e-6)


# ---------------------------------------------------------------- models against references


def test_models_against_angle_references(rng):
    wi, wo, n = upper_pairs(rng, (200,))
    ti, to, dphi, th, h = np_angles(wi, wo, n)
    ci, co = np.cos(ti), np.cos(to)
    # Torrance-Sparrow (R&H 2001 sec. 5.2), Fresnel at the exitant angle
    kd, ks, mu, sg = 0.2, 0.8, 1.5, 0.2
    f = np_fresnel_sp(co, mu) / ((mu - 1) / (mu + 1)) ** 2
    want = kd + ks * f * np.exp(-((th / sg) ** 2)) / (np.pi * sg**2) / (4 * ci * co)
    np.testing.assert_allclose(rf.torrance_sparrow(wi, wo, n, kd, ks, mu, sg), want, rtol=1e-9)
    # Cook-Torrance
    m = 0.3
    d = np.exp(-np.tan(th) ** 2 / m**2) / (np.pi * m**2 * np.cos(th) ** 4)
    oh = np.sum(wo * h, -1)
    g = np.minimum(1, np.minimum(2 * np.cos(th) * co / oh, 2 * np.cos(th) * ci / oh))
    f = np_fresnel_sp(np.sum(wi * h, -1), mu)
    want = kd / np.pi + ks * d * g * f / (4 * ci * co)
    np.testing.assert_allclose(rf.cook_torrance(wi, wo, n, kd, ks, m, mu), want, rtol=1e-9)
    # Ward
    a = 0.25
    want = kd / np.pi + ks * np.exp(-np.tan(th) ** 2 / a**2) / (4 * np.pi * a**2 * np.sqrt(ci * co))
    np.testing.assert_allclose(rf.ward_isotropic(wi, wo, n, kd, ks, a), want, rtol=1e-9)
    # Oren-Nayar with explicit angles and azimuths
    sg = 0.6
    A = 1 - 0.5 * sg**2 / (sg**2 + 0.33)
    B = 0.45 * sg**2 / (sg**2 + 0.09)
    al, be = np.maximum(ti, to), np.minimum(ti, to)
    want = 0.8 / np.pi * (A + B * np.maximum(0, np.cos(dphi)) * np.sin(al) * np.tan(be))
    np.testing.assert_allclose(rf.oren_nayar(wi, wo, n, 0.8, sg), want, rtol=1e-9)
    # Phong
    s = 7.5
    rl = np.sum((2 * co[:, None] * n - wo) * wi, -1)
    want = (s + 1) / (2 * np.pi) * np.maximum(rl, 0) ** s
    np.testing.assert_allclose(rf.phong_transfer(wi, wo, n, s), want, rtol=1e-9, atol=1e-300)
    np.testing.assert_allclose(rf.phong(wi, wo, n, s), want / ci, rtol=1e-9, atol=1e-300)
    # Lafortune in local coordinates
    lobes = np.array([[-1.0, 0.9, 8.0], [0.7, 0.5, 3.5]])
    li, lo = np_local(wi, n), np_local(wo, n)
    want = 0.3 / np.pi
    for cx, cz, e in lobes:
        base = cx * (li[:, 0] * lo[:, 0] + li[:, 1] * lo[:, 1]) + cz * li[:, 2] * lo[:, 2]
        want = want + np.maximum(base, 0) ** e
    np.testing.assert_allclose(rf.lafortune(wi, wo, n, 0.3, lobes), want, rtol=1e-9)


def test_special_cases():
    wi, wo = rf.local_directions(np.array([0.2, 0.9]), np.array([0.5, 1.1]), np.array([0.3, 2.5]))
    # Oren-Nayar with sigma = 0 is Lambertian of albedo a
    np.testing.assert_allclose(rf.oren_nayar(wi, wo, Z, 0.8, 0.0), rf.lambertian(wi, wo, Z, 0.8 / np.pi), rtol=1e-15)
    np.testing.assert_allclose(rf.lambertian(wi, wo, Z, 0.3), 0.3, rtol=0)
    # Torrance-Sparrow: mu=None is F = 1; at normal exitance the normalized Fresnel is 1
    np.testing.assert_allclose(
        rf.torrance_sparrow(wi, Z, Z, 0.1, 0.9, 1.5, 0.2), rf.torrance_sparrow(wi, Z, Z, 0.1, 0.9, None, 0.2), rtol=1e-14
    )
    # Phong s = 0 is a constant transfer 1/(2 pi) over the reflection hemisphere
    np.testing.assert_allclose(rf.phong_transfer(wi, Z, Z, 0.0), 1 / (2 * np.pi), rtol=1e-15)


# ---------------------------------------------------------------- reciprocity


@pytest.mark.parametrize("name", list(MODELS))
def test_reciprocity(rng, name):
    fn, params = MODELS[name]
    wi, wo, n = upper_pairs(rng, (200,))
    a = np.asarray(fn(wi, wo, n, *params))
    b = np.asarray(fn(wo, wi, n, *params))
    if name in RECIPROCAL:
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-300)
    elif name == "phong":
        # the transfer function is symmetric: rho(wi, wo) cos(theta_i) = rho(wo, wi) cos(theta_o)
        ci, co = np.sum(wi * n, -1), np.sum(wo * n, -1)
        np.testing.assert_allclose(a * ci, b * co, rtol=1e-11, atol=1e-300)
        assert not np.allclose(a, b)
    else:  # R&H's Torrance-Sparrow with F(theta_o) is not exactly reciprocal
        assert not np.allclose(a, b, rtol=1e-6)


# ---------------------------------------------------------------- energy (brute-force quadrature)


def albedo(fn, params, theta_o, quad):
    d, w = quad
    wo = np.array([np.sin(theta_o), 0.0, np.cos(theta_o)])
    return float(np.sum(w * d[:, 2] * np.asarray(fn(d, wo, Z, *params))))


def test_energy_lambertian_and_phong(quad):
    assert albedo(rf.lambertian, (0.25,), 0.7, quad) == pytest.approx(0.25 * np.pi, rel=1e-12)
    # normalized Phong, view along the normal (R = n): unit energy for any s
    for s in (0.0, 1.0, 10.0, 37.5, 200.0):
        assert albedo(rf.phong, (s,), 0.0, quad) == pytest.approx(1.0, rel=1e-6)


def test_energy_torrance_sparrow_lobe(quad):
    # 2 pi int exp(-(theta/2 sigma)^2)/(4 pi sigma^2) sin(theta) dtheta = 1 - O(sigma^2)
    for sg in (0.05, 0.1, 0.2):
        e = albedo(rf.torrance_sparrow, (0.0, 1.0, 1.5, sg), 0.0, quad)
        assert e == pytest.approx(1.0, abs=sg**2)
        assert e < 1
    # independent 1-D quadrature of the same integral
    sg = 0.1
    t = np.linspace(0, np.pi / 2, 200001)
    ref = np.trapezoid(2 * np.pi * np.exp(-((t / (2 * sg)) ** 2)) / (4 * np.pi * sg**2) * np.sin(t), t)
    assert albedo(rf.torrance_sparrow, (0.0, 1.0, None, sg), 0.0, quad) == pytest.approx(ref, rel=1e-6)


@pytest.mark.parametrize(
    "fn, params",
    [
        (rf.cook_torrance, (0.3, 0.7, 0.3, 1.5)),
        (rf.cook_torrance, (0.0, 1.0, 0.2, 1e6)),  # F ~ 1: everything but masking reflected
        (rf.cook_torrance, (0.0, 1.0, 0.8, 1e6)),
        (rf.ward_isotropic, (0.3, 0.7, 0.2)),
        (rf.ward_isotropic, (0.0, 1.0, 0.5)),
        (rf.oren_nayar, (1.0, 0.5)),
        (rf.oren_nayar, (1.0, 1.0)),
    ],
)
def test_energy_bounded(fn, params, quad):
    for to in (0.0, 0.5, 1.0, 1.3, 1.5):
        assert albedo(fn, params, to, quad) <= 1.0


def test_energy_small_roughness_normalization(quad):
    # Beckmann D and Ward's lobe are normalized: albedo -> ks at normal view as roughness -> 0
    assert albedo(rf.cook_torrance, (0.0, 1.0, 0.05, 1e8), 0.0, quad) == pytest.approx(1.0, abs=5e-3)
    assert albedo(rf.ward_isotropic, (0.0, 1.0, 0.05), 0.0, quad) == pytest.approx(1.0, abs=1e-2)
    # Lafortune lobe at normal view: (Cz cos(theta_i))^n has albedo Cz^n 2 pi/(n+2); plus kd
    e = 6.5
    cz = ((e + 2) / (2 * np.pi)) ** (1 / e)
    lobes = np.array([[-1.0, cz, e], [1.0, cz, e]])  # the second lobe: same value at wo = n
    assert albedo(rf.lafortune, (0.25, lobes), 0.0, quad) == pytest.approx(2.25, rel=1e-9)


# ---------------------------------------------------------------- horizon and gradients


def _call(name, wi, wo, n, params=None):
    fn, p = MODELS[name]
    return fn(wi, wo, n, *(p if params is None else params))


@pytest.mark.parametrize("name", list(MODELS))
def test_below_horizon_zero_and_finite_gradients(name):
    """Exactly 0 below either horizon, with finite (zero) gradients in every argument;
    finite positive values and finite gradients at the singular points inside."""
    fn, params = MODELS[name]
    s45 = np.sqrt(0.5)
    a = np.array([np.sin(0.4), 0.0, np.cos(0.4)])
    below = [
        ([1.0, 0.0, 0.0], [0.0, s45, s45]),  # wi . n = 0
        ([s45, 0.0, s45], [0.0, 1.0, 0.0]),  # wo . n = 0
        ([0.6, 0.0, -0.8], [0.0, s45, s45]),  # clearly below
        (np.array([1.0, 0.0, -1e-9]) / np.hypot(1, 1e-9), [-s45, 0.0, s45]),  # slightly below
        (-Z, -Z),
    ]
    inside = [(Z, Z), (a, a), (Z, a), (a, -a * [1, 1, -1])]  # wi = wo = n; wi = wo; theta_h = 0
    wi = np.array([c[0] for c in below + inside], dtype=np.float64)
    wo = np.array([c[1] for c in below + inside], dtype=np.float64)
    nb = len(below)
    param_idx = [i for i, p in enumerate(params) if p is not None]

    def f(wi, wo, n, *ps):
        full = list(params)
        for i, p in zip(param_idx, ps):
            full[i] = p
        return fn(wi, wo, n, *full)

    ps = [jnp.asarray(params[i], dtype=jnp.float64) for i in param_idx]
    n = np.broadcast_to(Z, wi.shape)
    val = np.asarray(f(wi, wo, n, *ps))
    np.testing.assert_array_equal(val[:nb], 0.0)
    assert np.all(np.isfinite(val[nb:]) & (val[nb:] > 0))
    # per-sample gradients (the samples are independent) and weighted parameter gradients
    grad = jax.jit(jax.grad(lambda w, *a: jnp.sum(w * f(*a)), argnums=tuple(range(1, 4 + len(ps)))))
    grads = grad(np.ones(len(wi)), wi, wo, n, *ps)
    for gi in grads:
        assert np.all(np.isfinite(gi))
    for gi in grads[:3]:
        np.testing.assert_array_equal(gi[:nb], 0.0)
    below_only = grad((np.arange(len(wi)) < nb).astype(np.float64), wi, wo, n, *ps)
    for gi in below_only:
        np.testing.assert_array_equal(gi, 0.0)


@pytest.mark.parametrize("name", ["cook_torrance", "torrance_sparrow", "oren_nayar", "lafortune"])
def test_gradients_match_finite_differences(rng, name):
    fn, params = MODELS[name]
    wi, wo, _ = upper_pairs(rng, (), normal=Z)
    idx = [i for i, p in enumerate(params) if p is not None and np.ndim(p) == 0]

    def g(x):
        full = list(params)
        for k, i in enumerate(idx):
            full[i] = x[3 + k]
        d = jnp.array([jnp.sin(x[0]), 0.0, jnp.cos(x[0])])
        e = jnp.stack([jnp.sin(x[1]) * jnp.cos(x[2]), jnp.sin(x[1]) * jnp.sin(x[2]), jnp.cos(x[1])])
        return fn(d, e, Z, *full)

    g = jax.jit(g)
    x0 = np.array([0.5, 0.7, 2.0] + [float(params[i]) for i in idx])
    jac = np.asarray(jax.grad(g)(jnp.asarray(x0)))
    eps = 1e-6
    fd = np.array([(float(g(x0 + eps * e)) - float(g(x0 - eps * e))) / (2 * eps) for e in np.eye(len(x0))])
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-8)


# ---------------------------------------------------------------- batching, dtype, jit, errors


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_batch_shapes(rng, shape):
    wi, wo, n = upper_pairs(rng, shape)
    for name in ("cook_torrance", "lafortune"):
        out = _call(name, wi, wo, n)
        assert out.shape == shape
        flat = _call(name, wi.reshape(-1, 3), wo.reshape(-1, 3), n.reshape(-1, 3))
        np.testing.assert_allclose(np.asarray(out).reshape(-1), flat, rtol=1e-14)
    for k in rf.rusinkiewicz_angles(wi, wo, n):
        assert k.shape == shape
    assert rf.uvw_from_directions(wi, wo, n).shape == shape + (3,)


def test_broadcasting_between_arguments(rng):
    wi, wo, _ = upper_pairs(rng, (3, 1, 1), normal=Z)
    kd = np.array([0.1, 0.2])
    out = rf.cook_torrance(wi, wo, Z, kd, 0.5, np.full((3, 1, 1), 0.3), 1.5)
    assert out.shape == (3, 1, 2)
    np.testing.assert_allclose(out[..., 1] - out[..., 0], 0.1 / np.pi, rtol=1e-12)
    # per-sample lobes (..., K, 3) and channels via an explicit axis
    lobes = np.broadcast_to(np.array([[-1.0, 1.0, 5.0]]), (3, 1, 2, 1, 3))
    assert rf.lafortune(wi, wo, Z, 0.2, lobes).shape == (3, 1, 2)
    rgb = rf.torrance_sparrow(wi, wo, Z, np.array([0.1, 0.2, 0.3]), 0.5, 1.5, 0.1)
    assert rgb.shape == (3, 1, 3)
    np.testing.assert_allclose(rgb[..., 2] - rgb[..., 0], 0.2, rtol=1e-12)


def test_float32(rng):
    wi, wo, n = upper_pairs(rng, (200,))
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    for name, (fn, params) in MODELS.items():
        params32 = tuple(f32(p) if isinstance(p, np.ndarray) else p for p in params)
        out = fn(f32(wi), f32(wo), f32(n), *params32)
        assert out.dtype == jnp.float32, name
        ref = np.asarray(fn(wi, wo, n, *params))
        np.testing.assert_allclose(out, ref, rtol=tol(np.float32, x32=2e-3), atol=1e-6 * ref.max())
    assert rf.fresnel_normalized(jnp.float32(0.5), 1.5).dtype == jnp.float32
    assert rf.uvw(jnp.float32(0.1), 0.2, 0.3).dtype == jnp.float32
    for a in rf.rusinkiewicz_angles(f32(wi), f32(wo), f32(n)):
        assert a.dtype == jnp.float32
    # mixed float32 directions and float64 parameters follow the wider dtype
    assert rf.ward_isotropic(f32(wi), f32(wo), f32(n), jnp.float64(0.1), 0.5, 0.2).dtype == jnp.float64


def test_jit_vmap_no_retrace(rng):
    wi, wo, n = upper_pairs(rng, (8,))
    traces = []

    @jax.jit
    def f(kd, ks, m, mu):
        traces.append(1)
        return rf.cook_torrance(wi, wo, n, kd, ks, m, mu)

    a = f(0.1, 0.5, 0.3, 1.5)
    b = f(0.2, 0.4, 0.25, 1.7)
    assert len(traces) == 1 and not np.allclose(a, b)
    np.testing.assert_allclose(b, rf.cook_torrance(wi, wo, n, 0.2, 0.4, 0.25, 1.7), rtol=1e-14)
    sig = jnp.array([0.1, 0.2, 0.3])
    v = jax.vmap(lambda s: rf.torrance_sparrow(wi, wo, n, 0.1, 0.5, 1.5, s))(sig)
    assert v.shape == (3, 8)
    np.testing.assert_allclose(v[1], rf.torrance_sparrow(wi, wo, n, 0.1, 0.5, 1.5, 0.2), rtol=1e-14)


def test_errors():
    good = np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="`wi`"):
        rf.cook_torrance(np.zeros(2), good, good, 0.1, 0.5, 0.3, 1.5)
    with pytest.raises(ValueError, match="`wo`"):
        rf.phong(good, np.zeros((4, 4)), good, 3.0)
    with pytest.raises(ValueError, match="`n`"):
        rf.rusinkiewicz_angles(good, good, 1.0)
    with pytest.raises(ValueError, match="`lobes`"):
        rf.lafortune(good, good, good, 0.1, np.ones(3))
    with pytest.raises(ValueError, match="`kd`"):
        rf.lambertian(np.ones((4, 3)), good, good, np.ones(3))
    with pytest.raises(ValueError, match="`sigma`"):
        rf.oren_nayar(np.ones((4, 3)), good, good, 1.0, np.ones((2, 2)))
    with pytest.raises(ValueError, match="`mu`"):
        rf.fresnel_dielectric(np.ones(3), np.ones(2))
    with pytest.raises(ValueError, match="`theta_d`"):
        rf.uvw(np.ones(3), 0.0, np.ones(4))
    with pytest.raises(ValueError, match="`mu`"):
        rf.fresnel_normalized(0.5, 1j)


def test_half_angle_matches_rusinkiewicz_theta_h(rng):
    """`half_angle` (the renderers' kernel) equals the theta_h of `rusinkiewicz_angles`, and is exact near 0."""
    import jaxsh

    n = np.array([0.0, 0.0, 1.0])
    wi = rng.normal(size=(200, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo = rng.normal(size=(200, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    th = np.asarray(jaxsh.half_angle(wi, wo, np.broadcast_to(n, wi.shape)))
    ref = np.asarray(jaxsh.rusinkiewicz_angles(wi, wo, np.broadcast_to(n, wi.shape))[0])
    np.testing.assert_allclose(th, ref, atol=1e-12)
    # tiny angle: wi, wo mirror-symmetric at 1e-9 from the normal
    e = 1e-9
    a = np.array([[np.sin(e), 0.0, np.cos(e)]])
    b = np.array([[np.sin(e), 0.0, np.cos(e)]])
    np.testing.assert_allclose(np.asarray(jaxsh.half_angle(a, b, n[None])), [e], rtol=1e-6)


def _half_angle_grad_closed_form(wi, wo, n):
    """d theta_h / d n for theta_h = atan2(|h x n|, h . n), h = wi + wo, written out in NumPy."""
    h = wi + wo
    x = np.cross(h, n)
    s = np.linalg.norm(x)
    c = h @ n
    grad_s = np.cross(x, h) / s  # d|h x n|/dn = ((h x n) x h) / |h x n|
    return (c * grad_s - s * h) / (s * s + c * c)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_half_angle_gradient_safe_at_and_near_zero(dtype):
    """theta_h = 0 (light, view, normal aligned): exact value, finite gradient (0: the cone's symmetric
    subgradient); at theta_h = 1e-7: jacfwd = jacrev = the closed-form gradient (float64 and float32)."""
    import jaxsh

    u = np.array([0.3, 0.2, 0.93])
    u = (u / np.linalg.norm(u)).astype(dtype)
    for n0 in (np.array([0.0, 0.0, 1.0], dtype), u):
        f = lambda n: jaxsh.half_angle(n0, n0, n)
        th = float(f(n0))
        # exact at the pole; elsewhere |h x n| of parallel vectors may round (FMA) to ~1 ulp
        assert th == 0.0 if n0[2] == 1 else th <= 2 * np.finfo(dtype).eps
        for jac in (jax.grad(f), jax.jacfwd(f), jax.jacrev(f)):
            g = np.asarray(jac(n0))
            assert g.dtype == dtype and np.all(np.isfinite(g))
            if th == 0.0:
                np.testing.assert_array_equal(g, 0.0)
    e = 1e-7
    w = np.array([np.sin(e), 0.0, np.cos(e)], dtype)
    n = np.array([0.0, 0.0, 1.0], dtype)
    f = lambda n: jaxsh.half_angle(w, w, n)
    np.testing.assert_allclose(float(f(n)), e, rtol=1e-6)
    want = _half_angle_grad_closed_form(w.astype(np.float64), w.astype(np.float64), n.astype(np.float64))
    tol = 1e-10 if dtype == np.float64 else 1e-5
    fwd, rev = np.asarray(jax.jacfwd(f)(n)), np.asarray(jax.jacrev(f)(n))
    np.testing.assert_allclose(fwd, rev, rtol=tol, atol=tol)
    np.testing.assert_allclose(rev, want, rtol=tol, atol=tol)
    if dtype == np.float64:  # a central difference with a step below theta_h
        h = 1e-10
        fd = [(float(f(n + h * ek)) - float(f(n - h * ek))) / (2 * h) for ek in np.eye(3)]
        np.testing.assert_allclose(fd, want, rtol=1e-5, atol=1e-5)


def test_half_angle_kernel_in_the_brdfs(rng):
    """torrance_sparrow / cook_torrance use the same safe kernel: finite gradients at theta_h = 0, and
    torrance_sparrow's lobe from theta_h computed independently (arccos, float64) away from 0."""
    n = np.array([0.0, 0.0, 1.0])
    for fn in (lambda wi: rf.torrance_sparrow(wi, n, n, 0.2, 0.5, 1.5, 0.1), lambda wi: rf.cook_torrance(wi, n, n, 0.2, 0.5, 0.3, 1.5)):
        g = np.asarray(jax.grad(fn)(n))
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(np.asarray(jax.jacfwd(fn)(n)), g, atol=1e-12)
    wi = rng.normal(size=(50, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo = np.array([0.3, 0.0, 0.95]) / np.linalg.norm([0.3, 0.0, 0.95])
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    th = np.arccos(np.clip(h @ n, -1, 1))
    want = 0.2 + 0.5 * np.asarray(rf.fresnel_normalized(wo @ n, 1.5)) * np.exp(-((th / 0.1) ** 2)) / (np.pi * 0.01) / (4 * (wi @ n) * (wo @ n))
    np.testing.assert_allclose(rf.torrance_sparrow(wi, wo, n, 0.2, 0.5, 1.5, 0.1), want, rtol=1e-9)
