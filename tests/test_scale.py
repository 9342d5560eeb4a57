"""Scale-out (solvers._scale): pixel-sharded solvers, batched fits, several processes, the CLI's --devices.

JAX fixes its device count when it starts, and this process already runs with one CPU device, so the
multi-device checks run `tests/_scale_worker.py` in a subprocess with
`XLA_FLAGS=--xla_force_host_platform_device_count=4` and assert on its JSON output. The reference of
each sharded result is the same solver on one device (itself tested against closed forms elsewhere).
"""

import json
import math
import os
import re
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers
from solvers.cli import main

from .helpers import Compiles

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
WORKER = os.path.join(HERE, "_scale_worker.py")
TOL = 1e-10  # float64, relative to each result leaf's largest entry
# the iterative fits (simplex + Levenberg-Marquardt) agree only to their stopping tolerances (rtol = atol = 1e-8 in
# float64): rounding of the reordered sums moves the iterates (measured up to 1.1e-8, also with equal step counts)
STOP_TOL = 1e-7


def _agrees(rel, steps_differ):
    del steps_differ  # reported by the worker; equal step counts do not imply rounding-level agreement (measured)
    return rel < STOP_TOL


def _env(devices=None):
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "force_host_platform_device_count" not in f]
    if devices:
        flags.append(f"--xla_force_host_platform_device_count={devices}")
    env["XLA_FLAGS"] = " ".join(flags)
    env["JAX_PLATFORMS"] = "cpu"
    return env


