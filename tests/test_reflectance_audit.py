"""BRDF models at a zero normal and with NaN parameters (audit, session 28).

A G-buffer miss has a zero normal, which is below the horizon: the value there is the constant 0, so its gradient
is exactly 0 (module docstring) — it was NaN, and a loss masked with `jnp.where(gb.mask, ...)` still got NaN
parameter gradients from the misses. A NaN index of refraction read as total internal reflection and gave the
value without Fresnel; it must propagate, as the docstring says NaN parameters do.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh

WI = jnp.array([0.3, 0.0, 0.954])
WO = jnp.array([0.0, 0.6, 0.8])
P = jnp.array([0.2, 0.7, 1.5, 0.2])
MODELS = {
    "torrance_sparrow": lambda p, n: jaxsh.torrance_sparrow(WI, WO, n, p[0], p[1], p[2], p[3]),
    "torrance_sparrow mu=None": lambda p, n: jaxsh.torrance_sparrow(WI, WO, n, p[0], p[1], None, p[3]),
    "cook_torrance": lambda p, n: jaxsh.cook_torrance(WI, WO, n, p[0], p[1], p[3], p[2]),
    "cook_torrance_smith": lambda p, n: jaxsh.cook_torrance_smith(WI, WO, n, p[0], p[1], p[2], p[3]),
    "ggx": lambda p, n: jaxsh.ggx(WI, WO, n, p[0], p[1], p[2], p[3]),
    "ward_isotropic": lambda p, n: jaxsh.ward_isotropic(WI, WO, n, p[0], p[1], p[3]),
    "oren_nayar": lambda p, n: jaxsh.oren_nayar(WI, WO, n, p[0], p[3]),
    "phong": lambda p, n: jaxsh.phong(WI, WO, n, 10 * p[3]),
    "lafortune": lambda p, n: jaxsh.lafortune(WI, WO, n, p[0], jnp.array([[-1.0, 1.0, 5.0]])),
}


@pytest.mark.parametrize("name", list(MODELS))
def test_zero_normal_gives_zero_value_and_zero_gradients(name):
    f = MODELS[name]
    n0 = jnp.zeros(3)
    assert float(f(P, n0)) == 0.0
    np.testing.assert_array_equal(np.asarray(jax.grad(f)(P, n0)), 0.0)
    np.testing.assert_array_equal(np.asarray(jax.grad(f, argnums=1)(P, n0)), 0.0)


def test_a_masked_loss_over_a_gbuffer_with_misses_has_finite_gradients():
    gb = jaxsh.sphere_gbuffer(jaxsh.OrthographicCamera(2.4 / 16, 16, 16, jaxsh.look_at(jnp.array([0.0, -5, 0]),
                              jnp.zeros(3), jnp.array([0.0, 0, 1]))), jnp.zeros(3), jnp.asarray(1.0))
    assert not bool(jnp.all(gb.mask))  # there are misses, with zero normals
    light = jnp.array([0.3, -0.8, 0.5]) / jnp.linalg.norm(jnp.array([0.3, -0.8, 0.5]))

    def loss(p):
        b = jaxsh.torrance_sparrow(light, gb.view, gb.normal, p[0], p[1], p[2], p[3])
        return jnp.sum(jnp.where(gb.mask, b, 0.0) ** 2)

    g = np.asarray(jax.grad(loss)(P))
    assert np.all(np.isfinite(g)) and np.any(g != 0)


def test_nan_index_of_refraction_propagates():
    n = jnp.array([0.0, 0.0, 1.0])
    assert np.isnan(float(jaxsh.fresnel_dielectric(0.5, np.nan)))
    assert np.isnan(float(jaxsh.fresnel_dielectric(np.nan, 1.5)))
    assert np.isnan(float(jaxsh.fresnel_normalized(np.nan, 1.5)))
    f = jax.jit(lambda mu: jaxsh.torrance_sparrow(WI, WO, n, 0.2, 0.5, mu, 0.2))
    assert np.isnan(float(f(jnp.asarray(np.nan))))
    assert np.isnan(float(jax.jit(lambda mu: jaxsh.ggx(WI, WO, n, 0.2, 0.5, mu, 0.2))(jnp.asarray(np.nan))))
    # total internal reflection itself is unchanged: mu < 1 beyond the critical angle gives F = 1
    assert float(jaxsh.fresnel_dielectric(0.1, 0.8)) == pytest.approx(1.0)
