"""Benchmark jaxsh's forward rendering (practical model, G-buffers, visibility, reference).

Run from the repository root with the project's venv::

    python benchmarks/bench_render.py            # full run (~1-2 min on 2 cores)
    python benchmarks/bench_render.py --quick    # reduced sizes (~30-60 s)

Options: ``--quick`` (smaller images / maps; most of what remains is compile
time), ``--seed N`` (unused by the scenes, kept for symmetry). The script enables float64 in
JAX (``jax_enable_x64``); the library itself never does.

What is measured (wall-clock on the host CPU; "first" is the first call,
i.e. trace + compile + run, "warm" the minimum of >= 3 runs after a warm-up
call, see ``_common.time_jax``; the multi-second 512x512 practical render is
timed once warm, after its first call):

1. Sphere, 512x512 (256x256 with --quick), orthographic camera: the analytic
   G-buffer (``sphere_gbuffer``) and the practical model of R&H 2001 eq. 24
   (``render_practical``) under a procedural HDR sky (``procedural_sky``,
   projected to SH lmax 40) plus one directional sun (a "fast" source).
   The SH projection of the sky is timed as well (once per lighting).
2. Mesh, 256x256 (128x128 with --quick): a torus (``trimesh.creation.torus``;
   an icosphere + box union if that is unavailable). ``mesh_gbuffer`` (ray
   casting, Embree if importable), the per-capture visibility precomputation
   -- ``directional_visibility`` for the sun, ``reflected_visibility``, and
   ``visibility_sh`` with lmax 2 and ~256 hemisphere rays per pixel -- and
   then ``render_practical`` with those shadows (warm / first).
3. Reference: ``render_reference`` (full Torrance-Sparrow reflection
   equation, quadrature over a disk source, exact for the sun) on a 96x96
   sphere (48x48 with --quick) lit by a disk area source + sun, and the
   practical model under the same lighting (the disk as
   ``disk_light_sh``, lmax 40). The RMS relative error of practical vs
   reference over the lit pixels (reference > 1% of its maximum) is printed.
   Peer of the reference: the same sum in NumPy (``numpy_reference``: the
   BRDF written out, pixels in chunks of 64), with the disk's quadrature
   nodes given to both as directional sources; the ratio and the largest
   difference relative to the image's maximum are printed.

Peer: Mitsuba 3, in a subprocess (``_mitsuba_peer.py``: Mitsuba's LLVM cannot
share a process with XLA's); if ``import mitsuba`` fails there, a line says why
it was not measured (the script never installs it). It renders the same 512x512
sphere under the same sky (envmap emitter) and sun with the ``direct``
integrator, 16 spp, ``roughplastic`` Beckmann alpha = sigma (llvm_ad_rgb
variant if available). This is a timing peer, not a pixel comparison: the
BRDFs differ, the result is Monte Carlo, and the envmap is not re-oriented.
The ratio is jaxsh (G-buffer + practical model, warm) / Mitsuba (warm).

Other processes on the machine add noise (the load average at start is
printed): on a quiet machine treat differences within ~20% as equal.
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
import trimesh  # noqa: E402

import jaxsh  # noqa: E402

warnings.filterwarnings("ignore", message=".*64-bit precision.*")
warnings.filterwarnings("ignore", category=FutureWarning)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from _common import (  # noqa: E402
    Table, add_hugepages_option, apply_hugepages, fmt_e, fmt_t, malloc_line, ratio, time_jax, time_np,
)

from solvers.synthetic import procedural_sky  # noqa: E402

from _common import PeerError, run_peer  # noqa: E402

# Mitsuba is never imported here: loading Dr.Jit's LLVM into a process that has loaded XLA crashes LLVM
# ("Cannot select: fminimum"). It runs in a subprocess (benchmarks/_mitsuba_peer.py via _common.run_peer).

# Material and lighting shared by all scenes.
KD = jnp.array([0.45, 0.35, 0.25])
KS = jnp.array([0.30, 0.30, 0.30])
MU = 1.5
SIGMA = 0.2
LMAX = 40
SUN_DIR = np.array([0.5, 0.4, 0.77])
SUN_DIR = SUN_DIR / np.linalg.norm(SUN_DIR)
SUN_E = jnp.array([[3.0, 2.8, 2.5]])
DISK_DIR = np.array([-0.4, 0.2, 0.9])
DISK_DIR = DISK_DIR / np.linalg.norm(DISK_DIR)
DISK_R = 0.3
DISK_L = jnp.array([2.0, 2.2, 2.5])


def ortho_cam(n, half_extent, eye=(0.0, -5.0, 1.5)):
    c2w = jaxsh.look_at(eye=jnp.asarray(eye), target=jnp.zeros(3), up=jnp.array([0.0, 0.0, 1.0]))
    return jaxsh.OrthographicCamera(scale=2 * half_extent / n, width=n, height=n, cam_to_world=c2w)


def make_mesh():
    if hasattr(trimesh.creation, "torus"):
        return trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=96, minor_sections=48), "torus"
    a = trimesh.creation.icosphere(subdivisions=4, radius=0.8)
    b = trimesh.creation.box(extents=(1.8, 0.5, 0.5))
    return trimesh.util.concatenate([a, b]), "icosphere+box"


def time_once(fn):
    """(first call incl. compile, one warm call) in seconds, for calls of several seconds."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return first, time.perf_counter() - t0


