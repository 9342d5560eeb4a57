"""Levenberg-Marquardt that stops at a minimum reached to rounding (`LevenbergMarquardt`).

`optimistix.LevenbergMarquardt` accepts a step when the loss $\\tfrac12\\lVert r\\rVert^2$ falls by at least
a hundredth of the decrease its Gauss-Newton model predicts (`optimistix.ClassicalTrustRegion`), and stops on
the first *accepted* step whose changes in the parameters and in the residuals are within the tolerances
(Cauchy termination). At a minimum reached to rounding, the predicted decrease is far below the loss's own
rounding, so whether the next step is accepted is decided by the last bit of the loss: one that comes out one
ulp higher is rejected, the trust region shrinks, and every rejected step costs another evaluation of the
residual and its Jacobian over all samples until one comes out equal or lower. Measured on
`benchmarks/bench_capture.py --small` (24 images of 153 × 128, 836,496 residuals): the same fit took 5 steps,
or 9 when the per-pixel terms differed in their last bit (one ulp in 24,411 of 836,496 irradiance values);
steps 5-8 were the rejections, each of a loss one ulp above the last accepted one.

Here a step is also accepted when the loss changed by no more than its rounding, `_FLAT` ulps of the loss
(`RoundingTrustRegion`): such a step cannot be told from an improvement, and the termination test then
decides on the step's size as it would for any accepted step. Where the loss still falls the trust region
works as optimistix's. Built from optimistix's public parts (`AbstractGaussNewton`, `AbstractDescent`,
`ClassicalTrustRegion`), as its documentation shows for custom solvers.

**The damped step** (`FactoredDampedNewtonDescent`). optimistix's `DampedNewtonDescent` solves
$\\min_\\delta \\lVert J\\delta - r\\rVert^2 + \\lambda\\lVert\\delta\\rVert^2$ ($\\lambda = 1/$step size) at every
step with `lineax.QR` on the stacked $[J; \\sqrt\\lambda I]$: a Householder QR (LAPACK `geqrf`), then
$Q^T [r; 0]$ by `jax.lax.linalg.ormqr` (LAPACK `dormqr`) and a triangular solve with $R$ read from the same
packed factor. On CPU that is a race: `dormqr` writes its factor operand while it runs (the reference
`dorm2r` sets the diagonal entry $A_{ii}$ to 1 while it applies reflector $i$, then puts it back), but the
custom call declares that operand read-only, so XLA may run the slice that reads $R$ from the same buffer at the
same time, and the solve then divides by 1 instead of $R_{11}$. Measured with JAX/jaxlib 0.10.2, lineax
0.1.1 on 2 cores: `lineax.linear_solve(MatrixLinearOperator(A), b, QR())` of a random $A$ of $2\\cdot10^7
\\times 2$ returned a wrong first component in 1 of 4 calls of the same compiled program ($-1.07$ against
$2.1\\cdot10^{-4}$), at $5.35\\cdot10^7 \\times 2$ in 2 of 5 (always exactly $(c_1 - R_{12} x_2)/1$); the
photometric capture of issue 11 (96 images of 612 × 512, 53.5 M residuals) then took 84 to 125 steps for the
same data, in one process or in two; bound to one core (`taskset -c 0`) it took 84 in 3 of 3.

Here the factor is made once per accepted point and never shares a buffer with a reader: the $R$ factor of
the augmented $[J \\mid r]$ (`jnp.linalg.qr(mode="r")`, `geqrf` alone, in place on a fresh copy) gives $R$ and
$c = Q^T r$ together, and since $\\lVert J\\delta - r\\rVert^2 = \\lVert R\\delta - c\\rVert^2 + \\rho^2$, every
step (accepted or rejected) solves only the small $\\min \\lVert R\\delta - c\\rVert^2 + \\lambda\\lVert\\delta\\rVert^2$
($[R; \\sqrt\\lambda I]$, $2k \\times k$). This is MINPACK's `lmpar` arrangement (Moré 1978): the
same minimizer as optimistix's step, and one QR of the $m \\times (k+1)$ matrix per accepted step instead of one
of $m \\times k$ and a `dormqr` per step.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, PyTree, Scalar

from ._lapack import unbatched

# A loss that changed by at most this many of its own ulps is taken as unchanged. The loss is a sum over the
# residuals (optimistix's `sum_squares`), rounded to a relative ~log2(m) eps for m terms summed pairwise; 64
# covers 2^64 terms, and is still 1.4e-14 relative in float64.
_FLAT = 64.0


class RoundingTrustRegion(optx.ClassicalTrustRegion):
    """`optimistix.ClassicalTrustRegion` that also accepts a step whose loss is within `_FLAT` ulps of the last
    accepted loss (module docstring); such a step leaves the trust region's size as it was."""

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        size, accept, result, new_state = super().step(first_step, y, y_eval, f_info, f_eval_info, state)
        f0, f1 = f_info.as_min(), f_eval_info.as_min()
        eps = jnp.finfo(jnp.result_type(f0)).eps
        flat = jnp.abs(f1 - f0) <= _FLAT * eps * jnp.abs(f0)
        size = jnp.where(flat & ~accept, state.step_size, size)
        return size, accept | flat, result, eqx.tree_at(lambda s: s.step_size, new_state, size)


