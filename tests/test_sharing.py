"""solvers.fit_sharing and the reflectance-sharing models (Zickler 2006 eqs. 10-15, secs. 6-8).

References: scipy's RBFInterpolator (kernel "linear", degree 1) for the
saddle-point solve; exactness at the centres; closed-form radiance for the
sample/render pipeline; the paper's protocols on synthetic scenes (reduced
here; the full-size runs are marked slow).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

import jaxsh
import solvers
from solvers import _sharing as S
from solvers import synthetic as Z

from .helpers import Compiles


def _data(rng, n, d, c=None):
    x = rng.uniform(-1, 1, size=(n, d))
    y = np.sin(2 * x[:, 0]) * np.cos(x[:, 1]) + 0.3 * x[:, -1] ** 2
    if c is not None:
        y = np.stack([y * (k + 1) + k for k in range(c)], -1)
    return x, y


@pytest.mark.parametrize("d,c", [(3, None), (3, 3), (5, 2)])
@pytest.mark.parametrize("smoothing", [0.0, 0.05])
def test_interpolation_equals_scipy(rng, d, c, smoothing):
    x, y = _data(rng, 250, d, c)
    s = rng.uniform(0.2, 1.0, size=d)
    fit = solvers.fit_sharing(x, y, 250, scale=s, smoothing=smoothing)
    assert solvers.status_name(fit.status) == "converged"
    xt = rng.uniform(-1.2, 1.2, size=(400, d))
    # scipy's kernel is -r and its smoothing adds to the diagonal: the same system as Psi - rho I (eq. 10)
    ref = RBFInterpolator(x * s, y, kernel="linear", degree=1, smoothing=smoothing)(xt * s)
    out = np.asarray(fit(xt))
    assert out.shape == ref.shape
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
    if smoothing == 0.0:  # interpolates: exact at the centres
        np.testing.assert_allclose(np.asarray(fit(x)), y, atol=1e-10)


def test_float32_fit(rng):
    x, y = _data(rng, 200, 3, 3)
    f64 = solvers.fit_sharing(x, y, 200)
    f32 = solvers.fit_sharing(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32), 200)
    assert f32.model.weights.dtype == jnp.float32
    xt = rng.uniform(-1, 1, size=(300, 3))
    # documented: float32 fitting accurate to ~1e-3 relative on small problems
    np.testing.assert_allclose(np.asarray(f32(jnp.asarray(xt, jnp.float32))), np.asarray(f64(xt)),
                               atol=1e-3 * np.abs(y).max())


def test_greedy_selection(rng):
    x, y = _data(rng, 3000, 3, 2)
    w = rng.uniform(0.2, 1.0, size=3000)
    fit = solvers.fit_sharing(x, y, 200, scale=[1.0, 1.0, 0.5], weights=w, key=jax.random.PRNGKey(1), n_add=30)
    idx = np.asarray(fit.center_index)
    assert solvers.status_name(fit.status) == "converged" and len(idx) == 200 and len(set(idx.tolist())) == 200
    assert int(fit.history_centers[-1]) == 200 and np.all(np.diff(np.asarray(fit.history_centers)) > 0)
    # the final model is the interpolant of its centres (independent: scipy on the selected subset)
    s = np.array([1.0, 1.0, 0.5])
    ref = RBFInterpolator(x[idx] * s, y[idx], kernel="linear", degree=1)(x * s)
    np.testing.assert_allclose(np.asarray(fit(x)), ref, atol=1e-8)
    # recorded residual = weighted relative RMS over all samples
    r = (y - ref) * w[:, None]
    np.testing.assert_allclose(float(fit.rel_rms), np.sqrt((r**2).sum() / ((y * w[:, None]) ** 2).sum()), rtol=1e-6)
    # greedy beats a random subset of the same size
    rnd = rng.choice(3000, 200, replace=False)
    r_rnd = (y - RBFInterpolator(x[rnd] * s, y[rnd], kernel="linear", degree=1)(x * s)) * w[:, None]
    assert float(fit.rel_rms) < 0.7 * np.sqrt((r_rnd**2).sum() / ((y * w[:, None]) ** 2).sum())


def test_greedy_tolerance_and_status(rng):
    x, y = _data(rng, 2000, 3)
    loose = solvers.fit_sharing(x, y, 400, tol=0.05, n_add=20)
    assert solvers.status_name(loose.status) == "converged" and float(loose.rel_rms) <= 0.05 and loose.model.n_centers < 400
    tight = solvers.fit_sharing(x, y, 40, tol=1e-9, n_add=10)
    assert solvers.status_name(tight.status) == "tolerance_not_reached" and tight.model.n_centers == 40


def test_result_contract(rng):
    """SharingFit is a `Solution`: Status, greedy rounds, absolute and relative weighted RMS, stats, throw=."""
    x, y = _data(rng, 800, 3, 2)
    w = rng.uniform(0.2, 1.0, size=800)
    fit = solvers.fit_sharing(x, y, 120, weights=w, n_add=20)
    assert isinstance(fit, solvers.Solution) and fit.estimate is fit.model
    assert int(fit.iterations) == len(fit.history_centers) - 1 > 0
    idx = np.asarray(fit.center_index)
    r = (y - RBFInterpolator(x[idx], y[idx], kernel="linear", degree=1)(x)) * w[:, None]
    np.testing.assert_allclose(float(fit.rms), np.sqrt((r**2).mean()), rtol=1e-6)
    np.testing.assert_allclose(float(fit.rel_rms), np.sqrt((r**2).sum() / ((y * w[:, None]) ** 2).sum()), rtol=1e-6)
    np.testing.assert_allclose(float(fit.rel_rms), float(fit.history_rms[-1]), rtol=1e-12)
    assert int(fit.stats["n_centers"]) == 120 and int(fit.stats["count"]) == 1600
    assert int(fit.status_code) == 0  # deprecated integer form, kept
    interp = solvers.fit_sharing(x[:50], y[:50], 50, throw=True)
    assert interp.converged and float(interp.rms) < 1e-13 and int(interp.iterations) == 0  # measured: rounding
    tight = solvers.fit_sharing(x, y, 40, tol=1e-9, n_add=10)
    assert tight.status == solvers.Status.tolerance_not_reached and int(tight.status_code) == 1
    with pytest.raises(solvers.SolveError, match="tolerance_not_reached"):
        solvers.fit_sharing(x, y, 40, tol=1e-9, n_add=10, throw=True)


def test_status_judges_the_requested_tol(rng):
    """The status reflects the final residual against `tol`, both sides; greedy, smoothing spline and image fits."""
    x, y = _data(rng, 300, 3)
    # smoothing spline with every sample a centre: its residual (independent: scipy) decides the status
    ref = RBFInterpolator(x, y, kernel="linear", degree=1, smoothing=0.5)(x)
    rel = np.sqrt(((y - ref) ** 2).sum() / (y**2).sum())
    assert rel > 1e-3
    above = solvers.fit_sharing(x, y, 300, smoothing=0.5, tol=0.5 * rel)
    below = solvers.fit_sharing(x, y, 300, smoothing=0.5, tol=2.0 * rel)
    np.testing.assert_allclose(float(above.rel_rms), rel, rtol=1e-6)
    assert solvers.status_name(above.status) == "tolerance_not_reached"
    assert solvers.status_name(below.status) == "converged"
    # image fit (eq. 12): 30 centres on Oren-Nayar data; the residual recomputed from the model and the samples
    normal, mask, _ = Z.sphere_geometry(24)
    lights = Z.theta_d_lights(np.array([0.2, 0.5, 0.8, 1.1, 1.3]))
    smp = S.reflectance_samples(Z.render_images(Z.oren_nayar_brdf, normal, mask, lights), normal, Z.VIEW, lights,
                                mask=mask, min_cos=0.1)
    free = S.fit_homogeneous(smp, 30, n_add=5)
    f, c = np.asarray(smp.values), np.asarray(smp.cos_i)[:, None]
    r = (f - np.asarray(free.fit(smp.points))) * c
    rel_img = np.sqrt((r**2).sum() / ((f * c) ** 2).sum())
    np.testing.assert_allclose(float(free.rel_rms), rel_img, rtol=1e-6)
    assert solvers.status_name(free.status) == "converged"  # no tol asked: no quality claim (documented)
    tight = S.fit_homogeneous(smp, 30, n_add=5, tol=0.5 * rel_img)
    assert solvers.status_name(tight.status) == "tolerance_not_reached" and float(tight.rel_rms) > 0.5 * rel_img
    with pytest.raises(solvers.SolveError, match="tolerance_not_reached"):
        S.fit_homogeneous(smp, 30, n_add=5, tol=0.5 * rel_img, throw=True)
    loose = S.fit_homogeneous(smp, 30, n_add=5, tol=1.5 * rel_img)
    assert solvers.status_name(loose.status) == "converged" and float(loose.rel_rms) <= 1.5 * rel_img


def _streak(pred, truth, normal, ok, light, n_rings=10):
    """The along-ring part of the prediction error, relative: $\\sqrt{\\sum_{rings}\\sum (e - \\bar e_{ring})^2 / \\sum t^2}$.

    Rings: pixels binned by $\\theta_h$ (angle of the normal to the half vector, equal-count bins). An
    isotropic BRDF's error that only depends on $\\theta_h$ has none; radial streaks (error varying with the
    azimuth about the highlight) are all of it.
    """
    h = (light + Z.VIEW) / np.linalg.norm(light + Z.VIEW)
    th = np.arccos(np.clip(normal[ok] @ h, -1, 1))
    e = pred[ok] - truth[ok]
    edges = np.quantile(th, np.linspace(0, 1, n_rings + 1))
    b = np.clip(np.searchsorted(edges, th, side="right") - 1, 0, n_rings - 1)
    within = sum(((e[b == k] - e[b == k].mean(0)) ** 2).sum() for k in range(n_rings))
    return within, (truth[ok] ** 2).sum()


def test_greedy_spread_removes_radial_streaks():
    """8 directional lights, Oren-Nayar sphere, held-out lights: spread-out greedy centres remove the streaks."""
    normal, mask, _ = Z.sphere_geometry(64)
    l_in, l_out = Z.cone_lights(8, 0.9), Z.cone_lights(6, 0.8, phase=1.1)
    truth = Z.render_images(Z.oren_nayar_brdf, normal, mask, l_out)
    smp = S.reflectance_samples(Z.render_images(Z.oren_nayar_brdf, normal, mask, l_in), normal, Z.VIEW, l_in,
                                mask=mask, min_cos=0.1)
    vm = Z.valid_masks(normal, mask, l_out, 0.1)
    out = {}
    for sp in (0.0, 1.0):
        m = S.fit_homogeneous(smp, 300, m_w=0.5, spread=sp)
        pred = np.stack([np.asarray(m.render(normal, Z.VIEW, li, mask=mask)) for li in l_out])
        parts = [_streak(pred[j], truth[j], normal, vm[j], l_out[j]) for j in range(len(l_out))]
        out[sp] = (Z.relative_rms(pred, truth, vm), math.sqrt(sum(p[0] for p in parts) / sum(p[1] for p in parts)))
    (err0, streak0), (err1, streak1) = out[0.0], out[1.0]
    print(f"plain top-n_add: error {err0:.4f}, streak {streak0:.4f}; spread 1.0: error {err1:.4f}, streak {streak1:.4f}")
    # The artefact is there with plain top-n_add. Which centres it piles up is decided by near-ties among
    # the worst residuals, so its size moves with rounding: measured 8.3 % / 9.5 % (streak / error), and
    # 4.9 % / 7.3 % when the same program is compiled with XLA's optimizations off
    # (JAX_DISABLE_MOST_OPTIMIZATIONS=1: the same arithmetic up to rounding).
    assert streak0 > 0.04 and err0 > 0.06
    assert streak1 < 0.6 * streak0 and streak1 < 0.03  # measured 2.4 %
    assert err1 < 0.035  # measured 2.7 %


def _render_case(n_px=12):
    normal, mask, xy = Z.sphere_geometry(n_px)
    mask = mask & (np.asarray(xy)[..., 0] < 0.7)  # part of the frame only
    light = np.array([0.4, -0.3, 0.866])
    return normal, mask, xy, light / np.linalg.norm(light)


def _full_render(f, normal, light, mask, xy, irradiance):
    """The render formula evaluated at every pixel, then masked (independent of the gathering)."""
    nn = np.asarray(normal)
    cos_i, cos_o = nn @ light, nn @ np.asarray(Z.VIEW)
    ok = mask & (cos_i > 0) & (cos_o > 0)
    q = np.asarray(jaxsh.sbrdf_points(jnp.broadcast_to(light, nn.shape), jnp.broadcast_to(Z.VIEW, nn.shape), nn, xy))
    return np.where(ok[..., None], f(q) * (cos_i * irradiance)[..., None], 0.0), ok


def test_render_only_masked_pixels(rng):
    """render gathers the rendered pixels: equal to the full evaluation; traced (jit) and empty masks too."""
    normal, mask, xy, light = _render_case()
    smp = S.reflectance_samples(rng.uniform(0.2, 1.0, size=(3, 12, 12, 2)), normal, Z.VIEW,
                                Z.theta_d_lights(np.array([0.3, 0.6, 0.9])), mask=mask, xy=xy)
    m = S.fit_sbrdf(smp, 40)
    assert isinstance(m, solvers.Solution) and m.status == m.fit.status and float(m.rel_rms) == float(m.fit.rel_rms)
    pred = np.asarray(m.render(normal, Z.VIEW, light, irradiance=1.5, mask=mask, xy=xy))
    ref, ok = _full_render(lambda q: np.maximum(np.asarray(m.fit(q.reshape(-1, 5))), 0.0).reshape(q.shape[:-1] + (2,)),
                           normal, light, mask, xy, 1.5)
    assert 0 < ok.sum() < ok.size and np.abs(pred).max() > 0
    # rounding only: the RBF sums are evaluated over other batches (gathered pixels / all pixels), so a pixel
    # where the sum cancels carries the rounding of its terms, which are of the size of the largest values:
    # an H200 gave 3.1e-14 at a value of 0.013 (largest value 8.6), a CPU 1.4e-13 at larger ones
    atol = 1e-14 * np.abs(ref).max()
    np.testing.assert_allclose(pred, ref, rtol=1e-12, atol=atol)
    traced = jax.jit(lambda mm: m.render(normal, Z.VIEW, light, irradiance=1.5, mask=mm, xy=xy))(mask)
    np.testing.assert_allclose(np.asarray(traced), ref, rtol=1e-12, atol=atol)
    empty = np.asarray(m.render(normal, Z.VIEW, light, mask=np.zeros_like(mask), xy=xy))
    assert empty.shape == ref.shape and np.all(empty == 0.0)
    nothing = m.render(normal[:0], Z.VIEW, light, mask=mask[:0], xy=xy[:0])  # a frame of no pixels
    assert nothing.shape == (0,) + ref.shape[1:]


def test_rendered_rows_pad_to_shared_buckets():
    """The gathered rows: sorted pixel indices, then the one-past-the-end sentinel; counts bucketed."""
    ok = np.zeros((100, 100), bool)
    ok[3, 5] = ok[50, 7] = ok[99, 99] = True
    sel = S._rendered_rows(ok)
    assert sel.dtype == np.int32 and sel.shape == (S._MIN_ROWS,)  # few pixels: the floor
    np.testing.assert_array_equal(sel[:3], [305, 5007, 9999])
    assert np.all(sel[3:] == ok.size)
    ok[:45] = True  # 4,501 rendered: the next power of two
    assert S._rendered_rows(ok).shape == (8192,)
    ok[:] = True  # every pixel: no padding beyond the image
    np.testing.assert_array_equal(S._rendered_rows(ok), np.arange(ok.size))
    small = np.zeros((12, 12), bool)  # an image below the floor: padded to its own size
    assert S._rendered_rows(small).shape == (144,) and np.all(S._rendered_rows(small) == 144)
    assert S._rendered_rows(jnp.asarray(ok)) is not None


def test_renders_under_new_lights_and_views_compile_nothing(rng):
    """After one render, renders under other lights and views reuse the compiled programs (each used to compile
    new ones: its count of rendered pixels set the shapes) and still equal the per-pixel formula."""
    normal, mask, xy, _ = _render_case(16)
    smp = S.reflectance_samples(rng.uniform(0.2, 1.0, size=(3, 16, 16, 2)), normal, Z.VIEW,
                                Z.theta_d_lights(np.array([0.3, 0.6, 0.9])), mask=mask, xy=xy)
    m = S.fit_sbrdf(smp, 40)
    p5 = rng.uniform(0, 1, size=(200, 5))
    dich = S.DichromaticReflectance(jnp.asarray(rng.uniform(0.2, 0.8, size=(8, 8, 3))),
                                    solvers.fit_sharing(p5, rng.uniform(0.5, 1, size=(200, 3)), 30, n_add=10),
                                    solvers.fit_sharing(p5, rng.uniform(0, 1, size=200), 30, n_add=10))
    renders = {"sbrdf": lambda li, v: m.render(normal, v, li, irradiance=1.5, mask=mask, xy=xy),
               "dichromatic": lambda li, v: dich.render(normal, v, li, xy, color=(0.9, 0.5, 0.3), mask=mask)}
    lights = Z.cone_lights(5, 1.0, phase=0.4)
    views = [Z.VIEW, np.array([0.3, 0.0, 0.954]) / np.linalg.norm([0.3, 0.0, 0.954])]
    for render in renders.values():
        jax.block_until_ready(render(lights[0], views[0]))
    counts = []
    for li in lights[1:]:
        for v in views:
            for name, render in renders.items():
                with Compiles() as c:
                    got = np.asarray(render(li, v))
                assert c.names == [], (name, c.names)
                nn = np.asarray(normal)
                ok = mask & (nn @ li > 0) & (nn @ v > 0)
                counts.append(int(ok.sum()))
                if name == "sbrdf":
                    q = np.asarray(jaxsh.sbrdf_points(jnp.broadcast_to(li, nn.shape), jnp.broadcast_to(v, nn.shape), nn, xy))
                    want = np.maximum(np.asarray(m.fit(q.reshape(-1, 5))), 0.0).reshape(q.shape[:-1] + (2,))
                    want = np.where(ok[..., None], want * (nn @ li * 1.5)[..., None], 0.0)
                    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
                else:
                    assert np.all(got[~ok] == 0.0) and np.all(got[ok] > 0.0)
    assert len(set(counts)) >= 4  # the lights and views rendered different pixel counts


def test_composite_models_contract_and_render(rng):
    """Eqs. 14, 15 models built by hand: combined contract (worst status, pooled RMS) and gathered render."""
    normal, mask, xy, light = _render_case()
    p5 = rng.uniform(0, 1, size=(300, 5))
    dfit = solvers.fit_sharing(p5, rng.uniform(0.5, 1, size=(300, 3)), 60, n_add=10)
    gfit = solvers.fit_sharing(p5, rng.uniform(0, 1, size=300), 30, tol=1e-12, n_add=10)
    assert solvers.status_name(gfit.status) == "tolerance_not_reached"
    albedo = jnp.asarray(rng.uniform(0.2, 0.8, size=(12, 12, 3)))
    m = S.DichromaticReflectance(albedo, dfit, gfit)
    assert solvers.status_name(m.status) == "tolerance_not_reached"
    assert int(m.iterations) == int(dfit.iterations) + int(gfit.iterations)
    pooled = np.sqrt((float(dfit.rms) ** 2 * 900 + float(gfit.rms) ** 2 * 300) / 1200)
    np.testing.assert_allclose(float(m.rms), pooled, rtol=1e-12)
    color = np.array([0.9, 0.5, 0.3])
    pred = np.asarray(m.render(normal, Z.VIEW, light, xy, color=color, irradiance=2.0, mask=mask))
    h = 12
    a = np.asarray(albedo)[np.clip(np.floor(np.asarray(xy)[..., 1] * h).astype(int), 0, h - 1),
                           np.clip(np.floor(np.asarray(xy)[..., 0] * h).astype(int), 0, h - 1)]

    def dich(q):
        d = np.maximum(np.asarray(dfit(q.reshape(-1, 5))), 0.0).reshape(q.shape[:-1] + (3,))
        g = np.maximum(np.asarray(gfit(q.reshape(-1, 5))), 0.0).reshape(q.shape[:-1])
        return color * (a * d + g[..., None])

    ref, _ = _full_render(dich, normal, light, mask, xy, 2.0)
    np.testing.assert_allclose(pred, ref, rtol=1e-12, atol=1e-14)
    one = S.OneImageReflectance(albedo, solvers.fit_sharing(p5[:, :4], rng.uniform(0, 1, size=300), 50, n_add=10))
    assert one.status == one.specular.status and float(one.rms) == float(one.specular.rms)
    pred1 = np.asarray(one.render(normal, Z.VIEW, light, xy, color=color, mask=mask))

    def spec(q):
        g = np.maximum(np.asarray(one.specular(q[..., :4].reshape(-1, 4))), 0.0).reshape(q.shape[:-1])
        return color * (a + g[..., None])

    ref1, _ = _full_render(spec, normal, light, mask, xy, 1.0)
    np.testing.assert_allclose(pred1, ref1, rtol=1e-12, atol=1e-14)
    with pytest.raises(solvers.SolveError):
        solvers._results.finish(m, True)


def test_no_private_jaxsh_imports():
    """The seam: solvers' sharing code uses public jaxsh names only."""
    import ast
    import inspect

    tree = ast.parse(inspect.getsource(S))
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            assert not node.module.startswith("jaxsh._"), node.module
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "jaxsh":
            assert not node.attr.startswith("_"), node.attr


