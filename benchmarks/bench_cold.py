"""Cold start of the command line: `jaxsh fit` in a fresh process, against the bare import (issue 13).

Run from the repository root with the project's venv::

    python benchmarks/bench_cold.py             # 3 views of 96x96 (the issue's capture), 3 repeats
    python benchmarks/bench_cold.py --size 64 --repeats 1

What is timed (wall clock of a whole child process, median of ``--repeats``):

* ``import``: ``python -c "import jax, jaxsh, solvers"``, the floor every run pays;
* ``fit, known lighting``: ``jaxsh fit`` on a 3-view capture whose lighting (an
  environment map plus a directional source) is given and whose BRDF is not
  (``solvers.fit_brdf``: grid, simplex, Levenberg-Marquardt, re-renders, files);
* ``fit, unknown lighting``: the same capture with lighting and BRDF unknown
  (``solvers.factorize``, l* 12);

each from a fresh install's point of view (``JAXSH_NO_CACHE=1``: no persistent
compilation cache), and again as a second run with the cache the first run of
the same command filled (a fresh ``JAXSH_CACHE_DIR`` per command), and for
another object with that cache: a sphere of radius 0.98 (about 4 % fewer
pixels), whose sample count falls in the same size bucket, so its fit finds
the compiled programs of the first (``jaxsh fit`` pads the samples to the
bucket, ``solvers.pad_observations(..., bucket=True)``). The issue's
goals: a cold known-lighting fit within 3x the bare import, unknown lighting
within 5x. The peer is the bare import itself, measured in the same run; the
numpy/scipy baselines of the same fits are in ``bench_inverse.py``.

The capture (not timed) is rendered by ``jaxsh render`` from a manifest with
the practical model: Torrance-Sparrow kd (0.3, 0.2, 0.1), ks 0.4, mu 1.5,
sigma 0.15, under an lmax-15 probe of two area sources plus a sun.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

PY = sys.executable
HERE = os.path.dirname(os.path.abspath(__file__))

SETUP = r"""
import json, sys
import numpy as np
import jaxsh, jaxsh.io as jio, solvers
from solvers.cli import main
root, size, radius = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
disks, _ = solvers.default_sources()
sh = sum(jaxsh.disk_light_sh(disks[0][k], disks[1][k], disks[2][k], 15) for k in range(2))
jio.write_image(f"{root}/probe.exr", np.maximum(np.asarray(jaxsh.synthesize_latlong(sh, 32, 64)), 0))
eyes = [np.array([0.5, -4.0, 3.0]), np.array([3.0, 1.0, 4.0]), np.array([-2.0, 3.0, 3.5])]
views = []
for eye in eyes:
    cam = np.asarray(jaxsh.look_at(eye, np.zeros(3), np.array([0, 0, 1.0])))
    views.append({"camera": {"model": "orthographic", "scale": 2.4 / size, "width": size, "height": size,
                             "cam_to_world": cam.tolist()}})
m = {"geometry": {"sphere": {"center": [0, 0, 0], "radius": radius}}, "views": views,
     "lighting": {"envmap": "probe.exr", "up": "+z", "layout": "latlong",
                  "directional": [{"direction": [0.3, 0.4, 0.87], "radiance": [2, 2, 2]}]},
     "brdf": {"model": "torrance_sparrow", "kd": [0.3, 0.2, 0.1], "ks": 0.4, "mu": 1.5, "sigma": 0.15},
     "solve": {}}
with open(f"{root}/render.json", "w") as f:
    json.dump(m, f)
assert main(["render", f"{root}/render.json", "--out", f"{root}/renders"]) == 0
for k, v in enumerate(views):
    v["image"] = f"renders/view_{k:03d}.exr"
known = dict(m, brdf=None)
unknown = dict(m, brdf=None, lighting=None, solve={"lighting_lmax": 12})
for name, mm in (("known", known), ("unknown", unknown)):
    with open(f"{root}/{name}.json", "w") as f:
        json.dump(mm, f)
