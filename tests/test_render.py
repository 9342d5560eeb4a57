"""The practical model (R&H eqs. 21-24) against the reference integrator, and its pieces."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh

from .helpers import random_dirs


def _sphere_pixels(s):
    """Normals of the visible hemisphere of a sphere seen orthographically along -z (view +z)."""
    u = (np.arange(s) + 0.5) / s * 2 - 1
    x, y = np.meshgrid(u, -u)
    m = x**2 + y**2 < 1
    return np.stack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, 1))], -1)[m]


D1 = np.array([0.4, 0.5, 0.77]) / np.linalg.norm([0.4, 0.5, 0.77])
R1 = 0.3
L1 = np.array([3.0, 2.5, 2.0])
D2 = np.array([-0.5, 0.2, 0.84]) / np.linalg.norm([-0.5, 0.2, 0.84])
E2 = np.array([4.0, 4.0, 3.5])
KD = np.array([0.25, 0.2, 0.15])
KS = np.array([0.6, 0.6, 0.6])
V = np.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize("sigma,bound", [(0.05, 0.005), (0.1, 0.01), (0.2, 0.02)])
def test_practical_model_vs_reference(sigma, bound):
    """Sphere under a disk (area) source + a directional source, pixels with theta_o < 60 deg.

    The model's remaining approximation is eq. 20 for the slow specular part (an O(sigma) error in
    A_l, see test_convolution.py), so the bound scales with sigma: 0.1 sigma relative RMS.
    Measured (64x64 sphere): 0.15 %, 0.44 %, 1.15 % for sigma = 0.05, 0.1, 0.2.
    """
    n = _sphere_pixels(40)
    lmax = int(np.ceil(4 / sigma))
    slow = jaxsh.disk_light_sh(D1, R1, L1, lmax)
    p = jaxsh.render_practical(n, V, KD, KS, 1.5, sigma, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None])
    ref = np.asarray(
        jaxsh.render_reference(n, V, KD, KS, 1.5, sigma, disks=(D1[None], np.array([R1]), L1[None]), directional=(D2[None], E2[None]), disk_nodes=(64, 128))
    )
    b = np.asarray(p.total)
    sel = n[:, 2] > 0.5
    rms = np.sqrt(np.mean((b - ref)[sel] ** 2)) / np.sqrt(np.mean(ref[sel] ** 2))
    assert rms < bound
    np.testing.assert_allclose(p.total, p.diffuse + p.specular_slow + p.specular_fast, atol=1e-14)


def test_reference_quadrature_converged():
    n = _sphere_pixels(12)
    args = (n, V, KD, KS, 1.5, 0.1)
    a = np.asarray(jaxsh.render_reference(*args, disks=(D1[None], np.array([R1]), L1[None]), disk_nodes=(48, 96)))
    b = np.asarray(jaxsh.render_reference(*args, disks=(D1[None], np.array([R1]), L1[None]), disk_nodes=(96, 192)))
    assert np.abs(a - b).max() < 1e-4 * np.abs(b).max()


def _scipy_disk_integral(n, v, c, radius, sigma, kd):
    """$\\int_{disk \\cap H(n)} (k_d + \\rho_s)\\cos\\theta_i\\,d\\omega$ for radiance 1, `torrance_sparrow` with
    F = 1 and K_s = 1, by scipy's adaptive quadrature in the pixel's own frame (θ from the normal, so the horizon is
    the end of the θ range; the disk's φ range at each θ in closed form). Shares nothing with `render_reference`."""
    from scipy import integrate

    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t = np.cross(n, a)
    t /= np.linalg.norm(t)
    b = np.cross(n, t)
    rho, phic, cn = np.hypot(c @ t, c @ b), np.arctan2(c @ b, c @ t), c @ n
    co = n @ v

    def integrand(phi, th):
        w = np.sin(th) * (np.cos(phi) * t + np.sin(phi) * b) + np.cos(th) * n
        h = (w + v) / np.linalg.norm(w + v)
        th_h = np.arccos(np.clip(h @ n, -1.0, 1.0))
        spec = np.exp(-(th_h / sigma) ** 2) / (np.pi * sigma**2) / (4.0 * co)  # rho_s cos(theta_i)
        return (kd * np.cos(th) + spec) * np.sin(th)

    def kappa(th):  # the disk at polar angle th: cos(phi - phic) >= kappa
        return (np.cos(radius) - np.cos(th) * cn) / (np.sin(th) * rho)

    def inner(th):
        k = kappa(th)
        if k >= 1.0:
            return 0.0
        d = np.pi if k <= -1.0 else np.arccos(k)
        return integrate.quad(integrand, phic - d, phic + d, args=(th,), epsabs=1e-13, epsrel=1e-11, limit=200)[0]

    grid = np.linspace(1e-9, np.pi / 2, 4001)
    kg = kappa(grid)
    kinks = [grid[i] for lvl in (-1.0, 1.0) for i in np.nonzero(np.diff(np.sign(kg - lvl)))[0]]
    return integrate.quad(inner, 0.0, np.pi / 2, points=kinks or None, epsabs=1e-12, epsrel=1e-10, limit=400)[0]


@pytest.mark.parametrize("cos_o,azimuth,elevation",
                         [(0.3, 0.0, 0.4), (0.3, 0.7, 0.4), (0.6, 0.0, 0.4), (0.5, 0.4, -0.3)])
def test_reference_disk_cut_by_the_horizon(cos_o, azimuth, elevation):
    """A disk that the pixel's horizon cuts, with the specular lobe reaching the horizon inside it (the integrand
    jumps there): the per-pixel nodes, clipped at the horizon, against scipy's adaptive quadrature in the pixel's own
    frame. The last case has the disk's centre below the horizon (only its outer part is visible).

    Measured: at `disk_nodes=(48, 192)` within 1e-10 in every case; at the default (48, 96) within 1.5e-5 (the
    lobe at azimuth 0.7 wants more azimuths: 1.4e-6 at 128, 8e-11 at 192). With nodes shared by every pixel, as
    before, these four cases erred by 1.2e-3, 9.8e-4, 9.7e-6 and 4.3e-5 at (48, 192)."""
    sigma, radius, kd = 0.15, 1.2, 0.2
    n = np.array([0.0, 0.0, 1.0])
    so = np.sqrt(1.0 - cos_o**2)
    v = np.array([-so * np.cos(azimuth), -so * np.sin(azimuth), cos_o])
    c = np.array([np.cos(elevation), 0.0, np.sin(elevation)])
    want = _scipy_disk_integral(n, v, c, radius, sigma, kd)
    disks = (c[None], np.array([radius]), np.ones((1, 1)))
    fine = jaxsh.render_reference(n[None], v[None], kd, 1.0, None, sigma, disks=disks, disk_nodes=(48, 192))
    assert abs(float(fine[0, 0]) / want - 1.0) < 1e-9
    default = jaxsh.render_reference(n[None], v[None], kd, 1.0, None, sigma, disks=disks)
    assert abs(float(default[0, 0]) / want - 1.0) < 3e-5


def test_reference_hemisphere_and_sphere_disks_closed_form():
    """Lambertian (K_d = 1) under a disk of radiance 1 and radius pi/2 (a hemisphere, centre c): the irradiance is
    (pi/2)(1 + n.c) (two hemispheres meeting at an angle); under the whole sphere (radius pi) it is pi. Every such
    pixel's horizon cuts the disk, so these are the clipped per-pixel rules at their largest. The sphere takes 192
    azimuths: where the horizon passes near the centre (|n.c| = 0.14 to 0.19 here) the cut radius swings from ~0 to
    ~pi over a few azimuths, and 96 of them left 1.6e-10 to 2.2e-9 (192: 6e-15)."""
    rng = np.random.default_rng(11)
    n = rng.normal(size=(12, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    v = n + 0.3 * rng.normal(size=(12, 3))  # seen: n.v > 0
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    assert np.all(np.sum(n * v, 1) > 0)
    c = np.array([0.2, -0.5, 0.84]) / np.linalg.norm([0.2, -0.5, 0.84])
    half = jaxsh.render_reference(n, v, 1.0, 0.0, None, 0.2, disks=(c[None], np.array([np.pi / 2]), np.ones((1, 1))))
    np.testing.assert_allclose(np.asarray(half)[:, 0], 0.5 * np.pi * (1.0 + n @ c), rtol=1e-12)
    full = jaxsh.render_reference(n, v, 1.0, 0.0, None, 0.2, disks=(c[None], np.array([np.pi]), np.ones((1, 1))),
                                  disk_nodes=(48, 192))
    np.testing.assert_allclose(np.asarray(full)[:, 0], np.pi, rtol=1e-12)


def test_reference_disk_rules_agree_where_no_horizon_cuts():
    """A chunk of pixels none of whose horizons cuts a disk takes the rule shared by every pixel (one matrix
    product); a chunk with such a pixel takes each pixel's own clipped rule. Where no horizon cuts, the two rules
    are the same nodes: the uncut pixels rendered alone (shared rule) equal them rendered in one chunk with cut
    pixels (own rules), to rounding; and the pixels come back in their order after the sort by cut."""
    c = np.array([0.2, 0.3, 0.93]) / np.linalg.norm([0.2, 0.3, 0.93])
    radius = 0.35
    rng = np.random.default_rng(5)
    n = rng.normal(size=(40, 3))
    n[:, 2] = np.abs(n[:, 2])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cut = np.abs(n @ c) < np.sin(radius)
    assert 5 < cut.sum() < 35
    v = np.array([0.1, -0.2, 0.97]) / np.linalg.norm([0.1, -0.2, 0.97])
    args = (0.3, 0.7, 1.5, 0.25)
    disks = (c[None], np.array([radius]), np.array([[1.0, 2.0]]))
    alone = np.asarray(jaxsh.render_reference(n[~cut], v, *args, disks=disks))
    mixed = np.asarray(jaxsh.render_reference(n, v, *args, disks=disks, chunk=64))
    np.testing.assert_allclose(mixed[~cut], alone, rtol=1e-12, atol=1e-14)
    # chunks of 8 after the sort: the cut pixels' chunks and the others' differ; the image is the same
    again = np.asarray(jaxsh.render_reference(n, v, *args, disks=disks, chunk=8))
    np.testing.assert_allclose(again, mixed, rtol=1e-12, atol=1e-14)
    assert np.all(mixed[n @ v <= 0] == 0) and np.all(mixed[n @ v > 0] > 0)


def test_reference_disk_nodes_gradient_with_respect_to_normals():
    """The per-pixel disk nodes move with the normal; the render's gradient with respect to the normals is finite
    and matches central differences, also for a normal along the disk's centre (no azimuth to the rim: the
    `sqrt`/`atan2` substitutes) and one perpendicular to it (A = 0: the horizon through the centre)."""
    c = np.array([0.0, 0.0, 1.0])  # its tangent frame is x, y exactly: the normal c has B_phi = 0 exactly
    normals = np.array([c, [1.0, 0.0, 0.0], [0.6, -0.3, 0.74], [0.3, 0.9, 0.2]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    v = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
    assert np.all(normals @ v > 0)

    def f(n):
        disks = (c[None], np.array([1.0]), np.ones((1, 1)))
        return jnp.sum(jaxsh.render_reference(n, v, 0.2, 1.0, None, 0.3, disks=disks))

    g = np.asarray(jax.grad(f)(jnp.asarray(normals)))
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0.1
    for i in range(len(normals)):
        for k in range(3):
            e = np.zeros_like(normals)
            e[i, k] = 1e-6
            fd = (float(f(normals + e)) - float(f(normals - e))) / 2e-6
            np.testing.assert_allclose(g[i, k], fd, rtol=1e-6, atol=1e-8)


def test_fast_sources_are_exact(rng):
    """Delta sources: model = reference to rounding (both exact), diffuse and specular."""
    n = random_dirs(rng, (50,))
    n[:, 2] = np.abs(n[:, 2])
    d = random_dirs(rng, (3,))
    e = rng.uniform(0.5, 2.0, size=(3, 3))
    p = jaxsh.render_practical(n, V, KD, KS, 1.4, 0.15, fast_directions=d, fast_energy=e)
    ref = jaxsh.render_reference(n, V, KD, KS, 1.4, 0.15, directional=(d, e))
    np.testing.assert_allclose(p.total, ref, atol=1e-13)
    assert np.all(np.asarray(p.specular_slow) == 0)
    # eq. 23 written out by hand for one pixel / source
    k, j = 7, 1
    h = (d[j] + V) / np.linalg.norm(d[j] + V)
    th = np.arccos(np.clip(h @ n[k], -1, 1))
    f = float(jaxsh.fresnel_normalized(n[k] @ V, 1.4)) if n[k] @ V > 0 else 0.0
    want = KS * f * np.exp(-((th / 0.15) ** 2)) * e[j] / (np.pi * 0.15**2) / (4 * (n[k] @ V)) if (n[k] @ d[j] > 0 and n[k] @ V > 0) else 0 * KS
    pj = jaxsh.render_practical(n[k], V, KD, KS, 1.4, 0.15, fast_directions=d[j][None], fast_energy=e[j][None])
    np.testing.assert_allclose(pj.specular_fast, want, atol=1e-12)


def test_paper_form_of_eq21_uses_nine_terms(rng):
    n = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    d = np.array([[0.0, 0.8, 0.6]])
    e = np.array([[1.0, 1.0, 1.0]])
    p = jaxsh.render_practical(n, V, KD, 0 * KS, None, 0.1, fast_directions=d, fast_energy=e, exact_fast_diffuse=False)
    want = KD * np.asarray(jaxsh.irradiance(jaxsh.directional_light_sh(d, e, 2), n))
    np.testing.assert_allclose(p.diffuse, want, atol=1e-13)
    exact = jaxsh.render_practical(n, V, KD, 0 * KS, None, 0.1, fast_directions=d, fast_energy=e)
    np.testing.assert_allclose(exact.diffuse, KD * np.maximum(n @ d[0], 0)[:, None], atol=1e-14)


def test_disk_light_sh_closed_form(rng):
    """Against projection of the cap's indicator on a fine lat-long grid (an independent quadrature)."""
    d = random_dirs(rng, ())
    r = 0.7
    c = np.asarray(jaxsh.disk_light_sh(d, r, 2.0, 6))
    h, w = 2048, 4096
    dirs = np.asarray(jaxsh.latlong_directions(h, w, dtype=np.float32))
    img = 2.0 * (dirs @ d.astype(np.float32) > np.cos(r)).astype(np.float64)
    proj = np.asarray(jaxsh.project_latlong(img, 6))
    np.testing.assert_allclose(c, proj, atol=2e-3)  # the indicator's edge limits the grid rule to O(1/H)
    assert float(jaxsh.disk_energy(r, 2.0)) == pytest.approx(c[0] * np.sqrt(4 * np.pi))


@pytest.mark.parametrize("r", [0.00465, 0.05, 0.5, 1.2, 2.5])
def test_disk_light_sh_small_caps_to_rounding(r):
    """Zonal coefficients against $2\\pi\\int_0^r Y_{l0}(\\theta)\\sin\\theta\\,d\\theta$ by
    100-node Gauss–Legendre in θ (smooth integrand: exact to rounding) with scipy's Legendre polynomials.

    A sun-sized cap (0.27°) loses 11 digits in $P_{l-1}(\\cos r) - P_{l+1}(\\cos r)$
    (measured 4.5e-12 relative before the derivative form, 2.3e-15 after).
    """
    from scipy import special

    lmax = 12
    got = np.asarray(jaxsh.disk_light_sh(np.array([0.0, 0.0, 1.0]), r, 1.0, lmax))
    x, w = np.polynomial.legendre.leggauss(100)
    t, w = (x + 1) * r / 2, w * r / 2
    for l in range(lmax + 1):
        ref = 2 * np.pi * np.sqrt((2 * l + 1) / (4 * np.pi)) * np.sum(w * special.eval_legendre(l, np.cos(t)) * np.sin(t))
        assert got[l * l + l] == pytest.approx(ref, rel=1e-13, abs=1e-14 * abs(got[0])), l  # abs: near-zero bands
    assert float(jaxsh.disk_energy(r, 1.0)) == pytest.approx(2 * np.pi * np.sum(w * np.sin(t)), rel=1e-14)


def test_slow_specular_tends_to_mirror_lookup(rng):
    """As sigma -> 0 the filtered lighting is the lighting itself at the mirror direction (eq. 22)."""
    lmax = 6
    c = rng.normal(size=(jaxsh.num_coeffs(lmax), 1))
    n = np.array([[0.2, 0.1, 0.97]]) / np.linalg.norm([0.2, 0.1, 0.97])
    p = jaxsh.render_practical(n, V, 0.0, 1.0, None, 1e-6, slow_sh=c)
    r = 2 * (n[0] @ V) * n[0] - V
    np.testing.assert_allclose(p.specular_slow[0, 0], np.asarray(jaxsh.real_sh(r, lmax)) @ c[:, 0], atol=1e-9)


def test_visibility_terms_multiply():
    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]])
    d = np.array([[0.3, 0.0, 0.95]])
    e = np.array([[1.0, 1.0, 1.0]])
    full = jaxsh.render_practical(n, V, KD, KS, 1.5, 0.1, fast_directions=d, fast_energy=e)
    shadowed = jaxsh.render_practical(n, V, KD, KS, 1.5, 0.1, fast_directions=d, fast_energy=e, fast_visibility=np.array([[0.0], [1.0]]))
    np.testing.assert_allclose(shadowed.total[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(shadowed.total[1], full.total[1], atol=1e-15)


def test_textures_batch_and_grad():
    n = _sphere_pixels(8)
    kd_tex = np.linspace(0.1, 0.9, n.shape[0])[:, None] * np.ones(3)
    slow = jaxsh.disk_light_sh(D1, R1, L1, 20)
    p = jaxsh.render_practical(n, V, kd_tex, KS, 1.5, 0.2, slow_sh=slow)
    assert p.total.shape == (n.shape[0], 3)
    g = jax.grad(lambda s: jnp.sum(jaxsh.render_practical(n, V, KD, KS, 1.5, s, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None]).total))(0.2)
    h = 1e-6
    f = lambda s: float(jnp.sum(jaxsh.render_practical(n, V, KD, KS, 1.5, s, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None]).total))
    assert float(g) == pytest.approx((f(0.2 + h) - f(0.2 - h)) / (2 * h), rel=1e-6)
    p32 = jaxsh.render_practical(n.astype(np.float32), V.astype(np.float32), KD.astype(np.float32), KS.astype(np.float32), 1.5, 0.2, slow_sh=np.asarray(slow, np.float32))
    assert p32.total.dtype == jnp.float32


def test_render_errors():
    with pytest.raises(ValueError, match="lighting"):
        jaxsh.render_practical(np.array([0, 0, 1.0]), V, KD, KS, 1.5, 0.1)
    with pytest.raises(ValueError, match="fast_energy"):
        jaxsh.render_practical(np.array([0, 0, 1.0]), V, KD, KS, 1.5, 0.1, fast_directions=np.ones((2, 3)), fast_energy=np.ones((3, 3)))
    with pytest.raises(ValueError, match="normals"):
        jaxsh.render_practical(np.ones((4, 2)), V, KD, KS, 1.5, 0.1, fast_directions=np.ones((1, 3)), fast_energy=np.ones((1, 3)))
    with pytest.raises(ValueError, match="lighting"):
        jaxsh.render_reference(np.array([0, 0, 1.0]), V, KD, KS, 1.5, 0.1)


def test_render_a_gbuffer_with_its_mask():
    """The README example: a sphere G-buffer (misses have zero normals) rendered with its mask."""
    cam = jaxsh.OrthographicCamera(scale=0.05, width=48, height=48, cam_to_world=jaxsh.look_at(eye=[0, 0, 5.0], target=[0, 0, 0]))
    g = jaxsh.sphere_gbuffer(cam, center=[0, 0, 0.0], radius=1.0)
    slow = jaxsh.disk_light_sh(D1, R1, L1, 20)
    b = jaxsh.render_practical(g.normal, g.view, KD, KS, 1.5, 0.2, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None], mask=g.mask)
    assert b.total.shape == (48, 48, 3)
    assert np.all(np.asarray(b.total)[~np.asarray(g.mask)] == 0)
    assert np.all(np.isfinite(np.asarray(b.total))) and float(b.total.max()) > 0
    m = np.asarray(g.mask)
    ref = jaxsh.render_practical(np.asarray(g.normal)[m], np.asarray(g.view)[m], KD, KS, 1.5, 0.2, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None])
    np.testing.assert_allclose(np.asarray(b.total)[m], ref.total, atol=1e-13)
    with pytest.raises(Exception, match="normals"):
        jaxsh.render_practical(g.normal, g.view, KD, KS, 1.5, 0.2, slow_sh=slow).total.block_until_ready()