def test_bad_input(rng):
    # duplicate, affinely degenerate (constant w, coplanar) and too few points are degenerate DATA: a status,
    # not an error (tests/test_degenerate.py)
    x, y = _data(rng, 50, 3)
    bad = y.copy()
    bad[4] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        solvers.fit_sharing(x, bad, 50)
    badx = x.copy()
    badx[1, 0] = np.inf
    with pytest.raises(ValueError, match="non-finite"):
        solvers.fit_sharing(badx, y, 50)
    with pytest.raises(ValueError, match="n_centers"):
        solvers.fit_sharing(x, y, 51)
    with pytest.raises(ValueError, match="n_centers"):
        solvers.fit_sharing(x, y, 3)
    with pytest.raises(ValueError, match="scale"):
        solvers.fit_sharing(x, y, 50, scale=[1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="scale"):
        solvers.fit_sharing(x, y, 50, scale=[1.0, 1.0])
    with pytest.raises(ValueError, match="values"):
        solvers.fit_sharing(x, y[:-1], 50)
    with pytest.raises(ValueError, match="images"):
        S.reflectance_samples(np.full((1, 4, 4), np.nan), np.zeros((4, 4, 3)) + [0, 0, 1.0], Z.VIEW, [[0, 0, 1.0]])


def test_samples_and_render_closed_form():
    """f = a + b w is reproduced exactly (degree-1 polynomial); radiance in closed form from angles."""
    normal, mask, _ = Z.sphere_geometry(24)
    lights = Z.theta_d_lights(np.array([0.2, 0.5, 0.8, 1.1]))

    def brdf(wi, wo, n):
        td = 0.5 * jnp.arccos(jnp.clip(jnp.sum(wi * wo, -1), -1.0, 1.0))
        return jnp.repeat((0.3 + 0.2 * (2 * td / math.pi))[..., None], 2, -1)

    imgs = Z.render_images(brdf, normal, mask, lights, irradiance=2.0)
    smp = S.reflectance_samples(imgs, normal, Z.VIEW, lights, irradiance=2.0, mask=mask)
    # the samples' reflectance equals the BRDF (shading and irradiance removed)
    td = 0.5 * np.arccos(np.clip((np.asarray(smp.wi) * np.asarray(smp.wo)).sum(-1), -1, 1))
    np.testing.assert_allclose(np.asarray(smp.values)[:, 0], 0.3 + 0.4 * td / math.pi, rtol=1e-12)
    m = S.fit_homogeneous(smp, 60)
    novel = np.array([0.3, -0.4, 0.866])
    novel = novel / np.linalg.norm(novel)
    pred = np.asarray(m.render(normal, Z.VIEW, novel, irradiance=1.5, mask=mask))
    ci = np.maximum(normal @ novel, 0.0) * mask
    tdn = 0.5 * np.arccos(novel[2])
    truth = (0.3 + 0.4 * tdn / math.pi) * 1.5 * ci
    np.testing.assert_allclose(pred[..., 0], truth, atol=1e-9)


def test_models_errors():
    normal, mask, xy = Z.sphere_geometry(16)
    smp = S.reflectance_samples(np.ones((2, 16, 16, 1)), normal, Z.VIEW, Z.theta_d_lights(np.array([0.3, 0.6])),
                                mask=mask, xy=xy)
    with pytest.raises(ValueError, match=r"\(u, v, w\)"):
        S.fit_homogeneous(smp, 50)
    m = S.fit_sbrdf(smp, 50)
    with pytest.raises(ValueError, match="xy"):
        m.brdf(normal, normal, normal)


def test_ward_baseline_recovers_its_parameters_and_reuses_its_program(rng):
    """The Ward baseline (figs. 7-9) fitted to noise-free Ward data recovers (rho_d, rho_s, alpha) per channel; a
    second fit of the same size (other data) runs the compiled program again without compiling. The data come from
    Ward's isotropic formula written out here in NumPy (Ward 1992), not from `jaxsh.ward_isotropic`, which the fit
    uses: a wrong factor in the library's formula fails this test."""

    def ward(wi, wo, rho_d, rho_s, alpha):  # n = +z
        h = wi + wo
        tan2 = (h[:, 0] ** 2 + h[:, 1] ** 2) / h[:, 2] ** 2  # tan^2 of the half vector's angle to the normal
        return rho_d / np.pi + rho_s * np.exp(-tan2 / alpha**2) / (4 * np.pi * alpha**2 * np.sqrt(wi[:, 2] * wo[:, 2]))

    def data(params, n=600):
        wi = rng.normal(size=(n, 3))
        wo = rng.normal(size=(n, 3))
        wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]) + 0.2, np.abs(wo[:, 2]) + 0.2
        wi /= np.linalg.norm(wi, axis=1, keepdims=True)
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        nrm = np.broadcast_to([0.0, 0.0, 1.0], (n, 3))
        f = np.stack([ward(wi, wo, *p) for p in params], -1)
        return wi, wo, nrm, f, wi[:, 2]

    truth1 = [(0.2, 0.3, 0.15), (0.05, 0.6, 0.3)]
    fit1 = Z.fit_ward(data(truth1))
    np.testing.assert_allclose(np.exp(np.asarray(fit1.theta)), truth1, rtol=1e-6)
    truth2 = [(0.4, 0.1, 0.08), (0.3, 0.25, 0.4)]
    d2 = data(truth2)
    with Compiles() as c:
        fit2 = Z.fit_ward(d2)
        theta2 = np.exp(np.asarray(fit2.theta))
    assert c.names == [], c.names
    np.testing.assert_allclose(theta2, truth2, rtol=1e-6)


