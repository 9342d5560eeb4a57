"""Bad input to the solvers (issue 12): a `ValueError` whose message names the argument, never a raw JAX error.

Property-based (hypothesis) over `solvers.observations` and every solver's
argument shapes and options: wrong shapes, channel mismatches between
arguments, NaN/inf inside masks, negative weights, bad option values. Each
case asserts that the argument's name is in the message (in backticks, as the
library writes it) and that no raw broadcasting error leaks. Sizes are tiny
and every case fails in the argument checks, before any compilation, so the
"ci" profile (tests/conftest.py) runs the whole file in seconds; "thorough"
draws more examples. Degenerate *data* (a status, not an error) is in
tests/test_degenerate.py.
"""

import re

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jaxsh
import solvers

from .helpers import hemisphere_normals

NONFINITE = st.sampled_from([np.nan, np.inf, -np.inf])
SIZE = 6


def _raises_named(fn, name):
    """`fn()` raises a ValueError naming `name` (as `` `name` `` or `` `name[k]` ``), never a raw JAX error."""
    with pytest.raises(ValueError) as info:
        fn()
    msg = str(info.value)
    assert re.search(rf"`{re.escape(name)}(\[\d+\])?(\.[a-z_]+)?`", msg), (name, msg)
    for raw in ("Incompatible types for broadcasting", "Incompatible shapes", "cannot reshape", "operands could not"):
        assert raw not in msg, msg
    return msg


# --------------------------------------------------------------------------- fixtures (module scope: built once)


@pytest.fixture(scope="module")
def gbs():
    cams = solvers.view_cameras(2, SIZE)
    return [jaxsh.sphere_gbuffer(c, jnp.zeros(3), jnp.asarray(1.0)) for c in cams]


def _masks(gbs):
    return [np.asarray(g.mask) for g in gbs]


def _images(gbs, c=3, value=0.5):
    return [np.full(m.shape + (c,), value) for m in _masks(gbs)]


@pytest.fixture(scope="module")
def obs(gbs):
    return solvers.observations(gbs, _images(gbs))


LIGHT = jaxsh.Lighting(np.eye(9, 3))  # 3 channels, l <= 2
BRDF = solvers.TorranceSparrow(np.full(3, 0.5), np.full(3, 0.3), 1.5, 0.2)


def _brdf(c):
    return solvers.TorranceSparrow(np.full(c, 0.5), np.full(c, 0.3), 1.5, 0.2)


# --------------------------------------------------------------------------- observations


@given(k=st.integers(0, 1), dh=st.integers(1, 3), axis=st.integers(0, 1))
def test_observations_image_shape(gbs, k, dh, axis):
    imgs = _images(gbs)
    shape = list(imgs[k].shape)
    shape[axis] += dh
    imgs[k] = np.ones(shape)
    _raises_named(lambda: solvers.observations(gbs, imgs), f"images[{k}]")


@given(c0=st.integers(1, 4), c1=st.integers(1, 4))
def test_observations_channel_mismatch_between_views(gbs, c0, c1):
    imgs = [_images(gbs, c0)[0], _images(gbs, c1)[1]]
    if c0 == c1:
        assert solvers.observations(gbs, imgs).n_channels == c0
    else:
        _raises_named(lambda: solvers.observations(gbs, imgs), "images[1]")


@given(n=st.integers(0, 4))
def test_observations_image_count(gbs, n):
    imgs = (_images(gbs) * 2)[:n]
    if n == 2:
        return
    _raises_named(lambda: solvers.observations(gbs, imgs), "images")


@given(bad=NONFINITE, k=st.integers(0, 1), pix=st.integers(0, 3), ch=st.integers(0, 2))
def test_observations_nonfinite_inside_the_mask(gbs, bad, k, pix, ch):
    imgs = _images(gbs)
    i, j = np.argwhere(_masks(gbs)[k])[pix]
    imgs[k][i, j, ch] = bad
    _raises_named(lambda: solvers.observations(gbs, imgs), f"images[{k}]")
    # the same pixel masked out by the user: no error, one sample fewer
    m = [np.ones_like(x) for x in _masks(gbs)]
    m[k][i, j] = False
    full = solvers.observations(gbs, _images(gbs)).n_samples
    assert solvers.observations(gbs, imgs, masks=m).n_samples == full - 1
    # invalid="drop" drops it too
    assert solvers.observations(gbs, imgs, invalid="drop").n_samples == full - 1


