"""The `jaxsh` command: `jaxsh demo`, `jaxsh fit`, `jaxsh render`."""

from __future__ import annotations

import argparse
import os
import sys
import time


def _demo(args) -> int:
    import jax

    # The demo runs in float64, scoped to this call (no global flag is changed).
    with jax.enable_x64(True):
        return _demo_x64(args)


_MATERIALS = [
    # R&H 2001 fig. 11 (known-lighting values): teflon, delrin, painted, and bronze (a metal: coloured K_s,
    # no Fresnel term, mu None; fitted with fresnel=False as in the paper)
    ("teflon", [0.89, 0.89, 0.89], [0.11, 0.11, 0.11], 1.78, 0.12),
    ("delrin", [0.87, 0.87, 0.87], [0.13, 0.13, 0.13], 1.44, 0.10),
    ("painted", [0.62, 0.71, 0.62], [0.29, 0.29, 0.29], 1.38, 0.15),
    ("bronze", [0.15, 0.08, 0.05], [0.85, 0.68, 0.59], None, 0.12),
]


def _demo_x64(args) -> int:
    import jax.numpy as jnp
    import numpy as np

    import jaxsh
    import solvers
    from solvers._fit_manifest import _brdf_json, _json

    t0 = time.perf_counter()
    print("jaxsh demo: inverse rendering of synthetic spheres (R&H 2001 sec. 6, fig. 11 materials)")
    print(f"  {args.views} orthographic views of {args.size}x{args.size}, {args.noise:.0%} noise, "
          "area source + ground bounce + directional source;")
    model_name = {"torrance_sparrow": "the full Torrance-Sparrow BRDF the solvers fit",
                  "cook_torrance": "Cook-Torrance (Beckmann, Smith G, Fresnel at the half angle): a fuller BRDF than the fitted one",
                  "ggx": "GGX with Smith G: a fuller BRDF than the fitted one"}[args.brdf_model]
    print(f"  images by the reference renderer ({model_name}; quadrature over the area sources)\n")
    report = {"materials": [], "settings": {"size": args.size, "views": args.views, "noise": args.noise, "lmax": args.lmax,
                                            "brdf_model": args.brdf_model}}
    images = {}
    ok = True
    for k, (name, kd, ks, mu, sigma) in enumerate(_MATERIALS[: args.materials]):
        truth = solvers.TorranceSparrow(jnp.asarray(kd), jnp.asarray(ks), None if mu is None else jnp.asarray(mu),
                                        jnp.asarray(sigma))
        fresnel = mu is not None
        t = time.perf_counter()
        cap = solvers.sphere_capture(truth, size=args.size, n_views=args.views, noise=args.noise, seed=k,
                                     brdf_model=args.brdf_model)
        t_render = time.perf_counter() - t
        obs = solvers.observations(cap.gbuffers, cap.images)
        t = time.perf_counter()
        known = solvers.fit_brdf(obs, cap.lighting, fresnel=fresnel)
        t_known = time.perf_counter() - t
        t = time.perf_counter()
        il = solvers.inverse_lighting(obs, truth, args.lmax)
        t_il = time.perf_counter() - t
        t = time.perf_counter()
        fac = solvers.factorize(obs, args.lmax, fresnel=fresnel)
        t_fac = time.perf_counter() - t
        tl = np.asarray(jaxsh.filter_lighting_microfacet(cap.lighting.total_sh(args.lmax), truth.sigma))
        corr_il = min(np.corrcoef(np.asarray(il.coeffs)[:9, c], tl[:9, c])[0, 1] for c in range(3))
        tf = np.asarray(cap.lighting.total_sh(2))
        corr_fac = min(np.corrcoef(np.asarray(fac.lighting.total_sh(2))[:, c], tf[:, c])[0, 1] for c in range(3))
        # held-out view under a new directional light (per-channel scale fitted for the factorization)
        cam = solvers.view_cameras(1, args.size, azimuths=[2.4], elevation=0.2)[0]
        gb = jaxsh.sphere_gbuffer(cam, jnp.zeros(3), jnp.asarray(1.0))
        m = np.asarray(gb.mask)
        n_, v_ = np.asarray(gb.normal)[m], np.asarray(gb.view)[m]
        d_new = np.array([[0.6, 0.7, 0.4]]) / np.linalg.norm([0.6, 0.7, 0.4])
        new_light = solvers.Lighting(None, jnp.asarray(d_new), jnp.asarray([[2.0, 2.0, 2.0]]))
        ref = np.asarray(jaxsh.render_reference(n_, v_, truth.kd, truth.ks, truth.mu, truth.sigma, directional=(d_new, np.full((1, 3), 2.0))))

        def relit(brdf, fit_scale):
            p = np.asarray(solvers.predict(brdf, new_light, n_, v_))
            if fit_scale:
                p = p * (np.sum(p * ref, 0) / np.sum(p * p, 0))
            return float(np.sqrt(np.mean((p - ref) ** 2) / np.mean(ref**2)))

        e_known, e_fac = relit(known.brdf, False), relit(fac.brdf, True)
        # the same held-out view under an area source + the sun: the reference renders it with the data's BRDF;
        # the floor is the true parameters under the practical model (its own error for this BRDF and light)
        disk_dir = np.array([[-0.5, 0.45, 0.74]]) / np.linalg.norm([-0.5, 0.45, 0.74])
        disks = (disk_dir, np.array([0.4]), np.array([[1.5, 1.45, 1.4]]))
        sun = cap.directional
        area_light = solvers.Lighting(jaxsh.disk_light_sh(jnp.asarray(disk_dir[0]), 0.4, jnp.asarray(disks[2][0]), 40),
                                      jnp.asarray(sun[0]), jnp.asarray(sun[1]))
        ref_area = np.asarray(jaxsh.render_reference(n_, v_, truth.kd, truth.ks, truth.mu, truth.sigma, disks=disks,
                                                     directional=sun, brdf_model=args.brdf_model))

        def relit_area(brdf, fit_scale):
            p = np.asarray(solvers.predict(brdf, area_light, n_, v_))
            if fit_scale:
                p = p * (np.sum(p * ref_area, 0) / np.sum(p * p, 0))
            return float(np.sqrt(np.mean((p - ref_area) ** 2) / np.mean(ref_area**2)))

        a_known, a_fac, a_floor = relit_area(known.brdf, False), relit_area(fac.brdf, True), relit_area(truth, False)
        print(f"{name}: render {t_render:.1f} s | known-lighting fit {t_known:.2f} s | inverse lighting {t_il:.2f} s "
              f"| factorization {t_fac:.2f} s")
        print(f"  {'':8} {'truth':>22} {'known lighting':>22} {'unknown lighting':>22}")
        fmt = lambda a: "none (F = 1)" if a is None else " ".join(f"{x:.3f}" for x in np.atleast_1d(np.asarray(a)))  # noqa: E731
        for pname in ("kd", "ks", "mu", "sigma"):
            print(f"  {pname:8} {fmt(getattr(truth, pname)):>22} {fmt(getattr(known.brdf, pname)):>22} "
                  f"{fmt(getattr(fac.brdf, pname)):>22}")
        tn = np.asarray(truth.ks) / np.asarray(truth.kd + truth.ks)
        print(f"  {'ks/(kd+ks)':8} {fmt(tn):>22} {'':>22} {fmt(fac.brdf.ks):>22}   (unknown lighting: Kd + Ks = 1 per channel)")
        print(f"  {'status':8} {'':>22} {solvers.status_name(known.status):>22} {solvers.status_name(fac.status):>22}")
        print(f"  {'rel RMS':8} {'':>22} {float(known.rel_rms):>22.4f} {float(fac.rel_rms):>22.4f}")
        print(f"  inverse lighting (known BRDF, l* = {args.lmax}): l<=2 correlation with the filtered truth {corr_il:.4f}, "
              f"supported l* {int(np.min(np.asarray(il.supported_lmax)))}")
        print(f"  factorization: l<=2 lighting correlation {corr_fac:.4f}; source found at "
              f"{np.round(np.asarray(fac.source.direction), 3).tolist()} (true {np.round(cap.directional[0][0], 3).tolist()})")
        print(f"  held-out view, new directional light: known-lighting BRDF {e_known:.2%}, factorized BRDF {e_fac:.2%} "
              "(scale fitted)")
        print(f"  held-out view, new area source + sun: known-lighting BRDF {a_known:.2%}, factorized BRDF {a_fac:.2%} "
              f"(scale fitted); floor (true parameters, practical model) {a_floor:.2%}\n")
        ok &= solvers.status_name(known.status) == "converged" and solvers.status_name(fac.status) == "converged"
        report["materials"].append({
            "name": name,
            "truth": _brdf_json(truth),
            "known_lighting": {"brdf": _brdf_json(known.brdf), "std_errors": {k_: _json(getattr(known.std_errors, k_)) for k_ in ("kd", "ks", "mu", "sigma")},
                               "status": solvers.status_name(known.status), "rms": float(known.rms), "rel_rms": float(known.rel_rms),
                               "iterations": int(known.iterations), "time_s": t_known, "relight_rel_rms": e_known},
            "inverse_lighting": {"lighting": {"lmax": args.lmax, "frame": "world, +z up", "coeffs": _json(il.coeffs)},
                                 "l2_correlation": float(corr_il), "supported_lmax": _json(il.supported_lmax),
                                 "status": solvers.status_name(il.status), "rel_rms": float(il.rel_rms), "time_s": t_il},
            "unknown_lighting": {"brdf": _brdf_json(fac.brdf), "std_errors": {k_: _json(getattr(fac.std_errors, k_)) for k_ in ("kd", "ks", "mu", "sigma")},
                                 "lighting": {"lmax": args.lmax, "frame": "world, +z up", "coeffs": _json(fac.lighting.slow_sh),
                                              "directional": [{"direction": _json(fac.lighting.fast_directions[0]), "radiance": _json(fac.lighting.fast_energy[0])}]},
                                 "sigma_eq26": float(fac.source.sigma_eq26), "l2_correlation": float(corr_fac),
                                 "status": solvers.status_name(fac.status), "rms": float(fac.rms), "rel_rms": float(fac.rel_rms),
                                 "iterations": int(fac.iterations), "time_s": t_fac, "relight_rel_rms_scale_fitted": e_fac},
            "held_out_area_light": {"known_lighting_rel_rms": a_known, "factorized_rel_rms_scale_fitted": a_fac,
                                    "floor_true_parameters_rel_rms": a_floor},
        })
        images[f"{name}_input_view0"] = cap.images[0]
        images[f"{name}_factorized_view0"] = obs.to_images(np.asarray(solvers.predict(fac.brdf, fac.lighting, obs.normals, obs.views)))[0]
        h = 4 * (args.lmax + 1)
        images[f"{name}_lighting_recovered"] = np.asarray(jaxsh.synthesize_latlong(fac.filtered_sh, h, 2 * h))
        images[f"{name}_lighting_true_filtered"] = np.asarray(jaxsh.synthesize_latlong(tl, h, 2 * h))
    report["total_time_s"] = time.perf_counter() - t0
    print(f"total {report['total_time_s']:.1f} s")
    if args.out:
        from jaxsh.io import write_image

        os.makedirs(args.out, exist_ok=True)
        for name, img in images.items():
            write_image(os.path.join(args.out, name + ".exr"), img)
            write_image(os.path.join(args.out, name + ".png"), np.maximum(img, 0))
        print(f"images written to {args.out}/")
    if args.json:
        d = os.path.dirname(args.json)
        if d:
            os.makedirs(d, exist_ok=True)
        from jaxsh.io import write_json

        write_json(args.json, report)
        print(f"report written to {args.json}")
    return 0 if ok else 1


