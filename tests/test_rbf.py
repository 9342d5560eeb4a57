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


def _random_model(rng, k, d, m, channels):
    """Centres `(k, d)`, weights `(k[, C])`, polynomial `(d + 1[, C])`, metric `(d,)` and points `(m, d)`."""
    wshape = (k,) if channels is None else (k, channels)
    return (rng.normal(size=(k, d)), rng.normal(size=wshape), rng.normal(size=(d + 1,) + wshape[1:]),
            rng.uniform(0.2, 1.5, size=d), rng.normal(size=(m, d)))


@pytest.mark.parametrize("d", [3, 5])
@pytest.mark.parametrize("channels", [None, 3])
def test_evaluate_matches_brute_force(rng, d, channels):
    k, m = 37, 301
    c, w, p, s, x = _random_model(rng, k, d, m, channels)
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


# --------------------------------------------------------------------------- the saddle-point solve (eq. 10)


def _samples(rng, n, d, c=None):
    x = rng.uniform(-1, 1, size=(n, d))
    y = np.sin(2 * x[:, 0]) * np.cos(x[:, 1]) + 0.3 * x[:, -1] ** 2
    if c is not None:
        y = np.stack([y * (k + 1) + k for k in range(c)], -1)
    return x, y


@pytest.mark.parametrize("channels", [None, 2])
@pytest.mark.parametrize("smoothing", [0.0, 0.1])
def test_rbf_fit_equals_scipy(rng, channels, smoothing):
    from scipy.interpolate import RBFInterpolator

    x, y = _samples(rng, 120, 3, channels)
    s = np.array([1.0, 0.7, 0.3])
    model = jaxsh.rbf_fit(x, y, s, smoothing)
    assert isinstance(model, jaxsh.RBFModel) and model.channels == channels and model.n_centers == 120
    assert model.chunk == jaxsh.rbf_auto_chunk(120)
    xt = rng.uniform(-1.2, 1.2, size=(200, 3))
    # scipy's kernel is -r, its smoothing adds to the diagonal: the system Psi - rho I of eq. 10
    ref = RBFInterpolator(x * s, y, kernel="linear", degree=1, smoothing=smoothing)(xt * s)
    np.testing.assert_allclose(np.asarray(model(xt)), ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
    # the public functional form gives the same coefficients
    lam, poly = jaxsh.rbf_solve(x, y, s, smoothing)
    np.testing.assert_allclose(lam, model.weights if channels else model.weights[:, 0], rtol=1e-12, atol=1e-14)


def test_rbf_solve_padded_active_mask(rng):
    """Inactive rows are decoupled: weight exactly 0, the rest is the fit of the active centres alone."""
    from scipy.interpolate import RBFInterpolator

    x, y = _samples(rng, 60, 3, 2)
    s = np.array([1.0, 1.0, 0.5])
    active = np.zeros(60, bool)
    active[rng.choice(60, 35, replace=False)] = True
    box = (x.min(0) - 0.3, x.max(0) + 0.2)  # any box: the polynomial spans the same space
    solve = jax.jit(lambda c, v, a: jaxsh.rbf_solve(c, v, s, 0.0, active=a, bounds=box))
    lam, poly = solve(x, y, active)
    assert lam.shape == (60, 2) and poly.shape == (4, 2)
    assert np.all(np.asarray(lam)[~active] == 0.0)
    xt = rng.uniform(-1, 1, size=(100, 3))
    ref = RBFInterpolator(x[active] * s, y[active], kernel="linear", degree=1)(xt * s)
    np.testing.assert_allclose(jaxsh.rbf_evaluate(x, lam, poly, xt, s), ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_rbf_solve_errors_and_singular(rng):
    x, y = _samples(rng, 10, 3)
    with pytest.raises(ValueError, match="values"):
        jaxsh.rbf_solve(x, y[:-1])
    with pytest.raises(ValueError, match="active"):
        jaxsh.rbf_solve(x, y, active=np.ones(9, bool))
    with pytest.raises(ValueError, match="bounds"):
        jaxsh.rbf_solve(x, y, bounds=(np.zeros(2), np.ones(2)))
    with pytest.raises(ValueError, match="smoothing"):
        jaxsh.rbf_solve(x, y, smoothing=np.zeros(2))
    with pytest.raises(ValueError, match="too few centres"):
        jaxsh.rbf_fit(x[:3], y[:3])
    # repeated centres: the system is singular, and `rbf_solve` (jit-safe, no value checks) returns something
    # non-finite or finite and meaningless (docstring), never a usable interpolant: over 10 draws (28 of 30 draws
    # came out finite, weights up to 2e18 and an error of 513 at the centres). That is why `rbf_fit` checks
    # concrete centres first (below).
    for seed in range(10):
        xs, ys = _samples(np.random.default_rng(seed), 10, 3)
        dup, ydup = np.concatenate([xs, xs[:1]]), np.concatenate([ys, ys[:1]])
        lam, poly = (np.asarray(a) for a in jaxsh.rbf_solve(dup, ydup))
        model = jaxsh.RBFModel(jnp.asarray(dup), jnp.asarray(lam), jnp.asarray(poly), jnp.ones(3))
        err = np.abs(np.asarray(model(dup)) - ydup).max() if np.all(np.isfinite(lam)) else np.inf
        assert not np.all(np.isfinite(lam)) or np.abs(lam).max() > 1e8 or err > 1e-6 * np.abs(ydup).max(), seed
    with pytest.raises(ValueError, match=r"got \(9,\)"):  # the shape as given (was reported as (9, 1))
        jaxsh.rbf_fit(x, y[:-1, 0] if y.ndim == 2 else y[:-1])


def test_rbf_fit_rejects_singular_centres(rng):
    """`rbf_fit` checks concrete centres on the host: a repeated centre at `smoothing` = 0 and centres in an affine
    subspace (coplanar in 3-D, exactly or to rounding) make eq. 10 singular and are a `ValueError` naming the rows
    or the dimension. A repeated centre with `smoothing` > 0 is a well-posed smoothing spline: equal to scipy's
    `RBFInterpolator` on the same samples. Traced centres are not checked (`jit`)."""
    from scipy.interpolate import RBFInterpolator

    x, y = _samples(rng, 12, 3)
    dup, ydup = np.concatenate([x[:5], x[3:4], x[5:]]), np.concatenate([y[:5], y[3:4] + 0.1, y[5:]])
    with pytest.raises(ValueError, match=r"`centers` rows 3 and 5 are equal"):
        jaxsh.rbf_fit(dup, ydup)
    model = jaxsh.rbf_fit(dup, ydup, smoothing=0.05)
    xt = rng.uniform(-1, 1, size=(50, 3))
    ref = RBFInterpolator(dup, ydup, kernel="linear", degree=1, smoothing=0.05)(xt)
    np.testing.assert_allclose(np.asarray(model(xt)), ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
    for z in (np.zeros(12), 0.3 * x[:, 0] - 0.7 * x[:, 1] + 0.2):  # a coordinate plane, a tilted plane
        with pytest.raises(ValueError, match="affine subspace of dimension 2 of their 3-D space"):
            jaxsh.rbf_fit(np.c_[x[:, :2], z], y, smoothing=0.1)
    jitted = jax.jit(lambda c, v: jaxsh.rbf_fit(c, v).weights)  # traced: no host check, the solve as it comes
    assert jitted(dup, ydup).shape[0] == 13


def test_rbf_auto_chunk():
    for k in (1, 37, 500, 2000, 10**6):
        c = jaxsh.rbf_auto_chunk(k)
        assert 64 <= c <= 16384 and c & (c - 1) == 0
        assert c * k <= (1 << 21) or c == 64


@pytest.mark.parametrize("channels", [None, 2])
def test_evaluate_count_uses_the_leading_centres(rng, channels):
    """`count=k` equals the brute-force interpolant of the first k centres alone, for k in and between blocks."""
    k, d, m = 37, 5, 211  # 37 centres: 4 blocks of 10, the last padded
    c, w, p, s, x = _random_model(rng, k, d, m, channels)
    f = jax.jit(lambda n: jaxsh.rbf_evaluate(c, w, p, x, s, chunk=64, count=n))
    for n in (0, 1, 9, 10, 11, 25, 36, 37, 50):
        nk = min(n, k)
        ref = _brute(c[:nk], w[:nk], p, x, s)
        np.testing.assert_allclose(np.asarray(f(jnp.asarray(n))), ref, rtol=1e-12, atol=1e-12, err_msg=f"count={n}")
        # eager calls with a Python int take the same path
        np.testing.assert_allclose(np.asarray(jaxsh.rbf_evaluate(c, w, p, x, s, count=n)), ref, rtol=1e-12,
                                   atol=1e-12)
    out32 = jaxsh.rbf_evaluate(c.astype(np.float32), w.astype(np.float32), p.astype(np.float32),
                               x.astype(np.float32), s.astype(np.float32), count=20)
    assert out32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(out32), _brute(c[:20], w[:20], p, x, s), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="`count` must be an integer scalar"):
        jaxsh.rbf_evaluate(c, w, p, x, s, count=2.5)
    with pytest.raises(ValueError, match="`count` must be an integer scalar"):
        jaxsh.rbf_evaluate(c, w, p, x, s, count=np.array([1, 2]))