class _FactoredState(eqx.Module):
    """`FactoredDampedNewtonDescent`'s state: `r` `(k, k)` and `c` `(k,)`, the upper triangle of the augmented
    $[J \\mid r]$'s R factor at the last accepted point; `y` a zero of the parameters' structure (to unravel
    the step)."""

    r: Float[Array, "k k"]
    c: Float[Array, " k"]
    y: PyTree[Array]


class FactoredDampedNewtonDescent(optx.AbstractDescent):
    """The Levenberg-Marquardt step $-\\delta$, $\\delta = \\arg\\min \\lVert J\\delta - r\\rVert^2 +
    \\lambda\\lVert\\delta\\rVert^2$ with $\\lambda = 1/$step size (optimistix's `DampedNewtonDescent`'s), from
    the R factor of $[J \\mid r]$ made once per accepted point (module docstring: no `dormqr`, whose use by
    `lineax.QR` races on CPU).

    For residuals given as any pytree of arrays and parameters of `k` entries (any pytree); the Jacobian is
    materialized, `(*s, k)` for a residual leaf of shape `s`, as `lineax.QR` did (as one `(m, k)` matrix). Each
    leaf's $[J \\mid r]$ is factored apart and, with `blocks` > 1, in `blocks` equal row blocks along the leaf's
    first axis (where it divides it); the small factors are stacked and factored again (TSQR: the R factor of
    stacked rows is that of the stacked R factors, up to the rows' signs, which the step does not see). With the
    samples sharded over `blocks` devices (`fit_brdf`), each device then factors its own rows and only the
    `(blocks (k + 1), k + 1)` factors are gathered, not the `(m, k + 1)` matrix. A step size at or below the
    dtype's eps gives $\\lambda$ = the dtype's largest value, a vanishing step, as optimistix's."""

    blocks: int = eqx.field(static=True, default=1)

    def init(self, y: PyTree[Array], f_info_struct) -> _FactoredState:
        del f_info_struct
        flat, _ = ravel_pytree(y)
        k = flat.shape[0]
        return _FactoredState(jnp.zeros((k, k), flat.dtype), jnp.zeros((k,), flat.dtype),
                              jax.tree_util.tree_map(jnp.zeros_like, y))

    def query(self, y: PyTree[Array], f_info: optx.FunctionInfo.ResidualJac, state: _FactoredState) -> _FactoredState:
        del y
        if not isinstance(f_info, optx.FunctionInfo.ResidualJac):
            raise ValueError("`FactoredDampedNewtonDescent` needs a least-squares problem's residual and Jacobian "
                             f"(`FunctionInfo.ResidualJac`), got {type(f_info).__name__}")
        flat, unravel = ravel_pytree(state.y)
        k = flat.shape[0]
        # the Jacobian of each residual leaf, (*s, k): J e_j for the k unit vectors (lineax's `as_matrix`, per leaf)
        cols = jax.vmap(lambda e: f_info.jac.mv(unravel(e)), out_axes=-1)(jnp.eye(k, dtype=flat.dtype))
        parts, stacked = [], False
        for j, r in zip(jax.tree_util.tree_leaves(cols), jax.tree_util.tree_leaves(f_info.residual)):
            a = jnp.concatenate([j, r[..., None].astype(j.dtype)], -1)  # (*s, k + 1)
            b = self.blocks if a.ndim > 1 and a.shape[0] % self.blocks == 0 else 1
            stacked |= b > 1
            parts.append(unbatched(_r_factor)(a.reshape(b, -1, k + 1)).reshape(-1, k + 1))  # b R factors
        # one leaf in one block is already triangular; stacked factors are not (even when they have k + 1 rows)
        stacked |= len(parts) > 1
        rf = unbatched(_r_factor)(jnp.concatenate(parts)) if stacked else parts[0]
        rf = jnp.pad(rf, ((0, k + 1 - rf.shape[0]), (0, 0)))  # fewer residuals than k + 1: zero rows
        return _FactoredState(rf[:k, :k], rf[:k, k], state.y)

    def step(self, step_size: Scalar, state: _FactoredState) -> tuple[PyTree[Array], optx.RESULTS]:
        r, c = state.r, state.c
        k = c.shape[0]
        dt = r.dtype
        step_size = jnp.asarray(step_size, dt)
        usable = step_size > jnp.finfo(dt).eps  # as optimistix's `damped_newton_step`
        lam = jnp.where(usable, 1 / jnp.where(usable, step_size, 1), jnp.finfo(dt).max)
        d = unbatched(_damped_solve)(r, c, lam)
        _, unravel = ravel_pytree(state.y)
        return unravel(-d), optx.RESULTS.successful


