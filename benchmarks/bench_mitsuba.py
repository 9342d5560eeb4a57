"""Benchmark jaxsh's practical model against Mitsuba 3 path tracing on the same scene (CPU).

Run from the repository root with the project's venv::

    python benchmarks/bench_mitsuba.py            # default run (~1 min on 2 cores)
    python benchmarks/bench_mitsuba.py --quick    # fewer spp levels

Mitsuba runs in a subprocess (``_mitsuba_peer.py`` via ``_common.run_peer``;
inputs and images pass through a temporary .npz): importing Mitsuba into a
process that has loaded XLA crashes LLVM ("Cannot select: fminimum"). All of
Mitsuba's renders are made by that one subprocess before jaxsh's side runs.

Options: ``--variant {auto,llvm_ad_rgb,scalar_rgb}`` (auto: llvm_ad_rgb if it
loads, else scalar_rgb; llvm needs libLLVM, e.g. Debian ``libllvm19`` --
``DRJIT_LIBLLVM_PATH`` is set to /usr/lib/x86_64-linux-gnu/libLLVM.so.19.1
when that file exists and the variable is unset), ``--max-spp N``,
``--seed N``. If Mitsuba cannot be imported the script prints
"Mitsuba not available: <reason>" and exits 0.

Scene (identical in both renderers): unit sphere at the origin, orthographic
camera at +z looking at the origin with +y up (``jaxsh.look_at``), 96x96
pixels covering [-1.2, 1.2]^2; a purely diffuse material, R&H Kd =
(0.7, 0.6, 0.5)/pi (R&H: BRDF = Kd, so Mitsuba's ``diffuse`` reflectance =
pi*Kd); lighting = the procedural HDR sky of ``solvers.synthetic``
(``procedural_sky(64, 128)``: blue gradient, dim ground, bright exponential
sun lobe of ~0.08 rad).

* Ground truth: ``jaxsh.render_reference(..., ks=0, envmap=procedural_sky(64,
  128))`` (float64; exact texel quadrature of the map). Its own discretization
  error is printed: the same reference with a 256x512 sampling of the sky.
* jaxsh: ``jaxsh.render_practical(..., slow_sh=jaxsh.project_latlong(env,
  lmax))`` for lmax in {2, 8}, float32, jit-compiled as one function
  "project the 64x128 map + shade the 96x96 G-buffer" (G-buffer precomputed:
  Mitsuba's primary rays correspond to ``jaxsh.sphere_gbuffer``). Warm time =
  min of repeated runs (``_common.time_jax``).
* Mitsuba 3 (``path`` integrator, max_depth=2 = direct lighting only, which is
  exact for a convex sphere; envmap importance sampling + BSDF sampling with
  MIS; ``independent`` sampler; ``hdrfilm`` with the ``box`` filter, i.e.
  pixel-area averages), at increasing spp. Time = ``mi.render`` wall clock
  (warm: the scene is loaded once and, for the llvm variant, the kernel is
  compiled by a first render that is not counted; min of a few runs for the
  fast levels), measured inside the peer process.

Error metric: RMS over pixels and channels of (x - ref)/ref over the sphere
pixels whose 3x3 neighbourhood is inside the sphere (a 1-pixel band at the
silhouette is excluded: Mitsuba averages each pixel's area, jaxsh shades its
centre).

Envmap conventions (checked at start-up): jaxsh's lat-long has +z up, row i at
theta = pi(i+1/2)/H, column j at phi = 2pi(j+1/2)/W from +x towards +y, and its
texels are quadrature nodes. Mitsuba's ``envmap`` looks a world direction d up
as v = to_world^-1 d, theta = acos(v.y) (+y up), phi = atan2(v.x, -v.z),
u = phi/2pi, with pixel-corner nodes: row y at theta = pi*y/(H-1) (rows 0 and
H-1 are the poles), column x at phi = 2pi*x/W (a wrap column is appended),
bilinear in between. Resampling a 64x128 texel-centre map onto those nodes
would add interpolation error, so Mitsuba is given the same analytic sky
evaluated directly at its own nodes (513x1024, identity ``to_world``): node
(y, x) holds sky(d) with d = (sin t sin p, cos t, -sin t cos p), t = pi*y/(H-1),
p = 2pi*x/W. The sky function is a copy of ``procedural_sky``'s formula and is
asserted equal to it on jaxsh's grid. The start-up check renders a diffuse
sphere under a sun lobe only, in both renderers, and compares the brightest
pixel (and the one a naive hand-over -- jaxsh's image given to Mitsuba as is
-- would produce).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

import jaxsh  # noqa: E402
from _common import PeerError, fmt_e, fmt_t, run_peer, time_jax  # noqa: E402
from solvers.synthetic import procedural_sky  # noqa: E402

RES = 96
HALF = 1.2
KD = np.array([0.7, 0.6, 0.5]) / np.pi
SIGMA = 0.1
SUN_DIR = (0.5, 0.3, 0.81)
SUN_SIZE = 0.08
MI_ENV = (513, 1024)  # Mitsuba's node grid for the analytic sky


# ---------------------------------------------------------------- lighting

def sky_radiance(d, sun_dir=SUN_DIR, sun_size=SUN_SIZE, sky=True):
    """procedural_sky's formula at arbitrary unit directions d (..., 3), jaxsh frame."""
    d = np.asarray(d, np.float64)
    z = d[..., 2:3]
    if sky:
        base = np.where(z > 0, np.array([0.35, 0.55, 1.0]) * (0.4 + 0.6 * z), np.array([0.25, 0.2, 0.15]) * (1 + z))
    else:
        base = np.zeros(d.shape[:-1] + (3,))
    s = np.asarray(sun_dir, np.float64)
    s = s / np.linalg.norm(s)
    cosang = np.clip(d @ s, -1, 1)[..., None]
    return base + np.array([60.0, 55.0, 45.0]) * np.exp((cosang - 1.0) / sun_size**2)


