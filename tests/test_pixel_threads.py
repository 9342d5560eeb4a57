"""`solvers._pixel_threads`: per-pixel maps in parts on host threads equal one call, compile once, fail alike.

The parts are forced small here (`_PART_MIN`, `host_cores` patched): the real threshold (16,384 pixels a part)
would make these tests slow, and what is checked does not depend on the size.
"""

import logging
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers
from solvers import _pixel_threads as pt

FIELDS = ("visible", "cos_o", "irradiance", "bands", "theta_h", "fast_weight", "fast_energy")


@pytest.fixture
def parts(monkeypatch):
    """`map_in_threads` with parts of at least 64 pixels, on `cores` cores (default 3)."""

    def set_(cores=3, part_min=64):
        monkeypatch.setattr(pt, "_PART_MIN", part_min)
        monkeypatch.setattr(pt, "host_cores", lambda: cores)

    set_()
    return set_


def _capture(rng, n, dtype=np.float64, lmax=6, channels=3):
    """`n` pixels of random visible normals and views, and a lighting with slow SH and two suns."""
    nrm = rng.normal(size=(n, 3))
    nrm[:, 2] = np.abs(nrm[:, 2]) + 0.3
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    v = nrm + 0.3 * rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.5
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    light = solvers.Lighting(jnp.asarray(rng.normal(size=((lmax + 1) ** 2, channels)), dtype),
                             jnp.asarray([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86]], dtype),
                             jnp.asarray(rng.uniform(0.5, 1.0, (2, channels)), dtype))
    return jnp.asarray(nrm, dtype), jnp.asarray(v, dtype), light


def _obs(rng, n, dtype=np.float64, **kw):
    nrm, v, light = _capture(rng, n, dtype, **kw)
    c = light.n_channels
    obs = solvers.Observations(
        normals=nrm, views=v, values=jnp.ones((n, c), dtype), weights=jnp.ones((n,), dtype),
        transfer=jnp.asarray(rng.normal(size=(n, 9)), dtype),
        fast_visibility=jnp.asarray(rng.uniform(0, 1, (n, 2)), dtype),
        reflected_visibility=jnp.asarray(rng.uniform(0, 1, (n,)), dtype), texel=None,
        view_index=jnp.zeros((n,), jnp.int32), pixel_index=jnp.arange(n, dtype=jnp.int32), image_shapes=((n, 1),),
    )
    return obs, light


def test_part_count_follows_cores_and_sizes(monkeypatch):
    monkeypatch.setattr(pt, "host_cores", lambda: 2)
    assert pt.n_parts(10) == 1 and pt.n_parts(2 * pt._PART_MIN - 1) == 1
    assert pt.n_parts(2 * pt._PART_MIN) == 2 and pt.n_parts(100 * pt._PART_MIN) == 2
    monkeypatch.setattr(pt, "host_cores", lambda: 64)
    assert pt.n_parts(3 * pt._PART_MIN) == 3 and pt.n_parts(100 * pt._PART_MIN) == pt._PARTS_MAX
    monkeypatch.setattr(pt, "host_cores", lambda: 1)
    assert pt.n_parts(100 * pt._PART_MIN) == 1


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_practical_terms_in_parts_equal_one_call_bitwise(rng, parts, dtype):
    """`practical_terms_for` on one CPU device, the band sums in 3 parts (the last padded), against the same call
    in one part: every field bitwise, in float64 and float32 (whose band sums take another recurrence)."""
    obs, light = _obs(rng, 1000 + (dtype == np.float32), dtype)  # not a multiple of the chunk or of 3
    got = solvers.practical_terms_for(obs, light, chunk=64)
    assert pt.n_parts(obs.n_samples) == 3
    parts(cores=1)
    want = solvers.practical_terms_for(obs, light, chunk=64)
    for f in FIELDS:
        a, b = np.asarray(getattr(got, f)), np.asarray(getattr(want, f))
        assert a.shape == b.shape and a.dtype == b.dtype, f
        assert np.array_equal(a, b), f"{f}: {np.max(np.abs(a.astype(float) - b))}"
    assert got.bands.shape == (obs.n_samples, 3, 7)


