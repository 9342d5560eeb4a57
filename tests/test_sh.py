"""The SH basis: convention, accuracy against scipy, identities, gradients, errors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, strategies as st

import jaxsh

from .helpers import accelerator_branches, primitives, random_dirs, scipy_complex_sh, scipy_real_sh


# ---------------------------------------------------------------- indexing


def test_indexing_roundtrip():
    i = 0
    for l in range(12):
        for m in range(-l, l + 1):
            assert jaxsh.sh_index(l, m) == i
            assert jaxsh.sh_degree_order(i) == (l, m)
            i += 1
    assert jaxsh.num_coeffs(11) == i
    np.testing.assert_array_equal(jaxsh.sh_degrees(2), [0, 1, 1, 1, 2, 2, 2, 2, 2])
    np.testing.assert_array_equal(jaxsh.sh_orders(2), [0, -1, 0, 1, -2, -1, 0, 1, 2])


def test_sh_lambda_closed_form():
    lam = jaxsh.sh_lambda(3)
    np.testing.assert_allclose(lam, [np.sqrt(4 * np.pi), np.sqrt(4 * np.pi / 3), np.sqrt(4 * np.pi / 5), np.sqrt(4 * np.pi / 7)])


@pytest.mark.parametrize("bad", [-1, 1.5, "3", True, None])
def test_index_errors(bad):
    with pytest.raises(ValueError, match="lmax"):
        jaxsh.num_coeffs(bad)


def test_sh_index_bad_m():
    with pytest.raises(ValueError, match="m"):
        jaxsh.sh_index(2, 3)


# ---------------------------------------------------------------- convention


def test_real_convention_l1_pinned():
    """docs/conventions.md: Y_{1,-1} = +c y, Y_{1,0} = +c z, Y_{1,1} = +c x, c = sqrt(3/4pi)."""
    c = np.sqrt(3 / (4 * np.pi))
    for d in np.eye(3):
        y = np.asarray(jaxsh.real_sh(d, 1))
        np.testing.assert_allclose(y[0], 1 / np.sqrt(4 * np.pi), rtol=1e-14)
        np.testing.assert_allclose(y[1:], c * d[[1, 2, 0]], atol=1e-15)


def test_real_convention_l2_closed_forms(rng):
    """Classic closed forms of the irradiance literature (no sign flips)."""
    d = random_dirs(rng, (50,))
    x, y, z = d.T
    got = np.asarray(jaxsh.real_sh(d, 2))[:, 4:]
    k = 0.5 * np.sqrt(15 / np.pi)
    want = np.stack(
        [k * x * y, k * y * z, 0.25 * np.sqrt(5 / np.pi) * (3 * z * z - 1), k * x * z, 0.5 * k * (x * x - y * y)],
        -1,
    )
    np.testing.assert_allclose(got, want, atol=1e-14)


def test_complex_phase_is_condon_shortley():
    d = np.array([1.0, 0.0, 0.0])
    y = np.asarray(jaxsh.complex_sh(d, 1))
    # Y_1^1(theta=pi/2, phi=0) = -sqrt(3/8pi) with the CS phase.
    assert y[3].real == pytest.approx(-np.sqrt(3 / (8 * np.pi)), rel=1e-14)
    assert y[1].real == pytest.approx(np.sqrt(3 / (8 * np.pi)), rel=1e-14)


# ---------------------------------------------------------------- accuracy vs scipy


def _test_dirs(rng, n):
    d = random_dirs(rng, (n,))
    special = np.array(
        [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 1, 0], [1e-9, 0, 1], [0, 1e-12, -1], [1, 1, 1e-13]],
        dtype=np.float64,
    )
    special /= np.linalg.norm(special, axis=-1, keepdims=True)
    return np.concatenate([d, special])


@pytest.mark.parametrize("lmax", [0, 1, 2, 7, 20, 21, 45])
def test_real_sh_matches_scipy_f64(rng, lmax):
    d = _test_dirs(rng, 200)
    got = np.asarray(jaxsh.real_sh(d, lmax))
    assert got.dtype == np.float64
    np.testing.assert_allclose(got, scipy_real_sh(d, lmax), rtol=0, atol=1e-12)


def test_real_sh_matches_scipy_lmax100(rng):
    d = _test_dirs(rng, 60)
    got = np.asarray(jaxsh.real_sh(d, 100))
    np.testing.assert_allclose(got, scipy_real_sh(d, 100), rtol=0, atol=1e-12)


def test_complex_sh_matches_scipy(rng):
    d = _test_dirs(rng, 100)
    got = np.asarray(jaxsh.complex_sh(d, 12))
    assert got.dtype == np.complex128
    np.testing.assert_allclose(got, scipy_complex_sh(d, 12), rtol=0, atol=1e-12)


@pytest.mark.parametrize("lmax", [1, 2, 4, 12, 13, 16, 30])
def test_float32_accuracy(rng, lmax):
    """float32 stays within 1e-5 of the exact values at the float32 inputs up to l = 30, poles included."""
    t = np.linspace(0, 0.08, 300)
    ph = rng.uniform(0, 2 * np.pi, 300)
    pole = np.stack([np.sin(t) * np.cos(ph), np.sin(t) * np.sin(ph), np.cos(t)], -1)
    d32 = np.concatenate([_test_dirs(rng, 2000), pole, -pole]).astype(np.float32)
    got = jaxsh.real_sh(d32, lmax)
    assert got.dtype == jnp.float32
    ref = scipy_real_sh(d32.astype(np.float64), lmax)
    assert np.abs(np.asarray(got, np.float64) - ref).max() <= 1e-5
    gotc = jaxsh.complex_sh(d32, lmax)
    assert gotc.dtype == jnp.complex64


def test_float32_difference_form_is_needed(rng):
    """The plain float32 three-term recurrence in z misses 1e-5 near the poles at l = 30; the
    difference form in w = 1 - |z| that `real_sh` runs below float64 stays within 5e-6."""
    from jaxsh import _sh

    t = np.linspace(0, 0.05, 200)
    pole = np.stack([np.sin(t), 0 * t, np.cos(t)], -1).astype(np.float32)
    pole = np.concatenate([pole, -pole])
    ref = scipy_real_sh(pole.astype(np.float64), 30)
    u = _sh._unit_vectors(jnp.asarray(pole))
    plain30 = np.asarray(_sh._basis_scan(u[:, 0], u[:, 1], u[:, 2], 30).T, np.float64)
    feat = _sh._z_features(u)
    diff30 = np.asarray(_sh._basis_scan(feat[:, 0], feat[:, 1], (feat[:, 2], feat[:, 3]), 30).T, np.float64)
    assert np.abs(plain30 - ref).max() > 1e-5
    assert np.abs(diff30 - ref).max() < 5e-6
    assert np.abs(np.asarray(jaxsh.real_sh(pole, 30), np.float64) - ref).max() < 5e-6
    # the unrolled band path (lmax <= 20) too
    ref20 = scipy_real_sh(pole.astype(np.float64), 20)
    assert np.abs(np.asarray(jaxsh.real_sh(pole, 20), np.float64) - ref20).max() < 5e-6


def test_unnormalized_directions_are_normalized(rng):
    d = random_dirs(rng, (20,))
    scale = rng.uniform(0.1, 10, size=(20, 1))
    np.testing.assert_allclose(jaxsh.real_sh(d * scale, 6), jaxsh.real_sh(d, 6), atol=1e-13)


# ---------------------------------------------------------------- identities


def test_orthonormal_by_quadrature():
    """Gauss-Legendre x uniform-phi quadrature, exact for degree <= 2*lmax."""
    lmax = 12
    nt, nphi = lmax + 1, 2 * lmax + 2
    z, w = np.polynomial.legendre.leggauss(nt)
    phi = 2 * np.pi * np.arange(nphi) / nphi
    s = np.sqrt(1 - z * z)
    d = np.stack(np.broadcast_arrays(s[:, None] * np.cos(phi), s[:, None] * np.sin(phi), z[:, None]), -1)
    wt = (w[:, None] * np.full(nphi, 2 * np.pi / nphi)).reshape(-1)
    y = np.asarray(jaxsh.real_sh(d.reshape(-1, 3), lmax))
    gram = (y * wt[:, None]).T @ y
    np.testing.assert_allclose(gram, np.eye(jaxsh.num_coeffs(lmax)), atol=1e-12)
    yc = np.asarray(jaxsh.complex_sh(d.reshape(-1, 3), lmax))
    gramc = (np.conj(yc) * wt[:, None]).T @ yc
    np.testing.assert_allclose(gramc, np.eye(jaxsh.num_coeffs(lmax)), atol=1e-12)


@given(st.integers(0, 2**32 - 1))
def test_addition_theorem(seed):
    """sum_m Y_lm(a) Y_lm(b) = (2l+1)/(4 pi) P_l(a . b), band by band, l <= 40."""
    lmax = 40  # one compilation; every band 0..40 is checked
    rng = np.random.default_rng(seed)
    a, b = random_dirs(rng, (2,))
    ya = np.asarray(jaxsh.real_sh(a, lmax))
    yb = np.asarray(jaxsh.real_sh(b, lmax))
    ls = jaxsh.sh_degrees(lmax)
    lhs = np.bincount(ls, weights=ya * yb)
    from scipy.special import eval_legendre

    rhs = (2 * np.arange(lmax + 1) + 1) / (4 * np.pi) * eval_legendre(np.arange(lmax + 1), np.dot(a, b))
    np.testing.assert_allclose(lhs, rhs, atol=1e-12)


def test_real_complex_change_of_basis(rng):
    d = random_dirs(rng, (30,))
    u = jaxsh.real_to_complex_matrix(6)
    np.testing.assert_allclose(u @ u.conj().T, np.eye(49), atol=1e-15)
    yr = np.asarray(jaxsh.real_sh(d, 6))
    yc = np.asarray(jaxsh.complex_sh(d, 6))
    np.testing.assert_allclose(yr @ u.T, yc, atol=1e-13)


def test_parity(rng):
    """Y_lm(-w) = (-1)^l Y_lm(w)."""
    d = random_dirs(rng, (40,))
    ls = jaxsh.sh_degrees(15)
    np.testing.assert_allclose(jaxsh.real_sh(-d, 15), (-1.0) ** ls * np.asarray(jaxsh.real_sh(d, 15)), atol=1e-12)


# ---------------------------------------------------------------- batching, jit


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2), (0,)])
def test_batch_shapes(rng, shape):
    d = random_dirs(rng, shape) if shape != (0,) else np.zeros((0, 3))
    y = jaxsh.real_sh(d, 3)
    assert y.shape == shape + (16,)
    if d.size:
        flat = np.asarray(jaxsh.real_sh(d.reshape(-1, 3), 3))
        np.testing.assert_allclose(np.asarray(y).reshape(-1, 16), flat, atol=0)
    assert jaxsh.complex_sh(d, 3).shape == shape + (16,)


def test_vmap_and_jit_agree(rng):
    d = random_dirs(rng, (5, 3))
    f = jax.jit(jax.vmap(lambda v: jaxsh.real_sh(v, 5)))
    np.testing.assert_allclose(f(d), jaxsh.real_sh(d, 5), atol=1e-14)


def test_no_retrace_for_new_values(rng):
    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(d):
        return jaxsh.real_sh(d, 4)

    for _ in range(3):
        f(random_dirs(rng, (7,)))


def _per_lm_recurrence(x, y, z, lmax: int):
    """List of the (lmax+1)**2 real SH, in flat order, as arrays shaped like x: the recurrence of `jaxsh._sh`'s
    module docstring written out per (l, m) in Python, a reference for the library's vectorized forms."""
    from jaxsh import _sh

    diag = _sh._diag_constants(lmax)
    c = [jnp.ones_like(x)]
    s = [jnp.zeros_like(x)]
    for m in range(1, lmax + 1):
        c.append(x * c[m - 1] - y * s[m - 1])
        s.append(x * s[m - 1] + y * c[m - 1])
    # q[m] holds (q_{l-1}^m, q_{l-2}^m) as the loop over l proceeds.
    prev = {}
    out = []
    for l in range(lmax + 1):
        row = {}
        for m in range(l + 1):
            if m == l:
                q = float(diag[l] * (np.sqrt(2.0) if m > 0 else 1.0))
            elif m == l - 1:
                q = float(np.sqrt(2 * l + 1)) * z * prev[m][0]
            else:
                alm = float(np.sqrt((4.0 * l * l - 1.0) / (l * l - m * m)))
                blm = float(np.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0)))
                q = alm * (z * prev[m][0] - blm * prev[m][1])
            row[m] = q
        for m in range(l + 1):
            prev[m] = (row[m], prev[m][0] if m in prev else None)
        for m in range(-l, l + 1):
            q = row[abs(m)]
            if m == 0:
                out.append(q * c[0] if isinstance(q, float) else q)  # l = 0: a constant
            elif m > 0:
                out.append(q * c[m])
            else:
                out.append(q * s[-m])
    return out


