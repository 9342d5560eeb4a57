"""`render_practical`'s slow specular term by table (method "table") against the per-pixel SH sum.

The bound under test (docs/conventions.md, "The slow specular term by table"): bicubic (4-point
Lagrange) interpolation of the filtered lighting on an H x 2H lat-long grid, continued across the
poles, errs by at most

    (27/512) (pi/H)^4 sum_l l^4 exp(-(sigma l)^2) a_l,    a_l = sqrt((2l+1)/(4 pi)) ||L_l||_2,

per channel, and `render_practical` picks H so that this is at most 1e-6 sum_l a_l for any lighting.
The exact values here are `real_sh` sums in float64 (`real_sh` is checked against scipy in
test_sh.py; one case below against scipy directly).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
from jaxsh._practical import _slow_table, _table_lookup, _table_rows

from .helpers import random_dirs, scipy_real_sh

V = np.array([0.0, 0.0, 1.0])
D1 = np.array([0.4, 0.5, 0.77]) / np.linalg.norm([0.4, 0.5, 0.77])
R1 = 0.3
L1 = np.array([3.0, 2.5, 2.0])
D2 = np.array([-0.5, 0.2, 0.84]) / np.linalg.norm([-0.5, 0.2, 0.84])
E2 = np.array([4.0, 4.0, 3.5])
KD = np.array([0.25, 0.2, 0.15])
KS = np.array([0.6, 0.6, 0.6])


def _degrees(lmax):
    return np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1)


def _band_sup(c, lmax):
    """a_l = sqrt((2l+1)/4pi) ||c_l||_2 per band and channel, (lmax+1, C): a bound on max |band l|."""
    c = np.asarray(c, np.float64).reshape(len(_degrees(lmax)), -1)
    return np.stack([np.sqrt((2 * l + 1) / (4 * np.pi)) * np.linalg.norm(c[l * l : (l + 1) ** 2], axis=0) for l in range(lmax + 1)])


def _bound(c, lmax, sigma, rows):
    """The interpolation error bound (per channel) for a table of `rows` rows."""
    l = np.arange(lmax + 1.0)
    w = l**4 * np.exp(-((sigma * l) ** 2))
    return 27.0 / 512.0 * (np.pi / rows) ** 4 * (w[:, None] * _band_sup(c, lmax)).sum(0)


def _filtered_exact(c, lmax, sigma, r):
    c = np.asarray(c, np.float64)
    return np.asarray(jaxsh.real_sh(np.asarray(r, np.float64), lmax)) @ (c * np.exp(-((sigma * _degrees(lmax)) ** 2))[:, None])


def _hard_directions(rng, rows):
    """Random directions plus the poles, the first/last grid rows (inside the padding), the phi seam."""
    h = np.pi / rows
    th = np.array([0.0, 1e-12, 0.3 * h, 0.5 * h, 0.9 * h, 1.7 * h, np.pi - 0.2 * h, np.pi - h, np.pi, 0.5 * np.pi, 1.0, 2.0])
    ph = np.array([0.0, 1e-13, 2 * np.pi - 1e-13, np.pi, 0.25 * h, 2 * np.pi - 0.25 * h, 1.234])
    t, p = np.meshgrid(th, ph, indexing="ij")
    grid = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    extra = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, -1e-300, 0.0], [1e-9, 0.0, 1.0]])
    d = np.concatenate([grid, extra, random_dirs(rng, (400,))])
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _high_band_lighting(rng, lmax, c=2):
    """Random lighting with most of its energy in the top bands (where interpolation is hardest)."""
    l = _degrees(lmax)
    return rng.normal(size=(len(l), c)) * ((l + 1.0) / (lmax + 1.0))[:, None] ** 2


@pytest.mark.parametrize("lmax,sigma,rows", [(8, 0.01, 16), (8, 0.01, 24), (12, 0.05, 32), (20, 0.02, 48), (40, 0.1, 64)])
def test_table_interpolation_within_the_bound(rng, lmax, sigma, rows):
    """Small grids, so that the error is large enough to test the bound and not the rounding."""
    c = _high_band_lighting(rng, lmax)
    r = _hard_directions(rng, rows)
    table = _slow_table(jnp.asarray(c), jnp.asarray(sigma), rows)
    got = np.asarray(_table_lookup(table, rows, jnp.asarray(r)))
    want = _filtered_exact(c, lmax, sigma, r)
    err = np.abs(got - want).max(0)
    bound = _bound(c, lmax, sigma, rows)
    assert np.all(err <= bound), (err, bound)
    assert np.all(err > 1e-4 * bound)  # the grid is coarse enough that the bound is what is tested


def test_table_grid_is_exact_at_its_nodes(rng):
    """At the grid's own directions the table is the synthesized lighting (the weights are 0, 1, 0, 0)."""
    lmax, rows = 10, 24
    c = rng.normal(size=(len(_degrees(lmax)), 3))
    d = np.asarray(jaxsh.latlong_directions(rows, 2 * rows)).reshape(-1, 3)
    got = np.asarray(_table_lookup(_slow_table(jnp.asarray(c), jnp.asarray(0.07), rows), rows, jnp.asarray(d)))
    want = scipy_real_sh(d, lmax) @ (c * np.exp(-((0.07 * _degrees(lmax)) ** 2))[:, None])
    np.testing.assert_allclose(got, want, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("lmax,sigma", [(16, 0.2), (40, 0.2), (40, 0.1), (30, 0.05), (6, 1e-3)])
def test_grid_choice_meets_the_documented_tolerance(lmax, sigma):
    """The chosen grid makes the bound <= 1e-6 sum_l a_l for the worst lighting (all in one band)."""
    rows = _table_rows(lmax, sigma)
    assert rows is not None and rows <= 1024
    for l in range(lmax + 1):  # all of the lighting in band l, a_l = 1
        c = np.zeros(((lmax + 1) ** 2, 1))
        c[l * l] = np.sqrt(4 * np.pi / (2 * l + 1))
        assert _bound(c, lmax, sigma, rows)[0] <= 1e-6 * 1.0
    smaller = [h for h in (16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024) if h < rows]
    if smaller:  # and it is the smallest grid of the ladder that does
        worst = max(_bound(np.eye((lmax + 1) ** 2)[:, [l * l]] * np.sqrt(4 * np.pi / (2 * l + 1)), lmax, sigma, smaller[-1])[0] for l in range(lmax + 1))
        assert worst > 1e-6
    assert _table_rows(lmax, None) is None or _table_rows(lmax, None) >= rows  # a traced sigma: from lmax alone
    assert _table_rows(60, 1e-3) is None  # beyond the ladder


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("lmax,sigma", [(16, 0.2), (40, 0.1), (24, 0.06)])
def test_render_table_vs_exact_within_the_documented_tolerance(rng, dtype, lmax, sigma):
    """`render_practical(method="table")` (F = 1, Ks = 1: the specular term is L_slow(R)) against the
    float64 per-pixel sum, at directions including the poles and the seam: within 1e-6 sum_l a_l in
    float64; float32 adds its rounding, bounded by that of the exact float32 path plus 25/16 times the
    float32 rounding of the tabulated values (their magnitude, sum_l e^{-(sigma l)^2} a_l, times 8 eps)."""
    c = rng.normal(size=((lmax + 1) ** 2, 3)) / (1.0 + _degrees(lmax))[:, None]
    r = _hard_directions(rng, 64)
    args = (r.astype(dtype), r.astype(dtype), np.zeros(3, dtype), np.ones(3, dtype), None, sigma)
    got = jaxsh.render_practical(*args, slow_sh=c.astype(dtype), method="table")
    assert got.specular_slow.dtype == dtype
    want = _filtered_exact(c, lmax, sigma, r)
    err = np.abs(np.asarray(got.specular_slow, np.float64) - want).max(0)
    s0 = _band_sup(c, lmax).sum(0)
    bound = _bound(c, lmax, sigma, _table_rows(lmax, sigma))
    if dtype == np.float64:
        assert np.all(err <= 1e-6 * s0)
        assert np.all(err <= bound + 1e-14 * s0)  # the bound, plus float64 rounding
    else:
        exact32 = jaxsh.render_practical(*args, slow_sh=c.astype(dtype), method="exact").specular_slow
        err32 = np.abs(np.asarray(exact32, np.float64) - want).max(0)
        mag = (np.exp(-((sigma * np.arange(lmax + 1)) ** 2))[:, None] * _band_sup(c, lmax)).sum(0)
        eps = np.finfo(np.float32).eps
        assert np.all(err <= bound + err32 + 25 / 16 * 8 * eps * mag), (err, err32, mag)


def _sphere_pixels(s):
    u = (np.arange(s) + 0.5) / s * 2 - 1
    x, y = np.meshgrid(u, -u)
    m = x**2 + y**2 < 1
    return np.stack([x, y, np.sqrt(np.clip(1 - x**2 - y**2, 0, 1))], -1)[m]


@pytest.mark.parametrize("sigma,bound", [(0.05, 0.005), (0.1, 0.01), (0.2, 0.02)])
def test_table_vs_reference_as_the_exact_path(sigma, bound):
    """The accuracy against the reference integrator (test_render.py's setup and bounds) is that of
    the exact path: both meet the bound and their RMS errors differ by < 1e-6 relative."""
    n = _sphere_pixels(40)
    lmax = int(np.ceil(4 / sigma))
    slow = jaxsh.disk_light_sh(D1, R1, L1, lmax)
    ref = np.asarray(
        jaxsh.render_reference(n, V, KD, KS, 1.5, sigma, disks=(D1[None], np.array([R1]), L1[None]), directional=(D2[None], E2[None]), disk_nodes=(64, 128))
    )
    sel = n[:, 2] > 0.5
    rms = {}
    for m in ("table", "exact"):
        p = jaxsh.render_practical(n, V, KD, KS, 1.5, sigma, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None], method=m)
        b = np.asarray(p.total)
        rms[m] = np.sqrt(np.mean((b - ref)[sel] ** 2)) / np.sqrt(np.mean(ref[sel] ** 2))
        np.testing.assert_allclose(p.total, p.diffuse + p.specular_slow + p.specular_fast, atol=1e-14)
        if m == "table":
            bt = b
    assert rms["table"] < bound and rms["exact"] < bound
    assert abs(rms["table"] - rms["exact"]) < 1e-6 * rms["exact"]
    f = np.asarray(jaxsh.fresnel_normalized(n @ V, 1.5))[:, None]
    assert np.all(np.abs(bt - b) <= 1e-6 * _band_sup(slow, lmax).sum(0) * KS * f)


