"""Per-pixel maps on every core of one CPU device: the pixels in equal parts, one host thread each.

XLA:CPU runs a program's loop over chunks of pixels on one core: `jaxsh.practical_terms`'s band sums
(`_sh_bands`, a `lax.map` over chunks of 256 mirror directions, lmax 40) took 450-480 ms at 127,584
pixels with a CPU time of 0.9 times the wall time on this project's 2-core machine, whatever the chunk
(128-4,096), and two such loops in one program ran one after the other. JAX dispatches a CPU program in the
calling thread and releases the GIL while it runs, so two host threads run two calls at once: the two
halves took 269 ms, 325-340 ms with the join (docs/performance.md, "Twenty-ninth round").

`map_in_threads(fn, pixels, ...)` splits the pixel arrays into `P` parts of `m` rows each (`m` a multiple
of `align`, the last part padded by repeating the last pixel, so that every part has the shape of the
first and one compiled program serves all of them), calls `fn` on each part in its own thread, and joins
the per-pixel outputs in one program (`[:N]`). Each pixel's output is computed by the same program on the
same chunk shape as in one call, so the joined result equals `fn(*pixels)` (bitwise, when `align` is the
callee's chunk; `tests/test_pixel_threads.py`).

It applies only where it can help and cannot change what is computed: concrete arrays on one CPU device
(not inside a caller's `jit`: tracers go to `fn` directly; sharded pixels take `_pixel_sums`' route), at
least two parts of `_PART_MIN` pixels, pixel arrays that agree on `N` (otherwise `fn` raises its own
error). `P` is the number of cores this process may use (`os.sched_getaffinity`), at most `_PARTS_MAX`.

What `fn` may run: programs without LAPACK calls. Two threads running `factorize`'s `_mu_blocks` (Gram blocks
from a `MirrorTable`, then a batched `eigh`, jaxlib's `lapack_dsyevd_ffi`) at once hung at their first
concurrent call, every thread waiting in `BlockUntilReady` and XLA's pool idle, with OpenBLAS at one thread or
two; its Gram part alone, its `eigh` part alone and a plain batched `eigh` ran 10-50 concurrent rounds without
it. `jaxsh.practical_terms` has no LAPACK call (its only custom calls are the run-time checks' error
callbacks): 300 calls on `bench_inverse.py`'s capture, in 2 and in 8 parts, all finished, bitwise equal.

The first call of a program must not compile it once per thread (JAX does not merge concurrent compilations
of the same program: two threads compiled `_practical_terms` twice, in 0.32 s and 0.54 s). So the first
call with a given `key` (the caller's description of the program: its static arguments and the shapes of its
closed-over arrays) runs the first part alone, then the others at once.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor, wait

import jax
import jax.numpy as jnp
import numpy as np

import jaxsh

_PART_MIN = 16384
_PARTS_MAX = 8

_pool: ThreadPoolExecutor | None = None
_pool_pid: int | None = None
_pool_lock = threading.Lock()
_compiled: set = set()


def host_cores() -> int:
    """The number of cores this process may run on (its CPU affinity; `os.cpu_count()` where unknown)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def n_parts(n: int) -> int:
    """How many parts `map_in_threads` makes of `n` pixels: `host_cores()`, at most `_PARTS_MAX`, and no more than
    `n // _PART_MIN` (so that each part is worth a thread); 1 means one call."""
    return max(1, min(host_cores(), _PARTS_MAX, n // _PART_MIN))


def _executor() -> ThreadPoolExecutor:
    """The threads of the parts after the first, made at the first use (and again in a forked child, which
    inherits the pool's bookkeeping but not its threads)."""
    global _pool, _pool_pid
    with _pool_lock:
        if _pool is None or _pool_pid != os.getpid():
            _pool = ThreadPoolExecutor(max_workers=_PARTS_MAX - 1, thread_name_prefix="jaxsh-pixels")
            _pool_pid = os.getpid()
        return _pool


@jaxsh.jit
def _split(pixels, parts: int, size: int):
    """`parts` slices of `size` rows of every array of `pixels`, the last padded by repeating the last row."""

    def one(x):
        pad = parts * size - x.shape[0]
        if pad:
            x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])])
        return tuple(x[i * size:(i + 1) * size] for i in range(parts))

    cut = [None if x is None else one(x) for x in pixels]
    return tuple(tuple(None if c is None else c[i] for c in cut) for i in range(parts))


