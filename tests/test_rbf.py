"""jaxsh.RBFModel / rbf_evaluate / sbrdf_points against NumPy brute force (Zickler 2006 eqs. 7, 11-13)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
from tests.helpers import random_dirs


def _brute(centers, weights, poly, points, scale):
    d = np.sqrt((((points[:, None, :] - centers[None, :, :]) * scale) ** 2).sum(-1))
    return d @ weights + poly[0] + points @ poly[1:]


@pytest.mark.parametrize("d", [3, 5])
@pytest.mark.parametrize("channels", [None, 3])
def test_evaluate_matches_brute_force(rng, d, channels):
    k, m = 37, 301
    c = rng.normal(size=(k, d))
    wshape = (k,) if channels is None else (k, channels)
    w = rng.normal(size=wshape)
    p = rng.normal(size=(d + 1,) + wshape[1:])
    s = rng.uniform(0.2, 1.5, size=d)
    x = rng.normal(size=(m, d))
    ref = _brute(c, w, p, x, s)
    for chunk in (None, 64, 1000):  # chunked (301 = 4*64 + 45), single block
        out = jaxsh.rbf_evaluate(c, w, p, x, s, chunk=chunk)
        assert out.shape == ref.shape
        np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12)
    model = jaxsh.RBFModel(c, w, p, s)
    np.testing.assert_allclose(model(x[0]), ref[0], rtol=1e-12)


def test_float32_evaluation(rng):
    k, d = 200, 5
    c = rng.uniform(-1, 1, size=(k, d))
    w = rng.normal(size=(k, 3)) * 0.1
    p = rng.normal(size=(d + 1, 3))
    x = rng.uniform(-1, 1, size=(500, d))
    ref = _brute(c, w, p, x, np.ones(d))
    out = jaxsh.RBFModel(jnp.asarray(c, jnp.float32), jnp.asarray(w, jnp.float32), jnp.asarray(p, jnp.float32))(
        jnp.asarray(x, jnp.float32)
    )
    assert out.dtype == jnp.float32
    # float32 rounding of O(K) terms of size O(|w| r): 1e-5 relative to the scale of the sum
    np.testing.assert_allclose(out, ref, atol=1e-5 * np.abs(w).sum(0).max() * 3)


def test_exact_at_centres_and_finite_gradient(rng):
    c = rng.normal(size=(10, 3))
    w = rng.normal(size=10)
    p = rng.normal(size=4)
    model = jaxsh.RBFModel(c, w, p, [1.0, 1.0, 0.3])
    # distances accumulated per coordinate: exactly zero at a centre
    r = jaxsh.scaled_distances(c, c, jnp.asarray([1.0, 1.0, 0.3]))
    assert np.all(np.diag(np.asarray(r)) == 0.0)
    g = jax.grad(lambda q: model(q))(jnp.asarray(c[0]))
    assert np.all(np.isfinite(g))
    # away from the centres: gradient equals a central difference
    q = jnp.asarray(rng.normal(size=3))
    g = jax.grad(lambda q: model(q))(q)
    h = 1e-6
    fd = [(model(q + h * e) - model(q - h * e)) / (2 * h) for e in np.eye(3)]
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


def test_shape_errors(rng):
    c = rng.normal(size=(5, 3))
    with pytest.raises(ValueError, match="points"):
        jaxsh.RBFModel(c, np.zeros(5), np.zeros(4))(np.zeros((2, 5)))
    with pytest.raises(ValueError, match="weights"):
        jaxsh.RBFModel(c, np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError, match="scale"):
        jaxsh.RBFModel(c, np.zeros(5), np.zeros(4), scale=np.ones(2))
    with pytest.raises(ValueError, match="centers"):
        jaxsh.RBFModel(np.zeros(3), np.zeros(1), np.zeros(4))


def test_sbrdf_points(rng):
    wi, wo, n = random_dirs(rng, (50,)), random_dirs(rng, (50,)), random_dirs(rng, (50,))
    q = np.asarray(jaxsh.sbrdf_points(wi, wo, n))
    np.testing.assert_allclose(q, jaxsh.uvw_from_directions(wi, wo, n), rtol=0, atol=0)
    # w = 2 theta_d / pi with theta_d half the angle between wi and wo (closed form, independent of the frame)
    td = 0.5 * np.arccos(np.clip((wi * wo).sum(-1), -1, 1))
    np.testing.assert_allclose(q[:, 2], 2 * td / np.pi, atol=1e-7)
    xy = rng.uniform(size=(50, 2))
    q5 = np.asarray(jaxsh.sbrdf_points(wi, wo, n, xy))
    np.testing.assert_array_equal(q5[:, :2], xy)
    np.testing.assert_array_equal(q5[:, 2:], q)
    with pytest.raises(ValueError, match="xy"):
        jaxsh.sbrdf_points(wi, wo, n, xy[:, :1])
