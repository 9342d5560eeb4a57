"""Argument validation shared by the public functions (private).

Shape and option errors are raised as `ValueError` while tracing; they name
the argument and the expected shape. The rules below hold for every public
function of `jaxsh`; each function's docstring says which of them apply.

**Data arrays versus parameters.** The pure array kernels (`real_sh`,
`rotate_sh`, `convolve`, `project_latlong`, the spectra, `irradiance`, the
lighting SH, ...) treat their *data* like `jax.numpy` does: NaN in, NaN out
(no check is paid on every element of a large array). A *parameter* outside
its documented range (σ ≤ 0, a Phong exponent s ≤ −1, a disk radius ∉ (0, π],
negative energy or radiance, lmax < 0) is an error, never a finite number:
a `ValueError` naming the argument and the valid range when the value is
concrete, an `equinox.error_if` run-time error when it is traced (under
`jit`; the returned value carries the check, so it is always used). A NaN
parameter is not "out of range": it propagates like data. Cameras and
G-buffers are entry points: there NaN and inf are errors too.

**Directions.** Direction inputs of the kernels (`real_sh`, `irradiance`,
`directional_light_sh`, `disk_light_sh`, `fit_sh`, ...) are normalized, so
their length does not matter; a zero-length or non-finite direction is an
error. Functions that require unit vectors without normalizing say so.

**dtypes.** Floating inputs keep their dtype (float32 or float64; several
inputs are promoted to the widest). Integer and bool arrays are converted to
the default float dtype (float32, or float64 under `jax_enable_x64`).
float16 and bfloat16 are rejected with a `ValueError` ("float16 is not
supported: use float32 or float64"): the recurrences and quadratures lose
all accuracy in 11 bits of mantissa. Complex input is rejected where a real
array is expected. The same rule holds for `dtype=` keywords.
"""

from __future__ import annotations

import functools
import logging
import math
import operator
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool

_HALF = (jnp.float16, jnp.bfloat16)


def _reject_half(dtype, name: str) -> None:
    if jnp.dtype(dtype) in tuple(jnp.dtype(d) for d in _HALF):
        raise ValueError(f"`{name}`: {jnp.dtype(dtype).name} is not supported: use float32 or float64")


def as_jax(x):
    """`jnp.asarray(x)`, with NumPy arrays and scalars and Python floats sent by `jax.device_put`: the same array
    (dtype canonicalized and weak type set the same way), without the small XLA program that `jnp.asarray`
    compiles for each new NumPy shape and dtype (jax 0.10; 10-20 ms each at first use: a cold `jaxsh fit`
    compiled fourteen such programs; docs/performance.md, "Sixth round").

    A NumPy array is copied on the host first: on the CPU, `jax.device_put` can alias a NumPy buffer (measured:
    a later write to the caller's array showed in the JAX array), and JAX arrays must not change."""
    if isinstance(x, (np.ndarray, np.generic)):
        return jax.device_put(np.array(x, copy=True))
    if isinstance(x, float):
        return jax.device_put(x)
    return jnp.asarray(x)


def as_float_array(x, name: str, complex_ok: bool = False):
    """`x` as a floating JAX array (the dtype rule of the module docstring).

    Integer and bool input go to the default float; float16/bfloat16 are a
    `ValueError`; complex input is a `ValueError` unless `complex_ok`.
    """
    try:
        if isinstance(x, (np.ndarray, np.generic)) and x.dtype.kind in "biu":
            x = jax.device_put(np.asarray(x, jnp.result_type(float)))  # converted on the host: a new array (`as_jax`)
        else:
            x = as_jax(x)
    except (TypeError, ValueError) as e:
        raise ValueError(f"`{name}` must be a numeric array, got {type(x).__name__}") from e
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        if not complex_ok:
            raise ValueError(f"`{name}` must be real, got dtype {x.dtype}")
        return x
    if not (jnp.issubdtype(x.dtype, jnp.number) or x.dtype == jnp.bool_):
        raise ValueError(f"`{name}` must be a numeric array, got dtype {x.dtype}")
    _reject_half(x.dtype, name)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def as_float_scalar(x, name: str):
    """`x` as a floating JAX scalar (shape `()`; dtype rule of `as_float_array`).

    Any other shape is a `ValueError` "`name` must be a scalar (shape ()), got shape (...)": a parameter
    annotated `Real[ArrayLike, ""]` is never broadcast or summed over silently.
    """
    x = as_float_array(x, name)
    if x.shape != ():
        raise ValueError(f"`{name}` must be a scalar (shape ()), got shape {tuple(x.shape)}")
    return x


