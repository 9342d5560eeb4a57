"""Bad input and degenerate data (issue 12): a named error, or a status — never a silent NaN or a traceback.

Organised by category: non-finite values, out-of-range values, shape / channel
mismatches (each asserting a `ValueError` whose message names the argument),
then degenerate data for every solver (all-black images, all-zero lighting,
one pixel: a `Status` and a `rel_rms` that is not NaN, no exception).
Property-based with hypothesis at small sizes (the "ci" profile of
conftest keeps it fast; "thorough" runs more examples).
"""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jaxsh
import solvers
from solvers import Status

KD = np.array([0.5, 0.4, 0.3])
KS = np.array([0.3, 0.3, 0.3])
GOOD_TS = dict(kd=KD, ks=KS, mu=1.5, sigma=0.2)
NONFINITE = st.sampled_from([np.nan, np.inf, -np.inf])


def _unit(rng, n):
    x = rng.normal(size=(n, 3))
    x[:, 2] = np.abs(x[:, 2]) + 0.5
    return x / np.linalg.norm(x, axis=1, keepdims=True)


GEOM_RNG = np.random.default_rng(7)
NORMALS = _unit(GEOM_RNG, 6)
VIEWS = np.tile([0.0, 0.0, 1.0], (6, 1))
SLOW = np.zeros((9, 3))
SLOW[0] = 1.0
LIGHT = jaxsh.Lighting(SLOW, np.array([[0.0, 0.6, 0.8]]), np.array([[2.0, 2.0, 2.0]]))


def _raises_named(fn, *names):
    """`fn()` raises a ValueError whose message names every argument in `names` (never a raw broadcasting error)."""
    with pytest.raises(ValueError) as info:
        fn()
    msg = str(info.value)
    for name in names:
        assert re.search(rf"`[^`]*(?<![A-Za-z_]){re.escape(name)}(?![A-Za-z_])[^`]*`", msg), (name, msg)
    assert "Incompatible types for broadcasting" not in msg
    return msg


# --------------------------------------------------------------------------- non-finite values


@given(field=st.sampled_from(["kd", "ks", "mu", "sigma"]), bad=NONFINITE)
def test_torrance_sparrow_rejects_nonfinite(field, bad):
    kw = dict(GOOD_TS)
    kw[field] = np.array([0.5, bad, 0.3]) if field in ("kd", "ks") else bad
    _raises_named(lambda: jaxsh.TorranceSparrow(**kw), field)
    # the keyword form of the renderers builds the same model: the same error
    _raises_named(lambda: jaxsh.render_practical(NORMALS, VIEWS, slow_sh=SLOW, **kw), field)


@given(field=st.sampled_from(["slow_sh", "fast_directions", "fast_energy", "disk_directions", "disk_radius",
                              "disk_radiance"]), bad=NONFINITE, row=st.integers(0, 1))
def test_lighting_rejects_nonfinite(field, bad, row):
    kw = dict(slow_sh=SLOW.copy(), fast_directions=np.array([[0.0, 0.6, 0.8], [0.6, 0.0, 0.8]]),
              fast_energy=np.ones((2, 3)), disk_directions=np.array([[0.0, 0.0, 1.0], [0.0, 0.8, 0.6]]),
              disk_radius=np.array([0.1, 0.2]), disk_radiance=np.ones((2, 3)))
    a = np.array(kw[field], dtype=float)
    a[row] = bad
    kw[field] = a
    _raises_named(lambda: jaxsh.Lighting(**kw), field)


@given(which=st.sampled_from(["normals", "views"]), pixel=st.integers(0, 5), bad=NONFINITE,
       renderer=st.sampled_from(["practical", "reference"]))
def test_render_rejects_nonfinite_geometry(which, pixel, bad, renderer):
    geo = {"normals": NORMALS.copy(), "views": VIEWS.copy()}
    geo[which][pixel] = bad
    brdf = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.2)
    if renderer == "practical":
        _raises_named(lambda: jaxsh.render_practical(geo["normals"], geo["views"], brdf, LIGHT), which)
    else:
        fast = jaxsh.Lighting(None, LIGHT.fast_directions, LIGHT.fast_energy)
        _raises_named(lambda: jaxsh.render_reference(geo["normals"], geo["views"], brdf, fast), which)