def jaxsh_map(h, w, **kw):
    return sky_radiance(np.asarray(jaxsh.latlong_directions(h, w, dtype=np.float64)), **kw)


def mitsuba_node_map(h, w, **kw):
    """Radiance on Mitsuba's envmap nodes (identity to_world): row y, column x."""
    t = np.pi * np.arange(h) / (h - 1)
    p = 2 * np.pi * np.arange(w) / w
    t, p = np.meshgrid(t, p, indexing="ij")
    d = np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], axis=-1)
    return sky_radiance(d, **kw).astype(np.float32)


# ---------------------------------------------------------------- jaxsh side

def gbuffer(dtype):
    cam = jaxsh.OrthographicCamera(
        jnp.asarray(2 * HALF / RES, dtype), RES, RES,
        jaxsh.look_at(eye=jnp.asarray([0.0, 0.0, 5.0], dtype), target=jnp.zeros(3, dtype), up=jnp.asarray([0.0, 1.0, 0.0], dtype)),
    )
    return jaxsh.sphere_gbuffer(cam, jnp.zeros(3, dtype), jnp.asarray(1.0, dtype))


def reference(gb, env):
    n = gb.normal[gb.mask]
    v = gb.view[gb.mask]
    out = jaxsh.render_reference(n, v, jnp.asarray(KD), jnp.zeros(3), None, SIGMA, envmap=jnp.asarray(env), chunk=512)
    img = np.zeros((RES, RES, 3))
    img[np.asarray(gb.mask)] = np.asarray(out)
    return img


def diffuse_numpy(gb, h, w):
    """Independent diffuse truth: Kd * sum over a (h, w) sampling of the sky of L w max(n.omega, 0)."""
    d = np.asarray(jaxsh.latlong_directions(h, w, dtype=np.float64)).reshape(-1, 3)
    lw = jaxsh_map(h, w).reshape(-1, 3) * np.asarray(jaxsh.latlong_weights(h, w, dtype=np.float64)).reshape(-1, 1)
    m = np.asarray(gb.mask)
    n = np.asarray(gb.normal)[m]
    out = np.concatenate([np.maximum(n[k:k + 512] @ d.T, 0.0) @ lw for k in range(0, len(n), 512)])
    img = np.zeros((RES, RES, 3))
    img[m] = out * KD
    return img