def _fit_manifests(paths) -> list[str]:
    """The manifests named on the command line: files as given, folders expanded to their `*.json` (sorted)."""
    out = []
    for p in paths:
        if os.path.isdir(p):
            found = sorted(os.path.join(p, f) for f in os.listdir(p) if f.endswith(".json"))
            if not found:
                raise ValueError(f"{p}: the folder holds no manifest (*.json)")
            out += found
        else:
            out.append(p)
    return out


def _devices_mesh(n):
    """A mesh over `n` devices for `--devices` (None: one device, no mesh). On CPU, asks JAX for `n` host devices."""
    if n is None:
        return None
    import jax

    if n < 1:
        raise ValueError(f"--devices must be >= 1, got {n}")
    try:  # the CPU backend gets `n` devices if it has not started yet (the command line's own configuration)
        jax.config.update("jax_num_cpu_devices", max(n, jax.config.jax_num_cpu_devices))
    except RuntimeError:
        pass  # already started (e.g. called from Python): use what it has
    if len(jax.devices()) < n:
        raise ValueError(f"--devices {n}: JAX sees only {len(jax.devices())} device(s) ({jax.default_backend()})")
    from ._scale import pixel_mesh

    return pixel_mesh(n)


def _fit(args) -> int:
    paths = _fit_manifests(args.manifest)
    mesh = _devices_mesh(args.devices)
    if len(paths) == 1 and not os.path.isdir(args.manifest[0]):
        return _fit_one(paths[0], args.out, mesh)
    # several manifests: one output folder per manifest, named after it, under --out
    stems = [os.path.splitext(os.path.basename(p))[0] for p in paths]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        raise ValueError(f"several manifests are named {dup[0]!r}: their outputs would collide under --out")
    rcs = []
    for p, stem in zip(paths, stems):
        print(f"{p}:")
        rcs.append(_fit_one(p, os.path.join(args.out, stem), mesh))
    print(f"{sum(rc == 0 for rc in rcs)}/{len(rcs)} fits succeeded")
    return 0 if all(rc == 0 for rc in rcs) else 1