# --------------------------------------------------------------------------- paper protocols (reduced)


@pytest.mark.slow  # notebook 06 sec. 1 runs this protocol (24 px) in CI and asserts the same comparisons (make test-all)
def test_homogeneous_protocol_reduced():
    """Sec. 6.1 at 40x40, 300 centres: RBF beats a fitted Ward model (both BRDFs) and Lafortune (metal)."""
    metal = Z.homogeneous_protocol(Z.metallic_brdf, n_px=40, centers=(100, 300), lafortune_lobes=(2,))
    v = metal["valid"]
    assert v["rbf300"] < v["rbf100"]
    assert v["rbf300"] < 0.8 * v["ward"] and v["rbf300"] < 0.9 * v["lafortune2"]
    assert v["rbf300"] < 0.35
    on = Z.homogeneous_protocol(Z.oren_nayar_brdf, n_px=40, centers=(300,), lafortune_lobes=())
    assert on["valid"]["rbf300"] < 0.5 * on["valid"]["ward"] and on["valid"]["rbf300"] < 0.07


@pytest.mark.slow  # notebook 06 sec. 2 runs this protocol (24 px) in CI and asserts the same comparison (make test-all)
def test_hemisphere_sharing_reduced():
    """Sec. 7.1 / fig. 11 at 40x40: sharing from 5 images beats per-pixel interpolation of 5 images."""
    r = Z.hemisphere_protocol(n_px=40, centers=(300,), n_out=12, no_sharing=(5,), sharing_centers=300)
    v = r["valid"]
    assert v["sharing5_rbf300"] < 0.5 * v["nosharing5"]
    assert v["sharing10_rbf300"] < 0.05


