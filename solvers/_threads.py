"""Keep OpenBLAS single-threaded while a solver runs (a scoped setting, restored on exit).

jaxlib runs its CPU LAPACK kernels (Cholesky, LU, eigh, SVD) through
SciPy's OpenBLAS. On a 2-core machine, OpenBLAS's worker threads and XLA's
intra-op thread pool spin against each other: 40 solves of three 169×169
systems took 16-20 s instead of 0.03 s (measured; it also happens outside
loops). `threadpoolctl.threadpool_limits(1, "blas")` for the duration of a
solver call removes that, without touching any global flag.
"""

from __future__ import annotations

import functools

from threadpoolctl import threadpool_limits


def blas_single_thread(fn):
    """Decorator: run `fn` with BLAS/LAPACK limited to one thread (threadpoolctl)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
