"""Multi-device checks of solvers._scale, run in a fresh process (tests/test_scale.py, benchmarks/bench_scale.py).

The number of (forced host) devices is fixed when JAX starts, so these run in a subprocess started with
`XLA_FLAGS=--xla_force_host_platform_device_count=D`. Usage:

    python tests/_scale_worker.py equal            # sharded == one-device, 3 solvers, uneven N ([perview]: one
                                                   # light per view)
    python tests/_scale_worker.py many [vmap] [sharded]  # fit_many, one degenerate member, batch sharded
    python tests/_scale_worker.py dist PORT RANK   # one of 2 jax.distributed processes
    python tests/_scale_worker.py checks           # failed run-time checks raise on every device
    python tests/_scale_worker.py kernels          # per-point kernels inside jax.shard_map (check_vma=True), and
                                                   # on sharded arrays (they stay sharded, nothing gathered)

Prints one JSON line on stdout.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np

if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

TRUTH = dict(kd=[0.3, 0.2, 0.1], ks=[0.4, 0.4, 0.4], mu=1.5, sigma=0.15)


def make_capture(size=24, n_views=2, seed=0, lmax=8, noise=0.01, scale=1.0):
    """A sphere under the demo's sources (slow SH + one directional light), imaged by the practical model + noise."""
    import jax.numpy as jnp

    import jaxsh
    import solvers

    disks, (ddir, drad) = solvers.default_sources()
    sh = sum(jaxsh.disk_light_sh(disks[0][k], disks[1][k], disks[2][k], lmax) for k in range(2))
    lighting = solvers.Lighting(jnp.asarray(sh), jnp.asarray(ddir), jnp.asarray(drad))
    brdf = solvers.TorranceSparrow(jnp.asarray(TRUTH["kd"]) * scale, jnp.asarray(TRUTH["ks"]) * scale,
                                   jnp.asarray(TRUTH["mu"]), jnp.asarray(TRUTH["sigma"]))
    rng = np.random.default_rng(seed)
    gbs, imgs = [], []
    for cam in solvers.view_cameras(n_views, size):
        gb = jaxsh.sphere_gbuffer(cam, jnp.zeros(3), jnp.asarray(1.0))
        img = np.asarray(solvers.predict(brdf, lighting, gb.normal, gb.view, mask=gb.mask))
        m = np.asarray(gb.mask)
        img = np.where(m[..., None], img + noise * np.sqrt(np.mean(img[m] ** 2)) * rng.normal(size=img.shape), 0.0)
        gbs.append(gb)
        imgs.append(img)
    return solvers.observations(gbs, imgs), lighting


def light_stage_capture(size=24, n_views=5, seed=0, noise=0.01):
    """Each view under its own directional light (photometric stereo, a light stage), no slow lighting: view k lit
    from 0.9 rad (52 degrees) off its camera, grey lights and RGB ones, one view with a second light. Returns the
    observations and the list of one `Lighting` per view."""
    import jax.numpy as jnp

    import jaxsh
    import solvers

    brdf = solvers.TorranceSparrow(jnp.asarray(TRUTH["kd"]), jnp.asarray(TRUTH["ks"]), jnp.asarray(TRUTH["mu"]),
                                   jnp.asarray(TRUTH["sigma"]))
    rng = np.random.default_rng(seed)
    gbs, imgs, lights = [], [], []
    for k, cam in enumerate(solvers.view_cameras(n_views, size)):
        gb = jaxsh.sphere_gbuffer(cam, jnp.zeros(3), jnp.asarray(1.0))
        m = np.asarray(gb.mask)
        to_cam = np.asarray(gb.view)[m].mean(0)
        side = np.cross(to_cam, [0.3, 0.5, 0.8])
        nc, ns = np.linalg.norm(to_cam), np.linalg.norm(side)
        dirs, energy = [np.cos(0.9) * to_cam / nc + np.sin(0.9) * side / ns], [[1.0, 0.9, 0.8] if k % 2 else [1.1]]
        if k == 1:
            dirs.append(np.cos(0.8) * to_cam / nc - np.sin(0.8) * side / ns)
            energy.append([0.4, 0.5, 0.6])
        lit = solvers.Lighting(None, jnp.asarray(np.array(dirs)), jnp.asarray(np.array(energy)))
        img = np.asarray(solvers.predict(brdf, lit, gb.normal, gb.view, mask=gb.mask))
        img = np.where(m[..., None], img + noise * np.sqrt(np.mean(img[m] ** 2)) * rng.normal(size=img.shape), 0.0)
        gbs.append(gb)
        imgs.append(img)
        lights.append(lit)
    return solvers.observations(gbs, imgs), lights