def test_auto_picks_the_table_for_large_images_only(rng):
    """`method="auto"`: the exact sum for few pixels, the table (same numbers) for many."""
    lmax = 16
    slow = np.asarray(jaxsh.disk_light_sh(D1, R1, L1, lmax))
    few = _sphere_pixels(16)
    assert few.shape[0] < 4096
    a = jaxsh.render_practical(few, V, KD, KS, 1.5, 0.2, slow_sh=slow).total
    np.testing.assert_array_equal(a, jaxsh.render_practical(few, V, KD, KS, 1.5, 0.2, slow_sh=slow, method="exact").total)
    many = _sphere_pixels(96)
    assert many.shape[0] * (lmax + 1) ** 2 >= 8 * 2 * _table_rows(lmax, 0.2) ** 2 and many.shape[0] >= 4096
    b = jaxsh.render_practical(many, V, KD, KS, 1.5, 0.2, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None])
    t = jaxsh.render_practical(many, V, KD, KS, 1.5, 0.2, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None], method="table")
    e = jaxsh.render_practical(many, V, KD, KS, 1.5, 0.2, slow_sh=slow, fast_directions=D2[None], fast_energy=E2[None], method="exact")
    np.testing.assert_array_equal(b.total, t.total)
    assert float(jnp.abs(b.total - e.total).max()) > 0  # a different route ...
    s0 = _band_sup(slow, lmax).sum(0)
    f = np.asarray(jaxsh.fresnel_normalized(many @ V, 1.5))[:, None]
    assert np.all(np.abs(np.asarray(b.specular_slow - e.specular_slow)) <= 1e-6 * s0 * KS * f)  # ... within the tolerance
    np.testing.assert_allclose(b.diffuse, e.diffuse, rtol=1e-14)  # the diffuse and fast terms do not use the table
    np.testing.assert_allclose(b.specular_fast, e.specular_fast, rtol=1e-14)


