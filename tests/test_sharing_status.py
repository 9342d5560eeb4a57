"""Status and residual units of the reflectance-sharing fits (solvers/_sharing.py), on degenerate and scaled data.

Independent expectations only: objects rendered by hand-written NumPy formulas (Lambertian, a colour
orthogonal to the source colour), and properties that need no reference — `rel_rms` invariant and `rms`
equivariant under a change of the images' (or values') units.

- `fit_dichromatic` / `fit_one_image`: `rms`/`rel_rms` in the units of the images (radiance), not pooled
  over the dimensionless diffuse samples and the specular ones (docs/sharing.md, "Units of rms");
- a matte object (all-zero specular images) is `converged`, not `no_signal` — its zero specular part is
  exact; `no_signal` is kept for all-zero data;
- `fit_one_image(irradiance=...)` of a bad shape is a `ValueError` naming `irradiance`;
- diffuse samples below zero (noise on dark pixels, a channel of the wrong sign) get albedo 0, the library's
  nonnegativity, and `rms` is that of the model `render` evaluates;
- `fit_sharing` / `fit_homogeneous` at scale extremes (values, weights, the metric): finite `rms`/`rel_rms`
  and a finite model, never NaN.
"""

import numpy as np
import pytest

import solvers

N = 14
VIEW = np.array([0.0, 0.0, 1.0])
LIGHTS = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 0.87], [0.0, 0.5, 0.87], [-0.4, 0.3, 0.87]])
LIGHTS = LIGHTS / np.linalg.norm(LIGHTS, axis=1, keepdims=True)
NOVEL = np.array([0.3, -0.35, 0.89]) / np.linalg.norm([0.3, -0.35, 0.89])


def _scene(n=N):
    """Hemisphere seen from +z: normals, mask, and `xy` at the texel centres (so the albedo map's nearest-texel
    lookup of `render` reads pixel (i, j) at pixel (i, j))."""
    i, j = np.mgrid[0:n, 0:n]
    x = (j + 0.5) / n * 2.0 - 1.0
    y = (i + 0.5) / n * 2.0 - 1.0
    r2 = x * x + y * y
    mask = r2 < 0.85
    z = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    normal = np.stack([x, y, z], -1)
    normal[~mask] = [0.0, 0.0, 1.0]
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    xy = np.stack([(j + 0.5) / n, (i + 0.5) / n], -1)
    return normal, mask, xy


def _albedo(xy):
    """A smooth RGB texture (H, W, 3) in [0.2, 0.8]."""
    u, v = xy[..., 0], xy[..., 1]
    return np.stack([0.5 + 0.3 * np.sin(3 * u), 0.4 + 0.2 * v, 0.3 + 0.1 * np.cos(2 * u + v)], -1)


def _lambertian(normal, mask, albedo, light, color, irradiance=1.0):
    """I_k = s_k E a_k max(n . l, 0) on the mask (Zickler 2006 eq. 14 with d_k = 1, g = 0)."""
    cos = np.clip(normal @ light, 0.0, None) * mask
    return color * irradiance * albedo * cos[..., None]


def _lobe(normal, mask, light, color, exponent=30.0, ks=0.6):
    """A Blinn-Phong-like highlight I_k = s_k ks (n . h)^e cos(theta_i), view +z."""
    h = (light + VIEW) / np.linalg.norm(light + VIEW)
    cos = np.clip(normal @ light, 0.0, None) * mask
    return color * (ks * np.clip(normal @ h, 0.0, None) ** exponent * cos)[..., None]


def _capture(colors, specular=True):
    normal, mask, xy = _scene()
    a = _albedo(xy)
    dif = np.stack([_lambertian(normal, mask, a, li, c) for li, c in zip(LIGHTS, colors)])
    spe = np.stack([_lobe(normal, mask, li, c) for li, c in zip(LIGHTS, colors)])
    return normal, mask, xy, a, dif, spe if specular else np.zeros_like(spe)


