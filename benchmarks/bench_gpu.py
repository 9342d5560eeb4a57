"""jaxsh on a GPU against the same machine's CPU backend, in one process: speed and agreement.

The peer here is jaxsh itself on the host's CPU cores (`jax.devices("cpu")`), in the same process and the
same run: the same programs, placed by committing their inputs to one device or the other. Each row reports
the first call (compilation included) and the best warm call on both, the ratio, and the largest difference
between the two results (relative to the result's largest value; iteration counts apart, which rounding may
shift by a step). On a machine without a GPU the script says so and exits 0 (nothing to compare).

Workloads (float64 unless marked):

- `real_sh` at 10⁶ directions, lmax 16, float64 and float32;
- `project_latlong` of a 1024 × 2048 × 3 map to lmax 32;
- `rotate_sh` of 10⁴ lmax-8 vectors, each by its own rotation;
- `render_practical` of a 512² sphere (lmax-12 sky plus a sun);
- `fit_brdf`, `inverse_lighting` and `factorize` (l* = 12, `bench_inverse.LSTAR`) on `bench_inverse.py`'s
  capture (3 views of `--size`² rendered with the reference renderer, 1 % noise).

    python benchmarks/bench_gpu.py [--size 256] [--json out.json] [--dry-run]

Pair it with `bench_scale.py --gpu` (several GPUs, a batch of captures). Timings on the GPU count the
device's work: every call is waited for with `jax.block_until_ready`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import jax

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="image side of the solvers' capture (3 views)")
    ap.add_argument("--json", help="write the rows here")
    ap.add_argument("--dry-run", action="store_true", help="no GPU needed: CPU against CPU (checks the script)")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)  # a benchmark script configures its own process
    gpus = [d for d in jax.devices() if d.platform == "gpu"] or (jax.devices("cpu") if args.dry_run else [])
    if not gpus:
        print(f"bench_gpu: no GPU (JAX {jax.__version__} sees {jax.devices()}); nothing to compare")
        return
    import jax.numpy as jnp
    import numpy as np

    import jaxsh
    import solvers
    from _common import time_jax
    from bench_inverse import LSTAR, make_capture
    from tests._scale_worker import compare

    gpu, cpu = gpus[0], jax.devices("cpu")[0]
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"bench_gpu: {gpu.device_kind} ({len(gpus)} GPU) against the host CPU backend ({cores} cores); "
          f"JAX {jax.__version__}, Python {platform.python_version()}, load average {os.getloadavg()[0]:.1f}")
    rows = []

    def row(name, fn, args, reps=3):
        """Time `fn(*args)` with the arguments committed to each device; compare the results."""
        out = {"task": name}
        res = {}
        for tag, dev in (("gpu", gpu), ("cpu", cpu)):
            a = jax.device_put(args, dev)
            with jax.default_device(dev):
                first, warm = time_jax(lambda: fn(*a), repeats=reps)
                res[tag] = jax.device_get(fn(*a))
            out[tag] = {"first_s": first, "warm_s": warm}
        c = compare(res["gpu"], res["cpu"])
        out["rel_diff"], out["leaf"], out["steps_differ"] = c["rel"], c["leaf"], bool(c["steps"])
        rows.append(out)
        g, h = out["gpu"], out["cpu"]
        print(f"{name:<44} GPU {g['first_s']:7.2f} s first, {g['warm_s'] * 1e3:9.2f} ms warm | CPU "
              f"{h['first_s']:7.2f} s, {h['warm_s'] * 1e3:9.2f} ms | CPU/GPU warm {h['warm_s'] / g['warm_s']:7.1f}x"
              f" | max rel diff {c['rel']:.1e}{' (steps differ)' if c['steps'] else ''}", flush=True)
        return res["gpu"]

    rng = np.random.default_rng(0)
    d = rng.standard_normal((10**6, 3))
    row("real_sh 1e6 dirs, lmax 16, float64", lambda x: jaxsh.real_sh(x, 16), (d,))
    row("real_sh 1e6 dirs, lmax 16, float32", lambda x: jaxsh.real_sh(x, 16), (d.astype(np.float32),))
    img = rng.random((1024, 2048, 3))
    row("project_latlong 1024x2048x3, lmax 32", lambda x: jaxsh.project_latlong(x, 32), (img,))
    q = rng.standard_normal((10**4, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    rot = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                    np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                    np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)
    row("rotate_sh 1e4 rotations, lmax 8", lambda c, r: jaxsh.rotate_sh(c, r, channels=False),
        (rng.standard_normal((10**4, 81)), rot))

    c2w = jaxsh.look_at(eye=jnp.array([0.0, -5.0, 1.5]), target=jnp.zeros(3), up=jnp.array([0.0, 0.0, 1.0]))
    cam = jaxsh.OrthographicCamera(scale=2.2 / 512, width=512, height=512, cam_to_world=c2w)
    gb = jaxsh.sphere_gbuffer(cam, jnp.zeros(3), jnp.asarray(1.0))
    sky = rng.standard_normal((169, 3)) * np.exp(-0.1 * jaxsh.sh_degrees(12))[:, None]
    sky[0] += 3.0
    sun_d, sun_e = np.array([[0.3, -0.4, 0.866]]), np.array([[4.0, 3.8, 3.5]])
    row("render_practical 512^2, lmax-12 sky + sun",
        lambda n, v, m, s, fd, fe: jaxsh.render_practical(n, v, [0.5, 0.4, 0.3], [0.2, 0.2, 0.2], 1.6, 0.15,
                                                          slow_sh=s, mask=m, fast_directions=fd,
                                                          fast_energy=fe).total,
        (gb.normal, gb.view, gb.mask, sky, sun_d, sun_e))

    _, gbs, images, lighting = make_capture(args.size, None)
    obs = solvers.observations(gbs, images)
    print(f"capture: 3 views of {args.size}^2, {obs.n_samples} samples")
    fb = row(f"fit_brdf ({obs.n_samples} samples)", solvers.fit_brdf, (obs, lighting), reps=2)
    row(f"inverse_lighting l*={LSTAR}", lambda o, b: solvers.inverse_lighting(o, b, LSTAR), (obs, fb.brdf))
    key = jax.random.PRNGKey(0)
    row(f"factorize l*={LSTAR}", lambda o: solvers.factorize(o, LSTAR, key=key), (obs,), reps=2)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "gpu": gpu.device_kind, "jax": jax.__version__, "size": args.size}, f, indent=1)


if __name__ == "__main__":
    main()