@given(bad=NONFINITE, k=st.integers(0, 1))
def test_observations_nonfinite_outside_the_mask_is_ignored(gbs, bad, k):
    imgs = _images(gbs)
    i, j = np.argwhere(~_masks(gbs)[k])[0]
    imgs[k][i, j] = bad
    o = solvers.observations(gbs, imgs)
    assert np.all(np.isfinite(np.asarray(o.values)))


@given(value=st.one_of(st.floats(-10.0, -1e-9), NONFINITE), k=st.integers(0, 1), pix=st.integers(0, 3))
def test_observations_bad_weights(gbs, value, k, pix):
    w = [np.ones(m.shape) for m in _masks(gbs)]
    i, j = np.argwhere(_masks(gbs)[k])[pix]
    w[k][i, j] = value
    if value == np.inf:
        return  # +inf is excluded below: a weight that is infinite is non-finite, covered by nan/-inf
    _raises_named(lambda: solvers.observations(gbs, _images(gbs), weights=w), f"weights[{k}]")


@given(name=st.sampled_from(["masks", "weights", "reflected_visibility", "texel"]), k=st.integers(0, 1),
       d=st.integers(1, 2))
def test_observations_per_view_shapes(gbs, name, k, d):
    arrs = [np.ones(m.shape, np.int32 if name == "texel" else float) for m in _masks(gbs)]
    arrs[k] = np.ones((SIZE + d, SIZE), arrs[k].dtype)
    _raises_named(lambda: solvers.observations(gbs, _images(gbs), **{name: arrs}), f"{name}[{k}]")
    _raises_named(lambda: solvers.observations(gbs, _images(gbs), **{name: arrs[:1]}), name)


@given(k=st.integers(0, 1), nt=st.integers(1, 12))
def test_observations_transfer_shape(gbs, k, nt):
    tr = [np.zeros(m.shape + (9,)) for m in _masks(gbs)]
    tr[k] = np.zeros(_masks(gbs)[k].shape + (nt,))
    if nt == 9:
        return
    _raises_named(lambda: solvers.observations(gbs, _images(gbs), transfer=tr), f"transfer[{k}]")


@given(k=st.integers(0, 1))
def test_observations_texel_dtype_and_range(gbs, k):
    tx = [np.zeros(m.shape, np.int32) for m in _masks(gbs)]
    bad = [t.copy() for t in tx]
    bad[k] = bad[k].astype(float)
    _raises_named(lambda: solvers.observations(gbs, _images(gbs), texel=bad), f"texel[{k}]")
    bad = [t.copy() for t in tx]
    bad[k][_masks(gbs)[k]] = -1
    _raises_named(lambda: solvers.observations(gbs, _images(gbs), texel=bad, n_texels=4), f"texel[{k}]")


@given(opt=st.sampled_from(["Raise", "ignore", "", "nan"]))
def test_observations_bad_option(gbs, opt):
    _raises_named(lambda: solvers.observations(gbs, _images(gbs), invalid=opt), "invalid")


# --------------------------------------------------------------------------- solver arguments


NOT_OBS = st.sampled_from([None, 3, "obs", np.ones((4, 3))])


@given(bad=NOT_OBS, solver=st.sampled_from(["fit_brdf", "fit_brdf_sh", "inverse_lighting", "inverse_lighting_dual",
                                            "factorize"]))
def test_solvers_reject_non_observations(bad, solver):
    calls = {
        "fit_brdf": lambda: solvers.fit_brdf(bad, LIGHT),
        "fit_brdf_sh": lambda: solvers.fit_brdf_sh(bad, np.eye(9, 3), 2),
        "inverse_lighting": lambda: solvers.inverse_lighting(bad, BRDF, 2),
        "inverse_lighting_dual": lambda: solvers.inverse_lighting_dual(bad, BRDF, 8),
        "factorize": lambda: solvers.factorize(bad, 3),
    }
    _raises_named(calls[solver], "obs")


@given(c=st.sampled_from([2, 4, 5]))
def test_fit_brdf_lighting_channels(obs, c):
    _raises_named(lambda: solvers.fit_brdf(obs, jaxsh.Lighting(np.eye(9, c))), "lighting")


@given(bad=st.sampled_from([None, 1.0, "sun", np.eye(9, 3)]), n=st.integers(0, 4))
def test_fit_brdf_lighting_type_and_count(obs, bad, n):
    _raises_named(lambda: solvers.fit_brdf(obs, bad), "lighting")
    if n != 2:  # one Lighting per view: obs has 2 views
        _raises_named(lambda: solvers.fit_brdf(obs, [LIGHT] * n), "lighting")