def test_one_image_reduced():
    """Sec. 8.4: eq. 15 from one image predicts a novel light within 20 % (the specular part helps)."""
    r = Z.one_image_protocol(n_px=40, n_centers=300)
    assert solvers.status_name(r["status"]) == "converged"
    assert r["valid"] < 0.2 and r["valid"] < r["diffuse_only_valid"]


def test_dichromatic_reduced():
    """Eq. 14 with the median albedo map: textured hemisphere, 6 images, held-out lights."""
    normal, mask, xy = Z.sphere_geometry(32)
    lights = Z.cone_lights(6, 0.9)
    novel = Z.cone_lights(4, 0.8, phase=1.1)
    dif = lambda wi, wo, n, q: Z.dichromatic_components(wi, wo, n, q)[0]  # noqa: E731
    spec = lambda wi, wo, n, q: jnp.repeat(Z.dichromatic_components(wi, wo, n, q)[1][..., None], 3, -1)  # noqa: E731
    s = np.tile(np.ones(3) / math.sqrt(3.0), (6, 1))
    d_in = Z.render_images(dif, normal, mask, lights, xy=xy) / math.sqrt(3.0)
    s_in = Z.render_images(spec, normal, mask, lights, xy=xy) / math.sqrt(3.0)
    m = S.fit_dichromatic(d_in, s_in, s, normal, Z.VIEW, lights, xy, 300, 300, mask=mask, min_cos=0.1)
    # the median albedo map recovers the texture up to the (smooth) d_k normalization
    a_true = np.asarray(Z.albedo_texture(jnp.asarray(xy)))[mask]
    a = np.asarray(m.albedo)[mask]
    ratio = a / a_true
    assert np.std(ratio) / np.mean(ratio) < 0.2
    truth = Z.render_images(dif, normal, mask, novel, xy=xy) + Z.render_images(spec, normal, mask, novel, xy=xy)
    pred = np.stack([np.asarray(m.render(normal, Z.VIEW, li, xy, color=np.ones(3), mask=mask)) for li in novel])
    vm = Z.valid_masks(normal, mask, novel, 0.1)
    assert Z.relative_rms(pred, truth, vm) < 0.1


