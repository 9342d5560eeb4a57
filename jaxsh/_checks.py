"""Argument validation shared by the public functions (private).

Shape and option errors are raised as `ValueError` while tracing; they name
the argument and the expected shape.
"""

from __future__ import annotations

import math
import operator

import jax.numpy as jnp
import numpy as np


def as_float_array(x, name: str):
    """`x` as a floating JAX array; integer and bool input go to the default float."""
    try:
        x = jnp.asarray(x)
    except TypeError as e:  # pragma: no cover - message only
        raise ValueError(f"`{name}` must be an array, got {type(x).__name__}") from e
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"`{name}` must be real, got dtype {x.dtype}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def check_lmax(lmax, name: str = "lmax") -> int:
    """A band limit: a non-negative Python integer (static)."""
    if isinstance(lmax, bool):
        raise ValueError(f"`{name}` must be a non-negative int, got {lmax!r}")
    try:
        value = operator.index(lmax)
    except TypeError:
        if isinstance(lmax, (np.ndarray, jnp.ndarray)) and np.ndim(lmax) == 0:
            raise ValueError(
                f"`{name}` must be a static Python int, got an array; band limits are "
                "static (mark them static under jit)"
            ) from None
        raise ValueError(f"`{name}` must be a non-negative int, got {lmax!r}") from None
    if value < 0:
        raise ValueError(f"`{name}` must be a non-negative int, got {value}")
    return value


def check_dirs(dirs, name: str = "dirs"):
    """Directions: a float array of shape (..., 3)."""
    dirs = as_float_array(dirs, name)
    if dirs.ndim < 1 or dirs.shape[-1] != 3:
        raise ValueError(f"`{name}` must have shape (..., 3), got {tuple(dirs.shape)}")
    return dirs


def check_positive_int(value, name: str) -> int:
    if isinstance(value, bool):
        raise ValueError(f"`{name}` must be a positive int, got {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        raise ValueError(f"`{name}` must be a positive int, got {value!r}") from None
    if v <= 0:
        raise ValueError(f"`{name}` must be a positive int, got {v}")
    return v


def lmax_from_size(n: int, name: str = "coeffs") -> int:
    """The band limit of a coefficient axis of length n = (lmax+1)**2."""
    root = math.isqrt(n)
    if n < 1 or root * root != n:
        raise ValueError(
            f"`{name}` has a coefficient axis of length {n}, which is not "
            "(lmax+1)**2 for any lmax"
        )
    return root - 1


def _is_square(n: int) -> bool:
    r = math.isqrt(n)
    return n >= 1 and r * r == n


def coeff_layout(shape, name: str = "coeffs", channels: bool | None = None):
    """Decide where the coefficient axis of a coefficient array is.

    One channel: `(..., n_coeffs)`; several channels: `(..., n_coeffs, C)`.
    With `channels=None` the layout is inferred from the shape and an
    ambiguous shape (both of the last two axes are perfect squares, e.g.
    `(9, 1)` or `(16, 9)`) raises a `ValueError` asking for `channels=`.

    Returns `(lmax, axis)` with `axis` -1 or -2.
    """
    shape = tuple(shape)
    if len(shape) == 0:
        raise ValueError(f"`{name}` must have shape (..., n_coeffs) or (..., n_coeffs, C), got ()")
    if channels is None:
        last_sq = _is_square(shape[-1])
        prev_sq = len(shape) >= 2 and _is_square(shape[-2])
        if last_sq and prev_sq:
            raise ValueError(
                f"`{name}` has shape {shape}: both (..., n_coeffs) and (..., n_coeffs, C) "
                "fit; pass channels=False (one channel, coefficients last) or "
                "channels=True (coefficients second to last, channels last)"
            )
        if last_sq:
            channels = False
        elif prev_sq:
            channels = True
        else:
            raise ValueError(
                f"`{name}` must have shape (..., n_coeffs) or (..., n_coeffs, C) with "
                f"n_coeffs = (lmax+1)**2, got {shape}"
            )
    if channels:
        if len(shape) < 2:
            raise ValueError(f"`{name}` must have shape (..., n_coeffs, C), got {shape}")
        return lmax_from_size(shape[-2], name), -2
    return lmax_from_size(shape[-1], name), -1