def bench_sphere(tab, n, sky_hw):
    h, w = sky_hw
    sky = procedural_sky(h, w)
    t_first, t_warm = time_jax(lambda: jaxsh.project_latlong(sky, lmax=LMAX))
    tab.add(f"sky {h}x{w} -> SH lmax {LMAX}", "project_latlong", fmt_t(t_warm), fmt_t(t_first), "")
    slow = jaxsh.project_latlong(sky, lmax=LMAX)
    cam = ortho_cam(n, 1.1)
    center = jnp.zeros(3)
    t_first, t_gb = time_jax(lambda: jaxsh.sphere_gbuffer(cam, center, 1.0))
    tab.add(f"sphere {n}x{n}", "sphere_gbuffer", fmt_t(t_gb), fmt_t(t_first), "")
    g = jaxsh.sphere_gbuffer(cam, center, 1.0)
    npx = int(g.mask.sum())

    def render():
        return jaxsh.render_practical(g.normal, g.view, KD, KS, MU, SIGMA, slow_sh=slow, mask=g.mask,
                                      fast_directions=jnp.asarray(SUN_DIR)[None], fast_energy=SUN_E).total

    t_first, t_warm = time_once(render)
    tab.add(f"sphere {n}x{n}", "render_practical (sky lmax 40 + sun)", fmt_t(t_warm), fmt_t(t_first),
            f"{npx / t_warm / 1e6:.2f} Mpx/s")
    t_warm = t_warm + t_gb
    tab.add(f"sphere {n}x{n}", "G-buffer + render_practical", fmt_t(t_warm), "", "sum of the warm rows")
    bench_mitsuba(tab, n, sky, t_warm)
    return slow