def _floor_and_wall():
    import trimesh

    box = trimesh.creation.box(extents=[2.0, 2.0, 0.2])
    wall = trimesh.creation.box(extents=[0.2, 2.0, 1.0])
    wall.apply_translation([0.0, 0.0, 0.6])
    return trimesh.util.concatenate([box, wall])


def test_reference_with_mesh_visibility_on_a_convex_object():
    """On a convex mesh the only occlusion is the horizon, which the BRDF already zeroes."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3)
    cam = jaxsh.OrthographicCamera(0.08, 24, 24, jaxsh.look_at(np.array([0, 0, 4.0]), np.zeros(3), np.array([0, 1.0, 0])))
    g = jaxsh.mesh_gbuffer(cam, mesh, smooth=False)
    m = np.asarray(g.mask)
    pts, nrm, vw = (np.asarray(a)[m] for a in (g.position, g.normal, g.view))
    light = dict(disks=(D1[None], np.array([R1]), L1[None]), directional=(D2[None], E2[None]), disk_nodes=(16, 32))
    a = np.asarray(jaxsh.render_reference(nrm, vw, KD, KS, 1.5, 0.2, mesh=mesh, points=pts, **light))
    b = np.asarray(jaxsh.render_reference(nrm, vw, KD, KS, 1.5, 0.2, **light))
    np.testing.assert_allclose(a, b, atol=1e-12)
    with pytest.raises(ValueError, match="mesh"):
        jaxsh.render_reference(nrm, vw, KD, KS, 1.5, 0.2, mesh=mesh, **light)


def test_practical_model_with_shadows_vs_reference_on_concave_mesh():
    """Floor + wall (R&H sec. 6.4): visibility terms bring the model to the ray-traced reference.

    Measured (40x40 view, 36 % of pixels shadowed): 3.8 % relative RMS with the visibility terms
    (9-term transfer vectors, binary shadow of the sun and of the mirror direction), 77 % without.
    """
    mesh = _floor_and_wall()
    cam = jaxsh.OrthographicCamera(0.07, 28, 28, jaxsh.look_at(np.array([0.3, -2.0, 4.0]), np.zeros(3), np.array([0, 0, 1.0])))
    g = jaxsh.mesh_gbuffer(cam, mesh, smooth=False)
    m = np.asarray(g.mask)
    pts, nrm, vw = (np.asarray(a)[m] for a in (g.position, g.normal, g.view))
    d1 = np.array([0.7, 0.2, 0.69]) / np.linalg.norm([0.7, 0.2, 0.69])
    d2 = np.array([-0.6, 0.3, 0.74]) / np.linalg.norm([-0.6, 0.3, 0.74])
    ks = np.array([0.3, 0.3, 0.3])
    ref = np.asarray(jaxsh.render_reference(nrm, vw, KD, ks, 1.5, 0.2, disks=(d1[None], np.array([R1]), L1[None]), directional=(d2[None], E2[None]), disk_nodes=(24, 48), mesh=mesh, points=pts))
    slow = jaxsh.disk_light_sh(d1, R1, L1, 20)
    t = np.asarray(jaxsh.visibility_sh(mesh, pts, nrm, 2, n_dirs=1024))
    fv = np.asarray(jaxsh.directional_visibility(mesh, pts, nrm, d2[None]))
    rv = np.asarray(jaxsh.reflected_visibility(mesh, pts, nrm, vw))
    common = dict(slow_sh=slow, fast_directions=d2[None], fast_energy=E2[None])
    with_vis = np.asarray(jaxsh.render_practical(nrm, vw, KD, ks, 1.5, 0.2, transfer=t, fast_visibility=fv, reflected_visibility=rv, **common).total)
    without = np.asarray(jaxsh.render_practical(nrm, vw, KD, ks, 1.5, 0.2, **common).total)
    rms = lambda x: np.sqrt(np.mean((x - ref) ** 2)) / np.sqrt(np.mean(ref**2))
    assert rms(with_vis) < 0.06
    assert rms(without) > 0.5


def test_split_disk_sources_slow_fast():
    """A sun much smaller than sigma becomes a delta with the disk's energy; a wide source goes to SH."""
    dirs = np.stack([D1, D2])
    radii = np.array([0.3, 0.005])
    rad = np.stack([L1, np.full(3, 1e4)])
    slow, fd, fe = jaxsh.split_disk_sources(dirs, radii, rad, sigma=0.1, lmax=20)
    np.testing.assert_allclose(slow, jaxsh.disk_light_sh(D1, 0.3, L1, 20), atol=1e-14)
    np.testing.assert_allclose(fd, D2[None], atol=1e-15)
    np.testing.assert_allclose(fe[0], 2 * np.pi * (1 - np.cos(0.005)) * 1e4, rtol=1e-12)
    # the delta approximation of the small disk against its exact quadrature in the reference renderer
    n = _sphere_pixels(16)
    exact = np.asarray(jaxsh.render_reference(n, V, KD, KS, 1.5, 0.1, disks=(D2[None], np.array([0.005]), np.full((1, 3), 1e4)), disk_nodes=(8, 16)))
    delta = np.asarray(jaxsh.render_reference(n, V, KD, KS, 1.5, 0.1, directional=(fd, fe)))
    assert np.sqrt(np.mean((exact - delta) ** 2)) / np.sqrt(np.mean(exact**2)) < 2e-3
    with pytest.raises(ValueError, match="angular_radii"):
        jaxsh.split_disk_sources(dirs, np.array([0.3]), rad, 0.1, 4)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("axis", ["pole", "generic"])
