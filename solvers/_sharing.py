"""Reflectance sharing (Zickler et al. 2006): fitting RBF (S)BRDFs to images.

`fit_sharing` solves the saddle-point system of eq. 10 (with the smoothing
of sec. 5.1) for the linear-kernel, degree-1 RBF of eqs. 12–13 and selects
centres greedily (sec. 6, after Carr et al. 2001). The paper's models are
built on it:

* `fit_homogeneous` — a homogeneous BRDF $f(u, v, w)$ (eq. 12);
* `fit_sbrdf` — a smoothly varying SBRDF $f(x, y, u, v, w)$ (eq. 13);
* `fit_dichromatic` — $I_k = s_k(a_k(\\vec x)\\,d_k(\\vec q) + g(\\vec q))\\cos\\theta_i$
  with a median albedo map (eq. 14);
* `fit_one_image` — $I_k = s_k(a_k(\\vec x) + g(x, y, u, v))\\cos\\theta_i$ from
  one decomposed image (eq. 15);

each with a `render` method that predicts radiance under new lighting and
views. The image-sample conventions are those of `jaxsh`: directions point
away from the surface (`light` = $\\omega_i$, `view` = $\\omega_o$), radiance
$I = \\rho\\,E\\cos\\theta_i$ for a directional source of irradiance $E$ at
normal incidence (DESIGN.md, "capture manifest").

??? cite "References"
    Zickler, T., Ramamoorthi, R., Enrique, S., Belhumeur, P. N. (2006).
    Reflectance sharing: predicting appearance from a sparse set of images
    of a known shape. IEEE TPAMI 28(8), 1287–1302.
    doi:10.1109/TPAMI.2006.170

    Carr, J. C., Beatson, R. K., Cherrie, J. B., Mitchell, T. J., Fright,
    W. R., McCallum, B. C., Evans, T. R. (2001). Reconstruction and
    representation of 3D objects with radial basis functions. SIGGRAPH 2001,
    67–76. doi:10.1145/383259.383266

    Wahba, G. (1990). *Spline Models for Observational Data*. SIAM
    (smoothing splines; the $\\Psi - \\rho I$ regularization).
"""

from __future__ import annotations

import operator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

import jaxsh
from jaxsh._rbf import _evaluate, _safe_sqrt, _sq_dist, auto_chunk

STATUS_NAMES = ("success", "tol_not_reached", "singular")


# --------------------------------------------------------------------------- input checks


def _concrete(x):
    """A NumPy copy of `x`, or None when `x` is a tracer."""
    try:
        return np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


def _as_float(x, name):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"`{name}` must be real, got dtype {x.dtype}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _check_int(v, name, lo=1):
    if isinstance(v, bool):
        raise ValueError(f"`{name}` must be an int >= {lo}, got {v!r}")
    try:
        v = operator.index(v)
    except TypeError:
        raise ValueError(f"`{name}` must be a static Python int >= {lo}, got {v!r}") from None
    if v < lo:
        raise ValueError(f"`{name}` must be an int >= {lo}, got {v}")
    return v


def _check_inputs(points, values, scale, weights):
    points = _as_float(points, "points")
    if points.ndim != 2:
        raise ValueError(f"`points` must have shape (N, d), got {tuple(points.shape)}")
    n, d = points.shape
    values = _as_float(values, "values")
    single = values.ndim == 1
    if single:
        values = values[:, None]
    if values.ndim != 2 or values.shape[0] != n:
        raise ValueError(f"`values` must have shape ({n},) or ({n}, C) to match `points` {(n, d)}, got {tuple(values.shape)}")
    if n < d + 1:
        raise ValueError(
            f"too few samples: `points` has {n} rows but a degree-1 polynomial in {d}-D needs at least d + 1 = {d + 1}"
        )
    if scale is None:
        scale = jnp.ones((d,))
    scale = _as_float(scale, "scale")
    if scale.ndim == 0:
        scale = jnp.broadcast_to(scale, (d,))
    if scale.shape != (d,):
        raise ValueError(f"`scale` must have shape ({d},) (the diagonal of M, eq. 11), got {tuple(scale.shape)}")
    if weights is not None:
        weights = _as_float(weights, "weights")
        if weights.shape != (n,):
            raise ValueError(f"`weights` must have shape ({n},), got {tuple(weights.shape)}")
    arrays = [points, values, scale] + ([] if weights is None else [weights])
    dt = max((a.dtype for a in arrays), key=lambda t: jnp.dtype(t).itemsize)
    points, values, scale = points.astype(dt), values.astype(dt), scale.astype(dt)
    weights = None if weights is None else weights.astype(dt)
    return points, values, scale, weights, single