def bench_mitsuba(tab, n, sky, t_ours, spp=16):
    """Mitsuba 3 peer, in a subprocess: the same sphere, sky (envmap emitter) and sun, direct illumination only.

    Not a pixel comparison: Mitsuba's ``roughplastic`` (Beckmann, alpha = sigma,
    ior 1.5) is close to but not the same BRDF, its envmap is +y up (the sky is
    not re-oriented), and the image is Monte Carlo (``spp`` samples per pixel,
    ``direct`` integrator, i.e. one bounce, no inter-reflection as in jaxsh).
    Timing as ``_common.time_np``: the first render (incl. the llvm kernel
    compile), then the minimum of 3 renders after a warm-up one, all inside
    the peer process (the subprocess start and scene load are not counted).
    """
    spec = {"variant": "auto", "jobs": [{
        "name": "sphere", "scene": "sky_sun_sphere",
        "params": {"n": n, "spp": spp, "alpha": SIGMA, "ior": MU, "sun_to": (-SUN_DIR).tolist(),
                   "sun_irradiance": np.asarray(SUN_E)[0].tolist(), "sky": "sky"},
        "renders": [{"spp": spp, "seeds": [0]}, {"spp": spp, "seeds": [0, 0, 0, 0]}]}]}
    try:
        meta, _ = run_peer("_mitsuba_peer.py", spec, {"sky": np.asarray(sky, np.float32)})
    except PeerError as e:
        print(f"Mitsuba peer failed: {e}")
        return None
    if not meta["ok"]:
        print(f"Mitsuba 3 was NOT measured: {meta['error']}; this script does not install it, "
              "so there is no peer renderer in this run.")
        return None
    if meta.get("variants_rejected"):
        print(f"Mitsuba variants rejected by a probe in a child process: {meta['variants_rejected']}")
    r = meta["jobs"]["sphere"]["renders"]
    t_first, t_warm = r[0]["times"][0], min(r[1]["times"][1:])
    tab.add(f"sphere {n}x{n}", f"Mitsuba {meta['version']} [{meta['variant']}] direct, {spp} spp (subprocess)",
            fmt_t(t_warm), fmt_t(t_first), f"jaxsh/Mitsuba (warm) = {ratio(t_ours, t_warm)}")
    return t_warm


def bench_mesh(tab, n, slow, n_rays):
    mesh, name = make_mesh()
    cam = ortho_cam(n, 1.6, eye=(0.0, -4.0, 3.0))
    engine = "embree" if jaxsh.embree_available() else "auto"
    t_first, t_warm = time_np(lambda: jaxsh.mesh_gbuffer(cam, mesh), repeats=3)
    g = jaxsh.mesh_gbuffer(cam, mesh)
    m = np.asarray(g.mask)
    npx = int(m.sum())
    label = f"{name} ({len(mesh.faces)} tris) {n}x{n}"
    tab.add(label, f"mesh_gbuffer [{engine}]", fmt_t(t_warm), fmt_t(t_first), f"{npx} px hit")
    p = np.asarray(g.position)[m]
    nn = np.asarray(g.normal)[m]
    v = np.asarray(g.view)[m]
    sun = SUN_DIR[None]

    t0 = time.perf_counter()
    fvis = jaxsh.directional_visibility(mesh, p, nn, sun)
    t_dv = time.perf_counter() - t0
    tab.add(label, "directional_visibility (1 sun)", fmt_t(t_dv), "", f"{float(fvis.mean()):.2f} lit")
    t0 = time.perf_counter()
    rvis = jaxsh.reflected_visibility(mesh, p, nn, v)
    t_rv = time.perf_counter() - t0
    tab.add(label, "reflected_visibility", fmt_t(t_rv), "", f"{float(rvis.mean()):.2f} visible")
    t0 = time.perf_counter()
    tr = jaxsh.visibility_sh(mesh, p, nn, lmax=2, n_dirs=n_rays)
    t_vs = time.perf_counter() - t0
    k = len(jaxsh.hemisphere_quadrature(n_rays, 2)[0])
    tab.add(label, f"visibility_sh lmax 2 ({k} rays/px)", fmt_t(t_vs), "", f"{npx * k / t_vs / 1e6:.2f} Mrays/s")
    tab.add(label, "visibility precompute total", fmt_t(t_dv + t_rv + t_vs), "", "per capture")

    # scatter the per-pixel data back into images
    def img(x, shape):
        out = np.zeros((n * n,) + shape)
        out[m.reshape(-1)] = np.asarray(x).reshape((-1,) + shape)
        return jnp.asarray(out.reshape((n, n) + shape))

    fvis_i, rvis_i, tr_i = img(fvis, (1,)), img(rvis, ()), img(tr, (9,))

    def render():
        return jaxsh.render_practical(g.normal, g.view, KD, KS, MU, SIGMA, slow_sh=slow, mask=g.mask,
                                      fast_directions=jnp.asarray(sun), fast_energy=SUN_E, transfer=tr_i,
                                      fast_visibility=fvis_i, reflected_visibility=rvis_i).total

    t_first, t_warm = time_jax(render)
    tab.add(label, "render_practical (shadowed)", fmt_t(t_warm), fmt_t(t_first), f"{npx / t_warm / 1e6:.2f} Mpx/s")


