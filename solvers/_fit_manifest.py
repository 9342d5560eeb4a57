"""`jaxsh fit`: recover what a capture manifest leaves unknown (R&H 2001 sec. 6).

* lighting given, BRDF unknown → `fit_brdf` (sec. 6.1);
* BRDF given, lighting unknown → `inverse_lighting` (sec. 6.2, eq. 25, with the
  known roughness deconvolved so the re-renders use the same model);
* both unknown → `factorize` (sec. 6.3; $K_d + K_s = 1$ per channel).

Writes `result.json` (docs/results.md), the lighting as a lat-long EXR + PNG,
and re-renders `view_###.exr/.png` of every view with the recovered values.
Meshes get the visibility terms of sec. 6.4.

Images are read with their declared `encoding`, their saturated pixels (at or
above `views[k].saturation`, in the file's units) dropped before the
`exposure` scale is applied. Everything the manifest names is validated, and
`--out` checked against every input, before the solve; all files are written
atomically.
"""

from __future__ import annotations

import math
import os
import sys
import time

import jax.numpy as jnp
import numpy as np

import jaxsh
from jaxsh import io as jio

from ._brdf import fit_brdf
from ._data import Lighting, TorranceSparrow, observations, predict, status_name
from ._factorize import factorize
from ._lighting import inverse_lighting
from ._render_manifest import (
    _mesh_visibility,
    camera_from_manifest,
    check_outputs,
    check_unsupported,
    lighting_from_block,
    lighting_from_manifest,
    view_lighting_blocks,
)


def _json(x):
    """Arrays to lists; non-finite numbers (undetermined std errors) to None."""
    if x is None:
        return None
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        v = float(a)
        return v if math.isfinite(v) else None
    return [_json(v) for v in a]


def _brdf_json(b: TorranceSparrow) -> dict:
    return {"model": "torrance_sparrow", "kd": _json(b.kd), "ks": _json(b.ks), "mu": _json(b.mu), "sigma": _json(b.sigma)}