# --------------------------------------------------------------------------- full-size protocols (slow)


@pytest.mark.slow
@pytest.mark.parametrize("which", ["metal", "oren_nayar"])
def test_homogeneous_protocol_full(which):
    brdf = Z.metallic_brdf if which == "metal" else Z.oren_nayar_brdf
    r = Z.homogeneous_protocol(brdf, n_px=100, centers=(250, 500, 1000), lafortune_lobes=(1, 3, 6))
    print(which, r["valid"], r["all"])
    v = r["valid"]
    assert v["rbf1000"] < v["ward"]
    # fig. 9: the RBF beats every fitted Lafortune model on both BRDFs. On Oren-Nayar it did not with the plain
    # top-n_add greedy rule (4.9 % vs 4.3 %); with spread-out picks (fit_sharing `spread`, docs/sharing.md) the
    # 1,000-centre RBF measured 1.65 % vs Lafortune 4.3 % at n_px = 64 (Ward 14.8 %).
    assert v["rbf1000"] < min(v[f"lafortune{k}"] for k in (1, 3, 6))


@pytest.mark.slow
def test_hemisphere_protocol_full():
    r = Z.hemisphere_protocol(n_px=100, centers=(500, 1000, 2000), no_sharing=(5, 50, 150), sharing_centers=2000)
    print(r["valid"], r["all"])
    v = r["valid"]
    assert v["sharing5_rbf2000"] < v["nosharing5"]