@jaxsh.jit
def _join(leaves, n: int, per_pixel: tuple[bool, ...]):
    """Leaf `k` of the parts' outputs joined along the pixels and cut to `n` rows where `per_pixel[k]`, else the
    first part's."""
    return [jnp.concatenate(xs)[:n] if p else xs[0] for xs, p in zip(zip(*leaves), per_pixel)]


def _applies(pixels: tuple) -> int:
    """The number of parts for `pixels` (1: call `fn` directly)."""
    arrays = [x for x in pixels if x is not None]
    if not arrays or any(isinstance(x, jax.core.Tracer) or not hasattr(x, "shape") or np.ndim(x) == 0 for x in arrays):
        return 1
    n = arrays[0].shape[0]
    if any(x.shape[0] != n for x in arrays):
        return 1
    for x in arrays:
        devices = getattr(getattr(x, "sharding", None), "device_set", None)
        if devices is not None and (len(devices) != 1 or next(iter(devices)).platform != "cpu"):
            return 1
    if jax.default_backend() != "cpu":
        return 1
    return n_parts(n)


def map_in_threads(fn, pixels: tuple, key, replicated: tuple[str, ...] = (), align: int = 1):
    """`fn(*pixels)`, made on `n_parts(N)` equal parts of the pixels in as many host threads and joined.

    `pixels`: arrays with the pixels on their first axis (`N` rows), or None. `fn`'s outputs are per-pixel
    arrays (first axis the part's rows) or, for the fields named in `replicated`, the same for every part
    (taken from the first). `key`: a hashable description of the program `fn` calls beyond the pixels' shapes
    (its static arguments and closed-over arrays), to run a first call's first part alone (module docstring).
    `align`: the parts' rows are a multiple of it (the callee's chunk).
    """
    parts = _applies(pixels)
    if parts < 2:
        return fn(*pixels)
    n = next(x for x in pixels if x is not None).shape[0]
    size = -(-n // (parts * align)) * align
    parts = -(-n // size)
    if parts < 2:
        return fn(*pixels)
    cut = _split(tuple(pixels), parts, size)
    sig = (key, size, tuple(None if x is None else (tuple(x.shape[1:]), str(x.dtype)) for x in pixels))
    outs = [None] * parts
    if sig not in _compiled:
        outs[0] = jax.block_until_ready(fn(*cut[0]))
        _compiled.add(sig)
        rest = list(range(1, parts))
    else:
        rest = list(range(parts))
    pool = _executor()
    futures = {i: pool.submit(lambda p: jax.block_until_ready(fn(*p)), cut[i]) for i in rest[1:]}
    try:
        outs[rest[0]] = jax.block_until_ready(fn(*cut[rest[0]]))
    except BaseException:
        wait(futures.values())  # no thread left running on the parts when the error reaches the caller
        raise
    for i, f in futures.items():
        outs[i] = f.result()
    flat = [jax.tree_util.tree_flatten_with_path(o) for o in outs]
    treedef = flat[0][1]
    per_pixel = tuple(
        not (getattr(path[-1], "name", None) in replicated if path else False) and leaf.shape[:1] == (size,)
        for path, leaf in flat[0][0]
    )
    leaves = [[leaf for _, leaf in f[0]] for f in flat]
    return jax.tree_util.tree_unflatten(treedef, _join(leaves, n, per_pixel))