WHITE = np.tile(np.ones(3) / np.sqrt(3.0), (4, 1))
# changes of units by powers of two: the scaled data are then exactly the data in other units (a factor such as
# 0.01 rounds each sample, which can flip a near-tie of the greedy centre selection and so change the fit itself)
UNITS = (2.0**-7, 1.0, 2.0**10)


def _name(res):
    return solvers.status_name(res.status)


# --------------------------------------------------------------------------- defect 1: units of rms / rel_rms


def test_dichromatic_rel_rms_invariant_under_image_units():
    """The same capture in other units (images x c): `rel_rms` unchanged, `rms` x c (it pooled dimensionless
    diffuse samples with specular ones in image units; in the audit's capture rel_rms was 0.0011 at x0.01,
    0.109 at x1, 0.68 at x1000)."""
    normal, mask, xy, _, dif, spe = _capture(WHITE)
    fits = {c: solvers.fit_dichromatic(dif * c, spe * c, WHITE, normal, VIEW, LIGHTS, xy, 20, 20, mask=mask)
            for c in UNITS}
    base = fits[1.0]
    assert _name(base) == "converged"
    assert 1e-3 < float(base.rel_rms) < 1.0  # a non-trivial residual (20 specular centres): the check means something
    for c, r in fits.items():
        assert _name(r) == "converged"
        np.testing.assert_allclose(float(r.rel_rms), float(base.rel_rms), rtol=1e-6)
        np.testing.assert_allclose(float(r.rms), c * float(base.rms), rtol=1e-6)
    # the same images in other units of irradiance: images x c with irradiance c is the same reflectance
    r = solvers.fit_dichromatic(dif * 8.0, spe * 8.0, WHITE, normal, VIEW, LIGHTS, xy, 20, 20, irradiance=8.0,
                                mask=mask)
    np.testing.assert_allclose(float(r.rel_rms), float(base.rel_rms), rtol=1e-6)
    np.testing.assert_allclose(float(r.rms), 8.0 * float(base.rms), rtol=1e-6)


def _off_colour_capture():
    """Lambertian diffuse (fitted exactly: d_k = 1) plus a specular image whose colour is orthogonal to the source
    colour: eq. 14's g (a multiple of the source colour) cannot represent any of it, so the residual in image
    units is that image itself, at the samples."""
    normal, mask, xy = _scene()
    a = _albedo(xy)
    s = np.ones(3) / np.sqrt(3.0)
    off = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)  # s . off = 0
    dif = np.stack([_lambertian(normal, mask, a, li, s, 2.0) for li in LIGHTS])
    spe = np.stack([_lobe(normal, mask, li, off) for li in LIGHTS])
    # the samples: lit and facing the camera inside the mask (reflectance_samples with min_cos = 0)
    keep = np.stack([mask & (normal @ li > 0) & (normal @ VIEW > 0) for li in LIGHTS])
    return normal, mask, xy, s, dif, spe, keep


def test_dichromatic_rms_is_the_image_residual():
    normal, mask, xy, s, dif, spe, keep = _off_colour_capture()
    res = solvers.fit_dichromatic(dif, spe, np.tile(s, (4, 1)), normal, VIEW, LIGHTS, xy, 20, 20, irradiance=2.0,
                                  mask=mask)
    rss = np.sum(spe[keep] ** 2)
    want_rms = np.sqrt(rss / (2 * 3 * keep.sum()))
    want_rel = np.sqrt(rss / (np.sum(dif[keep] ** 2) + np.sum(spe[keep] ** 2)))
    np.testing.assert_allclose(float(res.rms), want_rms, rtol=1e-6)
    np.testing.assert_allclose(float(res.rel_rms), want_rel, rtol=1e-6)
    assert _name(res) == "converged"  # the diffuse fit is exact; the specular samples are all zero


