"""LAPACK calls that stay unbatched on a CPU: `unbatched`, `map_lapack`.

jaxlib runs a *batched* CPU LAPACK call (an `eigh`, Cholesky, QR, SVD or LU of a stack of matrices, which is
what `jax.vmap` makes of one call) by fanning the matrices out into XLA's intra-op thread pool and waiting for
them from inside that pool (`jax::ParallelBatchMap`, jaxlib 0.10.2). When every thread of the pool is such a
waiting call, nothing is left to run the fanned-out work: the process hangs, every thread idle (native stacks:
two pool threads in `jax::CholeskyFactorization` → `ParallelBatchMap` → `BlockingCounter::Wait`, the callers
in `BlockUntilReady`). The pool has one thread per core, so on a 2-core machine two batched calls at once are
enough. Measured on one: `solvers.factorize` and `solvers.inverse_lighting` called from two host threads hung,
and so did one compiled program holding two independent batched Cholesky factorizations, called from a single
thread; with 4 forced host devices, which share the pool, so did any program with a batched `eigh`
(docs/performance.md, "Batched LAPACK calls on CPU"; docs/howto_scale.md). An unbatched call does not fan out.

So on a CPU the solvers make their LAPACK calls one matrix at a time:

- `unbatched(fn)` is `fn`, except that on a CPU a `jax.vmap` of it runs `fn` once per member in a loop
  (`jax.custom_batching.sequential_vmap`), however deep the `vmap`s around it (a `vmap`ped fit, `fit_many`);
  forward-mode derivatives pass through it, reverse mode does not (use it only where nothing is differentiated
  in reverse: the solvers' own eigen-, QR and LU solves), and every argument of `fn` is traced (give it arrays
  only: `jnp.linalg.eigh` itself would receive its keyword defaults as tracers);
- `map_lapack(fn, *args)` is `jax.vmap(fn)(*args)` over the leading axes, with `fn` `unbatched`.

The loop holds one copy of `fn` in the compiled program (9 unrolled `eigh` calls compiled in 0.71 s against
0.12 s for one batched call). Other platforms keep the batched calls. The platform is read at trace time
(`jax.default_backend()`).
"""

from __future__ import annotations

import jax
from jax.custom_batching import sequential_vmap


def unbatched(fn):
    """`fn`, whose `jax.vmap` runs one member at a time on a CPU (module docstring)."""
    if jax.default_backend() != "cpu":
        return fn
    return sequential_vmap(fn)


def map_lapack(fn, *args):
    """`jax.vmap(fn)(*args)` over the leading axis of each argument; on a CPU one member at a time (`unbatched`)."""
    return jax.vmap(unbatched(fn))(*args)