def test_normal_gradient_at_theta_h_zero(dtype, axis):
    """Normal, view and a fast source aligned (theta_h = 0: exactly at the pole, to rounding elsewhere)
    and 1e-7 away from it: the gradient of `render_practical` with respect to the normal is finite,
    jacfwd = jacrev, and (float64) equals a central difference; float32 agrees with float64."""
    if axis == "pole":
        u, tilt = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    else:
        u = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
        tilt = np.array([0.93, 0.0, -0.3]) / np.linalg.norm([0.93, 0.0, -0.3])  # orthogonal to u
    slow = np.asarray(jaxsh.disk_light_sh(D1, R1, L1, 8))
    light = jaxsh.Lighting(slow.astype(dtype), u[None].astype(dtype), E2[None].astype(dtype))
    brdf = jaxsh.TorranceSparrow(KD.astype(dtype), KS.astype(dtype), 1.5, 0.2)
    v = u.astype(dtype)

    def f(n):
        return jnp.sum(jaxsh.render_practical(n[None], v, brdf, light).total)

    def f64(n):
        b64 = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.2)
        return jnp.sum(jaxsh.render_practical(n[None], u, b64, jaxsh.Lighting(slow, u[None], E2[None])).total)

    tol = 1e-10 if dtype == np.float64 else 2e-4
    for e in (0.0, 1e-7):
        n0 = (np.cos(e) * u + np.sin(e) * tilt).astype(dtype)
        th = float(jaxsh.half_angle(v, v, n0))
        if e == 0.0:
            assert th == 0.0 if axis == "pole" else th <= 2 * np.finfo(dtype).eps  # |h x n| rounds (FMA)
        g = np.asarray(jax.grad(f)(n0))
        assert g.dtype == dtype and np.all(np.isfinite(g))
        np.testing.assert_allclose(np.asarray(jax.jacfwd(f)(n0)), g, rtol=tol, atol=tol * np.abs(g).max())
        if dtype == np.float64:
            h = 1e-6
            fd = np.array([(float(f(n0 + h * ek)) - float(f(n0 - h * ek))) / (2 * h) for ek in np.eye(3)])
            np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())
        else:
            want = np.asarray(jax.grad(f64)(n0.astype(np.float64)))
            np.testing.assert_allclose(g, want, rtol=2e-4, atol=2e-4 * np.abs(want).max())
    # the factored model has the same gradient
    terms_f = lambda n: jnp.sum(jaxsh.practical_terms(n[None], v[None], light)(brdf))
    np.testing.assert_allclose(np.asarray(jax.grad(terms_f)(v)), np.asarray(jax.grad(f)(v)), rtol=tol, atol=tol)