def test_one_image_rms_is_the_image_residual():
    normal, mask, xy, s, dif, spe, keep = _off_colour_capture()
    res = solvers.fit_one_image(dif[1], spe[1], s, normal, VIEW, LIGHTS[1], xy, 20, irradiance=2.0, mask=mask)
    k = keep[1]
    rss = np.sum(spe[1][k] ** 2)
    np.testing.assert_allclose(float(res.rms), np.sqrt(rss / (2 * 3 * k.sum())), rtol=1e-6)
    np.testing.assert_allclose(float(res.rel_rms), np.sqrt(rss / (np.sum(dif[1][k] ** 2) + rss)), rtol=1e-6)
    assert _name(res) == "converged"


def test_one_image_rel_rms_invariant_under_image_units():
    normal, mask, xy, _, dif, spe = _capture(WHITE)
    fits = {c: solvers.fit_one_image(dif[1] * c, spe[1] * c, WHITE[1], normal, VIEW, LIGHTS[1], xy, 20, mask=mask)
            for c in UNITS}
    assert float(fits[1.0].rel_rms) > 1e-3
    for c, r in fits.items():
        assert _name(r) == "converged"
        np.testing.assert_allclose(float(r.rel_rms), float(fits[1.0].rel_rms), rtol=1e-6)
        np.testing.assert_allclose(float(r.rms), c * float(fits[1.0].rms), rtol=1e-6)


# --------------------------------------------------------------------------- defect 2: a matte object has signal


def test_matte_object_dichromatic_converges():
    """All-zero specular images and informative diffuse ones: the zero specular reflectance is the answer, the
    status `converged` (it was `no_signal`, and `throw=True` raised), and the model renders the Lambertian object."""
    colors = np.array([[0.8, 0.5, 0.33], [0.5, 0.7, 0.5], [0.6, 0.6, 0.53], [0.7, 0.5, 0.51]])
    colors = colors / np.linalg.norm(colors, axis=1, keepdims=True)
    normal, mask, xy, a, dif, spe = _capture(colors, specular=False)
    res = solvers.fit_dichromatic(dif, spe, colors, normal, VIEW, LIGHTS, xy, 20, 20, mask=mask, throw=True)
    assert _name(res) == "converged"
    assert float(res.rel_rms) < 1e-8
    c = np.array([0.9, 0.4, 0.2])
    want = _lambertian(normal, mask, a, NOVEL, c, 1.5)
    got = np.asarray(res.render(normal, VIEW, NOVEL, xy, color=c, irradiance=1.5, mask=mask))
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)


def test_matte_object_one_image_converges():
    normal, mask, xy, a, dif, spe = _capture(WHITE, specular=False)
    res = solvers.fit_one_image(dif[2], spe[2], WHITE[2], normal, VIEW, LIGHTS[2], xy, 20, mask=mask, throw=True)
    assert _name(res) == "converged"
    assert float(res.rel_rms) < 1e-8
    lit = mask & (normal @ LIGHTS[2] > 0)  # texels never lit keep the median albedo: compare where lit
    want = _lambertian(normal, lit, a, NOVEL, WHITE[2])
    got = np.asarray(res.render(normal, VIEW, NOVEL, xy, color=WHITE[2], mask=lit))
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)


def test_zero_component_statuses():
    """Pure specular (all-zero diffuse images) converges too; all-zero images stay `no_signal`."""
    normal, mask, xy, _, dif, spe = _capture(WHITE)
    zero = np.zeros_like(dif)
    assert _name(solvers.fit_dichromatic(zero, spe, WHITE, normal, VIEW, LIGHTS, xy, 20, 20, mask=mask)) == "converged"
    one = solvers.fit_one_image(zero[1], spe[1], WHITE[1], normal, VIEW, LIGHTS[1], xy, 20, mask=mask)
    assert _name(one) == "converged"
    black = solvers.fit_dichromatic(zero, zero, WHITE, normal, VIEW, LIGHTS, xy, 20, 20, mask=mask)
    assert _name(black) == "no_signal" and float(black.rms) == 0.0 and float(black.rel_rms) == 0.0
    black1 = solvers.fit_one_image(zero[1], zero[1], WHITE[1], normal, VIEW, LIGHTS[1], xy, 20, mask=mask)
    assert _name(black1) == "no_signal"
    with pytest.raises(solvers.SolveError):
        solvers.fit_one_image(zero[1], zero[1], WHITE[1], normal, VIEW, LIGHTS[1], xy, 20, mask=mask, throw=True)