def test_table_with_mask_and_reflected_visibility():
    cam = jaxsh.OrthographicCamera(scale=0.03, width=80, height=80, cam_to_world=jaxsh.look_at(eye=[0, 0, 5.0], target=[0, 0, 0]))
    g = jaxsh.sphere_gbuffer(cam, center=[0, 0, 0.0], radius=1.0)
    slow = jaxsh.disk_light_sh(D1, R1, L1, 20)
    rv = np.linspace(0.0, 1.0, 80 * 80).reshape(80, 80)
    kw = dict(slow_sh=slow, mask=g.mask, reflected_visibility=rv)
    t = jaxsh.render_practical(g.normal, g.view, KD, KS, 1.5, 0.2, method="table", **kw)
    e = jaxsh.render_practical(g.normal, g.view, KD, KS, 1.5, 0.2, method="exact", **kw)
    m = np.asarray(g.mask)
    assert np.all(np.asarray(t.total)[~m] == 0)
    s0 = _band_sup(slow, 20).sum(0)
    f = np.asarray(jaxsh.fresnel_normalized(np.sum(np.asarray(g.normal) * np.asarray(g.view), -1), 1.5))[..., None]
    assert np.all(np.abs(np.asarray(t.specular_slow - e.specular_slow)) <= 1e-6 * s0 * KS * f)
    np.testing.assert_array_equal(np.asarray(t.specular_slow)[m & (rv == 0)], 0.0)


