"""`jaxsh fit`: recover what a capture manifest leaves unknown (R&H 2001 sec. 6).

* lighting given, BRDF unknown → `fit_brdf` (sec. 6.1), per texel with
  `solve.textured` (texture maps written as EXR), or reflectance sharing with
  `solve.brdf_model` `"sharing"` / `"sharing_spatial"` (Zickler 2006 eq. 12 /
  13, an RBF `.npz` next to `result.json`);
* BRDF given, lighting unknown → `inverse_lighting` (sec. 6.2, eq. 25, with the
  known roughness deconvolved so the re-renders use the same model);
* both unknown → `factorize` (sec. 6.3; $K_d + K_s = 1$ per channel).

Writes `result.json` (docs/results.md), the lighting as a lat-long EXR + PNG,
and re-renders `view_###.exr/.png` of every view with the recovered values.
Meshes get the visibility terms of sec. 6.4; normal maps
(`jaxsh.normal_map_gbuffer`) give no shadows.

Images are read with their declared `encoding` and `alpha`, their saturated
pixels (at or above `views[k].saturation`, in the file's units) dropped before
the `exposure` scale is applied; masks are read by `jaxsh.io.read_mask`.
Everything the manifest names is validated, and `--out` checked against every
input, before the solve; all files are written atomically.
"""

from __future__ import annotations

import math
import os
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxsh
from jaxsh import io as jio

from ._brdf import fit_brdf
from ._data import Lighting, TorranceSparrow, observations, predict, status_name
from ._factorize import factorize
from ._lighting import inverse_lighting
from ._scale import pad_observations, shard_observations
from ._render_manifest import (
    check_outputs,
    check_unsupported,
    lighting_from_block,
    lighting_from_manifest,
    lighting_where,
    manifest_mesh,
    pixel_xy,
    render_rbf_view,
    same_camera,
    view_geometry,
    view_lighting_blocks,
)
from ._sharing import Samples, fit_homogeneous, fit_sbrdf, reflectance_samples


# The roughness whose cut-off (`min(ceil(4 / sigma), H/2 - 1)`, `lighting_from_block`) a given environment map is
# projected to for the first fit of a known-lighting capture; a smoother fit projects it again (`fit_manifest`).
_FIRST_SIGMA = 0.1
# The largest per-sample terms (8 bytes x samples x channels x (l + 1) bands) an automatic cut-off may ask for
_TERMS_BYTES = 2**30


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


def _check_models(m: dict, blocks) -> None:
    """Before any work: the combinations `solve.brdf_model` / `solve.textured` need (one-line `ManifestError`)."""
    solve, path = m["solve"], m["path"]
    model, known = solve["brdf_model"], m["lighting"] is not None or blocks is not None
    if model != "torrance_sparrow":
        if not known or m["brdf"] is not None:
            raise jio.ManifestError(f"{path}: `solve.brdf_model` {model!r} recovers the BRDF under known lighting: "
                                    "give `lighting` (or `views[k].lighting`) and set `brdf` to null")
        for k, lit in enumerate(blocks or [m["lighting"]] * len(m["views"])):
            where = "lighting" if lit is m["lighting"] else f"views[{k}].lighting"
            if lit["envmap"] is not None or len(lit["directional"]) != 1:
                raise jio.ManifestError(
                    f"{path}: `{where}` must be exactly one `directional` source and no `envmap` for `solve.brdf_model` "
                    f"{model!r} (Zickler 2006: one directional light per image)")
        if model == "sharing_spatial" and not same_camera(m["views"]):
            raise jio.ManifestError(f"{path}: `solve.brdf_model` \"sharing_spatial\" takes its surface coordinates from the "
                                    "pixel grid of one camera: every `views[k].camera` must equal `views[0].camera`")
    _check_solve_fields(m, model, known, blocks)
    if solve["textured"] is not None:
        if not known or m["brdf"] is not None:
            raise jio.ManifestError(f"{path}: `solve.textured` fits a textured BRDF under known lighting: give `lighting` "
                                    "(or `views[k].lighting`) and set `brdf` to null")
        if not same_camera(m["views"]):
            raise jio.ManifestError(f"{path}: `solve.textured` has one texel per pixel of one camera: every "
                                    "`views[k].camera` must equal `views[0].camera`")