def test_blocked_argmax_equals_argmax(rng):
    """The greedy loop's two-level argmax picks `jnp.argmax`'s index: first maximum, ties, -inf, NaN, tails."""
    f = jax.jit(S._argmax)
    for n in (5, 2047, 2048, 4096, 5000, 10**5 + 17):
        x = rng.normal(size=n)
        cases = [x, np.full(n, -np.inf), np.zeros(n)]
        t = x.copy()
        t[[n // 3, n - 1]] = 10.0  # a tie between the head and the tail: the first wins
        cases.append(t)
        t = x.copy()
        t[-1] = 10.0  # the largest in the tail only
        cases.append(t)
        t = x.copy()
        t[[n // 2, n - 2]] = np.nan  # the first NaN, wherever it lies
        cases.append(t)
        t = x.copy()
        t[n - 1] = np.nan  # a NaN in the tail only
        cases.append(t)
        t = x.copy()
        t[[1, n // 2]] = [-np.inf, np.inf]  # both infinities (a NaN sum) and no NaN
        cases.append(t)
        for v in cases:
            assert int(f(jnp.asarray(v))) == int(np.argmax(v)), n


def test_host_draws_are_reproducible():
    """The host draw of the initial subset depends on the key only: equal keys, equal draws; raw and typed keys."""
    from solvers._host_random import host_rng

    a = host_rng(jax.random.PRNGKey(3)).permutation(1000)
    b = host_rng(jax.random.key(3)).permutation(1000)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(host_rng(None).permutation(50), host_rng(jax.random.PRNGKey(0)).permutation(50))
    assert not np.array_equal(a, host_rng(jax.random.PRNGKey(4)).permutation(1000))
