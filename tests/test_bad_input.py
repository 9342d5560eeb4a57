"""Bad input to the forward kernels, cameras and G-buffers (issue 12), by category.

Every case asserts either a `ValueError` whose message names the argument
(concrete values), an error whose message names it (traced values under
`jax.jit`: `equinox.error_if`), or a finite, documented result (the pure
array kernels propagate NaN in their *data*, like `jax.numpy`; see the
module docstring of `jaxsh._checks`). Property-based with hypothesis, small
sizes; the "ci" profile (conftest) keeps it fast, "thorough" runs more.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st

import jaxsh

# --------------------------------------------------------------------------- helpers

NONFINITE = st.sampled_from([math.nan, math.inf, -math.inf])


def _raises_named(fn, name, *extra):
    """`fn()` raises ValueError with `name` (and every string in `extra`) in the message."""
    with pytest.raises(ValueError) as info:
        fn()
    msg = str(info.value)
    for part in (name,) + extra:
        assert part in msg, f"{part!r} not in {msg!r}"


def _raises_named_jit(fn, name):
    """Under jit (traced values): an error whose message names the argument, never a value."""
    with pytest.raises(Exception, match=name):
        jax.block_until_ready(fn())


def _cam_ortho(n=6, dtype=np.float64):
    return jaxsh.OrthographicCamera(0.5 / n, n, n, np.asarray(jaxsh.look_at([0, 0, 5.0], [0, 0, 0], [0, 1.0, 0]), dtype))


def _cam_pinhole(n=6):
    return jaxsh.PinholeCamera(2.0 * n, 2.0 * n, n / 2, n / 2, n, n, jaxsh.look_at([0, 0, 5.0], [0, 0, 0], [0, 1.0, 0]))


def _rotation(seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))[None, :]
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _pose(seed):
    m = np.eye(4)
    m[:3, :3] = _rotation(seed)
    m[:3, 3] = np.random.default_rng(seed + 1).normal(size=3)
    return m


# =========================================================================== non-finite


@given(NONFINITE, st.integers(0, 3), st.integers(0, 3))
def test_nonfinite_cam_to_world(v, i, j):
    m = np.eye(4)
    m[i, j] = v
    _raises_named(lambda: jaxsh.OrthographicCamera(0.1, 4, 4, m), "cam_to_world")
    _raises_named(lambda: jaxsh.PinholeCamera(4.0, 4.0, 2.0, 2.0, 4, 4, m), "cam_to_world")


@given(NONFINITE, st.sampled_from(["fx", "fy", "cx", "cy"]))
def test_nonfinite_pinhole_intrinsics(v, name):
    kw = dict(fx=4.0, fy=4.0, cx=2.0, cy=2.0)
    kw[name] = v
    _raises_named(lambda: jaxsh.PinholeCamera(width=4, height=4, cam_to_world=np.eye(4), **kw), name)


@given(NONFINITE)
def test_nonfinite_ortho_scale(v):
    _raises_named(lambda: jaxsh.OrthographicCamera(v, 4, 4, np.eye(4)), "scale")


@given(NONFINITE, st.sampled_from(["eye", "target", "up"]), st.integers(0, 2))
def test_nonfinite_look_at(v, name, k):
    kw = dict(eye=[0.0, 0.0, 5.0], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    kw[name] = list(kw[name])
    kw[name][k] = v
    _raises_named(lambda: jaxsh.look_at(**kw), name)


def test_look_at_zero_up():
    _raises_named(lambda: jaxsh.look_at([0.0, 0, 5], [0.0, 0, 0], [0.0, 0, 0]), "up")


@given(NONFINITE, st.integers(0, 2))
def test_nonfinite_sphere_center_and_radius(v, k):
    cam = _cam_ortho()
    c = np.zeros(3)
    c[k] = v
    _raises_named(lambda: jaxsh.sphere_gbuffer(cam, c, 0.2), "center")
    _raises_named(lambda: jaxsh.sphere_gbuffer(cam, np.zeros(3), abs(v)), "radius")


def test_nonfinite_traced_camera_and_sphere():
    cam = _cam_ortho()
    _raises_named_jit(lambda: jax.jit(lambda c: jaxsh.sphere_gbuffer(cam, c, 0.2).mask)(jnp.array([jnp.nan, 0.0, 0.0])), "center")
    _raises_named_jit(lambda: jax.jit(lambda r: jaxsh.sphere_gbuffer(cam, jnp.zeros(3), r).mask)(jnp.inf), "radius")
    bad = jnp.eye(4).at[0, 3].set(jnp.nan)
    _raises_named_jit(lambda: jax.jit(lambda m: jaxsh.camera_rays(jaxsh.OrthographicCamera(0.1, 4, 4, m))[1])(bad), "cam_to_world")
    _raises_named_jit(lambda: jax.jit(lambda f: jaxsh.camera_rays(jaxsh.PinholeCamera(f, 4.0, 2.0, 2.0, 4, 4, jnp.eye(4)))[1])(jnp.nan), "fx")


@given(NONFINITE, st.integers(0, 11), st.integers(0, 2))
def test_nonfinite_mesh_vertices(v, i, k):
    mesh = trimesh.creation.icosahedron()
    verts = np.array(mesh.vertices)
    verts[i, k] = v
    bad = trimesh.Trimesh(vertices=verts, faces=mesh.faces, process=False)
    _raises_named(lambda: jaxsh.mesh_gbuffer(_cam_ortho(), bad, engine="numpy"), "mesh", "non-finite")


@given(NONFINITE, st.integers(0, 5), st.integers(0, 5), st.integers(0, 2))
def test_nonfinite_normal_map(v, i, j, k):
    n = np.zeros((6, 6, 3))
    n[..., 2] = 1.0
    n[i, j, k] = v
    _raises_named(lambda: jaxsh.normal_map_gbuffer(_cam_ortho(), n), "normals")


@given(NONFINITE, st.integers(0, 2))
def test_nonfinite_directions_are_errors(v, k):
    """Direction inputs are normalized; a non-finite one has no direction: a named ValueError."""
    d = np.array([[0.0, 0.0, 1.0], [0.3, 0.4, 0.5]])
    d[1, k] = v
    _raises_named(lambda: jaxsh.real_sh(d, 2), "dirs")
    _raises_named(lambda: jaxsh.irradiance(np.ones(9), d), "normals")
    _raises_named(lambda: jaxsh.directional_light_sh(d, np.ones(2), 2), "directions")
    _raises_named(lambda: jaxsh.disk_light_sh(d[1], 0.3, 1.0, 2), "direction")
    _raises_named(lambda: jaxsh.fit_sh(d, np.ones(2), 1), "dirs")


def test_zero_directions_are_errors():
    z = np.zeros((1, 3))
    _raises_named(lambda: jaxsh.real_sh(z, 2), "dirs", "zero-length")
    _raises_named(lambda: jaxsh.directional_light_sh(z, np.ones(1), 2), "directions")
    _raises_named(lambda: jaxsh.irradiance(np.ones(9), z), "normals")


@given(st.integers(0, 8), st.integers(0, 2))
def test_nan_data_propagates_in_pure_kernels(i, c):
    """Documented: NaN in the data of a pure array kernel gives NaN exactly where it acts, finite elsewhere."""
    coeffs = np.ones((9, 3))
    coeffs[i, c] = np.nan
    # convolve is diagonal: only that entry is NaN
    out = np.asarray(jaxsh.convolve(coeffs, jaxsh.lambertian_spectrum(2)))
    assert np.isnan(out[i, c]) and np.isfinite(np.delete(out.reshape(-1), i * 3 + c)).all()
    # rotate_sh mixes within the band of degree l = floor(sqrt(i)) and that channel only
    l = math.isqrt(i)
    rot = np.asarray(jaxsh.rotate_sh(coeffs, _rotation(i)))
    band = slice(l * l, (l + 1) ** 2)
    assert np.isnan(rot[band, c]).any()
    mask = np.ones_like(rot, dtype=bool)
    mask[band, c] = False
    assert np.isfinite(rot[mask]).all()
    # filtering a NaN lighting coefficient by a valid σ
    f = np.asarray(jaxsh.filter_lighting_microfacet(coeffs, 0.3))
    assert np.isnan(f[i, c]) and np.isfinite(f[:, [k for k in range(3) if k != c]]).all()


def test_nan_image_and_parameter_propagate():
    img = np.ones((6, 12))
    img[2, 3] = np.nan
    assert np.isnan(np.asarray(jaxsh.project_latlong(img, 2))).all()  # every coefficient integrates that pixel
    assert np.isnan(np.asarray(jaxsh.microfacet_spectrum(np.nan, 3))[1:]).all()
    assert np.isnan(np.asarray(jaxsh.phong_spectrum(np.nan, 3))).all()


# =========================================================================== out-of-range parameters

NONPOS = st.floats(max_value=0.0, allow_nan=False, allow_infinity=True)


@given(NONPOS)
def test_sigma_nonpositive(sigma):
    _raises_named(lambda: jaxsh.microfacet_spectrum(sigma, 4), "sigma", "(0, inf)")
    _raises_named(lambda: jaxsh.filter_lighting_microfacet(np.ones((9, 3)), sigma), "sigma")
    _raises_named(lambda: jaxsh.torrance_sparrow_spectrum(sigma, 4, n_theta=8, n_phi=8), "sigma")


def test_sigma_negative_is_not_its_absolute_value():
    """σ = −0.2 used to equal σ = 0.2 silently."""
    _raises_named(lambda: jaxsh.microfacet_spectrum(-0.2, 4), "sigma", "-0.2")
    np.testing.assert_allclose(jaxsh.microfacet_spectrum(0.2, 2), np.exp(-((0.2 * np.arange(3)) ** 2)), rtol=1e-14)


@given(st.floats(min_value=-10.0, max_value=0.0))
def test_sigma_nonpositive_under_jit(sigma):
    _raises_named_jit(lambda: jax.jit(lambda s: jaxsh.microfacet_spectrum(s, 4))(sigma), "sigma")
    _raises_named_jit(lambda: jax.jit(lambda s: jaxsh.filter_lighting_microfacet(jnp.ones((9, 3)), s))(sigma), "sigma")


@given(st.floats(max_value=-1.0, allow_nan=False, allow_infinity=True))
def test_phong_exponent(s):
    _raises_named(lambda: jaxsh.phong_spectrum(s, 4), "`s`", "> -1")
    _raises_named(lambda: jaxsh.phong_spectrum_gaussian(s, 4), "`s`")
    _raises_named_jit(lambda: jax.jit(lambda x: jaxsh.phong_spectrum(x, 4))(max(s, -1e6)), "`s`")


def test_phong_gaussian_zero():
    _raises_named(lambda: jaxsh.phong_spectrum_gaussian(0.0, 4), "`s`", "> 0")
    _raises_named(lambda: jaxsh.phong_spectrum(math.inf, 4), "`s`")


@given(st.one_of(st.floats(max_value=-1e-6), st.floats(min_value=math.pi / 2, allow_infinity=False)))
def test_torrance_sparrow_theta_o(theta_o):
    _raises_named(lambda: jaxsh.torrance_sparrow_spectrum(0.2, 4, theta_o, n_theta=8, n_phi=8), "theta_o")


@given(st.floats(max_value=1.0, exclude_max=True, allow_nan=False))
def test_torrance_sparrow_mu(mu):
    _raises_named(lambda: jaxsh.torrance_sparrow_spectrum(0.2, 4, 0.1, mu, n_theta=8, n_phi=8), "mu")


@given(st.one_of(NONPOS, st.floats(min_value=math.pi, exclude_min=True)))
def test_disk_radius(r):
    _raises_named(lambda: jaxsh.disk_light_sh([0.0, 0.0, 1.0], r, 1.0, 3), "angular_radius", "(0, pi]")
    _raises_named(lambda: jaxsh.disk_energy(r, 1.0), "angular_radius")


def test_disk_radius_pi_is_the_whole_sphere():
    """r = π is valid: a uniform sphere of radiance 2 has only L_00 = 2 sqrt(4π)."""
    c = np.asarray(jaxsh.disk_light_sh([0.0, 0.0, 1.0], math.pi, 2.0, 3))
    np.testing.assert_allclose(c[0], 2.0 * math.sqrt(4 * math.pi), rtol=1e-14)
    np.testing.assert_allclose(c[1:], 0.0, atol=1e-13)


@given(st.floats(max_value=-1e-300, allow_infinity=True), st.integers(0, 2))
def test_negative_energy_and_radiance(v, c):
    e = np.ones((2, 3))
    e[1, c] = v
    d = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    _raises_named(lambda: jaxsh.directional_light_sh(d, e, 2), "energy", ">= 0")
    _raises_named(lambda: jaxsh.disk_light_sh(d[0], 0.3, e[1], 2), "radiance", ">= 0")
    _raises_named_jit(lambda: jax.jit(lambda x: jaxsh.directional_light_sh(jnp.asarray(d), x, 2))(jnp.asarray(np.maximum(e, -1e300))), "energy")
    _raises_named_jit(lambda: jax.jit(lambda x: jaxsh.disk_light_sh(jnp.asarray(d[0]), x, 1.0, 2))(-0.5), "angular_radius")


@given(st.integers(-50, -1))
def test_negative_lmax(lmax):
    d = np.array([[0.0, 0.0, 1.0]])
    for fn in (
        lambda: jaxsh.real_sh(d, lmax),
        lambda: jaxsh.lambertian_spectrum(lmax),
        lambda: jaxsh.microfacet_spectrum(0.2, lmax),
        lambda: jaxsh.phong_spectrum(5.0, lmax),
        lambda: jaxsh.directional_light_sh(d, np.ones(1), lmax),
        lambda: jaxsh.disk_light_sh(d[0], 0.2, 1.0, lmax),
        lambda: jaxsh.project_latlong(np.ones((4, 8)), lmax),
        lambda: jaxsh.wigner_D(np.eye(3), lmax),
        lambda: jaxsh.fit_sh(d, np.ones(1), lmax),
    ):
        _raises_named(fn, "lmax")


@given(st.sampled_from(["fx", "fy"]), NONPOS)
def test_pinhole_focal_nonpositive(name, v):
    kw = dict(fx=4.0, fy=4.0)
    kw[name] = v
    _raises_named(lambda: jaxsh.PinholeCamera(cx=2.0, cy=2.0, width=4, height=4, cam_to_world=np.eye(4), **kw), name)


@given(NONPOS)
def test_ortho_scale_nonpositive(v):
    _raises_named(lambda: jaxsh.OrthographicCamera(v, 4, 4, np.eye(4)), "scale")


@given(
    st.sampled_from(["width", "height"]),
    st.one_of(st.integers(-5, 0), st.floats(0.5, 100.0).filter(lambda x: x != int(x)), st.just(16.0), st.just(True), st.just("16")),
)
def test_image_size_not_positive_int(name, v):
    """16.7 is an error, not 16 (and so is 16.0: sizes are Python ints)."""
    kw = dict(width=4, height=4)
    kw[name] = v
    _raises_named(lambda: jaxsh.OrthographicCamera(0.1, cam_to_world=np.eye(4), **kw), name)
    _raises_named(lambda: jaxsh.PinholeCamera(4.0, 4.0, 2.0, 2.0, cam_to_world=np.eye(4), **kw), name)


@given(st.integers(0, 1000), st.floats(1e-5, 0.5), st.integers(0, 2), st.integers(0, 2))
def test_cam_to_world_not_a_rotation(seed, eps, i, j):
    m = _pose(seed)
    m[i, j] += eps  # tolerance 1e-6 in float64: 1e-5 is well outside
    _raises_named(lambda: jaxsh.OrthographicCamera(0.1, 4, 4, m), "cam_to_world", "rotation")


@given(st.integers(0, 1000))
def test_cam_to_world_reflection_and_scale(seed):
    m = _pose(seed)
    refl = m.copy()
    refl[:3, 0] *= -1  # orthonormal, det -1
    _raises_named(lambda: jaxsh.PinholeCamera(4.0, 4.0, 2.0, 2.0, 4, 4, refl), "cam_to_world", "det")
    scaled = m.copy()
    scaled[:3, :3] *= 2.0
    _raises_named(lambda: jaxsh.OrthographicCamera(0.1, 4, 4, scaled), "cam_to_world")
    # a valid pose within float rounding is accepted (no false alarms)
    jaxsh.OrthographicCamera(0.1, 4, 4, m)


@given(st.integers(0, 1000), st.integers(0, 3), st.floats(1e-3, 10.0))
def test_cam_to_world_last_row(seed, k, v):
    m = _pose(seed)
    m[3, k] += v
    _raises_named(lambda: jaxsh.OrthographicCamera(0.1, 4, 4, m), "cam_to_world", "last row")


def test_cam_to_world_float32_tolerance():
    """float32 poses are checked at 1e-4 (the rounding of a float32 rotation is ~1e-7)."""
    m = _pose(3).astype(np.float32)
    jaxsh.OrthographicCamera(np.float32(0.1), 4, 4, m)
    m[0, 0] += 1e-3
    _raises_named(lambda: jaxsh.OrthographicCamera(np.float32(0.1), 4, 4, m), "cam_to_world")


def test_traced_camera_checked_at_run_time():
    bad = jnp.asarray(np.diag([1.0, 1.0, 2.0, 1.0]))
    _raises_named_jit(lambda: jax.jit(lambda m: jaxsh.camera_rays(jaxsh.OrthographicCamera(0.1, 4, 4, m))[1])(bad), "cam_to_world")
    # the check survives when only the directions (which do not depend on `scale`) are used
    _raises_named_jit(lambda: jax.jit(lambda s: jaxsh.camera_rays(jaxsh.OrthographicCamera(s, 4, 4, jnp.eye(4)))[1])(-1.0), "scale")
    _raises_named_jit(lambda: jax.jit(lambda s: jaxsh.camera_rays(jaxsh.OrthographicCamera(s, 4, 4, jnp.eye(4)))[0])(jnp.nan), "scale")


@given(NONPOS)
def test_sphere_radius(r):
    _raises_named(lambda: jaxsh.sphere_gbuffer(_cam_ortho(), np.zeros(3), r), "radius")


@given(st.floats(2e-3, 0.5), st.integers(0, 5), st.integers(0, 5))
def test_normal_map_not_unit(dev, i, j):
    n = np.zeros((6, 6, 3))
    n[..., 2] = 1.0
    n[i, j] *= 1.0 + dev * 1.01
    cam = _cam_ortho()
    _raises_named(lambda: jaxsh.normal_map_gbuffer(cam, n), "normals", "norm")
    _raises_named_jit(lambda: jax.jit(lambda x: jaxsh.normal_map_gbuffer(cam, x).normal)(jnp.asarray(n)), "normals")
    _raises_named_jit(lambda: jax.jit(lambda x: jaxsh.normal_map_gbuffer(cam, x).mask)(jnp.asarray(n)), "normals")


# --------------------------------------------------------------------------- aliasing


@given(st.integers(1, 12), st.integers(1, 24), st.integers(0, 12))
def test_project_latlong_aliasing(h, w, lmax):
    img = np.ones((h, w))
    if 2 * lmax >= h or 2 * lmax >= w:
        _raises_named(lambda: jaxsh.project_latlong(img, lmax), "lmax", f"{h}x{w}", "allow_aliasing")
        out = np.asarray(jaxsh.project_latlong(img, lmax, allow_aliasing=True))
        assert np.isfinite(out).all()
    else:
        # resolved: a constant map has only c_00 = sqrt(4 pi)
        c = np.asarray(jaxsh.project_latlong(img, lmax))
        np.testing.assert_allclose(c[0], math.sqrt(4 * math.pi), rtol=1e-12)
        np.testing.assert_allclose(c[1:], 0.0, atol=1e-12)


def test_project_latlong_aliasing_is_real():
    """Why it is an error: the aliased sums of a constant map are far from its coefficients (0 for l > 0)."""
    c = np.asarray(jaxsh.project_latlong(np.ones((4, 8)), 8, allow_aliasing=True))
    assert np.abs(c[1:]).max() > 4.0  # measured 4.38 (issue 12: "up to 4.4")
    c = np.asarray(jaxsh.project_latlong(np.ones((8, 16)), 8, allow_aliasing=True))
    assert np.abs(c[1:]).max() > 0.05  # measured 0.091 at lmax = H/2
    _raises_named(lambda: jaxsh.project_latlong(np.ones((8, 16)), 8, allow_aliasing=1), "allow_aliasing")


# =========================================================================== shape mismatch


@given(st.integers(1, 4), st.integers(1, 4))
def test_shape_mismatches(j, extra):
    d = np.tile([[0.0, 0.0, 1.0]], (j, 1))
    _raises_named(lambda: jaxsh.directional_light_sh(d, np.ones(j + extra), 2), "energy", f"({j},)")
    _raises_named(lambda: jaxsh.fit_sh(d, np.ones(j + extra), 1), "values")
    _raises_named(lambda: jaxsh.fit_sh(d, np.ones(j), 1, weights=np.ones(j + extra)), "weights")
    _raises_named(lambda: jaxsh.disk_light_sh(np.ones(3 + extra), 0.2, 1.0, 2), "direction")
    _raises_named(lambda: jaxsh.disk_light_sh([0.0, 0, 1], np.full(extra + 1, 0.2), 1.0, 2), "angular_radius")
    _raises_named(lambda: jaxsh.disk_light_sh([0.0, 0, 1], 0.2, np.ones((extra, 3)), 2), "radiance")
    _raises_named(lambda: jaxsh.convolve(np.ones((9, 3)), np.ones(2)), "`A`", "lmax + 1")
    _raises_named(lambda: jaxsh.rotate_sh(np.ones(9), np.ones((3, 3 + extra))), "`R`", "(..., 3, 3)")
    _raises_named(lambda: jaxsh.irradiance(np.ones(9), np.ones((j, 2))), "normals", "(..., 3)")
    _raises_named(lambda: jaxsh.filter_lighting_microfacet(np.ones((8, 3)), 0.2), "coeffs")
    _raises_named(lambda: jaxsh.sphere_gbuffer(_cam_ortho(), np.zeros(2 + 2 * extra), 0.2), "center")
    _raises_named(lambda: jaxsh.torrance_sparrow_spectrum(np.full(extra + 1, 0.2), 2), "sigma", "scalar")


@given(st.integers(1, 8), st.integers(1, 8))
def test_normal_map_shape_must_match_camera(h, w):
    cam = _cam_ortho(6)
    n = np.zeros((h, w, 3))
    if (h, w) == (6, 6):
        n = np.zeros((h, w, 2))
    _raises_named(lambda: jaxsh.normal_map_gbuffer(cam, n), "normals", "(6, 6, 3)")
    _raises_named(lambda: jaxsh.normal_map_gbuffer(cam, np.zeros((6, 6, 3)), mask=np.ones((h, w + 7), bool)), "mask", "(6, 6)")
    _raises_named(lambda: jaxsh.normal_map_gbuffer(cam, np.zeros((6, 6, 3)), mask=np.ones((6, 6))), "mask", "bool")


# =========================================================================== dtypes


HALF = st.sampled_from([jnp.float16, jnp.bfloat16])


@given(HALF)
def test_half_precision_rejected(dt):
    name = jnp.dtype(dt).name
    d = jnp.asarray([[0.0, 0.0, 1.0]], dt)
    for fn, arg in (
        (lambda: jaxsh.real_sh(d, 2), "dirs"),
        (lambda: jaxsh.irradiance(np.ones(9), d), "normals"),
        (lambda: jaxsh.directional_light_sh(d, np.ones(1), 2), "directions"),
        (lambda: jaxsh.convolve(jnp.ones(9, dt), np.ones(3)), "coeffs"),
        (lambda: jaxsh.rotate_sh(np.ones(9), jnp.eye(3, dtype=dt)), "R"),
        (lambda: jaxsh.project_latlong(jnp.ones((4, 8), dt), 1), "image"),
        (lambda: jaxsh.synthesize_latlong(jnp.ones(4, dt), 4, 8), "coeffs"),
        (lambda: jaxsh.microfacet_spectrum(jnp.asarray(0.2, dt), 3), "sigma"),
        (lambda: jaxsh.phong_spectrum(jnp.asarray(5.0, dt), 3), "s"),
        (lambda: jaxsh.lambertian_spectrum(3, dtype=dt), "dtype"),
        (lambda: jaxsh.latlong_directions(4, 8, dtype=dt), "dtype"),
        (lambda: jaxsh.latlong_weights(4, 8, dtype=dt), "dtype"),
        (lambda: jaxsh.OrthographicCamera(0.1, 4, 4, jnp.eye(4, dtype=dt)), "cam_to_world"),
        (lambda: jaxsh.PinholeCamera(jnp.asarray(4.0, dt), 4.0, 2.0, 2.0, 4, 4, np.eye(4)), "fx"),
        (lambda: jaxsh.look_at(jnp.asarray([0.0, 0.0, 5.0], dt), [0.0, 0, 0]), "eye"),
        (lambda: jaxsh.sphere_gbuffer(_cam_ortho(), jnp.zeros(3, dt), 0.2), "center"),
        (lambda: jaxsh.normal_map_gbuffer(_cam_ortho(), jnp.zeros((6, 6, 3), dt)), "normals"),
    ):
        _raises_named(fn, f"`{arg}`", name, "float32 or float64")


@given(st.integers(0, 3))
def test_integer_inputs_are_converted(k):
    """Integer arrays go to the default float (float64 in the tests) and give the float result."""
    di = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [1, 1, 1]])[: k + 1]
    df = di.astype(np.float64)
    np.testing.assert_array_equal(jaxsh.real_sh(di, 3), jaxsh.real_sh(df, 3))
    assert jaxsh.real_sh(di, 3).dtype == jnp.float64
    np.testing.assert_array_equal(jaxsh.directional_light_sh(di, np.arange(1, k + 2), 2), jaxsh.directional_light_sh(df, np.arange(1.0, k + 2), 2))
    img = np.arange(8 * 16).reshape(8, 16)
    np.testing.assert_array_equal(jaxsh.project_latlong(img, 3), jaxsh.project_latlong(img.astype(np.float64), 3))
    np.testing.assert_array_equal(jaxsh.convolve(np.arange(9), np.arange(1, 4)), jaxsh.convolve(np.arange(9.0), np.arange(1.0, 4)))
    np.testing.assert_array_equal(jaxsh.microfacet_spectrum(1, 3), jaxsh.microfacet_spectrum(1.0, 3))
    cam_i = jaxsh.OrthographicCamera(1, 4, 4, np.eye(4, dtype=int))
    cam_f = jaxsh.OrthographicCamera(1.0, 4, 4, np.eye(4))
    np.testing.assert_array_equal(jaxsh.camera_rays(cam_i)[0], jaxsh.camera_rays(cam_f)[0])


def test_complex_and_non_numeric_rejected():
    _raises_named(lambda: jaxsh.real_sh(np.array([[0, 0, 1j]]), 2), "dirs", "real")
    _raises_named(lambda: jaxsh.microfacet_spectrum(0.2 + 0j, 2), "sigma", "real")
    _raises_named(lambda: jaxsh.latlong_directions(4, 8, dtype=np.int32), "dtype")
    _raises_named(lambda: jaxsh.lambertian_spectrum(2, dtype="complex64"), "dtype")
    _raises_named(lambda: jaxsh.project_latlong(np.array([["a"]]), 0), "image")


@pytest.mark.parametrize("x64", [False, True])
def test_conversion_without_a_program(x64):
    """`as_float_array` (every public entry's conversion) gives what `jnp.asarray` + the float rule give — dtype,
    weak type, values, a copy — and compiles no XLA program for NumPy input of a new shape (`jnp.asarray` of a
    NumPy array compiles one per shape and dtype in jax 0.10)."""
    from jax import monitoring

    from jaxsh._checks import as_float_array

    compiles = []
    listener = lambda event, duration, **kw: compiles.append(event) if event == "/jax/core/compile/backend_compile_duration" else None  # noqa: E731
    monitoring.register_event_duration_secs_listener(listener)
    try:
        with jax.enable_x64(x64):
            jnp.zeros(1).block_until_ready()
            cases = [np.arange(6.0).reshape(2, 3) + 0.5, np.ones(3, np.float32), np.arange(4), np.array([True, False]),
                     np.float64(1.5), np.int32(3), 1.5, np.zeros((0, 3))]
            for k, x in enumerate(cases):
                compiles.clear()
                shape = (1000 + k, 3)  # NumPy arrays of shapes no program has seen yet
                fresh = np.resize(np.asarray(x), shape).astype(np.asarray(x).dtype) if np.size(x) else np.zeros(shape)
                got = as_float_array(fresh, "x")
                assert compiles == [], f"case {k}: {compiles}"
                want = jnp.asarray(fresh)
                want = want if jnp.issubdtype(want.dtype, jnp.floating) else want.astype(jnp.result_type(float))
                assert got.dtype == want.dtype and got.weak_type == want.weak_type and got.shape == want.shape
                np.testing.assert_array_equal(got, want)
                got0 = as_float_array(x, "x")
                want0 = jnp.asarray(x)
                want0 = want0 if jnp.issubdtype(want0.dtype, jnp.floating) else want0.astype(jnp.result_type(float))
                assert got0.dtype == want0.dtype and got0.weak_type == want0.weak_type
                np.testing.assert_array_equal(got0, want0)
            # the caller's array is copied, never aliased (`jax.device_put` alone aliased a NumPy buffer in about
            # two calls out of three here: a later write to it showed in the JAX array)
            for _ in range(20):
                for n in (3, 17, 64, 1000):
                    a = np.ones(n)
                    b = as_float_array(a, "x")
                    a[0] = 7.0
                    assert float(np.asarray(b)[0]) == 1.0
    finally:
        monitoring.unregister_event_duration_listener(listener)