"""


OTHER_RADIUS = 0.98  # another object: about 4 % fewer pixels, in the same size bucket (`solvers.pad_observations`)


def run(cmd, env=None):
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return dt


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=96, help="image side (3 views)")
    ap.add_argument("--repeats", type=int, default=3, help="runs of each command (median)")
    args = ap.parse_args()
    print(f"Python {sys.version.split()[0]}, {os.cpu_count()} CPUs, load average at start {os.getloadavg()}")
    jaxsh_bin = os.path.join(os.path.dirname(PY), "jaxsh")
    cli = [jaxsh_bin] if os.path.exists(jaxsh_bin) else [PY, "-m", "solvers.cli"]
    with tempfile.TemporaryDirectory() as root:
        t0 = time.perf_counter()
        other = os.path.join(root, "other")
        os.makedirs(other)
        run([PY, "-c", SETUP, root, str(args.size), "1.0"], env=dict(os.environ, JAXSH_NO_CACHE="1"))
        run([PY, "-c", SETUP, other, str(args.size), str(OTHER_RADIUS)], env=dict(os.environ, JAXSH_NO_CACHE="1"))
        print(f"captures: 3 views of {args.size}x{args.size}, sphere radius 1 and {OTHER_RADIUS}, rendered in "
              f"{time.perf_counter() - t0:.1f} s (not timed)")
        # no cache setting of the caller's: a JAX_COMPILATION_CACHE_DIR would warm the "cold" runs
        base_env = {k: v for k, v in os.environ.items()
                    if k not in ("JAXSH_CACHE_DIR", "JAXSH_NO_CACHE", "JAX_COMPILATION_CACHE_DIR")}
        t_imp = [run([PY, "-c", "import jax, jaxsh, solvers"], env=base_env) for _ in range(args.repeats)]
        imp = statistics.median(t_imp)
        rows = [("import jax, jaxsh, solvers", imp, None, None, None)]
        results, samples = {}, {}
        for name, goal in (("known", 3.0), ("unknown", 5.0)):
            cold, warm, cross = [], [], []
            for r in range(args.repeats):
                cache = os.path.join(root, f"cache_{name}_{r}")
                out = os.path.join(root, f"out_{name}")
                out_other = os.path.join(root, f"out_other_{name}")
                cold.append(run(cli + ["fit", os.path.join(root, f"{name}.json"), "--out", out],
                                env=dict(base_env, JAXSH_NO_CACHE="1")))
                run(cli + ["fit", os.path.join(root, f"{name}.json"), "--out", out], env=dict(base_env, JAXSH_CACHE_DIR=cache))
                warm.append(run(cli + ["fit", os.path.join(root, f"{name}.json"), "--out", out],
                                env=dict(base_env, JAXSH_CACHE_DIR=cache)))
                # another object (other pixel count, same size bucket), with the cache the first object's runs filled
                cross.append(run(cli + ["fit", os.path.join(other, f"{name}.json"), "--out", out_other],
                                 env=dict(base_env, JAXSH_CACHE_DIR=cache)))
            with open(os.path.join(root, f"out_{name}", "result.json")) as f:
                res = json.load(f)
            with open(os.path.join(root, f"out_other_{name}", "result.json")) as f:
                samples[name] = (res.get("samples"), json.load(f).get("samples"))
            results[name] = res
            rows.append((f"jaxsh fit, {name} lighting", statistics.median(cold), statistics.median(warm), goal,
                         statistics.median(cross)))
    print(f"\nCold start, 3 views of {args.size}x{args.size}, wall clock of the whole process (median of {args.repeats})")
    print(f"{'command':34s} {'no cache':>10s} {'/import':>8s} {'goal':>6s} {'met':>5s} {'2nd run, cache':>15s} {'/import':>8s}"
          f" {'other object, cache':>20s} {'/import':>8s}")
    for label, cold, warm, goal, cross in rows:
        if goal is None:
            print(f"{label:34s} {cold:9.2f}s {1.0:8.2f}")
            continue
        met = "yes" if cold / imp <= goal else "no"
        print(f"{label:34s} {cold:9.2f}s {cold / imp:8.2f} {goal:5.0f}x {met:>5s} {warm:14.2f}s {warm / imp:8.2f}"
              f" {cross:19.2f}s {cross / imp:8.2f}")
    print(f"other object: a sphere of radius {OTHER_RADIUS}, fitted with the cache that the first object's two runs "
          "filled; samples (valid, total, solved) of the first and the other object:")
    for name, (a, b) in samples.items():
        print(f"  {name}: {a} / {b}")
    k, u = results["known"], results["unknown"]
    print(f"\nknown lighting: status {k['status']}, kd {k['brdf']['kd']}, ks {k['brdf']['ks']}, mu {k['brdf']['mu']:.4f}, "
          f"sigma {k['brdf']['sigma']:.4f} (truth kd [0.3, 0.2, 0.1], ks 0.4, mu 1.5, sigma 0.15)")
    print(f"unknown lighting: status {u['status']}, ks/(kd+ks) {u['brdf']['ks']} (truth {[0.4 / 0.7, 0.4 / 0.6, 0.4 / 0.5]}), "
          f"mu {u['brdf']['mu']:.4f}, sigma {u['brdf']['sigma']:.4f}")
    for name, r in results.items():
        t = r.get("timings_s", {})
        print(f"{name}: timings_s " + ", ".join(f"{a} {b:.2f}" for a, b in t.items()))


if __name__ == "__main__":
    main()
