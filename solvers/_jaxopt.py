"""The one module that uses jaxopt (unmaintained upstream): box-constrained minimization.

optimistix has no bound-constrained solver; jaxopt's L-BFGS-B does. Its
DeprecationWarning is filtered here (and in the test configuration).
"""

from __future__ import annotations

import warnings

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    import jaxopt


def minimize_nonnegative(fun, x0, maxiter: int = 500, tol: float = 1e-8):
    """Minimize a smooth `fun(x)` subject to `x >= 0` (jaxopt.LBFGSB). Returns `(x, num_iter, error)`.

    `error` is L-BFGS-B's final projected-gradient norm: the run converged when `error <= tol`; callers
    turn it into a `Status` with `solvers._results.status_from_lbfgsb` (never drop it).
    """
    import jax.numpy as jnp

    solver = jaxopt.LBFGSB(fun=fun, maxiter=maxiter, tol=tol)
    lower = jnp.zeros_like(x0)
    upper = jnp.full_like(x0, jnp.inf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        res = solver.run(x0, bounds=(lower, upper))
    # the projection can leave -1e-19 round-off below the bound
    return jnp.maximum(res.params, 0.0), res.state.iter_num, res.state.error