def _check_values(p, v, s, w):
    """Value checks on concrete input (NaNs, scale, duplicates, coplanarity)."""
    for name, a in (("points", p), ("values", v), ("scale", s), ("weights", w)):
        if a is not None and not np.all(np.isfinite(a)):
            bad = int(np.sum(~np.isfinite(a)))
            raise ValueError(f"`{name}` contains {bad} non-finite entries (NaN or inf)")
    if not np.all(s > 0):
        raise ValueError(f"`scale` (the diagonal of M, eq. 11) must be positive, got {s}")
    n, d = p.shape
    _, first, counts = np.unique(p, axis=0, return_index=True, return_counts=True)
    if np.any(counts > 1):
        i = int(first[np.argmax(counts > 1)])
        dup = int(np.sum(counts[counts > 1] - 1))
        raise ValueError(
            f"`points` has {dup} duplicate rows (e.g. row {i}, {p[i].tolist()}); the RBF system (eq. 10) is "
            "singular with repeated centres — merge or drop duplicate samples"
        )
    rank = _affine_rank(p)
    if rank < d:
        raise ValueError(
            f"`points` are degenerate: their affine hull has dimension {rank} < d = {d} (e.g. coplanar data, or a "
            "coordinate that is constant such as w in a single image), so the degree-1 polynomial part of eq. 10 "
            "is not determined; drop that coordinate (cf. eq. 15) or add samples"
        )


def _affine_rank(p):
    c = p - p.mean(axis=0, keepdims=True)
    span = np.max(np.abs(c), axis=0)
    c = c / np.where(span > 0, span, 1.0)[None, :]
    if c.shape[0] > 4096:  # rank of the Gram matrix of a random subset is enough to spot exact degeneracy
        sv = np.linalg.svd(c, compute_uv=False)
    else:
        sv = np.linalg.svd(c, compute_uv=False)
    tol = sv.max(initial=0.0) * max(c.shape) * np.finfo(c.dtype).eps * 10
    return int(np.sum(sv > tol))


# --------------------------------------------------------------------------- the saddle-point solve (eq. 10)


def _poly_basis(x, shift, pscale):
    """[1, (x - shift)/pscale] for x (B, d) -> (B, d + 1)."""
    xh = (x - shift[None, :]) / pscale[None, :]
    return jnp.concatenate([jnp.ones_like(xh[:, :1]), xh], axis=1)


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


def _poly_normalization(points):
    lo = jnp.min(points, axis=0)
    hi = jnp.max(points, axis=0)
    shift = 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    return shift, jnp.where(half > 0.0, half, jnp.ones_like(half))


@eqx.filter_jit
def _interpolate(points, values, scale, smoothing):
    shift, pscale = _poly_normalization(points)
    active = jnp.ones((points.shape[0],), dtype=bool)
    lam, poly = _solve_saddle(points, values, active, scale, smoothing, shift, pscale)
    ok = jnp.all(jnp.isfinite(lam)) & jnp.all(jnp.isfinite(poly))
    return lam, poly, ok


class _GreedyState(eqx.Module):
    idx: Int[Array, " Kp"]
    count: Int[Array, ""]
    is_center: Array
    lam: Float[Array, "K C"]
    poly: Float[Array, "d1 C"]
    rel: Float[Array, ""]
    round: Int[Array, ""]
    hist_count: Int[Array, " R"]
    hist_rel: Float[Array, " R"]


