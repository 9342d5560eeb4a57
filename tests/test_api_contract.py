"""The documented contract of a few public functions, against independent references.

Each test pins one rule of docs/conventions.md or of the function's docstring that the code once broke:

* gradients of the half/difference angles at the mirror configuration θh = 0 (against central finite
  differences in float64 and the hand formula ∂θd/∂θo = 1/2);
* "Python scalars adopt the dtype of the arrays" (float32 stays float32 under x64);
* shapes: a `ValueError` naming the argument and the expected shape (never a silent reinterpretation,
  sum or broadcast);
* dtypes: integers go to the default float, float16 and non-numeric input are a `ValueError`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh

Z = np.array([0.0, 0.0, 1.0])


def _raises_named(fn, *parts):
    """`fn()` raises a ValueError whose message contains every string of `parts`."""
    with pytest.raises(ValueError) as info:
        fn()
    for part in parts:
        assert part in str(info.value), f"{part!r} not in {str(info.value)!r}"


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _reflect(v, n):
    return 2.0 * np.dot(n, v) * n - v


def _central_difference(f, x, h=1e-6):
    """Central differences of a scalar function of a float64 vector, coordinate by coordinate."""
    x = np.asarray(x, np.float64)
    g = np.zeros_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        g[i] = (float(f(jnp.asarray(x + e))) - float(f(jnp.asarray(x - e)))) / (2 * h)
    return g


def _assert_grad_matches_fd(f, x, atol=2e-6, rtol=1e-5):
    ad = np.asarray(jax.grad(f)(jnp.asarray(x)))
    fd = _central_difference(f, x)
    assert np.all(np.isfinite(ad))
    np.testing.assert_allclose(ad, fd, atol=atol, rtol=rtol)


# --------------------------------------------------------------------------- 1. θd and w at θh = 0


def _mirror_configuration(name):
    """(wi, wo, n) with wi = reflect(wo, n): the half vector along the normal, θh = 0."""
    if name == "plane":  # exactly θh = 0 in the local frame: h = (0, 0, 1)
        t0 = 0.4
        wo, n = np.array([np.sin(t0), 0.0, np.cos(t0)]), Z
    elif name == "azimuth":
        wo, n = _unit([0.3, -0.5, 0.8]), Z
    else:  # "tilted"
        wo, n = _unit([-0.4, 0.1, 0.9]), _unit([0.2, -0.3, 0.9])
    return _reflect(wo, n), wo, n


def _generic_configurations():
    """(wi, wo, n) above the horizon, away from θh = 0, θd = 0 and the wrap of the azimuths at 0 = 2π."""
    rng = np.random.default_rng(3)
    out = []
    while len(out) < 4:
        n = _unit(rng.normal(size=3) * [0.3, 0.3, 1.0] + [0, 0, 2])
        wi, wo = _unit(rng.normal(size=3)), _unit(rng.normal(size=3))
        s = wi + wo
        tangential = s - (s @ n) * n
        if wi @ n > 0.2 and wo @ n > 0.2 and np.linalg.norm(wi - wo) > 0.3 and np.linalg.norm(tangential) > 0.1:
            _, ph, _, pd = (float(a) for a in jaxsh.rusinkiewicz_angles(wi, wo, n))
            if min(ph, pd) > 0.05 and max(ph, pd) < 2 * np.pi - 0.05:
                out.append((wi, wo, n))
    return out


def _split(x):
    return x[0:3], x[3:6], x[6:9]


@pytest.mark.parametrize("name", ["plane", "azimuth", "tilted"])
def test_theta_d_and_w_gradients_at_the_mirror_configuration(name):
    """θd = angle(ωi, h) is smooth at θh = 0: the gradient of θd (`rusinkiewicz_angles`) and of
    w = 2θd/π (`uvw_from_directions`) in all 9 components of (wi, wo, n) equals central differences.
    (The polar form through φh gave 0 for ∂θd/∂θo, whose true value is 1/2.) The other smooth
    functions of the angles there, cos θh, θh² and u² + v² = sin² θh, too."""
    wi, wo, n = _mirror_configuration(name)
    x = np.concatenate([wi, wo, n])
    np.testing.assert_allclose(float(jaxsh.half_angle(wi, wo, n)), 0.0, atol=1e-7)
    outputs = {
        "theta_d": lambda z: jaxsh.rusinkiewicz_angles(*_split(z))[2],
        "w": lambda z: jaxsh.uvw_from_directions(*_split(z))[2],
        "cos theta_h": lambda z: jnp.cos(jaxsh.rusinkiewicz_angles(*_split(z))[0]),
        "theta_h^2": lambda z: jaxsh.rusinkiewicz_angles(*_split(z))[0] ** 2,
        "u^2+v^2": lambda z: jnp.sum(jaxsh.uvw_from_directions(*_split(z))[:2] ** 2),
    }
    for label, f in outputs.items():
        try:
            _assert_grad_matches_fd(f, x)
        except AssertionError as e:
            raise AssertionError(f"{label} at the {name} mirror configuration: {e}") from None


def test_theta_d_derivative_at_the_mirror_configuration_hand_formula():
    """In the plane of incidence with n = +z, ωi at polar angle t0 on one side and ωo at t on the other:
    h is at polar angle (t - t0)/2, so θd = (t + t0)/2 and ∂θd/∂t = 1/2, also at t = t0 (θh = 0).
    Tilting the normal does not move θd (it depends on ωi and ωo only): ∂θd/∂(tilt) = 0."""
    t0 = 0.4
    wi = jnp.array([-np.sin(t0), 0.0, np.cos(t0)])

    def theta_d(t):
        wo = jnp.stack([jnp.sin(t), 0.0 * t, jnp.cos(t)])
        return jaxsh.rusinkiewicz_angles(wi, wo, jnp.asarray(Z))[2]

    def w(t):
        wo = jnp.stack([jnp.sin(t), 0.0 * t, jnp.cos(t)])
        return jaxsh.uvw_from_directions(wi, wo, jnp.asarray(Z))[2]

    for t in (t0, t0 + 1e-3, t0 - 0.2):
        np.testing.assert_allclose(float(theta_d(t)), (t + t0) / 2, atol=1e-14)
        np.testing.assert_allclose(float(jax.grad(theta_d)(t)), 0.5, atol=1e-12)
        np.testing.assert_allclose(float(jax.grad(w)(t)), 1.0 / np.pi, atol=1e-12)

    wo = jnp.array([np.sin(t0), 0.0, np.cos(t0)])

    def tilted(a):
        return jaxsh.rusinkiewicz_angles(wi, wo, jnp.stack([jnp.sin(a), 0.0 * a, jnp.cos(a)]))[2]

    np.testing.assert_allclose(float(jax.grad(tilted)(0.0)), 0.0, atol=1e-12)


@pytest.mark.parametrize("k", range(4))
def test_rusinkiewicz_and_uvw_gradients_at_generic_points(k):
    """Away from the singular configurations every output is smooth: all four angles and all three of
    (u, v, w), gradients in the 9 components equal central differences; θd equals arccos(ωi·h) (NumPy)."""
    wi, wo, n = _generic_configurations()[k]
    x = np.concatenate([wi, wo, n])
    h = _unit(wi + wo)
    np.testing.assert_allclose(float(jaxsh.rusinkiewicz_angles(wi, wo, n)[2]), np.arccos(wi @ h), atol=1e-13)
    for i in range(4):
        _assert_grad_matches_fd(lambda z: jaxsh.rusinkiewicz_angles(*_split(z))[i], x)
    for i in range(3):
        _assert_grad_matches_fd(lambda z: jaxsh.uvw_from_directions(*_split(z))[i], x)


def test_theta_d_values_unchanged_against_numpy(rng):
    """θd is the angle between ωi and the half vector (Rusinkiewicz 1998), to rounding, at random pairs."""
    n = 200
    wi = rng.normal(size=(n, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wo = rng.normal(size=(n, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    ref = np.arctan2(np.linalg.norm(np.cross(h, wi), axis=1), np.sum(h * wi, axis=1))
    th, _, td, _ = jaxsh.rusinkiewicz_angles(wi, wo, Z)
    np.testing.assert_allclose(np.asarray(td), ref, atol=1e-14)
    np.testing.assert_allclose(np.asarray(jaxsh.uvw_from_directions(wi, wo, Z))[:, 2], 2 * ref / np.pi, atol=1e-14)
    np.testing.assert_allclose(np.asarray(th), np.arccos(np.clip(h[:, 2], -1, 1)), atol=1e-7)


# --------------------------------------------------------------------------- 2. Python scalars adopt the arrays' dtype


def test_filter_lighting_microfacet_keeps_float32_with_a_python_sigma():
    c = np.random.default_rng(0).normal(size=(9, 3)).astype(np.float32)
    out = jaxsh.filter_lighting_microfacet(c, 0.2)
    assert out.dtype == jnp.float32
    l = np.array([0, 1, 1, 1, 2, 2, 2, 2, 2], np.float64)
    np.testing.assert_allclose(np.asarray(out), np.exp(-((0.2 * l) ** 2))[:, None] * c, rtol=1e-6)
    # float32 with a float64 array: the widest
    assert jaxsh.filter_lighting_microfacet(c, np.float64(0.2)).dtype == jnp.float64
    assert jaxsh.filter_lighting_microfacet(c.astype(np.float64), 0.2).dtype == jnp.float64


def test_disk_light_sh_keeps_float32_with_python_scalars():
    d = np.array([0.0, 0.6, 0.8], np.float32)
    out = jaxsh.disk_light_sh(d, 0.2, 1.0, 2)
    assert out.dtype == jnp.float32
    ref = np.asarray(jaxsh.disk_light_sh(d.astype(np.float64), 0.2, 1.0, 2))
    np.testing.assert_allclose(np.asarray(out), ref, rtol=2e-5, atol=1e-7)
    # L_00 of a cap: radiance · 2π(1 - cos r)/√(4π) (hand formula)
    np.testing.assert_allclose(float(out[0]), 2 * np.pi * (1 - np.cos(0.2)) / np.sqrt(4 * np.pi), rtol=1e-5)
    assert jaxsh.disk_light_sh(d, 0.2, np.ones(3, np.float32), 2).dtype == jnp.float32
    assert jaxsh.disk_light_sh(d, np.float64(0.2), 1.0, 2).dtype == jnp.float64


def test_torrance_sparrow_spectrum_keeps_float32_with_the_default_theta_o():
    kw = dict(n_theta=16, n_phi=8)
    out = jaxsh.torrance_sparrow_spectrum(np.float32(0.2), 4, **kw)  # theta_o defaults to the Python float 0.0
    assert out.dtype == jnp.float32
    ref = np.asarray(jaxsh.torrance_sparrow_spectrum(0.2, 4, **kw))
    assert ref.dtype == np.float64
    np.testing.assert_allclose(np.asarray(out), ref, rtol=1e-5)
    assert jaxsh.torrance_sparrow_spectrum(np.float32(0.2), 4, 0.3, 1.5, **kw).dtype == jnp.float32
    assert jaxsh.torrance_sparrow_spectrum(np.float32(0.2), 4, np.float64(0.3), **kw).dtype == jnp.float64


# --------------------------------------------------------------------------- 3. split_disk_sources: shapes and dtypes

_D = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # K = 2 sources
_R = np.array([0.01, 0.5])  # the first is fast at sigma = 0.2, the second slow
_RAD = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])  # (K, C = 3)


def test_split_disk_sources_values():
    """Slow: the sum of `disk_light_sh`; fast: the disk's direction and energy 2π(1 - cos r)·radiance."""
    slow, fd, fe = jaxsh.split_disk_sources(_D, _R, _RAD, 0.2, 2)
    np.testing.assert_allclose(np.asarray(slow), np.asarray(jaxsh.disk_light_sh(_D[1], _R[1], _RAD[1], 2)), atol=1e-15)
    np.testing.assert_allclose(fd, _D[:1], atol=1e-15)
    np.testing.assert_allclose(fe, 2 * np.pi * (1 - np.cos(0.01)) * _RAD[:1], rtol=1e-12)


