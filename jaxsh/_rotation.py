"""Rotation of spherical-harmonic expansions: Wigner D matrices.

Convention (docs/conventions.md): rotations act on functions. For a rotation matrix
$R$ and $f = \\sum_i c_i Y_i$, `rotate_sh(c, R)` returns the coefficients of
$\\omega \\mapsto f(R^{\\mathsf T}\\omega)$, which is `wigner_D(R, lmax) @ c`;
equivalently $Y_i(R^{\\mathsf T}\\omega) = \\sum_j D_{ji}(R)\\,Y_j(\\omega)$.
It is a representation: $D(R_1R_2) = D(R_1)D(R_2)$, block-diagonal in $l$,
orthogonal (real basis) or unitary (complex basis). The $l = 1$ real block
is $R$ itself with rows and columns permuted to the order $(y, z, x)$ of
$m = -1, 0, 1$.

`wigner_D` builds the real blocks directly from the entries of $R$ by the
recurrence of Ivanic & Ruedenberg (1996, with the 1998 erratum): block
$l$ is a fixed linear combination of products of the $l = 1$ block with
block $l-1$. Everything is a polynomial in the entries of $R$ — no Euler
angles, so no singularity at β = 0 or π, and derivatives with respect to
$R$ are exact everywhere. Cost $O(l_{max}^3)$ per rotation, batched over any
leading shape of `R`. Accuracy (float64), measured as the largest
$|D^TD - I|$ over 6 random rotations: 8e-15 at $l_{max} = 16$, 3e-14 at
32, 2e-11 at 64 and 2e-8 at 96. The recurrence's rounding grows with $l$,
about tenfold every 10 degrees beyond 32.

`rotate_sh` never forms $D$. It factors the rotation with fixed tables
(the "J-matrix" method, as in SHTOOLS' `djpi2` + `SHRotateRealCoef`):
$D(R_z(\\alpha)R_y(\\beta)R_z(\\gamma)) = Z(\\alpha-\\tfrac\\pi2)\\,J^{\\mathsf T}\\,Z(\\beta)\\,J\\,Z(\\gamma+\\tfrac\\pi2)$,
with $J = D(R_y(\\pi/2))$ tabulated once per `lmax` (float64, NumPy, from the
recurrence above) and $Z(t) = D(R_z(t))$, which only mixes $c_{l,m}$ with
$c_{l,-m}$ by $\\cos mt$, $\\sin mt$. $J$ keeps cos-type ($m \\ge 0$) and
sin-type ($m < 0$) coefficients apart, so each step is one elementwise
product or one batched matrix product over the bands. The Euler angles are
read from $R$ without dividing by $\\sin\\beta$ (`_euler_zyz`), so β = 0, π
and their neighbourhoods are as accurate as anywhere else (float64 error
~1e-13 at $l_{max} = 32$). Derivatives with respect to $R$ do not go through
the angles: $D(R + dR) \\approx D(R)\\,(1 + \\sum_k \\omega_k G_k)$ with $\\omega$
the axial vector of $R^{\\mathsf T}dR$ and $G_k$ the fixed generators, which is
exact at every $R$ (gimbal lock included) for $dR$ tangent to the rotations.
Second derivatives are not: their tangent goes through the angles again, and
at β = 0 or π (the identity included) a Hessian of `rotate_sh` is NaN or
wrong (measured off by 4 at β = π). Use `wigner_D`, a polynomial in $R$, for
second-order derivatives there. The table $J$ is not taken from the
recurrence (whose rounding it inherited: 9.5e-12 at $l_{max} = 64$, 1.7e-10
at 80, 5.4e-9 at 96) but from its generator, by one eigendecomposition per
band (`_j_block`): against the synthesis $\\sum_i c_i Y_i(R^{\\mathsf T}\\omega)$ by
`real_sh`, relative to its largest value, `rotate_sh` is within 3e-14 at
$l_{max} = 64$, 2e-14 at 80 and 1.5e-13 at 96 (three random rotations each).

??? cite "References"
    Ivanic, J., Ruedenberg, K. (1996). Rotation matrices for real spherical
    harmonics. Direct determination by recursion. J. Phys. Chem. 100(15),
    6342–6347. doi:10.1021/jp953350u. Additions and corrections: J. Phys.
    Chem. A 102(45), 9099–9100 (1998). doi:10.1021/jp9833350
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Real

from ._compile import jit
from ._checks import as_float_array, check_lmax, coeff_layout
from ._indexing import real_to_complex_matrix

# Real SH order m = -1, 0, 1 is (y, z, x).
_PERM = np.array([1, 2, 0])


@functools.lru_cache(maxsize=None)
def _ir_tables(l: int):
    """Static index and coefficient tables of the Ivanic-Ruedenberg step to band l.

    Returns five (row index a, coefficient) pairs, one per term
    u·U, v·V (two parts), w·W (two parts), and the Q-matrix each term reads
    (0, +1 or -1). Rows a index block l-1 (offset by l-1); out-of-range rows
    carry a zero coefficient.
    """
    ms = np.arange(-l, l + 1)
    m = ms[:, None]
    n = ms[None, :]
    am = np.abs(m)
    d = (m == 0).astype(float)
    denom = np.where(np.abs(n) == l, 2.0 * l * (2 * l - 1), (l + n) * (l - n)).astype(float)
    u = np.sqrt(np.maximum((l + m) * (l - m), 0) / denom)
    v = 0.5 * np.sqrt((1 + d) * (l + am - 1) * (l + am) / denom) * (1 - 2 * d)
    w = -0.5 * np.sqrt(np.maximum((l - am - 1) * (l - am), 0) / denom) * (1 - d)
    mv = ms
    d1 = (mv == 1).astype(float)
    dm1 = (mv == -1).astype(float)
    # V = c1 * Q_{+1}[a1] + c2 * Q_{-1}[a2];  W = c3 * Q_{+1}[a3] + c4 * Q_{-1}[a4]
    a1 = np.where(mv == 0, 1, np.where(mv > 0, mv - 1, mv + 1))
    c1 = np.where(mv == 0, 1.0, np.where(mv > 0, np.sqrt(1 + d1), 1 - dm1))
    a2 = np.where(mv == 0, -1, np.where(mv > 0, -mv + 1, -mv - 1))
    c2 = np.where(mv == 0, 1.0, np.where(mv > 0, -(1 - d1), np.sqrt(1 + dm1)))
    a3 = np.where(mv > 0, mv + 1, mv - 1)
    c3 = np.where(mv == 0, 0.0, 1.0)
    a4 = np.where(mv > 0, -mv - 1, -mv + 1)
    c4 = np.where(mv == 0, 0.0, np.where(mv > 0, 1.0, -1.0))
    terms = []
    for q, a, coef in [
        (0, mv, u),
        (1, a1, v * c1[:, None]),
        (-1, a2, v * c2[:, None]),
        (1, a3, w * c3[:, None]),
        (-1, a4, w * c4[:, None]),
    ]:
        ok = np.abs(a) <= l - 1
        coef = np.where(ok[:, None], coef, 0.0)
        coef = np.where(np.isfinite(coef), coef, 0.0)
        if not np.any(coef):
            continue
        terms.append((q, np.clip(a, -(l - 1), l - 1) + (l - 1), coef))
    return terms


def _real_blocks_minor(r, lmax: int, xp=jnp) -> list:
    """Real Wigner blocks with the batch axes last: D^l of shape (2l+1, 2l+1, *batch).

    Batch-minor layout keeps every operation vectorized along the batch
    (the blocks themselves are tiny). `r` is (3, 3, *batch). `xp=np` runs the
    same recurrence in NumPy (float64, at trace time) for the fixed tables of
    `rotate_sh`.
    """
    batch = r.shape[2:]
    dtype = r.dtype
    trail = (1,) * len(batch)
    blocks = [xp.ones((1, 1) + batch, dtype)]
    if lmax == 0:
        return blocks
    r1 = r[_PERM[:, None], _PERM[None, :]]
    blocks.append(r1)
    prev = r1
    for l in range(2, lmax + 1):
        qs = {}
        first = prev[:, :1]
        last = prev[:, -1:]
        for i in (-1, 0, 1):
            rm, r0, rp = r1[i + 1, 0][None, None], r1[i + 1, 1][None, None], r1[i + 1, 2][None, None]
            col_pos = rp * last - rm * first
            col_neg = rp * first + rm * last
            qs[i] = xp.concatenate([col_neg, r0 * prev, col_pos], axis=1)  # (2l-1, 2l+1, *batch)
        out = None
        for q, rows, coef in _ir_tables(l):
            term = qs[q][rows] * xp.asarray(coef, dtype).reshape(coef.shape + trail)
            out = term if out is None else out + term
        blocks.append(out)
        prev = out
    return blocks


def _to_minor(r):
    return jnp.moveaxis(r, (-2, -1), (0, 1))


def _real_blocks(r, lmax: int) -> list:
    """Real Wigner blocks D^l, l = 0..lmax, each (..., 2l+1, 2l+1), for rotation matrices r."""
    return [jnp.moveaxis(b, (0, 1), (-2, -1)) for b in _real_blocks_minor(_to_minor(r), lmax)]


def _check_rotation(r, name="R"):
    r = as_float_array(r, name)
    if r.ndim < 2 or r.shape[-2:] != (3, 3):
        raise ValueError(f"`{name}` must have shape (..., 3, 3), got {tuple(r.shape)}")
    return r


def _block_diag(blocks, dtype):
    batch = blocks[0].shape[:-2]
    n = sum(b.shape[-1] for b in blocks)
    out = jnp.zeros(batch + (n, n), dtype)
    s = 0
    for b in blocks:
        k = b.shape[-1]
        out = out.at[..., s : s + k, s : s + k].set(b)
        s += k
    return out


def _complex_blocks(blocks):
    out = []
    for l, b in enumerate(blocks):
        u = real_to_complex_matrix(l)[l * l :, l * l :]
        cdt = jnp.complex128 if b.dtype == jnp.float64 else jnp.complex64
        uc = jnp.asarray(np.conj(u), cdt)
        ut = jnp.asarray(u.T, cdt)
        out.append(jnp.matmul(jnp.matmul(uc, b.astype(cdt)), ut))
    return out


def wigner_D(
    R: Real[ArrayLike, "*batch 3 3"], lmax: int, real: bool = True
) -> Float[Array, "*batch n_coeffs n_coeffs"] | Complex[Array, "*batch n_coeffs n_coeffs"]:
    """Block-diagonal Wigner D matrix of a rotation, in the real or complex SH basis.

    `wigner_D(R, lmax) @ c` are the coefficients of $f(R^{\\mathsf T}\\omega)$
    (see the module docstring for the convention and the algorithm). In the
    complex basis (`real=False`) $D^{\\mathbb C} = \\bar U D^{\\mathbb R} U^{\\mathsf T}$
    with $U$ = `real_to_complex_matrix`; for $R = R_z(\\alpha)R_y(\\beta)R_z(\\gamma)$
    its blocks are $D^l_{mm'} = e^{-im\\alpha}\\,d^l_{mm'}(\\beta)\\,e^{-im'\\gamma}$
    with the real Wigner small-d matrix (`wigner_d_y`).

    **Arguments:**

    - `R`: rotation matrices, shape `(..., 3, 3)` (traced; differentiable).
      `R` must be orthogonal with determinant +1: the recurrence does not
      check it (use `rotation_from_euler_zyz` or your own).
    - `lmax`: band limit (static int).
    - `real`: real basis (default) or complex basis.

    **Returns:** `(..., (lmax+1)**2, (lmax+1)**2)`, float (real) or complex.

    Comparable to `e3nn_jax.so3.wigner_D` (other axis convention) and to
    `pyshtools.rotate.djpi2` + `SHRotateRealCoef`.
    """
    R = _check_rotation(R)
    lmax = check_lmax(lmax)
    if not isinstance(real, bool):
        raise ValueError(f"`real` must be a bool, got {real!r}")
    return _wigner_D(R, lmax, real)


@jit
def _wigner_D(R, lmax, real):
    blocks = _real_blocks(R, lmax)
    if real:
        return _block_diag(blocks, R.dtype)
    cb = _complex_blocks(blocks)
    return _block_diag(cb, cb[0].dtype)


def wigner_D_blocks(R: Real[ArrayLike, "*batch 3 3"], lmax: int, real: bool = True) -> list:
    """The diagonal blocks $D^l(R)$ of `wigner_D`, as a list of `(..., 2l+1, 2l+1)` arrays."""
    R = _check_rotation(R)
    lmax = check_lmax(lmax)
    blocks = _real_blocks(R, lmax)
    return blocks if real else _complex_blocks(blocks)


def rotate_sh(
    coeffs: Real[ArrayLike, "..."], R: Real[ArrayLike, "... 3 3"], channels: bool | None = None
) -> Float[Array, "..."]:
    """Rotate a real SH expansion: the coefficients of $f(R^{\\mathsf T}\\omega)$.

    Equal to `wigner_D(R, lmax) @ coeffs`; the matrix is never formed. The
    rotation is applied as $Z(\\alpha-\\tfrac\\pi2)\\,J^{\\mathsf T}Z(\\beta)\\,J\\,Z(\\gamma+\\tfrac\\pi2)$
    with fixed per-band tables $J = D(R_y(\\pi/2))$ and the ZYZ angles of `R`
    read without dividing by $\\sin\\beta$ (module docstring): $O(l_{max}^3)$
    per rotation as batched matrix products, accurate at and near β = 0, π.
    Batch dimensions of `coeffs` and `R` broadcast; one `R` for many vectors
    costs one rotation with many channels.

    Derivatives: exact with respect to `coeffs`; with respect to `R`, along
    the rotations, $\\partial_t D(R e^{t\\Omega}) = D(R)\\sum_k\\omega_k G_k$, at
    every `R` (the identity and β = π included). A component of a tangent
    `dR` that leaves the rotations (the symmetric part of $R^{\\mathsf T}dR$) is
    ignored, so a gradient with respect to a raw `R` is the one of $D$
    restricted to SO(3); `wigner_D` differentiates its polynomial in `R` instead.

    **Arguments:**

    - `coeffs`: `(..., n_coeffs)` (one channel) or `(..., n_coeffs, C)`
      (channels last), n_coeffs = (lmax+1)².
    - `R`: rotation matrices `(..., 3, 3)`.
    - `channels`: `None` infers the layout from the shape and raises on an
      ambiguous one such as `(9, 1)`; `True`/`False` force it.

    **Returns:** rotated coefficients, the shape of `coeffs` broadcast with
    the batch shape of `R`. NaN in, NaN out (a pure array kernel; `R` is not
    checked for orthogonality, see `wigner_D`).
    """
    coeffs = as_float_array(coeffs, "coeffs")
    R = _check_rotation(R)
    lmax, axis = coeff_layout(coeffs.shape, "coeffs", channels)
    c = coeffs if axis == -2 else coeffs[..., None]
    try:
        batch = jnp.broadcast_shapes(c.shape[:-2], R.shape[:-2])
    except ValueError:
        raise ValueError(
            f"batch shapes of `coeffs` {tuple(c.shape[:-2])} and `R` {tuple(R.shape[:-2])} do not broadcast"
        ) from None
    dtype = jnp.result_type(c.dtype, R.dtype)
    out = _rotate(c.astype(dtype), R.astype(dtype), lmax, batch)
    return out if axis == -2 else out[..., 0]


@jit
def _rotate(c, R, lmax, batch):
    # c (..., n, C), R (..., 3, 3); flattened to (N, n, C) and (N, 3, 3).
    n, C = c.shape[-2:]
    if lmax == 0:
        return jnp.broadcast_to(c, batch + (n, C))
    if math.prod(batch) == 0:  # an empty batch (as `wigner_D`): nothing to rotate
        return jnp.zeros(batch + (n, C), c.dtype)
    if math.prod(R.shape[:-2]) == 1:
        # One rotation for all: the batch of `coeffs` rides along as channels.
        cb = jnp.broadcast_to(c, batch + (n, C))
        k = math.prod(batch)
        x = jnp.moveaxis(cb.reshape(k, n, C), 0, -1).reshape(1, n, C * k)
        out = _rotate_flat(x, R.reshape(1, 3, 3), lmax)
        return jnp.moveaxis(out.reshape(n, C, k), -1, 0).reshape(batch + (n, C))
    N = math.prod(batch)
    cb = jnp.broadcast_to(c, batch + (n, C)).reshape(N, n, C)
    Rb = jnp.broadcast_to(R, batch + (3, 3)).reshape(N, 3, 3)
    return _rotate_flat(cb, Rb, lmax).reshape(batch + (n, C))


# ---------------------------------------------------------------------------
# rotate_sh: the J-matrix (Z-Y-Z with fixed tables) form
# ---------------------------------------------------------------------------
#
# With Y = D(R_y(pi/2)) and Z(t) = D(R_z(t)) (real basis),
#     D(R_z(a) R_y(b) R_z(g)) = Z(a - pi/2) Y^T Z(b) Y Z(g + pi/2),
# because R_y(b) = R_z(-pi/2) R_y(-pi/2) R_z(b) R_y(pi/2) R_z(pi/2). R_y keeps the
# sign of y, so Y never mixes the cos-type (m >= 0) and sin-type (m < 0)
# coefficients of a band: it is two small dense blocks per band, stored padded as
# `_j_tables(lmax)[0]` of shape (2, L+1, L+1, L+1) = (part, l, m', m). Z(t) only
# mixes (l, m) with (l, -m) by cos(m t), sin(m t). Coefficients are packed as
# X[part, l, |m|] (part 0: m >= 0, part 1: m < 0, zero where |m| > l or part 1 at
# m = 0), so every step is one elementwise product or one batched matrix product.


@functools.lru_cache(maxsize=None)
def _j_tables(lmax: int):
    """Fixed float64 tables of the J-matrix form, computed once per `lmax`.

    Returns `(Y, pack, unpack, gen_idx, gen_coef)`:

    * `Y` (2, L+1, L+1, L+1): the cos-type and sin-type blocks of D(R_y(pi/2))
      for each band, zero-padded, indexed (type, l, |m|, |m'|);
    * `pack` (2 (L+1)^2,): flat coefficient index of X[type, l, |m|] (n = a zero slot);
    * `unpack` (n,): position in X.ravel() of each flat coefficient;
    * `gen_idx`, `gen_coef` (3, n, K): the generators G_x, G_y, G_z of the real
      representation (dD(exp(t K_k))/dt at t = 0), as K nonzeros per row.
    """
    L = lmax
    P = L + 1
    n = P * P
    blocks = [_j_block(l) for l in range(L + 1)]
    Y = np.zeros((2, P, P, P))
    pack = np.full((2, P, P), n)
    unpack = np.zeros(n, dtype=np.int64)
    gens = []
    for l, b in enumerate(blocks):
        cos_i = l + np.arange(0, l + 1)
        sin_i = l - np.arange(1, l + 1)
        Y[0, l, : l + 1, : l + 1] = b[np.ix_(cos_i, cos_i)]
        Y[1, l, 1 : l + 1, 1 : l + 1] = b[np.ix_(sin_i, sin_i)]
        pack[0, l, : l + 1] = l * l + cos_i
        pack[1, l, 1 : l + 1] = l * l + sin_i
        unpack[l * l + cos_i] = l * P + np.arange(0, l + 1)
        unpack[l * l + sin_i] = P * P + l * P + np.arange(1, l + 1)
        # Generators in the flat band basis (index l + m).
        ms = np.arange(-l, l + 1)
        gz = np.zeros((2 * l + 1, 2 * l + 1))
        gz[l + ms, l - ms] = -ms  # d/dt: c_m <- -m c_{-m}
        zq = _z_dense(l, np.pi / 2)
        gy = zq.T @ b.T @ gz @ b @ zq
        gx = zq.T @ gy @ zq
        gens.append((gx, gy, gz))
    K = max(int(np.max(np.sum(np.abs(g) > 1e-12, axis=1), initial=0)) for gg in gens for g in gg)
    K = max(K, 1)
    gen_idx = np.zeros((3, n, K), dtype=np.int64)
    gen_coef = np.zeros((3, n, K))
    for l, gg in enumerate(gens):
        for k, g in enumerate(gg):
            for r in range(2 * l + 1):
                (nz,) = np.nonzero(np.abs(g[r]) > 1e-12)
                gen_idx[k, l * l + r, : len(nz)] = l * l + nz
                gen_coef[k, l * l + r, : len(nz)] = g[r, nz]
    return Y, pack.reshape(-1), unpack, gen_idx, gen_coef


def _j_block(l: int) -> np.ndarray:
    """$J^l = D^l(R_y(\\pi/2))$, the real block of band `l` (flat index l + m), NumPy float64, from its generator.

    $D^l(R_y(t)) = \\exp(t\\,G)$ with $G = -\\mathrm{Re}(U^H A U)$: $A = (J_+ - J_-)/2$ the real antisymmetric
    tridiagonal matrix of $iJ_y$ in the complex basis ($\\sqrt{l(l+1) - m(m+1)}/2$ off the diagonal) and $U$ the
    band's block of `real_to_complex_matrix` (the sign and the transform checked against the derivative of the
    Ivanic–Ruedenberg recurrence at the identity). $iG$ is Hermitian with the eigenvalues $m = -l..l$ exactly
    (rounded to them), so $J^l = V e^{-i\\pi\\Lambda/2} V^H$ from one `eigh`: orthogonal to 2e-15 at every `l`. The
    recurrence evaluated at $R_y(\\pi/2)$, which gave the table before, loses about a digit every ten degrees
    beyond 32 (orthogonal to 4e-11 at l = 64, 4e-8 at 96)."""
    m = np.arange(-l, l).astype(np.float64)
    off = np.sqrt(l * (l + 1) - m * (m + 1)) / 2.0
    a = np.diag(off, -1) - np.diag(off, 1)
    u = np.zeros((2 * l + 1, 2 * l + 1), dtype=np.complex128)  # real -> complex, `real_to_complex_matrix`'s band
    u[l, l] = 1.0
    s = 1.0 / np.sqrt(2.0)
    for k in range(1, l + 1):
        sign = (-1.0) ** k
        u[l + k, l + k], u[l + k, l - k] = sign * s, 1j * sign * s
        u[l - k, l + k], u[l - k, l - k] = s, -1j * s
    g = -np.real(u.conj().T @ a @ u)
    g = 0.5 * (g - g.T)
    w, v = np.linalg.eigh(1j * g)
    return np.real((v * np.exp(-0.5j * np.pi * np.round(w))[None, :]) @ v.conj().T)


def _z_dense(l: int, t: float) -> np.ndarray:
    """Z(t) = D(R_z(t)) on band l (flat index l + m), NumPy float64."""
    z = np.zeros((2 * l + 1, 2 * l + 1))
    z[l, l] = 1.0
    for m in range(1, l + 1):
        c, s = np.cos(m * t), np.sin(m * t)
        z[l + m, l + m], z[l + m, l - m] = c, -s
        z[l - m, l + m], z[l - m, l - m] = s, c
    return z


def _euler_zyz(R):
    """ZYZ angles (a, b, g) with R = R_z(a) R_y(b) R_z(g), stable at gimbal lock.

    Never divides by sin b. With u = s e^{ia} = R02 + i R12, v = s e^{ig} =
    -R20 + i R21 (s = sin b):

        (R00 + R11) + i (R10 - R01) = (1 + cos b) e^{i(a+g)},   u v       = s^2 e^{i(a+g)},
        (R11 - R00) - i (R10 + R01) = (1 - cos b) e^{i(a-g)},   u conj(v) = s^2 e^{i(a-g)}.

    For cos b >= 0, a + g comes from the left form (magnitude >= 1, well
    conditioned) and a - g from u conj(v): its error ~eps/s enters D only
    through terms of order s, so D stays accurate to ~eps as b -> 0. Mirrored
    for cos b < 0. The half-angles fix a and g up to a common shift by pi, which
    is the same rotation with b -> -b: b = atan2(s', R22) with the signed
    s' = Re(u e^{-ia} + v e^{-ig}) / 2 absorbs it. At b = 0 or pi exactly the
    undetermined combination comes out as 0 and D is still exact.
    """
    R00, R01, R02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    R10, R11, R12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    R20, R21, R22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    ur, ui, vr, vi = R02, R12, -R20, R21
    up = R22 >= 0
    sum_re = jnp.where(up, R00 + R11, ur * vr - ui * vi)
    sum_im = jnp.where(up, R10 - R01, ur * vi + ui * vr)
    dif_re = jnp.where(up, ur * vr + ui * vi, R11 - R00)
    dif_im = jnp.where(up, ui * vr - ur * vi, -(R10 + R01))
    sig = jnp.arctan2(sum_im, sum_re)
    dlt = jnp.arctan2(dif_im, dif_re)
    a = 0.5 * (sig + dlt)
    g = 0.5 * (sig - dlt)
    s = 0.5 * ((ur * jnp.cos(a) + ui * jnp.sin(a)) + (vr * jnp.cos(g) + vi * jnp.sin(g)))
    b = jnp.arctan2(s, R22)
    return a, b, g


def _powers(c1, s1, lmax: int):
    """cos(m t), sin(m t) for m = 0..lmax from c1 = cos t, s1 = sin t: (L+1, ...) each.

    Complex multiplication in two short chains (m = qB + r with B ~ sqrt(L+1)), so
    the fused expressions stay small; the error grows like sqrt(m) eps.
    """
    nb = max(1, math.isqrt(lmax + 1))

    def chain(c, s, k):
        cs, ss = [jnp.ones_like(c)], [jnp.zeros_like(s)]
        for _ in range(k - 1):
            cs, ss = cs + [cs[-1] * c - ss[-1] * s], ss + [ss[-1] * c + cs[-1] * s]
        return jnp.stack(cs), jnp.stack(ss)

    cr, sr = chain(c1, s1, nb)  # r = 0..B-1
    cB = cr[-1] * c1 - sr[-1] * s1  # e^{iBt}
    sB = sr[-1] * c1 + cr[-1] * s1
    nq = -(-(lmax + 1) // nb)
    cq, sq = chain(cB, sB, nq)  # q = 0..nq-1
    cm = (cq[:, None] * cr[None] - sq[:, None] * sr[None]).reshape((nq * nb,) + c1.shape)
    sm = (sq[:, None] * cr[None] + cq[:, None] * sr[None]).reshape((nq * nb,) + c1.shape)
    return cm[: lmax + 1], sm[: lmax + 1]


def _trig_tables(R, lmax: int):
    """cos(m t), sin(m t), m = 0..lmax, for t = a - pi/2, b, g + pi/2: (6, L+1, N)."""
    a, b, g = _euler_zyz(R)
    ca, sa, cb, sb, cg, sg = jnp.cos(a), jnp.sin(a), jnp.cos(b), jnp.sin(b), jnp.cos(g), jnp.sin(g)
    # e^{i(a - pi/2)} = sin a - i cos a, e^{i(g + pi/2)} = -sin g + i cos g.
    cm, sm = _powers(jnp.stack([sa, cb, -sg]), jnp.stack([-ca, sb, cg]), lmax)  # (L+1, 3, N)
    return jnp.concatenate([jnp.moveaxis(cm, 0, 1), jnp.moveaxis(sm, 0, 1)], axis=0)


def _materialized_trig(R, lmax: int):
    # The tables are small ((L+1) x N) but each entry is read by L+1 bands: let XLA
    # fuse cos/sin into the consumers and it recomputes them per band (~10x slower
    # for batches). A conditional with identical branches is never fused into its
    # consumers, so the tables are computed once.
    f = functools.partial(_trig_tables, lmax=lmax)
    return jax.lax.cond(R[0, 2, 2] == R[0, 2, 2], f, f, R)


def _rotate_impl(c, R, lmax: int):
    """c (N, n, C), R (N, 3, 3) -> D(R) c, by Z Y^T Z Y Z (no Wigner matrix formed)."""
    Y, pack, unpack, _, _ = _j_tables(lmax)
    dt = c.dtype
    N, n, C = c.shape
    P = lmax + 1
    trig = _materialized_trig(R, lmax)  # (6, P, N)
    cs = trig[:, None, :, :, None]
    yt = jnp.asarray(Y, dt)
    ce = jnp.concatenate([jnp.moveaxis(c, 1, 0), jnp.zeros((1, N, C), dt)], axis=0)
    x = ce[pack].reshape(2, P, P, N, C)

    def z(x, k):
        co, si = cs[k], cs[3 + k]
        return jnp.stack([co * x[0] - si * x[1], si * x[0] + co * x[1]])

    x = z(x, 2)
    x = jnp.einsum("klpm,klmnc->klpnc", yt, x)
    x = z(x, 1)
    x = jnp.einsum("klmp,klmnc->klpnc", yt, x)
    x = z(x, 0)
    out = x.reshape(2 * P * P, N, C)[unpack]
    return jnp.moveaxis(out, 0, 1)


def _apply_generator(c, w, lmax: int):
    """sum_k w_k G_k c for axial vectors w (N, 3): the derivative of D at the identity."""
    _, _, _, gen_idx, gen_coef = _j_tables(lmax)
    dt = c.dtype
    cg = c[:, gen_idx]  # (N, 3, n, K, C)
    return jnp.einsum("nk,kij,nkijc->nic", w, jnp.asarray(gen_coef, dt), cg)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _rotate_flat(c, R, lmax: int):
    return _rotate_impl(c, R, lmax)


@_rotate_flat.defjvp
def _rotate_flat_jvp(lmax, primals, tangents):
    # D(R + dR) = D(R) D(I + R^T dR) for tangent dR = R Omega (Omega skew): the
    # derivative is D(R) (sum_k w_k G_k) with w the axial vector of Omega. Exact
    # at every R, gimbal lock included; a non-tangent part of dR is ignored.
    c, R = primals
    dc, dR = tangents
    out = _rotate_impl(c, R, lmax)
    om = jnp.einsum("nji,njk->nik", R, dR)
    w = 0.5 * jnp.stack([om[:, 2, 1] - om[:, 1, 2], om[:, 0, 2] - om[:, 2, 0], om[:, 1, 0] - om[:, 0, 1]], axis=-1)
    return out, _rotate_impl(_apply_generator(c, w, lmax) + dc, R, lmax)


def rotation_from_euler_zyz(alpha, beta, gamma) -> Float[Array, "*batch 3 3"]:
    """$R = R_z(\\alpha)\\,R_y(\\beta)\\,R_z(\\gamma)$ (active, right-handed), batched.

    With β = α_paper and α = β_paper, γ = 0, this is the $R_{\\alpha,\\beta} =
    R_z(\\beta)R_y(\\alpha)$ of R&H 2001 (eq. 6), which maps the local (normal)
    frame to the global one.
    """
    alpha, beta, gamma = (as_float_array(a, n) for a, n in ((alpha, "alpha"), (beta, "beta"), (gamma, "gamma")))
    alpha, beta, gamma = jnp.broadcast_arrays(alpha, beta, gamma)
    return jnp.matmul(jnp.matmul(_rz(alpha), _ry(beta)), _rz(gamma))


def _rz(a):
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2)


def _ry(a):
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, z, s], -1), jnp.stack([z, o, z], -1), jnp.stack([-s, z, c], -1)], -2)


def wigner_d_y(beta: Real[ArrayLike, "*batch"], lmax: int) -> Float[Array, "*batch n_coeffs n_coeffs"]:
    """Wigner small-d: the complex-basis D matrix of a rotation by β about +y.

    Block-diagonal, real; block $l$ is $d^l_{mm'}(\\beta)$, the
    $D^l_{mm'}(\\alpha)$ of R&H 2001 eq. 6 (with α the paper's tilt): for
    $R_{\\alpha,\\beta} = R_z(\\beta)R_y(\\alpha)$,
    $Y_{lm}(R_{\\alpha,\\beta}\\,\\omega') = \\sum_{m'} d^l_{mm'}(\\alpha)\\,e^{im\\beta}\\,Y_{lm'}(\\omega')$.
    Equals Wigner's closed-form $d^l_{mm'}$ (Condon-Shortley, e.g. Sakurai eq. 3.8.33).

    **Arguments:** `beta` any shape (traced); `lmax` static.
    **Returns:** `(..., (lmax+1)**2, (lmax+1)**2)` float.
    """
    beta = as_float_array(beta, "beta")
    lmax = check_lmax(lmax)
    return _wigner_d_y(beta, lmax)


@jit
def _wigner_d_y(beta, lmax):
    z = jnp.zeros_like(beta)
    d = _wigner_D(rotation_from_euler_zyz(z, beta, z), lmax, False)
    return jnp.real(d)