@given(pixel=st.integers(0, 5), which=st.sampled_from(["normals", "views"]))
def test_render_practical_nonfinite_geometry_inside_and_outside_the_mask(pixel, which):
    geo = {"normals": NORMALS.copy(), "views": VIEWS.copy()}
    geo[which][pixel] = np.nan
    brdf = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.2)
    mask = np.ones(6, bool)
    _raises_named(lambda: jaxsh.render_practical(geo["normals"], geo["views"], brdf, LIGHT, mask=mask), which)
    mask[pixel] = False  # outside the mask the pixel is not read: a finite image, 0 there
    out = np.asarray(jaxsh.render_practical(geo["normals"], geo["views"], brdf, LIGHT, mask=mask).total)
    assert np.all(np.isfinite(out)) and np.all(out[pixel] == 0)
    full = np.asarray(jaxsh.render_practical(NORMALS, VIEWS, brdf, LIGHT).total)
    np.testing.assert_allclose(out[mask], full[mask], rtol=1e-12)


def test_render_reference_rejects_nonfinite_envmap():
    env = np.ones((8, 16, 3))
    env[3, 4, 1] = np.nan
    _raises_named(lambda: jaxsh.render_reference(NORMALS, VIEWS, **GOOD_TS, envmap=env), "envmap")


def _capture_gbuffers(n_views=2, size=8):
    cams = solvers.view_cameras(n_views, size)
    return [jaxsh.sphere_gbuffer(c, jnp.zeros(3), jnp.asarray(1.0)) for c in cams]


@pytest.fixture(scope="module")
def gbuffers():
    return _capture_gbuffers()


@given(bad=NONFINITE)
def test_observations_reject_nonfinite_images_and_bad_weights(gbuffers, bad):
    imgs = [np.ones(np.asarray(g.mask).shape + (3,)) for g in gbuffers]
    m = np.asarray(gbuffers[1].mask)
    i, j = np.argwhere(m)[0]
    imgs[1][i, j, 2] = bad
    _raises_named(lambda: solvers.observations(gbuffers, imgs), "images[1]")
    ok = [np.ones(np.asarray(g.mask).shape + (3,)) for g in gbuffers]
    w = [np.ones(np.asarray(g.mask).shape) for g in gbuffers]
    w[0][tuple(np.argwhere(np.asarray(gbuffers[0].mask))[0])] = bad if not np.isinf(bad) or bad < 0 else -1.0
    _raises_named(lambda: solvers.observations(gbuffers, ok, weights=w), "weights[0]")


def _hemisphere(size=8):
    y, x = np.mgrid[-1 : 1 : size * 1j, -1 : 1 : size * 1j] * 0.9
    r2 = x * x + y * y
    mask = r2 < 0.8
    z = np.sqrt(np.clip(1 - r2, 0, None))
    normal = np.stack([x, y, z], -1) + np.random.default_rng(size).uniform(-0.02, 0.02, (size, size, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)  # jittered: no two samples share (u, v, w)
    normal[~mask] = 0.0  # a G-buffer's misses: zero normals, outside the mask
    return normal, mask


LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])


@given(bad=NONFINITE, row=st.integers(0, 2))
def test_reflectance_samples_reject_nonfinite_and_zero_lights(bad, row):
    normal, mask = _hemisphere()
    imgs = np.ones((3,) + mask.shape + (3,))
    lights = LIGHTS.copy()
    lights[row, 1] = bad
    _raises_named(lambda: solvers.reflectance_samples(imgs, normal, [0.0, 0.0, 1.0], lights, mask=mask), "lights")
    lights = LIGHTS.copy()
    lights[row] = 0.0
    _raises_named(lambda: solvers.reflectance_samples(imgs, normal, [0.0, 0.0, 1.0], lights, mask=mask), "lights")


def test_reflectance_samples_reject_zero_normals_inside_the_mask():
    normal, mask = _hemisphere()
    imgs = np.ones((3,) + mask.shape + (3,))
    solvers.reflectance_samples(imgs, normal, [0.0, 0.0, 1.0], LIGHTS, mask=mask)  # zeros outside: fine
    bad = mask.copy()
    bad[0, 0] = True
    _raises_named(lambda: solvers.reflectance_samples(imgs, normal, [0.0, 0.0, 1.0], LIGHTS, mask=bad), "normal")