def test_table_gradients(rng):
    """jax.grad through the table path w.r.t. kd, ks, mu, sigma (a traced sigma: the grid then comes from
    lmax alone), the lighting and the normals: central differences of the same path, and the exact path's
    gradient within the table's tolerance."""
    lmax = 8
    n = _sphere_pixels(10)
    slow = np.asarray(jaxsh.disk_light_sh(D1, R1, L1, lmax)) + 0.05 * rng.normal(size=((lmax + 1) ** 2, 3))

    def f(kd, ks, mu, sigma, sl, nn, method="table"):
        p = jaxsh.render_practical(nn, V, kd, ks, mu, sigma, slow_sh=sl, fast_directions=D2[None], fast_energy=E2[None], method=method)
        return jnp.sum(p.total * jnp.asarray([[1.0, 0.5, 0.25]]))

    x0 = (jnp.asarray(KD), jnp.asarray(KS), jnp.asarray(1.5), jnp.asarray(0.15), jnp.asarray(slow), jnp.asarray(n))
    g = jax.grad(f, argnums=tuple(range(6)))(*x0)
    fj = jax.jit(f)  # sigma traced, as under grad: the same grid
    ge = jax.grad(lambda *a: f(*a, method="exact"), argnums=tuple(range(6)))(*x0)
    hstep = 1e-6
    for k, (gk, gek) in enumerate(zip(g, ge)):
        gk, gek = np.asarray(gk), np.asarray(gek)
        assert np.all(np.isfinite(gk))
        flat = np.asarray(x0[k], np.float64).reshape(-1)
        idx = rng.choice(flat.size, size=min(flat.size, 4), replace=False)
        for i in idx:
            e = np.zeros_like(flat)
            e[i] = hstep
            xp = list(x0)
            xm = list(x0)
            xp[k] = jnp.asarray((flat + e).reshape(np.shape(x0[k])))
            xm[k] = jnp.asarray((flat - e).reshape(np.shape(x0[k])))
            fd = (float(fj(*xp)) - float(fj(*xm))) / (2 * hstep)
            assert gk.reshape(-1)[i] == pytest.approx(fd, rel=1e-5, abs=1e-7 * np.abs(gk).max())
        if k < 5:  # kd, ks, mu, sigma, lighting: the exact path's gradient, to the table's tolerance
            np.testing.assert_allclose(gk, gek, rtol=1e-5, atol=1e-5 * np.abs(gek).max())


def test_table_gradient_is_finite_at_the_pole():
    """R = +z exactly (normal = view = +z), the table's pole: the value within the tolerance, the gradient finite."""
    slow = np.asarray(jaxsh.disk_light_sh(D1, R1, L1, 10))
    nz = np.array([[0.0, 0.0, 1.0]])

    def f(nn, method):
        return jnp.sum(jaxsh.render_practical(nn, V, KD, KS, 1.5, 0.2, slow_sh=slow, method=method).specular_slow)

    s0 = _band_sup(slow, 10).sum(0)
    assert abs(float(f(nz, "table")) - float(f(nz, "exact"))) <= 1e-6 * float(np.sum(s0 * KS))
    g = np.asarray(jax.grad(lambda x: f(x, "table"))(jnp.asarray(nz)))
    assert np.all(np.isfinite(g))


def test_method_errors():
    n = np.array([[0.0, 0.0, 1.0]])
    slow = np.zeros((49, 3))
    with pytest.raises(ValueError, match="method"):
        jaxsh.render_practical(n, V, KD, KS, 1.5, 0.1, slow_sh=slow, method="bilinear")
    with pytest.raises(ValueError, match="method='exact'"):
        jaxsh.render_practical(n, V, KD, KS, 1.5, 1e-3, slow_sh=np.zeros((61**2, 3)), method="table")
    with pytest.raises(ValueError, match="traced sigma"):
        jax.grad(lambda s: jnp.sum(jaxsh.render_practical(n, V, KD, KS, 1.5, s, slow_sh=np.zeros((41**2, 3)), method="table").total))(0.2)
    # no slow lighting: nothing to tabulate, every method gives the same
    a = jaxsh.render_practical(n, V, KD, KS, 1.5, 0.1, fast_directions=D2[None], fast_energy=E2[None], method="table")
    b = jaxsh.render_practical(n, V, KD, KS, 1.5, 0.1, fast_directions=D2[None], fast_energy=E2[None], method="exact")
    np.testing.assert_array_equal(a.total, b.total)