def test_map_in_threads_runs_the_parts_in_threads_and_keeps_none_and_replicated(rng, parts):
    """Parts after a first call run at once in other threads; None pixels stay None; a replicated output is the
    first part's; the join cuts the padding."""
    nrm, v, light = _capture(rng, 700)
    names = []

    def fn(n, vv, none):
        assert none is None
        names.append(threading.current_thread().name)
        t = jaxsh.practical_terms(n, vv, light, chunk=32)
        return {"per_pixel": t.bands, "shared": t.fast_energy}

    out = pt.map_in_threads(fn, (nrm, v, None), key=("test_map", 1), replicated=("shared",), align=32)
    assert len(names) == 3 and names[0] == names[1] == threading.current_thread().name  # first call: part 0 alone
    names.clear()
    out2 = pt.map_in_threads(fn, (nrm, v, None), key=("test_map", 1), replicated=("shared",), align=32)
    assert len(names) == 3 and sum(n.startswith("jaxsh-pixels") for n in names) == 2
    want = jaxsh.practical_terms(nrm, v, light, chunk=32)
    for o in (out, out2):
        assert o["per_pixel"].shape == (700, 3, 7) and np.array_equal(np.asarray(o["per_pixel"]), np.asarray(want.bands))
        assert np.array_equal(np.asarray(o["shared"]), np.asarray(want.fast_energy))


def test_a_first_call_compiles_its_program_once(rng, parts, caplog):
    """Three parts of a program never compiled before: one XLA compilation of it, not one per thread."""
    nrm, v, light = _capture(rng, 523, lmax=3)  # shapes no other test compiles
    start = threading.Barrier(3)

    def fn(n, vv):
        try:  # parts that run at once start their calls together (a part run alone waits 1 s, then goes on)
            start.wait(timeout=1.0)
        except threading.BrokenBarrierError:
            pass
        return jaxsh.practical_terms(n, vv, light, chunk=48).bands

    caplog.set_level(logging.WARNING)
    with jax.log_compiles(True):
        out = pt.map_in_threads(fn, (nrm, v), key=("test_compile",), align=48)
    compiled = [r.getMessage() for r in caplog.records if "Finished XLA compilation of jit(_practical_terms)" in r.getMessage()]
    assert len(compiled) == 1, compiled
    assert out.shape == (523, 3, 4)


def test_fallbacks_call_the_function_directly(rng, parts):
    """Traced pixels (inside a caller's `jit`), pixel arrays that disagree on N, and parts too small: one call,
    whose own error a bad input gets."""
    nrm, v, light = _capture(rng, 400)
    calls = []

    def fn(n, vv):
        calls.append(n.shape)
        return jaxsh.practical_terms(n, vv, light).bands

    want = np.asarray(fn(nrm, v))
    calls.clear()
    got = jax.jit(lambda n, vv: pt.map_in_threads(fn, (n, vv), key=("test_fallback",)))(nrm, v)
    assert calls == [(400, 3)]
    # the caller's program inlines `fn`, so its rounding may differ (1.8e-15 at XLA's optimization level 0)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-13, atol=1e-13 * np.abs(want).max())
    calls.clear()
    with pytest.raises(ValueError, match="views"):
        pt.map_in_threads(fn, (nrm, v[:399]), key=("test_fallback",))
    assert calls == [(400, 3)]
    calls.clear()
    parts(part_min=1000)
    pt.map_in_threads(fn, (nrm, v), key=("test_fallback",))
    assert calls == [(400, 3)]


def test_a_failed_run_time_check_in_a_part_raises_as_one_call(rng, parts):
    """A zero normal in the last part: the same run-time error as one call, after every thread has finished."""
    nrm, v, light = _capture(rng, 600)
    bad = nrm.at[550].set(0.0)

    def fn(n, vv):
        return jaxsh.practical_terms(n, vv, light, chunk=32).bands

    for _ in range(2):  # a first call (part 0 alone) and a later one (all parts at once)
        with pytest.raises(Exception, match="`normals` contains a zero-length or non-finite direction"):
            pt.map_in_threads(fn, (bad, v), key=("test_error",), align=32)
    with pytest.raises(Exception, match="`normals` contains a zero-length or non-finite direction"):
        fn(bad, v)


def test_a_forked_child_gets_its_own_threads(monkeypatch):
    """A child made by `fork` inherits the pool object but not its threads: `_executor` makes a new one when the
    process id is not the pool's (the child's parts would otherwise wait for threads that do not exist)."""
    pool = pt._executor()
    assert pt._executor() is pool
    pid = pt.os.getpid()
    monkeypatch.setattr(pt.os, "getpid", lambda: pid + 1)
    child = pt._executor()
    assert child is not pool and pt._executor() is child
    assert child.submit(lambda: 7).result(timeout=10) == 7