# --------------------------------------------------------------------------- defect 3: irradiance of a bad shape


def test_one_image_irradiance_shape():
    normal, mask, xy, _, dif, spe = _capture(WHITE)
    args = (dif[1], spe[1], WHITE[1], normal, VIEW, LIGHTS[1], xy, 20)
    with pytest.raises(ValueError, match=r"`irradiance`.*\(1,\)"):
        solvers.fit_one_image(*args, irradiance=np.ones(3), mask=mask)
    with pytest.raises(ValueError, match=r"`irradiance`"):
        solvers.fit_one_image(*args, irradiance=np.ones((1, 3)), mask=mask)
    with pytest.raises(ValueError, match=r"`irradiance`"):
        solvers.fit_one_image(*args, irradiance=-1.0, mask=mask)
    a = solvers.fit_one_image(*args, irradiance=np.array([2.0]), mask=mask)
    b = solvers.fit_one_image(*args, irradiance=2.0, mask=mask)
    np.testing.assert_array_equal(np.asarray(a.albedo), np.asarray(b.albedo))
    # the albedo is the image over s_k E cos(theta_i): half of that at E = 1
    c = solvers.fit_one_image(*args, irradiance=1.0, mask=mask)
    np.testing.assert_allclose(np.asarray(a.albedo), 0.5 * np.asarray(c.albedo), rtol=1e-12)


def test_dichromatic_irradiance_must_be_positive():
    normal, mask, xy, _, dif, spe = _capture(WHITE)
    with pytest.raises(ValueError, match=r"`irradiance`"):
        solvers.fit_dichromatic(dif, spe, WHITE, normal, VIEW, LIGHTS, xy, 20, 20, irradiance=[1.0, 0.0, 1.0, 1.0],
                                mask=mask)


# --------------------------------------------------------------------------- defect 4: scale extremes


def _samples(dtype=np.float64):
    rng = np.random.default_rng(0)
    p = rng.uniform(size=(200, 3))
    y = np.sin(3 * p[:, 0]) + p[:, 1] * p[:, 2] + 1.0
    return p.astype(dtype), y.astype(dtype)


@pytest.mark.parametrize("c", [2.0**-660, 2.0**660])  # about 1e-199, 1e199: squares out of range
def test_fit_sharing_values_units_float64(c):
    p, y = _samples()
    base = solvers.fit_sharing(p, y, 50)
    r = solvers.fit_sharing(p, y * c, 50)
    assert _name(r) == "converged"
    np.testing.assert_allclose(float(r.rel_rms), float(base.rel_rms), rtol=1e-9)
    np.testing.assert_allclose(float(r.rms), c * float(base.rms), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(r(p[:20])), c * np.asarray(base(p[:20])), rtol=1e-9)
    # weights in other units select the same centres; rms scales with them
    w = solvers.fit_sharing(p, y, 50, weights=np.full(200, c))
    np.testing.assert_array_equal(np.asarray(w.center_index), np.asarray(base.center_index))
    np.testing.assert_allclose(float(w.rel_rms), float(base.rel_rms), rtol=1e-9)
    np.testing.assert_allclose(float(w.rms), c * float(base.rms), rtol=1e-9)