def test_split_disk_sources_rejects_transposed_and_bad_shapes():
    _raises_named(lambda: jaxsh.split_disk_sources(_D.T, _R, _RAD, 0.2, 2), "`directions`", "(K, 3)", "(3, 2)")
    _raises_named(lambda: jaxsh.split_disk_sources(_RAD.T, _R, _RAD, 0.2, 2), "`directions`", "(K, 3)")  # (3, 2)
    _raises_named(lambda: jaxsh.split_disk_sources(np.ones((2, 4)), _R, _RAD, 0.2, 2), "`directions`", "(K, 3)")
    _raises_named(lambda: jaxsh.split_disk_sources(np.ones(3), _R[:1], _RAD[:1], 0.2, 2), "`directions`", "(K, 3)")
    _raises_named(lambda: jaxsh.split_disk_sources(_D, _R, _RAD.T, 0.2, 2), "`radiance`", "(2, C)", "(3, 2)")
    _raises_named(lambda: jaxsh.split_disk_sources(_D, _R, np.ones((2, 3, 1)), 0.2, 2), "`radiance`", "(2, C)")
    _raises_named(lambda: jaxsh.split_disk_sources(_D, _R[None], _RAD, 0.2, 2), "`angular_radii`", "(2,)", "(1, 2)")
    _raises_named(lambda: jaxsh.split_disk_sources(_D, _R[:1], _RAD, 0.2, 2), "`angular_radii`", "(2,)")
    _raises_named(lambda: jaxsh.split_disk_sources(_D, np.float64(0.3), _RAD[:1], 0.2, 2), "`angular_radii`")
    _raises_named(lambda: jaxsh.split_disk_sources(np.zeros((2, 3)), _R, _RAD, 0.2, 2), "`directions`", "zero-length")
    _raises_named(lambda: jaxsh.split_disk_sources(_D.astype(np.float16), _R, _RAD, 0.2, 2), "`directions`", "float16")
    _raises_named(lambda: jaxsh.split_disk_sources(_D, _R, _RAD.astype(np.complex128), 0.2, 2), "`radiance`")
    _raises_named(lambda: jaxsh.split_disk_sources(_D, np.array([0.01, 4.0]), _RAD, 0.2, 2), "`angular_radii`")