# --------------------------------------------------------------------------- out-of-range values


@given(sigma=st.floats(-5.0, 0.0))
def test_torrance_sparrow_rejects_sigma_not_positive(sigma):
    _raises_named(lambda: jaxsh.TorranceSparrow(KD, KS, 1.5, sigma), "sigma")
    # sigma = -0.2 used to equal sigma = 0.2: now an error in the BRDF function too
    _raises_named(lambda: jaxsh.torrance_sparrow(NORMALS, VIEWS, NORMALS, 0.5, 0.5, 1.5, sigma), "sigma")


@given(mu=st.floats(-3.0, 1.0, exclude_max=True))
def test_torrance_sparrow_rejects_mu_below_one(mu):
    _raises_named(lambda: jaxsh.TorranceSparrow(KD, KS, mu, 0.2), "mu")
    _raises_named(lambda: jaxsh.render_practical(NORMALS, VIEWS, KD, KS, mu, 0.2, slow_sh=SLOW), "mu")


@given(field=st.sampled_from(["kd", "ks"]), value=st.floats(-10.0, -1e-12))
def test_torrance_sparrow_rejects_negative_albedo(field, value):
    kw = dict(GOOD_TS)
    kw[field] = np.array([0.2, value, 0.2])
    _raises_named(lambda: jaxsh.TorranceSparrow(**kw), field)


@given(field=st.sampled_from(["fast_energy", "disk_radiance"]), value=st.floats(-10.0, -1e-12))
def test_lighting_rejects_negative_energy(field, value):
    kw = dict(fast_directions=[[0.0, 0.0, 1.0]], fast_energy=[[1.0]], disk_directions=[[0.0, 0.6, 0.8]],
              disk_radius=[0.1], disk_radiance=[[1.0]])
    kw[field] = [[value]]
    _raises_named(lambda: jaxsh.Lighting(**kw), field)


@given(radius=st.one_of(st.floats(-3.0, 0.0), st.floats(np.pi, 10.0, exclude_min=True)))
def test_lighting_rejects_disk_radius_out_of_range(radius):
    _raises_named(lambda: jaxsh.Lighting(None, None, None, [[0.0, 0.0, 1.0]], [radius], [[1.0]]), "disk_radius")


def test_lighting_rejects_zero_directions():
    _raises_named(lambda: jaxsh.Lighting(None, [[0.0, 0.0, 0.0]], [[1.0]]), "fast_directions")


def test_unchecked_constructors_keep_the_shape_checks():
    se = jaxsh.TorranceSparrow.unchecked(np.full(3, np.inf), np.full(3, np.nan), np.inf, 0.0)
    assert np.isinf(float(se.mu)) and float(se.sigma) == 0.0
    with pytest.raises(ValueError, match="sigma"):
        jaxsh.TorranceSparrow.unchecked(KD, KS, 1.5, np.ones(2))
    lt = jaxsh.Lighting.unchecked(None, [[0.0, 0.0, 1.0]], [[-1.0]])
    assert float(lt.fast_energy[0, 0]) == -1.0
    # and the checks are back afterwards
    _raises_named(lambda: jaxsh.Lighting(None, [[0.0, 0.0, 1.0]], [[-1.0]]), "fast_energy")


BRDF_BAD = [
    # (function, good arguments after (wi, wo, n), index of the parameter, its name, bad values)
    (jaxsh.torrance_sparrow, [0.5, 0.5, 1.5, 0.2], 3, "sigma", st.floats(-2.0, 0.0)),
    (jaxsh.torrance_sparrow, [0.5, 0.5, 1.5, 0.2], 2, "mu", st.floats(-2.0, 1.0, exclude_max=True)),
    (jaxsh.cook_torrance, [0.5, 0.5, 0.3, 1.5], 2, "m", st.floats(-2.0, 0.0)),
    (jaxsh.cook_torrance, [0.5, 0.5, 0.3, 1.5], 3, "mu", st.floats(-2.0, 1.0, exclude_max=True)),
    (jaxsh.ward_isotropic, [0.5, 0.5, 0.2], 2, "alpha", st.floats(-2.0, 0.0)),
    (jaxsh.oren_nayar, [0.8, 0.3], 1, "sigma", st.floats(-2.0, -1e-9)),
    (jaxsh.phong, [10.0], 0, "s", st.floats(-5.0, -1.0)),
    (jaxsh.phong_transfer, [10.0], 0, "s", st.floats(-5.0, -1.0)),
]


