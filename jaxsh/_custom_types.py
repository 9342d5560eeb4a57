"""Type aliases for signatures (private; `solvers` uses the public names re-exported by jaxtyping).

The shapes in signatures are checked when the tests run (jaxtyping's import hook
with beartype, `--jaxtyping-packages` in `pyproject.toml`); they are not checked
for users, who get the `ValueError`s of `jaxsh._checks` instead.

**Inputs vs outputs.** A public function takes anything `jnp.asarray` takes and
converts it; so parameters are annotated with an *input* type and return values
with an *output* type:

- inputs: `Real[ArrayLike, "dims"]` (or `Float`/`Inexact`/`Int`/`Bool`), where
  `jaxtyping.ArrayLike` is `jax.typing.ArrayLike`: a `jax.Array` (tracers
  included), a `numpy.ndarray`, a NumPy scalar, or a Python scalar (only where
  the shape is `""`). `Real` rather than `Float` where integer input is
  converted to the default float (`as_float_array`). JAX's `ArrayLike` does not
  include Python lists; the few small vectors the README passes as lists
  (`center=[0, 0, 0.0]`, `eye=`, a colour) use the `...Like` aliases below,
  which add `Sequence`.
- outputs: `Float[Array, "dims"]` (a `jax.Array`).

**Dimension names.** `*batch` is a variadic batch shape, `*#batch` one that
broadcasts against the other `*#batch` arguments; a name is bound once per
call, so two arguments with the same name must agree. jaxtyping allows only one
variadic dimension per annotation: an array that is "batch, then optional
channels" is annotated with a single variadic (`"*batch n_coeffs"` is not
enough, so `"..."`), and the layout is stated in the docstring.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeAlias, Union

from jaxtyping import Array, ArrayLike, Float, Real

# Inputs.
ScalarLike: TypeAlias = Real[ArrayLike, ""]
"""A real scalar: Python `int`/`float`, a NumPy scalar or a 0-d array."""

Vector3Like: TypeAlias = Union[Real[ArrayLike, "3"], Sequence[float]]
"""A 3-vector (a point or a direction): an array of shape `(3,)` or a sequence of three numbers."""

ColorLike: TypeAlias = Union[Real[ArrayLike, "*C"], Sequence[float]]
"""Per-channel values: a scalar, an array `(C,)`, or a sequence of numbers."""

MatrixLike: TypeAlias = Union[Real[ArrayLike, "*batch J C"], Sequence[Sequence[float]]]
"""A `(J, C)` table (e.g. source energies), an array or nested sequences."""

# Outputs.
Scalar: TypeAlias = Float[Array, ""]
"""A 0-d float JAX array."""

__all__ = ["Array", "ArrayLike", "ColorLike", "MatrixLike", "Scalar", "ScalarLike", "Vector3Like"]
