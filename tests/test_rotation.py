"""Wigner D matrices and rotation of SH expansions."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, strategies as st

import jaxsh

from .helpers import random_dirs, random_rotation


def _quadrature_D(R, lmax, real=True):
    """Independent reference: D[n, m] = int conj(Y_n(w)) Y_m(R^T w) dw by exact Gauss quadrature."""
    d, w = jaxsh.gauss_legendre_grid(lmax + 1, 2 * lmax + 2)
    d = np.asarray(d).reshape(-1, 3)
    w = np.asarray(w).reshape(-1)
    f = jaxsh.real_sh if real else jaxsh.complex_sh
    y = np.asarray(f(d, lmax))
    yr = np.asarray(f(d @ R, lmax))  # row k: R^T w_k
    return (np.conj(y) * w[:, None]).T @ yr


def _wigner_small_d_closed_form(l, mp, m, beta):
    """Wigner's explicit sum (Sakurai 3.8.33): d^l_{m' m}(beta)."""
    total = 0.0
    f = math.factorial
    for k in range(0, 2 * l + 1):
        a, b, c = l + m - k, k, l - k - mp
        dd = k - m + mp
        if min(a, b, c, dd) < 0:
            continue
        total += (
            (-1) ** (k - m + mp)
            * math.sqrt(f(l + m) * f(l - m) * f(l + mp) * f(l - mp))
            / (f(a) * f(b) * f(c) * f(dd))
            * math.cos(beta / 2) ** (2 * l - 2 * k + m - mp)
            * math.sin(beta / 2) ** (2 * k - m + mp)
        )
    return total


@pytest.mark.parametrize("real", [True, False])
def test_wigner_D_matches_quadrature(rng, real):
    R = random_rotation(rng)
    lmax = 7
    np.testing.assert_allclose(jaxsh.wigner_D(R, lmax, real=real), _quadrature_D(R, lmax, real), atol=1e-13)


def test_l1_block_is_permuted_rotation(rng):
    R = random_rotation(rng)
    D = np.asarray(jaxsh.wigner_D(R, 1))
    p = [1, 2, 0]  # m = -1, 0, 1 <-> y, z, x
    np.testing.assert_allclose(D[1:, 1:], R[np.ix_(p, p)], atol=1e-15)
    assert D[0, 0] == 1.0


@given(st.integers(0, 2**32 - 1))
def test_representation_property(seed):
    rng = np.random.default_rng(seed)
    r1, r2 = random_rotation(rng, (2,))
    lmax = 10
    d12 = np.asarray(jaxsh.wigner_D(r1 @ r2, lmax))
    np.testing.assert_allclose(d12, np.asarray(jaxsh.wigner_D(r1, lmax)) @ np.asarray(jaxsh.wigner_D(r2, lmax)), atol=1e-12)
    np.testing.assert_allclose(np.asarray(jaxsh.wigner_D(r1.T, lmax)), np.asarray(jaxsh.wigner_D(r1, lmax)).T, atol=1e-12)


@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 9]))
def test_rotate_then_synthesize(seed, lmax):
    """sum_i (D c)_i Y_i(w) = sum_i c_i Y_i(R^T w)."""
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    c = rng.normal(size=jaxsh.num_coeffs(lmax))
    w = random_dirs(rng, (20,))
    lhs = np.asarray(jaxsh.real_sh(w, lmax)) @ np.asarray(jaxsh.rotate_sh(c, R))
    rhs = np.asarray(jaxsh.real_sh(w @ R, lmax)) @ c
    np.testing.assert_allclose(lhs, rhs, atol=1e-11)


def test_orthogonality_high_degree(rng):
    R = random_rotation(rng)
    D = np.asarray(jaxsh.wigner_D(R, 64))
    assert np.abs(D @ D.T - np.eye(D.shape[0])).max() <= 1e-10


@pytest.mark.parametrize("beta", [0.0, 1e-9, 1e-5, np.pi - 1e-9, np.pi, np.pi / 2, 2.0])
def test_small_d_against_wigner_formula(beta):
    """Near beta = 0 and pi included: the recurrence has no Euler-angle singularity."""
    lmax = 6
    d = np.asarray(jaxsh.wigner_d_y(jnp.asarray(beta), lmax))
    for l in range(lmax + 1):
        for mp in range(-l, l + 1):
            for m in range(-l, l + 1):
                want = _wigner_small_d_closed_form(l, mp, m, beta)
                assert abs(d[l * l + l + mp, l * l + l + m] - want) < 1e-12


def test_complex_D_zyz_closed_form(rng):
    """D^l_{mm'}(R_z(a) R_y(b) R_z(g)) = e^{-i m a} d^l_{mm'}(b) e^{-i m' g}."""
    a, b, g = 0.7, 1.1, -2.3
    R = jaxsh.rotation_from_euler_zyz(a, b, g)
    D = np.asarray(jaxsh.wigner_D(R, 5, real=False))
    d = np.asarray(jaxsh.wigner_d_y(jnp.asarray(b), 5))
    m = jaxsh.sh_orders(5)
    want = np.exp(-1j * m * a)[:, None] * d * np.exp(-1j * m * g)[None, :]
    np.testing.assert_allclose(D, want, atol=1e-13)


def test_rh_eq6(rng):
    """R&H 2001 eq. 6: Y_lm(R_{a,b} w') = sum_m' D^l_{mm'}(a) e^{imb} Y_lm'(w'), R_{a,b} = Rz(b) Ry(a)."""
    alpha, beta = 0.9, 2.2
    R = np.asarray(jaxsh.rotation_from_euler_zyz(beta, alpha, 0.0))
    w = random_dirs(rng, (10,))
    lhs = np.asarray(jaxsh.complex_sh(w @ R.T, 4))
    d = np.asarray(jaxsh.wigner_d_y(jnp.asarray(alpha), 4))
    m = jaxsh.sh_orders(4)
    rhs = np.asarray(jaxsh.complex_sh(w, 4)) @ (d * np.exp(1j * m * beta)[:, None]).T
    np.testing.assert_allclose(lhs, rhs, atol=1e-13)


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_batch_shapes(rng, shape):
    R = random_rotation(rng, shape)
    D = jaxsh.wigner_D(R, 3)
    assert D.shape == shape + (16, 16)
    c = rng.normal(size=shape + (16, 3))
    out = jaxsh.rotate_sh(c, R)
    assert out.shape == shape + (16, 3)
    np.testing.assert_allclose(out, np.einsum("...ij,...jc->...ic", np.asarray(D), c), atol=1e-13)


def test_broadcasting_coeffs_and_rotations(rng):
    R = random_rotation(rng, (4,))
    c = rng.normal(size=(9, 3))
    out = jaxsh.rotate_sh(c, R)
    assert out.shape == (4, 9, 3)
    for k in range(4):
        np.testing.assert_allclose(out[k], np.asarray(jaxsh.wigner_D(R[k], 2)) @ c, atol=1e-14)
    c5 = rng.normal(size=(5, 1, 16))
    assert jaxsh.rotate_sh(c5, R, channels=False).shape == (5, 4, 16)


def test_float32(rng):
    R = random_rotation(rng).astype(np.float32)
    D = jaxsh.wigner_D(R, 20)
    assert D.dtype == jnp.float32
    assert np.abs(np.asarray(D, np.float64) @ np.asarray(D, np.float64).T - np.eye(441)).max() < 1e-4
    c = rng.normal(size=441).astype(np.float32)
    assert jaxsh.rotate_sh(c, R).dtype == jnp.float32


def test_gradient_wrt_rotation_angles(rng):
    """d/dangle of rotate_sh through R(angle), vs finite differences; forward = reverse."""
    c = jnp.asarray(rng.normal(size=25))

    def f(angles):
        R = jaxsh.rotation_from_euler_zyz(angles[0], angles[1], angles[2])
        return jaxsh.rotate_sh(c, R)

    x = jnp.array([0.3, 1e-7, -1.0])  # beta near 0 (Euler singularity of other methods)
    jf = jax.jacfwd(f)(x)
    jr = jax.jacrev(f)(x)
    np.testing.assert_allclose(jf, jr, atol=1e-12)
    h = 1e-6
    for k in range(3):
        e = jnp.zeros(3).at[k].set(h)
        np.testing.assert_allclose(jf[:, k], (f(x + e) - f(x - e)) / (2 * h), atol=1e-7)


def test_no_retrace_new_rotation(rng):
    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(c, R):
        return jaxsh.rotate_sh(c, R)

    c = jnp.asarray(rng.normal(size=16))
    for _ in range(3):
        f(c, jnp.asarray(random_rotation(rng)))


def test_errors(rng):
    R = random_rotation(rng)
    with pytest.raises(ValueError, match=r"R.*\(\.\.\., 3, 3\)"):
        jaxsh.wigner_D(np.eye(2), 2)
    with pytest.raises(ValueError, match="lmax"):
        jaxsh.wigner_D(R, -1)
    with pytest.raises(ValueError, match="coeffs"):
        jaxsh.rotate_sh(np.ones(8), R)
    with pytest.raises(ValueError, match="channels="):
        jaxsh.rotate_sh(np.ones((9, 1)), R)
    with pytest.raises(ValueError, match="do not broadcast"):
        jaxsh.rotate_sh(np.ones((2, 9, 3)), random_rotation(rng, (3,)))
    with pytest.raises(ValueError, match="real"):
        jaxsh.wigner_D(R, 2, real="yes")


# ---------------------------------------------------------------------------
# rotate_sh (fixed J = D(R_y(pi/2)) tables, Euler angles read from R)
# ---------------------------------------------------------------------------

_GIMBAL_BETAS = [0.0, 1e-9, -1e-9, 1e-7, np.pi - 1e-9, np.pi, np.pi + 1e-9]


def _rot_axis_angle(axis, t):
    """Rodrigues' formula, NumPy float64: rotation by t about the unit `axis`."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(t) * k + (1.0 - np.cos(t)) * (k @ k)


@pytest.mark.parametrize("beta", _GIMBAL_BETAS)
def test_rotate_sh_gimbal_lock_sampled(rng, beta):
    """Near and at beta = 0, pi (Euler gimbal lock), lmax 32: Y(w) . rotate_sh(c, R) = Y(R^T w) . c.

    Independent of any Wigner matrix: both sides are the real SH basis at random points.
    Measured error ~6e-13 on values ~30 for every beta; the bound is 4e-12.
    """
    lmax = 32
    R = np.asarray(jaxsh.rotation_from_euler_zyz(0.7, beta, -2.1))
    c = rng.normal(size=jaxsh.num_coeffs(lmax))
    w = random_dirs(rng, (64,))
    lhs = np.asarray(jaxsh.real_sh(w, lmax)) @ np.asarray(jaxsh.rotate_sh(c, R))
    rhs = np.asarray(jaxsh.real_sh(w @ R, lmax)) @ c
    np.testing.assert_allclose(lhs, rhs, atol=4e-12)


@pytest.mark.parametrize("beta", _GIMBAL_BETAS)
def test_rotate_sh_gimbal_lock_small_d(beta):
    """Against Wigner's explicit small-d and the ZYZ closed form, near/at gimbal lock, lmax 6."""
    lmax = 6
    a, g = 1.3, -0.4
    R = np.asarray(jaxsh.rotation_from_euler_zyz(a, beta, g))
    m = jaxsh.sh_orders(lmax)
    dc = np.zeros((jaxsh.num_coeffs(lmax),) * 2, complex)
    for l in range(lmax + 1):
        for mp in range(-l, l + 1):
            for mm in range(-l, l + 1):
                dc[l * l + l + mp, l * l + l + mm] = _wigner_small_d_closed_form(l, mp, mm, beta)
    Dc = np.exp(-1j * m * a)[:, None] * dc * np.exp(-1j * m * g)[None, :]
    u = jaxsh.real_to_complex_matrix(lmax)
    Dr = np.real(u.T @ Dc @ np.conj(u))  # real basis: c_real = U^T a, a = conj(U) c_real
    eye = np.eye(jaxsh.num_coeffs(lmax))
    np.testing.assert_allclose(np.asarray(jaxsh.rotate_sh(eye, R, channels=True)), Dr, atol=1e-13)


def test_rotate_sh_gimbal_lock_not_from_euler(rng):
    """Matrices near gimbal lock built without Euler angles: R0 exp(t K) for tiny t about a tilted axis."""
    lmax = 16
    c = rng.normal(size=(jaxsh.num_coeffs(lmax), 2))
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    for r0 in (np.eye(3), np.diag([1.0, -1.0, -1.0])):  # beta = 0 and beta = pi
        for t in (0.0, 1e-12, 1e-9, 1e-6):
            R = r0 @ _rot_axis_angle(axis, t)
            want = np.asarray(jaxsh.wigner_D(R, lmax)) @ c
            np.testing.assert_allclose(np.asarray(jaxsh.rotate_sh(c, R)), want, atol=1e-12)


@pytest.mark.parametrize("lmax", [0, 1, 2, 3, 5, 16, 32])
def test_rotate_sh_matches_recursion(rng, lmax):
    """rotate_sh (J tables) against wigner_D (Ivanic-Ruedenberg recursion on R), batched."""
    R = random_rotation(rng, (3,))
    c = rng.normal(size=(3, jaxsh.num_coeffs(lmax), 2))
    want = np.einsum("nij,njc->nic", np.asarray(jaxsh.wigner_D(R, lmax)), c)
    np.testing.assert_allclose(np.asarray(jaxsh.rotate_sh(c, R, channels=True)), want, atol=1e-12)


@pytest.mark.parametrize("lmax", [64, 96])
def test_rotate_sh_high_degree_against_synthesis(rng, lmax):
    """rotate_sh at high degree against the synthesis at rotated directions, sum_i c_i Y_i(R^T w) by real_sh
    (no Wigner matrix involved). The J table from the generator (`_j_block`): measured 3e-14 (lmax 64) and
    1.5e-13 (96) relative to the largest value; from the recurrence at R_y(pi/2), as before, 9.5e-12 and 5.4e-9."""
    R = random_rotation(rng)
    c = rng.normal(size=jaxsh.num_coeffs(lmax))
    w = random_dirs(rng, (200,))
    lhs = np.asarray(jaxsh.real_sh(w, lmax)) @ np.asarray(jaxsh.rotate_sh(c, R))
    rhs = np.asarray(jaxsh.real_sh(w @ R, lmax)) @ c
    assert np.abs(lhs - rhs).max() < 1e-12 * np.abs(rhs).max()


def test_j_block_is_the_recurrence_at_low_degree():
    """The generator's J^l equals the Ivanic-Ruedenberg block at R_y(pi/2) where the recurrence is still exact to
    rounding, and is orthogonal with (J^l)^4 = I (R_y(2 pi) = 1) at every degree."""
    from jaxsh import _rotation

    ry = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    rec = _rotation._real_blocks_minor(ry[:, :, None], 16, xp=np)
    for l in range(17):
        np.testing.assert_allclose(_rotation._j_block(l), rec[l][:, :, 0], atol=1e-14)
    for l in (40, 100):
        j = _rotation._j_block(l)
        eye = np.eye(2 * l + 1)
        assert np.abs(j.T @ j - eye).max() < 1e-14
        assert np.abs(np.linalg.matrix_power(j, 4) - eye).max() < 1e-13


def test_rotate_sh_one_rotation_many_vectors(rng):
    """One R for a batch of coefficient vectors (the batch is folded into channels)."""
    R = random_rotation(rng)
    c = rng.normal(size=(5, 2, 25, 3))
    D = np.asarray(jaxsh.wigner_D(R, 4))
    np.testing.assert_allclose(np.asarray(jaxsh.rotate_sh(c, R)), np.einsum("ij,abjc->abic", D, c), atol=1e-13)
    np.testing.assert_allclose(np.asarray(jaxsh.rotate_sh(c, R[None, None])), np.einsum("ij,abjc->abic", D, c), atol=1e-13)


@pytest.mark.parametrize("lmax", [8, 32])
@pytest.mark.parametrize("beta", [None, 0.0, 1e-4, np.pi - 1e-4, np.pi])
def test_rotate_sh_float32_accuracy(rng, lmax, beta):
    """float32 in, float32 out; against float64 of the same (float32-rounded) inputs.

    Measured max error 3e-6 (lmax 8) to 1.2e-5 (lmax 32, beta near pi) for N(0,1)
    coefficients; the bound is 5e-5 (about 800 float32 eps).
    """
    R = random_rotation(rng) if beta is None else np.asarray(jaxsh.rotation_from_euler_zyz(0.7, beta, -2.1))
    R32 = R.astype(np.float32)
    c32 = rng.normal(size=jaxsh.num_coeffs(lmax)).astype(np.float32)
    out = jaxsh.rotate_sh(c32, R32)
    assert out.dtype == jnp.float32
    # float64 reference on the rounded matrix, re-orthogonalized (polar factor) so it is a rotation.
    u, _, vt = np.linalg.svd(R32.astype(np.float64))
    want = np.asarray(jaxsh.wigner_D(u @ vt, lmax)) @ c32.astype(np.float64)
    assert np.abs(np.asarray(out, np.float64) - want).max() < 5e-5


@pytest.mark.parametrize(
    "r0",
    [np.eye(3), np.diag([1.0, -1.0, -1.0]), jaxsh.rotation_from_euler_zyz(0.3, 1e-9, -1.0), None],
    ids=["identity", "beta=pi", "beta=1e-9", "random"],
)
def test_rotate_sh_gradient_at_gimbal_lock(rng, r0):
    """d/dt rotate_sh(c, R0 exp(t K)) at t = 0 for K = x, y, z and a tilted axis:
    jacfwd = jacrev = central finite differences, finite everywhere (also at R0 = I)."""
    lmax = 5
    r0 = random_rotation(rng) if r0 is None else np.asarray(r0)
    c = jnp.asarray(rng.normal(size=jaxsh.num_coeffs(lmax)))
    axes = np.concatenate([np.eye(3), np.array([[0.6, 0.0, 0.8]])])

    def f(t):
        Rs = [jnp.asarray(r0) @ (jnp.eye(3) + jnp.sin(t[i]) * _skew(a) + (1.0 - jnp.cos(t[i])) * _skew(a) @ _skew(a))
              for i, a in enumerate(axes)]
        return jnp.stack([jaxsh.rotate_sh(c, Ri) for Ri in Rs])

    t0 = jnp.zeros(4)
    jf = np.asarray(jax.jacfwd(f)(t0))
    jr = np.asarray(jax.jacrev(f)(t0))
    assert np.all(np.isfinite(jf)) and np.all(np.isfinite(jr))
    np.testing.assert_allclose(jf, jr, atol=1e-12)
    h = 1e-5
    for i in range(4):
        fd = np.asarray((f(t0.at[i].set(h)) - f(t0.at[i].set(-h))) / (2 * h))
        np.testing.assert_allclose(jf[:, :, i], fd, atol=1e-8)
    # and the derivative w.r.t. the coefficients is D itself
    jc = np.asarray(jax.jacfwd(lambda cc: jaxsh.rotate_sh(cc, jnp.asarray(r0)))(c))
    np.testing.assert_allclose(jc, np.asarray(jaxsh.wigner_D(r0, lmax)), atol=1e-13)


def _skew(a):
    return jnp.asarray([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
