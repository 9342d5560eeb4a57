"""Real-capture shapes (issue 11): lighting per image, identifiability reporting, per-texel results in `predict`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers

from .helpers import Compiles, quadrature_images, write_png16

C2W = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10], [0, 0, 0, 1]], float)  # looks down -z
TRUE = jaxsh.TorranceSparrow(jnp.asarray([0.5, 0.4, 0.3]), jnp.asarray([0.3, 0.35, 0.4]), 1.5, 0.2)


def _sphere(n=40):
    cam = jaxsh.OrthographicCamera(2.2 / n, n, n, C2W)
    return jaxsh.sphere_gbuffer(cam, np.zeros(3), 1.0)


def _lights(k=8, seed=0):
    """`k` unit directions, 20-60 degrees from the view axis +z, spread in azimuth."""
    rng = np.random.default_rng(seed)
    az = np.arange(k) * 2 * np.pi / k + rng.uniform(0, 0.3, k)
    el = np.deg2rad(np.linspace(20, 60, k))
    return np.stack([np.sin(el) * np.cos(az), np.sin(el) * np.sin(az), np.cos(el)], 1)


def _one_light(d, e=(1.0, 1.0, 1.0)):
    return solvers.Lighting(None, jnp.asarray(d[None]), jnp.asarray(np.asarray(e, float)[None]))


def _views(rng, k, radii=None):
    cams = []
    for _ in range(k):
        eye = rng.normal(size=3)
        eye = 6 * eye / np.linalg.norm(eye)
        up = np.array([0, 0, 1.0]) if abs(eye[2]) < 5 else np.array([1.0, 0, 0])
        cams.append(jaxsh.OrthographicCamera(0.08, 26, 26, jaxsh.look_at(eye, np.zeros(3), up)))
    return [jaxsh.sphere_gbuffer(c, np.zeros(3), r) for c, r in zip(cams, radii or (1.0,) * k)]


# --------------------------------------------------------------------------- lighting per image


@pytest.mark.slow  # ~3.5 % of the suite; per-view lighting is also covered by test_per_view_terms_are_each_views_own (make test-all)
def test_per_view_lighting_equals_single_lighting(rng):
    """All views sharing one lighting: the per-view path equals the single-lighting path."""
    gbs = _views(rng, 3)
    slow = rng.normal(size=(25, 3)) * 0.2
    slow[0] += 2.0
    light = solvers.Lighting(jnp.asarray(slow), jnp.asarray(_lights(2)), jnp.asarray([[1.0, 0.8, 0.6], [0.5, 0.5, 0.7]]))
    imgs = [np.asarray(jaxsh.render_practical(g.normal, g.view, TRUE, light, mask=g.mask).total) for g in gbs]
    obs = solvers.observations(gbs, imgs)
    same = [solvers.Lighting(light.slow_sh, light.fast_directions, light.fast_energy) for _ in gbs]
    one, per = solvers.practical_terms_for(obs, light), solvers.practical_terms_for(obs, same)
    for brdf in (TRUE, jaxsh.TorranceSparrow(jnp.asarray([0.2, 0.1, 0.4]), jnp.asarray([0.6, 0.1, 0.2]), None, 0.07)):
        np.testing.assert_allclose(np.asarray(per(brdf)), np.asarray(one(brdf)), rtol=0, atol=1e-12)
    r1 = solvers.fit_brdf(obs, light)
    r2 = solvers.fit_brdf(obs, same)
    assert solvers.status_name(r2.status) == "converged"
    for a, b in ((r1.brdf.kd, r2.brdf.kd), (r1.brdf.ks, r2.brdf.ks), (r1.brdf.mu, r2.brdf.mu), (r1.brdf.sigma, r2.brdf.sigma)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-8)
    p1 = solvers.predict(TRUE, light, gbs[0].normal, gbs[0].view, mask=gbs[0].mask)
    p2 = solvers.predict(TRUE, same, [g.normal for g in gbs], [g.view for g in gbs], mask=[g.mask for g in gbs])
    assert isinstance(p2, list) and len(p2) == 3
    np.testing.assert_allclose(np.asarray(p2[0]), np.asarray(p1), rtol=0, atol=1e-12)


def test_per_view_terms_are_each_views_own(rng):
    """Different lightings per view (slow orders, source counts, channel counts): each view's rows equal
    `jaxsh.practical_terms` of that view alone under its own lighting."""
    gbs = _views(rng, 3)
    lights = [
        solvers.Lighting(jnp.asarray(rng.normal(size=(9, 3))), jnp.asarray(_lights(3, 1)), jnp.asarray(rng.uniform(0.2, 1, (3, 3)))),
        _one_light(_lights(1, 2)[0], (0.7, 0.2, 0.4)),
        solvers.Lighting(jnp.asarray(rng.normal(size=(36,)))),  # one channel, lmax 5, no fast part
    ]
    imgs = [np.ones(g.mask.shape + (3,)) for g in gbs]
    obs = solvers.observations(gbs, imgs)
    terms = solvers.practical_terms_for(obs, lights)
    vi = np.asarray(obs.view_index)
    for brdf in (TRUE, jaxsh.TorranceSparrow(jnp.asarray([0.2, 0.1, 0.4]), jnp.asarray([0.6, 0.1, 0.2]), None, 0.07)):
        got = np.asarray(terms(brdf))
        for k, lit in enumerate(lights):
            sel = vi == k
            want = jaxsh.practical_terms(obs.normals[sel], obs.views[sel], lit)(brdf)
            np.testing.assert_allclose(got[sel], np.broadcast_to(np.asarray(want), got[sel].shape), rtol=0, atol=1e-12)
    # memory: O(pixels), the columns do not grow with the number of views
    assert terms.theta_h.shape == (obs.n_samples, 3 * 3) and terms.bands.shape == (obs.n_samples, 3, 6)
    with pytest.raises(ValueError, match="`lighting` must have one Lighting per view"):
        solvers.fit_brdf(obs, lights[:2])
    with pytest.raises(ValueError, match=r"`lighting\[1\]`"):
        solvers.fit_brdf(obs, [lights[0], "sun", lights[2]])
    with pytest.raises(ValueError, match="`lighting`"):
        solvers.fit_brdf(obs, "sun")


def test_per_view_fast_lights_terms_are_each_views_own_in_one_program(rng):
    """One light (or two) per view and no slow lighting, the photometric-stereo and light-stage case, which
    `practical_terms_for` makes for all pixels at once from each pixel's own view's sources (sharded pixels:
    tests/test_scale.py): each view's rows equal `jaxsh.practical_terms` of that view alone under its own
    lighting (grey and RGB lights, a view with two sources, with and without the shadow visibility), the columns
    are those of the view-by-view path, and views of different sizes cost one program (view by view: one per
    distinct view size)."""

    gbs = _views(rng, 4, radii=(1.0, 0.8, 0.9, 0.7))
    assert len({int(np.sum(np.asarray(g.mask))) for g in gbs}) == 4  # views of different sizes
    ld = _lights(5, 3)
    lights = [_one_light(ld[0], (0.7, 0.2, 0.4)),
              solvers.Lighting(None, jnp.asarray(ld[1][None]), jnp.asarray([[1.3]])),  # grey
              solvers.Lighting(None, jnp.asarray(ld[2:4]), jnp.asarray([[1.0, 0.9, 0.8], [0.3, 0.2, 0.6]])),
              _one_light(ld[4])]
    imgs = [np.ones(g.mask.shape + (3,)) for g in gbs]
    fvis = [rng.uniform(0.0, 1.0, g.mask.shape + (2,)) for g in gbs]
    vi = None
    for obs in (solvers.observations(gbs, imgs), solvers.observations(gbs, imgs, fast_visibility=fvis)):
        with Compiles() as c:
            terms = solvers.practical_terms_for(obs, lights)
        assert c.names == ["jit(_fast_terms_jit)"], c.names
        vi = np.asarray(obs.view_index)
        assert terms.theta_h.shape == terms.fast_weight.shape == (obs.n_samples, 2 * 3)
        np.testing.assert_array_equal(np.asarray(terms.fast_energy), np.tile(np.eye(3), (2, 1)))
        for brdf in (TRUE, jaxsh.TorranceSparrow(jnp.asarray([0.2, 0.1, 0.4]), jnp.asarray([0.6, 0.1, 0.2]), None, 0.07)):
            got = np.asarray(terms(brdf))
            for k, lit in enumerate(lights):
                sel = vi == k
                fv = None if obs.fast_visibility is None else obs.fast_visibility[sel][:, : lit.fast_directions.shape[0]]
                want = jaxsh.practical_terms(obs.normals[sel], obs.views[sel], lit, fast_visibility=fv)(brdf)
                np.testing.assert_allclose(got[sel], np.broadcast_to(np.asarray(want), got[sel].shape), rtol=0, atol=1e-12)
        # a view with one source: its second pair of columns is padding, weight 0 and half angle 0
        one = vi == 0
        assert np.all(np.asarray(terms.fast_weight)[one][:, 3:] == 0) and np.all(np.asarray(terms.theta_h)[one][:, 3:] == 0)
    # inside a caller's `jit`, the lightings traced: the same terms
    traced = jax.jit(lambda lts: solvers.practical_terms_for(obs, lts))(lights)
    for a, b in zip(jax.tree.leaves(traced), jax.tree.leaves(terms)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-15)
    # grey lights only: one channel, no channel columns
    grey = [solvers.Lighting(None, jnp.asarray(d[None]), jnp.asarray([[e]])) for d, e in zip(ld[:4], (1.0, 0.5, 2.0, 1.5))]
    t1 = solvers.practical_terms_for(obs, grey)
    assert t1.theta_h.shape == (obs.n_samples, 1) and t1.fast_energy.shape == (1, 1)
    for k, lit in enumerate(grey):
        sel = vi == k
        want = jaxsh.practical_terms(obs.normals[sel], obs.views[sel], lit, fast_visibility=obs.fast_visibility[sel][:, :1])
        np.testing.assert_allclose(np.asarray(t1(TRUE))[sel], np.asarray(want(TRUE)), rtol=0, atol=1e-12)


def test_photometric_stereo_fit_from_reference_images():
    """One sphere view repeated K=8 times, each image lit by one directional light, images from the
    reference renderer (full Torrance-Sparrow, exact delta sources): fit_brdf with the per-image lighting."""
    g = _sphere(40)
    dirs = _lights(8)
    lights = [_one_light(d) for d in dirs]
    imgs = [np.asarray(jaxsh.render_reference(g.normal, g.view, TRUE, lit)) * np.asarray(g.mask)[..., None] for lit in lights]
    obs = solvers.observations([g] * 8, imgs)
    res = solvers.fit_brdf(obs, lights)
    assert solvers.status_name(res.status) == "converged"
    # the practical model's Fresnel term (at theta_o, R&H eq. 24) differs from the reference's: the
    # tolerances are that model error, not noise
    np.testing.assert_allclose(np.asarray(res.brdf.kd), np.asarray(TRUE.kd), rtol=0.03)
    np.testing.assert_allclose(np.asarray(res.brdf.ks), np.asarray(TRUE.ks), rtol=0.15)
    np.testing.assert_allclose(float(res.brdf.sigma), 0.2, rtol=0.05)
    assert float(res.rel_rms) < 0.05
    # one Lighting holding all 8 sources lights every image with all of them: a much worse fit
    allin = solvers.Lighting(None, jnp.asarray(dirs), jnp.ones((8, 3)))
    assert float(solvers.fit_brdf(obs, allin, refine=False).rel_rms) > 5 * float(res.rel_rms)


def test_grey_lighting_fits_as_its_rgb_copy():
    """A one-channel (grey) `Lighting` lights every channel of RGB data (`practical_terms_for`): `fit_brdf`
    with grey energies `(J, 1)` gives the fit of the same lighting written `(J, 3)`: one light per image,
    homogeneous and per texel, and one lighting of four sources. Before, every grey-lit fit raised a TypeError
    in its standard errors (`(2, 2)` against `(6, 2)` blocks), and the per-texel `kd` fit in its solve's loop
    (carry shapes)."""
    g = _sphere(24)
    dirs = _lights(4)
    energy = np.array([0.8, 1.1, 0.9, 1.2])
    rgb = [_one_light(d, (e, e, e)) for d, e in zip(dirs, energy)]
    grey = [solvers.Lighting(None, jnp.asarray(d[None]), jnp.full((1, 1), e)) for d, e in zip(dirs, energy)]
    imgs = [np.asarray(jaxsh.render_reference(g.normal, g.view, TRUE, lit)) * np.asarray(g.mask)[..., None] for lit in rgb]
    tex = np.zeros(g.mask.shape, np.int32)
    tex[:, g.mask.shape[1] // 2:] = 1
    flat = solvers.observations([g] * 4, imgs)
    obs = solvers.observations([g] * 4, imgs, texel=[tex] * 4, n_texels=2)
    # one lighting (the four sources at once) for one image
    all4 = [solvers.Lighting(None, jnp.asarray(dirs), jnp.asarray(np.repeat(energy[:, None], c, 1))) for c in (3, 1)]
    one = solvers.observations([g], [np.asarray(jaxsh.render_reference(g.normal, g.view, TRUE, all4[0]))
                                     * np.asarray(g.mask)[..., None]])
    for o, (want_l, got_l), kw in ((flat, (rgb, grey), {}), (obs, (rgb, grey), {"textured": "kd"}),
                                   (one, all4, {"refine": False})):
        want, got = solvers.fit_brdf(o, want_l, **kw), solvers.fit_brdf(o, got_l, **kw)
        assert solvers.status_name(got.status) == solvers.status_name(want.status) == "converged"
        shape = (2, 3) if kw.get("textured") else (3,)
        for name in ("kd", "ks"):
            assert np.shape(getattr(got.brdf, name)) == np.shape(getattr(got.std_errors, name)) == shape
        # two programs of other shapes: equal to the fits' stopping tolerances (rtol = atol = 1e-8 in u)
        for a, b in ((got.brdf, want.brdf), (got.std_errors, want.std_errors)):
            for name in ("kd", "ks", "mu", "sigma"):
                np.testing.assert_allclose(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), rtol=1e-6,
                                           err_msg=f"{kw} {name}")
        if o is obs:  # lit one source per image, as rendered (reference images: the practical model's error)
            np.testing.assert_allclose(float(got.brdf.sigma), 0.2, rtol=0.05)


# --------------------------------------------------------------------------- identifiability


def test_mu_at_its_bound_is_reported_not_fought():
    """Data whose Fresnel rise at grazing is steeper than any mu in the search box gives (mu = 1.0002):
    the profile falls monotonically towards mu -> 1. The fit converges with mu at its bound, flagged,
    with an infinite standard error, and the other parameters recovered."""
    g = _sphere(40)
    lights = [_one_light(d) for d in _lights(8)]
    steep = jaxsh.TorranceSparrow(TRUE.kd, TRUE.ks, 1.0002, TRUE.sigma)
    imgs = [np.asarray(jaxsh.render_practical(g.normal, g.view, steep, lit, mask=g.mask).total) for lit in lights]
    res = solvers.fit_brdf(solvers.observations([g] * 8, imgs), lights)
    assert solvers.status_name(res.status) == "converged"
    assert bool(res.stats["at_bound"]["mu"]) and bool(res.stats["undetermined"]["mu"])
    assert not bool(res.stats["at_bound"]["sigma"])
    assert float(res.brdf.mu) == pytest.approx(solvers.MU_BOUNDS[0], rel=1e-6)
    assert np.isinf(float(res.std_errors.mu))
    assert np.all(np.isfinite(np.asarray(res.std_errors.kd))) and np.isfinite(float(res.std_errors.sigma))
    np.testing.assert_allclose(float(res.brdf.sigma), 0.2, rtol=1e-2)
    np.testing.assert_allclose(np.asarray(res.brdf.kd), np.asarray(TRUE.kd), rtol=1e-2)
    # a determined mu (data with mu = 1.5) is not flagged
    imgs_f = [np.asarray(jaxsh.render_practical(g.normal, g.view, TRUE, lit, mask=g.mask).total) for lit in lights]
    ok = solvers.fit_brdf(solvers.observations([g] * 8, imgs_f), lights)
    assert not bool(ok.stats["at_bound"]["mu"]) and not bool(ok.stats["undetermined"]["mu"])
    np.testing.assert_allclose(float(ok.brdf.mu), 1.5, rtol=1e-6)


def test_mu_weakly_determined_is_reported_by_its_standard_error():
    """Without grazing pixels (cos theta_o > 0.9 only) the Fresnel factor is nearly flat in mu: with 1 % noise the
    fit still converges (no `max_steps_reached`), and says how little it knows through a standard error several
    times that of the whole sphere; the truth lies within 3 standard errors of both estimates."""
    g = _sphere(40)
    lights = [_one_light(d) for d in _lights(8)]
    imgs = [np.asarray(jaxsh.render_practical(g.normal, g.view, TRUE, lit, mask=g.mask).total) for lit in lights]
    rng = np.random.default_rng(0)
    mask = np.asarray(g.mask)
    imgs = [im + 0.01 * np.sqrt(np.mean(im[mask] ** 2)) * rng.normal(size=im.shape) for im in imgs]
    centre = mask & (np.asarray(g.normal)[..., 2] > 0.9)
    # weight 0 drops a pixel: both fits have the same sample count, hence one compilation
    weak = solvers.fit_brdf(solvers.observations([g] * 8, imgs, weights=[centre.astype(float)] * 8), lights)
    full = solvers.fit_brdf(solvers.observations([g] * 8, imgs), lights)
    for res in (weak, full):
        assert solvers.status_name(res.status) == "converged"
        assert not bool(res.stats["at_bound"]["mu"])
        assert abs(float(res.brdf.mu) - 1.5) < 3 * float(res.std_errors.mu)
    assert float(weak.std_errors.mu) > 3 * float(full.std_errors.mu)  # measured 0.031 vs 0.0049


# --------------------------------------------------------------------------- per-texel results in predict


def test_per_texel_result_into_predict():
    g = _sphere(32)
    mask = np.asarray(g.mask)
    texel = np.broadcast_to((np.arange(32) // 8)[None, :], (32, 32)).astype(np.int32)  # 4 vertical stripes
    kd_t = np.array([[0.5, 0.4, 0.3], [0.2, 0.6, 0.3], [0.7, 0.1, 0.1], [0.3, 0.3, 0.6]])
    lights = [_one_light(d) for d in _lights(6)]
    imgs = [np.asarray(jaxsh.render_practical(g.normal, g.view, kd_t[texel], TRUE.ks, TRUE.mu, TRUE.sigma,
                                              fast_directions=lit.fast_directions, fast_energy=lit.fast_energy,
                                              mask=g.mask).total) for lit in lights]
    obs = solvers.observations([g] * 6, imgs, texel=[texel] * 6)
    res = solvers.fit_brdf(obs, lights, textured="kd")
    assert res.brdf.kd.shape == (4, 3)
    new = _one_light(np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81]))
    want = np.asarray(jaxsh.render_practical(g.normal, g.view, kd_t[texel], TRUE.ks, TRUE.mu, TRUE.sigma,
                                             fast_directions=new.fast_directions, fast_energy=new.fast_energy,
                                             mask=g.mask).total)
    got = np.asarray(solvers.predict(res.brdf, new, g.normal, g.view, mask=g.mask, texel=texel))
    np.testing.assert_allclose(got[mask], want[mask], rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="texel"):
        solvers.predict(res.brdf, new, g.normal, g.view, mask=g.mask)
    with pytest.raises(ValueError, match=r"`texel` must have shape \(32, 32\)"):
        solvers.predict(res.brdf, new, g.normal, g.view, texel=texel[:4])
    bad = texel.copy()
    bad[16, 16] = 9
    with pytest.raises(ValueError, match=r"`texel` has indices outside \[0, 4\)"):
        solvers.predict(res.brdf, new, g.normal, g.view, texel=bad)


def test_texel_counts_are_samples_of_positive_weight():
    """`texel_count` counts the samples that observe a texel: weight-0 samples (invalid pixels, the padding of
    `pad_observations`) do not, so a padded fit reports the unpadded counts, and a texel seen only by weight-0
    samples is unobserved (count 0, infinite standard error)."""
    g = _sphere(32)
    mask = np.asarray(g.mask)
    texel = np.broadcast_to((np.arange(32) // 8)[None, :], (32, 32)).astype(np.int32)
    kd_t = np.array([[0.5, 0.4, 0.3], [0.2, 0.6, 0.3], [0.7, 0.1, 0.1], [0.3, 0.3, 0.6]])
    lights = [_one_light(d) for d in _lights(6)]  # the shapes of the test above: its compiled fit serves here
    imgs = [np.asarray(jaxsh.render_practical(g.normal, g.view, kd_t[texel], TRUE.ks, TRUE.mu, TRUE.sigma,
                                              fast_directions=lit.fast_directions, fast_energy=lit.fast_energy,
                                              mask=g.mask).total) for lit in lights]
    weight = (texel != 0).astype(float)  # texel 0 has object pixels, all of weight 0
    obs = solvers.observations([g] * 6, imgs, texel=[texel] * 6, weights=[weight] * 6)
    want = np.array([6 * np.count_nonzero(mask & (texel == t) & (weight > 0)) for t in range(4)])
    assert want[0] == 0 and np.all(want[1:] > 0) and np.count_nonzero(mask & (texel == 0)) > 0
    for o in (obs, solvers.pad_observations(obs, bucket=True)):
        res = solvers.fit_brdf(o, lights, textured="kd")
        np.testing.assert_array_equal(np.asarray(res.texel_count), want)
        assert np.isinf(float(np.asarray(res.std_errors.kd)[0, 0]))
        np.testing.assert_allclose(np.asarray(res.brdf.kd)[1:], kd_t[1:], rtol=1e-6)


def test_fit_brdf_sh_per_view_lighting(rng):
    gbs = _views(rng, 2)
    sh = rng.normal(size=(9, 3)) * 0.3
    sh[0] += 2.0
    imgs = [np.asarray(jaxsh.render_practical(g.normal, g.view, TRUE, solvers.Lighting(jnp.asarray(sh)), mask=g.mask).total)
            for g in gbs]
    obs = solvers.observations(gbs, imgs)
    one = solvers.fit_brdf_sh(obs, sh, 2)
    per = solvers.fit_brdf_sh(obs, [solvers.Lighting(jnp.asarray(sh))] * 2, 2)
    np.testing.assert_allclose(np.asarray(per.rho), np.asarray(one.rho), rtol=0, atol=1e-10)
    # different lighting per view: images of one BRDF rendered by quadrature under each view's own SH lighting
    # (`helpers.quadrature_images`, independent of eqs. 9, 10) are fitted exactly, and only with each view's lighting
    sh2 = sh.copy()
    sh2[1:4] *= -1.5
    lights = [solvers.Lighting(jnp.asarray(sh)), solvers.Lighting(jnp.asarray(sh2))]

    def brdf(wi, wo, n):  # degree 2 in each direction: exact at lmax 2 under lmax-2 lighting
        return 0.3 / np.pi + 0.2 * jnp.sum(wi * wo, -1) ** 2

    obs2 = solvers.observations(gbs, quadrature_images(gbs, brdf, [sh, sh2], 2))
    fit = solvers.fit_brdf_sh(obs2, lights, 2)
    assert float(fit.rel_rms) < 1e-10
    assert float(solvers.fit_brdf_sh(obs2, sh, 2).rel_rms) > 1e-2  # one lighting for both views cannot explain them
    with pytest.raises(ValueError, match="lighting_sh"):
        solvers.fit_brdf_sh(obs2, lights[:1], 2)


# --------------------------------------------------------------------------- through the command line


HALF = (0.5, 0.5, 0.5)


def test_cli_photometric_capture_fit_then_render_held_out(tmp_path):
    """A photometric capture on disk (orthographic camera, sphere, 8 lights, one per 16-bit linear PNG, images
    by the reference renderer): `jaxsh fit` -> result.json -> `jaxsh render` of a held-out light."""
    import json

    from solvers.cli import main

    n = 40
    g = _sphere(n)
    mask = np.asarray(g.mask)
    dirs = _lights(9, seed=3)
    held, dirs = dirs[4], np.delete(dirs, 4, axis=0)
    cam = {"model": "orthographic", "scale": 2.2 / n, "width": n, "height": n, "cam_to_world": C2W.tolist()}
    views = []
    for k, d in enumerate(dirs):
        img = np.asarray(jaxsh.render_reference(g.normal, g.view, TRUE, _one_light(d, HALF))) * mask[..., None]
        assert img.max() < 0.95  # no clipping in the 16-bit file
        write_png16(tmp_path / f"img_{k:03d}.png", img)
        views.append({"image": f"img_{k:03d}.png", "camera": cam,
                      "lighting": {"directional": [{"direction": d.tolist(), "radiance": 0.5}]}})
    fit_m = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": 1}}, "encoding": "linear", "views": views,
             "lighting": None, "brdf": None}
    (tmp_path / "capture.json").write_text(json.dumps(fit_m))
    assert main(["fit", str(tmp_path / "capture.json"), "--out", str(tmp_path / "fit")]) == 0
    result = json.loads((tmp_path / "fit" / "result.json").read_text())
    assert result["status"] == "converged"
    assert result["at_bound"] == {"mu": False, "sigma": False}
    np.testing.assert_allclose(result["brdf"]["kd"], np.asarray(TRUE.kd), rtol=0.03)
    render_m = {"geometry": fit_m["geometry"], "views": [{"camera": cam}], "brdf": result["brdf"],
                "lighting": {"directional": [{"direction": held.tolist(), "radiance": 0.5}]}}
    (tmp_path / "held.json").write_text(json.dumps(render_m))
    assert main(["render", str(tmp_path / "held.json"), "--out", str(tmp_path / "render")]) == 0
    got = np.asarray(jaxsh.io.read_image(tmp_path / "render" / "view_000.exr"))[..., :3]
    want = np.asarray(jaxsh.render_reference(g.normal, g.view, TRUE, _one_light(held, HALF)))
    err = np.sqrt(np.mean((got[mask] - want[mask]) ** 2) / np.mean(want[mask] ** 2))
    assert err < 0.03  # the practical model's Fresnel-at-theta_o approximation, plus 16-bit quantization
    # a view lighting that overrides the top-level one renders that view under its own light
    render_m["views"] = [{"camera": cam}, {"camera": cam, "lighting": {"directional": [{"direction": dirs[0].tolist(),
                                                                                          "radiance": 0.5}]}}]
    (tmp_path / "two.json").write_text(json.dumps(render_m))
    assert main(["render", str(tmp_path / "two.json"), "--out", str(tmp_path / "two")]) == 0
    v0 = np.asarray(jaxsh.io.read_image(tmp_path / "two" / "view_000.exr"))
    v1 = np.asarray(jaxsh.io.read_image(tmp_path / "two" / "view_001.exr"))
    np.testing.assert_allclose(v0, np.asarray(jaxsh.io.read_image(tmp_path / "render" / "view_000.exr")), atol=1e-6)
    b = result["brdf"]
    want1 = np.asarray(jaxsh.render_practical(g.normal, g.view, jaxsh.TorranceSparrow(jnp.asarray(b["kd"]), jnp.asarray(b["ks"]),
                                              b["mu"], b["sigma"]), _one_light(dirs[0], HALF), mask=g.mask).total)
    np.testing.assert_allclose(v1[..., :3], want1, atol=1e-5)


def test_observations_float_masks_keep_pixels_above_one_half():
    """A float (soft) mask was cast with astype(bool): 0.1 counted as inside. Float masks now keep the pixels above
    0.5, as `jaxsh.io.read_mask` thresholds files; bool and integer masks keep their nonzero pixels."""
    g = jaxsh.sphere_gbuffer(solvers.view_cameras(1, 16)[0], jnp.zeros(3), jnp.asarray(1.0))
    obj = np.asarray(g.mask)
    img = np.ones((16, 16, 3))
    soft = np.where(np.arange(16)[None, :] < 8, 0.1, 0.9) * np.ones((16, 1))
    kept = obj & (soft > 0.5)
    assert 0 < kept.sum() < obj.sum()
    for m, want in ((soft, kept), (soft > 0.5, kept), ((soft > 0.5).astype(np.uint8), kept), (np.ones((16, 16)), obj)):
        assert solvers.observations([g], [img], masks=[m]).n_samples == int(want.sum())
