"""Real and complex spherical-harmonic bases, evaluated from Cartesian directions.

The recurrence is written in $(x, y, z)$ so that it has no `atan2`/`arccos`
and no singularity at the poles (the approach of sphericart: Bigi et al. 2023,
J. Chem. Phys. 159, 064802). With $\\bar q_l^m$ the fully normalized associated
Legendre function divided by $\\sin^m\\theta$,

$$Y_{l,0} = \\bar q_l^0(z),\\quad
  Y_{l,m} = \\sqrt2\\,\\bar q_l^m(z)\\,\\mathrm{Re}(x+iy)^m,\\quad
  Y_{l,-m} = \\sqrt2\\,\\bar q_l^m(z)\\,\\mathrm{Im}(x+iy)^m\\quad(m>0),$$

since $(x+iy)^m = \\sin^m\\theta\\,e^{im\\phi}$ on the unit sphere. The
$\\bar q$ obey the standard normalized three-term recurrence

$$\\bar q_m^m = \\sqrt{\\tfrac{2m+1}{2m}}\\,\\bar q_{m-1}^{m-1},\\quad
  \\bar q_{m+1}^m = \\sqrt{2m+3}\\,z\\,\\bar q_m^m,\\quad
  \\bar q_l^m = a_{lm}\\,(z\\,\\bar q_{l-1}^m - b_{lm}\\,\\bar q_{l-2}^m),$$

$a_{lm} = \\sqrt{(4l^2-1)/(l^2-m^2)}$, $b_{lm} = \\sqrt{((l-1)^2-m^2)/(4(l-1)^2-1)}$,
$\\bar q_0^0 = 1/\\sqrt{4\\pi}$. Every quantity is a polynomial in the unit
vector, so values and gradients are finite everywhere; no un-normalized
double factorial appears, so float32 stays accurate to high degree.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Real

from ._checks import check_dirs, check_lmax, check_nonzero_dirs
from ._indexing import sh_degrees, sh_orders

# Band limits up to this value use the unrolled, chunked evaluation
# (`_basis_blocked` inside `_real_sh_chunked`); larger ones a `lax.scan` over l
# (bounded compile time).
_UNROLL_MAX = 20

# Chunked evaluation: points are processed `_CHUNK` at a time in a
# `lax.fori_loop` so that all intermediates stay in cache; inside a chunk the
# points are laid out as (`_CHUNK // _BLOCK`, rows, `_BLOCK`) so that every
# row operation is vectorized over `_BLOCK` points and the final transpose to
# (points, coefficients) only strides over `_BLOCK * itemsize` bytes.
_CHUNK = 2048
_BLOCK = 32


def _diag_constants(lmax: int) -> np.ndarray:
    """$\\bar q_m^m$ for m = 0..lmax (float64, NumPy)."""
    q = np.empty(lmax + 1)
    q[0] = 1.0 / np.sqrt(4.0 * np.pi)
    for m in range(1, lmax + 1):
        q[m] = q[m - 1] * np.sqrt((2 * m + 1) / (2 * m))
    return q


def _recurrence_tables(lmax: int):
    """Tables A[l, m], B[l, m], D[l, m] with q_l = A z q_{l-1} - B q_{l-2} + D.

    The m > 0 entries carry the sqrt(2) of the real basis (folded into the
    diagonal seed; the recurrence is linear).
    """
    n = lmax + 1
    a = np.zeros((n, n))
    b = np.zeros((n, n))
    d = np.zeros((n, n))
    diag = _diag_constants(lmax) * np.where(np.arange(n) > 0, np.sqrt(2.0), 1.0)
    for l in range(n):
        d[l, l] = diag[l]
        if l >= 1:
            a[l, l - 1] = np.sqrt(2 * l + 1)
        for m in range(0, l - 1):
            alm = np.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
            blm = np.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))
            a[l, m] = alm
            b[l, m] = alm * blm
    return a, b, d


def _unit_vectors(dirs, name: str = "dirs"):
    """Normalize; a zero, infinite or NaN direction is an error (checked in jit)."""
    norm2 = jnp.sum(dirs * dirs, axis=-1, keepdims=True)
    bad = jnp.any(~(jnp.isfinite(norm2) & (norm2 > 0)))
    norm2 = eqx.error_if(norm2, bad, f"`{name}` contains a zero-length or non-finite direction")
    return dirs * jax.lax.rsqrt(norm2)


def _basis_unrolled(x, y, z, lmax: int):
    """List of the (lmax+1)**2 real SH, in flat order, as arrays shaped like x."""
    diag = _diag_constants(lmax)
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


def _basis_scan(x, y, z, lmax: int):
    """Real SH with a `lax.scan` over l (vectorized over m); shape (n_coeffs, N)."""
    dtype = x.dtype
    a, b, d = (jnp.asarray(t, dtype=dtype) for t in _recurrence_tables(lmax))
    n = lmax + 1

    def cs_step(carry, _):
        cm, sm = carry
        nxt = (x * cm - y * sm, x * sm + y * cm)
        return nxt, carry

    _, (cos_m, sin_m) = jax.lax.scan(cs_step, (jnp.ones_like(x), jnp.zeros_like(x)), None, length=n)

    def q_step(carry, tables):
        q1, q2 = carry  # q_{l-1}, q_{l-2}: (n, N)
        al, bl, dl = tables
        ql = al[:, None] * (z[None, :] * q1) - bl[:, None] * q2 + dl[:, None]
        return (ql, q1), ql

    zeros = jnp.zeros((n,) + x.shape, dtype)
    _, q = jax.lax.scan(q_step, (zeros, zeros), (a, b, d))  # (l, m, N)
    ls = sh_degrees(lmax)
    ms = sh_orders(lmax)
    trig = jnp.concatenate([sin_m[1:][::-1], cos_m], axis=0)  # rows m = -lmax..lmax
    return q[ls, np.abs(ms)] * trig[ms + lmax]


def _basis_blocked(unit, lmax: int, block: int = _BLOCK):
    """Real SH of unit vectors (C, 3) -> (C, n_coeffs), vectorized per l.

    The same recurrence as `_basis_unrolled`, but with arrays shaped
    (C // block, rows, block): one (l+1)-row slab of $\\bar q_l^m$ per degree
    (materialized with `optimization_barrier`, so XLA does not re-evaluate the
    recurrence chain for every output element), one slab of the
    $\\mathrm{Re}/\\mathrm{Im}\\,(x+iy)^m$ for m = -lmax..lmax, and one product
    per degree, assembled in flat order and transposed back once.
    """
    n = lmax + 1
    dtype = unit.dtype
    c_pts = unit.shape[0]
    if c_pts % block:
        block = c_pts
    g = c_pts // block
    a, b, d = _recurrence_tables(lmax)
    ut = unit.reshape(g, block, 3).transpose(0, 2, 1)  # (g, 3, block)
    x, y, z = ut[:, 0:1], ut[:, 1:2], ut[:, 2:3]  # (g, 1, block)

    def col(v):
        return jnp.asarray(np.asarray(v), dtype)[None, :, None]

    c = [jnp.ones_like(x)]
    s = [jnp.zeros_like(x)]
    for m in range(1, n):
        c.append(x * c[m - 1] - y * s[m - 1])
        s.append(x * s[m - 1] + y * c[m - 1])
    trig = jnp.concatenate(s[1:][::-1] + c, axis=1)  # rows m = -lmax..lmax
    trig = jax.lax.optimization_barrier(trig)
    qs = []
    q1 = q2 = None
    for l in range(n):
        parts = []
        if l >= 2:
            parts.append(col(a[l, : l - 1]) * (z * q1[:, : l - 1]) - col(b[l, : l - 1]) * q2[:, : l - 1])
        if l >= 1:
            parts.append(float(a[l, l - 1]) * (z * q1[:, l - 1 : l]))
        parts.append(jnp.full((g, 1, block), float(d[l, l]), dtype))
        ql = jnp.concatenate(parts, axis=1) if len(parts) > 1 else parts[0]
        ql = jax.lax.optimization_barrier(ql)  # rows m = 0..l
        qs.append(ql)
        q2, q1 = q1, ql
    rows = []
    for l in range(n):
        ql = qs[l]
        if l > 0:
            rows.append(ql[:, 1 : l + 1][:, ::-1] * trig[:, lmax - l : lmax])
        rows.append(ql[:, : l + 1] * trig[:, lmax : lmax + l + 1])
    out = jnp.concatenate(rows, axis=1)  # (g, n_coeffs, block)
    return out.transpose(0, 2, 1).reshape(c_pts, n * n)


def _real_sh_chunked(unit, lmax: int, chunk: int = _CHUNK):
    """`_basis_blocked` over chunks of `chunk` points (a `fori_loop`)."""
    n_pts = unit.shape[0]
    if n_pts == 0:
        return jnp.zeros((0, (lmax + 1) ** 2), unit.dtype)
    if n_pts <= chunk:
        return _basis_blocked(unit, lmax)
    n_chunks = -(-n_pts // chunk)

    def body(i, out):
        # The last chunk is shifted back to end at n_pts (it overlaps the
        # previous one; the overlap is recomputed identically).
        start = jnp.minimum(i * chunk, n_pts - chunk)
        u = jax.lax.dynamic_slice_in_dim(unit, start, chunk, 0)
        return jax.lax.dynamic_update_slice_in_dim(out, _basis_blocked(u, lmax), start, 0)

    out = jnp.zeros((n_pts, (lmax + 1) ** 2), unit.dtype)
    return jax.lax.fori_loop(0, n_chunks, body, out)


# float32 above this band limit uses the compensated recurrence (error-free
# transformations), which keeps |error| <= 1e-5 to l = 30 and beyond; the plain
# float32 recurrence reaches ~1.3e-5 near the poles at l = 16 and 5e-5 at l = 30.
_F32_COMPENSATED_FROM = 13


def _split(a):
    """Dekker's split of a float32 into two 12-bit halves (a = hi + lo exactly)."""
    c = 4097.0 * a
    hi = c - (c - a)
    return hi, a - hi


def _two_prod(a, b):
    """p + e = a*b exactly (Dekker; no FMA needed)."""
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    e = ((ah * bh - p) + ah * bl + al * bh) + al * bl
    return p, e


def _two_sum(a, b):
    """s + e = a + b exactly (Knuth)."""
    s = a + b
    bb = s - a
    e = (a - (s - bb)) + (b - bb)
    return s, e


def _df_mul_const(c_hi, c_lo, x_hi, x_lo):
    """(c_hi + c_lo) * (x_hi + x_lo) in double-float, renormalized."""
    p, e = _two_prod(c_hi, x_hi)
    e = e + (c_hi * x_lo + c_lo * x_hi)
    return _two_sum(p, e)


def _df_unit(dirs):
    r"""Normalize float32 directions with the z component as a double-float (zh + zl).

    Near the poles $Y_{l0}$ has slope $\sim l^2/2$ in z, so a one-ulp rounding of
    the normalized z alone costs ~3e-5 at l = 30 in float32: the norm, its
    reciprocal square root and z/|d| are therefore computed with error-free
    transformations. x and y enter only through $(x+iy)^m$ and stay float32.
    """
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    px, ex = _two_prod(x, x)
    py, ey = _two_prod(y, y)
    pz, ez = _two_prod(z, z)
    s, e = _two_sum(px, py)
    s, e2 = _two_sum(s, pz)
    e = e + e2 + ex + ey + ez
    s, e = _two_sum(s, e)
    bad = jnp.any(~(jnp.isfinite(s) & (s > 0)))
    s = eqx.error_if(s, bad, "`dirs` contains a zero-length or non-finite direction")
    r0 = jax.lax.rsqrt(s)
    p1, e1 = _two_prod(s, r0)
    p2, e2 = _two_prod(p1, r0)
    resid = ((1.0 - p2) - e2) - (e1 * r0 + e * r0 * r0)
    rh, rl = _two_sum(r0, 0.5 * r0 * resid)
    zh, zl = _two_prod(z, rh)
    zl = zl + z * rl
    zh, zl = _two_sum(zh, zl)
    return x * rh, y * rh, zh, zl


def _basis_compensated(x, y, z, lmax: int, z_lo=None):
    """Real SH (n_coeffs, N) with the three-term recurrence in double-float32 arithmetic.

    Same recurrence and tables as `_basis_scan`, but every q_l is carried as an
    unevaluated sum hi + lo of two float32 numbers and every product/sum uses
    error-free transformations (Dekker 1971, Knuth), with the constants split
    into hi + lo parts too: the recurrence then loses no accuracy near the poles,
    where plain float32 rounding grows like l·eps. About 4x the float32 cost.
    """
    dtype = x.dtype
    tabs = _recurrence_tables(lmax)
    hi_lo = []
    for t in tabs:
        hi = t.astype(np.float32)
        lo = (t - hi.astype(np.float64)).astype(np.float32)
        hi_lo.append((jnp.asarray(hi, dtype), jnp.asarray(lo, dtype)))
    (a_hi, a_lo), (b_hi, b_lo), (d_hi, d_lo) = hi_lo
    n = lmax + 1

    def cs_step(carry, _):
        cm, sm = carry
        return (x * cm - y * sm, x * sm + y * cm), carry

    _, (cos_m, sin_m) = jax.lax.scan(cs_step, (jnp.ones_like(x), jnp.zeros_like(x)), None, length=n)
    zz = z[None, :]
    zl = jnp.zeros_like(z) if z_lo is None else z_lo

    def q_step(carry, tables):
        q1h, q1l, q2h, q2l = carry
        ah, al, bh, bl, dh, dl = (t[:, None] for t in tables)
        # q_l = A z q_{l-1} - B q_{l-2} + D  (B already holds a_lm * b_lm; see _recurrence_tables)
        p, e = _two_prod(jnp.broadcast_to(zz, q1h.shape), q1h)
        e = e + zz * q1l + zl[None, :] * q1h
        p, e = _two_sum(p, e)
        th, tl = _df_mul_const(ah, al, p, e)
        uh, ul = _df_mul_const(bh, bl, q2h, q2l)
        qh, ql = _two_sum(th, -uh)
        ql = ql + (tl - ul)
        qh, e3 = _two_sum(qh, dh)
        qh, ql = _two_sum(qh, ql + e3 + dl)
        return (qh, ql, q1h, q1l), qh + ql

    zeros = jnp.zeros((n,) + x.shape, dtype)
    _, q = jax.lax.scan(q_step, (zeros, zeros, zeros, zeros), (a_hi, a_lo, b_hi, b_lo, d_hi, d_lo))
    ls = sh_degrees(lmax)
    ms = sh_orders(lmax)
    trig = jnp.concatenate([sin_m[1:][::-1], cos_m], axis=0)
    return q[ls, np.abs(ms)] * trig[ms + lmax]


def _real_sh_flat(unit, lmax: int):
    """Real SH of unit vectors (N, 3) -> (N, n_coeffs)."""
    if unit.dtype == jnp.float32 and lmax >= _F32_COMPENSATED_FROM:
        x, y, z = unit[:, 0], unit[:, 1], unit[:, 2]
        return _basis_compensated(x, y, z, lmax).T
    if lmax <= _UNROLL_MAX:
        return _real_sh_chunked(unit, lmax)
    x, y, z = unit[:, 0], unit[:, 1], unit[:, 2]
    return _basis_scan(x, y, z, lmax).T


def real_sh(dirs: Real[ArrayLike, "*batch 3"], lmax: int) -> Float[Array, "*batch n_coeffs"]:
    """Real orthonormal spherical harmonics $Y_{lm}(\\omega)$ for $l \\le l_{max}$.

    Convention (docs/conventions.md): orthonormal on the sphere, no sign flips,
    $Y_{1,-1} = c\\,y$, $Y_{1,0} = c\\,z$, $Y_{1,1} = c\\,x$ with
    $c = \\sqrt{3/4\\pi}$; in general $Y_{l,m} = \\sqrt2(-1)^m\\mathrm{Re}\\,Y_l^m$ and
    $Y_{l,-m} = \\sqrt2(-1)^m\\mathrm{Im}\\,Y_l^m$ for $m > 0$, with $Y_l^m$ the
    complex harmonics of `complex_sh`. Flat index $i = l^2 + l + m$. The same
    convention as sphericart.

    Evaluated by a normalized recurrence in Cartesian coordinates (see the
    module docstring): finite values and gradients everywhere, poles included.
    Accuracy against `scipy.special.sph_harm_y`: ≤ 1e-12 absolute for
    $l_{max} \\le 100$ in float64. In float32, ≤ 1e-5 absolute for
    $l_{max} \\le 30$ (measured 6.5e-6 at l = 12, 1.6e-6 at l = 30, 2.2e-6 at
    l = 40, poles included): near the poles $Y_{l0}$ has slope $\\sim l^2/2$ in
    z, so from `lmax` 13 on float32 input is normalized and run through the
    recurrence in double-float arithmetic (error-free transformations; a
    plain float32 recurrence reaches 1.3e-5 at l = 16 and 5e-5 at l = 30).
    That path costs ~5-10× the plain float32 one; float64 is unaffected.

    **Arguments:**

    - `dirs`: directions, shape `(..., 3)`. They are normalized here, so the
      result is a function on the sphere and its gradient is tangential; a
      zero-length or non-finite direction raises an error at run time (the
      one check this kernel makes on its data: a NaN direction has no
      harmonic).
    - `lmax`: band limit (static Python int, ≥ 0; negative is a `ValueError`).

    **Returns:** shape `(..., (lmax+1)**2)`, the dtype of `dirs`.

    Comparable to `sphericart.SphericalHarmonics(lmax)` and to
    `scipy.special.sph_harm_y` (complex, angles instead of directions).
    """
    dirs = check_nonzero_dirs(dirs)
    lmax = check_lmax(lmax)
    return _real_sh_jit(dirs, lmax)


@eqx.filter_jit
def _real_sh_jit(dirs, lmax):
    batch = dirs.shape[:-1]
    flat = dirs.reshape(-1, 3)
    if flat.dtype == jnp.float32 and lmax >= _F32_COMPENSATED_FROM:
        x, y, zh, zl = _df_unit(flat)
        out = _basis_compensated(x, y, zh, lmax, zl).T
    else:
        out = _real_sh_flat(_unit_vectors(flat), lmax)
    return out.reshape(batch + ((lmax + 1) ** 2,))


def _complex_from_real(yr, lmax: int):
    """Combine real SH (…, n) into complex SH (…, n) with the CS phase."""
    ls = sh_degrees(lmax)
    ms = sh_orders(lmax)
    base = ls * ls + ls
    pos = base + np.abs(ms)
    neg = base - np.abs(ms)
    re = yr[..., pos]
    im = yr[..., neg]
    am = np.abs(ms)
    sign_re = np.where(ms > 0, (-1.0) ** am, 1.0) / np.where(ms != 0, np.sqrt(2.0), 1.0)
    sign_im = np.where(ms > 0, (-1.0) ** am, np.where(ms < 0, -1.0, 0.0)) / np.where(
        ms != 0, np.sqrt(2.0), 1.0
    )
    dtype = yr.dtype
    lead = (1,) * (yr.ndim - 1)
    sign_re = jnp.asarray(sign_re, dtype).reshape(lead + (-1,))
    sign_im = jnp.asarray(sign_im, dtype).reshape(lead + (-1,))
    return jax.lax.complex(re * sign_re, im * sign_im)


def complex_sh(dirs: Real[ArrayLike, "*batch 3"], lmax: int) -> Complex[Array, "*batch n_coeffs"]:
    """Complex orthonormal spherical harmonics $Y_l^m(\\omega)$.

    $Y_l^m = N_{lm} P_l^m(\\cos\\theta) e^{im\\phi}$ with the Condon-Shortley
    phase inside $P_l^m$, exactly `scipy.special.sph_harm_y(l, m, θ, φ)`;
    $Y_l^{-m} = (-1)^m \\overline{Y_l^m}$. Same layout, accuracy and
    argument rules as `real_sh`; the result is complex64 for float32 input,
    complex128 for float64.
    """
    dirs = check_nonzero_dirs(dirs)
    lmax = check_lmax(lmax)
    return _complex_sh_jit(dirs, lmax)


@eqx.filter_jit
def _complex_sh_jit(dirs, lmax):
    return _complex_from_real(_real_sh_jit(dirs, lmax), lmax)