def _fit_one(path, out, mesh) -> int:
    import jax

    from ._fit_manifest import fit_manifest

    with jax.enable_x64(True):
        result = fit_manifest(path, out, mesh=mesh)
    b = result["brdf"]
    rel = result["rel_rms"]
    print(f"status {result['status']}, relative RMS {'undefined' if rel is None else f'{rel:.4f}'}")
    if b["model"] == "rbf":
        print(f"RBF reflectance (Zickler 2006 eq. {13 if b['spatial'] else 12}), {b['n_centers']} centres: {b['file']}")
    else:
        print(f"kd {b['kd']}  ks {b['ks']}  mu {b['mu']}  sigma {b['sigma']}")
    print(f"results in {out}/")
    from ._fit_manifest import _out_names
    from ._render_manifest import stale_outputs
    from jaxsh import io as jio

    _warn_stale(out, stale_outputs(out, [os.path.join(out, f) for f in _out_names(jio.read_manifest(path))]))
    return 0 if result["status"] in ("converged", "ill_conditioned") else 1


def _warn_stale(out, stale) -> None:
    """Name the files of an earlier run that this one did not replace (they are not deleted)."""
    if stale:
        shown = ", ".join(os.path.basename(p) for p in stale[:6]) + (", ..." if len(stale) > 6 else "")
        print(f"note: {out}/ also holds {len(stale)} file(s) of an earlier run that this run did not write: {shown} "
              "(not deleted; use an empty --out folder to keep runs apart)", file=sys.stderr)