def interior_mask(mask):
    m = np.asarray(mask)
    p = np.pad(m, 1)
    inner = np.ones_like(m)
    for di in range(3):
        for dj in range(3):
            inner &= p[di:di + RES, dj:dj + RES]
    return inner


def rms_rel(x, ref, sel):
    r = (x[sel] - ref[sel]) / ref[sel]
    return float(np.sqrt(np.mean(r**2)))


# ---------------------------------------------------------------- Mitsuba side (a subprocess)

def mitsuba_peer(args, env_sun_nodes, env_naive, env_nodes, spps):
    """Every Mitsuba render of this benchmark, in one subprocess (``_mitsuba_peer.py``; see the module docstring).

    Returns ``(meta, images)`` from ``_common.run_peer``.
    """
    params = {"half": HALF, "res": RES, "reflectance": (np.pi * KD).tolist()}
    jobs = [
        {"name": "sun", "scene": "env_sphere", "params": dict(params, env="env_sun"),
         "renders": [{"spp": 256, "seeds": [args.seed], "keep": True}]},
        {"name": "naive", "scene": "env_sphere", "params": dict(params, env="env_naive"),
         "renders": [{"spp": 256, "seeds": [args.seed], "keep": True}]},
        {"name": "main", "scene": "env_sphere", "params": dict(params, env="env"), "warmup_spp": 1,
         "renders": [{"spp": spp, "seeds": [args.seed + 1000 * k + r for r in range(3 if spp <= 64 else 1)], "keep": True}
                     for k, spp in enumerate(spps)]},
    ]
    return run_peer("_mitsuba_peer.py", {"variant": args.variant, "jobs": jobs},
                    {"env_sun": env_sun_nodes, "env_naive": env_naive, "env": env_nodes})


def brightest(img, sel):
    """Centroid (row, col) of luminance^8 over the sphere: the bright spot, robust to MC noise."""
    w = (np.clip(img.sum(-1), 0, None) * sel) ** 8
    i, j = np.indices(w.shape)
    return (round(float((w * i).sum() / w.sum()), 1), round(float((w * j).sum() / w.sum()), 1))


def expected_pixel(s):
    s = np.asarray(s) / np.linalg.norm(s)
    return (RES / 2 * (1 - s[1] / HALF), RES / 2 * (1 + s[0] / HALF))


# ---------------------------------------------------------------- main