# `solve` fields of reflectance sharing (Zickler 2006), and of its spatial form only
_SHARING_FIELDS = ("n_centers", "m_w", "tol", "min_cos", "max_samples")


def _check_solve_fields(m: dict, model: str, known: bool, blocks) -> None:
    """A `solve` field the chosen fit does not use is an error, never silently ignored (docs/manifest.md): the
    sharing settings outside `brdf_model` "sharing"/"sharing_spatial" (`m_xy` outside the spatial one);
    `fresnel` outside a Torrance-Sparrow fit of the BRDF (with a known `brdf` its μ is given); `render_lmax`
    where no lighting block has an `envmap` to project. (`textured`: `_check_models`.) The first such field,
    in name order, is reported."""
    given, path = set(m.get("given", {}).get("solve", [])), m["path"]
    sharing = model != "torrance_sparrow"
    unused = {f: "a setting of reflectance sharing (`solve.brdf_model` \"sharing\" or \"sharing_spatial\")"
              for f in _SHARING_FIELDS if not sharing}
    if model != "sharing_spatial":
        unused["m_xy"] = 'a setting of `solve.brdf_model` "sharing_spatial"'
    if sharing or m["brdf"] is not None:
        why = "the Torrance-Sparrow fit of the BRDF" + (" (the given `brdf` has its own μ)" if m["brdf"] is not None else "")
        unused["fresnel"] = f"a setting of {why}"
    lightings = [m["lighting"]] + [lit for lit in (blocks or []) if lit is not None]
    if not known or not any(lit is not None and lit["envmap"] is not None for lit in lightings):
        unused["render_lmax"] = "the cut-off of a given `envmap`, and no lighting block has one"
    bad = sorted(given & unused.keys())
    if bad:
        raise jio.ManifestError(f"{path}: `solve.{bad[0]}` is {unused[bad[0]]}: this fit does not use it; remove it")


def _out_names(m: dict) -> list[str]:
    n, solve = len(m["views"]), m["solve"]
    names = ["result.json", "lighting.exr", "lighting.png"] + [f"view_{k:03d}{e}" for k in range(n) for e in (".exr", ".png")]
    if solve["brdf_model"] != "torrance_sparrow":
        names.append("brdf_rbf.npz")
    if solve["textured"] is not None:
        names += ["kd.exr"] + (["ks.exr"] if solve["textured"] == "kd_ks" else [])
    return names


