"""`solvers._jacobian.explicit_jacobian`: same values and derivatives, and a linearization that holds only J."""

import jax
import jax.numpy as jnp
import numpy as np

from solvers._jacobian import explicit_jacobian


def _fn(table):
    def fn(p, args):
        # a residual whose tangent needs the whole (m, 40) table: p[1] scales the columns inside a nonlinearity
        cols = jnp.exp(-p[1] * jnp.arange(40.0))
        return jnp.sin(p[0] * (table @ cols)) - args

    return fn


def test_explicit_jacobian_has_the_derivatives_of_the_function_and_a_small_linearization(rng):
    m = 5000
    table = jnp.asarray(rng.normal(size=(m, 40)))
    args = jnp.asarray(rng.normal(size=m))
    fn = _fn(table)
    wrapped = explicit_jacobian(fn)
    p = jnp.asarray([0.3, 0.05])
    np.testing.assert_array_equal(np.asarray(wrapped(p, args)), np.asarray(fn(p, args)))
    # reference: central differences of the plain function (not autodiff of either)
    h = 1e-6
    fd = np.stack([(np.asarray(fn(p + h * e, args)) - np.asarray(fn(p - h * e, args))) / (2 * h) for e in jnp.eye(2)], 1)
    for jac in (jax.jacfwd(wrapped)(p, args), jax.jacrev(wrapped)(p, args)):
        np.testing.assert_allclose(np.asarray(jac), fd, rtol=1e-6, atol=1e-7)
    # the linearization keeps O(m k) numbers (J and the value), where the plain one keeps the (m, 40) table
    _, lin = jax.linearize(lambda q: wrapped(q, args), p)
    _, lin_plain = jax.linearize(lambda q: fn(q, args), p)
    size = sum(x.size for x in jax.tree_util.tree_leaves(lin))
    size_plain = sum(x.size for x in jax.tree_util.tree_leaves(lin_plain))
    assert size <= 3 * m + 10 < size_plain
    np.testing.assert_allclose(np.asarray(lin(jnp.asarray([1.0, -2.0]))), fd @ np.asarray([1.0, -2.0]), rtol=1e-6, atol=1e-6)



def test_explicit_jacobian_of_a_pytree_residual(rng):
    """A residual given as two leaves (`fit_brdf`'s `(N, C)` samples and the box's `(2,)` wall): each leaf's
    values are the function's, and its linearization applied to a tangent is that leaf's central differences
    (not autodiff of either) applied to it."""
    table = jnp.asarray(rng.normal(size=(300, 40)))
    args = jnp.asarray(rng.normal(size=300))
    flat = _fn(table)

    def fn(p, a):
        r = flat(p, a)
        return r.reshape(150, 2), jnp.stack([p[0] ** 2, jnp.sin(p[1])])

    wrapped = explicit_jacobian(fn)
    p = jnp.asarray([0.3, 0.05])
    for got, want in zip(wrapped(p, args), fn(p, args)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    h = 1e-6
    dp = np.asarray([1.0, -2.0])
    _, lin = jax.linearize(lambda q: wrapped(q, args), p)
    out = lin(jnp.asarray(dp))
    for i, got in enumerate(out):
        fd = np.stack([(np.asarray(fn(p + h * e, args)[i]) - np.asarray(fn(p - h * e, args)[i])) / (2 * h)
                       for e in jnp.eye(2)], -1)  # (*leaf, 2)
        assert got.shape == fd.shape[:-1]
        np.testing.assert_allclose(np.asarray(got), fd @ dp, rtol=1e-6, atol=1e-6)

def test_covariance_does_not_depend_on_the_parameters_units(rng):
    """`covariance_from_jacobian` against NumPy's float64 inverse of J^T J: with columns of very different scales
    (images 1000x brighter scale the Kd, Ks columns, not the mu, sigma ones) float32 gives the same standard errors;
    unscaled, float32 declared every parameter undetermined (inf). Rank-deficient and zero columns stay inf."""
    from solvers._normal_equations import covariance_from_jacobian

    base = rng.normal(size=(400, 4))
    rss, nobs = 3.7, 400.0
    for scale in ([1.0, 1.0, 1.0, 1.0], [1e3, 1e3, 1.0, 1.0], [1e-3, 1e4, 1.0, 1e2]):
        J = base * np.asarray(scale)
        want = np.sqrt(np.diag(np.linalg.inv(J.T @ J)) * rss / (nobs - 4))
        for dt, rtol in ((np.float64, 1e-10), (np.float32, 1e-4)):
            _, se = covariance_from_jacobian(jnp.asarray(J, dt), jnp.asarray(rss, dt), nobs, 4)
            np.testing.assert_allclose(np.asarray(se), want, rtol=rtol)
    rank3 = base.copy()
    rank3[:, 3] = rank3[:, 0] - 2 * rank3[:, 1]  # parameters 0, 1, 3 trade off exactly; 2 is determined
    zero = base.copy()
    zero[:, 1] = 0.0
    for J, inf in ((rank3, [True, True, False, True]), (zero, [False, True, False, False])):
        _, se = covariance_from_jacobian(jnp.asarray(J * [1e3, 1, 1, 1]), jnp.asarray(rss), nobs, 4)
        np.testing.assert_array_equal(np.isinf(np.asarray(se)), inf)