def test_split_disk_sources_keeps_the_input_dtype():
    """float32 in, float32 out: `slow_sh` a JAX array, the fast parts NumPy arrays (host side, documented)."""
    f32 = lambda a: np.asarray(a, np.float32)
    slow, fd, fe = jaxsh.split_disk_sources(f32(_D), f32(_R), f32(_RAD), 0.2, 2)
    assert isinstance(slow, jax.Array) and slow.dtype == jnp.float32
    assert isinstance(fd, np.ndarray) and fd.dtype == np.float32
    assert isinstance(fe, np.ndarray) and fe.dtype == np.float32
    ref = jaxsh.split_disk_sources(_D, _R, _RAD, 0.2, 2)
    for a, b in zip((slow, fd, fe), ref):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-5, atol=1e-6)
    # float32 with float64: the widest; integers: the default float (float64 under x64)
    out = jaxsh.split_disk_sources(f32(_D), _R, f32(_RAD), 0.2, 2)
    assert out[0].dtype == jnp.float64 and out[1].dtype == out[2].dtype == np.float64
    out = jaxsh.split_disk_sources(_D.astype(np.int64), _R, _RAD, 0.2, 2)
    for a, b in zip(out, ref):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-15)
    # one channel as (K,) is (K, 1)
    slow, _, fe = jaxsh.split_disk_sources(_D, _R, _RAD[:, 0], 0.2, 2)
    assert slow.shape == (9, 1) and fe.shape == (1, 1)


