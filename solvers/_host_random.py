"""Random draws on the host from a JAX key: NumPy's `default_rng` seeded with the key's data.

A draw of a few thousand indices takes milliseconds in NumPy, while `jax.random.permutation` or
`jax.random.choice(..., replace=False)` outside `jit` compiles a shuffle (sorts of `n` random keys) into a
program of its own: 0.2-0.5 s of a user's first call (docs/performance.md). Deterministic for a given key;
`key=None` is `jax.random.PRNGKey(0)`, whose data are (0, 0).
"""

import jax
import jax.numpy as jnp
import numpy as np


def host_rng(key) -> np.random.Generator:
    """A NumPy `Generator` seeded with the data of `key` (a raw `uint32` key or a typed PRNG key; `None`: (0, 0))."""
    if key is None:
        seed = [0, 0]
    else:
        data = jax.random.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key) else key
        seed = np.asarray(data).astype(np.uint32).ravel().tolist()
    return np.random.default_rng(seed)
