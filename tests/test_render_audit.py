"""Audit of the forward renderers: `render_practical`'s paper form under shadow, `render_reference`'s keyword form,
dtypes and non-unit geometry.

References: the addition theorem for the 9-term clamped cosine (Ramamoorthi & Hanrahan, "An efficient
representation for irradiance environment maps", SIGGRAPH 2001: $\\sum_{l \\le 2} A_l \\frac{2l+1}{4\\pi}
P_l(n\\cdot d)$, $A_l = \\pi, 2\\pi/3, \\pi/4$) and Lambert's cosine law $K_d E \\max(n \\cdot d, 0)$ for directional
sources, both written here in NumPy.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh


def _unit(x):
    x = np.asarray(x, np.float64)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _nine_term_cosine(n, d):
    """Lambert's clamped cosine to l = 2 (addition theorem): A_0/(4 pi) + A_1 (3/(4 pi)) t + A_2 (5/(4 pi)) P_2(t)."""
    t = n @ d
    return 0.25 + 0.5 * t + (5.0 / 16.0) * 0.5 * (3 * t * t - 1)


def test_paper_form_of_the_fast_diffuse_term_is_shadowed():
    """`exact_fast_diffuse=False` (eq. 21's 9-term irradiance for the fast sources) ignored `fast_visibility`: a source
    in full shadow still lit the diffuse term (2.0 for a source of energy 2 along the normal). Now each source's
    9-term cosine is multiplied by its visibility, as the exact form does (R&H sec. 6.4)."""
    rng = np.random.default_rng(0)
    n = _unit(rng.normal(size=(5, 3)) + [0, 0, 2])
    v = np.broadcast_to([0.0, 0.0, 1.0], n.shape)
    d = _unit([[0.3, 0.1, 1.0], [-0.5, 0.4, 0.8]])
    e = np.array([[2.0], [1.5]])
    vis = rng.integers(0, 2, size=(5, 2)).astype(float)
    vis[0] = [0.0, 0.0]
    vis[1] = [1.0, 1.0]
    brdf = jaxsh.TorranceSparrow(1.0, 0.0, None, 0.2)
    lit = jaxsh.Lighting(None, jnp.asarray(d), jnp.asarray(e))
    got = np.asarray(jaxsh.render_practical(n, v, brdf, lit, fast_visibility=vis, exact_fast_diffuse=False).diffuse)
    want = (np.stack([_nine_term_cosine(n, dj) for dj in d], 1) * vis) @ e
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    assert got[0, 0] == 0.0
    exact = np.asarray(jaxsh.render_practical(n, v, brdf, lit, fast_visibility=vis).diffuse)
    np.testing.assert_allclose(exact, (np.maximum(n @ d.T, 0) * vis) @ e, rtol=1e-12, atol=1e-14)


def test_reference_keyword_radiance_shapes_are_checked():
    """`render_reference(..., directional=(dirs, energy))`: energy of shape (2, 3) for one source rendered a 6-channel
    image, and an RGB (1, 3) for three sources one scalar each; both are now `Lighting`'s shape error. Valid forms
    give Lambert's law: a scalar per source (J,), or (J, C)."""
    n = _unit([[0.0, 0.2, 1.0], [0.3, -0.1, 1.0]])
    v = np.broadcast_to([0.0, 0.0, 1.0], n.shape)
    d = _unit([[0.2, 0.1, 1.0], [0.0, -0.6, 0.8], [0.7, 0.0, 0.7]])
    with pytest.raises(ValueError, match=r"fast_energy"):
        jaxsh.render_reference(n, v, 0.5, 0.0, None, 0.2, directional=(d[:1], np.ones((2, 3))))
    with pytest.raises(ValueError, match=r"fast_energy"):
        jaxsh.render_reference(n, v, 0.5, 0.0, None, 0.2, directional=(d, np.ones((1, 3))))
    e = np.array([1.0, 2.0, 0.5])
    got = np.asarray(jaxsh.render_reference(n, v, 0.5, 0.0, None, 0.2, directional=(d, e)))
    np.testing.assert_allclose(got[:, 0], 0.5 * np.maximum(n @ d.T, 0) @ e, rtol=1e-12)
    rgb = np.array([[1.0, 2.0, 3.0], [0.5, 0.5, 0.5], [0.0, 1.0, 0.0]])
    got = np.asarray(jaxsh.render_reference(n, v, 0.5, 0.0, None, 0.2, directional=(d, rgb)))
    np.testing.assert_allclose(got, 0.5 * np.maximum(n @ d.T, 0) @ rgb, rtol=1e-12)
    got = np.asarray(jaxsh.render_reference(n, v, 0.5, 0.0, None, 0.2, directional=(d[:1], 2.0)))
    np.testing.assert_allclose(got[:, 0], 0.5 * 2.0 * np.maximum(n @ d[0], 0), rtol=1e-12)


