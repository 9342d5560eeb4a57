"""Spherical-harmonic analysis and synthesis on lat-long grids; scattered fits.

Real SH in the flat layout of docs/conventions.md. A lat-long image is `(H, W)` (one
channel) or `(H, W, C)`; its coefficients are `(n_coeffs,)` or
`(n_coeffs, C)`.

The transforms separate variables (the standard fast route, as ducc0 and
s2fft do): a DFT along φ for every row (for analysis up to moderate lmax, the
lmax+1 needed frequencies as small matrix products on the rows in place,
`_row_dft_matmul`; otherwise an FFT), then, for every order m, a sum over
rows of the normalized associated Legendre functions $\\bar P_l^m(\\cos\\theta_i)$
(a batched matrix product). Cost $O(HW\\log W + H\\,l_{max}^2)$; no per-pixel
$Y_{lm}$ matrix is ever formed. The Legendre table is generated in the
graph (a `lax.scan` over l), never embedded as a constant.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

from ._compile import by_platform, jit
from ._checks import (error_if_any, as_float_array, check_dirs, check_lmax, check_lmax_range, check_nonzero_dirs, check_positive_int,
                      coeff_layout)
from ._grids import fejer1_weights, latlong_angles
from ._indexing import sh_degrees, sh_orders
from ._sh import _real_sh_flat, _recurrence_tables, _unit_vectors


# The largest `lmax` of `project_latlong` / `synthesize_latlong` below float64 and in float64
# (`jaxsh._checks.check_lmax_range`): in float32 on a (2 lmax + 2)-square grid, synthesis erred 1.8e-2 against an
# image RMS of 57 at lmax 200, 0.30 at 216 and 3.7 at 232 (the seeds sin(theta)^m flush to 0 in float32)
TRANSFORM_MAX_LMAX = (200, 1900)


def _legendre_scan(theta: np.ndarray, lmax: int, dtype, body, init):
    r"""Run `body` over l = 0..lmax with the Legendre rows of that l.

    `body(acc, parity, l, p_l)` receives the static parity of l (0 or 1, a
    Python int), the traced l and $p_l[m, h] = \sqrt{2-\delta_{m0}}\,
    \bar P_l^m(\cos\theta_h)$ (zero for m > l), and returns `(acc, out)`.
    Same normalized recurrence as the basis (`_sh`), seeded with
    $\bar q_m^m \sin^m\theta$ so no $1/\sin^m$ factor is ever formed. A seed
    that underflows is not negligible: the recurrence over l grows it back to
    order 1, so `TRANSFORM_MAX_LMAX` bounds `lmax` per dtype. Never
    materializes the whole `(l, m, h)` table: the transforms contract each
    row as it is made. The scan runs over pairs (l even, l odd) so that the
    bodies can specialize on the parity statically; a padding step beyond
    lmax has $p_l = 0$. The outputs are stacked as `(lmax+1, ...)`.
    """
    a, b, d = (np.asarray(t) for t in _recurrence_tables(lmax))
    npairs = (lmax + 2) // 2
    pad = 2 * npairs - (lmax + 1)
    a, b, d = (jnp.asarray(np.pad(t, ((0, pad), (0, 0))).reshape(npairs, 2, -1), dtype) for t in (a, b, d))
    z = jnp.asarray(np.cos(theta), dtype)
    m = np.arange(lmax + 1)
    sinpow = jnp.asarray(np.sin(theta)[None, :] ** m[:, None], dtype)  # (m, h)

    def step(carry, xs):
        q1, q2, acc = carry
        al, bl, dl, l0 = xs
        outs = []
        for par in (0, 1):
            ql = al[par][:, None] * (z[None, :] * q1) - bl[par][:, None] * q2 + dl[par][:, None] * sinpow
            acc, out = body(acc, par, l0 + par, ql)
            outs.append(out)
            q1, q2 = ql, q1
        return (q1, q2, acc), outs

    zeros = jnp.zeros_like(sinpow)
    (_, _, acc), outs = jax.lax.scan(step, (zeros, zeros, init), (a, b, d, jnp.arange(0, 2 * npairs, 2)))
    if outs[0] is not None:
        outs = jax.tree.map(lambda e, o: jnp.stack([e, o], axis=1).reshape((2 * npairs,) + e.shape[1:])[: lmax + 1], outs[0], outs[1])
    return acc, outs


def _half_rows(h: int):
    """Rows 0..ceil(H/2)-1 and their mirror images (θ ↔ π−θ)."""
    hc = (h + 1) // 2
    top = np.arange(hc)
    bot = h - 1 - top
    return hc, top, bot


def _flat_gather_indices(lmax: int):
    ls = sh_degrees(lmax)
    ms = sh_orders(lmax)
    return ls, np.abs(ms), ms < 0


def _check_image(image):
    image = as_float_array(image, "image")
    if image.ndim not in (2, 3) or image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"`image` must have shape (H, W) or (H, W, C) with H, W >= 1, got {tuple(image.shape)}")
    return image


def project_latlong(
    image: Real[ArrayLike, "H W *C"], lmax: int, *, allow_aliasing: bool = False
) -> Float[Array, "n_coeffs *C"]:
    """Real SH coefficients of a lat-long map: $c_{lm} = \\int f\\,Y_{lm}\\,d\\omega$.

    The integral is the exact Fejér-first-rule quadrature of the grid
    (`latlong_weights`): for a map that is band-limited to $L$ it returns the
    exact coefficients when $l_{max} + L < H$ and $W > l_{max} + L$ (in
    particular `synthesize_latlong` followed by `project_latlong` is the
    identity for $l_{max} < H/2$, $W > 2 l_{max}$).

    Computed as $c_{l,\\pm m} = \\sum_i w_i \\bar P_l^m(\\cos\\theta_i)
    \\cdot(\\mathrm{Re}, -\\mathrm{Im})\\,F_{im}$ with $F_{im} = \\frac{2\\pi}{W}\\sum_j
    f_{ij} e^{-im\\phi_j}$ (a DFT per row: matrix products, or an FFT for large lmax).

    **Arguments:**

    - `image`: `(H, W)` or `(H, W, C)`, row `i` ↔ θ = π(i+½)/H from +z, column
      `j` ↔ φ = 2π(j+½)/W from +x (docs/conventions.md). Any float dtype; the result
      has the same dtype.
    - `lmax`: band limit (static int).
    - `allow_aliasing`: the grid resolves band limits $l_{max} < H/2$ with
      $W > 2 l_{max}$ only; beyond that the quadrature aliases (a constant
      map gets $|c_{l>0}|$ up to 4.4), so by default such an `lmax` is a
      `ValueError` naming `lmax` and the image size. Pass
      `allow_aliasing=True` to compute the (aliased) sums anyway.

    **Returns:** `(n_coeffs,)` or `(n_coeffs, C)`. NaN in, NaN out (a pure
    array kernel, see `jaxsh._checks`).

    Comparable to `ducc0.sht.analysis_2d(..., geometry="F1")` (ducc0 uses the
    complex, m ≥ 0 layout).
    """
    image = _check_image(image)
    lmax = check_lmax_range(check_lmax(lmax), image.dtype, TRANSFORM_MAX_LMAX, "`project_latlong`")
    if not isinstance(allow_aliasing, bool):
        raise ValueError(f"`allow_aliasing` must be a bool, got {allow_aliasing!r}")
    h, w = image.shape[:2]
    if not allow_aliasing and (2 * lmax >= h or 2 * lmax >= w):
        raise ValueError(
            f"`lmax` = {lmax} aliases on a {h}x{w} lat-long image: the grid resolves lmax < H/2 and "
            f"lmax < W/2 (here lmax <= {max(min((h - 1) // 2, (w - 1) // 2), 0)}); use a larger image, "
            "a smaller `lmax`, or pass allow_aliasing=True"
        )
    if image.ndim == 3 and image.shape[2] == 0:  # no channel: no coefficient (the row DFT's split has no width)
        return jnp.zeros(((lmax + 1) ** 2, 0), image.dtype)
    return _project(image, lmax)


def _use_dft_matmul(lmax: int, w: int) -> bool:
    """Row DFT as matrix products (cost ~ W lmax) rather than an FFT (~ W log W plus a transpose).

    Measured on 1024x2048x3 (one thread): the products win up to lmax 128 at least (about 3x at
    lmax 32, 1.3x at lmax 128), so they are used up to lmax + 1 = 16 log2 W orders.
    """
    return bool(lmax + 1 <= 16 * np.log2(max(w, 2)))


def _dft_split(w: int) -> int:
    """Outer length R of the row split j = B r + s (R divides W): the divisor of W nearest 128."""
    divs = [d for d in range(1, w + 1) if w % d == 0]
    return min(divs, key=lambda d: (abs(np.log2(d / 128.0)), -d))


def _row_dft_matmul(f, lmax: int):
    r"""$(\mathrm{Re}, \mathrm{Im}) \sum_j f_{ijc} e^{-i m \phi_j}$ for m = 0..lmax, each `(H, M, C)`.

    Only the lowest `lmax + 1` of the W frequencies are needed, so instead of an
    FFT (and the `(H, W, C) -> (H, C, W)` transpose it needs) each row is
    split as $j = B r + s$ ($R = W / B$ outer, B inner samples) and
    $\sum_j f_j e^{-i m\phi_j} = \sum_s e^{-2\pi i m (s+\frac12)/W}
    \sum_r e^{-2\pi i m r / R} f_{Br+s}$: the inner sum is a matrix product
    `(2M, R) @ (R, B C)` on the row as it lies in memory, the outer sum a
    twiddle and a reduction over s. For even R the half-turn symmetry
    $e^{-i m (\phi + \pi)} = (-1)^m e^{-i m \phi}$ halves the product: even
    orders see $f_r + f_{r+R/2}$, odd orders $f_r - f_{r+R/2}$ (r < R/2).
    Exact in exact arithmetic (no truncation); the tables are NumPy
    constants of the static shapes, their angles reduced exactly (integer
    arithmetic) before the cosines are taken.
    """
    h, w, c = f.shape
    dtype = f.dtype
    big_r = _dft_split(w)
    b = w // big_r
    fold = big_r % 2 == 0
    m_all = np.arange(lmax + 1)
    groups = (m_all[0::2], m_all[1::2]) if fold else (m_all,)
    nr = big_r // 2 if fold else big_r
    r = np.arange(nr)
    s = np.arange(b)
    hp = jax.lax.Precision.HIGHEST
    tabs = []
    for m in groups:
        ang_r = 2 * np.pi * (np.outer(m, r) % big_r) / big_r
        a_tab = jnp.asarray(np.concatenate([np.cos(ang_r), -np.sin(ang_r)], axis=0), dtype)  # (2 Mg, nr)
        ang_s = np.pi * (np.outer(m, 2 * s + 1) % (2 * w)) / w
        tabs.append((a_tab, jnp.asarray(np.cos(ang_s)[:, :, None], dtype), jnp.asarray(-np.sin(ang_s)[:, :, None], dtype)))
    order = np.concatenate(groups)
    inv = np.argsort(order)

    def row(x):  # (R, B C) -> (M, C), (M, C)
        parts = (x[:nr] + x[nr:], x[:nr] - x[nr:]) if fold else (x,)
        res, ims = [], []
        for (a_tab, cs, sn), xp in zip(tabs, parts):
            if a_tab.shape[0] == 0:
                continue
            y = jnp.dot(a_tab, xp, precision=hp).reshape(2, -1, b, c)
            yc, ys = y[0], y[1]
            res.append(jnp.sum(cs * yc - sn * ys, axis=1))
            ims.append(jnp.sum(cs * ys + sn * yc, axis=1))
        re, im = jnp.concatenate(res, axis=0), jnp.concatenate(ims, axis=0)
        return re[inv], im[inv]

    # One row at a time on a CPU (each row's product in cache; measured fastest there, docs/performance.md);
    # on other platforms (GPU) all rows as one batched product, not H sequential steps of small kernels.
    return by_platform(f.reshape(h, big_r, b * c), cpu=lambda x: jax.lax.map(row, x), other=jax.vmap(row))


@jit
def _project(image, lmax):
    squeeze = image.ndim == 2
    f = image[..., None] if squeeze else image
    h, w, _ = f.shape
    dtype = f.dtype
    theta, _ = latlong_angles(h, w)
    roww = fejer1_weights(h) * (2 * np.pi / w)
    if _use_dft_matmul(lmax, w):
        re, im = _row_dft_matmul(f, lmax)  # (H, M, C) each
    else:
        m = np.arange(lmax + 1)
        ft = jnp.moveaxis(f, 1, -1)  # (H, C, W)
        if lmax <= w // 2:
            spec = jnp.fft.rfft(ft, axis=-1)[..., : lmax + 1]
        else:
            spec = jnp.fft.fft(ft, axis=-1)[..., m % w]
        # e^{-i m phi_j} = e^{-i m pi / W} e^{-2 pi i m j / W}
        spec = spec * jnp.asarray(np.exp(-1j * np.pi * m / w), spec.dtype)[None, None, :]
        spec = jnp.moveaxis(spec, -1, 1)  # (H, M, C)
        re, im = jnp.real(spec), jnp.imag(spec)
    # Quadrature weights in theta and phi.
    rw = jnp.asarray(roww[:, None, None], dtype)
    g = jnp.concatenate([re * rw, im * rw], axis=-1)  # (H, M, 2C)
    # Fold the rows about the equator: even/odd parts in z.
    hc, top, bot = _half_rows(h)
    gbot = g[bot]
    if h % 2:
        gbot = gbot.at[hc - 1].set(0.0)  # the equator row is its own mirror
    g_even = jnp.transpose(g[top] + gbot, (1, 0, 2))  # (M, Hc, 2C)
    g_odd = jnp.transpose(g[top] - gbot, (1, 0, 2))
    # P_l^m(-z) = (-1)^{l+m} P_l^m(z): for even l the even-m rows pair with the even part, the odd-m
    # rows with the odd part; for odd l the other way round. One contraction per (l, m).
    m_even = jnp.asarray(np.arange(lmax + 1) % 2 == 0)[:, None, None]
    g_for = (jnp.where(m_even, g_even, g_odd), jnp.where(m_even, g_odd, g_even))

    def body(acc, par, l, pl):
        return acc, jnp.einsum("mh,mhk->mk", pl, g_for[par])

    _, out = _legendre_scan(theta[:hc], lmax, dtype, body, None)  # (L, M, 2C)
    nc = f.shape[-1]
    cre, cim = out[..., :nc], out[..., nc:]
    ls, am, neg = _flat_gather_indices(lmax)
    coeffs = jnp.where(neg[:, None], -cim[ls, am], cre[ls, am])  # (n, C)
    return coeffs[:, 0] if squeeze else coeffs


def synthesize_latlong(
    coeffs: Real[ArrayLike, "n_coeffs *C"], height: int, width: int
) -> Float[Array, "H W *C"]:
    """Evaluate a real SH expansion on the pixel centres of a lat-long map.

    $f(\\theta_i, \\phi_j) = \\sum_{lm} c_{lm} Y_{lm}(\\theta_i, \\phi_j)$ by a
    Legendre sum per order m and an inverse FFT along φ (any width: orders
    above W/2 alias exactly as point evaluation would).

    **Arguments:**

    - `coeffs`: `(n_coeffs,)` or `(n_coeffs, C)`, n_coeffs = (lmax+1)².
    - `height`, `width`: the map size (static ints).

    **Returns:** `(height, width)` or `(height, width, C)` in the dtype of
    `coeffs`.
    """
    coeffs = as_float_array(coeffs, "coeffs")
    if coeffs.ndim not in (1, 2):
        raise ValueError(f"`coeffs` must have shape (n_coeffs,) or (n_coeffs, C), got {tuple(coeffs.shape)}")
    lmax, _ = coeff_layout(coeffs.shape, "coeffs", channels=coeffs.ndim == 2)
    check_lmax_range(lmax, coeffs.dtype, TRANSFORM_MAX_LMAX, "`synthesize_latlong`")
    h = check_positive_int(height, "height")
    w = check_positive_int(width, "width")
    return _synthesize(coeffs, lmax, h, w)


@jit
def _synthesize(coeffs, lmax, h, w):
    squeeze = coeffs.ndim == 1
    c = coeffs[:, None] if squeeze else coeffs
    dtype = c.dtype
    theta, _ = latlong_angles(h, w)
    n1 = lmax + 1
    # Dense (l, m) arrays of c_{l,m} and c_{l,-m} (zero for m > l).
    l_idx, m_idx = np.meshgrid(np.arange(n1), np.arange(n1), indexing="ij")
    valid = m_idx <= l_idx
    pos = np.where(valid, l_idx * l_idx + l_idx + m_idx, 0)
    negi = np.where(valid, l_idx * l_idx + l_idx - m_idx, 0)
    vmask = jnp.asarray(valid[..., None], dtype)
    a = c[pos] * vmask
    b = c[negi] * vmask * jnp.asarray((m_idx > 0)[..., None], dtype)
    ab = jnp.concatenate([a, b], axis=-1)  # (L, M, 2C)
    hc, top, bot = _half_rows(h)
    ab = jnp.pad(ab, ((0, 1), (0, 0), (0, 0)))  # the padding step of the pair scan reads row lmax+1

    def body(acc, par, l, pl):
        term = pl[:, :, None] * ab[l][:, None, :]  # (M, Hc, 2C)
        acc = list(acc)
        acc[par] = acc[par] + term  # sums over even l and over odd l
        return tuple(acc), None

    zero = jnp.zeros((n1, hc, ab.shape[-1]), dtype)
    (sum_even_l, sum_odd_l), _ = _legendre_scan(theta[:hc], lmax, dtype, body, (zero, zero))
    # even part in z: (l + m) even; odd part: (l + m) odd.
    m_even = jnp.asarray(np.arange(n1) % 2 == 0)[:, None, None]
    even = jnp.where(m_even, sum_even_l, sum_odd_l)
    odd = jnp.where(m_even, sum_odd_l, sum_even_l)
    upper = even + odd
    lower = (even - odd)[:, ::-1]
    if h % 2:
        lower = lower[:, 1:]
    s_all = jnp.transpose(jnp.concatenate([upper, lower], axis=1), (1, 2, 0))  # (H, 2C, M)
    nc = c.shape[-1]
    sre, sim = s_all[:, :nc], s_all[:, nc:]
    m = np.arange(n1)
    shift = np.exp(1j * np.pi * m / w)
    z = jax.lax.complex(sre, -sim)
    z = z * jnp.asarray(shift, z.dtype)[None, None, :]
    if lmax < w / 2:
        scale = np.where(m == 0, w, w / 2)
        spec = z * jnp.asarray(scale, z.dtype)[None, None, :]
        spec = jnp.pad(spec, ((0, 0), (0, 0), (0, w // 2 + 1 - n1)))
        out = jnp.fft.irfft(spec, n=w, axis=-1)
    else:
        reps = -(-n1 // w)
        zp = jnp.pad(z, ((0, 0), (0, 0), (0, reps * w - n1)))
        folded = zp.reshape(zp.shape[:-1] + (reps, w)).sum(axis=-2)
        out = jnp.real(jnp.fft.ifft(folded, axis=-1)) * w
    out = jnp.moveaxis(out.astype(dtype), -1, 1)  # (H, W, C)
    return out[..., 0] if squeeze else out


def fit_sh(
    dirs: Real[ArrayLike, "N 3"],
    values: Real[ArrayLike, "N *C"],
    lmax: int,
    weights: Real[ArrayLike, " N"] | None = None,
    ridge: float | Real[ArrayLike, ""] = 0.0,
) -> Float[Array, "n_coeffs *C"]:
    """Least-squares SH coefficients of scattered samples.

    Minimizes $\\sum_k w_k\\,(\\sum_i c_i Y_i(\\omega_k) - v_k)^2 + \\lambda \\lVert c\\rVert^2$
    per channel, by an SVD least-squares solve of the whitened, augmented
    system $[\\sqrt{w}\\,Y;\\ \\sqrt\\lambda I]\\,c = [\\sqrt{w}\\,v;\\ 0]$ (the
    minimum-norm solution when the samples do not determine every
    coefficient and $\\lambda = 0$).

    **Arguments:**

    - `dirs`: `(N, 3)` sample directions (normalized here).
    - `values`: `(N,)` or `(N, C)`.
    - `lmax`: band limit (static int).
    - `weights`: optional `(N,)` non-negative sample weights (e.g. solid angles).
    - `ridge`: $\\lambda \\ge 0$ (may be traced).

    **Returns:** `(n_coeffs,)` or `(n_coeffs, C)`.

    Comparable to `numpy.linalg.lstsq(Y, values)`.
    """
    dirs = check_nonzero_dirs(dirs)
    lmax = check_lmax(lmax)
    values = as_float_array(values, "values")
    if dirs.ndim != 2:
        raise ValueError(f"`dirs` must have shape (N, 3), got {tuple(dirs.shape)}")
    n = dirs.shape[0]
    if values.ndim not in (1, 2) or values.shape[0] != n:
        raise ValueError(f"`values` must have shape ({n},) or ({n}, C) to match `dirs`, got {tuple(values.shape)}")
    if weights is not None:
        weights = as_float_array(weights, "weights")
        if weights.shape != (n,):
            raise ValueError(f"`weights` must have shape ({n},), got {tuple(weights.shape)}")
    if jnp.ndim(ridge) != 0:
        raise ValueError(f"`ridge` must be a scalar (one lambda for every coefficient), got shape {jnp.shape(ridge)}")
    dtype = jnp.result_type(dirs.dtype, values.dtype)
    return _fit_sh(dirs.astype(dtype), values.astype(dtype), lmax, weights, jnp.asarray(ridge, dtype))


@jit
def _fit_sh(dirs, values, lmax, weights, ridge):
    squeeze = values.ndim == 1
    v = values[:, None] if squeeze else values
    dtype = v.dtype
    ridge = error_if_any(ridge, ridge < 0, "`ridge` must be >= 0")
    y = _real_sh_flat(_unit_vectors(dirs), lmax)
    if weights is not None:
        weights = error_if_any(weights, jnp.any(weights < 0), "`weights` must be non-negative")
        sw = jnp.sqrt(weights)[:, None]
        y = y * sw
        v = v * sw
    nc = y.shape[1]
    a = jnp.concatenate([y, jnp.sqrt(ridge) * jnp.eye(nc, dtype=dtype)], axis=0)
    rhs = jnp.concatenate([v, jnp.zeros((nc, v.shape[1]), dtype)], axis=0)
    c, *_ = jnp.linalg.lstsq(a, rhs)
    return c[:, 0] if squeeze else c
