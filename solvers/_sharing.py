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
normal incidence (docs/conventions.md, "Lighting").

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
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, Real

import jaxsh

from ._host_random import host_rng
from ._results import Solution, Status, check_float, check_int as _check_int, finish, rms_pair, status_name, worst


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


def _check_inputs(points, values, scale, weights):
    """Shapes and dtypes (`jaxsh.rbf_check_samples`, shared with `jaxsh.rbf_fit`), and the `(N,)` weights."""
    points, values, scale, single = jaxsh.rbf_check_samples(points, values, scale)
    n = points.shape[0]
    if weights is not None:
        weights = _as_float(weights, "weights")
        if weights.shape != (n,):
            raise ValueError(f"`weights` must have shape ({n},) (one per row of `points`), got {tuple(weights.shape)}")
        weights = weights.astype(points.dtype)
    return points, values, scale, weights, single


def _check_values(p, v, s, w):
    """Value checks on concrete input: finite arrays, positive scale, non-negative weights (a `ValueError`)."""
    for name, a in (("points", p), ("values", v), ("scale", s), ("weights", w)):
        if a is not None and not np.all(np.isfinite(a)):
            bad = int(np.sum(~np.isfinite(a)))
            raise ValueError(f"`{name}` contains {bad} non-finite entries (NaN or inf)")
    if not np.all(s > 0):
        raise ValueError(f"`scale` (the diagonal of M, eq. 11) must be positive, got {s}")
    if w is not None and np.any(w < 0):
        raise ValueError(f"`weights` must be >= 0 (residual weights, e.g. cos θi), got {float(np.min(w))}")


def _affine_rank(p):
    c = p - p.mean(axis=0, keepdims=True)
    span = np.max(np.abs(c), axis=0)
    # a coordinate that varies only at rounding level (e.g. w = 1e-16 noise in one image) is constant: per-coordinate
    # scaling would blow its noise up to full rank
    size = np.maximum(np.max(np.abs(p), axis=0), span.max(initial=0.0))
    const = span <= 1e3 * np.finfo(c.dtype).eps * size
    c = np.where(const[None, :], 0.0, c / np.where(span > 0, span, 1.0)[None, :])
    sv = np.linalg.svd(c, compute_uv=False)
    tol = sv.max(initial=0.0) * max(c.shape) * np.finfo(c.dtype).eps * 10
    return int(np.sum(sv > tol))


# --------------------------------------------------------------------------- greedy centre selection (sec. 6)


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
    rss: Float[Array, ""]
    cerr: Float[Array, ""]  # the solve's error at its own centres (`_solve_error`)


_ARGMAX_BLOCK = 1024


def _argmax(x):
    """`jnp.argmax` of a 1-D array (the first maximum; the first NaN if any), in two levels: the blocks' maxima,
    then the maximum of the block that holds the first largest one.

    The same index as `jnp.argmax`, 13x faster at 10⁵ entries on the CPU (XLA's argmax is a variadic
    (value, index) reduction that does not vectorize; a plain max does): the greedy loop's picks call it
    every centre (docs/performance.md). A plain max reduction on the CPU need not propagate NaN, so an input
    whose sum is NaN (a NaN, or both infinities) takes `jnp.argmax` itself (a `lax.cond`; the greedy loop
    stops on a non-finite residual, so that branch is not its path).
    """
    n = x.shape[0]
    b = _ARGMAX_BLOCK
    if n < 2 * b:
        return jnp.argmax(x)
    nb = n // b

    def fast(x):
        head = x[: nb * b].reshape(nb, b)
        j = jnp.argmax(jnp.max(head, axis=1))
        k = j * b + jnp.argmax(jax.lax.dynamic_index_in_dim(head, j, 0, keepdims=False))
        if nb * b == n:
            return k
        kt = nb * b + jnp.argmax(x[nb * b :])
        return jnp.where(x[kt] > x[k], kt, k)  # the head's index unless the tail holds a larger value

    return jax.lax.cond(jnp.isnan(jnp.sum(x)), jnp.argmax, fast, x)


@jaxsh.jit
def _greedy(points, values, weights, scale, smoothing, idx0, count0, is_center, tol, spread, n_centers: int, n_add: int,
            n_rounds: int, chunk: int):
    n, d = points.shape
    dt = points.dtype
    bounds = (jnp.min(points, axis=0), jnp.max(points, axis=0))  # the polynomial box: all samples, every round
    wv = values * weights[:, None]
    denom = jnp.sqrt(jnp.mean(jnp.sum(wv * wv, axis=1)))
    denom = jnp.where(denom > 0.0, denom, 1.0)

    def fit_eval(idx, count):
        active = jnp.arange(n_centers) < count
        sel = idx[:n_centers]
        c = points[sel]
        lam, poly = jaxsh.rbf_solve(c, values[sel], scale, smoothing, active=active, bounds=bounds)
        pred = jaxsh.rbf_evaluate(c, lam, poly, points, scale, chunk=chunk, count=count)  # the used centres only
        res = (values - pred) * weights[:, None]
        e2 = jnp.sum(res * res, axis=1)
        rel = jnp.sqrt(jnp.mean(e2)) / denom
        # eq. 10 at the active centres: f~(q_i) = g_i + rho lambda_i (inactive rows: lambda = 0, masked)
        cerr = jnp.max(jnp.where(active[:, None], jnp.abs(pred[sel] - values[sel] - smoothing * lam), 0.0))
        return lam, poly, e2, rel, cerr

    lam, poly, e2, rel, cerr = fit_eval(idx0, count0)
    hist_count = jnp.zeros((n_rounds,), dtype=count0.dtype).at[0].set(count0)
    hist_rel = jnp.full((n_rounds,), jnp.nan, dtype=dt).at[0].set(rel)
    state = _GreedyState(idx0, count0, is_center, lam, poly, rel, jnp.asarray(0), hist_count, hist_rel, jnp.sum(e2),
                         cerr)

    def cond(carry):
        s, _ = carry
        return (s.rel > tol) & (s.count < n_centers) & jnp.isfinite(s.rel) & (s.round + 1 < n_rounds)

    ps_t = (points * scale[None, :]).T  # the metric M of eq. 11; (d, N)

    def pick(j, carry):
        # the worst sample, preferring one outside the balls claimed by this round's earlier picks (see fit_sharing:
        # "spread"); never a centre already
        sup, base, idx, is_center, count0 = carry
        cand = _argmax(sup)
        cand = jnp.where(sup[cand] > -jnp.inf, cand, _argmax(base))
        pos = count0 + j
        active = jnp.arange(idx.shape[0]) < pos
        # squared distances per coordinate over contiguous rows (a reduction over a minor axis of 2-5 does not vectorize)
        pc = ps_t[:, cand]
        dc2 = sum((ps_t[k][idx] - pc[k]) ** 2 for k in range(d))
        lim = spread * jnp.sqrt(jnp.min(jnp.where(active, dc2, jnp.inf)))  # spread x the distance to the nearest centre
        r2 = sum((ps_t[k] - pc[k]) ** 2 for k in range(d))
        sup = jnp.where((lim > 0) & (r2 < lim * lim), -jnp.inf, sup).at[cand].set(-jnp.inf)
        base = base.at[cand].set(-jnp.inf)
        return sup, base, idx.at[pos].set(cand.astype(idx.dtype)), is_center.at[cand].set(True), count0

    def body(carry):
        s, e2 = carry
        score = jnp.where(s.is_center, -jnp.inf, e2)
        n_new = jnp.minimum(n_add, n_centers - s.count)
        _, _, idx, is_center, _ = jax.lax.fori_loop(0, n_new, pick, (score, score, s.idx, s.is_center, s.count))
        count = s.count + n_new
        lam, poly, e2, rel, cerr = fit_eval(idx, count)
        r = s.round + 1
        s = _GreedyState(
            idx, count, is_center, lam, poly, rel, r, s.hist_count.at[r].set(count), s.hist_rel.at[r].set(rel),
            jnp.sum(e2), cerr,
        )
        return s, e2

    state, _ = jax.lax.while_loop(cond, body, (state, e2))
    return state


# --------------------------------------------------------------------------- result


class SharingFit(Solution):
    """Result of `fit_sharing`: a fitted RBF (S)BRDF with its fitting record; callable like its model.

    **Fields:**

    - `model`: the `jaxsh.RBFModel` (centres trimmed to those selected);
      also `estimate`.
    - `center_index`: `(K,)` indices into the fitted `points` of the centres,
      in the order they were selected.
    - `history_centers`, `history_rms`: `(R,)` centre count and relative
      weighted RMS residual $\\sqrt{\\sum\\varepsilon_i^2/\\sum(w_i f_i)^2}$ over all
      samples after each greedy round (one entry for interpolation).
    - `status`: `Status.converged` (the solve succeeded and, when a `tol`
      was given, `rel_rms <= tol`); `Status.tolerance_not_reached`
      (`rel_rms > tol`: the centre budget ran out before `tol`, or a
      smoothing spline's residual is above it); `Status.singular` (the solve of
      eq. 10 gave a non-finite solution: the model is then the finite affine
      fallback of degenerate data, see `fit_sharing`, and `rms`/`rel_rms`
      are its residual); `Status.nonfinite` (finite solution, non-finite
      residual: `rms`/`rel_rms` are `inf`, never NaN); `Status.no_signal` (all-zero values
      or weights); `Status.ill_conditioned` (degenerate data, see
      `fit_sharing`: too few samples, affinely degenerate or duplicate
      points — a fallback fit, never an exception — or nearly coincident
      points that make the solve miss its own centres: the solve's model,
      not to be trusted).
    - `iterations`: greedy rounds after the initial fit (0 for interpolation).
    - `rms`: weighted RMS residual $\\sqrt{\\sum_{i,c}\\varepsilon_{ic}^2 / (N C)}$ over
      all `N` samples and `C` channels; `rel_rms`: `rms` over the weighted
      RMS of the data, $\\sqrt{\\sum\\varepsilon^2/\\sum(w f)^2}$ (the last
      `history_rms`). Always measured: an interpolant (`smoothing = 0`,
      every sample a centre) has a rounding-level residual (1e-15 float64,
      1e-6 float32), larger only when its solve failed to interpolate.
    - `stats`: `n_centers` (K), `rss` ($\\sum\\varepsilon^2$), `data_ss`
      ($\\sum (w f)^2$), `count` ($N C$) — so fits can be combined with
      `rms_pair` — and `n_merged` (duplicate rows merged, 0 normally).
      `rss`/`data_ss` are `inf` when they exceed the dtype's range (values
      near its square root); `rms`/`rel_rms` are computed in scaled units
      and stay finite.

    `fit(points)` evaluates `fit.model(points)`. `status_code` (0, 1, 2 for
    converged, tolerance not reached, singular/non-finite) is kept,
    deprecated, for old code: use `status`.
    """

    model: jaxsh.RBFModel
    center_index: Int[Array, " K"]
    history_centers: Int[Array, " R"]
    history_rms: Float[Array, " R"]
    status: Status
    iterations: Int[Array, ""]
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    stats: dict

    def __call__(self, points):
        return self.model(points)

    @property
    def estimate(self) -> jaxsh.RBFModel:
        """The fitted `jaxsh.RBFModel`."""
        return self.model

    @property
    def status_code(self) -> Int[Array, ""]:
        """Deprecated integer status (0 converged, 1 tolerance not reached, 2 singular or non-finite): use `status`."""
        return jnp.where(self.status == Status.converged, 0, jnp.where(self.status == Status.tolerance_not_reached, 1, 2))


