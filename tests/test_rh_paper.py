"""R&H 2001 / Ramamoorthi thesis ch. 3 results reproduced from the solvers (issue 14).

- the literal eq. 25 (the diffuse term summed to l*): a Lambertian object's odd l > 1 are
  ill-posed (zero singular values), even l ill-conditioned (tiny, nonzero), thesis eq. 3.33;
- a textured (K_d(x), K_s(x)) fit predicting the object under a new light (fig. 15 analogue);
- `fit_brdf_sh` on reference-rendered images, and the ringing of a truncated SH BRDF (fig. 6).

Expected values come from scipy (Legendre quadrature, scipy's spherical harmonics) or from the
reference renderer, never from the code under test.
"""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate as si
import scipy.special as sp

import jaxsh
import solvers

from .helpers import scipy_real_sh


def _clamped_cosine_coeff(l):
    """Lambda_l rho_l of the Lambertian BRDF = 2 pi int_0^1 P_l(x) x dx (thesis eq. 3.30), by quadrature."""
    return 2 * np.pi * si.quad(lambda x: sp.eval_legendre(l, x) * x, 0.0, 1.0, epsabs=1e-14, epsrel=1e-13)[0]


def _sphere_quadrature(n_theta, n_phi):
    """Gauss-Legendre in cos(theta) x uniform phi: exact for the products of SH up to degree 2 n_theta - 1."""
    x, wx = np.polynomial.legendre.leggauss(n_theta)
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    ct, ph = np.meshgrid(x, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    dirs = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3)
    w = (wx[:, None] * np.full(n_phi, 2 * np.pi / n_phi)[None, :]).reshape(-1)
    return dirs, w


def _obs(normals, views, values, weights):
    n = normals.shape[0]
    f = lambda a: jnp.asarray(a, jnp.float64)  # noqa: E731
    return solvers.Observations(f(normals), f(views), f(values), f(weights), None, None, None, None,
                                jnp.zeros(n, jnp.int32), jnp.arange(n, dtype=jnp.int32), ((n, 1),))


# --------------------------------------------------------------------------- the literal eq. 25


def test_closed_form_clamped_cosine_matches_thesis_table():
    """The independent reference itself: thesis eq. 3.33 (3 decimals)."""
    table = {0: 3.142, 1: 2.094, 2: 0.785, 3: 0.0, 4: -0.131, 5: 0.0, 6: 0.049}
    for l, v in table.items():
        assert abs(_clamped_cosine_coeff(l) - v) < 6e-4, (l, _clamped_cosine_coeff(l))


def test_literal_eq25_lambertian_odd_bands_ill_posed_even_ill_conditioned():
    """Thesis ch. 3 (after eq. 3.33): with the diffuse term summed to l* (eq. 25 as printed) inverse
    lighting from a Lambertian object is ill-posed for odd l > 1 and ill-conditioned for even l.

    Normals at a spherical quadrature (every normal seen head-on, weight = solid angle) make the
    weighted design matrix K_d diag(Lambda_l rho_l) Y: its singular values are exactly
    K_d |Lambda_l rho_l|, each 2l+1 times; compared with the closed form by scipy quadrature."""
    lmax = 8
    dirs, w = _sphere_quadrature(12, 26)  # exact to degree 23 >= 2 lmax
    kd = np.array([0.8, 0.5])
    a = np.array([_clamped_cosine_coeff(l) for l in range(lmax + 1)])
    rng = np.random.default_rng(3)
    L = rng.normal(size=((lmax + 1) ** 2, 2))
    deg = np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1)
    y = scipy_real_sh(dirs, lmax)
    img = (y * a[deg][None, :]) @ L * kd[None, :]  # R&H eq. 11 / thesis eq. 3.29, independent of jaxsh
    obs = _obs(dirs, dirs, img, w)
    lamb = solvers.TorranceSparrow(jnp.asarray(kd), jnp.zeros(2), None, jnp.asarray(0.1))
    res = solvers.inverse_lighting(obs, lamb, lmax, diffuse_bands="literal")

    expect = np.sort(np.abs(a[deg]))[::-1]
    sv = np.asarray(res.singular_values)
    odd = (deg % 2 == 1) & (deg > 1)
    n_odd = int(odd.sum())  # 7 + 11 + 15 = 33 coefficients of l = 3, 5, 7
    assert n_odd == 33 and np.all(np.abs(a[[3, 5, 7]]) < 1e-12)
    for c in range(2):
        np.testing.assert_allclose(sv[c, :-n_odd], kd[c] * expect[:-n_odd], rtol=1e-9)
    # ill-posed: zero up to round-off. The singular values are square roots of the eigenvalues of
    # A^T W A, whose round-off is ~eps * max, so "zero" reads ~sqrt(eps) * max (measured 9e-9)
    assert np.all(sv[:, -n_odd:] < 1e-7 * sv[:, :1])
    assert np.all(np.asarray(res.stats["rank"]) == 81 - n_odd)
    # ill-conditioned: even l > 2 nonzero but tiny; condition number of the l <= 8 even part
    even_hi = np.abs(a[[4, 6, 8]])
    assert np.all(even_hi > 1e-3 * np.pi) and np.all(even_hi < 0.05 * np.pi)
    assert sv[0, -n_odd - 1] == pytest.approx(kd[0] * abs(a[8]), rel=1e-9)
    # the solve finds the same: odd l > 1 undetermined, even l determined (noise-free data: recovered)
    det = np.asarray(res.determined)
    assert not np.any(det[odd]) and np.all(det[~odd])
    assert np.all(np.isinf(np.asarray(res.std_errors)[odd]))
    np.testing.assert_allclose(np.asarray(res.coeffs)[~odd], L[~odd], atol=1e-8)
    assert np.all(np.asarray(res.supported_lmax) == 2)
    assert solvers.status_name(res.status) == "ill_conditioned"
    # the noise gain of an even band is 1/|Lambda_l rho_l|: l = 8 is ~ |A_0/A_8| times noisier than l = 0
    res_n = solvers.inverse_lighting(_obs(dirs, dirs, img + 1e-3 * rng.normal(size=img.shape), w), lamb, lmax,
                                     diffuse_bands="literal")
    se = np.asarray(res_n.std_errors)[:, 0]
    assert se[64] / se[0] == pytest.approx(abs(a[0] / a[8]), rel=1e-6)