_IDS = [f"{b[0].__name__}-{b[3]}" for b in BRDF_BAD]
_WI, _WO, _N = NORMALS[:2], VIEWS[:2], np.tile([0.0, 0.0, 1.0], (2, 1))


@pytest.mark.parametrize("fn, args, k, name, values", BRDF_BAD, ids=_IDS)
@given(data=st.data())
def test_brdf_functions_reject_invalid_parameters(fn, args, k, name, values, data):
    bad = list(args)
    bad[k] = data.draw(values)
    _raises_named(lambda: fn(_WI, _WO, _N, *bad), name)


@pytest.mark.parametrize("fn, args, k, name, values", BRDF_BAD, ids=_IDS)
def test_brdf_functions_check_traced_parameters(fn, args, k, name, values):
    """Under jit the invalid parameter is an `equinox.error_if` naming it, never a finite number."""
    f = eqx.filter_jit(lambda p: fn(_WI, _WO, _N, *(args[:k] + [p] + args[k + 1 :])))
    assert np.all(np.isfinite(np.asarray(f(jnp.asarray(float(args[k]))))))
    bad = -1.5 if name == "s" else (0.5 if name == "mu" else -0.2)
    with pytest.raises(eqx.EquinoxRuntimeError, match=name):
        jax.block_until_ready(f(jnp.asarray(bad)))


@pytest.mark.parametrize("fn", [jaxsh.fresnel_dielectric, jaxsh.fresnel_normalized])
@given(mu=st.floats(-3.0, 0.0))
def test_fresnel_rejects_non_positive_index(fn, mu):
    _raises_named(lambda: fn(np.array([0.3, 0.9]), mu), "mu")


def test_brdf_functions_propagate_nan():
    wi, wo, n = NORMALS[:2], VIEWS[:2], np.tile([0.0, 0.0, 1.0], (2, 1))
    out = np.asarray(jaxsh.torrance_sparrow(wi, wo, n, 0.5, 0.5, 1.5, np.nan))
    assert np.all(np.isnan(out))
    # mu < 1 is valid for the Fresnel term itself (total internal reflection), documented
    assert np.all(np.asarray(jaxsh.fresnel_dielectric(np.array([0.1]), 0.7)) == 1.0)


def test_render_practical_traced_sigma_is_checked():
    def f(s):
        return jaxsh.render_practical(NORMALS, VIEWS, jaxsh.TorranceSparrow(KD, KS, 1.5, s), LIGHT).total

    g = eqx.filter_jit(f)
    assert np.all(np.isfinite(np.asarray(g(jnp.asarray(0.2)))))
    with pytest.raises(eqx.EquinoxRuntimeError, match="sigma"):
        jax.block_until_ready(g(jnp.asarray(-0.2)))


# --------------------------------------------------------------------------- shape and channel mismatches


@given(c_brdf=st.integers(2, 4), c_light=st.integers(2, 4), form=st.sampled_from(["model", "keywords"]))
def test_render_practical_channel_mismatch_names_both(c_brdf, c_light, form):
    if c_brdf == c_light:
        c_light = c_brdf + 1
    kd, ks = np.full(c_brdf, 0.4), np.full(c_brdf, 0.3)
    slow = np.zeros((9, c_light))
    slow[0] = 1.0
    if form == "model":
        _raises_named(lambda: jaxsh.render_practical(NORMALS, VIEWS, jaxsh.TorranceSparrow(kd, ks, 1.5, 0.2),
                                                     jaxsh.Lighting(slow)), "kd", "lighting.slow_sh")
    else:
        _raises_named(lambda: jaxsh.render_practical(NORMALS, VIEWS, kd, ks, 1.5, 0.2, slow_sh=slow), "kd", "slow_sh")


