"""Several devices for jaxsh's own kernels and checks: a failed run-time check raises on every device, and the
per-point kernels run on each device's points (inside a user's `jax.shard_map`, and on sharded arrays).

Like tests/test_scale.py (whose `_worker` these use), in a subprocess on 4 forced host devices; a file of its own
so that `pytest -n 2 --dist loadfile` can run it beside that one.
"""

import functools

import numpy as np
import pytest

from .test_scale import _worker


@functools.lru_cache(maxsize=None)
def _kernels():
    """The worker's `kernels` mode once for the two kernel tests (one JAX process)."""
    return _worker("kernels", timeout=300)


@pytest.mark.parametrize("on_error", ["raise", "nan"])
def test_failed_check_on_several_devices_raises_instead_of_aborting(on_error):
    """A traced check that fails on one of 4 devices (`real_sh`'s direction check, the same inside `jax.shard_map`,
    `jaxsh.error_if` under `vmap` and on integers), followed by a collective. Through `equinox.error_if` the
    failing device raised alone and XLA aborted the process after its 40 s rendezvous timeout
    (docs/howto_scale.md); now each case raises `equinox.EquinoxRuntimeError` with its message at once and the
    process goes on (the same call on good data gives the same value after the error). With `EQX_ON_ERROR=nan`
    the failed calls return NaN instead (an integer: its largest value)."""
    env = {} if on_error == "raise" else {"EQX_ON_ERROR": "nan"}
    r = _worker("checks", env=env, timeout=300)
    assert r["devices"] == 4 and r["bits_equal"] and r["sharding_kept"]
    assert r["effects"] == (on_error == "raise")  # the program holds the per-device callback, equinox's otherwise
    for name in ("real_sh", "shard_map", "vmap", "integers"):
        got = r[name]
        assert np.isfinite(got["good"]) and got["good_again"] == got["good"], (name, got)
        if on_error == "raise":
            assert got["raised"] == ["EquinoxRuntimeError", True] and got["bad"] is None, (name, got)
            assert got["seconds"] < 10.0, (name, got)
        elif name == "integers":  # equinox's "NaN" of an integer is its largest value
            assert got["raised"] is None and got["bad"] != got["good"], (name, got)
        else:
            assert got["raised"] is None and np.isnan(got["bad"]), (name, got)


def test_kernels_inside_shard_map_with_its_default_checks():
    """`real_sh` (float64, float32, both layouts), `complex_sh`, `render_practical`, `practical_terms`, `irradiance`,
    `torrance_sparrow` and `rbf_evaluate` inside a user's `jax.shard_map` with its default `check_vma=True`, on 4
    devices, equal the one-device call. `real_sh`'s loops started from constant carries, which that check rejected
    at trace time (`TypeError: scan body function carry input and carry output must have equal types`)."""
    r = dict(_kernels()["inside"])
    assert r.pop("devices") == 4
    for name, err in r.items():
        assert not isinstance(err, str), (name, err)
        assert err <= (1e-6 if "float32" in name else 1e-13), (name, err)


def test_kernels_on_sharded_arrays_stay_sharded():
    """`real_sh` (both layouts), `complex_sh`, `practical_terms` and `render_practical` (a per-pixel `kd`, a mask, a
    pixel count that is no render bucket) called on arrays split over 4 devices: the outputs stay split along the
    points, equal the one-device call, and no program they compiled gathers the points. Before, `real_sh` beyond
    degree 2 and `practical_terms` gathered every point into each device's loop and returned replicated arrays, and
    `render_practical` padded the pixels on the host and rendered them on one device."""
    r = dict(_kernels()["top"])
    assert r.pop("devices") == 4
    assert r.pop("gathers") == {}
    for name, got in r.items():
        want = "P(None, 'pixels')" if name == "real_sh_coeffs_first" else "P('pixels'"
        assert all(spec.startswith(want) for spec in got["specs"]), (name, got)
        assert got["err"] <= 1e-13, (name, got)