@eqx.filter_jit
def _greedy(points, values, weights, scale, smoothing, idx0, count0, is_center, tol, n_centers: int, n_add: int, n_rounds: int, chunk: int):
    n, d = points.shape
    dt = points.dtype
    shift, pscale = _poly_normalization(points)
    wv = values * weights[:, None]
    denom = jnp.sqrt(jnp.mean(jnp.sum(wv * wv, axis=1)))
    denom = jnp.where(denom > 0.0, denom, 1.0)

    def fit_eval(idx, count):
        active = jnp.arange(n_centers) < count
        sel = idx[:n_centers]
        c = points[sel]
        lam, poly = _solve_saddle(c, values[sel], active, scale, smoothing, shift, pscale)
        pred = _evaluate(c, lam, poly, scale, points, chunk)
        res = (values - pred) * weights[:, None]
        e2 = jnp.sum(res * res, axis=1)
        rel = jnp.sqrt(jnp.mean(e2)) / denom
        return lam, poly, e2, rel

    lam, poly, e2, rel = fit_eval(idx0, count0)
    hist_count = jnp.zeros((n_rounds,), dtype=count0.dtype).at[0].set(count0)
    hist_rel = jnp.full((n_rounds,), jnp.nan, dtype=dt).at[0].set(rel)
    state = _GreedyState(idx0, count0, is_center, lam, poly, rel, jnp.asarray(0), hist_count, hist_rel)

    def cond(carry):
        s, _ = carry
        return (s.rel > tol) & (s.count < n_centers) & jnp.isfinite(s.rel) & (s.round + 1 < n_rounds)

    def body(carry):
        s, e2 = carry
        score = jnp.where(s.is_center, -jnp.inf, e2)
        _, new = jax.lax.top_k(score, n_add)
        idx = jax.lax.dynamic_update_slice(s.idx, new.astype(s.idx.dtype), (s.count,))
        count = jnp.minimum(s.count + n_add, n_centers)
        is_center = s.is_center.at[new].set(True)
        lam, poly, e2, rel = fit_eval(idx, count)
        r = s.round + 1
        s = _GreedyState(
            idx, count, is_center, lam, poly, rel, r, s.hist_count.at[r].set(count), s.hist_rel.at[r].set(rel)
        )
        return s, e2

    state, _ = jax.lax.while_loop(cond, body, (state, e2))
    return state


# --------------------------------------------------------------------------- result


class SharingFit(eqx.Module):
    """A fitted RBF (S)BRDF with its fitting record; callable like its model.

    **Fields:**

    - `model`: the `jaxsh.RBFModel` (centres trimmed to those selected).
    - `center_index`: `(K,)` indices into the fitted `points` of the centres,
      in the order they were selected.
    - `history_centers`, `history_rms`: `(R,)` centre count and relative
      weighted RMS residual $\\sqrt{\\sum\\varepsilon_i^2/\\sum(w_i f_i)^2}$ over all
      samples after each greedy round (one entry for interpolation).
    - `status_code`: 0 `"success"`, 1 `"tol_not_reached"` (the centre budget
      ran out before `tol`), 2 `"singular"` (non-finite solution); `status`
      gives the name.

    `fit(points)` evaluates `fit.model(points)`.
    """

    model: jaxsh.RBFModel
    center_index: Int[Array, " K"]
    history_centers: Int[Array, " R"]
    history_rms: Float[Array, " R"]
    status_code: Int[Array, ""]

    def __call__(self, points):
        return self.model(points)

    @property
    def status(self) -> str:
        return STATUS_NAMES[int(self.status_code)]

    @property
    def rms(self):
        return self.history_rms[-1]


