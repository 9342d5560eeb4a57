"""A residual function whose linearization carries its dense Jacobian and nothing else (`explicit_jacobian`).

`optimistix.LevenbergMarquardt` linearizes the residual at each accepted
point and keeps the linearization in its state, which passes through a
`lax.cond` every step. A linearization made by `jax.linearize` holds every
intermediate of the residual that the tangent needs: for `fit_brdf` at
127,584 samples, the `(N, C, L)` mirror-band table and about a hundred
per-sample vectors, which XLA:CPU copied into the branch outputs twice per
step (found in the optimized HLO). With few parameters the Jacobian itself
(`(m, k)`, by forward mode, `k` columns) is far smaller, and a `custom_jvp`
makes it the only residual of the linearization.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def explicit_jacobian(fn):
    """`fn(p, args) -> (m,)` with the same values and derivatives, linearized as `J @ dp`, `J = jacfwd(fn)` `(m, k)`.

    For `p` of shape `(k,)` with small `k` (the forward-mode Jacobian costs `k` tangent evaluations).
    `args` is not differentiated (its tangent is ignored). `fn` may return a pytree of arrays: each leaf of
    shape `s` then gets its own Jacobian `(*s, k)` (`fit_brdf`'s residual keeps its `(N, C)` samples apart from
    the box's two wall entries, so that sharded samples are not concatenated)."""

    @jax.custom_jvp
    def wrapped(p, args):
        return fn(p, args)

    @wrapped.defjvp
    def _jvp(primals, tangents):
        p, args = primals
        dp = tangents[0]
        eye = jnp.eye(p.shape[0], dtype=p.dtype)
        y, jac = jax.vmap(lambda t: jax.jvp(lambda q: fn(q, args), (p,), (t,)), out_axes=(None, -1))(eye)
        return y, jax.tree_util.tree_map(lambda j: j @ dp, jac)

    return wrapped