def _render(args) -> int:
    import jax

    from ._render_manifest import render_manifest

    with jax.enable_x64(True):
        written = render_manifest(args.manifest, args.out)
    print(f"wrote {len(written)} files to {args.out}/")
    from ._render_manifest import stale_outputs

    _warn_stale(args.out, stale_outputs(args.out, written))
    return 0


def cache_dir() -> str | None:
    """The persistent XLA compilation cache of the command line, or None when it is off.

    `$JAXSH_CACHE_DIR`, else `$XDG_CACHE_HOME/jaxsh/xla`, else `~/.cache/jaxsh/xla`;
    `JAXSH_NO_CACHE=1` turns it off.
    """
    if os.environ.get("JAXSH_NO_CACHE"):
        return None
    d = os.environ.get("JAXSH_CACHE_DIR")
    if not d:
        d = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "jaxsh", "xla")
    return d


def _enable_cache() -> None:
    """Turn on JAX's persistent compilation cache for this process (the command line's own configuration;
    the library never changes `jax.config`). A second run of the same command reuses the compiled programs."""
    d = cache_dir()
    if d is None:
        return
    try:
        os.makedirs(d, exist_ok=True)
    except OSError:
        return  # a read-only home: run without the cache
    if "EQX_ON_ERROR" not in os.environ:
        # XLA programs with host callbacks are never cached, and `equinox.error_if` raises through one.
        # The commands validate the manifest and every input before any work, so a run-time check cannot
        # fire on them; in "nan" mode a check that did would give NaN, which the solvers report as status
        # `nonfinite` (exit 1) — never a silent number. An explicit EQX_ON_ERROR is respected. equinox reads
        # the mode at import (the `solvers` package has imported it by now) and at each call from
        # `equinox._errors.EQX_ON_ERROR`; if that changes in a future equinox, the programs with checks are
        # simply not cached.
        os.environ["EQX_ON_ERROR"] = "nan"
        errors = sys.modules.get("equinox._errors")
        if errors is not None and getattr(errors, "EQX_ON_ERROR", None) == "raise":
            errors.EQX_ON_ERROR = "nan"
    import jax

    jax.config.update("jax_compilation_cache_dir", d)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def _one_line(e: BaseException) -> str:
    msg = " ".join(str(e).split()) or type(e).__name__
    if isinstance(e, OSError) and e.filename is not None and os.fspath(e.filename) not in msg:
        msg = f"{e.filename}: {msg}"
    return msg