def test_scan_and_unrolled_paths_agree(rng):
    from jaxsh import _sh

    d = jnp.asarray(random_dirs(rng, (64, 3)).reshape(-1, 3))
    a = jnp.stack(_per_lm_recurrence(d[:, 0], d[:, 1], d[:, 2], 12), -1)
    b = _sh._basis_scan(d[:, 0], d[:, 1], d[:, 2], 12).T
    np.testing.assert_allclose(a, b, atol=1e-14)
    # the rolled kernel of `real_sh` (signed-layout windows) against the per-(l, m) Python recurrence
    np.testing.assert_allclose(_sh._real_sh_flat(d, 12), a, atol=1e-14)
    # the closed-form polynomials of lmax <= 2 (`_basis_low`), both layouts
    for lmax in (0, 1, 2):
        n = (lmax + 1) ** 2
        np.testing.assert_allclose(_sh._basis_low(d, lmax), a[:, :n], rtol=0, atol=1e-15)
        np.testing.assert_allclose(_sh._basis_low(d, lmax, coeffs_first=True), a[:, :n].T, rtol=0, atol=1e-15)


@pytest.mark.parametrize("lmax", [0, 1, 2, 7, 16, 25])
@pytest.mark.parametrize("n", [0, 1, 17, 600])
def test_real_sh_chunks_and_layouts(rng, lmax, n):
    """Every chunking case of the kernel (none, one partial chunk, several with a shifted last one) and both
    layouts equal scipy; `coeffs_first` is the transpose, made in that layout."""
    from jaxsh import _sh

    chunk = _sh._chunk_size(lmax)
    assert 17 < chunk < 600  # so the sizes below cover: no point, one partial chunk, several chunks
    d = _test_dirs(rng, n)[-n:] if n else np.zeros((0, 3))  # the last n include the poles
    got = np.asarray(jaxsh.real_sh(d, lmax))
    assert got.shape == (n, (lmax + 1) ** 2)
    if n:
        np.testing.assert_allclose(got, scipy_real_sh(d, lmax), rtol=0, atol=1e-12)
    t = np.asarray(jaxsh.real_sh(d, lmax, coeffs_first=True))
    assert t.shape == ((lmax + 1) ** 2, n)
    np.testing.assert_array_equal(t, got.T)