@pytest.mark.parametrize("renderer", ["practical", "reference"])
def test_float32_geometry_with_python_scalar_parameters_stays_float32(renderer):
    """docs/conventions.md: Python scalars adopt the dtype of the arrays. With x64 on (the test configuration, and the
    command line's) float32 normals and views with `kd=0.3` rendered float64 (the dtype was taken of `.dtype`,
    dropping the scalar's weak type)."""
    n = jnp.asarray(_unit([[0.0, 0.2, 1.0]]), jnp.float32)
    v = jnp.asarray([[0.0, 0.0, 1.0]], jnp.float32)
    lit = jaxsh.Lighting(None, jnp.asarray([[0.0, 0.0, 1.0]], jnp.float32), jnp.asarray([[1.0]], jnp.float32))
    brdf = jaxsh.TorranceSparrow(0.3, 0.5, None, 0.2)
    out = jaxsh.render_practical(n, v, brdf, lit).total if renderer == "practical" else \
        jaxsh.render_reference(n, v, brdf, lit)
    assert out.dtype == jnp.float32


def test_reference_normalizes_normals_and_views_like_the_practical_model():
    """|n| = 2 doubled `render_reference`'s diffuse term and halved its specular one while `render_practical`
    normalizes (its docstring: arguments as `render_practical`). Scaled normals and views now render the same image,
    and a zero normal (a miss) still renders 0."""
    n = _unit([[0.1, 0.2, 1.0], [0.0, 0.0, 1.0], [0.5, 0.0, 0.8]])
    v = _unit([[0.0, 0.1, 1.0], [0.2, 0.0, 1.0], [0.0, 0.0, 1.0]])
    lit = jaxsh.Lighting(None, jnp.asarray(_unit([[0.1, 0.0, 1.0]])), jnp.asarray([[1.0, 2.0, 0.5]]))
    brdf = jaxsh.TorranceSparrow(jnp.asarray([0.4, 0.3, 0.2]), jnp.asarray([0.3, 0.3, 0.3]), 1.5, 0.2)
    unit = np.asarray(jaxsh.render_reference(n, v, brdf, lit))
    scaled = np.asarray(jaxsh.render_reference(2.0 * n, 3.0 * v, brdf, lit))
    np.testing.assert_allclose(scaled, unit, rtol=1e-12)
    miss = np.asarray(jaxsh.render_reference(np.zeros((1, 3)), v[:1], brdf, lit))
    assert np.all(miss == 0)


@pytest.mark.parametrize("dt", [np.float32, np.float64])
def test_reference_small_disk_keeps_its_solid_angle_in_float32(dt):
    """A Lambertian surface (K_d = 1) facing a disk of unit radiance and angular radius r receives
    $\\int_{cap} \\cos\\theta\\,d\\omega = \\pi\\sin^2 r$. The cap's $1 - \\cos r$ was formed by subtraction: float32
    erred +1.4e-3 at r = 0.005 (the sun), -4.6e-2 at 1e-3 and +0.33 at 3e-4."""
    d = np.array([0.2, -0.3, 1.0])
    d /= np.linalg.norm(d)
    v = np.array([0.1, 0.4, 1.0]) / np.linalg.norm([0.1, 0.4, 1.0])
    for r in (0.1, 0.005, 0.001, 0.0003):
        out = jaxsh.render_reference(d[None].astype(dt), v[None].astype(dt), np.array([1.0], dt), np.array([0.0], dt),
                                     None, 0.2, disks=(d[None].astype(dt), np.array([r], dt), np.array([[1.0]], dt)))
        got = float(np.asarray(out)[0, 0])
        assert got == pytest.approx(np.pi * np.sin(r) ** 2, rel=2e-6 if dt == np.float32 else 1e-12), r
