"""Timing and table helpers shared by the benchmark scripts (not a benchmark itself)."""

from __future__ import annotations

import os
import sys
import time

import jax
import numpy as np


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


# --------------------------------------------------------------------------- peers in a subprocess


class PeerError(RuntimeError):
    """A peer subprocess failed (crashed, timed out, or wrote no result)."""


def run_peer(script, spec, arrays=None, timeout=1800):
    """Run a peer that cannot share a process with XLA: ``python script IN.npz OUT.npz`` in a subprocess.

    The peer gets ``spec`` (JSON-serialisable, stored as the string ``spec``)
    and the numpy ``arrays`` in a temporary ``IN.npz``, and writes ``OUT.npz``
    with a JSON string ``meta`` and any arrays. Returns ``(meta dict, {name:
    array})``. The subprocess is the same interpreter (``sys.executable``),
    never imports JAX, and inherits the environment. Raises ``PeerError``
    with the tail of its output when it exits non-zero (e.g. an LLVM abort)
    or times out.
    """
    import json
    import os
    import subprocess
    import sys
    import tempfile

    import numpy as np

    path = script if os.path.isabs(script) else os.path.join(os.path.dirname(os.path.abspath(__file__)), script)
    with tempfile.TemporaryDirectory(prefix="jaxsh_peer_") as d:
        inp, out = os.path.join(d, "in.npz"), os.path.join(d, "out.npz")
        np.savez(inp, spec=np.asarray(json.dumps(spec)), **(arrays or {}))
        try:
            p = subprocess.run([sys.executable, path, inp, out], capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired as e:
            raise PeerError(f"{os.path.basename(path)} timed out after {timeout} s") from e
        if p.returncode != 0 or not os.path.exists(out):
            tail = (p.stdout + p.stderr).strip().splitlines()[-8:]
            raise PeerError(f"{os.path.basename(path)} exited with status {p.returncode}: " + " | ".join(tail))
        with np.load(out, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            res = {k: z[k] for k in z.files if k != "meta"}
    return meta, res


# --------------------------------------------------------------------------- glibc's malloc and huge pages

HUGEPAGES = "glibc.malloc.hugetlb=1"


def hugepages_env(env):
    """A copy of `env` whose ``GLIBC_TUNABLES`` holds ``glibc.malloc.hugetlb=1`` (other tunables kept).

    With it (glibc >= 2.35), malloc advises transparent huge pages for the blocks it maps, which XLA's CPU
    buffers of more than 32 MB are: the first write of a fresh output then takes one fault per 2 MB instead of
    one per 4 KB page (docs/performance.md, "Page faults on large outputs"). NumPy already advises huge pages
    for its own large arrays, so NumPy and C++ peers are unaffected. Glibc reads the tunable when a process
    starts: it cannot be set from inside one.
    """
    kept = [t for t in env.get("GLIBC_TUNABLES", "").split(":") if t and not t.startswith("glibc.malloc.hugetlb=")]
    return {**env, "GLIBC_TUNABLES": ":".join(kept + [HUGEPAGES])}


def hugepages_on(env=None):
    """Whether `env` (default: this process's environment) sets ``glibc.malloc.hugetlb=1``."""
    env = os.environ if env is None else env
    return HUGEPAGES in env.get("GLIBC_TUNABLES", "").split(":")


def thp_mode():
    """The kernel's transparent huge page mode (``always``, ``madvise``, ``never``), or ``unknown``."""
    try:
        with open("/sys/kernel/mm/transparent_hugepage/enabled") as f:
            text = f.read()
    except OSError:
        return "unknown"
    return text.split("[", 1)[1].split("]", 1)[0] if "[" in text else "unknown"


def malloc_line():
    """One line for a benchmark's header: how large XLA buffers are backed in this run."""
    if hugepages_on():
        return (f"glibc malloc huge pages: on (GLIBC_TUNABLES={os.environ['GLIBC_TUNABLES']}; kernel THP mode "
                f"{thp_mode()})")
    return (f"glibc malloc huge pages: off, the default (kernel THP mode {thp_mode()}); --hugepages runs with "
            f"GLIBC_TUNABLES={HUGEPAGES} (docs/performance.md, 'Page faults on large outputs')")


def add_hugepages_option(parser):
    parser.add_argument(
        "--hugepages", action="store_true",
        help=f"run with GLIBC_TUNABLES={HUGEPAGES} (the script starts itself again with it): XLA's large CPU "
             "buffers on transparent huge pages, as NumPy's arrays already are",
    )


def apply_hugepages(args):
    """With ``--hugepages``, replace this process by the same command with `hugepages_env` (once)."""
    if getattr(args, "hugepages", False) and not hugepages_on():
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, [sys.executable] + sys.argv, hugepages_env(os.environ))


SEARCH_SAMPLES = 40000  # solvers.fit_brdf's default `search_pixels`


def search_subset(n: int, m: int = SEARCH_SAMPLES):
    """`m` indices evenly spaced over `n` samples, or None when `n <= m`: the samples `solvers.fit_brdf` runs its
    grid and Nelder-Mead on (`solvers._brdf._search_samples`, every sample of positive weight here)."""
    return None if n <= m else np.round(np.linspace(0, n - 1, m)).astype(np.int64)


def scipy_real_sh(d, lmax: int):
    """Real SH `(N, (lmax+1)^2)` of unit directions `d` `(N, 3)` in float64 from `scipy.special.sph_harm_y` (vectorized
    over the points; docs/conventions.md: $Y_{l,\\pm m} = \\sqrt2(-1)^m(\\mathrm{Re}, \\mathrm{Im})\\,Y_l^m$): the
    benchmarks' independent reference for the accuracy of both jaxsh and its peers."""
    from scipy.special import sph_harm_y

    d = np.asarray(d, np.float64)
    theta, phi = np.arctan2(np.hypot(d[:, 0], d[:, 1]), d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    out = np.empty((d.shape[0], (lmax + 1) ** 2))
    for l in range(lmax + 1):
        out[:, l * l + l] = sph_harm_y(l, 0, theta, phi).real
        for m in range(1, l + 1):
            y = sph_harm_y(l, m, theta, phi)
            out[:, l * l + l + m] = np.sqrt(2.0) * (-1) ** m * y.real
            out[:, l * l + l - m] = np.sqrt(2.0) * (-1) ** m * y.imag
    return out
