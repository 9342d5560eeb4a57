"""Radial-basis-function reflectance representation (Zickler et al. 2006) — evaluation and the linear solve.

The interpolant of Zickler 2006 eqs. 9, 11–13 with the linear kernel
$\\psi(r) = r$ and a degree-1 polynomial,

$$\\tilde f(\\vec q) = c_0 + \\sum_k c_k q_k + \\sum_{i=1}^{K} \\lambda_i\\,\\|M(\\vec q - \\vec q_i)\\|,$$

with the diagonal metric $M = \\mathrm{diag}(m_1, \\dots, m_d)$ of eq. 11
(`scale`): $\\mathrm{diag}(1, 1, m_w)$ for homogeneous BRDFs in $(u, v, w)$
(eq. 12), $\\mathrm{diag}(m_{xy}, m_{xy}, 1, 1, m_w)$ for spatially varying
ones in $(x, y, u, v, w)$ (eq. 13). The polynomial is in the *unscaled*
coordinates (it spans the same space as one in the scaled coordinates).

Layout: centres `(K, d)`, kernel weights `(K, C)`, polynomial coefficients
`(d + 1, C)` (row 0 the constant, row $1 + k$ the coefficient of $q_k$) —
channels last. The saddle-point solve of eq. 10 for given centres is
`rbf_fit` (all samples as centres) and `rbf_solve` (the padded,
active-mask form used inside a jitted loop); greedy centre selection and
the input checks on data (duplicates, degeneracy) are `solvers.fit_sharing`;
the shape checks of both are `rbf_check_samples`.

**Cost and memory.** Evaluation at $M$ points is $O(M K d)$; the points are
processed in chunks of `chunk` rows with `jax.lax.map`, so at most a
`(chunk, K)` distance matrix exists at a time. Distances are accumulated
coordinate by coordinate as 2-D broadcasts $\\sum_k (m_k q_k - m_k q_{i,k})^2$
(not the $|a|^2 + |b|^2 - 2a\\cdot b$ matrix-product trick, which loses
about $10^{-6}$ relative accuracy next to the centres), with the scaled
centres stored transposed, `(d, K)`, so that the inner loop over the centres
reads contiguous memory and vectorises; then one matrix
product with the weights handles all channels. The square root is guarded
(double `where`), so gradients with respect to the points are finite — and
the kernel's contribution zero — exactly at a centre, where $\\|\\cdot\\|$
has no derivative.

??? cite "References"
    Zickler, T., Ramamoorthi, R., Enrique, S., Belhumeur, P. N. (2006).
    Reflectance sharing: predicting appearance from a sparse set of images
    of a known shape. IEEE TPAMI 28(8), 1287–1302.
    doi:10.1109/TPAMI.2006.170 (eqs. 7, 9–15).

    Carr, J. C. et al. (2001). Reconstruction and representation of 3D
    objects with radial basis functions. SIGGRAPH 2001, 67–76.
    doi:10.1145/383259.383266
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, Real
from ._compile import jit
from ._custom_types import SequenceLike

from ._checks import as_float_array, is_traced
from ._reflectance import _frame, _prepare, _rusinkiewicz_local, _to_local, _uvw

# Elements of the largest (chunk, K) distance block when `chunk` is automatic.
_AUTO_BLOCK = 1 << 21
_COUNT_BLOCKS = 4  # blocks of centres of a `count`-limited evaluation (`_evaluate`)


def rbf_auto_chunk(n_centers: int) -> int:
    """The default evaluation chunk of `RBFModel` for `n_centers` centres (static).

    The largest power of two, between 64 and 16384, with at most ≈2M
    distances in a `(chunk, n_centers)` block.

    **Arguments:** `n_centers`: Python int.

    **Returns:** a Python int.
    """
    c = max(64, min(16384, _AUTO_BLOCK // max(int(n_centers), 1)))
    return int(1 << (c.bit_length() - 1))  # a power of two


def _safe_sqrt(x):
    ok = x > 0.0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def scaled_distances(
    a: Real[ArrayLike, "Na d"], b: Real[ArrayLike, "Nb d"], scale: Real[ArrayLike, " d"] | SequenceLike | None = None
) -> Float[Array, "Na Nb"]:
    """Anisotropic distances $\\|M(a_i - b_j)\\|$, $M = \\mathrm{diag}$(`scale`) (Zickler 2006 eq. 11).

    Accumulated per coordinate as 2-D broadcasts of $(a_{ik} - b_{jk})\\,s_k$: exactly zero at
    $a_i = b_j$, whatever contraction the compiler applies. Not chunked: the result is `(Na, Nb)`.

    **Arguments:** `a` `(Na, d)`, `b` `(Nb, d)`, `scale` `(d,)` or `None` (identity).

    **Returns:** `(Na, Nb)`.
    """
    a = as_float_array(a, "a")
    b = as_float_array(b, "b")
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"`a` and `b` must have shapes (Na, d) and (Nb, d), got {a.shape} and {b.shape}")
    d = a.shape[1]
    s = _check_scale(scale, d, a.dtype)
    dt = _widest(a, b, s)
    return _scaled_distances_jit(a.astype(dt), b.astype(dt), s.astype(dt))


def _sq_dist(a_s, b_s):
    """Squared distances of already-scaled points `(Na, d)`, `(Nb, d)`, unrolled over the coordinates."""
    return _sq_dist_t(a_s, b_s.T)


def _sq_dist_t(a_s, b_s_t, scale=None):
    """`_sq_dist` with the second set passed *transposed*, `(d, Nb)`.

    Each coordinate row `b_s_t[k]` is then contiguous, so the inner loop over
    `Nb` of the fused elementwise kernel vectorises (a strided column of a
    `(Nb, d)` array does not: evaluation is ≈1.3–1.6× slower that way).

    With `scale` `(d,)`, the points are raw and each coordinate's difference is
    scaled: exactly zero at $a_i = b_j$ whatever the compiler does. Scaling first,
    `a*s - b*s` may be contracted to `fma(a, s, -(b*s))`, the rounding error of
    `b*s`, not zero (seen at XLA's backend optimization levels 0-2: 1e-17 in float64).
    """
    r2 = None
    for k in range(a_s.shape[1]):
        diff = a_s[:, k][:, None] - b_s_t[k][None, :]
        if scale is not None:
            diff = diff * scale[k]
        r2 = diff * diff if r2 is None else r2 + diff * diff
    return r2


def _distances(a, b, s):
    return _safe_sqrt(_sq_dist_t(a, b.T, s))


_scaled_distances_jit = jit(_distances)


def _widest(*arrays):
    return max((x.dtype for x in arrays), key=lambda t: jnp.dtype(t).itemsize)


def _check_scale(scale, d: int, dtype):
    if scale is None:
        return jnp.ones((d,), dtype=dtype)
    s = as_float_array(scale, "scale")
    if s.ndim == 0:
        s = jnp.broadcast_to(s, (d,))
    if s.shape != (d,):
        raise ValueError(f"`scale` must have shape ({d},) (the diagonal of M, eq. 11), got {tuple(s.shape)}")
    return s


def _poly_eval(points, poly):
    """c_0 + Σ_k c_k q_k for points (B, d), poly (d+1, C) -> (B, C)."""
    return poly[0][None, :] + points @ poly[1:]


def _evaluate(centers, weights, poly, scale, points, chunk: int, count=None):
    """Chunked evaluation, points (M, d) -> (M, C); with `count` (traced int) only the first `count` centres.

    With `count`, the weights beyond `count` are masked to 0 and the K centres are split into `_COUNT_BLOCKS`
    blocks of one static size; a `fori_loop` over the first ceil(count / block) blocks adds each block's
    whole chunked evaluation, so the work follows `count` (the greedy loop of `solvers.fit_sharing` pads K)
    with one compiled block. (A loop over blocks of centres *inside* each chunk of points ran 1.6-2x slower
    per centre than this loop of whole-block kernels.)
    """
    m, d = points.shape
    if count is not None:
        k = centers.shape[0]
        bc = -(-k // _COUNT_BLOCKS)
        kp = bc * _COUNT_BLOCKS
        count = jnp.clip(jnp.asarray(count), 0, k)
        lam = jnp.where((jnp.arange(k) < count)[:, None], weights, 0.0)
        if kp > k:  # zero-weight padding to whole blocks
            centers = jnp.concatenate([centers, jnp.broadcast_to(centers[:1], (kp - k, d))], axis=0)
            lam = jnp.pad(lam, ((0, kp - k), (0, 0)))
        zero = jnp.zeros_like(poly)

        def step(j, acc):
            c = jax.lax.dynamic_slice_in_dim(centers, j * bc, bc, 0)
            w = jax.lax.dynamic_slice_in_dim(lam, j * bc, bc, 0)
            return acc + _evaluate(c, w, zero, scale, points, chunk)

        base = jnp.broadcast_to(_poly_eval(points, poly), (m, poly.shape[1]))
        return jax.lax.fori_loop(0, (count + bc - 1) // bc, step, base)
    cs_t = (centers * scale[None, :]).T  # (d, K), contiguous rows (see `_sq_dist`)

    def block(p):
        r = _safe_sqrt(_sq_dist_t(p * scale[None, :], cs_t))
        return r @ weights + _poly_eval(p, poly)

    if m <= chunk:
        return block(points)
    n_chunks = -(-m // chunk)
    pad = n_chunks * chunk - m
    pp = jnp.concatenate([points, jnp.broadcast_to(points[:1], (pad, d))], axis=0) if pad else points
    out = jax.lax.map(block, pp.reshape(n_chunks, chunk, d))
    return out.reshape(n_chunks * chunk, -1)[:m]


class RBFModel(eqx.Module):
    """An RBF interpolant with linear kernel and degree-1 polynomial (Zickler 2006 eqs. 9, 11–13).

    $$\\tilde f(\\vec q) = c_0 + \\sum_k c_k q_k + \\sum_i \\lambda_i\\,\\|M(\\vec q - \\vec q_i)\\|,\\quad
      M = \\mathrm{diag}(\\text{scale}).$$

    Built by `rbf_fit` (interpolation), by `solvers.fit_sharing` (greedy
    centres), or by hand.

    **Fields:**

    - `centers`: `(K, d)` centres $\\vec q_i$.
    - `weights`: `(K, C)` kernel weights $\\lambda_i$ (one column per channel).
    - `poly`: `(d + 1, C)` polynomial coefficients $(c_0, c_1, \\dots, c_d)$.
    - `scale`: `(d,)` the diagonal of $M$ (eq. 11).
    - `channels`: static; `None` for a scalar function (calls return `(M,)`),
      else `C` (calls return `(M, C)`).
    - `chunk`: static evaluation chunk (rows of points per block); default
      `rbf_auto_chunk(K)`.

    Calling the model, `model(points)` with `points` `(M, d)` (or `(d,)`),
    returns `(M,)`/`(M, C)` (or `()`/`(C,)`). The call is jitted; the
    dtype is the widest of the model's and the points' (evaluation in
    float32 is accurate to ≈1e-5 relative for 1,000-5,000 centres and runs
    ≈3× faster than float64 on CPU; the fitted coefficients should
    come from a float64 fit, see `solvers.fit_sharing`).
    """

    centers: Float[Array, "K d"]
    weights: Float[Array, "K C"]
    poly: Float[Array, "d1 C"]
    scale: Float[Array, " d"]
    channels: int | None = eqx.field(static=True)
    chunk: int = eqx.field(static=True)

    def __init__(self, centers, weights, poly, scale=None, chunk: int | None = None):
        centers = as_float_array(centers, "centers")
        if centers.ndim != 2 or centers.shape[0] < 1:
            raise ValueError(f"`centers` must have shape (K, d), got {tuple(centers.shape)}")
        k, d = centers.shape
        weights = as_float_array(weights, "weights")
        poly = as_float_array(poly, "poly")
        if weights.ndim == 1:
            if weights.shape != (k,) or poly.shape != (d + 1,):
                raise ValueError(
                    f"scalar model: `weights` must have shape ({k},) and `poly` ({d + 1},), "
                    f"got {tuple(weights.shape)} and {tuple(poly.shape)}"
                )
            self.channels = None
            weights, poly = weights[:, None], poly[:, None]
        else:
            c = weights.shape[-1]
            if weights.shape != (k, c) or poly.shape != (d + 1, c):
                raise ValueError(
                    f"`weights` must have shape ({k}, C) and `poly` ({d + 1}, C), "
                    f"got {tuple(weights.shape)} and {tuple(poly.shape)}"
                )
            self.channels = c
        s = _check_scale(scale, d, centers.dtype)
        dt = _widest(centers, weights, poly, s)
        self.centers = centers.astype(dt)
        self.weights = weights.astype(dt)
        self.poly = poly.astype(dt)
        self.scale = s.astype(dt)
        self.chunk = rbf_auto_chunk(k) if chunk is None else int(chunk)
        if self.chunk < 1:
            raise ValueError(f"`chunk` must be a positive int, got {chunk}")

    def astype(self, dtype) -> "RBFModel":
        """The same model with its arrays cast to `dtype` (e.g. float32 for fast evaluation)."""
        return RBFModel(self.centers.astype(dtype), self.weights.astype(dtype) if self.channels else self.weights[:, 0].astype(dtype),
                        self.poly.astype(dtype) if self.channels else self.poly[:, 0].astype(dtype), self.scale.astype(dtype), self.chunk)

    @property
    def dim(self) -> int:
        return self.centers.shape[1]

    @property
    def n_centers(self) -> int:
        return self.centers.shape[0]

    def __call__(self, points: Real[ArrayLike, "*M d"]) -> Float[Array, "..."]:
        p = as_float_array(points, "points")
        d = self.dim
        single = p.ndim == 1
        if single:
            p = p[None, :]
        if p.ndim != 2 or p.shape[1] != d:
            raise ValueError(f"`points` must have shape (M, {d}) or ({d},), got {tuple(jnp.shape(points))}")
        dt = _widest(p, self.centers)
        out = _call(self, p.astype(dt))
        if self.channels is None:
            out = out[..., 0]
        return out[0] if single else out


@jit
def _call(model, points):
    dt = points.dtype
    return _evaluate(
        model.centers.astype(dt), model.weights.astype(dt), model.poly.astype(dt), model.scale.astype(dt), points, model.chunk
    )


def rbf_evaluate(
    centers: Real[ArrayLike, "K d"],
    weights: Real[ArrayLike, "K *C"],
    poly: Real[ArrayLike, "d1 *C"],
    points: Real[ArrayLike, "M d"],
    scale: Real[ArrayLike, " d"] | SequenceLike | None = None,
    chunk: int | None = None,
    *,
    count: int | Int[ArrayLike, ""] | None = None,
) -> Float[Array, "M *C"]:
    """Evaluate the RBF interpolant of Zickler 2006 eqs. 12–13 at `points` (chunked).

    Functional form of `RBFModel(centers, weights, poly, scale, chunk)(points)`.

    **Arguments:** `centers` `(K, d)`; `weights` `(K,)` or `(K, C)`; `poly`
    `(d + 1,)` or `(d + 1, C)`; `points` `(M, d)`; `scale` `(d,)` (default
    ones); `chunk` static rows per block; `count`: only the first `count`
    centres contribute (an integer scalar, may be traced; clipped to
    `[0, K]`; default all): the result equals the evaluation with
    `weights[count:] = 0`, at the cost of the smallest quarter of K that
    holds `count` centres rather than of K. For a system padded to a fixed K whose
    used rows lead, as in `solvers.fit_sharing`'s greedy loop.

    **Returns:** `(M,)` or `(M, C)`.
    """
    model = RBFModel(centers, weights, poly, scale, chunk)
    if count is None:
        return model(points)
    c = jnp.asarray(count)
    if c.shape != () or not jnp.issubdtype(c.dtype, jnp.integer):
        raise ValueError(f"`count` must be an integer scalar, got shape {c.shape} and dtype {c.dtype}")
    p = as_float_array(points, "points")
    if p.ndim != 2 or p.shape[1] != model.dim:
        raise ValueError(f"`points` must have shape (M, {model.dim}), got {tuple(p.shape)}")
    dt = _widest(p, model.centers)
    out = _call_count(model, p.astype(dt), c)
    return out[..., 0] if model.channels is None else out


@jit
def _call_count(model, points, count):
    dt = points.dtype
    return _evaluate(model.centers.astype(dt), model.weights.astype(dt), model.poly.astype(dt), model.scale.astype(dt),
                     points, model.chunk, count)


# --------------------------------------------------------------------------- the saddle-point solve (eq. 10)


def _poly_basis(x, shift, pscale):
    """[1, (x - shift)/pscale] for x (B, d) -> (B, d + 1)."""
    xh = (x - shift[None, :]) / pscale[None, :]
    return jnp.concatenate([jnp.ones_like(xh[:, :1]), xh], axis=1)


def _poly_normalization(lo, hi):
    """Shift and half-width mapping the box [lo, hi] to [-1, 1] (unit half-width where lo == hi)."""
    shift = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    return shift, jnp.where(half > 0.0, half, jnp.ones_like(half))


def _solve_saddle(centers, rhs, active, scale, smoothing, shift, pscale):
    """Solve eq. 10 with Ψ − ρI for the active centres; inactive rows are decoupled (weight 0).

    LU with partial pivoting on the full symmetric-indefinite matrix (one
    factorization, all channels as right-hand sides). Returns kernel weights
    (K, C) and polynomial coefficients (d+1, C) in the *raw* coordinates.
    """
    k, d = centers.shape
    dt = centers.dtype
    cs = centers * scale[None, :]
    psi = _safe_sqrt(_sq_dist(cs, cs))
    eye = jnp.eye(k, dtype=dt)
    am = active.astype(dt)
    outer = am[:, None] * am[None, :]
    psi = psi * outer - smoothing * eye * am[None, :] + eye * (1.0 - am)[None, :]
    p = _poly_basis(centers, shift, pscale) * am[:, None]
    top = jnp.concatenate([psi, p], axis=1)
    bottom = jnp.concatenate([p.T, jnp.zeros((d + 1, d + 1), dtype=dt)], axis=1)
    a = jnp.concatenate([top, bottom], axis=0)
    b = jnp.concatenate([rhs * am[:, None], jnp.zeros((d + 1, rhs.shape[1]), dtype=dt)], axis=0)
    sol = jnp.linalg.solve(a, b)
    lam = sol[:k]
    ch = sol[k:]
    # back to raw coordinates: c0 + Σ c_k (x_k - m_k)/s_k
    lin = ch[1:] / pscale[:, None]
    c0 = ch[0] - jnp.sum(lin * shift[:, None], axis=0)
    poly = jnp.concatenate([c0[None, :], lin], axis=0)
    return lam, poly


def _solve_core(centers, values, active, scale, smoothing, lo, hi):
    shift, pscale = _poly_normalization(lo, hi)
    return _solve_saddle(centers, values, active, scale, smoothing, shift, pscale)


_solve_jit = jit(_solve_core)


def rbf_check_samples(
    points: Real[ArrayLike, "N d"],
    values: Real[ArrayLike, "N *C"],
    scale: Real[ArrayLike, " d"] | SequenceLike | None = None,
    *,
    name: str = "points",
) -> tuple[Float[Array, "N d"], Float[Array, "N C"], Float[Array, " d"], bool]:
    """Shape and dtype checks of RBF samples (Zickler 2006 eqs. 9–13): the arguments of `rbf_fit` / `rbf_solve`.

    Shared by `rbf_fit`, `rbf_solve` and `solvers.fit_sharing`, so all of
    them reject bad shapes with the same `ValueError` (naming the argument
    and the expected shape). Only shapes and dtypes are checked (jit-safe):
    values (NaN, duplicate or degenerate points, the sign of `scale`) are
    not.

    **Arguments:** `points` `(N, d)`, $N \\ge 1$ (called `name` in the
    messages, e.g. `"centers"`); `values` `(N,)` or `(N, C)`; `scale` `(d,)`
    or a scalar, the diagonal of $M$ (eq. 11), default ones.

    **Returns:** `(points, values, scale, single)`: `(N, d)`, `(N, C)` (a
    column added for `(N,)` values, then `single` is True), `(d,)`, all of
    the widest floating dtype of `points` and `values` (the dtype rules of
    the package: integers to the default float, float16 and complex
    rejected).
    """
    points = as_float_array(points, name)
    if points.ndim != 2 or points.shape[0] < 1:
        raise ValueError(f"`{name}` must have shape (N, d) with N >= 1, got {tuple(points.shape)}")
    k, d = points.shape
    values = as_float_array(values, "values")
    given = tuple(values.shape)
    single = values.ndim == 1
    if single:
        values = values[:, None]
    if values.ndim != 2 or values.shape[0] != k:
        raise ValueError(f"`values` must have shape ({k},) or ({k}, C) to match `{name}` {(k, d)}, got {given}")
    dt = _widest(points, values)
    s = _check_scale(scale, d, dt).astype(dt)
    return points.astype(dt), values.astype(dt), s, single


def _check_solve_inputs(centers, values, scale, smoothing):
    c, v, s, single = rbf_check_samples(centers, values, scale, name="centers")
    rho = as_float_array(smoothing, "smoothing")
    if rho.ndim != 0:
        raise ValueError(f"`smoothing` must be a scalar, got shape {tuple(rho.shape)}")
    return c, v, s, rho.astype(c.dtype), single


def _check_regular(c, rho) -> None:
    """`rbf_fit`'s host checks of concrete centres: no repeated row when `rho` is 0 (or traced), and
    $[1, \\vec q]$ of full column rank (`rbf_fit`'s docstring). Traced centres pass unchecked."""
    if is_traced(c):
        return
    q = np.asarray(c, dtype=np.float64)
    if is_traced(rho) or float(rho) == 0.0:
        order = np.lexsort(q.T[::-1])
        same = np.all(q[order[1:]] == q[order[:-1]], axis=1)
        if np.any(same):
            i, j = sorted(order[np.argmax(same):][:2])
            raise ValueError(
                f"`centers` rows {i} and {j} are equal ({q[i].tolist()}): with `smoothing` = 0 the RBF system "
                "(Zickler 2006 eq. 10) is singular; merge repeated samples (solvers.fit_sharing does) or give a "
                "positive `smoothing`"
            )
    lo, hi = q.min(axis=0), q.max(axis=0)
    box = np.where(hi > lo, hi - lo, 1.0)
    p = np.concatenate([np.ones((q.shape[0], 1)), 2.0 * (q - lo) / box - 1.0], axis=1)  # as `rbf_solve` builds P
    rank = np.linalg.matrix_rank(p)
    if rank < p.shape[1]:
        raise ValueError(
            f"`centers` lie in an affine subspace of dimension {rank - 1} of their {q.shape[1]}-D space (e.g. "
            "coplanar in 3-D): the degree-1 polynomial of the RBF system (Zickler 2006 eq. 10) is not determined; "
            "drop the constant coordinates or use solvers.fit_sharing, which reports such data as a status"
        )


def rbf_solve(
    centers: Real[ArrayLike, "K d"],
    values: Real[ArrayLike, "K *C"],
    scale: Real[ArrayLike, " d"] | SequenceLike | None = None,
    smoothing: float | Real[ArrayLike, ""] = 0.0,
    active: Bool[ArrayLike, " K"] | None = None,
    bounds: tuple[Real[ArrayLike, " d"], Real[ArrayLike, " d"]] | None = None,
) -> tuple[Float[Array, "K *C"], Float[Array, "d1 *C"]]:
    """Kernel weights and polynomial of the RBF of Zickler 2006 eqs. 9–13 through given centres (eq. 10).

    Solves the saddle-point system of eq. 10 with the smoothing of sec. 5.1,

    $$\\begin{bmatrix} \\Psi - \\rho I & P \\\\ P^\\top & 0 \\end{bmatrix}
      \\begin{bmatrix} \\lambda \\\\ c \\end{bmatrix} = \\begin{bmatrix} g \\\\ 0 \\end{bmatrix},\\quad
      \\Psi_{ij} = \\|M(\\vec q_i - \\vec q_j)\\|,\\; M = \\mathrm{diag}(\\text{scale}),$$

    by **LU with partial pivoting of the full $(K + d + 1)^2$ matrix**
    (`jnp.linalg.solve`): the linear kernel is only conditionally positive
    definite ($\\Psi$ has one positive and $K - 1$ negative eigenvalues on
    generic data), so Cholesky does not apply. One factorization serves all
    channels. The polynomial block $P = [1, \\hat q]$ is built in
    coordinates $\\hat q$ mapped from the box `bounds` $= (lo, hi)$ to
    $[-1, 1]$ (for conditioning); the returned coefficients are in raw
    coordinates.

    **Padded form.** With `active` (bool `(K,)`), only the active rows are
    centres: the inactive rows and columns of $\\Psi$ and $P$ are zeroed
    and given a unit diagonal, so their weights are exactly 0 and the active
    part is the system of the active centres alone. The shapes stay fixed
    whatever the number of active centres, so a greedy selection loop can
    call this inside one `jax.lax.while_loop` (see `solvers.fit_sharing`).

    No value checks (jit-safe): repeated or affinely degenerate active
    centres make the system singular: the result is non-finite, or finite and
    meaningless (measured on 30 random draws with one duplicated centre: 28
    finite, weights up to 2e18 and an error of 513 at the centres on data of
    order 1). Check the interpolant at the centres, as `solvers.fit_sharing`
    does (eq. 10), when the points are not known to be distinct.

    **Arguments:**

    - `centers`: `(K, d)` centres $\\vec q_i$.
    - `values`: `(K,)` or `(K, C)` values $g$ at the centres.
    - `scale`: `(d,)` the diagonal of $M$ (eq. 11); default ones.
    - `smoothing`: $\\rho \\ge 0$ (traced scalar).
    - `active`: `(K,)` bool, default all `True`.
    - `bounds`: `(lo, hi)`, each `(d,)`, the box of the polynomial
      normalization; default the bounding box of `centers` (all rows).

    **Returns:** `(weights, poly)`: `(K,)`/`(K, C)` kernel weights
    $\\lambda$ and `(d + 1,)`/`(d + 1, C)` polynomial coefficients
    $(c_0, c_1, \\dots, c_d)$ — the arguments of `RBFModel`/`rbf_evaluate`.
    """
    c, v, s, rho, single = _check_solve_inputs(centers, values, scale, smoothing)
    k, d = c.shape
    if active is None:
        act = jnp.ones((k,), dtype=bool)
    else:
        act = jnp.asarray(active)
        if act.shape != (k,) or act.dtype != jnp.bool_:
            raise ValueError(f"`active` must be a bool array of shape ({k},), got {act.dtype} {tuple(act.shape)}")
    if bounds is None:
        lo, hi = jnp.min(c, axis=0), jnp.max(c, axis=0)
    else:
        try:
            lo, hi = bounds
        except (TypeError, ValueError):
            raise ValueError("`bounds` must be a pair (lo, hi) of (d,) arrays") from None
        lo, hi = as_float_array(lo, "bounds").astype(c.dtype), as_float_array(hi, "bounds").astype(c.dtype)
        if lo.shape != (d,) or hi.shape != (d,):
            raise ValueError(f"`bounds` must be a pair (lo, hi) of ({d},) arrays, got {tuple(lo.shape)} and {tuple(hi.shape)}")
    lam, poly = _solve_jit(c, v, act, s, rho, lo, hi)
    return (lam[:, 0], poly[:, 0]) if single else (lam, poly)


def rbf_fit(
    centers: Real[ArrayLike, "K d"],
    values: Real[ArrayLike, "K *C"],
    scale: Real[ArrayLike, " d"] | SequenceLike | None = None,
    smoothing: float | Real[ArrayLike, ""] = 0.0,
    chunk: int | None = None,
) -> RBFModel:
    """The RBF interpolant (or smoothing spline) of Zickler 2006 eqs. 9–13 with every sample a centre.

    `RBFModel(centers, *rbf_solve(centers, values, scale, smoothing), scale, chunk)`:
    the saddle-point system of eq. 10 solved by LU (see `rbf_solve`), the
    polynomial normalized over the bounding box of `centers`. With
    `smoothing = 0` the model interpolates the values at the centres; with
    $\\rho > 0$ it is the smoothing spline $\\Psi - \\rho I$ of sec. 5.1
    (Wahba 1990).

    **Singular systems.** Repeated centres (with `smoothing` = 0) and
    centres in a proper affine subspace (e.g. coplanar in 3-D: the degree-1
    polynomial is then not determined, whatever the smoothing) make eq. 10
    singular, and its solve comes out non-finite or, worse, finite and
    meaningless (`rbf_solve`). Concrete `centers` are therefore checked on
    the host first (a sort of the rows and the rank of $[1, \\vec q]$, both
    far cheaper than the solve): either case is a `ValueError` naming the
    rows or the rank. Under `jit` (traced centres) nothing is checked;
    `solvers.fit_sharing` merges repeated samples, reports degenerate data as
    a status, checks its solve at the centres and adds greedy centre
    selection. Repeated centres with $\\rho > 0$ are allowed: the smoothing
    spline is then a weighted fit (as `scipy.interpolate.RBFInterpolator`).

    **Arguments:** `centers` `(K, d)` with $K \\ge d + 1$; `values` `(K,)` or
    `(K, C)`; `scale` `(d,)` the diagonal of $M$ (eq. 11), default ones;
    `smoothing` $\\rho \\ge 0$ (traced); `chunk` static evaluation chunk
    (default `rbf_auto_chunk(K)`).

    **Returns:** an `RBFModel` (scalar when `values` is `(K,)`).

    Comparable to `scipy.interpolate.RBFInterpolator(centers * scale, values,
    kernel="linear", degree=1, smoothing=smoothing)` evaluated at
    `x * scale` (scipy's kernel is $-r$, so its smoothing is this $\\rho$).
    """
    c, v, s, rho, single = _check_solve_inputs(centers, values, scale, smoothing)
    k, d = c.shape
    if k < d + 1:
        raise ValueError(f"too few centres: `centers` has {k} rows but a degree-1 polynomial in {d}-D needs at least d + 1 = {d + 1}")
    _check_regular(c, rho)
    lam, poly = _solve_jit(c, v, jnp.ones((k,), dtype=bool), s, rho, jnp.min(c, axis=0), jnp.max(c, axis=0))
    if single:
        lam, poly = lam[:, 0], poly[:, 0]
    return RBFModel(c, lam, poly, s, chunk)


# --------------------------------------------------------------------------- sample coordinates


def sbrdf_points(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    xy: Real[ArrayLike, "*#batch 2"] | None = None,
) -> Float[Array, "*batch D"]:
    """Domain points of (S)BRDF samples: $(u, v, w)$ (eq. 7) or $(x, y, u, v, w)$ (eq. 13).

    $(u, v, w)$ = `uvw_from_directions(wi, wo, n)`; with `xy` (surface
    coordinates, Zickler 2006 sec. 7: the surface as a graph over $(x, y)$)
    the spatial coordinates are prepended.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)` (broadcast);
    `xy`: `(..., 2)` or `None`.

    **Returns:** `(..., 3)` or `(..., 5)`.
    """
    wi, wo, n = _prepare([("wi", wi, "dir"), ("wo", wo, "dir"), ("n", n, "dir")])
    if xy is None:
        return _uvw_points(wi, wo, n)
    xy = as_float_array(xy, "xy")
    if xy.ndim < 1 or xy.shape[-1] != 2:
        raise ValueError(f"`xy` must have shape (..., 2), got {tuple(xy.shape)}")
    try:
        batch = jnp.broadcast_shapes(wi.shape[:-1], xy.shape[:-1])
    except ValueError:
        raise ValueError(f"the batch shape of `xy`, {xy.shape[:-1]}, does not broadcast with {wi.shape[:-1]}") from None
    dt = _widest(wi, xy)
    q = _uvw_points(wi.astype(dt), wo.astype(dt), n.astype(dt))
    return jnp.concatenate([jnp.broadcast_to(xy.astype(dt), batch + (2,)), jnp.broadcast_to(q, batch + (3,))], axis=-1)


@jit
def _uvw_points(wi, wo, n):
    t, b = _frame(n)
    th, _, td, pd = _rusinkiewicz_local(_to_local(wi, t, b, n), _to_local(wo, t, b, n))
    return _uvw(th, pd, td)
