"""Benchmark ``render_practical``'s default (table) path against a NumPy lookup renderer and the exact path.

Run from the repository root with the project's venv::

    python benchmarks/bench_render_table.py            # 512x512 (~1 min on 2 cores, most of it the exact path)
    python benchmarks/bench_render_table.py --quick    # 256x256

The scene of ``bench_render.py``: a 512x512 orthographic sphere (``sphere_gbuffer``), Torrance-Sparrow
kd = (0.45, 0.35, 0.25), ks = 0.3, mu = 1.5, sigma = 0.2, under a procedural HDR sky projected to SH
lmax 40 plus one directional sun (a fast source). The script enables float64 in JAX; the library
itself never does.

Rows (wall-clock on the host CPU; "first" is the first call in this process: trace + compile + run;
"warm" the minimum of repeated calls after it, ``_common.time_jax``; the exact path is timed once warm):

1. ``render_practical`` by default (``method="auto"``, which takes the table here: the filtered sky
   synthesized once on a lat-long grid chosen from lmax and sigma, bicubic lookup at the mirror
   directions; docs/conventions.md, "The slow specular term by table").
2. ``render_practical(method="exact")``: the (lmax+1)^2 harmonics at every pixel.
3. The peer: a plain NumPy renderer of the same image, as measured for issue 13 (docs/performance.md):
   the filtered lighting synthesized once on a 256x512 lat-long grid (``jaxsh.synthesize_latlong``,
   its only JAX call), bilinear lookup at the mirror directions, the 9-term irradiance, the sun's
   diffuse term and lobe (R&H eq. 23), Fresnel -- per call, on the masked pixels only.

Accuracy of each against the exact path: the maximum absolute difference over the image divided by
the image's maximum, and the RMS relative difference over the lit pixels (exact > 1% of its maximum).
The ratios are jaxsh default / NumPy peer (warm, and first call). Other processes on the machine add
noise (the load average is printed): treat differences within ~20% as equal on a quiet machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxsh  # noqa: E402

warnings.filterwarnings("ignore", message=".*64-bit precision.*")

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from _common import (  # noqa: E402
    Table, add_hugepages_option, apply_hugepages, fmt_e, fmt_t, malloc_line, ratio, time_jax, time_np,
)

from solvers.synthetic import procedural_sky  # noqa: E402

KD = np.array([0.45, 0.35, 0.25])
KS = np.array([0.30, 0.30, 0.30])
MU = 1.5
SIGMA = 0.2
LMAX = 40
SUN_DIR = np.array([0.5, 0.4, 0.77]) / np.linalg.norm([0.5, 0.4, 0.77])
SUN_E = np.array([[3.0, 2.8, 2.5]])


def ortho_cam(n, half_extent, eye=(0.0, -5.0, 1.5)):
    c2w = jaxsh.look_at(eye=jnp.asarray(eye), target=jnp.zeros(3), up=jnp.array([0.0, 0.0, 1.0]))
    return jaxsh.OrthographicCamera(scale=2 * half_extent / n, width=n, height=n, cam_to_world=c2w)


def numpy_renderer(normal, view, mask, slow, table_hw=(256, 512)):
    """The NumPy peer: eq. 24 with L_slow(R) from a bilinear lat-long lookup (returns the total image)."""
    nrm, vw, msk, slow = np.asarray(normal), np.asarray(view), np.asarray(mask), np.asarray(slow)
    h, w = table_hw
    deg = np.floor(np.sqrt(np.arange(slow.shape[0]))).astype(int)
    a9 = np.array([np.pi] + [2 * np.pi / 3] * 3 + [np.pi / 4] * 5)
    f0 = ((MU - 1) / (MU + 1)) ** 2

    def render():
        tab = np.asarray(jaxsh.synthesize_latlong(slow * np.exp(-((SIGMA * deg) ** 2))[:, None], h, w))
        n, v = nrm[msk], vw[msk]
        cos_o = np.einsum("ij,ij->i", n, v)
        r = 2 * cos_o[:, None] * n - v
        u = np.arccos(np.clip(r[:, 2], -1, 1)) * (h / np.pi) - 0.5
        q = (np.arctan2(r[:, 1], r[:, 0]) % (2 * np.pi)) * (w / (2 * np.pi)) - 0.5
        i0, j0 = np.floor(u).astype(int), np.floor(q).astype(int)
        tu, tq = (u - i0)[:, None], (q - j0)[:, None]
        i1, i0 = np.clip(i0 + 1, 0, h - 1), np.clip(i0, 0, h - 1)
        j1, j0 = (j0 + 1) % w, j0 % w
        l_slow = (1 - tu) * ((1 - tq) * tab[i0, j0] + tq * tab[i0, j1]) + tu * ((1 - tq) * tab[i1, j0] + tq * tab[i1, j1])
        x, y, z = n[:, 0], n[:, 1], n[:, 2]
        y9 = np.stack([np.full_like(x, 0.282095), 0.488603 * y, 0.488603 * z, 0.488603 * x, 1.092548 * x * y,
                       1.092548 * y * z, 0.315392 * (3 * z * z - 1), 1.092548 * x * z, 0.546274 * (x * x - y * y)], 1)
        e = y9 @ (slow[:9] * a9[:, None])
        cos_i = n @ SUN_DIR
        e += np.maximum(cos_i, 0)[:, None] * SUN_E
        g = np.sqrt(MU * MU - 1 + cos_o * cos_o)
        fres = 0.5 * (g - cos_o) ** 2 / (g + cos_o) ** 2 * (1 + ((cos_o * (g + cos_o) - 1) / (cos_o * (g - cos_o) + 1)) ** 2) / f0
        hv = SUN_DIR[None] + v
        hv /= np.linalg.norm(hv, axis=1, keepdims=True)
        th = np.arccos(np.clip(np.einsum("ij,ij->i", hv, n), -1, 1))
        lobe = np.exp(-((th / SIGMA) ** 2)) / (np.pi * SIGMA**2) * (cos_i > 0)
        spec = fres[:, None] * (l_slow + lobe[:, None] * SUN_E / (4 * cos_o[:, None]))
        out = np.zeros(msk.shape + (3,))
        out[msk] = KD * e + KS * spec
        return out

    return render


def accuracy(b, exact):
    b, exact = np.asarray(b), np.asarray(exact)
    mx = float(np.abs(b - exact).max() / np.abs(exact).max())
    lum = exact.mean(-1)
    lit = lum > 0.01 * lum.max()
    rel = np.abs(b - exact)[lit] / np.maximum(np.abs(exact)[lit], 1e-300)
    return mx, float(np.sqrt(np.mean(rel**2)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="a 256x256 image")
    add_hugepages_option(ap)
    args = ap.parse_args()
    apply_hugepages(args)
    size = 256 if args.quick else 512
    print(f"jaxsh {jaxsh.__version__}, JAX {jax.__version__}, numpy {np.__version__}, Python {platform.python_version()}, "
          f"{os.cpu_count()} CPUs; jaxsh compile options {jaxsh.compile_options()}")
    try:
        print(f"load average at start: {os.getloadavg()}")
    except OSError:
        pass
    print(malloc_line())
    t_all = time.perf_counter()
    sky = procedural_sky(256, 512)
    slow = jaxsh.project_latlong(sky, lmax=LMAX)
    g = jaxsh.sphere_gbuffer(ortho_cam(size, 1.1), jnp.zeros(3), 1.0)
    npx = int(np.asarray(g.mask).sum())
    light = dict(slow_sh=slow, fast_directions=jnp.asarray(SUN_DIR)[None], fast_energy=jnp.asarray(SUN_E))

    def ours(method="auto"):
        return lambda: jaxsh.render_practical(g.normal, g.view, KD, KS, MU, SIGMA, mask=g.mask, method=method, **light).total

    tab = Table(f"render_practical, sphere {size}x{size} ({npx} px), sky SH lmax {LMAX} + sun, sigma {SIGMA} (CPU, float64)",
                ["renderer", "warm", "first", "max|diff|/max vs exact", "RMS rel vs exact", "note"])
    t_first_d, t_warm_d = time_jax(ours(), repeats=5)
    b_default = np.asarray(ours()())
    t0 = time.perf_counter()
    b_exact = np.asarray(jax.block_until_ready(ours("exact")()))
    t_first_e = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(ours("exact")())
    t_warm_e = time.perf_counter() - t0
    peer = numpy_renderer(g.normal, g.view, g.mask, slow)
    t_first_p, t_warm_p = time_np(peer, repeats=5)
    b_peer = peer()
    # both once more, after each other (the minimum of both runs for each: load changes during a run; the peer
    # was timed once while jaxsh took the better of two passes, which favoured jaxsh)
    t_warm_d = min(t_warm_d, time_jax(ours(), repeats=5)[1])
    t_warm_p = min(t_warm_p, time_np(peer, repeats=5)[1])
    acc_d, acc_p = accuracy(b_default, b_exact), accuracy(b_peer, b_exact)
    tab.add("render_practical (default: table)", fmt_t(t_warm_d), fmt_t(t_first_d), fmt_e(acc_d[0]), fmt_e(acc_d[1]),
            "bicubic table (grid from the error bound, docs/performance.md)")
    tab.add("render_practical(method='exact')", fmt_t(t_warm_e), fmt_t(t_first_e), "0", "0",
            f"(lmax+1)^2 = {(LMAX + 1) ** 2} SH per pixel")
    tab.add("NumPy peer (bilinear lookup)", fmt_t(t_warm_p), fmt_t(t_first_p), fmt_e(acc_p[0]), fmt_e(acc_p[1]),
            "256x512 grid; first call compiles synthesize_latlong")
    tab.show()
    print(f"ratios, jaxsh default / NumPy peer: warm {ratio(t_warm_d, t_warm_p)}, first call {ratio(t_first_d, t_first_p)}; "
          f"default / exact: warm {ratio(t_warm_d, t_warm_e)}, first call {ratio(t_first_d, t_first_e)}")
    try:
        print(f"load average at end: {os.getloadavg()}")
    except OSError:
        pass
    print(f"total wall time {time.perf_counter() - t_all:.1f} s")


if __name__ == "__main__":
    main()