@given(opt=st.sampled_from(["ks", "KD", "both", "", 1]))
def test_fit_brdf_textured_option(obs, opt):
    _raises_named(lambda: solvers.fit_brdf(obs, LIGHT, textured=opt), "textured")


@given(rows=st.integers(1, 8), c=st.integers(1, 5))
def test_fit_brdf_sh_lighting_shape(obs, rows, c):
    if rows >= 9 and c in (1, 3):
        return
    _raises_named(lambda: solvers.fit_brdf_sh(obs, np.ones((rows, c)), 2), "lighting_sh")


@given(c=st.sampled_from([2, 4]))
def test_fit_brdf_sh_lighting_channels(obs, c):
    _raises_named(lambda: solvers.fit_brdf_sh(obs, np.ones((9, c)), 2), "lighting_sh")
    _raises_named(lambda: solvers.fit_brdf_sh(obs, jaxsh.Lighting(np.eye(9, c)), 2), "lighting_sh")


@given(lmax=st.sampled_from([-3, -1, 2.5, "2", None]))
def test_lmax_option(obs, lmax):
    _raises_named(lambda: solvers.fit_brdf_sh(obs, np.ones((9, 3)), lmax), "lmax")
    _raises_named(lambda: solvers.inverse_lighting(obs, BRDF, lmax), "lmax")
    _raises_named(lambda: solvers.factorize(obs, lmax), "lmax")


@given(c=st.sampled_from([2, 4, 5]), solver=st.sampled_from(["inverse_lighting", "inverse_lighting_dual"]))
def test_inverse_lighting_brdf_channels(obs, c, solver):
    fn = getattr(solvers, solver)
    _raises_named(lambda: fn(obs, _brdf(c), 2 if solver == "inverse_lighting" else 8), "brdf")


@given(bad=st.sampled_from([None, 0.5, "ts", LIGHT]), solver=st.sampled_from(["inverse_lighting",
                                                                               "inverse_lighting_dual"]))
def test_inverse_lighting_brdf_type(obs, bad, solver):
    _raises_named(lambda: getattr(solvers, solver)(obs, bad, 4), "brdf")


@given(opt=st.sampled_from([("chunk", 0), ("chunk", -5), ("ridge", -1.0), ("ridge", np.nan), ("rcond", -1e-3),
                            ("rcond", np.inf)]))
def test_inverse_lighting_options(obs, opt):
    name, value = opt
    _raises_named(lambda: solvers.inverse_lighting(obs, BRDF, 2, **{name: value}), name)


@given(opt=st.sampled_from([("height", 3), ("height", 0), ("height", 4.5), ("maxiter", 0), ("maxiter", -1),
                            ("tol", -1e-3), ("tol", np.nan)]))
def test_inverse_lighting_dual_options(obs, opt):
    name, value = opt
    kw = {"height": 8, name: value}
    _raises_named(lambda: solvers.inverse_lighting_dual(obs, BRDF, **kw), name)


@given(opt=st.sampled_from([("max_steps", 0), ("max_steps", -3), ("chunk", 0), ("search_pixels", 0),
                            ("fresnel", "no"), ("find_sigma", 0), ("refine", "yes"), ("refine_mu", None)]))
def test_factorize_options(obs, opt):
    name, value = opt
    _raises_named(lambda: solvers.factorize(obs, 3, **{name: value}), name)


@given(opt=st.sampled_from([("max_steps", 0), ("max_steps", -2), ("rtol", -1.0), ("atol", np.nan), ("fresnel", "no"),
                            ("fresnel", 1), ("refine", "no")]))
def test_fit_brdf_options(obs, opt):
    name, value = opt
    _raises_named(lambda: solvers.fit_brdf(obs, LIGHT, **{name: value}), name)


@given(init=st.sampled_from([(1.5, -0.1), (0.5, 0.2), (np.nan, 0.2), (1.0, 0.2), (1.5, 0.0), (1.5, np.inf), (1.5,),
                              "ab", (None, 0.2), (1.5, 2.0)]))
def test_fit_brdf_init(obs, init):
    """`init` outside the search box (`MU_BOUNDS`, `SIGMA_BOUNDS`) or not a pair of numbers: before, the search
    started at NaN and stopped at iteration 0 with status `nonfinite`."""
    _raises_named(lambda: solvers.fit_brdf(obs, LIGHT, init=init), "init")


# --------------------------------------------------------------------------- fit_sharing


def _pts(n=12, d=3, seed=0):
    return np.random.default_rng(seed).uniform(size=(n, d))


@given(shape=st.sampled_from([(12,), (12, 3, 1), (), (0, 3)]))
def test_fit_sharing_points_shape(shape):
    _raises_named(lambda: solvers.fit_sharing(np.ones(shape), np.ones(12), 4), "points")