def fit_sharing(
    points: Float[Array, "N d"],
    values: Float[Array, "N *C"],
    n_centers: int,
    scale: Float[Array, " d"] | None = None,
    smoothing: float | Float[Array, ""] = 0.0,
    key: Array | None = None,
    *,
    weights: Float[Array, " N"] | None = None,
    tol: float | None = None,
    n_init: int | None = None,
    n_add: int | None = None,
    chunk: int | None = None,
) -> SharingFit:
    """Fit the linear-kernel, degree-1 RBF of Zickler 2006 eqs. 9–13 to scattered samples.

    Solves the saddle-point system of eq. 10 with the smoothing of sec. 5.1,

    $$\\begin{bmatrix} \\Psi - \\rho I & P \\\\ P^\\top & 0 \\end{bmatrix}
      \\begin{bmatrix} \\lambda \\\\ c \\end{bmatrix} = \\begin{bmatrix} g \\\\ 0 \\end{bmatrix},\\quad
      \\Psi_{ij} = \\|M(\\vec q_i - \\vec q_j)\\|,\\; M = \\mathrm{diag}(\\text{scale}),$$

    by **LU with partial pivoting of the full $(K + d + 1)^2$ matrix**
    (`jnp.linalg.solve`): the linear kernel is only conditionally positive
    definite ($\\Psi$ has one positive and $K - 1$ negative eigenvalues on
    generic data), so Cholesky does not apply; LU on the whole indefinite
    system is exact in exact arithmetic and was faster and more accurate in
    float32 than a null-space (Schur) Cholesky. One factorization serves all
    channels (batched right-hand sides). The polynomial is solved in
    coordinates shifted and scaled to $[-1, 1]$ (for conditioning) and
    returned in raw coordinates.

    With `n_centers == N` every sample is a centre; with `smoothing = 0` the
    result interpolates and equals `scipy.interpolate.RBFInterpolator(points
    * scale, values, kernel="linear", degree=1, smoothing=smoothing)`
    evaluated at `x * scale` (scipy's kernel is $-r$, so its smoothing is
    this $\\rho$).

    With `n_centers < N` centres are chosen greedily (sec. 6, after Carr et
    al. 2001): start from `n_init` random samples (plus the samples at the
    extremes of each coordinate, so the polynomial is determined), fit,
    evaluate the weighted residuals $\\varepsilon_i = (f_i - \\tilde f(\\vec q_i))\\,w_i$
    (the paper's $w_i = \\cos\\theta_i$) at all samples, append the `n_add`
    worst samples (Euclidean norm over channels) and repeat, until the
    relative RMS residual is below `tol` or `n_centers` are used. The system
    is padded to `n_centers` (unused rows decoupled with unit diagonal), so
    the whole loop is one `jax.lax.while_loop` compiled once. Each round
    refactors the padded matrix ($\\frac23 K^3$ flops) rather than updating
    an inverse: an incremental inverse update was measured to diverge
    (PEERS.md), and at $N \\gg K$ the residual evaluation ($O(NK)$) costs
    about as much as the factorization.

    **Precision.** Fit in float64: the saddle-point matrices have condition
    numbers of $10^4$–$10^6$ for 1,000–5,000 centres. Float32 input is
    accepted (the fit then runs in float32 and is accurate to ≈1e-3
    relative on small problems); the fitted model can be cast to float32 for
    evaluation.

    **Arguments:**

    - `points`: `(N, d)` sample points, $(u, v, w)$ or $(x, y, u, v, w)$
      (see `jaxsh.sbrdf_points`), or any $d \\ge 1$.
    - `values`: `(N,)` or `(N, C)` samples (channels last).
    - `n_centers`: static int, $d + 1 \\le$ `n_centers` $\\le N$.
    - `scale`: `(d,)` the diagonal of $M$ (eq. 11), positive; default ones.
    - `smoothing`: $\\rho \\ge 0$ (traced).
    - `key`: PRNG key for the initial random subset (default `PRNGKey(0)`).
    - `weights`: `(N,)` residual weights for the greedy selection (default 1).
    - `tol`: target relative RMS residual for the greedy loop (default: run
      to `n_centers`).
    - `n_init`, `n_add`: initial subset size and centres added per round
      (static; defaults `max(n_centers // 10, d + 2)` and
      `max(n_centers // 10, 1)`).
    - `chunk`: static evaluation chunk (see `jaxsh.RBFModel`).

    **Returns:** a `SharingFit` (callable: `fit(x)` is `(M,)` or `(M, C)`).

    **Raises:** `ValueError` for bad shapes or options, too few samples
    ($N < d + 1$), NaN/inf input, non-positive `scale`, duplicate points and
    degenerate (e.g. coplanar) points — checked on concrete input. A
    singular system met inside the solve is reported as status
    `"singular"`.

    Comparable to `scipy.interpolate.RBFInterpolator(kernel="linear", degree=1)`
    (isotropic, all points as centres).
    """
    points, values, scale, weights, single = _check_inputs(points, values, scale, weights)
    n, d = points.shape
    n_centers = _check_int(n_centers, "n_centers", lo=d + 1)
    if n_centers > n:
        raise ValueError(f"`n_centers` = {n_centers} exceeds the number of samples N = {n}")
    smoothing = jnp.asarray(smoothing, dtype=points.dtype)
    cp, cv, cs = _concrete(points), _concrete(values), _concrete(scale)
    cw = None if weights is None else _concrete(weights)
    sm = _concrete(smoothing)
    if sm is not None and not (np.isfinite(sm) and sm >= 0):
        raise ValueError(f"`smoothing` must be a finite number >= 0, got {sm}")
    if cp is None or cv is None or cs is None:
        raise ValueError("`fit_sharing` checks its input for duplicates and degeneracy: call it outside `jit`")
    _check_values(cp, cv, cs, cw)
    if tol is not None:
        tol = float(tol)
        if not tol >= 0:
            raise ValueError(f"`tol` must be >= 0, got {tol}")
    chunk = auto_chunk(n_centers) if chunk is None else _check_int(chunk, "chunk")

    if n_centers == n:
        lam, poly, ok = _interpolate(points, values, scale, smoothing)
        idx = jnp.arange(n)
        rel = jnp.asarray([0.0 if float(sm) == 0.0 else np.nan], dtype=points.dtype)
        if float(sm) != 0.0:
            w = jnp.ones((n,), points.dtype) if weights is None else weights
            pred = _evaluate(points, lam, poly, scale, points, chunk)
            r = (values - pred) * w[:, None]
            wv = values * w[:, None]
            rel = (jnp.sqrt(jnp.sum(r * r)) / jnp.sqrt(jnp.sum(wv * wv)))[None]
        hist_c = jnp.asarray([n])
        code = jnp.asarray(0 if bool(ok) else 2)
    else:
        n_add = max(n_centers // 10, 1) if n_add is None else _check_int(n_add, "n_add")
        n_init = max(n_centers // 10, d + 2) if n_init is None else _check_int(n_init, "n_init", lo=d + 1)
        n_init = min(n_init, n_centers)
        key = jax.random.PRNGKey(0) if key is None else key
        idx0 = _initial_subset(cp, n_init, n_centers, key)
        count0 = len(idx0)
        pad = np.zeros(n_centers + n_add, dtype=np.int32)
        pad[:count0] = idx0
        n_rounds = 2 + -(-(n_centers - min(count0, n_centers)) // n_add)
        w = jnp.ones((n,), points.dtype) if weights is None else weights
        t = jnp.asarray(-1.0 if tol is None else tol, dtype=points.dtype)
        is_c = np.zeros(n, dtype=bool)
        is_c[idx0] = True
        st = _greedy(points, values, w, scale, smoothing, jnp.asarray(pad), jnp.asarray(min(count0, n_centers)),
                     jnp.asarray(is_c), t,
                     n_centers, n_add, n_rounds, chunk)
        k = int(st.count)
        lam, poly = st.lam[:k], st.poly
        idx = st.idx[:k]
        r = int(st.round) + 1
        hist_c, rel = st.hist_count[:r], st.hist_rel[:r]
        final = float(st.rel)
        if not np.isfinite(final):
            code = 2
        elif tol is not None and final > tol:
            code = 1
        else:
            code = 0
        code = jnp.asarray(code)
    centers = points[idx]
    if single:
        lam, poly = lam[:, 0], poly[:, 0]
    model = jaxsh.RBFModel(centers, lam, poly, scale, chunk=chunk)
    return SharingFit(model, idx, hist_c, rel, code)


def _initial_subset(p, n_init, n_centers, key):
    """Random subset plus the per-coordinate extreme samples, affinely spanning (concrete)."""
    n, d = p.shape
    extremes = np.unique(np.concatenate([np.argmin(p, axis=0), np.argmax(p, axis=0)]))
    perm = np.asarray(jax.random.permutation(key, n))
    chosen = list(dict.fromkeys(list(extremes) + list(perm[: max(n_init, 1)])))[: max(n_init, len(extremes))]
    pos = max(n_init, 1)
    while _affine_rank(p[np.asarray(chosen)]) < d and pos < n:
        extra = perm[pos : pos + d + 1]
        chosen = list(dict.fromkeys(chosen + list(extra)))
        pos += d + 1
    if len(chosen) > n_centers:
        raise ValueError(
            f"`n_centers` = {n_centers} is too small: {len(chosen)} initial centres are needed to determine the "
            "degree-1 polynomial (the coordinate extremes); raise `n_centers`"
        )
    return np.asarray(chosen, dtype=np.int32)
