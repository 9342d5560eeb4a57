"""Mitsuba 3 peer, run in a process of its own (not a benchmark itself; never imports JAX).

Importing Mitsuba (Dr.Jit's LLVM back-end) into a process that has loaded
XLA crashes LLVM ("Cannot select: fminimum"), so ``bench_render.py`` and
``bench_mitsuba.py`` never import Mitsuba: they call ``_common.run_peer``,
which runs this script as ``python _mitsuba_peer.py IN.npz OUT.npz``.

``IN.npz`` holds ``spec`` (a JSON string) and the input arrays (sky maps).
``spec``::

    {"variant": "auto" | "llvm_ad_rgb" | "scalar_rgb",
     "jobs": [{"name": str, "scene": "env_sphere" | "sky_sun_sphere", "params": {...},
               "warmup_spp": int (0: none; a render not counted, e.g. the llvm kernel compile),
               "renders": [{"spp": int, "seeds": [int, ...], "keep": bool}, ...]}, ...]}

``OUT.npz`` holds ``meta`` (JSON: ``ok``, ``error``, ``version``,
``variant``, ``variants_rejected`` (why a variant was skipped), and per job ``load_s`` and per render the wall-clock seconds of
each seed's ``mi.render``) and, for renders with ``keep``, the image of the
last seed as ``<job>/<render index>`` (float64, RGB).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

LLVM_DEFAULT = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
_REJECTED = [""]


def _probe(variant):
    """Import Mitsuba, set `variant` and render 4x4 pixels (run in a child process: an LLVM abort kills it)."""
    import mitsuba as mi

    mi.set_variant(variant)
    mi.render(mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                            "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 4, "height": 4}}}),
              spp=1)


def import_mitsuba(variant):
    """(mitsuba module, variant name) or (None, reason).

    Each candidate variant is first tried in a child process (``--probe``):
    with an unsuitable libLLVM (e.g. LLVM 14/15 where Dr.Jit wants 19) the
    ``llvm_ad_rgb`` variant aborts the whole process at its first render
    ("Cannot select: fminimum"), which no ``except`` can catch; ``auto`` then
    falls back to ``scalar_rgb``.
    """
    if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(LLVM_DEFAULT):
        os.environ["DRJIT_LIBLLVM_PATH"] = LLVM_DEFAULT
    try:
        import mitsuba as mi
    except Exception as e:  # noqa: BLE001
        return None, f"import failed: {type(e).__name__}: {e}"
    tried = ["llvm_ad_rgb", "scalar_rgb"] if variant == "auto" else [variant]
    errs = []
    for v in tried:
        p = subprocess.run([sys.executable, os.path.abspath(__file__), "--probe", v], capture_output=True, text=True,
                           timeout=600)
        if p.returncode != 0:
            lines = [x for x in (p.stdout + p.stderr).strip().splitlines() if x.strip()]
            why = next((x.strip() for x in lines if "Cannot select" in x or "Error" in x), lines[-1] if lines else "")
            errs.append(f"{v}: probe exited with status {p.returncode} ({why[:120]})")
            continue
        mi.set_variant(v)
        _REJECTED[0] = "; ".join(errs)
        return mi, v
    return None, "; ".join(errs)


def scene_env_sphere(mi, p, arrays):
    """bench_mitsuba.py's scene: diffuse unit sphere, orthographic camera on +z, envmap on Mitsuba's nodes."""
    T = mi.ScalarTransform4f
    half, res = float(p["half"]), int(p["res"])
    emitter = {"type": "envmap", "bitmap": mi.Bitmap(np.asarray(arrays[p["env"]], np.float32))}
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 2, "hide_emitters": True},
        "sensor": {
            "type": "orthographic",
            "to_world": T().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]) @ T().scale([half, half, 1.0]),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": 1},
        },
        "sphere": {"type": "sphere", "center": [0, 0, 0], "radius": 1.0,
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(p["reflectance"])}}},
        "env": emitter,
    })


def scene_sky_sun_sphere(mi, p, arrays):
    """bench_render.py's scene: roughplastic sphere under a lat-long sky (envmap) and a directional sun."""
    T = mi.ScalarTransform4f
    n, spp = int(p["n"]), int(p["spp"])
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {"type": "orthographic",
                   "to_world": T().look_at(origin=[0, -5, 1.5], target=[0, 0, 0], up=[0, 0, 1]) @ T().scale([1.1, 1.1, 1]),
                   "film": {"type": "hdrfilm", "width": n, "height": n, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "sphere": {"type": "sphere", "bsdf": {"type": "roughplastic", "distribution": "beckmann",
                                              "alpha": float(p["alpha"]), "int_ior": float(p["ior"])}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(np.array(arrays[p["sky"]], dtype=np.float32, copy=True))},
        "sun": {"type": "directional", "direction": list(p["sun_to"]),
                "irradiance": {"type": "rgb", "value": list(p["sun_irradiance"])}},
    })


SCENES = {"env_sphere": scene_env_sphere, "sky_sun_sphere": scene_sky_sun_sphere}


def run(spec, arrays):
    mi, variant = import_mitsuba(spec.get("variant", "auto"))
    if mi is None:
        return {"ok": False, "error": variant}, {}
    meta = {"ok": True, "error": None, "version": mi.__version__, "variant": variant, "jobs": {},
            "variants_rejected": _REJECTED[0]}
    images = {}
    for job in spec["jobs"]:
        t0 = time.perf_counter()
        scene = SCENES[job["scene"]](mi, job.get("params", {}), arrays)
        info = {"load_s": time.perf_counter() - t0, "renders": []}
        if job.get("warmup_spp", 0):
            t0 = time.perf_counter()
            np.asarray(mi.render(scene, spp=int(job["warmup_spp"])))
            info["warmup_s"] = time.perf_counter() - t0
        for r, item in enumerate(job["renders"]):
            ts, img = [], None
            for seed in item["seeds"]:
                t0 = time.perf_counter()
                img = np.array(mi.render(scene, spp=int(item["spp"]), seed=int(seed)), dtype=np.float64)[..., :3]
                ts.append(time.perf_counter() - t0)
            info["renders"].append({"spp": int(item["spp"]), "times": ts})
            if item.get("keep", False):
                images[f"{job['name']}/{r}"] = img
        meta["jobs"][job["name"]] = info
    return meta, images


def main(argv):
    if len(argv) == 2 and argv[0] == "--probe":
        _probe(argv[1])
        return 0
    if len(argv) != 2:
        print(__doc__)
        return 2
    with np.load(argv[0], allow_pickle=False) as z:
        spec = json.loads(str(z["spec"]))
        arrays = {k: z[k] for k in z.files if k != "spec"}
    meta, images = run(spec, arrays)
    np.savez(argv[1], meta=np.asarray(json.dumps(meta)), **images)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