@given(c_env=st.integers(2, 5))
def test_render_reference_channel_mismatch_names_both(c_env):
    c_env = c_env if c_env != 3 else 4
    _raises_named(lambda: jaxsh.render_reference(NORMALS, VIEWS, **GOOD_TS, envmap=np.ones((8, 16, c_env))),
                  "kd", "envmap")
    _raises_named(lambda: jaxsh.render_reference(NORMALS, VIEWS, **GOOD_TS, directional=([[0.0, 0.0, 1.0]],
                                                                                          [np.ones(c_env)])),
                  "kd", "fast_energy")


@given(k=st.integers(1, 12))
def test_render_practical_transfer_shape(k):
    if k == 9:
        k = 10
    brdf = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.2)
    transfer = np.ones((6, k))
    if k > 9:  # the trailing axis is fine, the batch is not
        transfer = np.ones((5, 9))
    _raises_named(lambda: jaxsh.render_practical(NORMALS, VIEWS, brdf, LIGHT, transfer=transfer), "transfer")


@given(j=st.integers(0, 4))
def test_render_practical_fast_visibility_shape(j):
    if j == 1:  # LIGHT has one fast source
        j = 2
    brdf = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.2)
    msg = _raises_named(lambda: jaxsh.render_practical(NORMALS, VIEWS, brdf, LIGHT, fast_visibility=np.ones((6, j))),
                        "fast_visibility")
    assert "fast_directions" in msg


def test_render_practical_mask_and_texture_shapes():
    brdf = jaxsh.TorranceSparrow(KD, KS, 1.5, 0.2)
    _raises_named(lambda: jaxsh.render_practical(NORMALS, VIEWS, brdf, LIGHT, mask=np.ones(5, bool)), "mask")
    tex = jaxsh.TorranceSparrow(np.full((5, 3), 0.4), KS, 1.5, 0.2)
    _raises_named(lambda: jaxsh.render_practical(NORMALS, VIEWS, tex, LIGHT), "kd")
    _raises_named(lambda: jaxsh.render_reference(NORMALS, VIEWS, tex, jaxsh.Lighting(None, [[0, 0, 1.0]], [[1.0]])),
                  "kd")


def test_reflectance_samples_normalise_light_directions():
    """A light direction is a direction: norm 2 gives the same samples (values and count) as norm 1."""
    normal, mask = _hemisphere()
    rng = np.random.default_rng(3)
    imgs = rng.uniform(0.2, 1.0, size=(3,) + mask.shape + (3,))
    s1 = solvers.reflectance_samples(imgs, normal, [0.0, 0.0, 1.0], LIGHTS, mask=mask)
    s2 = solvers.reflectance_samples(imgs, normal, [0.0, 0.0, 1.0], 2.0 * LIGHTS, mask=mask)
    assert s1.values.shape == s2.values.shape
    np.testing.assert_allclose(np.asarray(s2.values), np.asarray(s1.values), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(s2.points), np.asarray(s1.points), rtol=1e-12, atol=1e-14)
    # independently: f = I / (E cos theta_i) with the unit light
    li, p = np.asarray(s1.image), np.asarray(s1.pixel)
    nn = normal.reshape(-1, 3)[p]
    nn = nn / np.linalg.norm(nn, axis=1, keepdims=True)
    cos = np.sum(nn * LIGHTS[li], axis=1)
    want = imgs.reshape(3, -1, 3)[li, p] / cos[:, None]
    np.testing.assert_allclose(np.asarray(s1.values), want, rtol=1e-12)


# --------------------------------------------------------------------------- degenerate data: a status, never a raise


TRUTH = solvers.TorranceSparrow(np.array([0.6, 0.45, 0.3]), np.array([0.3, 0.3, 0.3]), 1.6, 0.2)


def _ok_result(res, allowed=None):
    assert isinstance(res.status, Status)
    name = res.status_name
    if allowed is not None:
        assert name in allowed, name
    rel = float(res.rel_rms)
    assert not np.isnan(rel), name
    assert not np.isnan(float(res.rms))
    return name


@pytest.fixture(scope="module")
def black_obs(gbuffers):
    return solvers.observations(gbuffers, [np.zeros(np.asarray(g.mask).shape + (3,)) for g in gbuffers])


