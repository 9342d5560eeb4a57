"""The one module that uses jaxopt (unmaintained upstream): box-constrained minimization.

optimistix has no bound-constrained solver; jaxopt's L-BFGS-B does. Its
DeprecationWarning is filtered here (and in the test configuration).
"""

from __future__ import annotations

import warnings

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    import jaxopt


def effective_tol(tol: float, dtype) -> float:
    """The stopping tolerance `minimize_nonnegative` uses: `max(tol, 256 eps)` of `dtype`.

    jaxopt's test is absolute: the largest component of the projected gradient
    `clip(x - grad, lower, upper) - x` at most `tol`. Its round-off is a
    small multiple of `eps` (the dual lighting's refinement in float32
    stalls at 1.5e-8 at h = 16 and 3.4e-6 at h = 64), so a `tol` below that
    (1e-8 in float32, eps 1.2e-7) could never be met: the run would report
    `max_steps_reached` at a solution already exact to the dtype. The floor
    is 3.1e-5 in float32 and 5.7e-14 in float64.
    """
    import jax.numpy as jnp

    return max(float(tol), 256.0 * float(jnp.finfo(dtype).eps))


def minimize_nonnegative(fun, x0, maxiter: int = 500, tol: float = 1e-8):
    """Minimize a smooth `fun(x)` subject to `x >= 0` (jaxopt.LBFGSB). Returns `(x, num_iter, error)`.

    `error` is L-BFGS-B's final projected-gradient norm (the largest component, absolute: scale `fun` and `x`
    so that means something): the run converged when `error <= effective_tol(tol, x0.dtype)`, the tolerance
    it stops at; callers turn it into a `Status` with `solvers._results.status_from_lbfgsb` and that
    tolerance (never drop it).
    """
    import jax.numpy as jnp

    solver = jaxopt.LBFGSB(fun=fun, maxiter=maxiter, tol=effective_tol(tol, x0.dtype))
    lower = jnp.zeros_like(x0)
    upper = jnp.full_like(x0, jnp.inf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        res = solver.run(x0, bounds=(lower, upper))
    # the projection can leave -1e-19 round-off below the bound
    return jnp.maximum(res.params, 0.0), res.state.iter_num, res.state.error