def test_literal_eq25_on_a_rendered_sphere_and_the_default():
    """Three views of a Lambertian sphere rendered by the reference renderer (hemispheres of normals,
    not a quadrature): the literal form still has exactly 33 zero singular values (odd 3 <= l <= 7) and
    nonzero even ones; the default form ("l2") has the l > 2 columns cut by construction."""
    lamb = solvers.TorranceSparrow(jnp.array([0.6, 0.45, 0.3]), jnp.zeros(3), None, jnp.asarray(0.1))
    cap = solvers.sphere_capture(lamb, size=32, noise=0.0, sources=(None, solvers.default_sources()[1]))
    obs = solvers.observations(cap.gbuffers, cap.clean)
    lit = solvers.inverse_lighting(obs, lamb, 8, diffuse_bands="literal")
    l2 = solvers.inverse_lighting(obs, lamb, 8)
    sv = np.asarray(lit.singular_values)
    assert np.all(sv[:, -33:] < 1e-7 * sv[:, :1])  # sqrt(eps) floor of the Gram eigen-solve (measured 4e-9)
    assert np.all(np.asarray(lit.stats["rank"]) == 48)
    assert np.all(sv[:, :-33] > 1e-4 * sv[:, :1])
    deg = np.repeat(np.arange(9), 2 * np.arange(9) + 1)
    odd = (deg % 2 == 1) & (deg > 1)
    det = np.asarray(lit.determined)
    assert not np.any(det[odd]) and np.all(det[~odd])
    assert np.all(np.asarray(l2.singular_values)[:, 9:] < 1e-6 * np.asarray(l2.singular_values)[:, :1])
    # l <= 2 agree between the forms up to the even-band leakage the literal model absorbs
    assert float(lit.rel_rms) <= float(l2.rel_rms) + 1e-12
    with pytest.raises(ValueError, match="diffuse_bands"):
        solvers.inverse_lighting(obs, lamb, 8, diffuse_bands="all")


