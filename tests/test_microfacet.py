"""Fuller reference BRDFs (jaxsh._microfacet: Cook-Torrance/Beckmann and GGX with Smith G, Fresnel at the
half angle) and an inverse test that can see the practical model's error.

Expected values are independent: NumPy/SciPy formulas written out here (Snell's-law Fresnel, scipy's erf),
quadrature for the normalizations and albedos, and the simplified Torrance-Sparrow model for the small-sigma
limit.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special as sp

import jaxsh
import solvers
from jaxsh import _microfacet as mf

from .helpers import random_dirs

Z = np.array([0.0, 0.0, 1.0])
MODELS = {"cook_torrance": jaxsh.cook_torrance_smith, "ggx": jaxsh.ggx}


# ---------------------------------------------------------------- independent NumPy references


def np_fresnel(c, mu):
    """Unpolarized dielectric Fresnel reflectance from Snell's law and the s/p amplitudes (Born & Wolf 1.5.2)."""
    c = np.asarray(c, np.float64)
    ct = np.sqrt(1 - (1 - c**2) / mu**2)  # cos of the refracted angle (mu >= 1: no TIR)
    rs = (c - mu * ct) / (c + mu * ct)
    rp = (mu * c - ct) / (mu * c + ct)
    return 0.5 * (rs**2 + rp**2)


def np_microfacet(wi, wo, n, kd, ks, mu, sigma, model):
    """rho = kd + ks F(wi.h)/F(0) D G1(wi) G1(wo) / (4 cos_i cos_o), written out (Walter et al. 2007)."""
    ci, co = wi @ n, wo @ n
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
    ch = h @ n
    th = np.arccos(np.clip(ch, -1, 1))
    t2 = np.tan(th) ** 2

    def tan2(c):
        return (1 - c**2) / c**2

    if model == "cook_torrance":
        d = np.exp(-t2 / sigma**2) / (np.pi * sigma**2 * ch**4)

        def g1(c):
            a = 1 / (sigma * np.sqrt(tan2(c)))
            return 2 / (1 + sp.erf(a) + np.exp(-a * a) / (a * np.sqrt(np.pi)))
    else:
        d = sigma**2 / (np.pi * ch**4 * (sigma**2 + t2) ** 2)

        def g1(c):
            return 2 / (1 + np.sqrt(1 + sigma**2 * tan2(c)))

    f = 1.0 if mu is None else np_fresnel(np.sum(wi * h, -1), mu) / ((mu - 1) / (mu + 1)) ** 2
    return kd + ks * f * d * g1(ci) * g1(co) / (4 * ci * co)