def uneven(obs, multiple=4):
    """`obs` with the last samples dropped until its size is NOT a multiple of `multiple`."""
    n = obs.n_samples
    if n % multiple == 0:
        obs = obs.subset(np.arange(n - 1))
    return obs


def _leaves(res):
    import jax

    out = {}
    for path, leaf in jax.tree_util.tree_leaves_with_path(res):
        a = np.asarray(leaf)
        if a.dtype.kind in "fiub":
            out[jax.tree_util.keystr(path)] = a.astype(np.float64)
    return out


_STEPS = ("num_steps", "num_mu_candidates", ".iterations")  # iteration counts: rounding can change a search's path


def compare(a, b):
    """Max over the result's leaves of |a - b| / max|b| (inf/NaN patterns must match), iteration counts apart.

    Returns `rel` (every leaf but the iteration counts), `leaf` (where it is largest) and `steps` (the leaves
    whose iteration counts differ: `[a, b]`). A different rounding of the pixel sums can move a simplex or
    Levenberg-Marquardt iterate across a stopping test one step earlier or later; the estimates still agree.
    """
    la, lb = _leaves(a), _leaves(b)
    assert la.keys() == lb.keys()
    worst, where, steps = 0.0, "", {}
    for k in la:
        x, y = la[k], lb[k]
        if x.shape != y.shape or not np.array_equal(np.isfinite(x), np.isfinite(y)):
            return {"rel": float("inf"), "leaf": k, "steps": steps}
        if any(s in k for s in _STEPS):
            if not np.array_equal(x, y):
                steps[k] = [x.tolist(), y.tolist()]
            continue
        fin = np.isfinite(y)
        if not np.array_equal(x[~fin], y[~fin], equal_nan=True):
            return {"rel": float("inf"), "leaf": k, "steps": steps}
        if not fin.any():
            continue
        scale = np.max(np.abs(y[fin]))
        d = np.max(np.abs(x[fin] - y[fin]))
        r = d / scale if scale > 0 else d
        if r > worst:
            worst, where = float(r), k
    return {"rel": worst, "leaf": where, "steps": steps}


def _status(res):
    import solvers

    return solvers.status_name(res.status)