def fit_sharing(
    points: Real[ArrayLike, "N d"],
    values: Real[ArrayLike, "N *C"],
    n_centers: int,
    scale: Real[ArrayLike, " d"] | Sequence[float] | None = None,
    smoothing: float | Real[ArrayLike, ""] = 0.0,
    key: Array | None = None,
    *,
    weights: Real[ArrayLike, " N"] | None = None,
    tol: float | None = None,
    n_init: int | None = None,
    n_add: int | None = None,
    spread: float = 1.0,
    chunk: int | None = None,
    throw: bool = False,
) -> SharingFit:
    """Fit the linear-kernel, degree-1 RBF of Zickler 2006 eqs. 9–13 to scattered samples.

    Solves the saddle-point system of eq. 10 with the smoothing of sec. 5.1,

    $$\\begin{bmatrix} \\Psi - \\rho I & P \\\\ P^\\top & 0 \\end{bmatrix}
      \\begin{bmatrix} \\lambda \\\\ c \\end{bmatrix} = \\begin{bmatrix} g \\\\ 0 \\end{bmatrix},\\quad
      \\Psi_{ij} = \\|M(\\vec q_i - \\vec q_j)\\|,\\; M = \\mathrm{diag}(\\text{scale}),$$

    by **LU with partial pivoting of the full $(K + d + 1)^2$ matrix**
    (`jnp.linalg.solve`, via `jaxsh.rbf_fit` / `jaxsh.rbf_solve`): the linear kernel is only conditionally positive
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
    worst samples (Euclidean norm over channels; *spread*, see below) and repeat, until the
    relative RMS residual is below `tol` or `n_centers` are used. The system
    is padded to `n_centers` (unused rows decoupled with unit diagonal), so
    the whole loop is one `jax.lax.while_loop` compiled once. Each round
    refactors the padded matrix ($\\frac23 K^3$ flops) rather than updating
    an inverse: an incremental inverse update was measured to diverge
    (docs/performance.md), and at $N \\gg K$ the residual evaluation ($O(NK)$) costs
    about as much as the factorization.

    **Precision.** Fit in float64: the saddle-point matrices have condition
    numbers of $10^4$–$10^6$ for 1,000–5,000 centres. Float32 input is
    accepted (the fit then runs in float32 and is accurate to ≈1e-3
    relative on small problems); the fitted model can be cast to float32 for
    evaluation.

    **Scale.** The fit does not depend on the units of `values` and
    `weights`: internally they are divided by powers of
    two (exact in floating point) so their squares neither overflow nor
    underflow, and the result is returned in the caller's units — `rel_rms`
    is invariant, `rms` scales with `values` and `weights`, and the model
    with `values` (float32 values of 1e±30, or float64 ones of 1e±200, fit
    as the unscaled data do). When `scale` times the extent of the points is
    so large or small that the kernel's squared distances would leave the
    dtype's range (beyond $2^{\\pm e/4}$, $e$ the dtype's largest binary
    exponent: about 1e±77 in float64, 1e±9.6 in float32), $M$ is divided
    by a power of two $\\sigma$ and $\\rho$ by $\\sigma$ — the same function
    ($\\Psi$ is homogeneous of degree 1 in $M$), returned as a model whose
    `scale` is $M/\\sigma$ and whose kernel weights are $\\sigma\\lambda$.

    **Arguments:**

    - `points`: `(N, d)` sample points, $(u, v, w)$ or $(x, y, u, v, w)$
      (see `jaxsh.sbrdf_points`), or any $d \\ge 1$.
    - `values`: `(N,)` or `(N, C)` samples (channels last).
    - `n_centers`: static int, $d + 1 \\le$ `n_centers` $\\le N$ (for
      $N < d + 1$ samples, degenerate data below, any `n_centers` $\\ge 1$).
    - `scale`: `(d,)` the diagonal of $M$ (eq. 11), positive; default ones.
    - `smoothing`: $\\rho \\ge 0$ (traced).
    - `key`: PRNG key for the initial random subset (default `PRNGKey(0)`).
    - `weights`: `(N,)` residual weights for the greedy selection (default 1).
    - `tol`: the requested relative weighted RMS residual `rel_rms`. It
      stops the greedy loop as soon as it is reached, and it is what the
      status judges: a fit whose final `rel_rms` is above `tol` (the centre
      budget ran out first, or a smoothing spline, `smoothing > 0`, that
      does not fit that closely) has status `tolerance_not_reached`, not
      `converged`. Default `None`: run to `n_centers`, and the status then
      only says the solve succeeded — it makes **no claim about the fit's
      quality** (e.g. 300 centres at 19 % error is `converged`); pass `tol`
      to have the quality checked.
    - `n_init`, `n_add`: initial subset size and centres added per round
      (static; defaults `max(n_centers // 10, d + 2)` and
      `max(n_centers // 10, 1)`).
    - `spread`: $s \\ge 0$, how far apart one round's new centres are
      kept (default 1). The picks of a round are made one at a time, worst
      residual first; a pick at $\\vec q_j$ whose nearest centre (earlier
      ones and this round's) is at distance $\\delta_j$ in the metric $M$
      *claims* the ball $\\|M(\\vec q - \\vec q_j)\\| < s\\,\\delta_j$: the
      samples inside are skipped for the rest of the round (they fall back
      to plain worst-first only when every sample is claimed). `spread=0`
      is the plain top-`n_add` rule.

      Why: the `n_add` worst residuals of a round are neighbours — one
      image's specular peak or grazing rim — so plain top-`n_add` puts
      tens of nearly coincident centres in one spot per round. With the
      linear kernel each centre is a cone $\\|M(\\vec q - \\vec q_i)\\|$;
      clusters of cones at the few sampled $w$ (one per image) and sparse
      centres elsewhere make the interpolant at a held-out $w$ vary with
      the azimuth $2\\phi_d$ of $(u, v)$ (eq. 7), which is the azimuth about
      the highlight in the image: *radial streaks* in the prediction error
      of a held-out light. Measured (tests/test_sharing.py
      `test_greedy_spread_removes_radial_streaks`; sphere, 8 lights in a
      0.9 rad cone, 300 centres, $m_w = 0.5$, 6 held-out lights): the
      held-out error on Oren–Nayar falls from 9.5 % to 2.7 % and the
      along-ring part of it (the streaks) from 8.3 % to 2.4 %; on the
      two-lobe Cook–Torrance metal from 3.6 % to 1.2 % (streaks 2.7 % to
      0.8 %). $s = 2$ is within 10 % of $s = 1$; a random subset of the same
      size gives 3.3 %. The cost is $O(n_{add}(N + K)d)$ a round, small next
      to the residual evaluation.
    - `chunk`: static evaluation chunk (see `jaxsh.RBFModel`).
    - `throw`: raise `SolveError` unless the status is `Status.converged`
      (default `False`: check `fit.status`).

    **Returns:** a `SharingFit` (callable: `fit(x)` is `(M,)` or `(M, C)`).

    **Raises:** `ValueError` for bad shapes or options (naming the
    argument), NaN/inf input, non-positive `scale` and negative `weights` —
    checked on concrete input.

    **Degenerate data** is a status, never an exception (or `SolveError`
    with `throw=True`); `rms`/`rel_rms` stay finite:

    - too few samples ($N < d + 1$) or affinely degenerate points (their
      affine hull has dimension $< d$: coplanar data, or a constant
      coordinate such as $w$ in a single image): the degree-1 polynomial of
      eq. 10 is not determined, so the result is the fallback of the
      minimum-norm weighted least-squares affine fit $c_0 + c\\cdot\\vec q$
      (one centre, kernel weight 0), status `ill_conditioned`. Drop the
      constant coordinate (cf. eq. 15) or add samples;
    - duplicate points (eq. 10 is singular with repeated centres): the
      samples at each repeated point are merged — their weighted mean value
      (plain mean where their weights are 0) with the sum of their weights
      (their count without `weights`) — the merged samples are fitted
      (`n_centers` capped at their number, `center_index` pointing at the
      first of each merged group) and `rms`/`rel_rms` are measured on all
      `N` samples as given; status `ill_conditioned`, `stats["n_merged"]`
      the rows merged away and `stats["merged_status"]` the status of the
      fit of the merged samples.

    A singular system met inside the solve (non-finite kernel weights) is
    reported as `Status.singular`; the result is then the finite affine
    fallback above (one centre, kernel weight 0) with its own `rms`/`rel_rms`
    — never a NaN model or residual.

    A numerically singular system with finite weights (nearly coincident
    but distinct points, e.g. 1 ulp apart with different values) is caught
    by checking eq. 10 at the centres: when
    $\\max_i|\\tilde f(\\vec q_i) - g_i - \\rho\\lambda_i|$ exceeds
    $10\\sqrt{\\epsilon}$ of the largest $|g|$ (1.5e-7 float64, 3.5e-3
    float32; well-posed fits measured 1e-14 and 1e-5 at 300–4,000 centres)
    the status is `ill_conditioned` and `rms`/`rel_rms` are the model's
    measured residual. Such a model can be far off between the samples:
    merge or drop the nearly coincident points.

    Comparable to `scipy.interpolate.RBFInterpolator(kernel="linear", degree=1)`
    (isotropic, all points as centres).
    """
    points, values, scale, weights, single = _check_inputs(points, values, scale, weights)
    n, d = points.shape
    # N < d + 1 samples are degenerate data (a fallback fit and a status, below): there `n_centers = N`, the
    # budget `min(budget, N)` of a caller, is accepted (it used to be a ValueError asking for d + 1)
    n_centers = _check_int(n_centers, "n_centers", lo=d + 1 if n >= d + 1 else 1)
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
    chunk = jaxsh.rbf_auto_chunk(n_centers) if chunk is None else _check_int(chunk, "chunk")
    n_add = None if n_add is None else _check_int(n_add, "n_add")
    n_init = None if n_init is None else _check_int(n_init, "n_init", lo=d + 1)
    spread = check_float(spread, "spread")
    # units ("Scale" in the docstring): values, weights and the metric M divided by powers of two (exact), so no
    # square overflows or underflows; the fit is undone into the caller's units by `_rescaled`
    nu = _pow2(np.max(np.abs(cv), initial=0.0))
    om = 1.0 if cw is None else _pow2(np.max(cw, initial=0.0))
    sig = _metric_unit(cp, cs)
    if nu != 1.0:
        cv = (cv.astype(np.float64) / nu).astype(cv.dtype)
        values = jnp.asarray(cv)
    if om != 1.0:
        cw = (cw.astype(np.float64) / om).astype(cw.dtype)
        weights = jnp.asarray(cw)
    if sig != 1.0:
        cs = (cs.astype(np.float64) / sig).astype(cs.dtype)
        scale = jnp.asarray(cs)
        smoothing = smoothing / sig  # (sig Psi' - rho I) lam = (Psi' - rho / sig I)(sig lam): the same function
    fit = _fit_scaled(points, values, weights, scale, smoothing, cp, cv, cw, sm, single, n_centers, key, tol, n_init,
                      n_add, spread, chunk)
    return finish(_rescaled(fit, nu, om), throw)