@pytest.mark.parametrize("lmax", [0, 1, 2, 3])
@pytest.mark.parametrize("coeffs_first", [False, True])
def test_real_sh_low_degrees_written_out(lmax, coeffs_first):
    """At lmax <= 2 (every diffuse term's 9 harmonics) `real_sh` is written out (closed-form polynomials), a program
    without loops (less to compile in every program that holds it); from lmax 3 the rolled kernel. The
    values are checked against scipy by the tests above, for both paths."""
    from jaxsh import _sh

    d = jnp.ones((1000, 3))
    prims = primitives(jax.make_jaxpr(lambda v: _sh._real_sh_flat(v, lmax, coeffs_first))(d).jaxpr)
    assert bool(prims & {"while", "scan"}) == (lmax > _sh._UNROLLED_LMAX)


def test_real_sh_coeffs_first_batch_and_float32(rng):
    d = random_dirs(rng, (4, 5)).astype(np.float32)
    a = jaxsh.real_sh(d, 6)
    b = jaxsh.real_sh(d, 6, coeffs_first=True)
    assert a.shape == (4, 5, 49) and b.shape == (49, 4, 5) and b.dtype == jnp.float32
    np.testing.assert_array_equal(np.moveaxis(np.asarray(b), 0, -1), np.asarray(a))
    with pytest.raises(ValueError, match="coeffs_first"):
        jaxsh.real_sh(d, 6, coeffs_first="yes")