def run_equal(which=("fit_brdf", "inverse_lighting", "factorize")):
    import equinox as eqx
    import jax

    import solvers

    jax.config.update("jax_enable_x64", True)
    obs, lighting = make_capture()
    obs = uneven(obs, len(jax.devices()))
    mesh = solvers.pixel_mesh()
    sobs = solvers.shard_observations(obs, mesh)
    out = {"devices": len(jax.devices()), "n": obs.n_samples, "n_padded": sobs.n_samples,
           "shards": len(sobs.values.sharding.device_set)}
    if "fit_brdf" in which or "inverse_lighting" in which:
        print("fit_brdf", file=sys.stderr, flush=True)
        # the search subset drawn (`search_pixels`), as on large captures
        ref = solvers.fit_brdf(obs, lighting, search_pixels=300)
        got = solvers.fit_brdf(sobs, lighting, search_pixels=300)
        out["fit_brdf_again_compiles"] = _compiled_by(lambda: solvers.fit_brdf(sobs, lighting, search_pixels=300))
        # `fitted` has a row per sample of `sobs`: the padding (weight 0, at the end) is the model at sample 0's geometry
        pad = np.asarray(got.fitted)[obs.n_samples:]
        out["fitted_padding_is_sample_0"] = bool(np.allclose(pad, np.asarray(got.fitted)[:1], rtol=1e-12, atol=0))
        got = eqx.tree_at(lambda r: r.fitted, got, got.fitted[: obs.n_samples])
        out["fit_brdf"] = dict(compare(got, ref), status=[_status(got), _status(ref)],
                               sigma=[float(got.brdf.sigma), float(ref.brdf.sigma)])
        # fit_brdf's per-pixel terms made on each device's pixels (solvers._pixel_sums.map_over_pixels)
        terms = solvers.practical_terms_for(sobs, lighting)
        out["terms_specs"] = {k: str(getattr(terms, k).sharding.spec) for k in ("bands", "irradiance", "cos_o")}
    if "inverse_lighting" in which:
        print("inverse_lighting", file=sys.stderr, flush=True)
        brdf = solvers.TorranceSparrow(ref.brdf.kd, ref.brdf.ks, ref.brdf.mu, ref.brdf.sigma)
        ref = solvers.inverse_lighting(obs, brdf, 6)
        got = solvers.inverse_lighting(sobs, brdf, 6)
        out["inverse_lighting"] = dict(compare(got, ref), status=[_status(got), _status(ref)])
        # the pixel sums on each device's pixels (solvers._pixel_sums): no per-pixel array gathered, in either form
        import jax.numpy as jnp

        from solvers import _lighting
        from solvers._pixel_sums import pixel_sharding

        c = obs.n_channels
        for lit in (False, True):
            compiled = _lighting._inverse_lighting.lower(
                sobs, jnp.broadcast_to(brdf.kd, (c,)), jnp.broadcast_to(brdf.ks, (c,)), brdf.mu, brdf.sigma, 6, True,
                0.0, 1e-12, 4096, lit, pixel_sharding(sobs.normals)).compile()
            text = compiled.compiled.as_text()
            out[f"inverse_lighting_collectives_literal_{lit}"] = [text.count("all-gather("), text.count("all-reduce(")]
    if "factorize" in which:
        out.update(_factorize_equal(obs, sobs))
    if "perview" in which:
        out["perview"] = _perview_equal(len(jax.devices()))
    return out


def _perview_equal(k):
    """`fit_brdf` of `light_stage_capture` (one lighting per view, fast sources only) on sharded pixels against one
    device, the specs of its per-pixel terms, the all-gathers of the programs of `solvers._data` it compiled, and
    those of the fit's own programs (`solvers._brdf`)."""
    import equinox as eqx
    import jax

    import solvers
    from solvers import _brdf, _data

    obs, lights = light_stage_capture()
    obs = uneven(obs, k)
    sobs = solvers.shard_observations(obs, solvers.pixel_mesh())
    # with the Levenberg-Marquardt refinement (on all samples, here as many as the simplex saw): the estimate is then
    # the minimum to rounding, not the simplex's, whose path rounding moves (92 against 95 steps, the covariance
    # 1.2e-7 apart at XLA's optimization level 0), and the refinement's steps run on sharded pixels as well
    ref = solvers.fit_brdf(obs, lights, refine=True)
    counter = _gathers_of(_data)
    with counter as gathers:
        terms = solvers.practical_terms_for(sobs, lights)
        jax.block_until_ready(terms)
    with _gathers_of(_brdf) as fit_gathers:  # the fit's own programs: the Levenberg-Marquardt QR per device (TSQR)
        got = solvers.fit_brdf(sobs, lights, refine=True)
    n = obs.n_samples
    got = eqx.tree_at(lambda r: r.fitted, got, got.fitted[:n])
    one = solvers.practical_terms_for(obs, lights)
    diff = max(float(np.max(np.abs(np.asarray(a)[:n].astype(float) - np.asarray(b).astype(float))))
               for a, b in zip(jax.tree.leaves(terms), jax.tree.leaves(one)) if np.ndim(b) and np.shape(b)[0] == n)
    return dict(compare(got, ref), status=[_status(got), _status(ref)], sigma=[float(got.brdf.sigma), float(ref.brdf.sigma)],
                lm_steps=[int(got.stats["num_steps_lm"]), int(ref.stats["num_steps_lm"])],
                cov_cond=float(np.linalg.cond(np.asarray(ref.covariance))),
                rest=compare(eqx.tree_at(lambda r: r.covariance, got, ref.covariance), ref),
                terms_specs={f: str(getattr(terms, f).sharding.spec) for f in ("irradiance", "theta_h", "fast_weight", "cos_o")},
                terms_diff=diff, gathers=gathers, compiled=sorted({sig[0] for sig in counter.seen}), views=len(lights), n=n,
                fit_gathers=fit_gathers)