# --------------------------------------------------------------------------- 4. scalar angles of the light-field functions


@pytest.fixture(scope="module")
def lighting_and_rho():
    L = jaxsh.real_to_complex_coeffs(np.random.default_rng(0).normal(size=9))
    rho_i = jaxsh.brdf_incident_coefficients(lambda ti, to, dp: jnp.cos(ti) + 0 * to + 0 * dp, 0.3, 2)
    return L, rho_i


def test_reflect_sh_rejects_array_angles(lighting_and_rho):
    """`alpha`, `beta`, `phi_o` are scalars: an array is a ValueError naming it (`alpha` of shape (2,) was summed
    over: reflect_sh(alpha=[0.1, 0.3]) returned B(0.1) + B(0.3))."""
    L, rho_i = lighting_and_rho
    two = jnp.array([0.1, 0.3])
    _raises_named(lambda: jaxsh.reflect_sh(L, rho_i, two, 0.2), "`alpha`", "scalar", "(2,)")
    _raises_named(lambda: jaxsh.reflect_sh(L, rho_i, 0.1, two), "`beta`", "scalar", "(2,)")
    _raises_named(lambda: jaxsh.reflect_sh(L, rho_i, 0.1, 0.2, two), "`phi_o`", "scalar", "(2,)")
    _raises_named(lambda: jaxsh.reflect_sh(L, rho_i, np.ones((1, 1)), 0.2), "`alpha`", "(1, 1)")