# ---------------------------------------------------------------- gradients


@pytest.mark.parametrize("lmax", [2, 3, 24])
def test_gradient_vs_finite_differences(rng, lmax):
    d = random_dirs(rng, (4,))
    w = rng.normal(size=jaxsh.num_coeffs(lmax))

    def f(v):
        return jnp.dot(jaxsh.real_sh(v, lmax), w)

    g = jax.vmap(jax.grad(f))(d)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (jax.vmap(f)(d + e) - jax.vmap(f)(d - e)) / (2 * h)
        np.testing.assert_allclose(g[:, k], fd, rtol=1e-6, atol=1e-6)
    # The direction is normalized inside: the gradient is tangential.
    np.testing.assert_allclose(np.sum(np.asarray(g) * d, -1), 0, atol=1e-10)
    jfwd = jax.jacfwd(f)(d[0])
    jrev = jax.jacrev(f)(d[0])
    np.testing.assert_allclose(jfwd, jrev, atol=1e-11)


@pytest.mark.parametrize("lmax", [2, 10])
def test_gradient_finite_at_poles(lmax):
    poles = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1e-300, 0.0, 1.0]])
    g = jax.jacrev(lambda v: jaxsh.real_sh(v, lmax))(poles)
    assert np.all(np.isfinite(np.asarray(g)))


