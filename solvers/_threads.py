"""Keep OpenBLAS single-threaded while a solver runs (a scoped setting, restored on exit).

jaxlib runs its CPU LAPACK kernels (Cholesky, LU, eigh, SVD) through
SciPy's OpenBLAS. On a 2-core machine, OpenBLAS's worker threads and XLA's
intra-op thread pool spin against each other: 40 solves of three 169×169
systems took 16-20 s instead of 0.03 s (measured; it also happens outside
loops). `threadpoolctl.threadpool_limits(1, "blas")` for the duration of a
solver call removes that, without touching any global flag. The limit applies only when JAX's default
backend is the CPU: on a GPU the solvers' linear algebra runs on the device
(cuSOLVER), and the host's BLAS threads are left as they are.
"""

from __future__ import annotations

import functools

import jax
from threadpoolctl import threadpool_limits


def blas_single_thread(fn):
    """Decorator: run `fn` with BLAS/LAPACK limited to one thread (threadpoolctl)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if jax.default_backend() != "cpu":  # GPU/TPU: LAPACK runs on the device; leave the host BLAS alone
            return fn(*args, **kwargs)
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