def fit_manifest(manifest_path, out_dir, progress: bool = True) -> dict:
    """Run the fit a manifest asks for and write the results (module docstring). Returns `result.json`'s dict."""
    t_all = time.perf_counter()
    timings = {}

    def say(msg):
        if progress:
            print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", file=sys.stderr, flush=True)

    m = jio.read_manifest(manifest_path)
    blocks = view_lighting_blocks(m, "fit")  # None: the top-level lighting (or none) for every view
    if (m["lighting"] is not None or blocks is not None) and m["brdf"] is not None:
        raise jio.ManifestError(f"{m['path']}: both `lighting` and `brdf` are given: nothing to recover (set one to null)")
    check_unsupported(m, "fit")
    for k, v in enumerate(m["views"]):
        if not v.get("image"):
            raise jio.ManifestError(f"{m['path']}: `views[{k}].image` is required by `jaxsh fit`")
        for key in ("image", "mask"):
            if v.get(key) and not os.path.exists(v[key]):
                raise jio.ManifestError(f"{m['path']}: `views[{k}].{key}` file not found: {v[key]}")
    n = len(m["views"])
    names = ["result.json", "lighting.exr", "lighting.png"] + [f"view_{k:03d}{e}" for k in range(n) for e in (".exr", ".png")]
    outs = dict(zip(names, check_outputs(m, out_dir, names)))
    solve = m["solve"]
    lmax = int(solve["lighting_lmax"])
    for k, view in enumerate(m["views"]):  # headers only: every shape checked before any work
        c = view["camera"]
        if view.get("mask"):
            info = jio.read_image_info(view["mask"])
            if (info["width"], info["height"]) != (c["width"], c["height"]):
                raise jio.ManifestError(f"{m['path']}: `views[{k}].mask` is {info['width']}x{info['height']} but "
                                        f"`views[{k}].camera` is {c['width']}x{c['height']}: {view['mask']}")
    mesh = jio.read_mesh(m["geometry"]["mesh"]) if "mesh" in m["geometry"] else None
    def to_lighting(parts):
        slow, fd, fe = parts
        return Lighting(None if slow is None else jnp.asarray(slow), None if fd is None else jnp.asarray(fd),
                        None if fe is None else jnp.asarray(fe))

    known = None
    per_view = None  # one Lighting per view (`views[k].lighting`), else None
    if m["lighting"] is not None:
        known = to_lighting(lighting_from_manifest(m, 0.1, solve.get("render_lmax")))
    if blocks is not None:
        per_view = [known if (blk is m["lighting"] and known is not None)
                    else to_lighting(lighting_from_block(blk, 0.1, solve.get("render_lmax"))) for blk in blocks]
        if known is None:
            known = per_view[0]  # for lighting.exr / result.json
    view_light = (lambda k: known) if per_view is None else (lambda k: per_view[k])
    t = time.perf_counter()
    gbs, imgs, masks, extras = [], [], [], []
    for k, view in enumerate(m["views"]):
        say(f"view {k + 1}/{n}: G-buffer{' and visibility' if mesh is not None else ''}")
        cam = camera_from_manifest(view["camera"])
        if mesh is None:
            g = jaxsh.sphere_gbuffer(cam, m["geometry"]["sphere"]["center"], m["geometry"]["sphere"]["radius"])
            extra = {}
        else:
            g = jaxsh.mesh_gbuffer(cam, mesh)
            extra = _mesh_visibility(mesh, g, None if known is None else view_light(k).fast_directions)
        img, unclipped = jio.read_radiance(view["image"], view["encoding"], view["exposure"], view["saturation"])
        img = np.asarray(img, np.float64)[..., :3]
        if img.shape[:2] != tuple(np.asarray(g.mask).shape):
            raise jio.ManifestError(
                f"{view['image']}: image is {img.shape[1]}x{img.shape[0]} but `views[{k}].camera` is "
                f"{np.asarray(g.mask).shape[1]}x{np.asarray(g.mask).shape[0]}"
            )
        mask = unclipped
        if view.get("mask"):
            # masks are not radiance: code values are scaled to [0, 1] (no transfer function), used where > 0.5
            mk = np.asarray(jio.read_image(view["mask"], "linear"))
            mask = mask & ((mk[..., 0] if mk.ndim == 3 else mk) > 0.5)
        gbs.append(g)
        imgs.append(img)
        masks.append(mask)
        extras.append(extra)
    vis = {}
    for key in ("transfer", "reflected_visibility", "fast_visibility"):
        if extras and key in extras[0]:
            vis[key] = [np.asarray(e[key]) for e in extras]
    if "fast_visibility" in vis:  # per-view source counts differ: pad the columns (unused ones are ignored)
        j = max(a.shape[-1] for a in vis["fast_visibility"])
        vis["fast_visibility"] = [np.pad(a, ((0, 0), (0, 0), (0, j - a.shape[-1]))) for a in vis["fast_visibility"]]
    obs = observations(gbs, imgs, masks=masks, saturation=solve.get("saturation"), **vis)
    timings["setup"] = time.perf_counter() - t
    say(f"{obs.n_samples} valid pixels in {len(gbs)} views")
    t = time.perf_counter()
    std = None
    if known is not None:
        say("known lighting: fitting Kd, Ks, mu, sigma (simplex + Levenberg-Marquardt, R&H sec. 6.1)")
        res = fit_brdf(obs, known if per_view is None else per_view, fresnel=bool(solve.get("fresnel", True)))
        brdf, lighting, std = res.brdf, known, res.std_errors
        light_sh = known.total_sh(lmax)
        display_sh = light_sh
    elif m["brdf"] is not None:
        b = m["brdf"]
        brdf = TorranceSparrow(jnp.asarray(b["kd"]), jnp.asarray(b["ks"]), None if b["mu"] is None else jnp.asarray(b["mu"]),
                               jnp.asarray(b["sigma"]))
        say(f"known BRDF: inverse lighting to l* = {lmax} (eq. 25, roughness deconvolved)")
        res = inverse_lighting(obs, brdf, lmax, deconvolve=True)
        lighting = res.lighting
        light_sh = res.coeffs
        display_sh = jaxsh.filter_lighting_microfacet(res.coeffs, brdf.sigma)
        std = TorranceSparrow(jnp.zeros(3), jnp.zeros(3), None, jnp.zeros(()))
    else:
        say(f"unknown lighting and BRDF: factorization (R&H sec. 6.3), l* = {lmax}")
        res = factorize(obs, lmax, fresnel=bool(solve.get("fresnel", True)))
        brdf, lighting, std = res.brdf, res.lighting, res.std_errors
        light_sh = lighting.slow_sh
        display_sh = res.filtered_sh
    timings["solve"] = time.perf_counter() - t
    say(f"solved: status {status_name(res.status)}, relative RMS {float(res.rel_rms):.4f}")
    os.makedirs(out_dir, exist_ok=True)

    def out(name):
        return outs[name]

    t = time.perf_counter()
    h = max(32, 4 * (lmax + 1))
    env = np.asarray(jaxsh.synthesize_latlong(display_sh, h, 2 * h))
    jio.write_image(out("lighting.exr"), env)
    jio.write_image(out("lighting.png"), np.maximum(env, 0))
    for k, g in enumerate(gbs):
        lit_k = lighting if per_view is None else per_view[k]
        img = np.asarray(predict(brdf, lit_k, g.normal, g.view, mask=g.mask, **extras[k]))
        jio.write_image(out(f"view_{k:03d}.exr"), img)
        jio.write_image(out(f"view_{k:03d}.png"), img)
    timings["write"] = time.perf_counter() - t
    lighting_json = {"lmax": lmax, "frame": "world, +z up", "coeffs": _json(jnp.asarray(light_sh)[: jaxsh.num_coeffs(lmax)])}
    if m["lighting"] is None and lighting.fast_directions is not None:
        lighting_json["directional"] = [
            {"direction": _json(d), "radiance": _json(e)} for d, e in zip(lighting.fast_directions, lighting.fast_energy)
        ]
    result = {
        "brdf": _brdf_json(brdf),
        "lighting": lighting_json,
        "std_errors": {"kd": _json(std.kd), "ks": _json(std.ks), "mu": _json(std.mu), "sigma": _json(std.sigma)}
        if known is not None or m["brdf"] is None else None,
        "status": status_name(res.status),
        "rms": _json(res.rms),
        "rel_rms": _json(res.rel_rms),
        "iterations": int(getattr(res, "iterations", 0)),
        "timings_s": timings,
    }
    if per_view is not None:
        result["lighting"]["per_view"] = "views[k].lighting of the manifest (this block: view 0's, or the top-level one)"
    if known is not None:
        result["at_bound"] = {k: bool(v) for k, v in res.stats["at_bound"].items()}
        result["undetermined"] = {k: bool(v) for k, v in res.stats["undetermined"].items()}
    if m["brdf"] is not None:
        result["lighting"]["std_errors"] = _json(res.std_errors)
        result["lighting"]["supported_lmax"] = _json(res.supported_lmax)
    jio.write_json(out("result.json"), result)
    say(f"wrote {out_dir}/result.json, lighting.exr/.png and {len(gbs)} re-renders")
    return result
