"""Type aliases for signatures (private to `jaxsh`; `solvers`, which never imports a private
name of `jaxsh`, spells the same types with `jaxtyping` and `collections.abc.Sequence`).

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
  include Python lists; the small vectors and tables the README passes as
  lists (`center=[0, 0, 0.0]`, `eye=`, a colour, `fast_energy=[[...]]`) add
  `SequenceLike`, and per-channel values that may be one number for all
  channels (`kd=0.5`) add `ScalarLike`.
- outputs: `Float[Array, "dims"]` (a `jax.Array`).

**Dimension names.** `*batch` is a variadic batch shape, `*#batch` one that
broadcasts against the other `*#batch` arguments; a name is bound once per
call, so two arguments with the same name must agree. jaxtyping allows only one
variadic dimension per annotation (`"*batch n_coeffs *C"` raises when
evaluated): an array that is "batch, then optional channels" is annotated
`"..."` (or with the one variadic that is unambiguous, e.g. `"n_coeffs *C"`),
and its layouts are stated in the docstring. A dimension computed from an
`int` argument is written with braces: `" {lmax}+1"`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, TypeAlias

from jaxtyping import Array, ArrayLike, Float, Real

# Inputs.
ScalarLike: TypeAlias = Real[ArrayLike, ""]
"""A real scalar: Python `int`/`float`, a NumPy scalar or a 0-d array."""

SequenceLike: TypeAlias = Sequence[Any]
"""A (nested) Python list or tuple of numbers, as `jnp.asarray` takes it; its
shape is checked by the function (`ValueError`), not by the annotation. Added
to the array-like input type of the small vectors and tables that the README
passes as lists: `look_at(eye=[0, 0, 5.0], ...)`, `sphere_gbuffer(center=...)`,
colours `(C,)`, source tables `(J, C)`."""

# Outputs.
Scalar: TypeAlias = Float[Array, ""]
"""A 0-d float JAX array."""

__all__ = ["Array", "ArrayLike", "Scalar", "ScalarLike", "SequenceLike"]