def hemisphere_rule(n_theta=400, n_phi=400):
    """Gauss-Legendre in theta in [0, pi/2] x uniform phi: directions (M, 3) about +z and weights (dw)."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    t = 0.25 * np.pi * (x + 1)
    wt = 0.25 * np.pi * w * np.sin(t)
    p = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    d = np.stack([np.sin(t)[:, None] * np.cos(p), np.sin(t)[:, None] * np.sin(p), np.cos(t)[:, None] + 0 * p], -1)
    return d.reshape(-1, 3), (wt[:, None] * np.full(n_phi, 2 * np.pi / n_phi)).reshape(-1)


@pytest.fixture(scope="module")
def hemi():
    return hemisphere_rule()


def albedo(fn, params, theta_o, hemi):
    """Directional albedo int rho(wi, wo) cos(theta_i) dwi at exitance angle theta_o, by quadrature."""
    d, w = hemi
    wo = np.array([np.sin(theta_o), 0.0, np.cos(theta_o)])
    rho = np.asarray(fn(d, wo[None], Z[None], *params))
    return float(np.sum(rho * d[:, 2] * w))


# ---------------------------------------------------------------- the BRDFs


@pytest.mark.parametrize("model", sorted(MODELS))
@pytest.mark.parametrize("mu", [None, 1.6])
def test_matches_the_written_out_formula(rng, model, mu):
    wi, wo = random_dirs(rng, (400,)), random_dirs(rng, (400,))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]) + 0.02, np.abs(wo[:, 2]) + 0.02
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    for sigma in (0.07, 0.3, 0.8):
        got = np.asarray(MODELS[model](wi, wo, Z[None], 0.1, 0.7, mu, sigma))
        np.testing.assert_allclose(got, np_microfacet(wi, wo, Z, 0.1, 0.7, mu, sigma, model), rtol=1e-10)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_reciprocity_and_horizon(rng, model):
    n = random_dirs(rng, (500,))
    wi, wo = random_dirs(rng, (500,)), random_dirs(rng, (500,))
    fn = MODELS[model]
    a = np.asarray(fn(wi, wo, n, 0.2, 0.6, 1.5, 0.25))
    b = np.asarray(fn(wo, wi, n, 0.2, 0.6, 1.5, 0.25))
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)  # Helmholtz: f(wi, wo) = f(wo, wi)
    below = (np.sum(wi * n, -1) <= 0) | (np.sum(wo * n, -1) <= 0)
    assert below.any() and (~below).any()
    assert np.all(a[below] == 0.0) and np.all(a[~below] > 0.0)


@pytest.mark.parametrize("name, d", [("beckmann", mf._beckmann_d), ("ggx", mf._ggx_d)])
@pytest.mark.parametrize("sigma", [0.05, 0.2, 0.5, 1.0])
def test_distribution_is_normalized(name, d, sigma):
    """int D(theta_h) cos(theta_h) dw_h = 1 over the hemisphere (Walter et al. 2007 eq. 4), by quadrature in
    u = cos(theta_h) (2 pi int_0^1 D u du; composite Gauss-Legendre, panels refined towards u = 1 where a sharp lobe lives)."""
    x, w = np.polynomial.legendre.leggauss(100)
    edges = np.array([0.0, 0.25, 0.5, 0.75, 0.9, 0.97, 0.99, 0.997, 0.999, 0.9999, 1.0])  # composite rule
    lo, hi = edges[:-1, None], edges[1:, None]
    u, wu = (lo + 0.5 * (hi - lo) * (x + 1)).ravel(), (0.5 * (hi - lo) * w).ravel()
    val = np.asarray(jax.jit(d)(jnp.asarray((1 - u * u) / (u * u)), jnp.asarray(u), jnp.asarray(sigma)))
    assert 2 * np.pi * np.sum(wu * val * u) == pytest.approx(1.0, abs=1e-8)


@pytest.mark.parametrize("g1", [mf._smith_g1_beckmann, mf._smith_g1_ggx])
def test_smith_g1_range_and_normal_incidence(g1):
    theta = np.linspace(0.0, np.pi / 2 - 1e-3, 400)
    t2 = jnp.asarray(np.tan(theta) ** 2)
    for sigma in (0.05, 0.3, 1.0):
        g = np.asarray(jax.jit(g1)(t2, jnp.asarray(sigma)))
        assert np.all((g > 0) & (g <= 1.0))
        assert g[0] == 1.0  # normal incidence: nothing masked
        assert np.all(np.diff(g) <= 1e-15)  # masking grows towards grazing
        assert g[-1] < 0.5 if sigma >= 0.3 else g[-1] < 1.0
    # and the full G = G1 G1 of the BRDF: at wi = wo = n the BRDF is ks D(0)/4 exactly (G = 1, F/F0 = 1)
    for fn in MODELS.values():
        assert float(fn(Z, Z, Z, 0.0, 1.0, 1.5, 0.3)) == pytest.approx(1 / (4 * np.pi * 0.09), rel=1e-13)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_fresnel_at_the_half_angle(model):
    """The Fresnel factor is the dielectric F at theta_d (wi.h), normalized by F(0): the ratio of the BRDF
    with and without Fresnel, at configurations of known theta_d, equals the textbook closed form
    F = (g-c)^2/(2(g+c)^2) [1 + ((c(g+c)-1)/(c(g-c)+1))^2], g^2 = mu^2 - 1 + c^2."""
    mu, fn = 1.7, MODELS[model]
    f0 = ((mu - 1) / (mu + 1)) ** 2
    for td in (0.1, 0.6, 1.0, 1.3):
        # half vector tilted 0.2 rad from the normal, wi and wo at +-td about it (in the plane of incidence)
        th = 0.2
        wi = np.array([np.sin(th + td), 0.0, np.cos(th + td)])
        wo = np.array([np.sin(th - td), 0.0, np.cos(th - td)])
        if wi[2] <= 0 or wo[2] <= 0:
            continue
        c = np.cos(td)
        g = np.sqrt(mu**2 - 1 + c**2)
        f = (g - c) ** 2 / (2 * (g + c) ** 2) * (1 + ((c * (g + c) - 1) / (c * (g - c) + 1)) ** 2)
        ratio = float(fn(wi, wo, Z, 0.0, 1.0, mu, 0.3)) / float(fn(wi, wo, Z, 0.0, 1.0, None, 0.3))
        assert ratio == pytest.approx(f / f0, rel=1e-12)


@pytest.mark.parametrize("model", sorted(MODELS))
@pytest.mark.parametrize("sigma", [0.1, 0.3, 0.6])
def test_white_furnace_bound(model, sigma, hemi):
    """ks = 1, kd = 0, no Fresnel: single scattering loses energy to masking, never creates it. (At normal
    view and small sigma the exact albedo is 1 - O(e^{-1/sigma^2}): the bound holds to the quadrature's
    round-off, 1e-12.)"""
    for to in (0.0, 0.6, 1.1, 1.45):
        assert albedo(MODELS[model], (0.0, 1.0, None, sigma), to, hemi) <= 1.0 + 1e-12


def test_white_furnace_small_roughness_at_normal_view(hemi):
    # normalized D, G -> 1: the albedo at normal view tends to ks (Beckmann's tails are negligible; GGX's
    # heavy tails are masked at grazing angles, measured 0.985 at sigma = 0.1)
    assert albedo(jaxsh.cook_torrance_smith, (0.0, 1.0, None, 0.1), 0.0, hemi) == pytest.approx(1.0, abs=5e-3)
    assert 0.97 < albedo(jaxsh.ggx, (0.0, 1.0, None, 0.1), 0.0, hemi) < 1.0


def test_cook_torrance_tends_to_the_simplified_torrance_sparrow():
    """Small sigma, normal view: with m = sigma, D_Beckmann/S = 1 + O(sigma^2) over the lobe, G -> 1 and
    F(theta_d)/F(0) -> 1. Measured max relative difference over theta_h <= 2 sigma: 0.17 % (sigma 0.025),
    0.67 % (0.05), 2.75 % (0.1), i.e. about 2.7 sigma^2 -- the leading term of the expansion,
    (1/cos^4 - 1) - (tan^2 - theta^2)/sigma^2 = 2 th^2 - (2/3) th^4/sigma^2 = -2.67 sigma^2 at th = 2 sigma."""
    errs = []
    for sigma in (0.025, 0.05, 0.1):
        th = np.linspace(0, 2 * sigma, 60)
        wi = np.stack([np.sin(2 * th), 0 * th, np.cos(2 * th)], -1)  # wo = n: theta_h = theta_i / 2
        ct = np.asarray(jaxsh.cook_torrance_smith(wi, Z[None], Z[None], 0.0, 1.0, 1.5, sigma))
        ts = np.asarray(jaxsh.torrance_sparrow(wi, Z[None], Z[None], 0.0, 1.0, 1.5, sigma))
        errs.append(np.max(np.abs(ct / ts - 1)))
        assert errs[-1] < 3 * sigma**2
    assert errs[0] < errs[1] < errs[2]
    assert errs[2] / errs[1] == pytest.approx(4.0, rel=0.1)  # sigma^2 scaling


@pytest.mark.parametrize("model", sorted(MODELS))
def test_gradients_finite_at_singular_configurations(model):
    fn = MODELS[model]
    g = jax.grad(lambda p: fn(jnp.asarray(Z), jnp.asarray(Z), jnp.asarray(Z), 0.1, p[0], p[1], p[2]))(jnp.array([0.5, 1.5, 0.2]))
    assert np.all(np.isfinite(np.asarray(g)))
    below = jnp.asarray([0.6, 0.0, -0.8])
    gw = jax.grad(lambda w: fn(w, jnp.asarray(Z), jnp.asarray(Z), 0.1, 0.5, 1.5, 0.2))(below)
    assert np.all(np.asarray(gw) == 0.0)


def test_argument_errors():
    with pytest.raises(ValueError, match="sigma"):
        jaxsh.ggx(Z, Z, Z, 0.1, 0.5, 1.5, 0.0)
    with pytest.raises(ValueError, match="mu"):
        jaxsh.cook_torrance_smith(Z, Z, Z, 0.1, 0.5, 0.9, 0.2)
    with pytest.raises(ValueError, match="brdf_model"):
        jaxsh.render_reference(Z, Z, 0.1, 0.5, 1.5, 0.2, directional=(Z[None], np.ones((1, 1))), brdf_model="phong")


@pytest.mark.parametrize("model", ["torrance_sparrow", "cook_torrance", "ggx"])
def test_render_reference_integrates_the_chosen_brdf(rng, model):
    """Under directional sources the reference is exactly sum_j L_j rho(w_j, wo) max(n.w_j, 0)."""
    n = random_dirs(rng, (50,))
    v = n + 0.5 * random_dirs(rng, (50,))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    ld = random_dirs(rng, (3,))
    le = rng.uniform(0.5, 2.0, (3, 1))
    got = np.asarray(jaxsh.render_reference(n, v, 0.2, 0.5, 1.5, 0.25, directional=(ld, le), brdf_model=model))
    fn = {"torrance_sparrow": jaxsh.torrance_sparrow, **MODELS}[model]
    want = sum(
        le[j, 0] * np.asarray(fn(ld[j][None], v, n, 0.2, 0.5, 1.5, 0.25)) * np.maximum(n @ ld[j], 0) for j in range(3)
    )
    np.testing.assert_allclose(got[:, 0], want, rtol=1e-12, atol=1e-15)


def _pairs_case(rng, dtype):
    """60 pixels (some seen from behind, some grazing, one with n = v) x 240 directions (some grazing, one
    equal to the mirror direction of a pixel: theta_h = 0 exactly, one at n)."""
    n = random_dirs(rng, (60,))
    v = random_dirs(rng, (60,))
    v[:40] = n[:40] + 0.7 * v[:40]  # mostly above the horizon
    v[40:45] = np.cross(n[40:45], random_dirs(rng, (5,))) + 1e-3 * n[40:45]  # grazing exitance (rho ~ 1/cos)
    v[45] = n[45]
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    d = random_dirs(rng, (240,))
    d[:20] = np.cross(n[:20], random_dirs(rng, (20,))) + 1e-7 * n[:20]  # grazing incidence
    d[20] = 2 * (n[0] @ v[0]) * n[0] - v[0]  # the mirror direction of pixel 0
    d[21] = n[45]
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return n.astype(dtype), v.astype(dtype), d.astype(dtype)


@pytest.mark.parametrize("dtype,rtol", [(np.float64, 1e-11), (np.float32, 2e-4)])
@pytest.mark.parametrize("model", ["torrance_sparrow", "cook_torrance", "ggx"])
@pytest.mark.parametrize("mu", [None, 1.5])
def test_render_reference_pairwise_form_equals_the_brdf_of_each_pair(rng, model, mu, dtype, rtol):
    """The reference renderer evaluates the BRDF over (pixel, direction) pairs from per-pair scalars
    (`jaxsh._reference_pairs`). Against the public BRDF of each pair, pair by pair, including pixels seen
    from behind, grazing pairs and theta_h = 0; in float32 within the BRDF's own float32 rounding."""
    n, v, d = _pairs_case(rng, dtype)
    sigma = 0.2
    le = rng.uniform(0.5, 2.0, (240, 1)).astype(dtype)
    par = [dtype(0.25), dtype(0.5), None if mu is None else dtype(mu), dtype(sigma)]  # the dtype rule: widest wins
    got = np.asarray(jaxsh.render_reference(n, v, *par, directional=(d, le), brdf_model=model))
    assert got.dtype == dtype
    fn = {"torrance_sparrow": jaxsh.torrance_sparrow, **MODELS}[model]
    n64, v64, d64 = (a.astype(np.float64) for a in (n, v, d))
    rho = np.asarray(fn(d64[None], v64[:, None], n64[:, None], 0.25, 0.5, mu, sigma))  # (60, 240), float64
    want = np.sum(rho * np.maximum(n64 @ d64.T, 0.0) * le[:, 0].astype(np.float64)[None], -1)
    np.testing.assert_allclose(got[:, 0], want, rtol=rtol, atol=1e-12 if dtype == np.float64 else 1e-5)
    behind = np.sum(n64 * v64, -1) <= 0
    assert behind.sum() > 5 and np.all(got[behind] == 0)
    # the lobe at theta_h = 0 is in the sum: pixel 0 sees a pair at the peak of its lobe
    assert rho[0, 20] > 0.5 * np.max(rho[0])
    # the loop over pixels in chunks of 7 (the last one padded) gives the same image as one chunk: the same sum
    # of 240 non-negative terms per pixel, by a program of another shape, so within the sum's rounding bound
    # (n - 1) eps (XLA's optimization level 0 rounded one float32 pixel 32 ulp apart; a padding or
    # chunking error is of the order of the image)
    again = np.asarray(jaxsh.render_reference(n, v, *par, directional=(d, le), brdf_model=model, chunk=7))
    np.testing.assert_allclose(again, got, rtol=(d.shape[0] - 1) * np.finfo(dtype).eps, atol=0)