@given(rows=st.integers(1, 20), extra_dim=st.booleans())
def test_fit_sharing_values_shape(rows, extra_dim):
    if rows == 12 and not extra_dim:
        return
    v = np.ones((rows, 2, 1)) if extra_dim else np.ones(rows)
    _raises_named(lambda: solvers.fit_sharing(_pts(), v, 4), "values")


@given(d=st.integers(1, 5))
def test_fit_sharing_scale_shape(d):
    if d == 3:
        return
    _raises_named(lambda: solvers.fit_sharing(_pts(), np.ones(12), 4, scale=np.ones(d)), "scale")


@given(value=st.one_of(st.floats(-5.0, 0.0), NONFINITE))
def test_fit_sharing_scale_value(value):
    _raises_named(lambda: solvers.fit_sharing(_pts(), np.ones(12), 4, scale=[1.0, value, 1.0]), "scale")


@given(rows=st.integers(1, 20), value=st.one_of(st.floats(-5.0, -1e-9), NONFINITE), i=st.integers(0, 11))
def test_fit_sharing_weights(rows, value, i):
    if rows != 12:
        _raises_named(lambda: solvers.fit_sharing(_pts(), np.ones(12), 4, weights=np.ones(rows)), "weights")
    w = np.ones(12)
    w[i] = value
    _raises_named(lambda: solvers.fit_sharing(_pts(), np.ones(12), 4, weights=w), "weights")


@given(which=st.sampled_from(["points", "values"]), bad=NONFINITE, i=st.integers(0, 11))
def test_fit_sharing_nonfinite(which, bad, i):
    p, v = _pts(), np.ones((12, 2))
    (p if which == "points" else v)[i, 0] = bad
    _raises_named(lambda: solvers.fit_sharing(p, v, 4), which)


@given(n_centers=st.sampled_from([0, 3, 13, 100, 4.0, True, "8", None]))
def test_fit_sharing_n_centers(n_centers):
    _raises_named(lambda: solvers.fit_sharing(_pts(), np.ones(12), n_centers), "n_centers")


@given(opt=st.sampled_from([("smoothing", -1.0), ("smoothing", np.nan), ("smoothing", np.inf), ("tol", -0.1),
                            ("tol", np.nan), ("n_init", 0), ("n_init", 2.5), ("n_add", 0), ("n_add", -1),
                            ("chunk", 0), ("chunk", "big")]))
def test_fit_sharing_options(opt):
    name, value = opt
    _raises_named(lambda: solvers.fit_sharing(_pts(), np.ones(12), 8, **{name: value}), name)


def test_fit_sharing_complex_and_half():
    _raises_named(lambda: solvers.fit_sharing(_pts().astype(complex), np.ones(12), 4), "points")
    _raises_named(lambda: solvers.fit_sharing(_pts().astype(np.float16), np.ones(12), 4), "points")
    _raises_named(lambda: solvers.fit_sharing(_pts(), np.ones(12) + 0j, 4), "values")


# --------------------------------------------------------------------------- reflectance samples and the models


LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]])


def _samples_args(c=3):
    normal, mask = hemisphere_normals(SIZE)
    return dict(images=np.ones((3, SIZE, SIZE, c)), normal=normal, view=[0.0, 0.0, 1.0], lights=LIGHTS, mask=mask)


BAD_SAMPLE_SHAPES = [
    ("images", np.ones((SIZE, SIZE))), ("images", np.ones((1, 3, SIZE, SIZE, 3))),
    ("normal", np.ones((SIZE, SIZE + 1, 3))), ("normal", np.ones((SIZE, SIZE, 2))),
    ("view", np.ones(2)), ("view", np.ones((SIZE, SIZE, 4))),
    ("lights", np.ones((2, 3))), ("lights", np.ones((3, 2))),
    ("irradiance", np.ones(2)), ("irradiance", np.ones((3, 2))),
    ("mask", np.ones((SIZE, SIZE - 1), bool)), ("xy", np.ones((SIZE, SIZE, 3))),
    ("visible", np.ones((2, SIZE, SIZE), bool)),
]


@given(case=st.sampled_from(BAD_SAMPLE_SHAPES))
def test_reflectance_samples_shapes(case):
    name, value = case
    kw = _samples_args()
    kw[name] = value
    _raises_named(lambda: solvers.reflectance_samples(**kw), name)


@given(case=st.sampled_from([("irradiance", 0.0), ("irradiance", -1.0), ("irradiance", np.nan),
                             ("irradiance", np.inf)]))