def numpy_disk_nodes(direction, radius, n_theta, n_phi):
    """Gauss-Legendre (in cos) x uniform-azimuth nodes on a spherical cap and their solid-angle weights (NumPy)."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    umin = np.cos(radius)
    u = 0.5 * (1 - umin) * x + 0.5 * (1 + umin)
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    t = np.cross(direction, [1.0, 0.0, 0.0] if abs(direction[0]) < 0.9 else [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    b = np.cross(direction, t)
    s = np.sqrt(1 - u * u)
    d = (u[:, None, None] * direction + (s[:, None] * np.cos(phi))[..., None] * t
         + (s[:, None] * np.sin(phi))[..., None] * b)
    return d.reshape(-1, 3), (0.5 * (1 - umin) * w[:, None] * np.full(n_phi, 2 * np.pi / n_phi)).reshape(-1)


def numpy_reference(n, v, dirs, energy, chunk=64):
    """The peer of `render_reference` under directional sources: sum_j E_j rho_TS(w_j, v, n) max(n.w_j, 0), the
    simplified Torrance-Sparrow BRDF written out in NumPy (theta_h by arctan2 of |h x n| and h.n; the exact
    dielectric Fresnel at theta_o over its value at normal incidence), pixels in chunks."""
    kd, ks = np.asarray(KD), np.asarray(KS)
    out = np.empty((n.shape[0], energy.shape[1]))
    f0 = ((MU - 1) / (MU + 1)) ** 2
    for i in range(0, n.shape[0], chunk):
        nn, vv = n[i : i + chunk], v[i : i + chunk]
        ci = nn @ dirs.T
        co = np.sum(nn * vv, -1)[:, None]
        h = dirs[None] + vv[:, None]
        x = np.cross(h, nn[:, None])
        th = np.arctan2(np.sqrt(np.sum(x * x, -1)), np.sum(h * nn[:, None], -1))
        cos_t = np.sqrt(np.maximum(1 - (1 - co**2) / MU**2, 0.0))
        rs = (co - MU * cos_t) / (co + MU * cos_t)
        rp = (MU * co - cos_t) / (MU * co + cos_t)
        f = 0.5 * (rs**2 + rp**2) / f0
        spec = f * np.exp(-((th / SIGMA) ** 2)) / (np.pi * SIGMA**2) / (4 * np.where(co > 0, co, 1.0))
        lit = (ci > 0) & (co > 0)
        out[i : i + chunk] = kd * (np.where(lit, ci, 0.0) @ energy) + ks * (np.where(lit, spec, 0.0) @ energy)
    return out


def bench_reference(tab, n, disk_nodes):
    cam = ortho_cam(n, 1.1)
    g = jaxsh.sphere_gbuffer(cam, jnp.zeros(3), 1.0)
    m = np.asarray(g.mask)
    nn, v = g.normal[m], g.view[m]
    ddir = jnp.asarray(DISK_DIR)
    sun = jnp.asarray(SUN_DIR)[None]

    def ref():
        return jaxsh.render_reference(nn, v, KD, KS, MU, SIGMA, directional=(sun, SUN_E),
                                      disks=(ddir[None], jnp.array([DISK_R]), DISK_L[None]), disk_nodes=disk_nodes)

    t_first, t_warm = time_jax(ref, repeats=1)
    tab.add(f"sphere {n}x{n} ({m.sum()} px)", f"render_reference (disk {disk_nodes[0]}x{disk_nodes[1]} + sun)",
            fmt_t(t_warm), fmt_t(t_first), "")
    # The same quadrature sum against a NumPy peer: the disk's nodes given to both as directional sources
    dirs, wts = numpy_disk_nodes(DISK_DIR, DISK_R, *disk_nodes)
    energy = np.concatenate([wts[:, None] * np.asarray(DISK_L)[None], np.asarray(SUN_E)])
    dirs = np.concatenate([dirs, SUN_DIR[None]])
    nn_np, v_np = np.asarray(nn), np.asarray(v)

    def ref_nodes():
        return jaxsh.render_reference(nn, v, KD, KS, MU, SIGMA, directional=(jnp.asarray(dirs), jnp.asarray(energy)))

    t_first, t_warm = time_jax(ref_nodes, repeats=1)
    t_np_first, t_np = time_np(lambda: numpy_reference(nn_np, v_np, dirs, energy), repeats=1)
    got, want = np.asarray(ref_nodes()), numpy_reference(nn_np, v_np, dirs, energy)
    err = float(np.max(np.abs(got - want)) / np.max(np.abs(want)))
    tab.add(f"sphere {n}x{n} ({m.sum()} px)", f"render_reference ({dirs.shape[0]} directional sources)", fmt_t(t_warm),
            fmt_t(t_first), f"NumPy peer {fmt_t(t_np)}: ratio {ratio(t_warm, t_np)}; max rel diff {fmt_e(err)}")
    slow = jaxsh.disk_light_sh(ddir, DISK_R, DISK_L, lmax=LMAX)

    def prac():
        return jaxsh.render_practical(nn, v, KD, KS, MU, SIGMA, slow_sh=slow, fast_directions=sun,
                                      fast_energy=SUN_E).total

    t_first, t_warm = time_jax(prac)
    b_ref = np.asarray(ref())
    b_pr = np.asarray(prac())
    lum_ref = b_ref.mean(-1)
    lit = lum_ref > 0.01 * lum_ref.max()
    rel = np.abs(b_pr - b_ref)[lit] / np.maximum(b_ref[lit], 1e-12)
    rms = float(np.sqrt(np.mean(rel**2)))
    tab.add(f"sphere {n}x{n} ({m.sum()} px)", "render_practical (disk lmax 40 + sun)", fmt_t(t_warm), fmt_t(t_first),
            f"RMS rel err {fmt_e(rms)} ({rms:.1%}; median {np.median(rel):.1%})")
    return rms


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller images and maps")
    ap.add_argument("--seed", type=int, default=0)
    add_hugepages_option(ap)
    args = ap.parse_args()
    apply_hugepages(args)
    q = args.quick
    print(f"jaxsh {jaxsh.__version__}, JAX {jax.__version__}, numpy {np.__version__}, trimesh {trimesh.__version__}, "
          f"Python {platform.python_version()}, {os.cpu_count()} CPUs, embree = {jaxsh.embree_available()}; "
          f"jaxsh compile options {jaxsh.compile_options()}")
    try:
        print(f"load average at start: {os.getloadavg()}")
    except OSError:
        pass
    print(malloc_line())
    print(f"float64 (jax_enable_x64 = {jax.config.jax_enable_x64}); material kd={np.asarray(KD).tolist()}, "
          f"ks={np.asarray(KS).tolist()}, mu={MU}, sigma={SIGMA}")
    t_all = time.perf_counter()
    tab = Table("Forward rendering (jaxsh, CPU, float64)", ["scene", "step", "warm", "first", "note"])
    slow = bench_sphere(tab, 256 if q else 512, (128, 256) if q else (256, 512))
    tab.sep()
    bench_mesh(tab, 128 if q else 256, slow, 256)
    tab.sep()
    bench_reference(tab, 48 if q else 96, (24, 48) if q else (48, 96))
    tab.show()
    if any("Mitsuba" in (r[1] if r else "") for r in tab.rows):
        print("Mitsuba row: timing peer only (Monte Carlo, roughplastic BRDF, envmap not re-oriented); "
              "the ratio compares jaxsh's G-buffer + practical model with Mitsuba's render of the same sphere.")
    print(f"total wall time {time.perf_counter() - t_all:.1f} s")


if __name__ == "__main__":
    main()
