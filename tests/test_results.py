"""The one result contract (solvers/_results.py): every solver result is a `solvers.Solution`.

Small practical-model scenes (eq. 24 rendered by `jaxsh.render_practical`) keep these tests quick;
the recovery accuracy itself is tested in test_inverse.py.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest

import jaxsh
import solvers
from solvers._results import (
    rms_pair,
    signal_status,
    status_from_lbfgsb,
    status_from_optimistix,
    worst,
    worst_batched,
)

TRUTH = solvers.TorranceSparrow(jnp.array([0.6, 0.45, 0.3]), jnp.array([0.3, 0.3, 0.3]), jnp.asarray(1.6), jnp.asarray(0.15))
FIELDS = ("status", "iterations", "rms", "rel_rms", "stats")


@pytest.fixture(scope="module")
def scene():
    gbs = [jaxsh.sphere_gbuffer(c, np.zeros(3), 1.0) for c in solvers.view_cameras(3, 20)]
    d = np.array([[0.3, 0.2, 0.93]])
    d /= np.linalg.norm(d)
    e = np.array([[2.0, 2.0, 2.0]])
    slow = jaxsh.disk_light_sh(np.array([-0.5, 0.3, 0.81]), 0.5, np.array([1.0, 0.9, 0.8]), 12)
    imgs = [np.asarray(jaxsh.render_practical(g.normal, g.view, TRUTH.kd, TRUTH.ks, TRUTH.mu, TRUTH.sigma, slow_sh=slow,
                                              fast_directions=d, fast_energy=e, mask=g.mask).total) for g in gbs]
    light = solvers.Lighting(jnp.asarray(slow), jnp.asarray(d), jnp.asarray(e))
    return gbs, imgs, light


@pytest.fixture(scope="module")
def obs(scene):
    gbs, imgs, _ = scene
    return solvers.observations(gbs, imgs)


@pytest.fixture(scope="module")
def obs_zero(scene):
    gbs, imgs, _ = scene
    return solvers.observations(gbs, [np.zeros_like(x) for x in imgs])


def _check_contract(res, estimate):
    assert isinstance(res, solvers.Solution)
    for f in FIELDS:
        assert hasattr(res, f), f
    assert isinstance(res.status, type(solvers.Status.converged))
    assert isinstance(res.stats, dict) and res.stats
    assert np.asarray(res.iterations).dtype.kind == "i" and int(res.iterations) >= 0
    assert np.isfinite(float(res.rms)) and float(res.rms) >= 0
    assert not np.isnan(float(res.rel_rms))
    assert res.estimate is estimate


def test_every_solver_result_is_a_solution(scene, obs):
    _, _, light = scene
    r = solvers.fit_brdf(obs, light)
    _check_contract(r, r.brdf)
    assert r.converged and int(r.iterations) == int(r.stats["num_steps_simplex"] + r.stats["num_steps_lm"])
    il = solvers.inverse_lighting(obs, TRUTH, 4)
    _check_contract(il, il.coeffs)
    assert int(il.iterations) == 0 and np.all(np.asarray(il.stats["rank"]) == 25)
    du = solvers.inverse_lighting_dual(obs, TRUTH, 8, nonneg=False)
    _check_contract(du, du.image)
    assert int(du.iterations) == 0
    dn = solvers.inverse_lighting_dual(obs, TRUTH, 8, maxiter=20)
    _check_contract(dn, dn.image)
    assert 0 < int(dn.iterations) <= 20
    sh = solvers.fit_brdf_sh(obs, light.total_sh(2), 2)
    _check_contract(sh, sh.rho)
    assert int(sh.iterations) == 0
    fa = solvers.factorize(obs, 4, search_pixels=None, max_steps=30)
    _check_contract(fa, fa.brdf)
    assert int(fa.stats["num_mu_candidates"]) == 9 + 9 + 9  # stage 1: a grid, 9 Chebyshev points; the joint model's 9
    assert int(fa.iterations) == 27 + int(fa.stats["num_sigma_candidates"])
    assert int(fa.stats["num_steps_bisection"]) > 0 and np.all(np.asarray(fa.stats["num_steps_golden"]) > 0)
    assert solvers.status_name(fa.status) in ("converged", "max_steps_reached")


def test_rel_rms_is_never_nan_without_signal(scene, obs_zero):
    _, _, light = scene
    il = solvers.inverse_lighting(obs_zero, TRUTH, 4)
    assert float(il.rms) == 0.0 and float(il.rel_rms) == 0.0
    assert solvers.status_name(il.status) == "no_signal"
    sh = solvers.fit_brdf_sh(obs_zero, light.total_sh(2), 2)
    assert float(sh.rel_rms) == 0.0 and solvers.status_name(sh.status) == "no_signal"
    br = solvers.fit_brdf(obs_zero, light, refine=False, max_steps=20)
    assert not np.isnan(float(br.rel_rms)) and solvers.status_name(br.status) == "no_signal"
    with pytest.raises(solvers.SolveError, match="no_signal"):
        solvers.inverse_lighting(obs_zero, TRUTH, 4, throw=True)


def test_throw_raises_only_on_failure(scene, obs):
    _, _, light = scene
    res = solvers.fit_brdf(obs, light, max_steps=1, refine=False)
    assert solvers.status_name(res.status) == "max_steps_reached"
    with pytest.raises(solvers.SolveError, match="max_steps_reached"):
        solvers.fit_brdf(obs, light, max_steps=1, refine=False, throw=True)
    ok = solvers.fit_brdf(obs, light, throw=True)
    assert ok.converged
    assert solvers.inverse_lighting(obs, TRUTH, 4, throw=True).converged
    lamb = solvers.TorranceSparrow(TRUTH.kd, jnp.zeros(3), TRUTH.mu, TRUTH.sigma)
    with pytest.raises(solvers.SolveError, match="ill_conditioned"):
        solvers.inverse_lighting(obs, lamb, 4, throw=True)
    # the L-BFGS-B error is not dropped: one iteration does not reach the tolerance
    d1 = solvers.inverse_lighting_dual(obs, TRUTH, 8, maxiter=1)
    assert solvers.status_name(d1.status) == "max_steps_reached" and float(d1.stats["lbfgsb_error"]) > 1e-8
    with pytest.raises(solvers.SolveError, match="max_steps_reached"):
        solvers.inverse_lighting_dual(obs, TRUTH, 8, maxiter=1, throw=True)
    assert solvers.fit_brdf_sh(obs, light.total_sh(2), 2, throw=True).converged


def test_finish_under_jit_uses_error_if():
    from solvers._results import finish

    class Toy(solvers.Solution):
        x: jax.Array
        status: solvers.Status
        iterations: jax.Array
        rms: jax.Array
        rel_rms: jax.Array
        stats: dict

    @jax.jit
    def run(flag):
        st = solvers.Status.where(flag, solvers.Status.converged, solvers.Status.diverged)
        toy = Toy(x=jnp.zeros(()), status=st, iterations=jnp.asarray(0), rms=jnp.zeros(()), rel_rms=jnp.zeros(()), stats={})
        return finish(toy, True).rms

    assert float(run(True)) == 0.0
    with pytest.raises(Exception, match="throw=True"):
        jax.block_until_ready(run(False))


# --------------------------------------------------------------------------- the status mappings

# Written from the documented table in solvers/_results.py, item by item.
OPTX_TABLE = {
    "successful": "converged",
    "max_steps_reached": "max_steps_reached",
    "nonlinear_max_steps_reached": "max_steps_reached",
    "nonlinear_divergence": "diverged",
    "singular": "singular",
    "breakdown": "breakdown",
    "stagnation": "breakdown",
    "nonfinite": "nonfinite",
    "nonfinite_input": "nonfinite",
    "conlim": "ill_conditioned",
}


def test_status_from_optimistix_maps_every_item():
    names = [n for n in optx.RESULTS._name_to_item]
    assert set(names) == set(OPTX_TABLE), names
    for name in names:
        assert solvers.status_name(status_from_optimistix(getattr(optx.RESULTS, name))) == OPTX_TABLE[name], name
    for name in lx.RESULTS._name_to_item:  # lineax items are promoted
        assert solvers.status_name(status_from_optimistix(getattr(lx.RESULTS, name))) == OPTX_TABLE[name], name
    # traced, and from a real solve
    jitted = jax.jit(lambda r: status_from_optimistix(r))
    assert solvers.status_name(jitted(optx.RESULTS.nonlinear_divergence)) == "diverged"
    sol = optx.minimise(lambda y, _: jnp.sum((y - 1.0) ** 2), optx.NelderMead(1e-8, 1e-8), jnp.zeros(2), max_steps=3,
                        throw=False)
    assert solvers.status_name(status_from_optimistix(sol.result)) == "max_steps_reached"


def test_status_from_lbfgsb():
    assert solvers.status_name(status_from_lbfgsb(12, 1e-10, 100, 1e-8)) == "converged"
    assert solvers.status_name(status_from_lbfgsb(100, 1e-3, 100, 1e-8)) == "max_steps_reached"
    assert solvers.status_name(status_from_lbfgsb(3, jnp.nan, 100, 1e-8)) == "nonfinite"
    assert solvers.status_name(status_from_lbfgsb(3, jnp.inf, 100, 1e-8)) == "nonfinite"


def test_worst_rms_pair_and_signal():
    S = solvers.Status
    assert solvers.status_name(worst(S.converged, S.converged)) == "converged"
    assert solvers.status_name(worst(S.converged, S.singular, S.diverged)) == "singular"
    batched = jax.vmap(lambda b: S.where(b, S.converged, S.breakdown))(jnp.array([True, False, True]))
    assert solvers.status_name(worst_batched(batched)) == "breakdown"
    assert solvers.status_name(signal_status(0.0)) == "no_signal"
    assert solvers.status_name(signal_status(1.0)) == "converged"
    rms, rel = rms_pair(8.0, 32.0, 2)  # rms = sqrt(8/2) = 2, data rms = sqrt(32/2) = 4
    assert float(rms) == 2.0 and float(rel) == 0.5
    assert float(rms_pair(0.0, 0.0, 5)[1]) == 0.0
    assert float(rms_pair(1.0, 0.0, 5)[1]) == np.inf
    assert float(rms_pair(0.0, 0.0, 0)[0]) == 0.0
    assert eqx.is_array(rms)
