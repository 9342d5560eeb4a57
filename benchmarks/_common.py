"""Timing and table helpers shared by the benchmark scripts (not a benchmark itself)."""

from __future__ import annotations

import time

import jax


def _block(r):
    jax.block_until_ready(r)
    return r


# Fast calls are repeated beyond `repeats` until MIN_TOTAL seconds were spent
# (at most MAX_REPEATS runs): the minimum is then less sensitive to other load.
MIN_TOTAL = 0.3
MAX_REPEATS = 30


def time_jax(fn, repeats=3):
    """(first call incl. compile, min of >= `repeats` warm runs) in seconds; results discarded."""
    t0 = time.perf_counter()
    r = _block(fn())
    first = time.perf_counter() - t0
    del r
    r = _block(fn())  # warm-up
    del r
    ts = []
    while len(ts) < repeats or (sum(ts) < MIN_TOTAL and len(ts) < MAX_REPEATS):
        t0 = time.perf_counter()
        r = _block(fn())
        ts.append(time.perf_counter() - t0)
        del r
    return first, min(ts)


def time_np(fn, repeats=3, warmup=True):
    """(first call, min warm) in seconds for a non-JAX callable."""
    t0 = time.perf_counter()
    r = fn()
    first = time.perf_counter() - t0
    del r
    if warmup and repeats > 1:
        r = fn()
        del r
    ts = []
    while len(ts) < repeats or (sum(ts) < MIN_TOTAL and len(ts) < MAX_REPEATS):
        t0 = time.perf_counter()
        r = fn()
        ts.append(time.perf_counter() - t0)
        del r
    return first, min(ts)


def fmt_t(t):
    if t is None:
        return "-"
    if t >= 1.0:
        return f"{t:7.2f} s"
    if t >= 1e-3:
        return f"{t * 1e3:7.2f} ms"
    return f"{t * 1e6:7.1f} us"


def fmt_e(x):
    return "-" if x is None else f"{x:.1e}"


class Table:
    def __init__(self, title, cols):
        self.title = title
        self.cols = cols
        self.rows = []
        self._t = time.perf_counter()

    def add(self, *vals):
        self.rows.append([("" if v is None else str(v)) for v in vals])
        # print progressively too (long runs), flushed
        now = time.perf_counter()
        print(f"  .. [{now - self._t:5.1f} s] " + " | ".join(r for r in self.rows[-1] if r), flush=True)
        self._t = now

    def sep(self):
        self.rows.append(None)

    def show(self):
        w = [len(c) for c in self.cols]
        for r in self.rows:
            if r is None:
                continue
            for i, v in enumerate(r):
                w[i] = max(w[i], len(v))
        line = "-+-".join("-" * x for x in w)
        print()
        print("=" * len(line))
        print(self.title)
        print("=" * len(line))
        print(" | ".join(c.ljust(x) for c, x in zip(self.cols, w)))
        print(line)
        for r in self.rows:
            if r is None:
                print(line)
            else:
                print(" | ".join(v.ljust(x) for v, x in zip(r, w)))
        print(flush=True)


def ratio(t_ours, t_peer):
    if t_ours is None or t_peer is None or t_peer == 0:
        return "-"
    r = t_ours / t_peer
    return f"{r:.2f}" if r >= 0.1 else f"{r:.3f}" if r >= 0.001 else f"{r:.1e}"