@pytest.fixture(scope="module")
def one_pixel_obs(gbuffers):
    m = np.zeros(np.asarray(gbuffers[0].mask).shape, bool)
    m[tuple(np.argwhere(np.asarray(gbuffers[0].mask))[3])] = True
    return solvers.observations(gbuffers[:1], [np.ones(m.shape + (3,))], masks=[m])


@pytest.fixture(scope="module")
def ones_obs(gbuffers):
    return solvers.observations(gbuffers, [np.ones(np.asarray(g.mask).shape + (3,)) for g in gbuffers])


def test_fit_brdf_degenerate(black_obs, one_pixel_obs, ones_obs):
    assert _ok_result(solvers.fit_brdf(black_obs, LIGHT, max_steps=10)) == "no_signal"
    _ok_result(solvers.fit_brdf(one_pixel_obs, LIGHT, max_steps=10))
    zero_light = jaxsh.Lighting(np.zeros((9, 3)))
    assert _ok_result(solvers.fit_brdf(ones_obs, zero_light, max_steps=10)) != "converged"


def test_inverse_lighting_degenerate(black_obs, one_pixel_obs):
    assert _ok_result(solvers.inverse_lighting(black_obs, TRUTH, 2)) == "no_signal"
    assert _ok_result(solvers.inverse_lighting(one_pixel_obs, TRUTH, 2)) != "converged"
    assert _ok_result(solvers.inverse_lighting_dual(black_obs, TRUTH, 8, maxiter=5)) == "no_signal"
    _ok_result(solvers.inverse_lighting_dual(one_pixel_obs, TRUTH, 8, maxiter=5))


def test_inverse_lighting_zero_brdf_is_a_status(ones_obs):
    zero = solvers.TorranceSparrow(np.zeros(3), np.zeros(3), 1.5, 0.2)
    assert _ok_result(solvers.inverse_lighting(ones_obs, zero, 2)) != "converged"


@pytest.mark.parametrize("method", ["sh", "dual"])
@pytest.mark.parametrize("refine", [False, True])
def test_factorize_black_images(black_obs, refine, method):
    res = solvers.factorize(black_obs, 3, refine=refine, max_steps=5, lighting_method=method)  # raised "All-NaN
    # slice encountered"; the dual path with the refinement searches mu on the joint model and takes the source's
    # direction from the image's SH projection (session 33)
    assert _ok_result(res) == "no_signal"


@pytest.mark.parametrize("method", ["sh", "dual"])
def test_factorize_one_pixel(one_pixel_obs, method):
    assert _ok_result(solvers.factorize(one_pixel_obs, 3, max_steps=5, lighting_method=method)) != "converged"


def test_fit_sharing_no_signal():
    rng = np.random.default_rng(0)
    p = rng.uniform(size=(30, 3))
    assert _ok_result(solvers.fit_sharing(p, np.zeros(30), 8)) == "no_signal"
    assert _ok_result(solvers.fit_sharing(p, np.ones(30), 8, weights=np.zeros(30))) == "no_signal"
    assert _ok_result(solvers.fit_sharing(p, np.ones((30, 2)), 8)) == "converged"


def test_sharing_models_black_images():
    normal, mask = _hemisphere(10)
    black = np.zeros((3,) + mask.shape + (3,))
    smp = solvers.reflectance_samples(black, normal, [0.0, 0.0, 1.0], LIGHTS, mask=mask)
    assert _ok_result(solvers.fit_homogeneous(smp, 8)) == "no_signal"
    xy = np.stack(np.meshgrid(np.linspace(0, 1, 10), np.linspace(0, 1, 10)), -1)
    res = solvers.fit_dichromatic(black, black, np.ones((3, 3)), normal, [0.0, 0.0, 1.0], LIGHTS, xy, 14, 14,
                                  mask=mask)
    assert _ok_result(res) == "no_signal"
    res = solvers.fit_one_image(black[0], black[0], np.ones(3), normal, [0.0, 0.0, 1.0], LIGHTS[0], xy, 12, mask=mask)
    assert _ok_result(res) == "no_signal"


