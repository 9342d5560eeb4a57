"""Batched CPU LAPACK calls deadlock; the solvers keep theirs unbatched (`solvers._lapack`).

jaxlib runs a batched CPU LAPACK call by fanning the matrices out into XLA's intra-op pool and waiting inside it, so
a few such calls at once (two on a 2-core machine) hang the process. These tests check the means (`unbatched`,
`map_lapack`: no batched call in the compiled program, the same values as `jax.vmap`), the small pivoted solve that
replaced a batched one, and the end: every solver's compiled programs without a batched LAPACK call, and `factorize`
and `inverse_lighting` finishing when two host threads call them at once (both hung before).
"""

from __future__ import annotations

import glob
import json
import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from solvers._lapack import map_lapack, unbatched
from solvers.synthetic._sharing_scenes import _solve_pivoted

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def batched_lapack_calls(hlo: str) -> list[str]:
    """The LAPACK custom calls of compiled HLO text whose batch (the leading `num_batch_dims` axes of the first
    operand) holds more than one matrix: `target [shape]` each."""
    out = []
    for line in hlo.splitlines():
        if 'custom_call_target="lapack' not in line:
            continue
        target = re.search(r'custom_call_target="(\w+)"', line).group(1)
        nb = int(re.search(r'num_batch_dims="(\d+)"', line).group(1))
        dims = [int(d) for d in re.search(r"operand_layout_constraints=\{\w+\[([\d,]*)\]", line).group(1).split(",") if d]
        if int(np.prod(dims[:nb])) > 1:
            out.append(f"{target} {dims}")
    return out


def _spd_stack(rng, k=5, n=6):
    a = rng.standard_normal((k, n, n))
    return a @ np.swapaxes(a, -1, -2) + n * np.eye(n)


def test_unbatched_vmap_runs_one_matrix_at_a_time(rng):
    """A `vmap` of `unbatched(eigh)` compiles to unbatched LAPACK calls with `jax.vmap`'s values; a plain `vmap`
    compiles to one batched call (so the check sees what it looks for). Nested `vmap`s and forward-mode derivatives
    pass through."""
    a = jnp.asarray(_spd_stack(rng))

    def eigh(x):
        return jnp.linalg.eigh(x)

    plain = jax.jit(jax.vmap(eigh))
    ours = jax.jit(jax.vmap(unbatched(eigh)))
    assert batched_lapack_calls(plain.lower(a).compile().as_text())
    assert batched_lapack_calls(ours.lower(a).compile().as_text()) == []
    w0, v0 = plain(a)
    w1, v1 = ours(a)
    np.testing.assert_allclose(w1, w0, rtol=1e-13)
    np.testing.assert_allclose(np.abs(v1), np.abs(v0), atol=1e-12)  # eigenvectors up to sign
    w2, _ = jax.vmap(jax.vmap(unbatched(eigh)))(a[None])
    np.testing.assert_allclose(w2[0], w0, rtol=1e-13)
    _, dw = jax.jvp(lambda x: jax.vmap(unbatched(eigh))(x)[0], (a,), (a,))
    np.testing.assert_allclose(dw, w0, rtol=1e-11)  # d(eig(tA))/dt at t=1 is eig(A): eigenvalues scale with A


def test_map_lapack_equals_vmap_and_compiles_unbatched(rng):
    a = jnp.asarray(_spd_stack(rng))
    b = jnp.asarray(rng.standard_normal((5, 6)))
    prog = jax.jit(lambda a, b: map_lapack(lambda m, r: jnp.linalg.solve(m, r), a, b))
    assert batched_lapack_calls(prog.lower(a, b).compile().as_text()) == []
    np.testing.assert_allclose(prog(a, b), np.linalg.solve(np.asarray(a), np.asarray(b)[..., None])[..., 0], rtol=1e-12)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_solve_pivoted_against_numpy(rng, dtype):
    """`_solve_pivoted` (`no_sharing_predict`'s per-pixel solve) against `numpy.linalg.solve` on random systems and
    on the saddle systems it solves, whose zero diagonal needs the row swaps; `vmap`ped, as it is used."""
    n = 7
    a = rng.standard_normal((20, n, n))
    pts = rng.standard_normal((20, n - 1, 3))
    psi = np.linalg.norm(pts[:, :, None] - pts[:, None, :], axis=-1)  # linear kernel: 0 on the diagonal
    saddle = np.zeros((20, n, n))
    saddle[:, : n - 1, : n - 1] = psi
    saddle[:, : n - 1, n - 1] = saddle[:, n - 1, : n - 1] = 1.0
    b = rng.standard_normal((20, n))
    tol = 1e-10 if dtype == np.float64 else 2e-3
    for m in (a, saddle):
        got = jax.jit(jax.vmap(_solve_pivoted))(jnp.asarray(m, dtype), jnp.asarray(b, dtype))
        assert got.dtype == dtype
        want = np.linalg.solve(m, b[..., None])[..., 0]
        np.testing.assert_allclose(got, want, rtol=tol, atol=tol * np.max(np.abs(want)))


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the batched LAPACK calls in question are jaxlib's CPU kernels")
def test_solvers_compile_no_batched_lapack_call_and_run_in_two_threads(tmp_path):
    """Every compiled program of inverse_lighting, inverse_lighting_dual, factorize, fit_brdf (with the
    Levenberg–Marquardt refinement), fit_many, fit_brdf_sh and no_sharing_predict holds no batched LAPACK call (before:
    the channels' `eigh`, LU and SVD, the μ rounds' pseudo-inverses, the batch's covariance `eigh` and QR), and
    `factorize` and `inverse_lighting` called from two host threads each finish (both hung on 2 cores before)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    env["JAX_PLATFORMS"] = "cpu"
    p = subprocess.run([sys.executable, os.path.join(HERE, "_lapack_worker.py"), str(tmp_path)], env=env,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    files = glob.glob(str(tmp_path / "*after_optimizations.txt"))
    assert len(files) > 20  # the dump holds the solvers' programs
    found = {}
    for f in files:
        with open(f) as fh:
            calls = batched_lapack_calls(fh.read())
        if calls:
            found[os.path.basename(f)] = calls
    assert found == {}
    assert len(out["ran"]) == 7
    assert out["threads_finished"], out
