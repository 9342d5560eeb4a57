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
works as optimistix's. Built from optimistix's public parts (`AbstractGaussNewton`, `DampedNewtonDescent`,
`ClassicalTrustRegion`), as its documentation shows for custom solvers.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

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


def _quiet(**kwargs):
    del kwargs


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """`optimistix.LevenbergMarquardt` with `RoundingTrustRegion` (module docstring): the same damped Newton
    descent, linear solver and Cauchy termination on `rtol`, `atol` (with `norm`)."""

    rtol: float
    atol: float
    norm: Callable
    descent: optx.DampedNewtonDescent
    search: RoundingTrustRegion
    verbose: Callable

    def __init__(self, rtol: float, atol: float, norm: Callable = optx.max_norm,
                 linear_solver: lx.AbstractLinearSolver = lx.QR(), verbose: Callable | None = None):
        self.rtol = rtol
        self.atol = atol
        self.norm = norm
        self.descent = optx.DampedNewtonDescent(linear_solver=linear_solver)
        self.search = RoundingTrustRegion()
        self.verbose = _quiet if verbose is None else verbose