def _pow2(x) -> float:
    """The power of two `2**e` with `x / 2**e` in [0.5, 1) (1.0 for 0 or a non-finite `x`)."""
    x = float(x)
    if not (np.isfinite(x) and x > 0):
        return 1.0
    return float(np.ldexp(1.0, int(np.frexp(x)[1])))


def _metric_unit(p, s) -> float:
    """1.0, or a power of two dividing `scale` when the scaled extent of the points is so large or small that the
    squared distances of the kernel would overflow or underflow (beyond 2**±(maxexp/4) of the dtype)."""
    p64 = p.astype(np.float64)
    span = np.max(p64, axis=0) - np.min(p64, axis=0)
    span = np.where(span > 0, span, np.maximum(np.max(np.abs(p64), axis=0), 1.0))
    ext = float(np.max(s.astype(np.float64) * span))
    lim = 2.0 ** (np.finfo(p.dtype).maxexp // 4)
    if not (np.isfinite(ext) and ext > 0) or 1.0 / lim <= ext <= lim:
        return 1.0
    return _pow2(ext)


def _rescaled(fit: SharingFit, nu: float, om: float) -> SharingFit:
    """A fit of values / `nu` with weights / `om` in the caller's units: kernel weights and polynomial x `nu`,
    `rms` x `nu om`, `rss`/`data_ss` x `(nu om)**2` (`rel_rms`, the history and the status are unchanged)."""
    if nu == 1.0 and om == 1.0:
        return fit

    def times(a, *factors):  # in float64, then the dtype (an overflow is inf: the value is not representable)
        a = np.asarray(a)
        out = a.astype(np.float64)
        with np.errstate(over="ignore", under="ignore"):
            for f in factors:
                out = out * np.float64(f)
            return jnp.asarray(out.astype(a.dtype))

    model = eqx.tree_at(lambda m: (m.weights, m.poly), fit.model,
                        (times(fit.model.weights, nu), times(fit.model.poly, nu)))
    stats = dict(fit.stats)
    stats["rss"] = times(fit.stats["rss"], nu, om, nu, om)
    stats["data_ss"] = times(fit.stats["data_ss"], nu, om, nu, om)
    return SharingFit(model=model, center_index=fit.center_index, history_centers=fit.history_centers,
                      history_rms=fit.history_rms, status=fit.status, iterations=fit.iterations,
                      rms=times(fit.rms, nu, om), rel_rms=fit.rel_rms, stats=stats)


def _fit_scaled(points, values, weights, scale, smoothing, cp, cv, cw, sm, single, n_centers, key, tol, n_init, n_add,
                spread, chunk) -> SharingFit:
    """`fit_sharing` on checked input in the units of `fit_sharing` (values and weights at most 1 in magnitude)."""
    n, d = points.shape
    # NumPy on the concrete copies: each eager jnp op here compiled a program of its own (15-25 ms a first call)
    w = jnp.asarray(np.ones((n,), cp.dtype)) if weights is None else weights
    wv = cv if cw is None else cv * cw[:, None]
    data_ss = jnp.asarray(np.sum(wv * wv), points.dtype)
    count = n * values.shape[1]
    # degenerate data (docstring): a fallback fit and a status, never an exception
    if n < d + 1:
        return _affine_fallback(points, values, w, scale, single, chunk, data_ss, count)
    if n_centers > n:
        raise ValueError(f"`n_centers` = {n_centers} exceeds the number of samples N = {n}")
    _, first, inverse, counts = np.unique(cp, axis=0, return_index=True, return_inverse=True, return_counts=True)
    if np.any(counts > 1):
        return _merged_fit(points, values, w, weights is not None, first, inverse.reshape(-1), n_centers, scale,
                           smoothing, key, tol, n_init, n_add, spread, chunk, single, data_ss, count)
    if _affine_rank(cp) < d:
        return _affine_fallback(points, values, w, scale, single, chunk, data_ss, count)

    if n_centers == n:
        model = jaxsh.rbf_fit(points, values[:, 0] if single else values, scale, smoothing, chunk=chunk)
        solved = _finite(model.weights, model.poly)
        idx = jnp.arange(n)
        # measured, not assumed 0 for an interpolant: a numerically singular system (nearly coincident points)
        # gave a finite model that missed its own samples, reported as rel_rms 0 and `converged`
        pred = model(points).reshape(n, -1)
        r = (values - pred) * w[:, None]
        rss = jnp.sum(r * r)
        cerr = np.max(np.abs(np.asarray(pred) - cv - float(smoothing) * np.asarray(model.weights).reshape(n, -1)),
                      initial=0.0)
        rounds = 0
        hist_c = jnp.asarray([n])
        hist_rel = rms_pair(rss, data_ss, count)[1][None]
        # a smoothing spline (rho > 0) does not interpolate: its residual is judged against `tol` like a greedy fit's
        reached = tol is None or not float(hist_rel[0]) > tol
    else:
        n_add = max(n_centers // 10, 1) if n_add is None else n_add
        n_init = max(n_centers // 10, d + 2) if n_init is None else n_init
        n_init = min(n_init, n_centers)
        idx0 = _initial_subset(cp, n_init, n_centers, key)  # key None: the draw of PRNGKey(0)
        count0 = len(idx0)
        pad = np.zeros(n_centers + n_add, dtype=np.int32)
        pad[:count0] = idx0
        n_rounds = 2 + -(-(n_centers - min(count0, n_centers)) // n_add)
        t = jnp.asarray(-1.0 if tol is None else tol, dtype=points.dtype)
        is_c = np.zeros(n, dtype=bool)
        is_c[idx0] = True
        st = _greedy(points, values, w, scale, smoothing, jnp.asarray(pad), jnp.asarray(min(count0, n_centers)),
                     jnp.asarray(is_c), t, jnp.asarray(spread, points.dtype),
                     n_centers, n_add, n_rounds, chunk)
        # trimmed on the host (a slice at each centre count k would compile a program per k)
        st = jax.device_get(st)
        k, rounds = int(st.count), int(st.round)
        lam, poly, idx_np = st.lam[:k], st.poly, st.idx[:k]
        hist_c, hist_rel = st.hist_count[: rounds + 1], st.hist_rel[: rounds + 1]
        solved = _finite(lam, poly)
        rss = jnp.asarray(st.rss)
        cerr = float(st.cerr)
        reached = tol is None or not float(st.rel) > tol
        if single:
            lam, poly = lam[:, 0], poly[:, 0]
        idx = jnp.asarray(idx_np)
        model = jaxsh.RBFModel(jnp.asarray(cp[idx_np]), jnp.asarray(lam), jnp.asarray(poly), scale, chunk=chunk)
    if not solved:
        # the solve of eq. 10 failed (non-finite weights): the finite affine fallback, reported as `singular`
        return _affine_fallback(points, values, w, scale, single, chunk, data_ss, count, failed=True)
    return _sharing_fit(model, idx, hist_c, hist_rel, rounds, rss, data_ss, count, solved, reached,
                        degenerate=_inaccurate(cerr, cv))


def _inaccurate(cerr, cv) -> bool:
    """Whether the solve of eq. 10 missed its own centres: $\\max_i|\\tilde f(\\vec q_i) - g_i - \\rho\\lambda_i|$ (0 in
    exact arithmetic) above `_SOLVE_RTOL` $\\sqrt{\\epsilon}$ of the largest $|g|$ (the system is numerically singular:
    nearly coincident distinct points). Measured on well-posed fits: 1e-14 (float64) and 1e-5 (float32) at
    300-4,000 centres; nearly coincident points gave 1e-3 to 1e16."""
    vmax = float(np.max(np.abs(cv), initial=0.0))
    if not (vmax > 0):
        return False
    cerr = float(cerr)
    return not (cerr <= _SOLVE_RTOL * float(np.sqrt(np.finfo(cv.dtype).eps)) * vmax)


_SOLVE_RTOL = 10.0  # x sqrt(eps): 1.5e-7 (float64), 3.5e-3 (float32; the documented float32 accuracy is 1e-3)


@jaxsh.jit
def _rms_pair(rss, data_ss, count):
    """`rms_pair` as one program (its eager ops compiled one program each at a first call)."""
    return rms_pair(rss, data_ss, count)


def _sharing_fit(model, idx, hist_c, hist_rel, rounds, rss, data_ss, count, solved, reached, degenerate=False,
                 n_merged=0) -> SharingFit:
    """The `SharingFit` and its status (first match: singular, nonfinite, no_signal, ill_conditioned, tolerance)."""
    rss = jnp.asarray(rss)
    finite_rss = bool(np.isfinite(float(rss)))
    if not finite_rss:
        rss = jnp.asarray(np.inf, rss.dtype)  # a non-finite residual is unbounded: rms and rel_rms inf, never NaN
    rms, rel = _rms_pair(rss, jnp.asarray(data_ss, rss.dtype), jnp.asarray(count, rss.dtype))
    if not solved:
        status = Status.singular
    elif not (finite_rss and np.isfinite(float(rel))):
        status = Status.nonfinite
    elif not float(data_ss) > 0:
        status = Status.no_signal  # all-zero values (black images) or weights: the zero fit, no information
    elif degenerate:
        status = Status.ill_conditioned  # too few, duplicate or affinely degenerate points (fit_sharing docstring)
    elif not reached:
        status = Status.tolerance_not_reached
    else:
        status = Status.converged
    stats = {"n_centers": jnp.asarray(model.n_centers), "rss": rss, "data_ss": data_ss, "count": jnp.asarray(count),
             "n_merged": jnp.asarray(n_merged)}
    return SharingFit(model=model, center_index=jnp.asarray(idx), history_centers=jnp.asarray(hist_c),
                      history_rms=jnp.asarray(hist_rel), status=status, iterations=jnp.asarray(rounds), rms=rms,
                      rel_rms=rel, stats=stats)


def _weighted_rss(model, points, values, w):
    r = (values - model(points).reshape(values.shape)) * w[:, None]
    return jnp.sum(r * r)


def _affine_fallback(points, values, w, scale, single, chunk, data_ss, count, failed=False) -> SharingFit:
    """Minimum-norm weighted LSQ $c_0 + c\\cdot\\vec q$ (one centre, zero kernel weight): eq. 10 is undetermined
    (status `ill_conditioned`), or its solve failed (`failed`: status `singular`)."""
    p, v, wn = np.asarray(points), np.asarray(values), np.asarray(w)
    mean = p.mean(axis=0)
    a = np.concatenate([np.ones((p.shape[0], 1)), p - mean], axis=1) * wn[:, None]
    x = np.linalg.lstsq(a, v * wn[:, None], rcond=None)[0]  # (d + 1, C), minimum norm
    poly = np.concatenate([x[:1] - mean[None, :] @ x[1:], x[1:]], axis=0).astype(p.dtype)
    lam = np.zeros((1, v.shape[1]), p.dtype)
    if single:
        lam, poly = lam[:, 0], poly[:, 0]
    model = jaxsh.RBFModel(points[:1], jnp.asarray(lam), jnp.asarray(poly), scale, chunk=chunk)
    rss = _weighted_rss(model, points, values, w)
    rel = rms_pair(rss, data_ss, count)[1]
    return _sharing_fit(model, np.zeros(1, np.int32), [1], rel[None], 0, rss, data_ss, count,
                        _finite(model.poly) and not failed, True, degenerate=True)


def _merged_fit(points, values, w, weighted, first, inverse, n_centers, scale, smoothing, key, tol, n_init, n_add, spread, chunk,
                single, data_ss, count) -> SharingFit:
    """Duplicate points merged (weighted mean value, summed weight), fitted, measured on the samples as given."""
    groups = first.shape[0]
    v, wn = np.asarray(values), np.asarray(w)
    wsum = np.bincount(inverse, weights=wn, minlength=groups)
    cnt = np.bincount(inverse, minlength=groups)
    mean_w = np.stack([np.bincount(inverse, weights=wn * v[:, c], minlength=groups) for c in range(v.shape[1])], 1)
    mean_u = np.stack([np.bincount(inverse, weights=v[:, c], minlength=groups) for c in range(v.shape[1])], 1)
    merged = np.where(wsum[:, None] > 0, mean_w / np.where(wsum > 0, wsum, 1.0)[:, None], mean_u / cnt[:, None])
    merged = merged.astype(v.dtype)
    d1 = points.shape[1] + 1
    sub = fit_sharing(points[jnp.asarray(first)], merged[:, 0] if single else merged, max(min(n_centers, groups), d1),
                      scale, smoothing, key, weights=(wsum if weighted else cnt).astype(v.dtype), tol=tol,
                      n_init=None if n_init is None else max(min(n_init, groups), d1), n_add=n_add, spread=spread,
                      chunk=chunk)
    rss = _weighted_rss(sub.model, points, values, w)
    solved = _finite(sub.model.weights, sub.model.poly) and status_name(sub.status) != "singular"
    fit = _sharing_fit(sub.model, first[np.asarray(sub.center_index)], sub.history_centers, sub.history_rms,
                       sub.iterations, rss, data_ss, count, solved, True,
                       degenerate=True, n_merged=points.shape[0] - groups)
    fit.stats["merged_status"] = sub.status  # the merged samples' own fit (e.g. tolerance_not_reached)
    return fit


def _finite(*arrays) -> bool:
    """Whether every entry is finite (on the host: eager `jnp` ops would each compile a program)."""
    return all(bool(np.all(np.isfinite(np.asarray(a)))) for a in arrays)


def _initial_subset(p, n_init, n_centers, key):
    """Random subset plus the per-coordinate extreme samples, affinely spanning (concrete)."""
    n, d = p.shape
    extremes = np.unique(np.concatenate([np.argmin(p, axis=0), np.argmax(p, axis=0)]))
    perm = host_rng(key).permutation(n)  # on the host: jax.random.permutation compiled a shuffle (0.2 s)
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


# --------------------------------------------------------------------------- image samples and the paper's models


class Samples(eqx.Module):
    """Reflectance samples taken from images (Zickler 2006 secs. 6–8).

    **Fields** (one row per kept sample; `N` samples):

    - `points`: `(N, 3)` $(u, v, w)$ (eq. 7) or `(N, 5)` $(x, y, u, v, w)$ (eq. 13).
    - `values`: `(N, C)` reflectance $f = I / (E\\cos\\theta_i)$ (shading removed).
    - `cos_i`: `(N,)` $\\cos\\theta_i$ (the greedy residual weight, sec. 6).
    - `wi`, `wo`, `n`: `(N, 3)` light, view, normal; `xy`: `(N, 2)` or `None`.
    - `image`, `pixel`: `(N,)` int, the source image and flat pixel index.
    """

    points: Array
    values: Array
    cos_i: Array
    wi: Array
    wo: Array
    n: Array
    xy: Array | None
    image: Array
    pixel: Array

    def baseline_data(self):
        """`(wi, wo, n, values, cos_i)` — the arguments of the parametric baselines."""
        return self.wi, self.wo, self.n, self.values, self.cos_i


def _unit_rows(a, name, where=""):
    """Directions normalised to unit length (a direction's length carries no meaning); zero or non-finite rows are errors."""
    norm = np.linalg.norm(a, axis=-1, keepdims=True)
    bad = ~np.isfinite(norm[..., 0]) | (norm[..., 0] == 0)
    if bad.any():
        i = tuple(int(k) for k in np.argwhere(bad)[0])
        raise ValueError(f"`{name}` must be finite non-zero directions{' ' + where if where else ''}, got {a[i].tolist()} at {i}")
    return a / norm


def _per_light(x, n_lights, channels, name):
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        a = np.full((n_lights,), float(a))
    if a.shape == (n_lights,):
        a = np.broadcast_to(a[:, None], (n_lights, channels))
    if a.shape != (n_lights, channels):
        raise ValueError(f"`{name}` must be a scalar, ({n_lights},) or ({n_lights}, {channels}), got {a.shape}")
    return a


def reflectance_samples(
    images: Real[ArrayLike, "L H W *C"],
    normal: Real[ArrayLike, "H W 3"],
    view: Real[ArrayLike, "*HW 3"] | Sequence[float],
    lights: Real[ArrayLike, "L 3"] | Sequence[Sequence[float]],
    irradiance=1.0,
    mask=None,
    xy: Real[ArrayLike, "H W 2"] | None = None,
    visible=None,
    min_cos: float = 0.0,
) -> Samples:
    """Turn images under directional lights into reflectance samples (Zickler 2006 secs. 6, 8.1).

    Sample $f = I/(E\\cos\\theta_i)$ at each pixel in `mask` with
    $\\cos\\theta_i$ and $\\cos\\theta_o > $ `min_cos` and (if given)
    `visible` — shadowed and grazing pixels are discarded and shading is
    removed by dividing by $\\cos\\theta_i$ (sec. 8.1). Points are $(u, v, w)$
    or, with `xy`, $(x, y, u, v, w)$ (`jaxsh.sbrdf_points`).

    **Arguments:** `images` `(L, H, W, C)` or `(L, H, W)`; `normal` `(H, W, 3)`;
    `view` `(H, W, 3)` or `(3,)` (towards the camera); `lights` `(L, 3)`
    (towards the lights). Normals, views and lights are directions: they are
    normalised to unit length here (a light of norm 2 is the same light; its
    strength is `irradiance`), and a zero or non-finite one (inside `mask`)
    is a `ValueError`; `irradiance` scalar, `(L,)` or `(L, C)`; `mask`
    `(H, W)` bool; `xy` `(H, W, 2)`; `visible` `(L, H, W)` bool.

    **Returns:** `Samples` (concrete NumPy-backed arrays; call outside `jit`).

    **Raises:** `ValueError` naming the argument for bad shapes, non-finite
    images inside `mask`, zero or non-finite directions, irradiance not
    $> 0$ — and, as a data *builder* (not a solver, so it has no status to
    return), when no sample is left: "no usable samples" (every pixel
    masked, shadowed, grazing or facing away). The fits take any non-empty
    `Samples`; degenerate ones (too few, a constant $w$, duplicates) give a
    status there (`fit_sharing`).
    """
    imgs = np.asarray(images, dtype=np.float64)
    if imgs.ndim == 3:
        imgs = imgs[..., None]
    if imgs.ndim != 4:
        raise ValueError(f"`images` must have shape (L, H, W) or (L, H, W, C), got {imgs.shape}")
    nl, h, w, c = imgs.shape
    nrm = np.asarray(normal, dtype=np.float64)
    if nrm.shape != (h, w, 3):
        raise ValueError(f"`normal` must have shape ({h}, {w}, 3), got {nrm.shape}")
    v = np.asarray(view, dtype=np.float64)
    if v.shape == (3,):
        v = np.broadcast_to(v, (h, w, 3))
    if v.shape != (h, w, 3):
        raise ValueError(f"`view` must have shape (3,) or ({h}, {w}, 3), got {v.shape}")
    lt = np.asarray(lights, dtype=np.float64)
    if lt.shape != (nl, 3):
        raise ValueError(f"`lights` must have shape ({nl}, 3), got {lt.shape}")
    lt = _unit_rows(lt, "lights")
    e = _per_light(irradiance, nl, c, "irradiance")
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise ValueError(f"`irradiance` must be finite and > 0, got {e.min() if np.all(np.isfinite(e)) else 'a non-finite value'}")
    m = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if m.shape != (h, w):
        raise ValueError(f"`mask` must have shape ({h}, {w}), got {m.shape}")
    nrm = np.where(m[..., None], nrm, np.asarray([0.0, 0.0, 1.0]))
    v = np.where(m[..., None], v, np.asarray([0.0, 0.0, 1.0]))
    nrm = _unit_rows(nrm, "normal", "inside the mask")
    v = _unit_rows(v, "view", "inside the mask")
    if xy is not None:
        xy = np.asarray(xy, dtype=np.float64)
        if xy.shape != (h, w, 2):
            raise ValueError(f"`xy` must have shape ({h}, {w}, 2), got {xy.shape}")
    if visible is not None:
        visible = np.asarray(visible, bool)
        if visible.shape != (nl, h, w):
            raise ValueError(f"`visible` must have shape ({nl}, {h}, {w}), got {visible.shape}")
    if not np.all(np.isfinite(imgs[:, m])):
        raise ValueError("`images` contain non-finite values (NaN or inf) inside the mask")
    cos_i = np.einsum("hwk,lk->lhw", nrm, lt)
    cos_o = np.sum(nrm * v, -1)
    keep = m[None] & (cos_i > min_cos) & (cos_o > min_cos)[None]
    if visible is not None:
        keep &= visible
    li, pi, pj = np.nonzero(keep)
    if li.size == 0:
        raise ValueError("no usable samples: every pixel is masked, shadowed or facing away")
    ci = cos_i[li, pi, pj]
    vals = imgs[li, pi, pj] / (e[li] * ci[:, None])
    wi = lt[li]
    wo = v[pi, pj]
    nn = nrm[pi, pj]
    pts = np.asarray(jaxsh.sbrdf_points(wi, wo, nn, None if xy is None else xy[pi, pj]))
    return Samples(
        jnp.asarray(pts), jnp.asarray(vals), jnp.asarray(ci), jnp.asarray(wi), jnp.asarray(wo), jnp.asarray(nn),
        None if xy is None else jnp.asarray(xy[pi, pj]), jnp.asarray(li), jnp.asarray(pi * w + pj),
    )


def _flat(a, shape, k):
    return jnp.broadcast_to(jnp.asarray(a), shape + (k,)).reshape(-1, k)


def _host_or_jax(x):
    """`x` itself when it is a JAX array (or tracer), else a NumPy array: an argument for a jitted program."""
    return x if isinstance(x, jax.Array) else np.asarray(x)


def _render_geometry(normal, view, light, mask):
    """`(shape, normal, view, light, cos_i, ok)` of a render: one compiled program per shape and dtype."""
    normal = _host_or_jax(normal)
    return (normal.shape[:-1],) + _render_geometry_jit(
        normal, _host_or_jax(view), _host_or_jax(light), None if mask is None else _host_or_jax(mask))


def _unit_or_zero(a):
    """Rows of `a` normalised; rows already unit to 64 eps keep their bits (a render with the arrays the samples
    were taken from evaluates the same (u, v, w), which matters at theta_d = 0, where phi_d is rounding noise);
    zero rows stay zero (not rendered)."""
    n2 = jnp.sum(a * a, -1, keepdims=True)
    unit = jnp.abs(n2 - 1.0) <= 64 * jnp.finfo(a.dtype).eps
    return jnp.where(unit, a, jnp.where(n2 > 0, a / jnp.sqrt(jnp.where(n2 > 0, n2, 1.0)), 0.0))


@jaxsh.jit
def _render_geometry_jit(normal, view, light, mask):
    normal = jnp.asarray(normal)
    view = jnp.broadcast_to(jnp.asarray(view, normal.dtype), normal.shape)
    light = jnp.broadcast_to(jnp.asarray(light, normal.dtype), normal.shape)
    # a light direction is a direction: normalised, as in `reflectance_samples` (zero rows stay zero: not lit)
    ln2 = jnp.sum(light * light, -1, keepdims=True)
    light = light * jnp.where(ln2 > 0, jax.lax.rsqrt(jnp.where(ln2 > 0, ln2, 1.0)), 0.0)
    # so are normals and views (only the light used to be: a normal map or view of another length changed
    # cos(theta_i) and the (u, v, w) of the half vector, so the render silently disagreed with the samples)
    normal, view = _unit_or_zero(normal), _unit_or_zero(view)
    cos_i = jnp.sum(normal * light, -1)
    cos_o = jnp.sum(normal * view, -1)
    ok = (cos_i > 0.0) & (cos_o > 0.0)
    if mask is not None:
        ok = ok & jnp.asarray(mask, bool)
    # harmless substitute geometry where the pixel is not rendered
    nsafe = jnp.where(ok[..., None], normal, jnp.asarray([0.0, 0.0, 1.0], normal.dtype))
    lsafe = jnp.where(ok[..., None], light, jnp.asarray([0.6, 0.0, 0.8], normal.dtype))
    vsafe = jnp.where(ok[..., None], view, jnp.asarray([0.0, 0.0, 1.0], normal.dtype))
    return nsafe, vsafe, lsafe, jnp.where(ok, cos_i, 0.0), ok


# the fewest rows a render evaluates (`_rendered_rows`): 4,096 rows of an RBF with K centres cost about
# K·4096 distances (10-30 ms at K = 2,000-5,000 on 2 cores), less than compiling one more program (0.2-0.3 s)
_MIN_ROWS = 4096


def _rendered_rows(ok):
    """Flat indices of the rendered pixels, padded, or `None` when `ok` is traced.

    The padding indices are `ok.size` (one past the last pixel): the evaluation reads pixel
    `ok.size - 1` there (substitute geometry when it is not rendered) and the scatter drops them.
    The padded count is the next power of two, at least `_MIN_ROWS`, at most `ok.size`, so the
    compiled programs are few: a render under a new light or view reuses the program of an earlier
    one whenever its count of rendered pixels falls in the same bucket (then it compiles nothing),
    and every render of an image of at most `_MIN_ROWS` pixels shares one program per model size.
    """
    c = _concrete(ok)
    if c is None:
        return None
    idx = np.flatnonzero(c.reshape(-1))
    m = idx.size
    size = max(1, min(c.size, max(_MIN_ROWS, 1 << max(m - 1, 0).bit_length())))
    sel = np.full(size, c.size, dtype=np.int32)
    sel[:m] = idx
    return sel


def _eval_rendered(fn, args, ok, *rows):
    """`fn(args, *rows)` at the rendered pixels only (gather, evaluate, scatter), zero at the others.

    `fn` is a module-level function (a static argument of the compiled program: a closure made
    per call would compile anew each call); `args` its pytree of models; `rows` are flat `(P, k)`
    arrays (or `None`); `fn` returns an array or a tuple of arrays with `P` leading rows. Same
    values as evaluating every pixel and masking, at the cost of the rendered pixels only
    (Zickler sec. 8.2 renders objects that cover part of the frame). Concrete `ok`: one compiled
    program per (shape, padded count; `_rendered_rows`); traced `ok`: every pixel is evaluated.
    """
    sel = _rendered_rows(ok)
    if sel is None or sel.size > rows[0].shape[0]:  # traced, or no pixels at all (nothing to gather from)
        return fn(args, *rows)
    return _eval_rows_jit(fn, args, sel, *rows)


@jaxsh.jit
def _eval_rows_jit(fn, args, sel, *rows):
    total = rows[0].shape[0]
    take = jnp.minimum(sel, total - 1)
    vals = fn(args, *(None if r is None else r[take] for r in rows))
    return jax.tree.map(
        lambda v: jnp.zeros((total,) + v.shape[1:], v.dtype).at[sel].set(v, mode="drop", indices_are_sorted=True), vals)


def _component_status(statuses, signal=None) -> Status:
    """The status of a model of several components (Zickler eqs. 14, 15) from the statuses of their fits.

    The `worst` of them, except that a component whose samples are all zero (`no_signal`: its fit is the exact
    zero function, a valid answer: a matte object has no specular part, a metal no diffuse one) counts as
    `converged`; the model is `no_signal` only when every component is all zero (and `signal`, the evidence of
    a component without a fit such as eq. 15's albedo map, is False).
    """
    zero = [st == Status.no_signal for st in statuses]
    none = zero[0]
    for z in zero[1:]:
        none = jnp.logical_and(none, z)
    if signal is not None:
        none = jnp.logical_and(none, jnp.logical_not(jnp.asarray(signal)))
    return Status.where(none, Status.no_signal, worst(*(Status.where(z, Status.converged, st)
                                                        for z, st in zip(zero, statuses))))


def _pooled_residual(fits):
    """`(rms, rel_rms, rss, data_ss, count)` pooled over the fits' own samples (each in its fit's units)."""
    rss, data_ss = sum(f.stats["rss"] for f in fits), sum(f.stats["data_ss"] for f in fits)
    count = sum(f.stats["count"] for f in fits)
    return (*_rms_pair(rss, data_ss, jnp.asarray(count, rss.dtype)), rss, data_ss, count)


def _radiance_residual(pairs):
    """`(rms, rel_rms, rss, data_ss, count)` of image samples against the model's radiance, in the images' units.

    `pairs`: `(observed, predicted)` arrays (NumPy), one pair per component image (diffuse, specular). Computed
    in float64 in the unit of a power of two of the largest observed value (no square overflows), so `rel_rms` is
    invariant and `rms` equivariant under a change of the images' units.
    """
    obs = [np.asarray(o, np.float64) for o, _ in pairs]
    unit = _pow2(max(float(np.max(np.abs(o), initial=0.0)) for o in obs))
    rss_n = sum(float(np.sum(((np.asarray(o, np.float64) - np.asarray(m, np.float64)) / unit) ** 2)) for o, m in pairs)
    ss_n = sum(float(np.sum((o / unit) ** 2)) for o in obs)
    count = sum(o.size for o in obs)
    rss_n = rss_n if np.isfinite(rss_n) else np.inf
    rms = unit * np.sqrt(rss_n / count) if count else 0.0
    rel = np.sqrt(rss_n / ss_n) if ss_n > 0 else (np.inf if rss_n > 0 else 0.0)
    with np.errstate(over="ignore"):
        rss, data_ss = rss_n * unit * unit, ss_n * unit * unit
    return tuple(jnp.asarray(x) for x in (rms, rel, rss, data_ss)) + (count,)


def _residual_fields(residual):
    rms, rel, rss, data_ss, count = residual
    return jnp.asarray(rms), jnp.asarray(rel), {"rss": jnp.asarray(rss), "data_ss": jnp.asarray(data_ss),
                                                "count": jnp.asarray(count)}


class RBFReflectance(Solution):
    """An RBF BRDF $\\tilde f(u, v, w)$ (eq. 12) or SBRDF $\\tilde f(x, y, u, v, w)$ (eq. 13).

    **Fields:** `fit` (`SharingFit`, its `model` the `jaxsh.RBFModel`),
    `spatial` (static bool: 5-D with surface coordinates).

    The result contract (`Solution`) is the fit's: `status`, `iterations`,
    `rms`, `rel_rms`, `stats` are those of `fit`; `estimate` is the
    reflectance model itself.

    `brdf(wi, wo, n, xy=None)` evaluates the reflectance `(..., C)`;
    `render(normal, view, light, irradiance, mask, xy)` predicts an image
    $I = \\max(\\tilde f, 0)\\,E\\cos\\theta_i$ under a new directional light
    and/or view (0 where $\\cos\\theta_i \\le 0$, $\\cos\\theta_o \\le 0$ or
    off the mask). Negative RBF values (possible away from the data) are
    clamped to 0.

    **Extrapolation is not flagged.** Away from the sampled points (e.g. a
    light whose $w = 2\\theta_d/\\pi$ lies outside the training lights'
    range) the model continues linearly (the degree-1 polynomial plus the
    cones): nothing marks such pixels. Measured (textured Lambertian plus a
    Blinn lobe, 6 lights within 0.35 rad of the view, $w \\le 0.107$, 400
    centres): 0.8 % error for a light at 0.2 rad, 2.2 % at 0.5, 7.1 % at
    0.8, 13.7 % at 1.1 rad ($w = 0.35$); the paper (sec. 7.1) says the
    same: accuracy decreases away from the convex hull of the samples.
    """

    fit: SharingFit
    spatial: bool = eqx.field(static=True)
    status: Status
    iterations: Int[Array, ""]
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    stats: dict

    def __init__(self, fit: SharingFit, spatial: bool):
        self.fit = fit
        self.spatial = bool(spatial)
        self.status, self.iterations, self.rms, self.rel_rms = fit.status, fit.iterations, fit.rms, fit.rel_rms
        self.stats = fit.stats

    @property
    def estimate(self) -> "RBFReflectance":
        """The reflectance model itself (it has `brdf` and `render`)."""
        return self

    def brdf(self, wi, wo, n, xy=None):
        return _rbf_brdf(self.fit.model, self.spatial, wi, wo, n, xy)

    def render(self, normal, view, light, irradiance=1.0, mask=None, xy=None):
        """Predicted radiance `(H, W, C)` (or `(H, W)`) for a directional light (Zickler 2006 sec. 8.2)."""
        return render_rbf(self.fit.model, normal, view, light, irradiance, mask, xy)


def _rbf_brdf(model, spatial, wi, wo, n, xy):
    if spatial and xy is None:
        raise ValueError("this SBRDF (eq. 13) needs surface coordinates `xy` (..., 2)")
    wi, wo, n = (jnp.asarray(a) for a in (wi, wo, n))
    shape = jnp.broadcast_shapes(wi.shape[:-1], wo.shape[:-1], n.shape[:-1])
    if spatial:
        shape = jnp.broadcast_shapes(shape, jnp.shape(xy)[:-1])
    q = jaxsh.sbrdf_points(_flat(wi, shape, 3), _flat(wo, shape, 3), _flat(n, shape, 3),
                           _flat(xy, shape, 2) if spatial else None)
    out = model(q)
    return out.reshape(shape + out.shape[1:])


def _rbf_rows(args, wi, wo, n, xy):
    """$\\max(\\tilde f, 0)$ of `render_rbf` at flat rows (`_eval_rendered`'s `fn`); `args` = (model, spatial)."""
    model, spatial = args
    return jnp.maximum(_rbf_brdf(model, spatial, wi, wo, n, xy), 0.0)


def render_rbf(model: jaxsh.RBFModel, normal, view, light, irradiance=1.0, mask=None, xy=None):
    """An image under one directional light from an RBF (S)BRDF model (Zickler 2006 sec. 8.2).

    $I = \\max(\\tilde f, 0)\\,E\\cos\\theta_i$, 0 where $\\cos\\theta_i \\le 0$,
    $\\cos\\theta_o \\le 0$ or off `mask`; only the rendered pixels are
    evaluated. `model` is a `jaxsh.RBFModel` over $(u, v, w)$ (3-D, eq. 12)
    or $(x, y, u, v, w)$ (5-D, eq. 13; then `xy` `(..., 2)` is required) —
    e.g. `RBFReflectance.fit.model`, or the `"model"` of
    `jaxsh.io.read_rbf`. Arguments as `RBFReflectance.render`: `normal`
    `(H, W, 3)`, `view` and `light` `(3,)` or `(H, W, 3)` (towards the camera
    / the light; all three are directions, normalized here as in
    `reflectance_samples`; a zero one is not rendered), `irradiance` scalar or `(C,)`
    (a one-channel model under a `(C,)` irradiance gives C channels).
    """
    d = int(model.centers.shape[1])
    if d not in (3, 5):
        raise ValueError(f"`model` must be an RBF over (u, v, w) or (x, y, u, v, w) points, got d = {d}")
    spatial = d == 5
    if spatial and xy is None:
        raise ValueError("this SBRDF (eq. 13) needs surface coordinates `xy` (..., 2)")
    shape, n, v, li, cos, ok = _render_geometry(normal, view, light, mask)
    xyf = _flat(xy, shape, 2) if spatial else None
    f = _eval_rendered(_rbf_rows, (model, spatial), ok, _flat(li, shape, 3), _flat(v, shape, 3), _flat(n, shape, 3), xyf)
    f = f.reshape(shape + f.shape[1:])
    e = jnp.asarray(irradiance, f.dtype)
    scale = jnp.where(ok, cos, 0.0)
    if f.ndim == len(shape):
        return f * scale * e
    try:  # scalar or (C,); a one-channel (grey) model under coloured light gives C channels
        cs = jnp.broadcast_shapes(f.shape[-1:], jnp.shape(e))
    except ValueError:
        raise ValueError(f"`irradiance` {jnp.shape(e)} does not match the model's {f.shape[-1]} channels") from None
    e = jnp.broadcast_to(e, cs).reshape((1,) * len(shape) + cs)
    return f * scale[..., None] * e


def _check_samples(samples):
    if not isinstance(samples, Samples):
        raise ValueError(f"`samples` must be a solvers.Samples (see reflectance_samples), got {type(samples).__name__}")


def fit_homogeneous(samples: Samples, n_centers: int, m_w: float = 0.3, smoothing=0.0, key=None, *, throw: bool = False,
                    **kwargs) -> RBFReflectance:
    """Homogeneous BRDF $\\tilde f(u, v, w)$ of Zickler 2006 eq. 12, $M = \\mathrm{diag}(1, 1, m_w)$.

    Greedy centres with residuals weighted by $\\cos\\theta_i$ (sec. 6).
    Extra keyword arguments go to `fit_sharing` (`tol`, `n_init`, `n_add`,
    `chunk`). The paper's $m_w$ is 0.1–0.5. `throw=True` raises
    `SolveError` unless the fit's status is `Status.converged`.

    **Status and `tol`.** Pass `tol` (the relative weighted RMS residual
    over the samples, $\\sqrt{\\sum ((f_i - \\tilde f_i)\\cos\\theta_i)^2 / \\sum (f_i\\cos\\theta_i)^2}$)
    to have the status judge the fit: `tolerance_not_reached` when
    `rel_rms > tol` after `n_centers` centres. Without `tol`, `converged`
    only means the solve succeeded, whatever `rel_rms` is.
    """
    _check_samples(samples)
    m_w = check_float(m_w, "m_w", strict=True)
    if samples.points.shape[1] != 3:
        raise ValueError(f"`samples` must have (u, v, w) points (N, 3), got {tuple(samples.points.shape)}")
    fit = fit_sharing(samples.points, samples.values, n_centers, scale=jnp.asarray([1.0, 1.0, m_w]),
                      smoothing=smoothing, key=key, weights=samples.cos_i, **kwargs)
    return finish(RBFReflectance(fit, False), throw)


def fit_sbrdf(samples: Samples, n_centers: int, m_xy: float = 0.3, m_w: float = 0.3, smoothing=0.0, key=None, *,
              throw: bool = False, **kwargs) -> RBFReflectance:
    """Smoothly varying SBRDF $\\tilde f(x, y, u, v, w)$ of Zickler 2006 eq. 13, $M = \\mathrm{diag}(m_{xy}, m_{xy}, 1, 1, m_w)$.

    Reflectance sharing: one 5-D interpolant over all surface points, so
    angular samples seen at one point inform its neighbours (sec. 7). The
    paper's $m_{xy}$ is 0.2–0.4 for $(x, y) \\in [0, 1]^2$. Extra keyword
    arguments, `throw` and the status's judgement of `tol` as in
    `fit_homogeneous`.
    """
    _check_samples(samples)
    m_xy, m_w = check_float(m_xy, "m_xy", strict=True), check_float(m_w, "m_w", strict=True)
    if samples.points.shape[1] != 5:
        raise ValueError(f"`samples` must have (x, y, u, v, w) points (N, 5), got {tuple(samples.points.shape)}")
    fit = fit_sharing(samples.points, samples.values, n_centers,
                      scale=jnp.asarray([m_xy, m_xy, 1.0, 1.0, m_w]), smoothing=smoothing, key=key,
                      weights=samples.cos_i, **kwargs)
    return finish(RBFReflectance(fit, True), throw)


def _lookup(amap, xy):
    """Nearest-texel lookup of an (H, W, C) map over [0, 1]^2 (column ↔ x, row ↔ y)."""
    h, w = amap.shape[:2]
    j = jnp.clip(jnp.floor(xy[..., 0] * w).astype(jnp.int32), 0, w - 1)
    i = jnp.clip(jnp.floor(xy[..., 1] * h).astype(jnp.int32), 0, h - 1)
    return amap[i, j]


def _check_albedo(albedo):
    """An RGB albedo map `(H, W, 3)` over $(x, y) \\in [0, 1]^2$ (a `(H, W)` map used to fail in `render` with a
    broadcasting error that did not name it)."""
    shape = tuple(jnp.shape(albedo))
    if len(shape) != 3 or shape[-1] != 3 or shape[0] < 1 or shape[1] < 1:
        raise ValueError(f"`albedo` must be an RGB map of shape (H, W, 3) over (x, y) in [0, 1]^2, got {shape}")


def _nonneg_albedo(med):
    """The median albedo map with the library's nonnegativity (as `fit_brdf`'s $K_d \\ge 0$): medians $\\le 0$ (noise
    on dark pixels, a component image of the wrong sign) are 0; positive ones at least $10^{-6}$ of the largest, so
    that $r_k / a_k$ stays bounded. A pixel a little below zero used to be raised to that floor: its diffuse samples
    divided by it were $\\sim 10^6$ times the data, and the $d_k$ fit through them was garbage (relative RMS 1,219 on
    a capture whose clean fit has 0.071, `converged`)."""
    pos = med > 0
    floor = 1e-6 * np.max(med, initial=0.0)
    return np.where(pos, np.maximum(med, floor), 0.0)


def _pos(values):
    """$\\max(v, 0)$ in float64 NumPy: the RBF components as `render` evaluates them (`_dichromatic_rows`)."""
    return np.maximum(np.asarray(values, np.float64), 0.0)


def _fill(amap):
    """Replace NaN texels (never observed) by the per-channel median of the observed ones."""
    med = np.nanmedian(amap.reshape(-1, amap.shape[-1]), axis=0)
    return np.where(np.isnan(amap), med[None, None, :], amap)


def _dichromatic_rows(fits, wi, wo, n, xy):
    """$(\\max(d_k, 0), \\max(g, 0))$ of eq. 14 at flat rows (`_eval_rendered`'s `fn`); `fits` = (diffuse, specular)."""
    q = jaxsh.sbrdf_points(wi, wo, n, xy)
    return jnp.maximum(fits[0](q), 0.0), jnp.maximum(fits[1](q), 0.0)


def _one_image_rows(specular, wi, wo, n, xy):
    """$\\max(g, 0)$ of eq. 15 at flat rows (`_eval_rendered`'s `fn`), $g$ over $(x, y, u, v)$."""
    return jnp.maximum(specular(jaxsh.sbrdf_points(wi, wo, n, xy)[:, :4]), 0.0)


class DichromaticReflectance(Solution):
    """Zickler 2006 eq. 14: $I_k = s_k\\,(a_k(\\vec x)\\,d_k(\\vec q) + g(\\vec q))\\,E\\cos\\theta_i$.

    **Fields:** `albedo` `(H, W, 3)` map over $(x, y) \\in [0, 1]^2$ (the
    per-point median of the diffuse samples, sec. 8.1); `diffuse`
    (`SharingFit`, 3 channels $d_k$, one set of centres); `specular`
    (`SharingFit`, scalar $g$).

    Result contract (`Solution`), from the two fits:

    - `status`: the `worst` of theirs, except that a fit whose samples are
      all zero (`no_signal`: a matte object's specular part, a metal's
      diffuse part) counts as `converged` — its fit, the zero function, is
      exact. The model is `no_signal` only when both are (all-zero images).
    - `iterations`: their greedy rounds summed.
    - `rms`/`rel_rms`: from `fit_dichromatic`, in the **units of the
      images** (radiance): the RMS over the samples (lit pixels, images and
      channels) of both component images of $I_{d,k} - s_k E\\cos\\theta_i\\,a_k d_k(\\vec q)$
      and $I_{s,k} - s_k E\\cos\\theta_i\\,g(\\vec q)$ (the fitted $d_k$, $g$
      clamped at 0, as `render` evaluates them); `rel_rms` is it over the RMS of those
      image samples. So `rel_rms` does not change, and `rms` scales, when
      the images are scaled. The specular residual includes the part of
      $I_s$ not in the source colour. Built by hand from two fits
      (`DichromaticReflectance(albedo, diffuse, specular)`, no images),
      they pool the fits' own weighted residuals, each in its own sample
      units (`diffuse.rel_rms`, `specular.rel_rms` are the fits' own).
    - `stats`: `{"diffuse": ..., "specular": ...}` (each fit's stats) and
      `rss`, `data_ss`, `count` of `rms`/`rel_rms` (as in `SharingFit`).

    `estimate` is the model itself.
    """

    albedo: Array
    diffuse: SharingFit
    specular: SharingFit
    status: Status
    iterations: Int[Array, ""]
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    stats: dict

    def __init__(self, albedo, diffuse: SharingFit, specular: SharingFit, residual=None):
        """`residual`: `(rms, rel_rms, rss, data_ss, count)` in the images' units (`fit_dichromatic`), or `None`."""
        _check_albedo(albedo)
        self.albedo, self.diffuse, self.specular = albedo, diffuse, specular
        self.status = _component_status((diffuse.status, specular.status))
        self.iterations = jnp.asarray(diffuse.iterations) + jnp.asarray(specular.iterations)
        residual = _pooled_residual((diffuse, specular)) if residual is None else residual
        self.rms, self.rel_rms, sums = _residual_fields(residual)
        self.stats = {"diffuse": diffuse.stats, "specular": specular.stats, **sums}

    @property
    def estimate(self) -> "DichromaticReflectance":
        """The reflectance model itself (it has `render`)."""
        return self

    def render(self, normal, view, light, xy, color=(1.0, 1.0, 1.0), irradiance=1.0, mask=None):
        """Predicted radiance `(H, W, 3)` under a directional light of RGB unit colour `color`."""
        shape, n, v, li, cos, ok = _render_geometry(normal, view, light, mask)
        d, g = _eval_rendered(_dichromatic_rows, (self.diffuse, self.specular), ok, _flat(li, shape, 3), _flat(v, shape, 3),
                              _flat(n, shape, 3), _flat(xy, shape, 2))
        d, g = d.reshape(shape + (3,)), g.reshape(shape)
        a = _lookup(self.albedo, jnp.asarray(xy))
        s = jnp.asarray(color, d.dtype).reshape((1,) * len(shape) + (3,))
        rad = s * (a * d + g[..., None])
        return rad * (jnp.where(ok, cos, 0.0) * jnp.asarray(irradiance, d.dtype))[..., None]


def fit_dichromatic(
    diffuse_images, specular_images, colors, normal, view, lights, xy, n_centers_diffuse: int,
    n_centers_specular: int, irradiance=1.0, mask=None, m_xy: float = 0.3, m_w: float = 0.3, smoothing=0.0,
    key=None, min_cos: float = 0.0, *, throw: bool = False, **kwargs,
) -> DichromaticReflectance:
    """Fit the dichromatic SBRDF of Zickler 2006 eq. 14 from separated images (sec. 8.1).

    Shading is removed ($\\div E s_k\\cos\\theta_i$; shadowed pixels dropped),
    the RGB albedo $a_k(\\vec x)$ is the median over the images of the
    diffuse samples at each pixel, the normalized diffuse samples
    $r_k/a_k$ are fitted by three 5-D RBFs $d_k$ (shared centres, batched
    channels) and the specular samples $\\sum_k I_{s,k}s_k / (E\\cos\\theta_i\\sum_k s_k^2)$
    by one 5-D RBF $g$, both with $M = \\mathrm{diag}(m_{xy}, m_{xy}, 1, 1, m_w)$.

    **Arguments:** `diffuse_images`, `specular_images` `(L, H, W, 3)`;
    `colors` `(L, 3)` unit RGB source colours $\\hat s$; `normal`, `view`,
    `lights`, `xy`, `irradiance`, `mask` as in `reflectance_samples`.
    `irradiance` is a scalar or `(L,)`: one $E$ per light, finite and
    $> 0$ (the colour of each source is `colors`).
    Pixels never lit keep the median albedo of the others. The albedo is
    nonnegative (as `fit_brdf`'s $K_d$): a median $\\le 0$ (noise on a dark
    pixel) gives 0, and the diffuse samples of a pixel with albedo 0 in every
    channel are left out of the $d_k$ fit (docs/sharing.md, "Diffuse samples
    below zero"). `throw=True`
    raises `SolveError` unless the status is `converged`; a `tol` keyword
    applies to both fits, and the status is the worse of theirs
    (`tolerance_not_reached` when either residual is above `tol`), an
    all-zero component (a matte object: `specular_images` all zero)
    counting as converged (`DichromaticReflectance`).

    **Returns:** a `DichromaticReflectance`; its `rms`/`rel_rms` are in the
    units of the images (radiance), over the lit samples of both images.
    """
    m_xy, m_w = check_float(m_xy, "m_xy", strict=True), check_float(m_w, "m_w", strict=True)
    dimg = np.asarray(diffuse_images, np.float64)
    simg = np.asarray(specular_images, np.float64)
    if dimg.ndim != 4 or dimg.shape[-1] != 3 or simg.shape != dimg.shape:
        raise ValueError(
            f"`diffuse_images` and `specular_images` must both have shape (L, H, W, 3), got {dimg.shape} and {simg.shape}"
        )
    nl, h, w, _ = dimg.shape
    s = np.asarray(colors, np.float64)
    if s.shape != (nl, 3):
        raise ValueError(f"`colors` must have shape ({nl}, 3), got {s.shape}")
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"`colors` must be finite and > 0 (the source colours divide the images), got {s.tolist()}")
    e = _per_light(irradiance, nl, 1, "irradiance")[:, 0]
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise ValueError(f"`irradiance` must be finite and > 0, got {e.tolist()}")
    eff = (s * e[:, None])[:, None, None, :]
    ds = reflectance_samples(dimg / eff, normal, view, lights, 1.0, mask, xy, min_cos=min_cos)
    # median albedo map (sec. 8.1)
    stack = np.full((nl, h * w, 3), np.nan)
    stack[np.asarray(ds.image), np.asarray(ds.pixel)] = np.asarray(ds.values)
    seen = ~np.all(np.isnan(stack), axis=0)
    albedo = np.full((h * w, 3), np.nan)
    cols = np.nonzero(seen[:, 0])[0]
    albedo[cols] = np.nanmedian(stack[:, cols], axis=0)
    albedo = _nonneg_albedo(_fill(albedo.reshape(h, w, 3)))
    a_s = albedo.reshape(-1, 3)[np.asarray(ds.pixel)]
    # a zero albedo (black images, pixels whose median sample is <= 0) determines no d_k: 0 for such a channel,
    # not 0/0; a sample whose every channel has albedo 0 is left out of the d_k fit (its prediction is 0 whatever d_k)
    dvals = np.divide(np.asarray(ds.values), a_s, out=np.zeros(a_s.shape), where=a_s > 0)
    informs = np.any(a_s > 0, axis=1)
    d_rows = np.nonzero(informs)[0] if np.any(informs) else np.arange(a_s.shape[0])
    sc = jnp.asarray([m_xy, m_xy, 1.0, 1.0, m_w])
    dfit = fit_sharing(np.asarray(ds.points)[d_rows], dvals[d_rows], n_centers_diffuse, scale=sc, smoothing=smoothing,
                       key=key, weights=np.asarray(ds.cos_i)[d_rows], **kwargs)
    spec = np.sum(simg * s[:, None, None, :], -1) / (np.sum(s * s, -1) * e)[:, None, None]
    ss = reflectance_samples(spec, normal, view, lights, 1.0, mask, xy, min_cos=min_cos)
    gfit = fit_sharing(ss.points, ss.values[:, 0], n_centers_specular, scale=sc, smoothing=smoothing, key=key,
                       weights=ss.cos_i, **kwargs)
    # rms / rel_rms in the images' units: I - s_k E cos(theta_i) (a_k d_k or g) at the samples of each image
    es = s * e[:, None]  # (L, 3)
    di, dp, si, sp = (np.asarray(a) for a in (ds.image, ds.pixel, ss.image, ss.pixel))
    # the model as `render` evaluates it: max(d_k, 0), max(g, 0)
    d_pred = es[di] * np.asarray(ds.cos_i, np.float64)[:, None] * a_s * _pos(dfit(ds.points))
    g_pred = es[si] * (np.asarray(ss.cos_i, np.float64) * _pos(gfit(ss.points)))[:, None]
    residual = _radiance_residual([(dimg.reshape(nl, h * w, 3)[di, dp], d_pred),
                                   (simg.reshape(nl, h * w, 3)[si, sp], g_pred)])
    return finish(DichromaticReflectance(jnp.asarray(albedo), dfit, gfit, residual), throw)


class OneImageReflectance(Solution):
    """Zickler 2006 eq. 15: $I_k = s_k\\,(a_k(\\vec x) + g(x, y, u, v))\\,E\\cos\\theta_i$.

    The one-image special case: all samples share $w$, so the specular
    function drops it; the diffuse part is Lambertian with the albedo map
    `albedo` `(H, W, 3)` read off the image. `specular` is the 4-D
    `SharingFit`. Result contract (`Solution`):

    - `status`: the specular fit's, except that an all-zero specular image
      (`no_signal`: a matte object) with a non-zero albedo map is
      `converged` (its fit, the zero function, is exact); `no_signal` only
      when the albedo map is zero too (a black image).
    - `iterations`: the specular fit's greedy rounds.
    - `rms`/`rel_rms`: from `fit_one_image`, in the **units of the image**
      (radiance), over the lit samples of both component images, as in
      `DichromaticReflectance` ($I_{d,k} - s_k E\\cos\\theta_i\\,a_k$ and
      $I_{s,k} - s_k E\\cos\\theta_i\\,g$). Built by hand
      (`OneImageReflectance(albedo, specular)`), the specular fit's own.
    - `stats`: `{"specular": ...}` (the fit's stats) and `rss`, `data_ss`,
      `count` of `rms`/`rel_rms`.

    `estimate` is the model itself.
    """

    albedo: Array
    specular: SharingFit
    status: Status
    iterations: Int[Array, ""]
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    stats: dict

    def __init__(self, albedo, specular: SharingFit, residual=None):
        """`residual`: `(rms, rel_rms, rss, data_ss, count)` in the image's units (`fit_one_image`), or `None`."""
        _check_albedo(albedo)
        self.albedo, self.specular = albedo, specular
        a = _concrete(albedo)
        signal = jnp.any(jnp.asarray(albedo) != 0) if a is None else bool(np.any(a != 0))
        self.status = _component_status((specular.status,), signal)
        self.iterations = specular.iterations
        if residual is None:
            residual = (specular.rms, specular.rel_rms, specular.stats["rss"], specular.stats["data_ss"],
                        specular.stats["count"])
        self.rms, self.rel_rms, sums = _residual_fields(residual)
        self.stats = {"specular": specular.stats, **sums}

    @property
    def estimate(self) -> "OneImageReflectance":
        """The reflectance model itself (it has `render`)."""
        return self

    def render(self, normal, view, light, xy, color=(1.0, 1.0, 1.0), irradiance=1.0, mask=None):
        """Predicted radiance `(H, W, 3)` under a new directional light / view."""
        shape, n, v, li, cos, ok = _render_geometry(normal, view, light, mask)
        g = _eval_rendered(_one_image_rows, self.specular, ok, _flat(li, shape, 3), _flat(v, shape, 3), _flat(n, shape, 3),
                           _flat(xy, shape, 2))
        g = g.reshape(shape)
        a = _lookup(self.albedo, jnp.asarray(xy))
        rad = jnp.asarray(color, g.dtype).reshape((1,) * len(shape) + (3,)) * (a + g[..., None])
        return rad * (jnp.where(ok, cos, 0.0) * jnp.asarray(irradiance, g.dtype))[..., None]


def fit_one_image(
    diffuse_image, specular_image, color, normal, view, light, xy, n_centers: int, irradiance=1.0, mask=None,
    m_xy: float = 0.3, smoothing=0.0, key=None, min_cos: float = 0.0, *, throw: bool = False, **kwargs,
) -> OneImageReflectance:
    """Fit eq. 15 of Zickler 2006 from one separated image (sec. 8.4).

    $a_k(\\vec x) = \\max(I_{d,k}/(s_k E\\cos\\theta_i), 0)$ per lit pixel (unlit
    pixels get the median albedo); $g$ is a 4-D RBF over $\\vec q = (x, y, u, v)$
    with $M = \\mathrm{diag}(m_{xy}, m_{xy}, 1, 1)$, fitted to
    $\\sum_k I_{s,k}s_k/(E\\cos\\theta_i\\sum_k s_k^2)$.

    **Arguments:** `diffuse_image`, `specular_image` `(H, W, 3)`; `color`
    `(3,)`; `light` `(3,)`; `irradiance` a scalar (or a one-element array,
    `(1,)`: the one light's $E$), finite and $> 0$ — the colour is `color`;
    the rest (and `throw`) as in `fit_dichromatic`. A bad shape is a
    `ValueError` naming the argument.

    **Returns:** a `OneImageReflectance`: `status` `converged` for a matte
    object (all-zero `specular_image`), `no_signal` only for a black image;
    `rms`/`rel_rms` in the image's units (radiance).
    """
    m_xy = check_float(m_xy, "m_xy", strict=True)
    dimg = np.asarray(diffuse_image, np.float64)
    simg = np.asarray(specular_image, np.float64)
    if dimg.ndim != 3 or dimg.shape[-1] != 3 or simg.shape != dimg.shape:
        raise ValueError(f"`diffuse_image` and `specular_image` must have shape (H, W, 3), got {dimg.shape} and {simg.shape}")
    h, w, _ = dimg.shape
    s = np.asarray(color, np.float64)
    if s.shape != (3,):
        raise ValueError(f"`color` must have shape (3,), got {s.shape}")
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"`color` must be finite and > 0 (the source colour divides the image), got {s.tolist()}")
    e_arr = np.asarray(irradiance, np.float64)
    if e_arr.size != 1 or e_arr.ndim > 1:
        raise ValueError(
            f"`irradiance` must be a scalar or (1,) (one light; its colour is `color`), got shape {e_arr.shape}")
    e = float(e_arr.reshape(()))
    if not (np.isfinite(e) and e > 0):
        raise ValueError(f"`irradiance` must be finite and > 0, got {e}")
    lt = np.asarray(light, np.float64)
    if lt.shape != (3,):
        raise ValueError(f"`light` must have shape (3,) (towards the light), got {lt.shape}")
    lt = lt.reshape(1, 3)
    ds = reflectance_samples(dimg[None] / (s * e), normal, view, lt, 1.0, mask, xy, min_cos=min_cos)
    albedo = np.full((h * w, 3), np.nan)
    albedo[np.asarray(ds.pixel)] = np.asarray(ds.values)
    albedo = np.maximum(_fill(albedo.reshape(h, w, 3)), 0.0)  # one sample per pixel: its nonnegative LSQ albedo
    spec = np.sum(simg * s, -1) / (np.sum(s * s) * e)
    ss = reflectance_samples(spec[None], normal, view, lt, 1.0, mask, xy, min_cos=min_cos)
    pts = ss.points[:, :4]
    gfit = fit_sharing(pts, ss.values[:, 0], n_centers, scale=jnp.asarray([m_xy, m_xy, 1.0, 1.0]),
                       smoothing=smoothing, key=key, weights=ss.cos_i, **kwargs)
    # rms / rel_rms in the image's units: I - s_k E cos(theta_i) (a_k or g) at the samples
    dp, sp = np.asarray(ds.pixel), np.asarray(ss.pixel)
    d_pred = (s * e) * np.asarray(ds.cos_i, np.float64)[:, None] * albedo.reshape(-1, 3)[dp]
    g_pred = (s * e) * (np.asarray(ss.cos_i, np.float64) * _pos(gfit(pts)))[:, None]  # max(g, 0), as `render`
    residual = _radiance_residual([(dimg.reshape(h * w, 3)[dp], d_pred), (simg.reshape(h * w, 3)[sp], g_pred)])
    return finish(OneImageReflectance(jnp.asarray(albedo), gfit, residual), throw)