# --------------------------------------------------------------------------- textured K_d, K_s (sec. 6.4, fig. 15)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def test_textured_kd_ks_fit_predicts_the_object_under_a_new_light():  # 8 s at XLA's level 0 (`make test`)
    """Fig. 15 analogue: a sphere with 4 texels of different K_d and K_s (RGB), six views each lit by the
    area source plus its own directional source, all rendered by the reference renderer (quadrature over
    the disk, the full Torrance-Sparrow BRDF). `fit_brdf(textured="kd_ks")` with the lighting known; the
    fitted texture then predicts a held-out view under a NEW light (another disk and sun) and is compared
    with the reference render of the truth, next to the floor: the true parameters under the practical
    model (eq. 24) the fit uses."""
    kd_t = np.array([[0.55, 0.35, 0.2], [0.2, 0.5, 0.3], [0.6, 0.15, 0.15], [0.25, 0.3, 0.55]])
    ks_t = np.array([[0.3, 0.3, 0.3], [0.15, 0.15, 0.15], [0.4, 0.35, 0.3], [0.25, 0.25, 0.25]])
    mu, sigma = 1.6, 0.15
    disk = (_unit([0.45, -0.55, 0.7])[None], np.array([0.6]), np.array([[1.6, 1.5, 1.35]]))
    slow = jaxsh.disk_light_sh(disk[0][0], 0.6, disk[2][0], 24)
    suns = [_unit(d) for d in ([-0.35, 0.5, 0.8], [0.6, 0.3, 0.75], [0.1, -0.7, 0.7], [-0.7, -0.2, 0.7],
                               [0.5, 0.6, 0.6], [-0.2, 0.2, 0.95])]
    e = np.array([[3.0, 3.0, 3.0]])

    def texel_of(p):  # quadrants in x, y
        return ((p[..., 0] > 0).astype(np.int32) * 2 + (p[..., 1] > 0).astype(np.int32))

    def render(cam, sun, disks):
        g = jaxsh.sphere_gbuffer(cam, np.zeros(3), 1.0)
        m = np.asarray(g.mask)
        n, v = np.asarray(g.normal)[m], np.asarray(g.view)[m]
        t = texel_of(n)
        out = np.asarray(jaxsh.render_reference(n, v, kd_t[t], ks_t[t], mu, sigma, disks=disks,
                                                directional=(sun[None], e), disk_nodes=(24, 48)))
        return g, m, n, v, t, out

    cams = solvers.view_cameras(6, 32, azimuths=np.linspace(0.0, 2 * np.pi, 6, endpoint=False), elevation=0.5)
    gbs, imgs, texels, lights = [], [], [], []
    for cam, sun in zip(cams, suns):
        g, m, n, v, t, out = render(cam, sun, disk)
        img = np.zeros(m.shape + (3,))
        img[m] = out
        tex = np.zeros(m.shape, np.int64)
        tex[m] = t
        gbs.append(g), imgs.append(img), texels.append(tex)
        lights.append(solvers.Lighting(slow, jnp.asarray(sun[None]), jnp.asarray(e)))
    obs = solvers.observations(gbs, imgs, texel=texels, n_texels=4)
    res = solvers.fit_brdf(obs, lights, textured="kd_ks")
    assert solvers.status_name(res.status) == "converged"
    assert np.all(np.asarray(res.texel_count) > 0)
    kd, ks = np.asarray(res.brdf.kd), np.asarray(res.brdf.ks)
    assert kd.shape == ks.shape == (4, 3)
    kd_err = np.abs(kd - kd_t).max()
    ks_err = np.abs(ks - ks_t).max()
    assert kd_err < 0.02 and ks_err < 0.03, (kd_err, ks_err)  # measured 0.005, 0.010
    assert abs(float(res.brdf.sigma) - sigma) < 0.15 * sigma

    # held-out view, new lighting: a different area source and sun
    new_disk = (_unit([-0.5, 0.4, 0.6])[None], np.array([0.4]), np.array([[1.2, 1.4, 1.6]]))
    new_sun = _unit([0.2, 0.8, 0.55])
    cam = solvers.view_cameras(1, 40, azimuths=[0.5], elevation=0.3)[0]
    g, m, n, v, t, ref = render(cam, new_sun, new_disk)
    new = solvers.Lighting(jaxsh.disk_light_sh(new_disk[0][0], 0.4, new_disk[2][0], 24), jnp.asarray(new_sun[None]),
                           jnp.asarray(e))
    pred = np.asarray(solvers.predict(res.brdf, new, n, v, texel=t))
    truth = solvers.TorranceSparrow(jnp.asarray(kd_t), jnp.asarray(ks_t), jnp.asarray(mu), jnp.asarray(sigma))
    floor = np.asarray(solvers.predict(truth, new, n, v, texel=t))

    def rel(x):
        return np.sqrt(np.mean((x - ref) ** 2)) / np.sqrt(np.mean(ref**2))

    err, err_floor = rel(pred), rel(floor)
    print(f"textured kd_ks: kd err {kd_err:.4f}, ks err {ks_err:.4f}, sigma {float(res.brdf.sigma):.4f}, "
          f"mu {float(res.brdf.mu):.3f}; new light: fitted {err:.4%}, true params {err_floor:.4%}")
    assert err < 0.02, err  # measured 0.93 % (true parameters: 0.90 %)
    assert err < err_floor + 0.003


# --------------------------------------------------------------------------- fit_brdf_sh on reference images (sec. 6.1, fig. 6)


