"""Scale-out throughput (solvers._scale): a batch of captures and one large capture on 1, 2 and 4 devices.

Workloads (synthetic spheres under the demo's sources, practical model + 1 % noise; tests/_scale_worker.py):

- **batch**: `solvers.fit_many` of `--batch` captures (default 64) of 12-24 px, 1-2 views, different
  sizes (power-of-two buckets), the batch axis sharded over the devices;
- **large**: one capture of `--views` views (default 24) of `--size` px: `fit_brdf`, `inverse_lighting`
  (l* = 8) and `factorize` (l* = 8, its searches on a quarter of the pixels, so that its passes over all
  pixels are the sharded part; docs/howto_scale.md) on `solvers.shard_observations` (pixels sharded; each
  device sums its own pixels, one all-reduce adds them);
- **kernels**: `jaxsh.real_sh` (lmax 16) and `jaxsh.render_practical` (`method="exact"`) of `--points` points
  (default 2^17) split over the devices (`jax.device_put` with `NamedSharding(mesh, P("pixels", None))`), called
  outside `jit`: each device evaluates its own points, the output stays split.

Each device count runs in its own process (`XLA_FLAGS=--xla_force_host_platform_device_count=D`: JAX fixes
its devices at start). Reported: first call (with compilation) and the best warm call, throughput, and the
scaling efficiency $T_1 / (D\\,T_D)$. Peer, in the same run: the numpy/scipy serial loop of the fit
(`scipy_fit_brdf` of benchmarks/bench_inverse.py, one BLAS thread) over the batch; it also runs the
Levenberg-Marquardt refinement that `fit_many` skips (`refine=None`), about 8 % of its CPU time, so the
peer does a little more work than jaxsh here. On a GPU machine the
device counts are GPUs (`--gpu`). Forced host devices share the machine's cores: on a 2-core machine 4
devices cannot run faster than 2. The load average is printed (other processes add noise).

    python benchmarks/bench_scale.py [--batch 64] [--views 24] [--size 24] [--points 131072] [--devices 1 2 4]
        [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def child(args) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, ROOT)
    import numpy as np

    import solvers
    from tests._scale_worker import make_capture

    d = len(jax.devices())
    out = {"devices": d, "backend": jax.default_backend()}
    rng = np.random.default_rng(1)
    caps = [make_capture(size=int(rng.choice([12, 16, 20, 24])), n_views=1 + k % 2, seed=k, lmax=8)
            for k in range(args.batch)]
    mesh = solvers.pixel_mesh(d, axis="batch")

    def timed(fn, reps=2):
        t0 = time.perf_counter()
        r = fn()
        jax.block_until_ready(jax.tree_util.tree_leaves(r))
        first = time.perf_counter() - t0
        best = float("inf")
        for _ in range(reps):
            t0 = time.perf_counter()
            r = fn()
            jax.block_until_ready(jax.tree_util.tree_leaves(r))
            best = min(best, time.perf_counter() - t0)
        return first, best, r

    f, b, res = timed(lambda: solvers.fit_many(caps, mesh=mesh if d > 1 else None))
    out["batch"] = {"n": len(caps), "first_s": f, "warm_s": b, "captures_per_s": len(caps) / b,
                    "converged": sum(solvers.status_name(r.status) == "converged" for r in res)}
    obs, lit = make_capture(size=args.size, n_views=args.views, seed=99, lmax=8)
    sobs = solvers.shard_observations(obs, solvers.pixel_mesh(d))
    f, b, r = timed(lambda: solvers.fit_brdf(sobs, lit))
    out["large_fit_brdf"] = {"n_pixels": obs.n_samples, "first_s": f, "warm_s": b, "sigma": float(r.brdf.sigma)}
    brdf = r.brdf
    f, b, _ = timed(lambda: solvers.inverse_lighting(sobs, brdf, 8), reps=3)
    out["large_inverse_lighting"] = {"first_s": f, "warm_s": b}
    # the search subset (a quarter of the pixels) is gathered on every device; the passes over all pixels are sharded
    sub = max(obs.n_samples // 4, (8 + 1) ** 2 + 4)  # at least the search's unknowns at lmax 8
    f, b, r = timed(lambda: solvers.factorize(sobs, 8, search_pixels=sub), reps=2)
    out["large_factorize"] = {"first_s": f, "warm_s": b, "search_pixels": sub, "mu": float(r.brdf.mu),
                              "status": solvers.status_name(r.status)}
    # the kernels on arrays split over the devices (outside jit): each device evaluates its own points
    import jaxsh
    from jax.sharding import NamedSharding, PartitionSpec as P

    rows_on = NamedSharding(solvers.pixel_mesh(d), P("pixels", None))
    dirs = rng.normal(size=(args.points, 3))
    sdirs = jax.device_put(dirs, rows_on)
    f, b, y = timed(lambda: jaxsh.real_sh(sdirs, 16), reps=3)
    out["real_sh"] = {"n": args.points, "first_s": f, "warm_s": b, "spec": str(y.sharding.spec)}
    del y
    normals = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    normals[:, 2] = np.abs(normals[:, 2])
    views = np.broadcast_to([0.0, 0.0, 1.0], normals.shape)
    sn, sv = jax.device_put(normals, rows_on), jax.device_put(np.ascontiguousarray(views), rows_on)
    light = caps[0][1]
    brdf = jaxsh.TorranceSparrow(kd=[0.3, 0.2, 0.1], ks=[0.4, 0.4, 0.4], mu=1.5, sigma=0.15)
    f, b, y = timed(lambda: jaxsh.render_practical(sn, sv, brdf, light, method="exact"), reps=3)
    out["render_practical"] = {"n": args.points, "first_s": f, "warm_s": b, "spec": str(y.total.sharding.spec)}
    if args.peer:
        sys.path.insert(0, os.path.join(ROOT, "benchmarks"))
        from threadpoolctl import threadpool_limits

        from bench_inverse import scipy_fit_brdf

        def loop():
            for o, lt in caps:
                light = (np.asarray(lt.slow_sh), np.asarray(lt.fast_directions), np.asarray(lt.fast_energy))
                scipy_fit_brdf(np.asarray(o.normals), np.asarray(o.views), np.asarray(o.values), light)

        with threadpool_limits(1, "blas"):
            t0 = time.perf_counter()
            loop()
            out["peer_batch_s"] = time.perf_counter() - t0
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--size", type=int, default=24)
    ap.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--points", type=int, default=2 ** 17,
                    help="directions / pixels of the kernels' row (real_sh lmax 16, render_practical exact)")
    ap.add_argument("--gpu", action="store_true", help="count GPUs instead of forced host devices")
    ap.add_argument("--json", help="write the measurements here")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--peer", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print(json.dumps(child(args)))
        return
    load0 = os.getloadavg()
    print(f"bench_scale: batch {args.batch} captures, large capture {args.views} views of {args.size} px; "
          f"{os.cpu_count()} cores, load average {load0[0]:.1f}")
    rows = []
    for d in args.devices:
        env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
        if args.gpu:
            env["CUDA_VISIBLE_DEVICES"] = ",".join(map(str, range(d)))
        else:
            env["JAX_PLATFORMS"] = "cpu"
            env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={d}"
        cmd = [sys.executable, os.path.abspath(__file__), "--child", str(d), "--batch", str(args.batch), "--views",
               str(args.views), "--size", str(args.size), "--points", str(args.points)] + (["--peer"] if d == args.devices[0] else [])
        p = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(p.stderr[-3000:])
        rows.append(json.loads(p.stdout.strip().splitlines()[-1]))
    base = rows[0]
    print(f"\n{'devices':>7} | {'batch warm s':>12} {'captures/s':>10} {'eff.':>5} | {'large fit s':>11} {'eff.':>5} | "
          f"{'large IL s':>10} {'eff.':>5} | {'large fact. s':>13} {'eff.':>5} | first calls (compile) s")
    def efficiency(r, k):  # T_1 / (D T_D), D relative to the first row's device count
        return base[k]["warm_s"] / (r["devices"] / base["devices"] * r[k]["warm_s"])

    for r in rows:
        e = lambda k: efficiency(r, k)  # noqa: E731
        print(f"{r['devices']:>7} | {r['batch']['warm_s']:12.2f} {r['batch']['captures_per_s']:10.1f} {e('batch'):5.2f} | "
              f"{r['large_fit_brdf']['warm_s']:11.3f} {e('large_fit_brdf'):5.2f} | "
              f"{r['large_inverse_lighting']['warm_s']:10.4f} {e('large_inverse_lighting'):5.2f} | "
              f"{r['large_factorize']['warm_s']:13.3f} {e('large_factorize'):5.2f} | "
              f"{r['batch']['first_s']:.1f} / {r['large_fit_brdf']['first_s']:.1f} / "
              f"{r['large_inverse_lighting']['first_s']:.1f} / {r['large_factorize']['first_s']:.1f}")
    print(f"\nkernels on sharded arrays, {base['real_sh']['n']} points: real_sh lmax 16 / render_practical exact "
          f"(the lighting of the batch's first capture), warm s, efficiency, output spec")
    for r in rows:
        e = lambda k: efficiency(r, k)  # noqa: E731
        print(f"{r['devices']:>7} | real_sh {r['real_sh']['warm_s']:.3f} {e('real_sh'):5.2f} {r['real_sh']['spec']:<18} | "
              f"render_practical {r['render_practical']['warm_s']:.3f} {e('render_practical'):5.2f} "
              f"{r['render_practical']['spec']}")
    peer = base.get("peer_batch_s")
    if peer is not None:
        print(f"peer: numpy/scipy serial loop of the same {args.batch} fits (1 BLAS thread): {peer:.2f} s "
              f"({args.batch / peer:.1f} captures/s); jaxsh fit_many on 1 device: {base['batch']['warm_s']:.2f} s")
    print(f"large capture: {base['large_fit_brdf']['n_pixels']} pixels (factorize's search on "
          f"{base['large_factorize']['search_pixels']}; its status {[r['large_factorize']['status'] for r in rows]}, "
          f"mu {[round(r['large_factorize']['mu'], 6) for r in rows]}); batch converged: "
          f"{[r['batch']['converged'] for r in rows]} of {args.batch}")
    load1 = os.getloadavg()
    print(f"load average {load0[0]:.1f} at start, {load1[0]:.1f} at end ({os.cpu_count()} cores: forced host devices "
          f"beyond the free cores share them and cannot scale)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "load": [load0, load1], "args": vars(args)}, f, indent=1)


if __name__ == "__main__":
    main()