def main(argv=None, *, cache: bool | None = None) -> int:
    """Run the command line. `cache` (default: on for a real command line, `argv is None`; off when called
    with an explicit `argv`, e.g. from tests) turns on the persistent compilation cache (`cache_dir`)."""
    parser = argparse.ArgumentParser(prog="jaxsh", description="Signal-processing inverse rendering in JAX.")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="run the end-to-end synthetic inverse-rendering pipeline (no input files)")
    p.add_argument("--out", help="directory for images (EXR + PNG)")
    p.add_argument("--json", help="write a JSON report here")
    p.add_argument("--size", type=int, default=64, help="image size in pixels (default 64)")
    p.add_argument("--views", type=int, default=3, help="number of views (default 3)")
    p.add_argument("--noise", type=float, default=0.01, help="noise, as a fraction of the image RMS (default 0.01)")
    p.add_argument("--lmax", type=int, default=12, help="lighting cutoff l* (default 12)")
    p.add_argument("--materials", type=int, default=len(_MATERIALS),
                   help=f"how many of the fig. 11 materials, in the order {', '.join(m[0] for m in _MATERIALS)} (1-{len(_MATERIALS)})")
    p.add_argument("--brdf-model", default="cook_torrance", choices=["cook_torrance", "ggx", "torrance_sparrow"],
                   help="the BRDF the input images are rendered with (default cook_torrance: fuller than the fitted model)")
    p.set_defaults(func=_demo)
    q = sub.add_parser("fit", help="recover what a capture manifest leaves unknown (lighting and/or BRDF)")
    q.add_argument("manifest", nargs="+", help="capture manifest(s), or folders of them (*.json)")
    q.add_argument("--out", default="fit_out", help="output directory (result.json, lighting.exr/.png, view_###); "
                   "with several manifests, one subfolder per manifest (named after it)")
    q.add_argument("--devices", type=int, default=None,
                   help="shard each fit's pixels over this many devices (on CPU: host devices; default: one device)")
    q.set_defaults(func=_fit)
    q = sub.add_parser("render", help="render every view of a manifest with given lighting and BRDF")
    q.add_argument("manifest")
    q.add_argument("--out", default="render_out", help="output directory (view_000.exr/.png, ...)")
    q.set_defaults(func=_render)
    args = parser.parse_args(argv)
    if (argv is None) if cache is None else cache:
        _enable_cache()
    # Every error is one line naming the file and the field: exit 2 for bad input (manifest, files,
    # options, --out), 1 for anything else that fails; a failed solve returns 1 from its command.
    # JAXSH_TRACEBACK=1 lets exceptions through, for debugging.
    if os.environ.get("JAXSH_TRACEBACK"):
        return args.func(args)
    try:
        return args.func(args)
    except (ValueError, OSError) as e:  # ManifestError is a ValueError
        print(f"jaxsh {args.command}: {_one_line(e)}", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - the command line shows no tracebacks
        print(f"jaxsh {args.command}: failed: {type(e).__name__}: {_one_line(e)} "
              "(set JAXSH_TRACEBACK=1 for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