def common_dtype(*arrays):
    """The float dtype several arrays are computed in: `jnp.result_type` of the arrays themselves.

    The arrays, not their dtypes: a Python scalar (weakly typed after `as_float_array`) adopts the dtype of
    the other arrays (float32 stays float32 under `jax_enable_x64`). When strict promotion
    (`jax_numpy_dtype_promotion="strict"`) refuses to combine float32 and float64, the widest dtype.
    """
    try:
        return jnp.result_type(*arrays)
    except jax.dtypes.TypePromotionError:
        return max((jnp.dtype(a.dtype) for a in arrays), key=lambda d: d.itemsize)


def check_dtype(dtype, name: str = "dtype"):
    """A `dtype=` keyword: None (the default float) or float32/float64."""
    if dtype is None:
        return jnp.result_type(float)
    try:
        dt = jnp.dtype(dtype)
    except TypeError:
        raise ValueError(f"`{name}` must be a float dtype (float32 or float64), got {dtype!r}") from None
    _reject_half(dt, name)
    if not jnp.issubdtype(dt, jnp.floating):
        raise ValueError(f"`{name}` must be a float dtype (float32 or float64), got {dt.name}")
    return dt


def is_traced(x) -> bool:
    """True when `x` is a JAX tracer (its values are not known now)."""
    return isinstance(x, jax.core.Tracer)


def error_if_any(x, bad, msg: str):
    """`equinox.error_if(x, jnp.any(bad), msg)`, without moving a sharded `x` to one device (`jaxsh.error_if`).

    `equinox.error_if` passes `x` itself through a `lax.cond` whose other branch raises from a host callback.
    XLA's SPMD partitioner places that conditional on one device, so an `x` sharded over several devices went
    through that device and was partitioned again (XLA logs "Involuntary full rematerialization"). Here the
    condition is reduced to a scalar, the error is attached to an unsigned integer 0 (`_error_token`), and `x`
    is returned with that 0 OR-ed into its bits: exactly `x` (signed zeros, subnormals, infinities and NaN
    payloads included), still carrying the check as a data dependence, for one fused bitwise operation. Its
    derivative is that of the identity. Integers are OR-ed the same way, complex numbers part by part, booleans
    by a logical or with `False`.
    """
    x = jnp.asarray(x)
    pred = jnp.any(bad)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        token = _error_token(pred, msg, _UINT[x.real.dtype.itemsize])
        return jax.lax.complex(_or_bits(x.real, token), _or_bits(x.imag, token))
    if x.dtype == jnp.bool_:
        return x | _error_token(pred, msg, jnp.uint8).astype(bool)
    return _or_bits(x, _error_token(pred, msg, _UINT[x.dtype.itemsize]))


def error_if(x: ArrayLike, pred: Bool[ArrayLike, "..."], msg: str) -> Array:
    """Return `x`, with a run-time error "`msg`" wherever `pred` holds: `equinox.error_if` for jaxsh's programs.

    The same contract as `equinox.error_if(x, jnp.any(pred), msg)`: the returned array must be used in place of
    `x` (it carries the check); under `jax.jit` a true `pred` raises `equinox.EquinoxRuntimeError` with `msg`
    when the program runs (inside `equinox.filter_jit` or `jaxsh.jit`; under a bare `jax.jit` the message is
    inside a `jax.errors.JaxRuntimeError`); the `EQX_ON_ERROR` environment variable (`nan`, `off`,
    `breakpoint`) is honoured. Two differences, both for several devices:

    - `x` keeps its sharding: the check is attached to its bits, not passed through a conditional that XLA
      places on one device;
    - in a process with more than one device, the error is raised by a host callback on *every* device of the
      program (`jax.debug.callback(..., partitioned=True)`). `equinox.error_if` raises on one device only; the
      others then wait for it in the program's next collective until XLA aborts the process (measured on 2-4
      host devices: killed after XLA's 40 s rendezvous timeout). This route makes the program effectful, which
      costs JAX's slower dispatch path (about 0.1 ms a call); with one device nothing changes.

    **Arguments:**

    - `x`: an array of any dtype, returned bit for bit.
    - `pred`: a boolean array; any true entry is an error.
    - `msg`: the error message.

    **Returns:** `x`, carrying the check.
    """
    if not isinstance(msg, str):
        raise ValueError(f"`msg` must be a str, got {type(msg).__name__}")
    return error_if_any(x, pred, msg)


