"""solvers._scale: options checked up front, and empty captures (0 samples) padded into consistent observations.

The multi-device and multi-process checks are in tests/test_scale.py (subprocesses with forced host devices).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import solvers

from ._scale_worker import TRUTH, make_capture


def test_bad_options_name_the_argument():
    obs, lit = make_capture(size=8, n_views=1)
    caps = [(obs, lit)]
    # these raised AttributeError, or were silently read as something else (fresnel="no" fitted mu, an `axis`
    # without a mesh was ignored, a bool or a string of a count made a one-device mesh)
    for kw, match in (({"mesh": "x"}, "`mesh` must be a jax.sharding.Mesh"),
                      ({"mesh": 4}, "`mesh` must be a jax.sharding.Mesh"),
                      ({"axis": "batch"}, "`axis` .* needs a `mesh`"),
                      ({"fresnel": "no"}, "`fresnel` must be True or False"),
                      ({"mesh": solvers.pixel_mesh(1, axis="batch"), "axis": "pixels"}, "`axis` 'pixels' is not an axis")):
        with pytest.raises(ValueError, match=match):
            solvers.fit_many(caps, **kw)
    for devices in (True, "2", ["cpu"]):
        with pytest.raises(ValueError, match="`devices`"):
            solvers.pixel_mesh(devices)
    mesh = solvers.pixel_mesh(1, axis="batch")
    assert mesh.shape == {"batch": 1} and mesh.devices.flat[0] == jax.devices()[0]


def test_padding_an_empty_capture():
    """0 samples: no sample 0 to copy. The padding was 0 rows of geometry under `size` rows of values (an
    inconsistent Observations; `fit_many` then raised a TypeError on such a capture instead of its status)."""
    obs, lit = make_capture(size=8, n_views=1)
    empty = obs.subset(np.arange(0))
    for host in (True, False):  # concrete arrays are padded on the host, traced ones by JAX
        if host:
            p = solvers.pad_observations(empty, size=4)
        else:
            p = jax.jit(lambda o: solvers.pad_observations(o, size=4))(empty)
        for f in ("normals", "views", "values", "weights", "view_index", "pixel_index"):
            a = np.asarray(getattr(p, f))
            assert a.shape[0] == 4 and np.all(np.isfinite(a)), f
            assert a.dtype == getattr(empty, f).dtype, f
        np.testing.assert_array_equal(np.asarray(p.normals), np.tile([0.0, 0.0, 1.0], (4, 1)))  # unit normals
        np.testing.assert_array_equal(np.asarray(p.views), np.tile([0.0, 0.0, 1.0], (4, 1)))
        np.testing.assert_array_equal(np.asarray(p.weights), 0.0)
        np.testing.assert_array_equal(np.asarray(p.values), 0.0)


def test_fit_many_with_an_empty_capture():
    """The empty capture reports `no_signal` (as `fit_brdf` of it does); the other is fitted (its truth)."""
    obs, lit = make_capture(size=8, n_views=1)
    empty = obs.subset(np.arange(0))
    res = solvers.fit_many([(obs, lit), (empty, lit)])
    assert [solvers.status_name(r.status) for r in res] == ["converged", "no_signal"]
    assert res[1].fitted.shape == (0, 3) and int(res[1].stats["n_obs"]) == 0
    assert res[0].fitted.shape == (obs.n_samples, 3) and int(res[0].stats["n_obs"]) == 3 * obs.n_samples
    assert abs(float(res[0].brdf.sigma) - TRUTH["sigma"]) < 0.01  # the rendered sphere's sigma (1 % noise)
    np.testing.assert_allclose(np.asarray(res[0].brdf.kd), TRUTH["kd"], rtol=0.05)
    assert res[0].brdf.sigma.dtype == jnp.float64