def test_reflect_sh_scalar_and_vmapped_angles(lighting_and_rho):
    """Many normals by `jax.vmap`: each value equals its own call."""
    L, rho_i = lighting_and_rho
    alphas = jnp.array([0.1, 0.3, 0.7])
    each = np.array([float(jaxsh.reflect_sh(L, rho_i, a, 0.2, 0.4)) for a in (0.1, 0.3, 0.7)])
    batched = jax.vmap(lambda a: jaxsh.reflect_sh(L, rho_i, a, 0.2, 0.4))(alphas)
    assert batched.shape == (3,)
    np.testing.assert_allclose(np.asarray(batched), each, rtol=1e-13)
    # the transfer function cos θi under constant lighting Y00: B = ∫ Y00 cos θi dω = π Y00, the irradiance
    c = np.zeros(9)
    c[0] = 1.0
    Lc = jaxsh.real_to_complex_coeffs(c)
    e = float(jaxsh.irradiance(c, Z))  # ∫ L cos θi dω for L = Y00
    np.testing.assert_allclose(float(jaxsh.reflect_sh(Lc, rho_i, 0.0, 0.0)), e, rtol=1e-6)


def test_light_field_basis_and_incident_coefficients_reject_array_angles():
    two = jnp.array([0.1, 0.3])
    wo = [0.3, 0.0, 0.95]
    _raises_named(lambda: jaxsh.light_field_basis(two, 0.2, wo, 2), "`alpha`", "scalar", "(2,)")
    _raises_named(lambda: jaxsh.light_field_basis(0.1, two, wo, 2), "`beta`", "scalar", "(2,)")
    _raises_named(lambda: jaxsh.light_field_basis(0.1, 0.2, [wo, wo], 2), "`wo_local`", "(3,)", "(2, 3)")
    _raises_named(lambda: jaxsh.light_field_basis(0.1, 0.2, [0.3, 0.95], 2), "`wo_local`", "(2,)")
    transfer = lambda ti, to, dp: jnp.cos(ti) + 0 * to + 0 * dp
    _raises_named(lambda: jaxsh.brdf_incident_coefficients(transfer, two, 2), "`theta_o`", "scalar", "(2,)")
    assert jaxsh.light_field_basis(0.1, 0.2, wo, 2).shape == (9, 3, 5)
    assert jaxsh.brdf_incident_coefficients(transfer, 0.3, 2).shape == (9,)