def _on_error() -> str:
    """equinox's `EQX_ON_ERROR` setting, read from the environment when a check is traced (the command line sets
    it after import, `solvers.cli._enable_cache`, so that its programs hold no host callback)."""
    return os.environ.get("EQX_ON_ERROR", "raise")


def _raise_on_every_device() -> bool:
    """Whether a failed check raises on every device (`error_if`): a process with several devices, not a TPU
    (whose runtime has no partitioned callbacks)."""
    return jax.device_count() > 1 and jax.default_backend() != "tpu"


def _manual_axes() -> tuple:
    """The mesh axes of the enclosing `jax.shard_map` (empty outside one)."""
    mesh = jax.sharding.get_abstract_mesh()
    return () if mesh.empty else tuple(mesh.manual_axes)


class _EquinoxRuntimeError(RuntimeError):
    """Raised in the host callback of a failed check on several devices. `equinox.filter_jit` (every jaxsh program
    is one) recognizes an XLA error that names this class and raises `equinox.EquinoxRuntimeError` with the
    message instead, as it does for the callback of `equinox.error_if`."""


class _QuietFailedChecks(logging.Filter):
    """Drop JAX's log record of a callback that raised `_EquinoxRuntimeError` (one per device): the error itself
    reaches the caller. Every other record passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[0] if record.exc_info else None
        return not (exc is not None and issubclass(exc, _EquinoxRuntimeError))


@functools.lru_cache(maxsize=None)
def _quiet_failed_checks() -> None:
    logging.getLogger("jax._src.debugging").addFilter(_QuietFailedChecks())


def _raise_if(pred, *, msg: str) -> None:
    if np.any(np.asarray(pred)):
        from equinox import _jit  # hand the message to filter_jit, as equinox's own callback does

        if hasattr(_jit, "last_error_info"):
            _jit.last_error_info = (msg, [])
        raise _EquinoxRuntimeError(msg)


def _error_token(pred, msg: str, dtype):
    """An unsigned-integer 0 of `dtype` carrying the run-time check "`pred` is an error, with message `msg`".

    With one device (or `EQX_ON_ERROR` other than `raise`): `equinox.error_if` on the 0. With several devices:
    the predicate is reduced over `vmap` (`equinox.internal.unvmap_any`), so the `lax.cond` stays a conditional,
    and inside `jax.shard_map` over its manual mesh axes (a `psum`); it is then one scalar on every device, so
    every device takes the same branch, and the error branch's callback raises on each (`error_if`).
    """
    zero = jnp.zeros((), dtype)
    if _on_error() != "raise" or not _raise_on_every_device():
        return eqx.error_if(zero, pred, msg)
    if not is_traced(pred):
        if bool(np.any(np.asarray(pred))):
            raise eqx.EquinoxTracetimeError(msg)
        return zero
    from equinox.internal import unvmap_any  # here: 30 ms of `import jaxsh` otherwise, for several devices only

    _quiet_failed_checks()
    pred = unvmap_any(pred)
    manual = _manual_axes()
    if manual:  # inside `jax.shard_map`: each device holds its own predicate; all of them must take the branch
        pred = jax.lax.psum(pred.astype(jnp.int32), manual) > 0

    def fail():
        jax.debug.callback(functools.partial(_raise_if, msg=msg), pred, partitioned=True)
        return zero

    return jax.lax.cond(pred, fail, lambda: zero)


_UINT = {1: jnp.uint8, 2: jnp.uint16, 4: jnp.uint32, 8: jnp.uint64}


@jax.custom_jvp
def _or_bits(x, token):
    bits = jax.lax.bitcast_convert_type(x, token.dtype)
    return jax.lax.bitcast_convert_type(bits | token, x.dtype)


@_or_bits.defjvp
def _or_bits_jvp(primals, tangents):
    return _or_bits(*primals), tangents[0]


def check_values(x, bad, name: str, expected: str):
    """Reject the entries of `x` where `bad(x)` holds (a parameter-range check).

    Concrete `x`: `ValueError` "`name` must be {expected}, got {value}".
    Traced `x`: `equinox.error_if` with the same message; the returned
    array carries the check and must be used in place of `x`.
    """
    if is_traced(x):
        return error_if_any(x, bad(x), f"`{name}` must be {expected}")
    mask = np.asarray(bad(np.asarray(x)))  # NumPy on concrete values: no eager XLA programs
    if np.any(mask):
        v = np.asarray(x, dtype=np.float64)
        shown = v[()] if v.ndim == 0 else v[np.broadcast_to(mask, v.shape)].ravel()[:4]
        text = f"{shown:.6g}" if v.ndim == 0 else np.array2string(shown, precision=6)
        raise ValueError(f"`{name}` must be {expected}, got {text}")
    return x


def check_finite(x, name: str):
    """NaN and inf are errors (concrete: ValueError; traced: error_if)."""
    return check_values(x, lambda a: ~(abs(a) < jnp.inf), name, "finite (no NaN or inf)")  # NumPy or JAX


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


def check_lmax_range(lmax: int, dtype, limits: tuple[int, int], what: str) -> int:
    """`lmax` within the degree a dtype's range allows (`limits`: below float64, float64), else a `ValueError`.

    The harmonics are evaluated from seeds $\\sin^m\\theta$ (times constants), which leave the floating-point
    range long before the harmonics themselves get small: at degree $l$ the seed of order $m \\approx l/e$ at
    $\\sin\\theta = 1/e$ is about $e^{-l/e}$, so float32 seeds underflow from $l \\approx 200$ and float64 ones
    from $l \\approx 1925$, and every harmonic above them comes out 0 where it is of order 1 (measured: float32
    `real_sh` returned 0 for -1.44 at l = 256; float64 0 for -0.662 at l = 2100)."""
    lo, hi = limits
    limit = hi if jnp.dtype(dtype) == jnp.float64 else lo
    if lmax > limit:
        raise ValueError(
            f"`lmax` = {lmax} is beyond what {what} evaluates in {jnp.dtype(dtype).name}: at most {limit} (the "
            f"sin(theta)^m seeds of its recurrence underflow beyond it{'; use float64' if limit == lo else ''})")
    return lmax


def check_dirs(dirs, name: str = "dirs"):
    """Directions: a float array of shape (..., 3) (values not checked)."""
    dirs = as_float_array(dirs, name)
    if dirs.ndim < 1 or dirs.shape[-1] != 3:
        raise ValueError(f"`{name}` must have shape (..., 3), got {tuple(dirs.shape)}")
    return dirs


def check_nonzero_dirs(dirs, name: str = "dirs"):
    """Directions the caller normalizes: shape (..., 3), finite and non-zero.

    Concrete input with a zero-length or non-finite direction is a
    `ValueError` here; traced input is checked at run time by the kernel
    (`_sh._unit_vectors`).
    """
    dirs = check_dirs(dirs, name)
    if not is_traced(dirs):
        d = np.asarray(dirs)
        # one pass without a (..., 3) temporary, then two reductions (a NaN makes the minimum NaN, which is not
        # > 0): 5 ms at 10⁶ directions, against 18 ms for `sum(d * d)` and `all(isfinite & > 0)`
        n2 = np.einsum("...i,...i->...", d, d)
        if n2.size and not (n2.min() > 0 and n2.max() < np.inf):
            raise ValueError(f"`{name}` contains a zero-length or non-finite direction (directions are normalized, so they must be finite and non-zero)")
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