def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--variant", default="auto", choices=["auto", "llvm_ad_rgb", "scalar_rgb"])
    ap.add_argument("--max-spp", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    max_spp = args.max_spp or (256 if args.quick else 4096)
    spps = [s for s in (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192) if s <= max_spp]
    s_test = (0.55, -0.45, 0.70)
    env_sun = jaxsh_map(64, 128, sun_dir=s_test, sun_size=0.1, sky=False)
    t0 = time.perf_counter()
    try:
        meta, mimg = mitsuba_peer(args, mitsuba_node_map(*MI_ENV, sun_dir=s_test, sun_size=0.1, sky=False),
                                  env_sun.astype(np.float32), mitsuba_node_map(*MI_ENV), spps)
    except PeerError as e:
        print(f"Mitsuba peer failed: {e}")
        return 1
    t_peer = time.perf_counter() - t0
    if not meta["ok"]:
        print(f"Mitsuba not available: {meta['error']}")
        return 0
    variant = meta["variant"]
    if meta.get("variants_rejected"):
        print(f"Mitsuba variants rejected by a probe in a child process: {meta['variants_rejected']}")
    print(f"mitsuba {meta['version']} variant {variant} (in a subprocess: {fmt_t(t_peer)} for all its renders); "
          f"jax {jax.__version__} on {jax.devices()[0].platform}; {os.cpu_count()} CPUs; load average {os.getloadavg()}")

    # ---- scene, jaxsh side
    gb64 = gbuffer(jnp.float64)
    sel = interior_mask(gb64.mask)
    print(f"{RES}x{RES} px, sphere {int(np.asarray(gb64.mask).sum())} px, {int(sel.sum())} in the error mask "
          f"(1-px silhouette band excluded)")
    env = jaxsh_map(64, 128)
    assert np.allclose(env, np.asarray(procedural_sky(64, 128)), rtol=1e-12, atol=1e-12), \
        "sky_radiance() no longer matches solvers.synthetic.procedural_sky"

    # ---- convention check: sun lobe only, off-axis (Mitsuba's renders came from the peer)
    t0 = time.perf_counter()
    ref_sun = reference(gb64, env_sun)
    img_sun = mimg["sun/0"]
    img_naive = mimg["naive/0"]  # jaxsh's image handed over as is
    ex = expected_pixel(s_test)
    print(f"\nConvention check (diffuse sphere, sun lobe only at {s_test}; "
          f"centroid of the bright spot (row, col), sun-facing pixel ~({ex[0]:.1f}, {ex[1]:.1f})):")
    print(f"  jaxsh reference            {brightest(ref_sun, sel)}")
    print(f"  Mitsuba, converted envmap  {brightest(img_sun, sel)}   RMS rel err vs jaxsh ref (256 spp) "
          f"{rms_rel(img_sun, ref_sun, sel & (ref_sun.sum(-1) > 0.05 * ref_sun.sum(-1).max())):.3f} (lit pixels)")
    print(f"  Mitsuba, naive hand-over   {brightest(img_naive, sel)}   (jaxsh image, identity to_world: wrong)")
    ok = np.abs(np.subtract(brightest(img_sun, sel), brightest(ref_sun, sel))).max() <= 1.0
    print(f"  -> conventions {'agree' if ok else 'DISAGREE'}  [{time.perf_counter() - t0:.1f} s]")
    if not ok:
        print("convention check failed; the timing comparison below would be meaningless")
        return 1

    # ---- ground truth
    t0 = time.perf_counter()
    ref = reference(gb64, env)
    t_ref = time.perf_counter() - t0
    t0 = time.perf_counter()
    ref_hi = diffuse_numpy(gb64, 256, 512)
    t_ref_hi = time.perf_counter() - t0
    floor = rms_rel(ref, ref_hi, sel)
    print(f"\nReference (render_reference, 64x128 texels, float64): {fmt_t(t_ref)}; vs Kd * sum_texels L w max(n.w, 0) "
          f"in NumPy on a 256x512 sampling ({fmt_t(t_ref_hi)}): RMS rel diff {fmt_e(floor)} (the truth's own floor)")
    ref_uniform = reference(gb64, np.ones((64, 128, 3)))
    print(f"  Kd check: uniform unit sky gives {ref_uniform[48, 48].round(4)} = pi*Kd {(np.pi * KD).round(4)}")
    if not np.allclose(ref_uniform[48, 48], np.pi * KD, rtol=1e-3):
        raise SystemExit("Kd check failed: the reference under a uniform unit sky is not pi * Kd")

    # ---- jaxsh practical model
    gb32 = gbuffer(jnp.float32)
    env32 = jnp.asarray(env, jnp.float32)
    kd32 = jnp.asarray(KD, jnp.float32)
    ks32 = jnp.zeros(3, jnp.float32)

    rows_j = []
    print("\njaxsh practical model (float32, jit: project_latlong(64x128) + render_practical 96x96):")
    for lmax in (2, 8):
        @jax.jit
        def run(env_, n, v, m, lmax=lmax):
            sh = jaxsh.project_latlong(env_, lmax)
            return jaxsh.render_practical(n, v, kd32, ks32, None, jnp.float32(SIGMA), slow_sh=sh, mask=m).total

        fn = lambda: run(env32, gb32.normal, gb32.view, gb32.mask)  # noqa: E731
        first, warm = time_jax(fn)
        err = rms_rel(np.asarray(fn(), np.float64), ref, sel)
        rows_j.append((lmax, warm, err))
        print(f"  lmax {lmax}: first {fmt_t(first)}, warm {fmt_t(warm)}, RMS rel err {fmt_e(err)}", flush=True)

    # ---- Mitsuba at increasing spp (rendered by the peer above)
    info = meta["jobs"]["main"]
    print(f"\nMitsuba ({variant}, path max_depth=2, envmap {MI_ENV[0]}x{MI_ENV[1]} nodes, box filter); "
          f"scene load {fmt_t(info['load_s'])} (not counted):")
    rows_m = []
    for k, (spp, r) in enumerate(zip(spps, info["renders"])):
        err = rms_rel(mimg[f"main/{k}"], ref, sel)
        rows_m.append((spp, min(r["times"]), err))
        print(f"  spp {spp:5d}: {fmt_t(min(r['times']))}, RMS rel err {fmt_e(err)}", flush=True)

    # fit err ~ a / sqrt(spp) on the levels well above the reference floor
    spp_a = np.array([r[0] for r in rows_m], float)
    err_a = np.array([r[2] for r in rows_m])
    t_a = np.array([r[1] for r in rows_m])
    use = err_a > 3 * floor
    a = float(np.exp(np.mean(np.log(err_a[use]) + 0.5 * np.log(spp_a[use])))) if use.any() else float("nan")
    # time per spp from the largest level (fixed overheads matter less there)
    t_per_spp = t_a[-1] / spp_a[-1]

    print("\n" + "=" * 100)
    print("Mitsuba spp / time to reach the jaxsh practical model's error (RMS rel err vs render_reference)")
    print(f"fit: Mitsuba err ~ {a:.3f}/sqrt(spp); {fmt_t(t_per_spp)} per spp at {int(spp_a[-1])} spp")
    print("=" * 100)
    print(f"{'lmax':>4} | {'jaxsh err':>9} | {'jaxsh warm':>10} | {'first measured spp <= err':>26} | "
          f"{'Mitsuba time':>12} | {'fit spp':>8} | {'fit time':>10} | ratio t_mitsuba/t_jaxsh")
    for lmax, tj, ej in rows_j:
        hit = [r for r in rows_m if r[2] <= ej]
        if hit:
            s_hit, t_hit = hit[0][0], hit[0][1]
            meas = f"{s_hit:d}"
            tm = fmt_t(t_hit)
        else:
            s_hit = t_hit = None
            meas = f"> {spps[-1]} (not reached)"
            tm = "-"
        fit_spp = (a / ej) ** 2 if ej > 0 else float("inf")
        fit_t = fit_spp * t_per_spp
        fit_note = "" if ej > 2 * floor else "  (err near the reference floor: fit unreliable)"
        ratio = t_hit / tj if t_hit else fit_t / tj
        rtxt = f"{ratio:.0f}x" + ("" if t_hit else " (fit)")
        print(f"{lmax:>4} | {fmt_e(ej):>9} | {fmt_t(tj):>10} | {meas:>26} | {tm:>12} | {fit_spp:8.0f} | "
              f"{fmt_t(fit_t):>10} | {rtxt}{fit_note}")
    print("\nNotes: the practical model's diffuse term is Kd times the 9-coefficient (l <= 2) irradiance (R&H eq. 24)")
    print("whatever lmax is given (lmax only feeds the specular term), hence the same error at lmax 2 and 8.")
    print("jaxsh time includes the SH projection of the 64x128 map; the G-buffer (primary visibility) is")
    print("precomputed for jaxsh and not timed, while Mitsuba's time includes ray tracing its camera rays.")
    print("Both use all CPU cores. Mitsuba's error at a given spp is one random realisation.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