# --------------------------------------------------------------------------- 5. half_angle validates like torrance_sparrow


def test_half_angle_validates_its_arguments():
    _raises_named(lambda: jaxsh.half_angle(np.array([[0.6, 0.8]]), np.array([[0.6, 0.8]]), np.array([[1.0, 0.0]])), "`wi`", "(..., 3)", "(1, 2)")
    _raises_named(lambda: jaxsh.half_angle(Z, np.ones((4, 2)), Z), "`wo`", "(..., 3)")
    _raises_named(lambda: jaxsh.half_angle(Z, Z, np.ones(4)), "`n`", "(..., 3)")
    _raises_named(lambda: jaxsh.half_angle(*(np.array([1.0, 0, 0], np.float16),) * 3), "`wi`", "float16")
    _raises_named(lambda: jaxsh.half_angle(np.ones((4, 3)), np.ones((5, 3)), np.ones((4, 3))), "`wo`", "(5,)", "(4,)")
    _raises_named(lambda: jaxsh.half_angle(Z.astype(complex), Z, Z), "`wi`", "real")


def test_half_angle_values_dtypes_and_broadcasting(rng):
    """θh = arccos(h·n) (NumPy, away from 0); integer input goes to the default float; float32 stays float32;
    leading dimensions broadcast."""
    wi = rng.normal(size=(20, 3)) + [0, 0, 2]
    wo = rng.normal(size=(20, 3)) + [0, 0, 2]
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    ref = np.arccos(h[:, 2])
    np.testing.assert_allclose(np.asarray(jaxsh.half_angle(wi, wo, Z)), ref, atol=1e-12)
    out = jaxsh.half_angle(np.array([1, 0, 0]), np.array([0, 0, 1]), np.array([0, 0, 1]))
    assert out.dtype == jnp.float64
    np.testing.assert_allclose(float(out), np.pi / 4, atol=1e-15)
    out32 = jaxsh.half_angle(wi.astype(np.float32), wo.astype(np.float32), Z.astype(np.float32))
    assert out32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(out32), ref, atol=1e-5)
    assert jaxsh.half_angle(wi.astype(np.float32), wo, Z).dtype == jnp.float64  # the widest
    assert jaxsh.half_angle(wi[:1], wo, Z).shape == (20,)
    assert jaxsh.half_angle(wi[:, None], wo[None, :5], Z).shape == (20, 5)


# --------------------------------------------------------------------------- 6. complex_to_real_coeffs: the float conversion


def test_complex_to_real_coeffs_integer_input_keeps_its_digits():
    """Integers go to the default float (float64 under x64): 2**40 + 1 comes back exactly (U_00 = 1, so the
    L00 coefficient of a real expansion is its complex one)."""
    big = np.array([2**40 + 1] + [0] * 8)
    out = jaxsh.complex_to_real_coeffs(big)
    assert out.dtype == jnp.float64
    assert float(out[0]) == 2**40 + 1
    c = np.arange(9)
    np.testing.assert_allclose(np.asarray(jaxsh.complex_to_real_coeffs(jaxsh.real_to_complex_coeffs(c))), c, atol=1e-13)
    # the floats and complex of each width keep it
    assert jaxsh.complex_to_real_coeffs(np.ones(9, np.float32)).dtype == jnp.float32
    assert jaxsh.complex_to_real_coeffs(np.ones(9, np.complex64)).dtype == jnp.float32
    assert jaxsh.complex_to_real_coeffs(np.ones(9, np.complex128)).dtype == jnp.float64


def test_complex_to_real_coeffs_rejects_float16_and_non_numeric_input():
    _raises_named(lambda: jaxsh.complex_to_real_coeffs(np.arange(9, dtype=np.float16)), "`coeffs`", "float16")
    _raises_named(lambda: jaxsh.complex_to_real_coeffs(np.array(["a"] * 9)), "`coeffs`", "numeric")