def _compiled_by(call):
    """The names of the programs XLA compiled during `call()` (a second call on sharded pixels: none; an eager
    `jax.shard_map` of a new closure compiled again at every call)."""
    import jax

    from tests.helpers import Compiles

    with Compiles() as c:
        jax.block_until_ready(jax.tree_util.tree_leaves(call()))
    return c.names


def _factorize_equal(obs, sobs):
    """`factorize` on the sharded `sobs` against one device, with the search subset drawn (as on large captures), in
    the default form and in those that take other paths over all pixels (stage 1's mu, stage 1's model as the
    result, no Fresnel); the all-gathers of every program it compiled; and its all-pixel pass alone, sharded against one
    device."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import solvers
    from solvers import _factorize
    from solvers._pixel_sums import pixel_sharding

    out = {}
    with _gathers_of(_factorize) as gathers:
        for name, kw in (("factorize", {}), ("factorize_mu_stage1", {"refine_mu": False}),
                         ("factorize_stage1", {"refine": False}), ("factorize_metal", {"fresnel": False})):
            print(name, file=sys.stderr, flush=True)
            ref = solvers.factorize(obs, 6, search_pixels=300, **kw)
            got = solvers.factorize(sobs, 6, search_pixels=300, **kw)
            if not kw:
                out["factorize_again_compiles"] = _compiled_by(lambda: solvers.factorize(sobs, 6, search_pixels=300))
            spec = str(got.fitted.sharding.spec)
            got = eqx.tree_at(lambda r: r.fitted, got, got.fitted[: obs.n_samples])  # a row per sample of `sobs`
            out[name] = dict(compare(got, ref), status=[_status(got), _status(ref)], fitted_spec=spec)
    out["factorize_gathers"] = gathers
    # the pass over all pixels alone: each device's blocks summed, its rows left on it, in the pixels' order
    where = pixel_sharding(sobs.normals)
    mu = jnp.asarray(1.5)
    bl, (rd, rs), _ = _factorize._all_pixel_blocks(sobs, mu, 6, 64, 1e-12, True, where=where)
    bl1, (rd1, rs1), _ = _factorize._all_pixel_blocks(obs, mu, 6, 64, 1e-12, True)
    n = obs.n_samples
    out["pass_rows_specs"] = [str(rd.sharding.spec), str(rs.sharding.spec)]
    out["pass_rows_shapes"] = [list(rd.shape), list(rs.shape)]
    out["pass_rows_rel"] = max(float(np.max(np.abs(np.asarray(a)[:, :n] - np.asarray(b)[:, :n])) / np.max(np.abs(np.asarray(b))))
                               for a, b in ((rd, rd1), (rs, rs1)))
    # the padding sample of `sobs` (weight 0, after the n samples) adds nothing to the blocks
    out["pass_blocks_rel"] = compare(bl.g, bl1.g)["rel"]  # (not `h22`: an eigenvector's sign is arbitrary)
    return out


class _gathers_of:
    """Within the block, every jitted program of `module` (`jaxsh.jit`) is also compiled once per signature to
    count its all-gathers (XLA's compiled text): the dict `{name: [all-gathered shapes]}` of those with any."""

    def __init__(self, module):
        self.module, self.saved, self.found, self.seen = module, {}, {}, set()

    def __enter__(self):
        import re

        import jax

        import jaxsh

        for name in dir(self.module):
            fn = getattr(self.module, name)
            if not isinstance(fn, jaxsh._compile._LazyJit):
                continue
            self.saved[name] = fn

            def counted(*a, _fn=fn, _name=name, **k):
                sig = (_name, tuple((x.shape, str(x.dtype), str(getattr(x, "sharding", ""))) if hasattr(x, "dtype")
                                    else repr(x) for x in jax.tree_util.tree_leaves((a, k))))
                if sig not in self.seen:
                    self.seen.add(sig)
                    text = _fn.lower(*a, **k).compile().compiled.as_text()
                    shapes = re.findall(r"= (\S+) all-gather\(", text)
                    if shapes:
                        self.found.setdefault(_name, []).extend(shapes)
                return _fn(*a, **k)

            setattr(self.module, name, counted)
        return self.found

    def __exit__(self, *exc):
        for name, fn in self.saved.items():
            setattr(self.module, name, fn)
        return False


def many_captures(views=(1, 2, 1, 1, 2, 1, 1, 2, 1), size=12, degenerate=2):
    """Captures of `size` px and 1 or 2 views (two sample counts; different seeds and scales); member `degenerate` black."""
    import jax.numpy as jnp

    import solvers

    caps = []
    for i, nv in enumerate(views):
        obs, lit = make_capture(size=size, n_views=nv, seed=i, scale=1.0 + 0.1 * i)
        if i == degenerate:
            obs = solvers.Observations(obs.normals, obs.views, jnp.zeros_like(obs.values), obs.weights, obs.transfer,
                                       obs.fast_visibility, obs.reflected_visibility, obs.texel, obs.view_index,
                                       obs.pixel_index, obs.image_shapes, obs.n_texels)
        caps.append((obs, lit))
    return caps


def run_many(which=("vmap", "sharded")):
    """`fit_many` of `many_captures()` (one bucket of 256: 3 members per device on 4) against each `fit_brdf`."""
    import jax

    import solvers

    jax.config.update("jax_enable_x64", True)
    caps = many_captures()
    out = {"devices": len(jax.devices()), "n": [o.n_samples for o, _ in caps]}
    singles = [solvers.fit_brdf(o, lit) for o, lit in caps]
    out["status_single"] = [_status(r) for r in singles]
    out["sigma_single"] = [float(r.brdf.sigma) for r in singles]
    for name in which:
        print(name, file=sys.stderr, flush=True)
        mesh = solvers.pixel_mesh(axis="batch") if name == "sharded" else None
        got = solvers.fit_many(caps, mesh=mesh)
        out[f"status_{name}"] = [_status(r) for r in got]
        cmp = [compare(a, b) for a, b in zip(got, singles)]
        out[f"{name}_vs_single"] = [c["rel"] for c in cmp]
        out[f"{name}_steps_differ"] = [c["steps"] for c in cmp]
    out["sigma"] = [float(r.brdf.sigma) for r in got]
    return out


def run_dist(port: int, rank: int):
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.distributed.initialize(coordinator_address=f"localhost:{port}", num_processes=2, process_id=rank,
                               initialization_timeout=60)
    import solvers

    obs, lighting = make_capture()
    obs = uneven(obs, 2)
    mesh = solvers.pixel_mesh()  # every process's devices
    sobs = solvers.shard_observations(obs, mesh)
    fit = solvers.fit_brdf(sobs, lighting, search_pixels=300)  # the search subset drawn across processes
    il = solvers.inverse_lighting(sobs, fit.brdf, 6)
    out = {"rank": rank, "processes": jax.process_count(), "global_devices": len(jax.devices()),
           "local_devices": len(jax.local_devices()), "status": [_status(fit), _status(il)],
           "kd": np.asarray(fit.brdf.kd).tolist(), "ks": np.asarray(fit.brdf.ks).tolist(),
           "mu": float(fit.brdf.mu), "sigma": float(fit.brdf.sigma), "rms": float(fit.rms),
           "coeffs": np.asarray(il.coeffs).ravel().tolist(), "il_rms": float(il.rms)}
    # fit_many with its batch sharded across the processes (one member per process, the second one black): every
    # process gets every capture's result (the batch's shards gathered), each its own fit_brdf in this process
    caps = many_captures(views=(1, 1), size=10, degenerate=1)
    many = solvers.fit_many(caps, mesh=solvers.pixel_mesh(axis="batch"))
    single = [solvers.fit_brdf(o, lit) for o, lit in caps]
    out["many_status"] = [_status(r) for r in many]
    out["many_status_single"] = [_status(r) for r in single]
    out["many_vs_single"] = [compare(a, b)["rel"] for a, b in zip(many, single)]
    jax.distributed.shutdown()
    return out


def run_single_reference():
    """The one-process, one-device answer of `run_dist`."""
    import jax

    import solvers

    jax.config.update("jax_enable_x64", True)
    obs, lighting = make_capture()
    obs = uneven(obs, 2)
    fit = solvers.fit_brdf(obs, lighting, search_pixels=300)
    il = solvers.inverse_lighting(obs, fit.brdf, 6)
    return {"kd": np.asarray(fit.brdf.kd).tolist(), "ks": np.asarray(fit.brdf.ks).tolist(), "mu": float(fit.brdf.mu),
            "sigma": float(fit.brdf.sigma), "rms": float(fit.rms), "coeffs": np.asarray(il.coeffs).ravel().tolist(),
            "il_rms": float(il.rms)}


def run_top():
    """jaxsh's per-point kernels called on sharded arrays (`jax.device_put` with the points split over the devices),
    outside any `jit`: each output's sharding spec, its largest difference from the same call on host arrays (one
    device), and the all-gathers of every program they compiled (`_gathers_of`)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import NamedSharding, PartitionSpec as P

    import jaxsh
    from jaxsh import _practical, _render, _sh
    from solvers import pixel_mesh

    jax.config.update("jax_enable_x64", True)
    mesh = pixel_mesh()
    k = len(jax.devices())
    n = 300 * k  # not a render bucket: render_practical would pad it on the host
    rng = np.random.default_rng(2)

    def unit(a):
        return a / np.linalg.norm(a, axis=-1, keepdims=True)

    normals = unit(rng.normal(size=(n, 3)) + [0.0, 0.0, 2.0])
    views = unit(rng.normal(size=(n, 3)) + [0.0, 0.0, 2.0])
    kd = rng.uniform(0.1, 0.5, size=(n, 3))
    mask = rng.uniform(size=n) > 0.1
    sky = np.r_[[[1.0, 0.9, 0.8]], 0.1 * rng.normal(size=(80, 3))]
    light = jaxsh.Lighting(slow_sh=sky, fast_directions=[[0.3, 0.2, 0.9]], fast_energy=[[2.0, 2.0, 2.0]])
    brdf = jaxsh.TorranceSparrow(kd=kd, ks=[0.4, 0.4, 0.4], mu=1.5, sigma=0.2)
    rows = NamedSharding(mesh, P("pixels", None))
    sn, sv = jax.device_put(normals, rows), jax.device_put(views, rows)
    calls = {
        "real_sh": lambda a, b, m: jaxsh.real_sh(a, 12),
        "real_sh_coeffs_first": lambda a, b, m: jaxsh.real_sh(a, 12, coeffs_first=True),
        "complex_sh": lambda a, b, m: jaxsh.complex_sh(a, 8),
        "practical_terms": lambda a, b, m: [x for x in jax.tree.leaves(jaxsh.practical_terms(a, b, light))
                                            if x.ndim and x.shape[0] == n and x.dtype != bool],
        "render_practical": lambda a, b, m: list(jaxsh.render_practical(a, b, brdf, light, mask=m)),
    }
    out = {"devices": k}
    with _gathers_of(_sh) as g1, _gathers_of(_practical) as g2, _gathers_of(_render) as g3:
        for name, f in calls.items():
            got = jax.tree.leaves(f(sn, sv, jax.device_put(mask, NamedSharding(mesh, P("pixels")))))
            ref = jax.tree.leaves(f(normals, views, mask))
            out[name] = {"specs": sorted({str(getattr(x.sharding, "spec", type(x.sharding).__name__)) for x in got}),
                         "err": max(float(np.max(np.abs(np.asarray(a) - np.asarray(b)))) for a, b in zip(got, ref))}
    out["gathers"] = {**g1, **g2, **g3}
    return out


def run_kernels():
    """jaxsh's per-point kernels inside `jax.shard_map` with its default `check_vma=True`, against the same call on
    one device: the largest absolute difference per kernel, or the error's first line. The loops' carries must
    vary over the devices as the loops' outputs do; constants as initial carries were a trace-time `TypeError`."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import PartitionSpec as P

    import jaxsh
    from solvers import pixel_mesh

    jax.config.update("jax_enable_x64", True)
    mesh = pixel_mesh()
    n = 64 * len(jax.devices())
    rng = np.random.default_rng(1)

    def unit(a):
        return a / np.linalg.norm(a, axis=-1, keepdims=True)

    normals = unit(rng.normal(size=(n, 3)) + [0.0, 0.0, 2.0])
    views = unit(rng.normal(size=(n, 3)) + [0.0, 0.0, 2.0])
    sky = np.r_[[[1.0, 0.9, 0.8]], 0.1 * rng.normal(size=(80, 3))]
    light = jaxsh.Lighting(slow_sh=sky, fast_directions=[[0.3, 0.2, 0.9]], fast_energy=[[2.0, 2.0, 2.0]])
    brdf = jaxsh.TorranceSparrow(kd=[0.3, 0.2, 0.1], ks=[0.4, 0.4, 0.4], mu=1.5, sigma=0.2)
    centers = rng.normal(size=(20, 3))
    kernels = {
        "real_sh": lambda a, b: jaxsh.real_sh(a, 12),
        "real_sh_float32": lambda a, b: jaxsh.real_sh(a.astype(jnp.float32), 12),
        "real_sh_coeffs_first": lambda a, b: jaxsh.real_sh(a, 12, coeffs_first=True).T,
        "complex_sh": lambda a, b: jnp.abs(jaxsh.complex_sh(a, 8)),
        "render_practical": lambda a, b: jaxsh.render_practical(a, b, brdf, light),
        "practical_terms": lambda a, b: [x for x in jax.tree.leaves(jaxsh.practical_terms(a, b, light))
                                         if x.ndim and x.shape[0] == a.shape[0]],
        "irradiance": lambda a, b: jaxsh.irradiance(sky[:9], a),
        "torrance_sparrow": lambda a, b: jaxsh.torrance_sparrow(b, b, a, 0.3, 0.4, 1.5, 0.2),
        "rbf_evaluate": lambda a, b: jaxsh.rbf_evaluate(centers, sky[:20], sky[20:24], a),
    }
    out = {"devices": len(jax.devices())}
    for name, f in kernels.items():
        g = jax.jit(jax.shard_map(f, mesh=mesh, in_specs=(P("pixels", None), P("pixels", None)),
                                  out_specs=P("pixels")))
        try:
            got = jax.tree.leaves(g(normals, views))
        except Exception as e:  # noqa: BLE001 - reported, and the test fails on it
            out[name] = f"{type(e).__name__}: {str(e).splitlines()[0]}"
            continue
        ref = jax.tree.leaves(f(normals, views))
        out[name] = max(float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))
                        for a, b in zip(got, ref))
    return out