@pytest.mark.parametrize("model", ["torrance_sparrow", "cook_torrance", "ggx"])
def test_render_reference_gradients_against_finite_differences(rng, model):
    """d/d(sigma, mu, ks) of a reference render (a disk by quadrature + grazing directional sources) by
    autodiff against central differences; finite although some pairs are below a horizon."""
    n, v, d = _pairs_case(rng, np.float64)
    d1 = np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])
    le = np.ones((240, 1))

    def f(x):
        sigma, mu, ks = x[0], x[1], x[2]
        out = jaxsh.render_reference(n, v, 0.25, ks, mu, sigma, disks=(d1[None], np.array([0.3]), np.ones((1, 1))),
                                     directional=(d, le), disk_nodes=(12, 24), brdf_model=model)
        return jnp.sum(out)

    x = jnp.array([0.2, 1.5, 0.5])
    g = np.asarray(jax.grad(f)(x))
    assert np.all(np.isfinite(g))
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-6
        fd = (float(f(x + e)) - float(f(x - e))) / 2e-6
        np.testing.assert_allclose(g[k], fd, rtol=1e-6)


# ---------------------------------------------------------------- an inverse test that can see model error

CT_TRUTH = solvers.TorranceSparrow(jnp.array([0.12, 0.09, 0.07]), jnp.array([0.3, 0.3, 0.3]), jnp.asarray(1.6), jnp.asarray(0.15))
LMAX = 24  # e^{-(sigma l)^2} = e^{-13} at l = 24: the practical model's slow lighting is converged


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _render_ct(cams, disks, directional):
    gbs, imgs = [], []
    for cam in cams:
        gb = jaxsh.sphere_gbuffer(cam, jnp.zeros(3), jnp.asarray(1.0))
        m = np.asarray(gb.mask)
        img = np.zeros(m.shape + (3,))
        t = CT_TRUTH
        img[m] = np.asarray(jaxsh.render_reference(
            np.asarray(gb.normal)[m], np.asarray(gb.view)[m], t.kd, t.ks, t.mu, t.sigma,
            disks=disks, directional=directional, disk_nodes=(32, 64), brdf_model="cook_torrance"))
        gbs.append(gb)
        imgs.append(img)
    return gbs, imgs