def _worker(*args, devices=4, timeout=600, env=None):
    p = subprocess.run([sys.executable, WORKER, *map(str, args)], env=dict(_env(devices), **(env or {})),
                       capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stderr[-3000:]
    # a per-pixel array routed through one device: XLA's partitioner logs this when an operation it cannot split (the
    # host callback of a run-time check, `equinox.error_if`) holds a sharded array (jaxsh._checks.error_if_any)
    assert "Involuntary full rematerialization" not in p.stderr, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


def test_sharded_solvers_equal_one_device_with_uneven_pixels():
    r = _worker("equal", "fit_brdf", "inverse_lighting", "perview")
    assert r["devices"] == 4 and r["shards"] == 4
    assert r["n"] % 4 != 0 and r["n_padded"] % 4 == 0 and r["n_padded"] - r["n"] < 4
    for name in ("fit_brdf", "inverse_lighting"):
        got = r[name]
        assert got["status"][0] == got["status"][1] == "converged", (name, got)
        # every leaf (estimate, std errors, rms, n_obs, ...) but the iteration counts, which rounding may shift
        assert _agrees(got["rel"], got["steps"]), (name, got)
    assert r["inverse_lighting"]["rel"] < TOL  # a direct solve: rounding only
    # its pixel sums run on each device's pixels: no per-pixel array gathered (10 and 14 all-gathers when XLA's
    # partitioner split the chunk loops itself), the sums added by a few all-reduces
    for lit in (False, True):
        gathers, reduces = r[f"inverse_lighting_collectives_literal_{lit}"]
        assert gathers == 0 and 1 <= reduces <= 4, (lit, gathers, reduces)
    assert abs(r["fit_brdf"]["sigma"][1] - 0.15) < 0.01  # a real fit, not a trivial one
    # the band table (N, C, lmax+1) was replicated on every device when XLA's partitioner split its chunk loop
    assert set(r["terms_specs"].values()) == {"P('pixels',)"}, r["terms_specs"]
    # a second sharded fit compiles nothing (its per-pixel terms, an eager `shard_map` of a new closure, were compiled
    # again at every call: 1.1 s warm against 0.03 s, 3,008 pixels on 2 devices)
    assert r["fit_brdf_again_compiles"] == [], r["fit_brdf_again_compiles"]
    assert r["fitted_padding_is_sample_0"]  # `fitted` of the padded samples: sample 0's geometry (compared above: the rest)
    # one light per view, no slow lighting (a light stage): the terms made on each device's pixels from each pixel's
    # own view's sources, and kept there (the per-view path made them view by view on one device and replicated
    # them: P() on every field)
    pv = r["perview"]
    assert pv["views"] == 5 and pv["n"] % 4 != 0
    assert pv["status"][0] == pv["status"][1] == "converged" and _agrees(pv["rel"], pv["steps"]), pv
    assert pv["lm_steps"][0] >= 1 and pv["lm_steps"][1] >= 1  # the refinement ran, on the sharded pixels too
    assert abs(pv["sigma"][1] - 0.15) < 0.01  # a real fit
    assert set(pv["terms_specs"].values()) == {"P('pixels',)"}, pv["terms_specs"]
    assert pv["terms_diff"] < 1e-14 and pv["gathers"] == {} and "_fast_terms_jit" in pv["compiled"], pv
    # the fit gathers no per-sample array: the Levenberg-Marquardt QR factors each device's rows and gathers the
    # (devices x 3, 3) factors (before: the (N C,) residual at every step and the (N C + 2, 3) [J | r] at every
    # accepted step, 5,640 and 16,926 entries here)
    sizes = [math.prod(int(d) for d in re.match(r"\w+\[([\d,]*)\]", shape).group(1).split(",") if d)
             for shapes in pv["fit_gathers"].values() for shape in shapes]
    assert "_fit_brdf" in pv["fit_gathers"] and max(sizes) <= 4 * 3 * 3 < pv["n"], pv["fit_gathers"]


# factorize's stage 1 finds K_s by golden section and mu by a parabola through RSS values: a minimizer located
# from function values is resolved only to ~sqrt(eps) = 1.5e-8 (relative) when the rounding of the sums changes,
# and the lighting, the source found in it and its background inherit that, amplified (measured on 4 forced
# devices: brdf 3e-8 to 8e-8, the lighting 1.5e-7, the source background 2.8e-7; unchanged with 1e-11 stopping
# tolerances for the refinement). The inverse lighting at these parameters is well conditioned (singular
# values within 4x), so the spread is the minimizers', not an ill-conditioned solve's.
MINIMIZER_TOL = 1e-6


# Not marked slow (35 s here, four forms of factorize): it also guards against a deadlock. A batched CPU `eigh` (the mu rounds'
# pseudo-inverses) hung this process on 4 forced host devices until `pinv_psd` sent stacks through `eigh_stack`.
def test_sharded_factorize_equals_one_device():
    r = _worker("equal", "factorize", timeout=300)
    for name in ("factorize", "factorize_mu_stage1", "factorize_stage1", "factorize_metal"):
        assert r[name]["status"][0] == r[name]["status"][1] == "converged", (name, r[name])
        assert r[name]["rel"] < MINIMIZER_TOL, (name, r[name])
        assert r[name]["fitted_spec"] == "P('pixels',)", (name, r[name])  # the model at each pixel, where it is
    # the passes over all pixels run on each device's pixels: no program of factorize gathers a per-pixel array (with
    # the sharded branch switched off, as before, this finds 29 all-gathers in 5 programs: the all-pixel pass, the
    # refinement's pixels in `_subset_first`'s order, stage 1's direct sums and model, the rows without a table)
    assert r["factorize_gathers"] == {}, r["factorize_gathers"]
    assert r["factorize_again_compiles"] == [], r["factorize_again_compiles"]  # a second call compiles nothing
    # the pass alone: the blocks summed over the devices, every pixel's rows on its device, in the pixels' order
    assert r["pass_rows_specs"] == ["P(None, 'pixels')"] * 2, r["pass_rows_specs"]
    assert r["pass_rows_shapes"] == [[9, r["n_padded"]], [49, r["n_padded"]]], r["pass_rows_shapes"]
    assert r["pass_rows_rel"] < 1e-13 and r["pass_blocks_rel"] < 1e-13, (r["pass_rows_rel"], r["pass_blocks_rel"])


def test_fit_many_one_degenerate_member_vmapped_and_sharded_batch():
    r = _worker("many", "vmap", "sharded")
    assert r["devices"] == 4 and len(set(r["n"])) == 2 and max(r["n"]) <= 256  # two sizes, one bucket
    single = r["status_single"]
    others = [k for k in range(len(single)) if k != 2]
    assert single[2] == "no_signal"  # the all-zero member
    assert [single[k] for k in others] == ["converged"] * len(others)
    assert r["status_vmap"] == single and r["status_sharded"] == single
    for k in others:  # the others are unaffected: each equals its own fit_brdf (the padding reorders the sums)
        assert _agrees(r["vmap_vs_single"][k], r["vmap_steps_differ"][k]), r
        assert _agrees(r["sharded_vs_single"][k], r["sharded_steps_differ"][k]), r
        assert abs(r["sigma_single"][k] - 0.15) < 0.02


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


# Marked slow (45 s of the CI suite's 14 on 2 cores: three JAX processes, each compiling the fits): `make test-all`
# runs it. The CI suite keeps the sharded solvers on 4 forced devices and fit_many's sharded batch (above).
@pytest.mark.slow
def test_two_processes_agree_with_one():
    ref = _worker("single", devices=1)
    port = _free_port()
    procs = [subprocess.Popen([sys.executable, WORKER, "dist", str(port), str(rank)], env=_env(1),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for rank in range(2)]
    outs = []
    for p in procs:
        try:
            so, se = p.communicate(timeout=180)
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            pytest.skip("the jax.distributed runtime did not finish within 180 s on localhost")
        outs.append((p.returncode, so, se))
    if any(rc != 0 for rc, _, _ in outs):
        err = " ".join(se[-400:] for _, _, se in outs)
        if any(k in err for k in ("initialize", "oordination", "DEADLINE", "UNAVAILABLE", "Gloo", "collectives")):
            pytest.skip(f"the jax.distributed runtime could not start on localhost: {err[-300:]}")
        raise AssertionError(err)
    res = [json.loads(so.strip().splitlines()[-1]) for _, so, _ in outs]
    for r in res:
        assert r["processes"] == 2 and r["global_devices"] == 2 and r["local_devices"] == 1
        assert r["status"] == ["converged", "converged"]
        for key in ("kd", "ks", "mu", "sigma", "rms", "coeffs", "il_rms"):  # all downstream of the iterative fit_brdf
            a, b = np.asarray(r[key]), np.asarray(ref[key])
            assert np.max(np.abs(a - b)) <= STOP_TOL * np.max(np.abs(b)), key
    assert res[0]["coeffs"] == res[1]["coeffs"]  # both processes hold the same (replicated) answer
    for r in res:  # fit_many, its batch sharded over the processes: every result readable in every process
        assert r["many_status"] == r["many_status_single"] == ["converged", "no_signal"], r
        assert max(r["many_vs_single"]) < STOP_TOL, r  # each member its own fit_brdf (the padding reorders sums)


def test_pad_observations_adds_weightless_finite_samples():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    obs = solvers.Observations(jnp.asarray(n), jnp.asarray(n), jnp.asarray(rng.random((5, 3))), jnp.ones(5), None, None,
                               None, None, jnp.zeros(5, jnp.int32), jnp.arange(5), ((1, 5),))
    p = solvers.pad_observations(obs, 4)
    assert p.n_samples == 8
    np.testing.assert_array_equal(np.asarray(p.weights), [1, 1, 1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(np.asarray(p.values)[5:], 0.0)
    np.testing.assert_array_equal(np.asarray(p.normals)[5:], np.broadcast_to(n[0], (3, 3)))  # a valid unit normal
    assert solvers.pad_observations(obs, 5) is obs
    with pytest.raises(ValueError, match="`size`"):
        solvers.pad_observations(obs, size=3)
    with pytest.raises(ValueError, match="`axis`"):
        solvers.shard_observations(obs, solvers.pixel_mesh(1), axis="batch")
    with pytest.raises(ValueError, match="`captures`"):
        solvers.fit_many([])


def _sphere_obs(radius, size=24, seed=0):
    """Two orthographic views of a Torrance-Sparrow sphere under a directional source (practical model)."""
    cams = solvers.view_cameras(2, size)
    gbs = [jaxsh.sphere_gbuffer(c, jnp.zeros(3), jnp.asarray(radius)) for c in cams]
    brdf = solvers.TorranceSparrow(jnp.asarray([0.5, 0.4, 0.3]), jnp.asarray([0.3, 0.3, 0.3]), jnp.asarray(1.6),
                                   jnp.asarray(0.15))
    light = solvers.Lighting(jnp.zeros((16, 3)).at[0].set(0.8), jnp.asarray([[0.3, 0.4, 0.866]]),
                             jnp.asarray([[2.0, 2.0, 2.0]]))
    rng = np.random.default_rng(seed)
    imgs = [np.asarray(solvers.predict(brdf, light, g.normal, g.view, mask=g.mask)) * (1 + 0.01 * rng.normal(size=(size, size, 1)))
            for g in gbs]
    return solvers.observations(gbs, imgs), light


def test_size_buckets_and_host_padding():
    from solvers._scale import _size_bucket

    for n in [0, 1, 1023, 1024]:
        assert _size_bucket(n) == 1024
    for lo in (1024, 65536):  # four buckets an octave (multiples of lo / 4)
        assert sorted({_size_bucket(n) for n in range(lo + 1, 2 * lo + 1)}) == [lo + lo // 4 * j for j in range(1, 5)]
    for n in [1025, 1500, 2047, 2049, 4097, 10**5 + 1, 127_584, 10**6]:
        b = _size_bucket(n)
        assert n <= b < 1.25 * n and _size_bucket(b) == b
    obs, _ = _sphere_obs(1.0)
    small, _ = _sphere_obs(0.95)
    assert small.n_samples < obs.n_samples
    p = solvers.pad_observations(obs, bucket=True)
    assert p.n_samples == _size_bucket(obs.n_samples) > obs.n_samples
    np.testing.assert_array_equal(np.asarray(p.weights)[obs.n_samples:], 0.0)
    np.testing.assert_array_equal(np.asarray(p.values)[obs.n_samples:], 0.0)
    np.testing.assert_array_equal(np.asarray(p.normals)[obs.n_samples:], np.broadcast_to(np.asarray(obs.normals)[0], (p.n_samples - obs.n_samples, 3)))
    np.testing.assert_array_equal(np.asarray(p.normals)[: obs.n_samples], np.asarray(obs.normals))
    assert isinstance(p.values, jax.Array) and p.values.dtype == obs.values.dtype
    # on the host: another sample count compiles nothing
    with Compiles() as c:
        q = solvers.pad_observations(small, bucket=True)
    assert c.names == [] and q.n_samples == _size_bucket(small.n_samples)
    assert solvers.pad_observations(p, bucket=True) is p  # a bucket size is its own bucket
    # float32 observations stay float32 (and int index arrays int)
    o32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, small)
    q32 = solvers.pad_observations(o32, bucket=True)
    assert q32.values.dtype == q32.normals.dtype == jnp.float32 and q32.view_index.dtype == small.view_index.dtype
    np.testing.assert_array_equal(np.asarray(q32.values)[: small.n_samples], np.asarray(o32.values))
    # arrays committed to a device go back to it (on a GPU machine, CPU-placed observations stay on the CPU);
    # uncommitted ones stay uncommitted (the default device)
    cpu = jax.devices("cpu")[0]
    on_cpu = solvers.pad_observations(jax.device_put(small, cpu), bucket=True)
    assert on_cpu.values.committed and on_cpu.values.devices() == {cpu} and on_cpu.normals.committed
    assert not q.values.committed and q.values.devices() == {jax.devices()[0]}
    np.testing.assert_array_equal(np.asarray(on_cpu.normals), np.asarray(q.normals))
    with pytest.raises(ValueError, match="`size` or `bucket=True`"):
        solvers.pad_observations(obs, size=p.n_samples, bucket=True)
    with pytest.raises(ValueError, match="`bucket` must be True or False"):
        solvers.pad_observations(obs, bucket="yes")


def test_captures_in_one_bucket_share_the_fits_programs():
    """Padded to their bucket, captures of different sample counts reuse `fit_brdf`'s and `factorize`'s compiled
    programs, and each padded fit is its unpadded fit (to the stopping tolerances: the sums are regrouped)."""
    from solvers._scale import _size_bucket

    obs_a, light = _sphere_obs(1.0)
    obs_b, _ = _sphere_obs(0.97, seed=1)
    assert obs_a.n_samples != obs_b.n_samples
    assert _size_bucket(obs_a.n_samples) == _size_bucket(obs_b.n_samples)
    pa, pb = (solvers.pad_observations(o, bucket=True) for o in (obs_a, obs_b))
    with Compiles() as c0:  # the first capture compiles the fits (so that the check below is not vacuous)
        jax.block_until_ready(solvers.fit_brdf(pa, light).brdf.kd)
        jax.block_until_ready(solvers.factorize(pa, 6).brdf.kd)
    assert any("_fit_brdf" in n for n in c0.names) and any("_refine_search" in n for n in c0.names), c0.names
    with Compiles() as c:
        fb = solvers.fit_brdf(pb, light)
        fz = solvers.factorize(pb, 6)
        jax.block_until_ready((fb.brdf.kd, fz.brdf.kd))
    assert c.names == []
    ref_b = solvers.fit_brdf(obs_b, light)
    ref_z = solvers.factorize(obs_b, 6)
    # fit_brdf to its stopping tolerances, factorize to its minimizers' resolution (see MINIMIZER_TOL)
    for r, ref, tol in ((fb, ref_b, STOP_TOL), (fz, ref_z, MINIMIZER_TOL)):
        assert solvers.status_name(r.status) == solvers.status_name(ref.status) == "converged"
        for k in ("kd", "ks", "mu", "sigma"):
            a, b = np.asarray(getattr(r.brdf, k)), np.asarray(getattr(ref.brdf, k))
            assert np.max(np.abs(a - b)) <= tol * np.max(np.abs(b)), k
        assert int(r.stats["n_obs"]) == int(ref.stats["n_obs"])  # the padding is not counted
        f, f_ref = np.asarray(r.fitted)[: obs_b.n_samples], np.asarray(ref.fitted)
        assert np.max(np.abs(f - f_ref)) <= tol * np.max(np.abs(f_ref))
    # the fit itself is right: kd and sigma of the rendered sphere (1 % noise)
    np.testing.assert_allclose(np.asarray(fb.brdf.kd), [0.5, 0.4, 0.3], rtol=0.05)
    assert abs(float(fb.brdf.sigma) - 0.15) < 0.01


def test_solver_blas_limit_applies_only_on_cpu(monkeypatch):
    from threadpoolctl import threadpool_info

    from solvers._threads import blas_single_thread

    def blas_threads():
        return [d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"]

    outside = blas_threads()
    inner = blas_single_thread(blas_threads)
    monkeypatch.setattr(jax, "default_backend", lambda: "cpu")  # as on a machine without a GPU
    assert all(t == 1 for t in inner())  # CPU backend: OpenBLAS limited to one thread inside a solver
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert inner() == outside  # a GPU run leaves the host BLAS alone


_NEEDS_GPU = pytest.mark.skipif(
    not any(d.platform == "gpu" for d in jax.devices()) if jax.default_backend() == "gpu" else True,
    reason="needs a CUDA device (pip install 'jaxsh[cuda]'; benchmarks/gpu_checks.sh)")


@_NEEDS_GPU
def test_gpu_sharded_fit_matches_cpu():  # pragma: no cover - runs only with a GPU
    from tests._scale_worker import make_capture

    obs, lighting = make_capture()
    gpu = solvers.fit_brdf(solvers.shard_observations(obs, solvers.pixel_mesh()), lighting)
    with jax.default_device(jax.devices("cpu")[0]):
        cpu = solvers.fit_brdf(jax.device_put(obs, jax.devices("cpu")[0]), lighting)
    assert solvers.status_name(gpu.status) == "converged"
    np.testing.assert_allclose(float(gpu.brdf.sigma), float(cpu.brdf.sigma), rtol=1e-8)


@_NEEDS_GPU
def test_gpu_kernels_and_float32_products_match_cpu():  # pragma: no cover - runs only with a GPU
    """On the GPU: `real_sh` and `project_latlong` in their GPU forms equal the CPU's, and float32 products are
    float32, not TF32 (docs/performance.md, "Seventeenth round": the float32 RBF evaluation was 7x over its bound)."""
    from tests.test_rbf import _brute

    gpu, cpu = jax.devices("gpu")[0], jax.devices("cpu")[0]
    rng = np.random.default_rng(0)
    d = rng.standard_normal((20_000, 3))
    for dt, tol in ((np.float64, 1e-12), (np.float32, 3e-6)):
        a = jaxsh.real_sh(jax.device_put(d.astype(dt), gpu), 16)
        b = jaxsh.real_sh(jax.device_put(d.astype(dt), cpu), 16)
        assert a.devices() == {gpu} and b.devices() == {cpu} and a.dtype == dt
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=tol)
    img = rng.random((128, 256, 3))
    a, b = (jaxsh.project_latlong(jax.device_put(img, dev), 32) for dev in (gpu, cpu))
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)
    c, w, p = rng.uniform(-1, 1, size=(200, 5)), rng.normal(size=(200, 3)) * 0.1, rng.normal(size=(6, 3))
    x = rng.uniform(-1, 1, size=(500, 5))
    f32 = [jax.device_put(jnp.asarray(v, jnp.float32), gpu) for v in (c, w, p, x)]
    out = jaxsh.RBFModel(*f32[:3])(f32[3])
    assert out.devices() == {gpu}
    np.testing.assert_allclose(np.asarray(out, np.float64), _brute(c, w, p, x, np.ones(5)),
                               rtol=0, atol=1e-5 * np.abs(w).sum(0).max() * 3)  # test_rbf's float32 bound


@pytest.mark.slow  # two fits here plus a 4-device process (~3 min on a loaded 2-core machine): make test-all
def test_cli_fits_several_manifests_on_several_devices(tmp_path):
    from tests.test_cli import _fit_capture

    paths = []
    for k, sigma in enumerate((0.2, 0.3)):
        d = tmp_path / f"c{k}"
        d.mkdir()
        p, m = _fit_capture(d, n_views=1, size=24, sigma=sigma)
        m["brdf"] = None
        q = tmp_path / "manifests" / f"cap{k}.json"
        q.parent.mkdir(exist_ok=True)
        for v in m["views"]:
            v["image"] = str(d / v["image"])
        m["lighting"]["envmap"] = str(d / "probe.exr")
        q.write_text(json.dumps(m))
        paths.append(q)
    # one device, in this process: the reference of each fit (the single-manifest command, its layout unchanged)
    for q in paths:
        assert main(["fit", str(q), "--out", str(tmp_path / "one" / q.stem)]) == 0
    # a folder of manifests on 4 (forced host) devices, in a fresh process
    cmd = [sys.executable, "-m", "solvers.cli", "fit", str(tmp_path / "manifests"), "--devices", "4", "--out",
           str(tmp_path / "four")]
    p = subprocess.run(cmd, env=dict(_env(4), JAXSH_NO_CACHE="1"), capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "2/2 fits succeeded" in p.stdout
    for q in paths:
        one = json.loads((tmp_path / "one" / q.stem / "result.json").read_text())
        four = json.loads((tmp_path / "four" / q.stem / "result.json").read_text())
        assert four["status"] == one["status"] == "converged"
        for key in ("kd", "ks", "mu", "sigma"):
            a, b = np.asarray(four["brdf"][key]), np.asarray(one["brdf"][key])
            assert np.max(np.abs(a - b)) <= STOP_TOL * np.max(np.abs(b)), key  # iterative fits: see STOP_TOL
        assert abs(four["rms"] - one["rms"]) <= STOP_TOL * one["rms"]
        assert (tmp_path / "four" / q.stem / "view_000.exr").exists()
    assert main(["fit", str(paths[0]), "--devices", "8", "--out", str(tmp_path / "x")]) == 2  # this process: 1 device