@pytest.mark.parametrize("c", [2.0**-100, 2.0**100])  # about 1e-30, 1e30
def test_fit_sharing_extremes_float32(c):
    """float32: values x 1e+-30 (squares out of range) and a metric of 1e+-30: the fit of the unscaled data."""
    p, y = _samples(np.float32)
    base = solvers.fit_sharing(p, y, 50)
    assert base.rms.dtype == np.float32 and _name(base) == "converged"
    r = solvers.fit_sharing(p, y * np.float32(c), 50)
    assert _name(r) == "converged"
    np.testing.assert_allclose(float(r.rel_rms), float(base.rel_rms), rtol=1e-3)
    np.testing.assert_allclose(float(r.rms) / c, float(base.rms), rtol=1e-3)
    m = solvers.fit_sharing(p, y, 50, scale=np.full(3, c, np.float32))
    assert _name(m) == "converged"
    assert np.isfinite(float(m.rms)) and np.isfinite(float(m.rel_rms))
    np.testing.assert_allclose(float(m.rel_rms), float(base.rel_rms), rtol=1e-2)
    np.testing.assert_allclose(np.asarray(m(p[:20])), np.asarray(base(p[:20])), rtol=1e-3)


def _homogeneous_samples(irradiance=1.0):
    normal, mask, xy, _, dif, spe = _capture(WHITE)
    return solvers.reflectance_samples(dif + spe, normal, VIEW, LIGHTS, irradiance=irradiance, mask=mask)


def test_fit_homogeneous_extreme_metric_is_finite():
    """m_w = 1e300: the kernel's squared distances overflow. Whatever the status, no NaN and a finite model."""
    smp = _homogeneous_samples()
    r = solvers.fit_homogeneous(smp, 30, m_w=1e300)
    assert not np.isnan(float(r.rms)) and not np.isnan(float(r.rel_rms))
    model = r.fit.model
    assert np.all(np.isfinite(np.asarray(model.weights))) and np.all(np.isfinite(np.asarray(model.poly)))
    assert np.all(np.isfinite(np.asarray(r.fit(smp.points))))
    assert np.all(np.isfinite(np.asarray(r.render(np.asarray([[[0.0, 0.0, 1.0]]]), VIEW, LIGHTS[1]))))


def test_fit_homogeneous_tiny_irradiance():
    """Irradiance 2**-996 (1.5e-300): reflectance samples of 1e300, whose squares overflow; the fit at irradiance 1."""
    e = 2.0**-996
    base = solvers.fit_homogeneous(_homogeneous_samples(), 30)
    r = solvers.fit_homogeneous(_homogeneous_samples(e), 30)
    assert _name(r) == _name(base)
    np.testing.assert_allclose(float(r.rel_rms), float(base.rel_rms), rtol=1e-9)
    np.testing.assert_allclose(float(r.rms) * e, float(base.rms), rtol=1e-9)
    tiny = solvers.fit_homogeneous(_homogeneous_samples(1e-300), 30)  # not a power of two: rounding, same size
    assert not np.isnan(float(tiny.rms)) and abs(float(tiny.rel_rms) - float(base.rel_rms)) < 0.05


# --------------------------------------------------------------------------- defect 4: diffuse samples below zero


def _relative_error(got, want, keep):
    return float(np.sqrt(np.sum((got - want)[keep] ** 2) / np.sum(want[keep] ** 2)))