def test_reflectance_samples_irradiance_value(case):
    name, value = case
    kw = _samples_args()
    kw[name] = value
    _raises_named(lambda: solvers.reflectance_samples(**kw), name)


@given(bad=NONFINITE, k=st.integers(0, 2), pix=st.integers(0, 3), ch=st.integers(0, 2))
def test_reflectance_samples_nonfinite_inside_mask(bad, k, pix, ch):
    kw = _samples_args()
    i, j = np.argwhere(kw["mask"])[pix]
    kw["images"][k, i, j, ch] = bad
    _raises_named(lambda: solvers.reflectance_samples(**kw), "images")
    kw["mask"] = kw["mask"].copy()
    kw["mask"][i, j] = False  # outside the mask: ignored
    s = solvers.reflectance_samples(**kw)
    assert np.all(np.isfinite(np.asarray(s.values)))


@pytest.fixture(scope="module")
def samples():
    return solvers.reflectance_samples(**_samples_args())


@given(which=st.sampled_from(["fit_homogeneous", "fit_sbrdf"]), n_centers=st.sampled_from([0, 2, 10**6, 3.5, None]))
def test_models_n_centers(samples, which, n_centers):
    if which == "fit_sbrdf":
        kw = _samples_args()
        xy = np.stack(np.meshgrid(np.linspace(0, 1, SIZE), np.linspace(0, 1, SIZE)), -1)
        smp = solvers.reflectance_samples(**kw, xy=xy)
    else:
        smp = samples
    _raises_named(lambda: getattr(solvers, which)(smp, n_centers), "n_centers")


@given(case=st.sampled_from([("fit_homogeneous", "m_w", 0.0), ("fit_homogeneous", "m_w", -0.3),
                             ("fit_homogeneous", "m_w", np.nan), ("fit_sbrdf", "m_xy", -1.0),
                             ("fit_sbrdf", "m_xy", np.inf), ("fit_sbrdf", "m_w", 0.0)]))
def test_models_metric_options(samples, case):
    which, name, value = case
    if which == "fit_sbrdf":
        xy = np.stack(np.meshgrid(np.linspace(0, 1, SIZE), np.linspace(0, 1, SIZE)), -1)
        smp = solvers.reflectance_samples(**_samples_args(), xy=xy)
    else:
        smp = samples
    _raises_named(lambda: getattr(solvers, which)(smp, 8, **{name: value}), name)


def test_models_sample_dimension(samples):
    _raises_named(lambda: solvers.fit_sbrdf(samples, 8), "samples")  # (u, v, w) samples: no xy
    _raises_named(lambda: solvers.fit_homogeneous("samples", 8), "samples")


# --------------------------------------------------------------------------- predict


@given(c_brdf=st.integers(2, 4), c_light=st.integers(2, 4))
def test_predict_channel_mismatch(gbs, c_brdf, c_light):
    g = gbs[0]
    if c_brdf == c_light:
        out = solvers.predict(_brdf(c_brdf), jaxsh.Lighting(np.eye(9, c_light)), g.normal, g.view, mask=g.mask)
        assert out.shape[-1] == c_brdf
        return
    msg = _raises_named(lambda: solvers.predict(_brdf(c_brdf), jaxsh.Lighting(np.eye(9, c_light)), g.normal,
                                                g.view, mask=g.mask), "kd")  # the BRDF's field
    assert "`lighting" in msg


@given(bad=st.sampled_from([None, 1.0, "sun", []]))
def test_predict_lighting_type(gbs, bad):
    g = gbs[0]
    _raises_named(lambda: solvers.predict(BRDF, bad, g.normal, g.view), "lighting")


@given(k=st.integers(0, 3))
def test_predict_per_image_lists(gbs, k):
    g = gbs[0]
    if k == 2:
        return
    _raises_named(lambda: solvers.predict(BRDF, [LIGHT, LIGHT], [g.normal] * k, g.view), "normals")


@given(d=st.integers(1, 3))
def test_predict_texel_shape(gbs, d):
    g = gbs[0]
    tex = solvers.TorranceSparrow(np.full((4, 3), 0.5), np.full(3, 0.3), 1.5, 0.2)
    _raises_named(lambda: solvers.predict(tex, LIGHT, g.normal, g.view, texel=np.zeros((SIZE, SIZE + d), int)),
                  "texel")
    msg = _raises_named(lambda: solvers.predict(tex, LIGHT, g.normal, g.view), "brdf")  # `brdf.kd`: not a pixel map
    assert "`texel=`" in msg