def fit_manifest(manifest_path, out_dir, progress: bool = True, mesh=None) -> dict:
    """Run the fit a manifest asks for and write the results (module docstring). Returns `result.json`'s dict.

    `mesh`: a `jax.sharding.Mesh` (`solvers.pixel_mesh`): the pixels of a Torrance-Sparrow fit are sharded
    over it (`solvers.shard_observations`; the same result to rounding). None: one device."""
    t_all = time.perf_counter()
    timings = {}

    def say(msg):
        if progress:
            print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", file=sys.stderr, flush=True)

    m = jio.read_manifest(manifest_path)
    blocks = view_lighting_blocks(m, "fit")  # None: the top-level lighting (or none) for every view
    if (m["lighting"] is not None or blocks is not None) and m["brdf"] is not None:
        raise jio.ManifestError(f"{m['path']}: both `lighting` and `brdf` are given: nothing to recover (set one to null)")
    if m["brdf"] is not None and m["brdf"]["model"] != "torrance_sparrow":
        raise jio.ManifestError(f"{m['path']}: `brdf.model` \"rbf\" cannot be the known BRDF of inverse lighting "
                                "(give a Torrance-Sparrow `brdf`, or render with `jaxsh render`)")
    if m["brdf"] is not None and any(np.ndim(m["brdf"][key]) > 1 for key in ("kd", "ks")):
        raise jio.ManifestError(f"{m['path']}: a texture-map `brdf.kd`/`brdf.ks` is not supported by inverse lighting "
                                "(`jaxsh fit` with a known BRDF needs RGB values)")
    check_unsupported(m, "fit")
    _check_models(m, blocks)
    for k, v in enumerate(m["views"]):
        if not v.get("image"):
            raise jio.ManifestError(f"{m['path']}: `views[{k}].image` is required by `jaxsh fit`")
        for key in ("image", "mask"):
            if v.get(key) and not os.path.exists(v[key]):
                raise jio.ManifestError(f"{m['path']}: `views[{k}].{key}` file not found: {v[key]}")
    n = len(m["views"])
    names = _out_names(m)
    outs = dict(zip(names, check_outputs(m, out_dir, names)))
    solve = m["solve"]
    model = solve["brdf_model"]
    lmax = int(solve["lighting_lmax"])
    for k, view in enumerate(m["views"]):  # headers only: every shape checked before any work
        c = view["camera"]
        if view.get("mask"):
            try:
                info = jio.read_image_info(view["mask"])
            except ValueError as e:
                raise jio.ManifestError(f"{m['path']}: `views[{k}].mask` cannot be read: {e}") from None
            if (info["width"], info["height"]) != (c["width"], c["height"]):
                raise jio.ManifestError(f"{m['path']}: `views[{k}].mask` is {info['width']}x{info['height']} but "
                                        f"`views[{k}].camera` is {c['width']}x{c['height']}: {view['mask']}")
    surface = manifest_mesh(m)  # the object's triangles (trimesh) or None; `mesh` is the device mesh

    def to_lighting(parts):
        # NumPy parts as they are: `Lighting`'s fields convert them (`as_float_array`: a host copy sent by
        # `device_put`, no XLA program per shape)
        return Lighting(*parts)

    def given_lighting(sigma):
        """(the top-level `Lighting` or view 0's, one `Lighting` per view or None, the envmaps' SH cut-off or None):
        the maps projected to `solve.render_lmax`, else to the cut-off of roughness `sigma` (`envmap_lmax`)."""
        known = None
        per_view = None  # one Lighting per view (`views[k].lighting`), else None
        if m["lighting"] is not None:
            known = to_lighting(lighting_from_manifest(m, sigma, solve.get("render_lmax")))
        if blocks is not None:
            per_view = [known if (blk is m["lighting"] and known is not None)
                        else to_lighting(lighting_from_block(blk, sigma, solve.get("render_lmax"), manifest=m["path"],
                                                             where=lighting_where(m, blocks, k)))
                        for k, blk in enumerate(blocks)]
            if known is None:
                known = per_view[0]  # for lighting.exr / result.json
        cuts = [math.isqrt(lit.slow_sh.shape[0]) - 1 for lit in (per_view or [known])
                if lit is not None and lit.slow_sh is not None]
        return known, per_view, (max(cuts) if cuts else None)

    known, per_view, used_lmax = given_lighting(_FIRST_SIGMA)
    view_light = (lambda k: known) if per_view is None else (lambda k: per_view[k])
    t = time.perf_counter()
    gbs, imgs, masks, extras = [], [], [], []
    maps = {}
    for k in range(n):
        say(f"view {k + 1}/{n}: G-buffer{' and visibility' if surface is not None else ''}")
        g, extra = view_geometry(m, k, surface, None if known is None else view_light(k).fast_directions, maps)
        img, mask = _read_view(m, k, np.asarray(g.mask))
        gbs.append(g)
        imgs.append(img)
        masks.append(mask)
        extras.append(extra)
    if model != "torrance_sparrow":
        timings["setup"] = time.perf_counter() - t
        return _fit_sharing(m, gbs, imgs, masks, extras, per_view or [known] * n, known, outs, timings, say, out_dir)
    vis = {}
    for key in ("transfer", "reflected_visibility", "fast_visibility"):
        if extras and key in extras[0]:
            vis[key] = [np.asarray(e[key]) for e in extras]
    if "fast_visibility" in vis:  # per-view source counts differ: pad the columns (unused ones are ignored)
        j = max(a.shape[-1] for a in vis["fast_visibility"])
        vis["fast_visibility"] = [np.pad(a, ((0, 0), (0, 0), (0, j - a.shape[-1]))) for a in vis["fast_visibility"]]
    textured = solve["textured"]
    texel = None
    if textured is not None:  # one texel per pixel of the (common) camera
        hh, ww = np.asarray(gbs[0].mask).shape
        texel = np.arange(hh * ww, dtype=np.int32).reshape(hh, ww)
        vis["texel"] = [texel] * n
        vis["n_texels"] = hh * ww
    if known is not None or m["brdf"] is None:
        # Every object pixel is a sample, the invalid ones (masked, clipped) with weight 0: the fit is the same,
        # views sharing a camera get the same pixel count (one compiled program for all of them), and the
        # re-renders below are the fit's own model at every object pixel (`fitted`) instead of a renderer's
        # compiled program.
        sat = solve.get("saturation")
        valid = [mk & (np.all(im < sat, -1) if sat is not None else True) for mk, im in zip(masks, imgs)]
        imgs = [np.where(v[..., None], im, 0.0) for v, im in zip(valid, imgs)]
        # `observations` drops weight-0 pixels, so the weights are set afterwards, in its sample order (views in
        # turn, each view's object pixels in raster order)
        obs = observations(gbs, imgs, masks=[np.asarray(g.mask) for g in gbs], **vis)
        w = np.concatenate([v.reshape(-1)[np.asarray(g.mask).reshape(-1)] for v, g in zip(valid, gbs)])
        obs = eqx.tree_at(lambda o: o.weights, obs, jax.device_put(w.astype(np.asarray(obs.weights).dtype)))
        n_valid = int(np.count_nonzero(w))
    else:
        obs = observations(gbs, imgs, masks=masks, saturation=solve.get("saturation"), **vis)
        n_valid = obs.n_samples
    timings["setup"] = time.perf_counter() - t
    say(f"{n_valid} valid pixels in {len(gbs)} views")
    # The solvers' input (`obs` stays for the re-renders): padded with weight-0 samples to a size bucket, so that
    # captures whose pixel counts share a bucket share the compiled programs (in the compilation cache too), then
    # sharded over `mesh` if any. The same fit to rounding.
    sobs = pad_observations(obs, bucket=True)
    sobs = sobs if mesh is None else shard_observations(sobs, mesh)
    t = time.perf_counter()
    std = None
    if known is not None:
        say("known lighting: fitting " + ("Kd, Ks" if textured is None else f"per-texel {textured}") +
            ", mu, sigma (grid + simplex, R&H sec. 6.1; Levenberg-Marquardt on all samples after a search on a subset)")
        res = fit_brdf(sobs, known if per_view is None else per_view, fresnel=bool(solve.get("fresnel", True)),
                       textured=textured)
        # The maps were cut off for the roughness `_FIRST_SIGMA`; a surface fitted as smoother reflects finer
        # detail of them (the filter exp(-(sigma l)^2) of eq. 24 is still 1e-7 at l = 4 / sigma): project them
        # again at the fitted sigma's cut-off and fit again, until the cut-off covers the fit (at most twice).
        # The fit's per-sample terms hold (l + 1) bands per sample and channel: the cut-off is capped so that they
        # stay within `_TERMS_BYTES` (a 3 x 512^2 capture: l <= 67 instead of ~255 for a mirror-like sphere).
        cap = max(int(4.0 / _FIRST_SIGMA), _TERMS_BYTES // (8 * sobs.n_samples * max(obs.n_channels, 1)) - 1)
        for _ in range(2):
            if used_lmax is None or solve.get("render_lmax") is not None:
                break
            sigma_fit = float(np.min(np.asarray(res.brdf.sigma)))
            known2, per_view2, lmax2 = given_lighting(max(sigma_fit, 4.0 / cap))
            if lmax2 <= used_lmax:
                break
            capped = f" (capped by the capture's size; `solve.render_lmax` sets it)" if sigma_fit < 4.0 / cap else ""
            say(f"fitted sigma {sigma_fit:.4f} reflects the environment map beyond its cut-off l = {used_lmax}: "
                f"fitting again with the map to l = {lmax2}{capped}")
            known, per_view, used_lmax = known2, per_view2, lmax2
            res = fit_brdf(sobs, known if per_view is None else per_view, fresnel=bool(solve.get("fresnel", True)),
                           textured=textured)
        brdf, lighting, std = res.brdf, known, res.std_errors
        light_sh = known.total_sh(lmax)
        display_sh = light_sh
    elif m["brdf"] is not None:
        b = m["brdf"]
        brdf = TorranceSparrow(jnp.asarray(b["kd"]), jnp.asarray(b["ks"]), None if b["mu"] is None else jnp.asarray(b["mu"]),
                               jnp.asarray(b["sigma"]))
        say(f"known BRDF: inverse lighting to l* = {lmax} (eq. 25, roughness deconvolved)")
        res = inverse_lighting(sobs, brdf, lmax, deconvolve=True)
        lighting = res.lighting
        light_sh = res.coeffs
        display_sh = jaxsh.filter_lighting_microfacet(res.coeffs, brdf.sigma)
        std = TorranceSparrow.unchecked(jnp.zeros(3), jnp.zeros(3), None, jnp.zeros(()))
    else:
        say(f"unknown lighting and BRDF: factorization (R&H sec. 6.3), l* = {lmax}")
        res = factorize(sobs, lmax, fresnel=bool(solve.get("fresnel", True)))
        brdf, lighting, std = res.brdf, res.lighting, res.std_errors
        light_sh = lighting.slow_sh
        display_sh = res.filtered_sh
    timings["solve"] = time.perf_counter() - t
    say(f"solved: status {status_name(res.status)}, relative RMS {float(res.rel_rms):.4f}")
    os.makedirs(out_dir, exist_ok=True)

    def out(name):
        return outs[name]

    t = time.perf_counter()
    _write_lighting(out, display_sh, lmax)
    if known is not None or m["brdf"] is None:  # the model at the estimate, as the fit evaluated it (eq. 24;
        # `sobs` may carry padding at the end)
        renders = obs.to_images(np.asarray(res.fitted)[: obs.n_samples])
    else:
        renders = [np.asarray(predict(brdf, lighting if per_view is None else per_view[k], g.normal, g.view,
                                      mask=g.mask, **extras[k])) for k, g in enumerate(gbs)]
    for k, img in enumerate(renders):
        jio.write_image(out(f"view_{k:03d}.exr"), img)
        jio.write_image(out(f"view_{k:03d}.png"), img)
    brdf_json = _brdf_json(brdf)
    if textured is not None:  # per-texel values as maps in the camera's pixel grid; unobserved texels 0
        seen = np.asarray(res.texel_count) > 0
        hh, ww = texel.shape
        for key in ("kd",) + (("ks",) if textured == "kd_ks" else ()):
            # unobserved texels 0, and with "kd_ks" the texels whose K_s the images do not determine (noise over a
            # vanishing specular term where no view sees a highlight: up to 1e55, docs/manifest.md, `textured`)
            keep = seen[:, None] & (~np.asarray(res.stats["undetermined"]["ks"]) if key == "ks" else True)
            a = np.where(keep, np.asarray(getattr(brdf, key)), 0.0).reshape(hh, ww, -1)
            big = int(np.count_nonzero(~(np.abs(a) <= np.finfo(np.float32).max)))
            if big:
                raise ValueError(f"solve.textured {textured!r}: the fitted {key} of {big} pixels is beyond the float32 "
                                 f"range of {key}.exr")
            jio.write_image(out(f"{key}.exr"), a, camera=m["views"][0]["camera"])  # the map's camera, for render
            brdf_json[key] = f"{key}.exr"
        if textured == "kd":  # one Ks for all texels (broadcast to (T, C) by the fit)
            brdf_json["ks"] = _json(np.asarray(brdf.ks).reshape(-1, np.shape(brdf.ks)[-1])[0])
    timings["write"] = time.perf_counter() - t
    lighting_json = _lighting_json(light_sh, lmax)
    if known is not None and used_lmax is not None:
        lighting_json["envmap_lmax"] = used_lmax
    if m["lighting"] is None and lighting.fast_directions is not None:
        lighting_json["directional"] = [
            {"direction": _json(d), "radiance": _json(e)} for d, e in zip(lighting.fast_directions, lighting.fast_energy)
        ]
    std_json = None
    if known is not None or m["brdf"] is None:
        std_json = {k_: (None if textured is not None and np.ndim(getattr(std, k_)) > 1 else _json(getattr(std, k_)))
                    for k_ in ("kd", "ks", "mu", "sigma")}
        if textured == "kd":  # the one Ks's error (broadcast to (T, C) like the estimate)
            std_json["ks"] = _json(np.asarray(std.ks).reshape(-1, np.shape(std.ks)[-1])[0])
    result = {
        "brdf": brdf_json,
        "lighting": lighting_json,
        "std_errors": std_json,
        "status": status_name(res.status),
        "rms": _json(res.rms),
        "rel_rms": _json(res.rel_rms),
        "iterations": int(getattr(res, "iterations", 0)),
        "samples": {"valid": n_valid, "total": obs.n_samples, "solved": sobs.n_samples},
        "timings_s": timings,
    }
    if textured is not None:
        result["texels"] = {"grid": "the pixels of views[0].camera (row-major)", "width": int(texel.shape[1]),
                            "height": int(texel.shape[0]), "observed": int(np.count_nonzero(seen)),
                            "unobserved_value": 0.0}
    if per_view is not None:
        result["lighting"]["per_view"] = "views[k].lighting of the manifest (this block: view 0's, or the top-level one)"
    if known is not None:
        result["at_bound"] = {k: bool(v) for k, v in res.stats["at_bound"].items()}
        und = res.stats["undetermined"]
        result["undetermined"] = {k: bool(und[k]) for k in ("mu", "sigma")}
        if "ks" in und:  # per texel and channel ("kd_ks"): the observed pixels' values that ks.exr holds as 0
            result["undetermined"]["ks_values"] = int(np.count_nonzero(np.asarray(und["ks"])[seen]))
    if known is None and m["brdf"] is None:  # factorization: mu (with Fresnel), sigma at an end of their search ranges
        result["at_bound"] = {k: bool(v) for k, v in res.stats["at_bound"].items()}
    if m["brdf"] is not None:
        result["lighting"]["std_errors"] = _json(res.std_errors)
        result["lighting"]["supported_lmax"] = [int(x) for x in np.asarray(res.supported_lmax).reshape(-1)]  # ints (results.md)
    jio.write_json(out("result.json"), result)
    say(f"wrote {out_dir}/result.json, lighting.exr/.png and {len(gbs)} re-renders")
    return result


def _read_view(m: dict, k: int, object_mask) -> tuple[np.ndarray, np.ndarray]:
    """`(radiance (H, W, 3) float64, usable bool (H, W))` of view `k`: its image read with the declared `encoding`,
    `exposure`, `saturation` and `alpha`, and its `mask` (`jaxsh.io.read_mask`). Every problem is a `ManifestError`
    naming the manifest, the field and the file; so is a non-finite pixel on the object that nothing excludes."""
    view, path = m["views"][k], m["path"]
    where = f"views[{k}].image"
    try:
        img, usable = jio.read_radiance(view["image"], view["encoding"], view["exposure"], view["saturation"],
                                        alpha=view["alpha"])
    except ValueError as e:
        raise jio.ManifestError(f"{path}: `{where}` cannot be used: {e}") from None
    img = np.asarray(img, np.float64)
    h, w = object_mask.shape
    if img.shape[:2] != (h, w):
        raise jio.ManifestError(f"{path}: `{where}` is {img.shape[1]}x{img.shape[0]} but `views[{k}].camera` is "
                                f"{w}x{h}: {view['image']}")
    if img.shape[2] != 3:
        raise jio.ManifestError(f"{path}: `{where}` must have 3 colour channels (RGB), got {img.shape[2]} "
                                f"(alpha not counted): {view['image']}")
    if view.get("mask"):
        try:
            usable = usable & jio.read_mask(view["mask"])
        except ValueError as e:
            raise jio.ManifestError(f"{path}: `views[{k}].mask` cannot be used: {e}") from None
    bad = ~np.all(np.isfinite(img), -1) & usable & object_mask
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise jio.ManifestError(
            f"{path}: `{where}` has {int(bad.sum())} non-finite (NaN/inf) pixels on the object, e.g. (row {i}, column "
            f"{j}): {view['image']}; fix the image, or exclude them with `views[{k}].mask` (a pixel is used where the "
            "mask's first channel is > 0.5 of full scale)")
    return img, usable


def _lighting_json(light_sh, lmax: int) -> dict:
    return {"lmax": lmax, "frame": "world, +z up", "coeffs": _json(jnp.asarray(light_sh)[: jaxsh.num_coeffs(lmax)])}


def _write_lighting(out, display_sh, lmax: int) -> None:
    h = max(32, 4 * (lmax + 1))
    env = np.asarray(jaxsh.synthesize_latlong(display_sh, h, 2 * h))
    jio.write_image(out("lighting.exr"), env)
    jio.write_image(out("lighting.png"), np.maximum(env, 0))


def _fit_sharing(m, gbs, imgs, masks, extras, lights, known, outs, timings, say, out_dir) -> dict:
    """Reflectance sharing (Zickler 2006): eq. 12 (`"sharing"`) or eq. 13 (`"sharing_spatial"`) from one light per view."""
    solve = m["solve"]
    spatial = solve["brdf_model"] == "sharing_spatial"
    t = time.perf_counter()
    hh, ww = np.asarray(gbs[0].mask).shape
    xy = pixel_xy(ww, hh) if spatial else None
    parts, per_view = [], []
    dirs = np.stack([np.asarray(lit.fast_directions)[0] for lit in lights])
    irr = np.stack([np.asarray(lit.fast_energy)[0] for lit in lights])
    keep = np.stack([mk & np.asarray(g.mask) for mk, g in zip(masks, gbs)])
    if solve.get("saturation") is not None:  # the extra threshold of every view, in linear radiance
        keep &= np.stack([np.all(im < solve["saturation"], -1) for im in imgs])
    keep &= (irr.min(-1) > 0)[:, None, None]  # a black light carries no reflectance sample
    if "fast_visibility" in extras[0]:
        keep &= np.stack([np.asarray(e["fast_visibility"])[..., 0] > 0.5 for e in extras])
    one_grid = all(np.array_equal(np.asarray(g.normal), np.asarray(gbs[0].normal))
                   and np.array_equal(np.asarray(g.view), np.asarray(gbs[0].view)) for g in gbs[1:])
    groups = [list(range(len(gbs)))] if one_grid else [[k] for k in range(len(gbs))]  # photometric stereo: one call
    per_view = [0] * len(gbs)
    for ks in groups:
        g = gbs[ks[0]]
        if not keep[ks].any():
            continue
        try:
            s = reflectance_samples(np.stack([imgs[k] for k in ks]), g.normal, g.view, dirs[ks], irradiance=irr[ks],
                                    mask=keep[ks].any(0), xy=xy, visible=keep[ks], min_cos=solve["min_cos"])
        except ValueError as err:
            if "no usable samples" not in str(err):
                raise
            continue  # every pixel of these views is grazing or facing away: counted as 0 samples
        img_idx = np.asarray(ks)[np.asarray(s.image)]
        s = Samples(s.points, s.values, s.cos_i, s.wi, s.wo, s.n, s.xy, jnp.asarray(img_idx), s.pixel)
        for k in ks:
            per_view[k] = int(np.count_nonzero(img_idx == k))
        parts.append(s)
    total = sum(per_view)
    if total == 0:
        raise ValueError(f"{m['path']}: no usable reflectance samples in any view (every pixel is masked, clipped, "
                         f"shadowed or beyond `solve.min_cos` = {solve['min_cos']})")
    samples = parts[0] if len(parts) == 1 else jax.tree.map(lambda *a: jnp.concatenate(a), *parts)
    n_used = total
    if total > solve["max_samples"]:  # a few hundred centres need far fewer samples than millions of pixels
        sel = np.sort(np.random.default_rng(0).choice(total, solve["max_samples"], replace=False))
        samples = jax.tree.map(lambda a: a[sel], samples)
        n_used = solve["max_samples"]
    timings["setup"] += time.perf_counter() - t
    k_c = min(solve["n_centers"], n_used)
    say(f"{total} reflectance samples in {len(gbs)} views ({n_used} used); reflectance sharing, Zickler 2006 eq. "
        f"{'13' if spatial else '12'}, up to {k_c} centres")
    t = time.perf_counter()
    kw = {"tol": solve["tol"]} if solve["tol"] is not None else {}
    if spatial:
        res = fit_sbrdf(samples, k_c, m_xy=solve["m_xy"], m_w=solve["m_w"], **kw)
    else:
        res = fit_homogeneous(samples, k_c, m_w=solve["m_w"], **kw)
    timings["solve"] = time.perf_counter() - t
    say(f"solved: status {status_name(res.status)}, relative RMS {float(res.rel_rms):.4f}")
    os.makedirs(out_dir, exist_ok=True)
    t = time.perf_counter()
    lmax = int(solve["lighting_lmax"])
    _write_lighting(outs.__getitem__, known.total_sh(lmax), lmax)
    model = res.fit.model
    jio.write_rbf(outs["brdf_rbf.npz"], model, spatial=spatial, width=ww if spatial else None, height=hh if spatial else None,
                  camera=m["views"][0]["camera"] if spatial else None)
    block = {"model": "rbf", "spatial": spatial, "rbf": {"model": model, "spatial": spatial, "width": ww, "height": hh}}
    for k, (g, extra, lit) in enumerate(zip(gbs, extras, lights)):
        img = render_rbf_view(block, g, np.asarray(lit.fast_directions), np.asarray(lit.fast_energy),
                              extra.get("fast_visibility"))
        jio.write_image(outs[f"view_{k:03d}.exr"], img)
        jio.write_image(outs[f"view_{k:03d}.png"], img)
    timings["write"] = time.perf_counter() - t
    result = {
        "brdf": {"model": "rbf", "file": "brdf_rbf.npz", "spatial": spatial, "n_centers": int(model.centers.shape[0])},
        "lighting": _lighting_json(known.total_sh(lmax), lmax),
        "std_errors": None,
        "status": status_name(res.status),
        "rms": _json(res.rms),
        "rel_rms": _json(res.rel_rms),
        "iterations": int(res.iterations),
        "timings_s": timings,
        "sharing": {
            "equation": 13 if spatial else 12,
            "metric": {"m_w": solve["m_w"], **({"m_xy": solve["m_xy"]} if spatial else {})},
            "samples": n_used, "samples_total": total, "samples_per_view": per_view,
            "history_centers": [int(x) for x in np.asarray(res.fit.history_centers)],
            "history_rel_rms": _json(res.fit.history_rms),
            **({"xy": f"pixel grid of views[0].camera: x = (column + 0.5) / {ww}, y = (row + 0.5) / {hh}"} if spatial else {}),
        },
    }
    if m["lighting"] is None:
        result["lighting"]["per_view"] = "views[k].lighting of the manifest (this block: view 0's)"
    jio.write_json(outs["result.json"], result)
    say(f"wrote {out_dir}/result.json, brdf_rbf.npz, lighting.exr/.png and {len(gbs)} re-renders")
    return result