def test_dichromatic_pixels_a_little_below_zero_do_not_poison_the_fit():
    """1 % of the lit pixels at -0.002 (1 % of the mean diffuse value) in every image: their median albedo was
    raised to the floor 1e-6 max(albedo), so their diffuse samples r/a were ~1e6 times the data, and the d_k fit
    through them gave relative RMS 1,219 and a novel-light error of 239x the signal, status `converged`. Now
    their albedo is 0, they are left out of the d_k fit, and everywhere else the novel light is predicted as
    from the clean images."""
    normal, mask, xy, a, dif, spe = _capture(WHITE)
    lit_all = np.stack([mask & (normal @ li > 0) for li in LIGHTS]).all(0)
    cand = np.argwhere(lit_all)
    pick = cand[np.random.default_rng(1).choice(len(cand), len(cand) // 100, replace=False)]
    bad = dif.copy()
    bad[:, pick[:, 0], pick[:, 1], :] = -0.002
    clean = solvers.fit_dichromatic(dif, spe, WHITE, normal, VIEW, LIGHTS, xy, 20, 20, mask=mask)
    res = solvers.fit_dichromatic(bad, spe, WHITE, normal, VIEW, LIGHTS, xy, 20, 20, mask=mask)
    assert _name(res) == "converged"
    albedo = np.asarray(res.albedo)
    assert np.all(albedo >= 0) and np.all(albedo[pick[:, 0], pick[:, 1]] == 0)
    assert float(res.rel_rms) < 1.1 * float(clean.rel_rms) < 0.1
    c = np.array([0.9, 0.4, 0.2])
    want = _lambertian(normal, mask, _albedo(xy), NOVEL, c) + _lobe(normal, mask, NOVEL, c)
    keep = mask & (normal @ NOVEL > 0)
    keep[pick[:, 0], pick[:, 1]] = False
    e_clean = _relative_error(np.asarray(clean.render(normal, VIEW, NOVEL, xy, color=c, mask=mask)), want, keep)
    e_bad = _relative_error(np.asarray(res.render(normal, VIEW, NOVEL, xy, color=c, mask=mask)), want, keep)
    assert e_clean < 0.06 and e_bad < 1.01 * e_clean


def test_dichromatic_channel_of_the_wrong_sign_is_not_a_tiny_albedo():
    """The green diffuse channel negated (a colour conversion gone wrong). Its albedo was the floor 8e-7 and d_g
    about -1e5, whose product fitted the negative data exactly: `rel_rms` 0.073, as for the true images, while
    `render` (max(d_k, 0)) showed green 0. Now the green albedo is 0 and `rms` is the residual of what `render`
    evaluates, so it holds at least the green diffuse data's energy (a bound from the data alone)."""
    normal, mask, xy, a, dif, spe = _capture(WHITE)
    bad = dif.copy()
    bad[..., 1] *= -1.0
    res = solvers.fit_dichromatic(bad, spe, WHITE, normal, VIEW, LIGHTS, xy, 20, 20, mask=mask)
    assert np.all(np.asarray(res.albedo)[..., 1] == 0) and np.all(np.asarray(res.albedo)[mask][:, [0, 2]] > 0.1)
    lit = np.stack([mask & (normal @ li > 0) for li in LIGHTS])
    green_ss = np.sum(bad[..., 1][lit] ** 2)
    data_ss = np.sum(bad[lit] ** 2) + np.sum(spe[lit] ** 2)
    assert float(res.rel_rms) ** 2 >= green_ss / data_ss * (1 - 1e-9)
    np.testing.assert_allclose(float(res.stats["data_ss"]), data_ss, rtol=1e-9)


def test_one_image_albedo_is_the_nonnegative_ratio():
    """One sample per pixel: the albedo is the nonnegative least-squares value max(I_d / (s E cos), 0), computed
    here from the images; pixels pushed below zero by noise were given a negative albedo (and `render` negative
    radiance)."""
    normal, mask, xy, a, dif, spe = _capture(WHITE)
    rng = np.random.default_rng(2)
    d = dif[1] + 0.03 * rng.normal(size=dif[1].shape) * mask[..., None]
    cos = normal @ LIGHTS[1]
    lit = mask & (cos > 0)
    assert np.any(d[lit] < 0)  # the noise does push some lit samples below zero
    res = solvers.fit_one_image(d, spe[1], WHITE[1], normal, VIEW, LIGHTS[1], xy, 20, irradiance=2.0, mask=mask)
    want = np.maximum(d[lit] / (WHITE[1] * 2.0 * cos[lit][:, None]), 0.0)
    np.testing.assert_allclose(np.asarray(res.albedo)[lit], want, rtol=1e-12, atol=0)
    assert np.all(np.asarray(res.albedo) >= 0)
    img = np.asarray(res.render(normal, VIEW, LIGHTS[1], xy, color=WHITE[1], irradiance=2.0, mask=mask))
    assert np.all(img >= 0)