def _known_lighting(disks, directional):
    slow = sum(jaxsh.disk_light_sh(jnp.asarray(disks[0][k]), disks[1][k], jnp.asarray(disks[2][k]), LMAX)
               for k in range(disks[0].shape[0]))
    if directional is None:
        return solvers.Lighting(slow)
    return solvers.Lighting(slow, jnp.asarray(directional[0]), jnp.asarray(directional[1]))


def test_fit_on_cook_torrance_data_relit_under_a_new_area_source():
    """Data the practical model cannot reproduce: a sphere rendered with Cook-Torrance (Beckmann, Smith G,
    Fresnel at the half angle) under the demo's area sources plus a directional source, 3 views of 24 px,
    noise-free. `fit_brdf` (practical model, eq. 24) under the known lighting; then a held-out view (the demo's,
    azimuth 2.4, elevation 0.2) is relit under a *different* area source, alone and with the same sun, and
    predicted by the fitted parameters and by the *true* parameters under the practical model (the floor).

    Measured (float64): training rel. RMS 5.9 %; fit mu 1.86 (truth 1.6), Ks 0.314 (0.3), sigma 0.148 (0.15).
    Held-out, new area source alone: fitted 6.6 %, floor 3.6 % (1.8x); new area source + the same sun:
    fitted 4.0 %, floor 0.78 % (5x). The fit compensates the half-angle Fresnel and G of the data with a
    larger mu and Ks for the training views and lighting; that compensation does not carry over to a new view
    and light, so the fitted model predicts worse than the true parameters would -- the gap this test exists
    to show (with `torrance_sparrow` data the fit matches the floor; issue 14). Asserted: the floor is
    clearly above 0, the fitted error within 2x floor + 0.5 % for the area source (where the floor is the
    eq. 24 area-light approximation), and in both cases no worse than 1.2x the training residual (the fit
    generalizes as well as it fits).
    """
    disks, directional = solvers.default_sources()
    gbs, imgs = _render_ct(solvers.view_cameras(3, 24), disks, directional)
    res = solvers.fit_brdf(solvers.observations(gbs, imgs), _known_lighting(disks, directional))
    assert solvers.status_name(res.status) == "converged"
    assert float(res.brdf.sigma) == pytest.approx(0.15, rel=0.05)

    new_disks = (_unit([-0.3, 0.6, 0.75])[None], np.array([0.4]), np.array([[2.0, 1.8, 1.6]]))
    cam = solvers.view_cameras(1, 24, azimuths=[2.4], elevation=0.2)
    errs = {}
    for name, sun in (("area", None), ("area+sun", directional)):
        (gb,), (img,) = _render_ct(cam, new_disks, sun)
        m = np.asarray(gb.mask)
        light = _known_lighting(new_disks, sun)

        def err(brdf):
            p = np.asarray(solvers.predict(brdf, light, gb.normal, gb.view, mask=gb.mask))[m]
            return float(np.sqrt(np.mean((p - img[m]) ** 2) / np.mean(img[m] ** 2)))

        errs[name] = (err(res.brdf), err(CT_TRUTH))
    for name, (fit, floor) in errs.items():
        assert floor > 0.005, (name, errs)  # the test can see model error
        assert fit <= 1.2 * float(res.rel_rms), (name, errs, float(res.rel_rms))
    fit, floor = errs["area"]
    assert fit <= 2.0 * floor + 0.005, errs
