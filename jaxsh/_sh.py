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
double factorial appears, so float32 stays accurate to high degree, up to
where the seeds $\\sin^m\\theta$ leave its range (`REAL_SH_MAX_LMAX`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Real

from ._compile import by_platform, jit, on_row_shards, row_sharding
from ._checks import error_if_any, check_dirs, check_lmax, check_lmax_range, check_nonzero_dirs
from ._indexing import sh_degrees, sh_orders

# The kernel (`_rows_chunk`) runs the recurrence over l as a rolled loop on a chunk of points laid out
# (coefficients, points): its compiled size does not grow with lmax (measured on 2 cores: 0.12-0.19 s of XLA
# compilation at any lmax, against 0.6-1.5 s for the former Python-unrolled bands at lmax 12-20), and each row
# operation is vectorized over the chunk of `_CHUNK_POINTS` points (`_chunk_size`).
_CHUNK_POINTS = 128
# At lmax <= 2 (the irradiance's 9 harmonics, in every diffuse term) the harmonics are written out instead
# (`_basis_low`: polynomials of degree <= 2 in one elementwise pass, no loop). Measured at 154,000 points for the
# written-out recurrence it replaced: 0.07-0.1 s less XLA compilation and 0.02 s less tracing per program that
# holds it than the rolled loop; the closed form compiles as fast as that recurrence (the whole `real_sh` program
# 0.07-0.11 s against 0.10-0.13 s) and runs about twice as fast. From lmax 3 the rolled loop compiles as fast as
# a written-out form and from 4 faster.
_UNROLLED_LMAX = 2
# The largest `lmax` `real_sh` accepts below float64 and in float64 (`jaxsh._checks.check_lmax_range`): measured
# against float64 over a sweep of 2,000 polar angles, float32 errs 1.3e-5 at lmax 150, 1.5e-5 at 170 and 2.0e-4 at
# 190 (its seeds sin(theta)^m reach the subnormal range), and returns 0 for harmonics of order 1 from about 200
REAL_SH_MAX_LMAX = (170, 1900)


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


def _unit_vectors(dirs, name: str = "dirs", check: bool = True):
    """Normalize; a zero, infinite or NaN direction is an error (checked in jit; `check=False`: not checked, for
    directions derived from checked ones, e.g. a mirror direction, whose length is that of its view)."""
    norm2 = jnp.sum(dirs * dirs, axis=-1, keepdims=True)
    if check:
        bad = jnp.any(~(jnp.isfinite(norm2) & (norm2 > 0)))
        norm2 = error_if_any(norm2, bad, f"`{name}` contains a zero-length or non-finite direction")
    return dirs * jax.lax.rsqrt(norm2)


def _sh2(x, y, z, k: int):
    """The first `k` (1, 4 or 9) real SH at unit components `x, y, z`, in closed form: a list of arrays shaped like x.

    The recurrence of the module docstring written out at l <= 2, with $\\bar q_0^0 = 1/\\sqrt{4\\pi}$:
    $Y_{00} = \\tfrac12\\sqrt{1/\\pi}$; $(Y_{1,-1}, Y_{10}, Y_{11}) = \\sqrt{3/4\\pi}\\,(y, z, x)$;
    $(Y_{2,-2}, Y_{2,-1}, Y_{21}) = \\tfrac12\\sqrt{15/\\pi}\\,(xy, yz, xz)$;
    $Y_{20} = \\tfrac14\\sqrt{5/\\pi}\\,(3z^2 - 1)$; $Y_{22} = \\tfrac14\\sqrt{15/\\pi}\\,(x^2 - y^2)$ (the constants
    0.282095, 0.488603, 1.092548, 0.315392, 0.546274 of Ramamoorthi & Hanrahan's irradiance maps, SIGGRAPH
    2001, eq. 3)."""
    c0, c1, c2 = 0.28209479177387814, 0.4886025119029199, 1.0925484305920792
    c3, c4 = 0.31539156525252005, 0.5462742152960396
    ys = [jnp.full_like(x, c0), c1 * y, c1 * z, c1 * x, c2 * x * y, c2 * y * z, c3 * (3.0 * z * z - 1.0), c2 * x * z,
          c4 * (x * x - y * y)]
    return ys[:k]


def _basis_low(unit, lmax: int, coeffs_first: bool = False):
    """Real SH of unit vectors `(N, 3)` at `lmax` <= 2: `(N, n_coeffs)`, or `(n_coeffs, N)` with `coeffs_first`.

    One elementwise expression of the output's shape, $\\sum_k Y_k(u) \\otimes e_k$ (`_sh2`'s columns times the unit
    rows), which XLA computes in one pass that writes each element once: about twice as fast as stacking the nine
    harmonics made as separate arrays (`bench_sh.py`, 10⁶ directions, lmax 2, two interleaved runs: float64 21-24
    against 48-51 ms, float32 13 against 24-27 ms; docs/performance.md, "Thirteenth round")."""
    n = (lmax + 1) ** 2
    out = None
    for col, e in zip(_sh2(unit[:, 0], unit[:, 1], unit[:, 2], n), np.eye(n)):
        e = jnp.asarray(e, unit.dtype)
        t = e[:, None] * col[None, :] if coeffs_first else col[:, None] * e[None, :]
        out = t if out is None else out + t
    return out


def _scan_parts(x, y, z, lmax: int):
    """What `_basis_scan` and `_band_sums_scan` share: the z features `(1 or 2, 1, N)`, the rows
    $\\cos m\\phi, \\sin m\\phi$ (times $\\sin^m\\theta$) `(lmax+1, N)` each, and the step of the recurrence over l."""
    zf = tuple(v[None, :] for v in z) if isinstance(z, tuple) else (z[None, :],)
    n = lmax + 1

    def cs_step(carry, _):
        cm, sm = carry
        nxt = (x * cm - y * sm, x * sm + y * cm)
        return nxt, carry

    _, (cos_m, sin_m) = jax.lax.scan(cs_step, (jnp.ones_like(x), jnp.zeros_like(x)), None, length=n)

    def q_step(carry, tables):
        q1, q2 = carry  # q_{l-1}, then q_{l-2} or Δ_{l-1} (difference form): (n, N)
        al, bl, dl, rl, btl = (t[:, None] for t in tables)
        if len(zf) == 1:
            ql = al * (zf[0] * q1) - bl * q2 + dl
            return (ql, q1), ql
        # Difference form below float64 (see `_z_features` and `_rows_chunk`).
        sig, sw = zf
        delta = btl * (sig * q2) - al * (sw * q1)
        ql = rl * (sig * q1) + delta + dl
        return (ql, delta), ql

    dtype = x.dtype
    a, b, d = (jnp.asarray(t, dtype=dtype) for t in _recurrence_tables(lmax))
    rho, beta = (jnp.asarray(t, dtype=dtype) for t in _delta_tables(lmax))
    zeros = jnp.zeros_like(x, shape=(n,) + x.shape)  # `zeros_like`: per point, like x (`_rows_chunk`)
    return cos_m, sin_m, q_step, (a, b, d, rho, beta), (zeros, zeros)


def _basis_scan(x, y, z, lmax: int):
    """Real SH with a `lax.scan` over l (vectorized over m); shape (n_coeffs, N).

    `z` is the z coordinate or the tuple of z features of `_z_features`.
    """
    cos_m, sin_m, q_step, tables, init = _scan_parts(x, y, z, lmax)
    _, q = jax.lax.scan(q_step, init, tables)  # (l, m, N)
    ls = sh_degrees(lmax)
    ms = sh_orders(lmax)
    trig = jnp.concatenate([sin_m[1:][::-1], cos_m], axis=0)  # rows m = -lmax..lmax
    return q[ls, np.abs(ms)] * trig[ms + lmax]


def _band_sums_scan(x, y, z, coeffs, lmax: int):
    """Band sums $P_l = \\sum_m c_{lm} Y_{lm}$ of `coeffs` `(n_coeffs, C)` at the points: `(lmax+1, C, N)`.

    The recurrence of `_basis_scan`, with each band contracted as soon as it is made:
    $P_l = \\sum_{m \\ge 0} \\bar q_l^m\\,(c_{l,m}\\cos_m + c_{l,-m}\\sin_m)$, one `(C, 2(lmax+1)) @ (2(lmax+1), N)`
    product per l. $O(N\\,l_{max}^2\\,C)$ work like the basis, but the `(N, n_coeffs)` basis is never stored
    and no multiply-add is spent on other bands' zeros (the block-matrix route of `jaxsh._practical`
    spent $l_{max}/2$ times more).
    """
    cos_m, sin_m, q_step, tables, init = _scan_parts(x, y, z, lmax)
    n = lmax + 1
    l_, m_ = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    ok = m_ <= l_
    i_cos = np.where(ok, l_ * l_ + l_ + m_, 0)
    i_sin = np.where(ok & (m_ > 0), l_ * l_ + l_ - m_, 0)
    c_cos = jnp.where(ok[:, :, None], coeffs[i_cos], 0.0)  # (l, m, C)
    c_sin = jnp.where((ok & (m_ > 0))[:, :, None], coeffs[i_sin], 0.0)
    c_lm = jnp.concatenate([c_cos, c_sin], axis=1).transpose(0, 2, 1)  # (l, C, 2n)
    trig = jnp.concatenate([cos_m, sin_m], axis=0)  # (2n, N)

    def step(carry, xs):
        tab, cl = xs
        carry, ql = q_step(carry, tab)
        return carry, cl @ (jnp.concatenate([ql, ql], axis=0) * trig)

    _, p = jax.lax.scan(step, init, (tables, c_lm))
    return p


@functools.lru_cache(maxsize=None)
def _delta_tables(lmax: int):
    """rho[l, m] = q_l^m(1) / q_{l-1}^m(1) (l > m) and beta[l, m] = B[l, m] / rho[l-1, m] (l > m+1).

    From $\\bar q_l = A\\,\\bar q_{l-1} - B\\,\\bar q_{l-2}$ at z = 1:
    $\\rho_l = A - B/\\rho_{l-1}$, $\\rho_{m+1} = A$ (float64, NumPy; no overflow).
    """
    a, b, _ = _recurrence_tables(lmax)
    n = lmax + 1
    rho = np.zeros((n, n))
    beta = np.zeros((n, n))
    for m in range(n):
        for l in range(m + 1, n):
            if l == m + 1:
                rho[l, m] = a[l, m]
            else:
                beta[l, m] = b[l, m] / rho[l - 1, m]
                rho[l, m] = a[l, m] - beta[l, m]
    return rho, beta


def _z_features(unit):
    """Per-point inputs of the recurrence: (x, y, z) or, below float64, (x, y, σ, σw).

    Near the poles $Y_{l0}$ has slope $\\sim l^2/2$ in z, so the one-ulp rounding
    of a float32 z alone costs ~3e-5 at l = 30. Below float64 z is therefore
    carried as $z = σ(1 - w)$ with $σ = \\pm1$ and
    $w = 1 - |z| = (x^2+y^2)/(r^2 (1 + |z|/r))$, which is accurate to a few ulp
    *relative* (no cancellation), and the products $z\\,v$ of the recurrence are
    formed as $σ v - σw\\,v$: the recurrence then sees z to far better than one
    ulp near the poles, at the cost of one multiply-add. σ is piecewise constant
    (no gradient), so values and gradients are those of the smooth formula.
    """
    if unit.dtype == jnp.float64:
        return unit
    x, y, z = unit[:, 0], unit[:, 1], unit[:, 2]
    s2 = x * x + y * y
    r2 = s2 + z * z
    rinv = jax.lax.rsqrt(r2)
    zn = z * rinv
    sig = jnp.where(z < 0, -1.0, 1.0).astype(unit.dtype)
    w = s2 / (r2 * (1.0 + sig * zn))
    return jnp.stack([x * rinv, y * rinv, sig, sig * w], axis=-1)


@functools.lru_cache(maxsize=None)
def _signed_tables(lmax: int):
    """The recurrence's coefficients in the *signed* layout: row l, position j holds order m = j - l.

    Returns float64 arrays `(lmax+1, 2 lmax+1)`: A, B (three-term form, `_recurrence_tables`), rho, beta
    (difference form, `_delta_tables`), and the seeds at the two edges, D⁻ (position 0, m = -l: times
    Im (x+iy)^l) and D⁺ (position 2l, m = l: times Re (x+iy)^l). Every entry with |m| > l, or where the
    term does not exist, is 0: a band's positions beyond 2l come out 0, and so does anything read from
    outside the band above (`_rows_chunk`).
    """
    a, b, d = _recurrence_tables(lmax)
    rho, beta = _delta_tables(lmax)
    n, w = lmax + 1, 2 * lmax + 1
    out = np.zeros((6, n, w))
    for l in range(n):
        m = np.abs(np.arange(2 * l + 1) - l)
        mi = np.minimum(m, lmax)
        one = m <= l - 1
        two = m <= l - 2
        out[0, l, : 2 * l + 1] = np.where(one, a[l, mi], 0.0)
        out[1, l, : 2 * l + 1] = np.where(two, b[l, mi], 0.0)
        out[2, l, : 2 * l + 1] = np.where(one, rho[l, mi], 0.0)
        out[3, l, : 2 * l + 1] = np.where(two, beta[l, mi], 0.0)
        if l > 0:
            out[4, l, 0] = d[l, l]
        out[5, l, 2 * l] = d[l, l]
    return tuple(out)


def _rows_chunk(feat, lmax: int):
    """Real SH of one chunk of features `(P, k)` (`_z_features`) in the layout `(n_coeffs, P)`.

    Degree l is one window of 2·lmax+1 rows in the signed layout of `_signed_tables`, written at row
    $l^2$ of the output: its first 2l+1 rows are $Y_{l,-l..l}$, the rest 0 (overwritten by the next
    degrees). In that layout $Y_{l-1,m}$ sits one position lower than $Y_{l,m}$ and $Y_{l-2,m}$ two, so the
    flat recurrence $Y_{l,m} = A_{lm}zY_{l-1,m} - B_{lm}Y_{l-2,m}$ (plus the seeds at |m| = l) reads both
    previous degrees straight from the output, as the windows starting at rows $(l-1)^2 - 1$ and
    $(l-2)^2 - 2$ (two zero rows lead the buffer, so no start is negative); what those windows hold beyond
    the previous bands meets a zero coefficient. One loop body for every l: a rolled `fori_loop`.

    Below float64 the difference form of `_basis_scan` runs instead (z = σ(1 - w), `_z_features`):
    $Y_l = σρ_lY_{l-1} + Δ_l$, $Δ_l = σβ_lΔ_{l-1} - A_lσwY_{l-1}$, with Δ carried in the same layout.
    """
    dt = feat.dtype
    p = feat.shape[0]
    ft = feat.T[:, None, :]  # (k, 1, P)
    x, y = ft[0], ft[1]
    zf = tuple(ft[2:])
    a, b, rho, beta, dm, dp = (jnp.asarray(t, dt)[:, :, None] for t in _signed_tables(lmax))
    n, w = (lmax + 1) ** 2, 2 * lmax + 1

    def body(l, carry):
        out, cm, sm, delta = carry
        y1 = jax.lax.dynamic_slice_in_dim(out, (l - 1) * (l - 1) + 1, w, 0)  # Y_{l-1, m} at the positions of Y_{l, m}
        seed = dm[l] * sm + dp[l] * cm
        if len(zf) == 1:
            y2 = jax.lax.dynamic_slice_in_dim(out, (l - 2) * (l - 2), w, 0)
            yl = a[l] * (zf[0] * y1) - b[l] * y2 + seed
        else:
            sig, sw = zf
            delta = beta[l] * (sig * jnp.pad(delta[:-1], ((1, 0), (0, 0)))) - a[l] * (sw * y1)
            yl = rho[l] * (sig * y1) + delta + seed
        out = jax.lax.dynamic_update_slice_in_dim(out, yl, l * l + 2, 0)
        return out, x * cm - y * sm, x * sm + y * cm, delta

    # the carries made `_like` the points (not constants): inside `jax.shard_map` they then vary over the devices
    # as the loop's outputs do, which its default `check_vma=True` requires
    init = (jnp.zeros_like(x, shape=(n + 2, p)), jnp.ones_like(x), jnp.zeros_like(x),
            jnp.zeros_like(x, shape=(w if len(zf) > 1 else 1, p)))
    out = jax.lax.fori_loop(0, lmax + 1, body, init)[0]
    return out[2:]


def _chunk_size(lmax: int) -> int:
    """Points per chunk of `_real_sh_flat`: `_CHUNK_POINTS` (128) at every `lmax`.

    Measured on 2 cores at 10⁵ directions, both dtypes and layouts, chunks of 16-512 points: 128 ran fastest
    or within 10 % of the fastest at lmax 8-48. Each loop step works on a window of 2·lmax+1 rows of the
    chunk, so the chunk need not shrink as lmax grows: the former rule (at most 512 KB of float64 output per
    chunk: 64 points at lmax 24, 16 at lmax 48) took 1.0-1.5× (lmax 24) and 1.1-2.5× (lmax 48) as long, the
    overhead of each loop step outweighing the cache it saved. 512 points ran up to 2× slower
    (docs/performance.md, tenth round)."""
    del lmax
    return _CHUNK_POINTS


def _real_sh_flat(unit, lmax: int, coeffs_first: bool = False):
    """Real SH of unit vectors `(N, 3)`: `(N, n_coeffs)`, or `(n_coeffs, N)` with `coeffs_first`.

    On a CPU, `_rows_chunk` over chunks of `_chunk_size` points in a `fori_loop` (the last chunk shifted back
    to end at N; its overlap is recomputed identically), each transposed to the points-first layout in cache;
    on other platforms (GPU) `_rows_chunk` on all N points at once (`jaxsh._compile.by_platform`: the
    choice is made for the device the program is compiled for). At `lmax <= _UNROLLED_LMAX` the written-out
    polynomials (`_basis_low`) instead.
    """
    if lmax <= _UNROLLED_LMAX:
        return _basis_low(unit, lmax, coeffs_first)
    feat = _z_features(unit)
    n_pts = feat.shape[0]
    n = (lmax + 1) ** 2
    if n_pts == 0:
        return jnp.zeros((n, 0) if coeffs_first else (0, n), feat.dtype)
    chunk = _chunk_size(lmax)

    def whole(feat):  # every point at once: one loop over l on (2 lmax + 1, N) windows
        r = _rows_chunk(feat, lmax)
        return r if coeffs_first else r.T

    if n_pts <= chunk:
        return whole(feat)
    axis = 1 if coeffs_first else 0

    def chunked(feat):
        def body(i, out):
            start = jnp.minimum(i * chunk, n_pts - chunk)
            r = _rows_chunk(jax.lax.dynamic_slice_in_dim(feat, start, chunk, 0), lmax)
            return jax.lax.dynamic_update_slice_in_dim(out, r if coeffs_first else r.T, start, axis)

        out = jnp.zeros_like(feat, shape=(n, n_pts) if coeffs_first else (n_pts, n))
        return jax.lax.fori_loop(0, -(-n_pts // chunk), body, out)

    # Chunks that stay in cache on a CPU; on an accelerator each of the N/128 chunks' (lmax+1) steps would be
    # a few kernel launches (at 10^6 directions, lmax 16, an H200 took 2.5 s: 1.7x the host CPU), while the
    # whole-array loop is lmax+1 steps of large kernels (22 ms there).
    return by_platform(feat, cpu=chunked, other=whole)


def real_sh(
    dirs: Real[ArrayLike, "*batch 3"], lmax: int, *, coeffs_first: bool = False
) -> Float[Array, "*batch n_coeffs"] | Float[Array, "n_coeffs *batch"]:
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
    $l_{max} \\le 30$ (measured 1.1e-6 at l = 16, 2.1e-6 at l = 30, 2.8e-6 at
    l = 40, poles included): near the poles $Y_{l0}$ has slope $\\sim l^2/2$
    in z, so below float64 z is carried as $σ(1 - w)$, $w = 1 - |z|$ without
    cancellation, and the recurrence runs in a difference form whose rounding
    errors grow like l rather than l² there (`_z_features`, `_rows_chunk`;
    a plain float32 recurrence reaches 1.3e-5 at l = 16 and 5e-5 at l = 30).
    The recurrence over l is one rolled loop (`_rows_chunk`), so the compiled
    program is small at any `lmax` (0.1-0.3 s of XLA compilation on 2 cores);
    at `lmax` ≤ 2 (the 9 harmonics of every diffuse term) it is written out
    instead, a loop-free program that compiles in about half that time.

    **Arguments:**

    - `dirs`: directions, shape `(..., 3)`. They are normalized here, so the
      result is a function on the sphere and its gradient is tangential; a
      zero-length or non-finite direction raises an error at run time (the
      one check this kernel makes on its data: a NaN direction has no
      harmonic).
    - `lmax`: band limit (static Python int, ≥ 0; negative is a `ValueError`).
    - `coeffs_first`: return the coefficient axis first, `((lmax+1)**2, ...)`
      (the layout of a design matrix's transpose, `Y[i, k] = Y_i(ω_k)`), made in
      that layout rather than transposed afterwards.

    **Returns:** shape `(..., (lmax+1)**2)` (or `((lmax+1)**2, ...)` with
    `coeffs_first`), the dtype of `dirs`. For `dirs` split over several
    devices along its first axis (a `NamedSharding`, evenly), each device
    evaluates its own directions and the result is split the same way
    (docs/howto_scale.md).

    Comparable to `sphericart.SphericalHarmonics(lmax)` and to
    `scipy.special.sph_harm_y` (complex, angles instead of directions).
    """
    dirs = check_nonzero_dirs(dirs)
    lmax = check_lmax_range(check_lmax(lmax), dirs.dtype, REAL_SH_MAX_LMAX, "`real_sh`")
    if not isinstance(coeffs_first, (bool, np.bool_)):
        raise ValueError(f"`coeffs_first` must be a bool, got {coeffs_first!r}")
    where = row_sharding(dirs) if lmax > _UNROLLED_LMAX else None
    if where is not None:  # each device's directions on that device (`row_sharding`)
        return _real_sh_rows(dirs, lmax, bool(coeffs_first), where)
    return _real_sh_jit(dirs, lmax, bool(coeffs_first))


@jit
def _real_sh_rows(dirs, lmax, coeffs_first, where):
    return on_row_shards(lambda d: _real_sh_body(d, lmax, coeffs_first), where, (dirs,), out_axis=int(coeffs_first))


@jit
def _real_sh_jit(dirs, lmax, coeffs_first=False):
    return _real_sh_body(dirs, lmax, coeffs_first)


def _real_sh_body(dirs, lmax, coeffs_first=False):
    batch = dirs.shape[:-1]
    flat = dirs.reshape(-1, 3)
    out = _real_sh_flat(_unit_vectors(flat), lmax, coeffs_first)
    n = (lmax + 1) ** 2
    return out.reshape((n,) + batch if coeffs_first else batch + (n,))


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
    lmax = check_lmax_range(check_lmax(lmax), dirs.dtype, REAL_SH_MAX_LMAX, "`complex_sh`")
    where = row_sharding(dirs) if lmax > _UNROLLED_LMAX else None
    if where is not None:
        return _complex_sh_rows(dirs, lmax, where)
    return _complex_sh_jit(dirs, lmax)


@jit
def _complex_sh_jit(dirs, lmax):
    return _complex_from_real(_real_sh_body(dirs, lmax), lmax)


@jit
def _complex_sh_rows(dirs, lmax, where):
    return on_row_shards(lambda d: _complex_from_real(_real_sh_body(d, lmax), lmax), where, (dirs,))
