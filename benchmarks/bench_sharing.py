"""Benchmark reflectance sharing (Zickler 2006): RBF fit, evaluation, greedy centres, 512x512 prediction.

Run from the repository root with the project's venv::

    python benchmarks/bench_sharing.py            # full run (~3-4 min on 2 cores)
    python benchmarks/bench_sharing.py --quick    # 1,000 / 2,000 centres, 256x256, greedy from 3e4 (~1 min)

Data: 5-D SBRDF samples (x, y, u, v, w) of the synthetic hemisphere with
linearly varying Cook-Torrance roughness (Zickler 2006 sec. 7.1), 3 colour
channels, metric M = diag(0.3, 0.3, 1, 1, 0.5) (eq. 11); random subsets of
1,000 / 2,000 / 5,000 samples are the centres. float64 throughout (the script
enables ``jax_enable_x64``; the library itself never does).

Rows (wall-clock; "first" = trace + compile + run, "warm" = min of repeated
runs, ``_common.time_jax``; the multi-second scipy peer calls are timed once,
without a warm-up: NumPy/SciPy compile nothing):

1. fit, all samples as centres (interpolation, eq. 10): ``solvers.fit_sharing``
   (LU of the saddle-point matrix, 3 right-hand sides; includes the input
   checks: duplicates, degeneracy) vs ``scipy.interpolate.RBFInterpolator(
   points * scale, values, kernel="linear", degree=1)`` (construction = its
   solve) vs ``interpax.RBFInterpolator`` (same arguments) if installed.
2. evaluation at 512x512 = 262,144 points: ``RBFModel.__call__`` (chunked)
   vs scipy's ``__call__`` vs interpax's. The max abs difference to scipy is
   printed. The float32 row evaluates the same (float64-fitted) model cast
   to float32 (``RBFModel.astype``); its ratio is against scipy (float64).
3. the 512x512 prediction of ``RBFReflectance.render`` (uvw of every pixel +
   evaluation + shading) with 2,000 centres; then 8 new lights, each lighting
   its own set of pixels (the time per light, compilation included: a new
   light used to compile new programs), against scipy's ``__call__``
   evaluating the same model at the same rendered points (computed outside
   its timing) and shading them in NumPy.
4. greedy selection of 2,000 centres from 10^5 samples (200 initial + 200 a
   round): ``fit_sharing(n_centers=2000)`` vs the same loop written with scipy
   (refit ``RBFInterpolator`` on the centres, evaluate at all samples, add
   the 200 worst).

Ratios are jaxsh / peer (below 1 = jaxsh faster). Other processes on the
machine add noise (the load average at start is printed).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.interpolate import RBFInterpolator  # noqa: E402

warnings.filterwarnings("ignore", category=DeprecationWarning)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from _common import (  # noqa: E402
    Table, add_hugepages_option, apply_hugepages, fmt_e, fmt_t, malloc_line, ratio, time_jax, time_np,
)

import jaxsh  # noqa: E402
import solvers  # noqa: E402
from solvers import synthetic as Z  # noqa: E402

try:
    import interpax

    INTERPAX_ERR = None
except Exception as e:  # pragma: no cover
    interpax = None
    INTERPAX_ERR = f"{type(e).__name__}: {e}"

SCALE = np.array([0.3, 0.3, 1.0, 1.0, 0.5])


def samples(n_px, n_lights, seed=0):
    normal, mask, xy = Z.sphere_geometry(n_px)
    lights = Z.cone_lights(n_lights, 1.0)
    imgs = Z.render_images(Z.varying_cook_torrance, normal, mask, lights, xy=xy)
    smp = solvers.reflectance_samples(imgs, normal, Z.VIEW, lights, mask=mask, xy=xy, min_cos=0.1)
    p, v = np.asarray(smp.points), np.asarray(smp.values)
    p, first = np.unique(p, axis=0, return_index=True)
    v = v[first]
    perm = np.random.default_rng(seed).permutation(len(p))
    return p[perm], v[perm]


def time_once(fn):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return first, time.perf_counter() - t0


def scipy_greedy(p, v, w, k_max, n_init, n_add, seed=0):
    rng = np.random.default_rng(seed)
    idx = list(rng.choice(len(p), n_init, replace=False))
    ps = p * SCALE
    while True:
        itp = RBFInterpolator(ps[idx], v[idx], kernel="linear", degree=1)
        if len(idx) >= k_max:
            return itp
        e = np.sum(((v - itp(ps)) * w[:, None]) ** 2, axis=1)
        e[idx] = -1.0
        idx += list(np.argsort(-e)[:n_add])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    add_hugepages_option(ap)
    args = ap.parse_args()
    apply_hugepages(args)
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, load average {os.getloadavg()[0]:.2f}; "
          f"interpax: {interpax.__version__ if interpax else 'not available (' + str(INTERPAX_ERR) + ')'}")
    print(malloc_line())
    sizes = (1000, 2000) if args.quick else (1000, 2000, 5000)
    n_eval = 256 if args.quick else 512
    p_all, v_all = samples(160, 10)
    print(f"{len(p_all)} unique 5-D samples, 3 channels")
    rng = np.random.default_rng(1)
    ev = np.concatenate([rng.uniform(p_all.min(0), p_all.max(0), size=(n_eval * n_eval, 5))])
    tab = Table("Reflectance sharing: jaxsh vs scipy / interpax (float64, 3 channels, 5-D)",
                ["task", "impl", "warm", "first", "jaxsh/peer", "note"])
    for k in sizes:
        p, v = p_all[:k], v_all[:k]
        t1, tw = time_jax(lambda: solvers.fit_sharing(p, v, k, scale=SCALE).model.weights, repeats=2)
        tab.add(f"fit {k}", "jaxsh fit_sharing (LU)", fmt_t(tw), fmt_t(t1), "", "")
        ts1, tsw = time_np(lambda: RBFInterpolator(p * SCALE, v, kernel="linear", degree=1), repeats=2)
        tab.add(f"fit {k}", "scipy RBFInterpolator", fmt_t(tsw), fmt_t(ts1), ratio(tw, tsw), "")
        if interpax is not None:
            ti1, tiw = time_jax(lambda: interpax.RBFInterpolator(jnp.asarray(p * SCALE), jnp.asarray(v),
                                                                 kernel="linear", degree=1)._coeffs, repeats=2)
            tab.add(f"fit {k}", "interpax RBFInterpolator", fmt_t(tiw), fmt_t(ti1), ratio(tw, tiw), "")
        model = solvers.fit_sharing(p, v, k, scale=SCALE).model
        sp = RBFInterpolator(p * SCALE, v, kernel="linear", degree=1)
        evj = jnp.asarray(ev)
        t1, tw = time_once(lambda: model(evj))
        ours = np.asarray(model(evj))
        tab.add(f"eval {n_eval}^2 ({k} c.)", "jaxsh RBFModel", fmt_t(tw), fmt_t(t1), "", "")
        m32 = model.astype(jnp.float32)
        ev32 = jnp.asarray(ev, jnp.float32)
        t1, tw32 = time_once(lambda: m32(ev32))
        ours32 = np.asarray(m32(ev32))
        t0 = time.perf_counter()
        ref = sp(ev * SCALE)
        tsw = time.perf_counter() - t0
        err = float(np.max(np.abs(ours - ref)) / np.max(np.abs(ref)))
        tab.add(f"eval {n_eval}^2 ({k} c.)", "scipy __call__", fmt_t(tsw), "", ratio(tw, tsw),
                f"max rel diff {fmt_e(err)}")
        err32 = float(np.max(np.abs(ours32 - ref)) / np.max(np.abs(ref)))
        tab.add(f"eval {n_eval}^2 ({k} c.)", "jaxsh RBFModel float32", fmt_t(tw32), "", ratio(tw32, tsw),
                f"vs scipy; max rel diff {fmt_e(err32)}")
        if interpax is not None:
            ip = interpax.RBFInterpolator(jnp.asarray(p * SCALE), jnp.asarray(v), kernel="linear", degree=1)
            evs = jnp.asarray(ev * SCALE)
            ti1, tiw = time_once(lambda: ip(evs))
            tab.add(f"eval {n_eval}^2 ({k} c.)", "interpax __call__", fmt_t(tiw), fmt_t(ti1), ratio(tw, tiw), "")
        tab.sep()
    # 512x512 prediction (render) with 2,000 centres
    normal, mask, xy = Z.sphere_geometry(n_eval)
    m = solvers.RBFReflectance(solvers.fit_sharing(p_all[:2000], v_all[:2000], 2000, scale=SCALE), True)
    light = np.array([0.3, -0.2, 0.933])
    light = light / np.linalg.norm(light)
    nj, mj, xyj = jnp.asarray(normal), jnp.asarray(mask), jnp.asarray(xy)
    t1, tw = time_once(lambda: m.render(nj, Z.VIEW, light, mask=mj, xy=xyj))
    tab.add(f"render {n_eval}^2", "RBFReflectance.render, 2000 c.", fmt_t(tw), fmt_t(t1), "",
            f"{int(mask.sum())} px on the object")
    # new lights: each renders its own set of pixels (a user predicting held-out images); jaxsh per light,
    # compilation included, against scipy evaluating the same model at the same rendered points (given)
    novel = Z.cone_lights(8, 1.2, phase=1.3)
    t0 = time.perf_counter()
    ours = [np.asarray(m.render(nj, Z.VIEW, li, mask=mj, xy=xyj)) for li in novel]
    t_new = (time.perf_counter() - t0) / len(novel)
    sp = RBFInterpolator(p_all[:2000] * SCALE, v_all[:2000], kernel="linear", degree=1)
    pts, oks = [], []
    for li in novel:
        ok = mask & (normal @ li > 0) & (normal @ Z.VIEW > 0)
        pts.append(np.asarray(jaxsh.sbrdf_points(np.broadcast_to(li, normal.shape)[ok], np.broadcast_to(Z.VIEW, normal.shape)[ok],
                                                 normal[ok], xy[ok])))
        oks.append(ok)
    t0 = time.perf_counter()
    peer = []
    for li, q, ok in zip(novel, pts, oks):
        img = np.zeros(normal.shape[:-1] + (3,))
        img[ok] = np.maximum(sp(q * SCALE), 0.0) * (normal[ok] @ li)[:, None]
        peer.append(img)
    t_sp = (time.perf_counter() - t0) / len(novel)
    diff = max(float(np.max(np.abs(a - b))) for a, b in zip(ours, peer)) / max(float(np.max(np.abs(b))) for b in peer)
    tab.add(f"render {n_eval}^2, 8 new lights", "RBFReflectance.render, per light", fmt_t(t_new), "", ratio(t_new, t_sp),
            "compilation included")
    tab.add(f"render {n_eval}^2, 8 new lights", "scipy __call__ at the rendered points", fmt_t(t_sp), "", "",
            f"points given; max rel diff {fmt_e(diff)}")
    tab.sep()
    # greedy
    n_g = 30000 if args.quick else 100000
    p_g, v_g = samples(200 if not args.quick else 110, 10 if args.quick else 6, seed=2)
    p_g, v_g = p_g[:n_g], v_g[:n_g]
    w = np.ones(len(p_g))
    k_g = 1000 if args.quick else 2000
    t0 = time.perf_counter()
    g = solvers.fit_sharing(p_g, v_g, k_g, scale=SCALE, n_init=k_g // 10, n_add=k_g // 10)
    jax.block_until_ready(g.model.weights)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    g = solvers.fit_sharing(p_g, v_g, k_g, scale=SCALE, n_init=k_g // 10, n_add=k_g // 10,
                            key=jax.random.PRNGKey(3))
    jax.block_until_ready(g.model.weights)
    t_warm = time.perf_counter() - t0
    tab.add(f"greedy {k_g} of {len(p_g)}", "jaxsh fit_sharing", fmt_t(t_warm), fmt_t(t_first), "",
            f"rel. RMS {float(g.rel_rms):.4f}, {len(g.history_centers)} rounds")
    t0 = time.perf_counter()
    itp = scipy_greedy(p_g, v_g, w, k_g, k_g // 10, k_g // 10)
    t_sp = time.perf_counter() - t0
    r = v_g - itp(p_g * SCALE)
    rel = float(np.sqrt(np.sum(r**2) / np.sum(v_g**2)))
    tab.add(f"greedy {k_g} of {len(p_g)}", "scipy loop", fmt_t(t_sp), "", ratio(t_warm, t_sp), f"rel. RMS {rel:.4f}")
    tab.show()


if __name__ == "__main__":
    main()