# ---------------------------------------------------------------- errors


@pytest.mark.parametrize("shape", [(3, 2), (4,), ()])
def test_bad_dirs_shape(shape):
    with pytest.raises(ValueError, match=r"dirs.*\(\.\.\., 3\)"):
        jaxsh.real_sh(np.ones(shape), 2)


def test_negative_lmax():
    with pytest.raises(ValueError, match="lmax"):
        jaxsh.real_sh(np.ones(3), -1)
    with pytest.raises(ValueError, match="lmax"):
        jaxsh.complex_sh(np.ones(3), 2.5)


@pytest.mark.parametrize("bad", [[0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [np.inf, 0.0, 0.0], [0.0, 0.0, -np.inf],
                                 "huge"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_zero_or_nonfinite_direction_raises(bad, dtype):
    """Concrete input: a `ValueError` before anything runs, wherever the bad row is (one in 1,000; a "huge"
    direction, 1e200 in float64 and 1e20 in float32, squares to inf); traced input: the kernel's run-time error."""
    d = np.tile(np.array([0.3, -0.4, 0.5], dtype), (1000, 1))
    d[617] = [1e200 if dtype == np.float64 else 1e20, 0.0, 0.0] if bad == "huge" else bad
    with pytest.raises(ValueError, match="`dirs` contains a zero-length or non-finite direction"):
        jaxsh.real_sh(d, 2)
    with pytest.raises(ValueError, match="zero-length or non-finite"):
        jaxsh.real_sh(d[617], 5)  # a single direction, the loop path
    with pytest.raises(Exception, match="zero-length or non-finite"):
        jax.jit(lambda v: jaxsh.real_sh(v, 2))(d).block_until_ready()
    d[617] = [1e-3, 0.0, 0.0]  # short but non-zero: fine
    assert np.all(np.isfinite(np.asarray(jaxsh.real_sh(d, 2))))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_real_sh_accelerator_branch(monkeypatch, rng, dtype):
    """Off the CPU, `real_sh` runs its loop over l on all points at once instead of 128-point chunks (an H200
    took 2.5 s in chunks, 22 ms at once, at 10⁶ directions): the same values, checked here against scipy."""
    from jaxsh._sh import _real_sh_flat, _unit_vectors

    d = random_dirs(rng, (1000,))
    d[:2] = [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]
    d = d.astype(dtype)
    cpu = [np.asarray(jax.jit(lambda x: _real_sh_flat(_unit_vectors(x), 12, cf))(d)) for cf in (False, True)]
    accelerator_branches(monkeypatch)
    acc = [np.asarray(jax.jit(lambda x: _real_sh_flat(_unit_vectors(x), 12, cf))(d)) for cf in (False, True)]
    tol = 1e-14 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(acc[0], cpu[0], rtol=0, atol=tol)
    np.testing.assert_allclose(acc[1], acc[0].T, rtol=0, atol=0)
    np.testing.assert_allclose(acc[0], scipy_real_sh(d.astype(np.float64), 12), rtol=0,
                               atol=1e-12 if dtype == np.float64 else 3e-6)