@pytest.mark.slow  # ~80 s: reference renders of several views (make test-all)
def test_fit_brdf_sh_on_reference_images_fig6():
    """Fig. 6 (bottom) analogue on data with model error: a Cook-Torrance sphere (Beckmann, Smith G,
    Fresnel at the half angle; not representable at order 6) rendered by the reference renderer under the
    low-frequency area sources, SH BRDF fitted to order 6 (eqs. 9, 10), five views at one elevation. Under the same low-frequency
    lighting a held-out view is predicted closely ("only the low-frequency components of the BRDF are
    important"); lit by a directional source at the viewpoint, the truncated BRDF rings: negative radiance
    and an error of the order of the signal."""
    truth = solvers.TorranceSparrow(jnp.array([0.15]), jnp.array([0.4]), jnp.asarray(1.6), jnp.asarray(0.15))
    disks, _ = solvers.default_sources()
    disks = (disks[0], disks[1], disks[2][:, :1])
    cap = solvers.sphere_capture(truth, size=32, n_views=5, noise=0.0, azimuths=np.linspace(0, 2 * np.pi, 5, endpoint=False),
                                 elevation=0.6, sources=(disks, None), disk_nodes=(24, 48), brdf_model="cook_torrance")
    obs = solvers.observations(cap.gbuffers, [im[..., :1] for im in cap.clean])
    lmax = 6
    sh = np.asarray(cap.lighting.total_sh(lmax))[:, :1]
    # truncated SVD (rcond 1e-2, rank 76 of 140): with the default 1e-10 (rank 137) the weakly determined
    # coefficients absorb the model error, and the held-out view is off by 9.5 % (143 % at elevation 0.3)
    # and the directional rendering by ~10x the signal (measured)
    res = solvers.fit_brdf_sh(obs, sh, lmax, rcond=1e-2)
    assert solvers.status_name(res.status) == "converged"
    assert float(res.rel_rms) < 0.1  # measured 0.078: the order-6 model error on these images
    cam = solvers.view_cameras(1, 32, azimuths=[0.6], elevation=0.6)[0]  # between two training views
    g = jaxsh.sphere_gbuffer(cam, np.zeros(3), 1.0)
    m = np.asarray(g.mask)
    n, v = np.asarray(g.normal)[m], np.asarray(g.view)[m]
    ref = np.asarray(jaxsh.render_reference(n, v, truth.kd, truth.ks, truth.mu, truth.sigma, disks=disks, disk_nodes=(24, 48),
                                            brdf_model="cook_torrance"))[:, :1]
    pred = np.asarray(solvers.predict_brdf_sh(res.rho, sh, n, v))
    err_low = np.sqrt(np.mean((pred - ref) ** 2)) / np.sqrt(np.mean(ref**2))
    # a directional source at the viewpoint (fig. 6 bottom right)
    d = v[:1]  # orthographic camera: one view direction
    e = np.array([[3.0]])
    ref_d = np.asarray(jaxsh.render_reference(n, v, truth.kd, truth.ks, truth.mu, truth.sigma, directional=(d, e),
                                              brdf_model="cook_torrance"))
    pred_d = np.asarray(solvers.predict_brdf_sh(res.rho, np.asarray(jaxsh.directional_light_sh(d, e, lmax)), n, v))
    err_dir = np.sqrt(np.mean((pred_d - ref_d) ** 2)) / np.sqrt(np.mean(ref_d**2))
    neg = -pred_d.min() / ref_d.max()
    print(f"fit_brdf_sh order {lmax}: rank {np.asarray(res.rank)} / {res.n_unknowns}, train rel rms {float(res.rel_rms):.4f}; "
          f"held-out view, same area light: {err_low:.4f}; directional at the viewpoint: {err_dir:.4f}, "
          f"most negative radiance {neg:.3f} of the true peak")
    assert err_low < 0.1, err_low  # measured 0.075
    assert err_dir > 5 * err_low  # measured 0.68
    assert neg > 0.05  # measured 0.13: ringing
    # order 12 (fig. 6, top right): "sharper, but exhibits more pronounced ringing"
    sh12 = np.asarray(cap.lighting.total_sh(12))[:, :1]
    res12 = solvers.fit_brdf_sh(obs, sh12, 12, rcond=1e-2)
    pred12_d = np.asarray(solvers.predict_brdf_sh(res12.rho, np.asarray(jaxsh.directional_light_sh(d, e, 12)), n, v))
    peak, peak6, peak12 = ref_d.max(), pred_d.max(), pred12_d.max()
    neg12 = -pred12_d.min() / peak
    print(f"order 12: rank {np.asarray(res12.rank)} / {res12.n_unknowns}; directional peak {peak12:.4f} (order 6 {peak6:.4f}, "
          f"truth {peak:.4f}); most negative {neg12:.3f} (order 6 {neg:.3f})")
    # sharper: a higher, narrower highlight (measured peak 5.07 against 3.79 at order 6; the truth's is 4.29, so
    # order 12 overshoots it, Gibbs-like); more pronounced ringing: measured -0.186 against -0.130 of the peak
    assert peak12 > 1.15 * peak6
    assert neg12 > 1.2 * neg