def _quiet(**kwargs):
    del kwargs


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """`optimistix.LevenbergMarquardt` with `RoundingTrustRegion` and `FactoredDampedNewtonDescent` (module
    docstring): the same damped Gauss-Newton step and Cauchy termination on `rtol`, `atol` (with `norm`); `blocks`:
    `FactoredDampedNewtonDescent`'s row blocks (the devices the residuals are sharded over)."""

    rtol: float
    atol: float
    norm: Callable
    descent: FactoredDampedNewtonDescent
    search: RoundingTrustRegion
    verbose: Callable

    def __init__(self, rtol: float, atol: float, norm: Callable = optx.max_norm, verbose: Callable | None = None,
                 blocks: int = 1):
        self.rtol = rtol
        self.atol = atol
        self.norm = norm
        self.descent = FactoredDampedNewtonDescent(blocks)
        self.search = RoundingTrustRegion()
        self.verbose = _quiet if verbose is None else verbose


def _r_factor(a):
    """The R factor of `a` `(..., m, n)` (`geqrf` alone)."""
    return jnp.linalg.qr(a, mode="r")


def _damped_solve(r, c, lam):
    """min |R d - c|^2 + lam |d|^2 for an upper-triangular `r` `(k, k)`: the 2k x k least-squares problem
    [R; sqrt(lam) I] d = [c; 0] by QR. Under a `vmap` (a batch of fits, `fit_many`) it runs one fit at a time on a
    CPU (`unbatched`: a batched CPU LAPACK call can deadlock, `solvers._lapack`)."""
    k = c.shape[0]
    q2, r2 = jnp.linalg.qr(jnp.concatenate([r, jnp.sqrt(lam) * jnp.eye(k, dtype=r.dtype)]))
    return jax.scipy.linalg.solve_triangular(r2, q2[:k].T @ c, lower=False)