def run_checks():
    """A failed run-time check on several devices: raised as `equinox.EquinoxRuntimeError`, not a process abort.

    Each case is timed: equinox's own route (one device raises, the others wait in the next collective) ended in
    XLA's abort after its 40 s rendezvous timeout, so a case that returns at all, quickly, with the message, is
    the check. With `EQX_ON_ERROR=nan` in the environment the same calls return NaN instead."""
    import time

    import equinox as eqx
    import jax
    import jax.numpy as jnp
    from jax.sharding import NamedSharding, PartitionSpec as P

    import jaxsh
    from solvers import pixel_mesh

    jax.config.update("jax_enable_x64", True)
    mesh = pixel_mesh()
    rows = NamedSharding(mesh, P("pixels", None))
    flat = NamedSharding(mesh, P("pixels"))
    n = 256 * len(jax.devices())
    dirs = np.random.default_rng(0).normal(size=(n, 3))
    bad_dirs = dirs.copy()
    bad_dirs[n - 3] = 0.0  # on the last device only

    def total(f):  # a collective after the check: where the other devices used to wait
        return eqx.filter_jit(lambda *a: jnp.sum(f(*a)))

    sh = total(lambda d: jaxsh.real_sh(d, 4))
    mapped = total(jax.shard_map(lambda d: jaxsh.real_sh(d, 4), mesh=mesh, in_specs=P("pixels", None),
                                 out_specs=P("pixels", None), check_vma=False))
    vmapped = total(jax.vmap(lambda v: jaxsh.error_if(v, v == 7.0, "no sevens")))
    integers = total(lambda v: jaxsh.error_if(v, v == 7, "no sevens"))
    values = np.arange(n, dtype=np.float64).reshape(-1, 4) + 10.0
    cases = {
        "real_sh": (sh, (jax.device_put(dirs, rows),), (jax.device_put(bad_dirs, rows),), "zero-length"),
        "shard_map": (mapped, (jax.device_put(dirs, rows),), (jax.device_put(bad_dirs, rows),), "zero-length"),
        "vmap": (vmapped, (jax.device_put(values, rows),), (jax.device_put(np.where(values == n + 5.0, 7.0, values),
                                                                             rows),), "no sevens"),
        "integers": (integers, (jax.device_put(np.arange(8, 8 + n), flat),),
                     (jax.device_put(np.arange(n) + 7 * (np.arange(n) == n - 2), flat),), "no sevens"),
    }
    out = {"devices": len(jax.devices()), "effects": bool(jax.make_jaxpr(lambda d: jaxsh.real_sh(d, 4))(dirs).effects)}
    for name, (f, good, bad, text) in cases.items():
        ok = float(f(*good))
        t = time.perf_counter()
        try:
            r = float(f(*bad))
            raised = None
        except eqx.EquinoxRuntimeError as e:
            r, raised = None, ("EquinoxRuntimeError", text in str(e))
        except Exception as e:  # noqa: BLE001 - reported, and the test fails on it
            r, raised = None, (type(e).__name__, text in str(e))
        out[name] = {"good": ok, "bad": r, "raised": raised, "seconds": time.perf_counter() - t,
                     "good_again": float(f(*good))}
    x = jax.device_put(np.array([-0.0, 0.0, 1.5, -np.inf, np.inf, np.nan, 1e-310, -3.0] * (n // 8)), flat)
    y = jax.jit(lambda v: jaxsh.error_if(v, v == 7.0, "no sevens"))(x)
    out["bits_equal"] = bool(np.array_equal(np.asarray(y).view(np.uint64), np.asarray(x).view(np.uint64)))
    out["sharding_kept"] = str(y.sharding.spec) == str(P("pixels"))
    return out


if __name__ == "__main__":
    mode = sys.argv[1]
    if mode == "equal":
        res = run_equal(sys.argv[2:] or ("fit_brdf", "inverse_lighting", "factorize"))
    elif mode == "many":
        res = run_many(sys.argv[2:] or ("vmap", "sharded"))
    elif mode == "dist":
        res = run_dist(int(sys.argv[2]), int(sys.argv[3]))
    elif mode == "kernels":  # both in one process: one JAX start
        res = {"inside": run_kernels(), "top": run_top()}
    elif mode == "checks":
        res = run_checks()
    elif mode == "single":
        res = run_single_reference()
    else:
        raise SystemExit(f"unknown mode {mode!r}")
    print(json.dumps(res))