def test_public_error_if_on_one_device():
    """`jaxsh.error_if` is the checks' own route: on one device it is `equinox.error_if` on a scalar (no effect in
    the program, so JAX's fast dispatch path stays; the per-device callback of several devices is tested in
    tests/test_scale_kernels.py), `x` returned bit for bit, `EquinoxRuntimeError` with the message when it fails."""
    x = jnp.array([1.0, -0.0, jnp.nan])
    f = eqx.filter_jit(lambda v: jaxsh.error_if(v, v > 5.0, "too large"))
    assert np.array_equal(np.asarray(f(x)).view(np.uint64), np.asarray(x).view(np.uint64))
    assert not jax.make_jaxpr(lambda v: jaxsh.error_if(v, v > 5.0, "too large"))(x).effects
    assert not jax.make_jaxpr(lambda d: jaxsh.real_sh(d, 4))(jnp.ones((4, 3))).effects
    with pytest.raises(eqx.EquinoxRuntimeError, match="too large"):
        f(x.at[0].set(6.0)).block_until_ready()
    with pytest.raises(ValueError, match="`msg` must be a str"):
        jaxsh.error_if(x, x > 5.0, 3)
    # every dtype comes back bit for bit (integers OR-ed like floats, complex part by part, booleans by `| False`)
    for v in (jnp.array([3, -4], jnp.int32), jnp.array([200, 4], jnp.uint8), jnp.array([True, False]),
              jnp.array([1 + 2j, -0.0 - 3j]), jnp.array([jnp.nan + 1j], jnp.complex64)):
        y = eqx.filter_jit(lambda a: jaxsh.error_if(a, jnp.zeros(a.shape, bool), "never"))(v)
        assert y.dtype == v.dtype and np.array_equal(np.asarray(y).view(np.uint8), np.asarray(v).view(np.uint8)), v
        with pytest.raises(eqx.EquinoxRuntimeError, match="always"):
            eqx.filter_jit(lambda a: jaxsh.error_if(a, jnp.ones(a.shape, bool), "always"))(v).block_until_ready()


def test_run_time_checks_return_their_argument_exactly():
    """`error_if_any` (every traced check of jaxsh) returns `x` bit for bit, signed zeros, infinities and NaN
    included, keeps its derivative 1 and its vmap, and raises with its message; it checks a scalar, not `x`, so that a
    sharded `x` stays sharded (tests/test_scale.py)."""
    from jaxsh._checks import error_if_any

    x = jnp.array([-0.0, 0.0, 1.5, -jnp.inf, jnp.inf, jnp.nan, 1e-310, -3.0])  # 1e-310: subnormal (a product flushed it)
    f = eqx.filter_jit(lambda v: error_if_any(v, v == 7.0, "no sevens"))  # filter_jit: equinox's own error type
    y = np.asarray(f(x))
    assert np.array_equal(y.view(np.uint64), np.asarray(x).view(np.uint64))  # -0.0 stays -0.0, the NaN's bits stay
    x32 = jnp.array([-0.0, 1e-40, jnp.nan, 2.5], jnp.float32)  # float32 keeps its dtype and bits
    y32 = np.asarray(f(x32))
    assert y32.dtype == np.float32 and np.array_equal(y32.view(np.uint32), np.asarray(x32).view(np.uint32))
    g = jax.grad(lambda v: jnp.sum(error_if_any(v, v < -5.0, "too small") * v))(jnp.array([2.0, -1.0]))
    np.testing.assert_array_equal(np.asarray(g), [4.0, -2.0])
    with pytest.raises(eqx.EquinoxRuntimeError, match="no sevens"):
        f(x.at[2].set(7.0)).block_until_ready()
    vf = eqx.filter_jit(jax.vmap(lambda v: error_if_any(v, v == 7.0, "no sevens")))
    np.testing.assert_array_equal(np.asarray(vf(jnp.ones((3, 2)))), np.ones((3, 2)))
    with pytest.raises(eqx.EquinoxRuntimeError, match="no sevens"):
        vf(jnp.ones((3, 2)).at[1, 0].set(7.0)).block_until_ready()
    n = jnp.array([3, 4])  # integers go through equinox.error_if unchanged
    assert np.array_equal(np.asarray(jax.jit(lambda v: error_if_any(v, v < 0, "neg"))(n)), [3, 4])