def test_pixel_buckets_bound_the_padding():
    from jaxsh._render import _MIN_PIXELS, _pixel_bucket

    sizes = np.arange(1, 300_000, 37)
    b = np.array([_pixel_bucket(int(n)) for n in sizes])
    assert np.all(b >= sizes) and np.all(b[sizes <= _MIN_PIXELS] == _MIN_PIXELS)
    assert np.all(b[sizes > _MIN_PIXELS] < 1.25 * sizes[sizes > _MIN_PIXELS])
    for lo in (1024, 65536):  # four buckets an octave above 1,024 pixels (multiples of lo / 4)
        assert sorted({_pixel_bucket(n) for n in range(lo + 1, 2 * lo + 1)}) == [lo + lo // 4 * j for j in range(1, 5)]
    assert _pixel_bucket(5000) == _pixel_bucket(4900) == 5120 and _pixel_bucket(262144) == 262144


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_pixel_counts_in_one_bucket_share_the_compiled_programs(dtype):
    """Flat pixel lists of different lengths (views of one object) reuse the programs of the first render; each
    pixel's value is its own, whatever the other rows (per-pixel textures, visibility and a mask included)."""
    from .helpers import Compiles

    rng = np.random.default_rng(3)
    n = random_dirs(rng, (5000,))
    n[:, 2] = np.abs(n[:, 2]) + 0.1
    n = (n / np.linalg.norm(n, axis=1, keepdims=True)).astype(dtype)
    v = np.broadcast_to(V, n.shape).astype(dtype)
    kd = rng.uniform(0.1, 0.5, (5000, 3)).astype(dtype)  # a texture
    fvis = (rng.uniform(size=(5000, 1)) > 0.3).astype(dtype)
    mask = rng.uniform(size=5000) > 0.1
    slow = (0.1 * rng.normal(size=(25, 3))).astype(dtype)
    slow[0] = 1.0
    lit = jaxsh.Lighting(slow_sh=slow, fast_directions=np.array([[0.3, 0.2, 0.933]], dtype),
                         fast_energy=np.array([[2.0, 1.5, 1.0]], dtype))

    def render(k):
        brdf = jaxsh.TorranceSparrow(kd[:k], KS.astype(dtype), dtype(1.5), dtype(0.2))
        return jaxsh.render_practical(n[:k], v[:k], brdf, lit, fast_visibility=fvis[:k], mask=mask[:k]).total

    full = np.asarray(render(5000))
    with Compiles() as c:
        part = np.asarray(render(4900))
    assert c.names == [], c.names
    assert part.shape == (4900, 3) and part.dtype == dtype
    tol = 1e-13 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(part, full[:4900], rtol=tol, atol=tol)
    assert np.all(part[~mask[:4900]] == 0.0) and np.abs(part).max() > 0.1
    traced = np.asarray(jax.jit(render, static_argnums=0)(4900))  # under the caller's jit: no padding
    np.testing.assert_allclose(traced, part, rtol=10 * tol, atol=10 * tol)


def test_directional_light_sh_against_scipy(rng):
    """R&H sec. 5.2: delta sources have $L_{lm} = \\sum_j L_j Y_{lm}(\\omega_j)$, checked against scipy's harmonics
    (`helpers.scipy_real_sh`, the convention of docs/conventions.md) at unnormalized directions, one and three
    channels; an antipodal or mirrored direction would differ in every odd band."""
    from tests.helpers import scipy_real_sh

    d = rng.normal(size=(4, 3)) * rng.uniform(0.5, 3.0, size=(4, 1))
    e = rng.uniform(0.2, 2.0, size=(4, 3))
    want = scipy_real_sh(d, 6).T @ e
    np.testing.assert_allclose(np.asarray(jaxsh.directional_light_sh(d, e, 6)), want, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(np.asarray(jaxsh.directional_light_sh(d, e[:, 0], 6))[:, 0], want[:, 0], rtol=1e-12,
                               atol=1e-13)
