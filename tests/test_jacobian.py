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
