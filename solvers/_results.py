"""One result contract for every solver: `Status`, `Solution`, the optimistix/lineax/jaxopt mapping.

Every solver result (`fit_brdf`, `fit_brdf_sh`, `inverse_lighting`,
`inverse_lighting_dual`, `factorize`, `fit_sharing` and the
reflectance-sharing models) is a final `equinox.Module` subclassing the
abstract `Solution`, so it carries the same fields:

- the estimate (a named field such as `brdf` or `coeffs`; `estimate` returns it),
- `status`: a `Status` item (one enumeration for all solvers),
- `iterations`: int array, the steps the solver took (0 for direct solves),
- `rms`: weighted RMS residual $\\sqrt{\\sum w r^2 / n}$, $n$ the samples of positive weight (in the data's units
  when the weights average 1), `rel_rms`: `rms` over the weighted RMS of the
  data (never NaN: 0 when both are 0, `inf` when only the data are 0),
- `stats`: a dict of solver statistics (what each solver adds is in its docstring).

Like optimistix, each solver takes `throw=`: with `throw=True` a status other
than `converged` raises `SolveError` (outside jit) naming the status;
with the default `throw=False` the caller checks `result.status`.
This mirrors `optimistix.RESULTS` / `throw=` (optimistix `_solution.py`).
"""


import math
import operator
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

import jaxsh


class Status(eqx.Enumeration):
    """Outcome of a solve, shared by all solvers (`result.status == Status.converged`).

    Items: `converged`; `max_steps_reached` (the iteration limit came first);
    `nonfinite` (non-finite values in the residual or solution);
    `ill_conditioned` (the linear system is numerically singular: some
    directions are undetermined, see the result's singular values / rank);
    `singular` (a linear solve failed outright, e.g. an exactly singular or
    indefinite system); `diverged` (the nonlinear solver diverged);
    `breakdown` (an iterative linear solver broke down or stagnated);
    `tolerance_not_reached` (a budget such as the number of RBF centres ran
    out before the requested tolerance); `no_signal` (the data carry no
    information: all-zero images or all-zero lighting).
    """

    converged = "converged"
    max_steps_reached = "the iteration limit was reached before the tolerance"
    nonfinite = "non-finite values appeared in the residual or the solution"
    ill_conditioned = "the linear system is numerically singular; see the singular values"
    singular = "a linear solve failed: the system is singular or indefinite"
    diverged = "the nonlinear solver diverged"
    breakdown = "the iterative linear solver broke down or stagnated"
    tolerance_not_reached = "the budget (e.g. RBF centres) ran out before the requested tolerance"
    no_signal = "the data carry no signal (all-zero images, lighting or weights)"


_NAMES = (
    "converged", "max_steps_reached", "nonfinite", "ill_conditioned", "singular", "diverged", "breakdown",
    "tolerance_not_reached", "no_signal",
)


_BY_MESSAGE = {Status[getattr(Status, _n)]: _n for _n in _NAMES}
assert len(_BY_MESSAGE) == len(_NAMES)  # the messages are distinct


def status_name(status) -> str:
    """The item name of a `Status` value, e.g. `"converged"` (outside jit).

    Looked up in NumPy (the value fetched to the host, its message mapped to the name): comparing device arrays,
    each `==` is an eager XLA program compiled at its first use in a process (0.03-0.08 s measured). A traced
    status raises `jax.errors.ConcretizationTypeError`."""
    status = jax.device_get(status)
    if isinstance(status, type(Status.converged)):  # an `equinox` enumeration item
        name = _BY_MESSAGE.get(Status[status])  # the item's message, looked up in NumPy (no XLA program)
        if name is not None:
            return name
    for name in _NAMES:
        if bool(status == getattr(Status, name)):
            return name
    raise ValueError(f"not a Status: {status!r}")


class SolveError(RuntimeError):
    """Raised by a solver called with `throw=True` whose status is not `converged`."""


class Solution(eqx.Module):
    """Abstract base of every solver result (module docstring): estimate, status, iterations, rms, rel_rms, stats."""

    status: eqx.AbstractVar[Status]
    iterations: eqx.AbstractVar[Int[Array, ""]]
    rms: eqx.AbstractVar[Float[Array, ""]]
    rel_rms: eqx.AbstractVar[Float[Array, ""]]
    stats: eqx.AbstractVar[dict[str, Any]]

    @property
    def estimate(self):
        """The solver's estimate (the result's main field)."""
        raise NotImplementedError

    @property
    def converged(self) -> bool:
        """`status == Status.converged` (outside jit)."""
        return status_name(self.status) == "converged"

    @property
    def status_name(self) -> str:
        """The status item name (outside jit)."""
        return status_name(self.status)


def status_from_optimistix(result) -> Status:
    """Map an `optimistix.RESULTS` item (or a `lineax.RESULTS` one, promoted) to `Status`, faithfully.

    | optimistix / lineax item | `Status` |
    |---|---|
    | successful | converged |
    | nonlinear_max_steps_reached, max_steps_reached | max_steps_reached |
    | nonlinear_divergence | diverged |
    | singular | singular |
    | breakdown, stagnation | breakdown |
    | nonfinite, nonfinite_input | nonfinite |
    | conlim (condition-number limit) and any other | ill_conditioned |
    """
    R = optx.RESULTS
    if getattr(result, "_enumeration", None) is lx.RESULTS:
        result = R.promote(result)
    out = Status.ill_conditioned
    pairs = [
        ("successful", Status.converged),
        ("nonlinear_max_steps_reached", Status.max_steps_reached),
        ("max_steps_reached", Status.max_steps_reached),
        ("nonlinear_divergence", Status.diverged),
        ("singular", Status.singular),
        ("breakdown", Status.breakdown),
        ("stagnation", Status.breakdown),
        ("nonfinite", Status.nonfinite),
        ("nonfinite_input", Status.nonfinite),
    ]
    for name, st in pairs:
        item = getattr(R, name, None)
        if item is not None:
            out = Status.where(result == item, st, out)
    return out


def status_from_lbfgsb(num_iter, error, maxiter: int, tol: float) -> Status:
    """Status of a jaxopt L-BFGS-B run from its final projected-gradient `error` (never dropped).

    converged when `error <= tol`; max_steps_reached when the iteration limit
    was hit first; nonfinite when the error is not finite.
    """
    error = jnp.asarray(error)
    st = Status.where(error <= tol, Status.converged, Status.max_steps_reached)
    st = Status.where(jnp.isfinite(error), st, Status.nonfinite)
    return st


def worst(*statuses: Status) -> Status:
    """Combine the statuses of successive stages: the first that is not `converged`, else `converged`."""
    out = Status.converged
    for st in reversed(statuses):
        out = Status.where(st == Status.converged, out, st)
    return out


def worst_batched(status: Status) -> Status:
    """Reduce a batched `Status` (e.g. from a vmapped solve, one per channel) to its first non-`converged` item."""
    bad = jnp.ravel(status != Status.converged)
    k = jnp.argmax(bad)
    return jax.tree_util.tree_map(lambda v: jnp.ravel(v)[k], status)


def rms_pair(rss, data_ss, count) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """`(rms, rel_rms)` from a residual sum of squares, the data's sum of squares and the sample count.

    `rms = sqrt(rss / count)` (0 for `count == 0`); `rel_rms = rms / data_rms`
    with `0/0 = 0` and `x/0 = inf`: never NaN unless `rss` or `data_ss` is NaN (then NaN, not 0) or both are
    infinite (inf/inf).
    """
    rss = jnp.asarray(rss)
    data_ss = jnp.asarray(data_ss, rss.dtype)
    count = jnp.asarray(count, rss.dtype)
    safe = jnp.where(count > 0, count, 1)
    rms = jnp.where(count > 0, jnp.sqrt(jnp.maximum(rss, 0) / safe), 0)
    drms = jnp.where(count > 0, jnp.sqrt(jnp.maximum(data_ss, 0) / safe), 0)
    rel = jnp.where(drms > 0, rms / jnp.where(drms > 0, drms, 1), jnp.where(rms > 0, jnp.inf, 0))
    rel = jnp.where(jnp.isnan(rms) | jnp.isnan(drms), jnp.nan, rel)  # a NaN residual is no perfect fit
    return rms, rel.astype(rms.dtype)


def signal_status(data_ss) -> Status:
    """`no_signal` when a weighted sum of squares is 0, else `converged`.

    Applied to the data (all-zero images or weights) and to the model's
    design (all-zero lighting for `fit_brdf`/`fit_brdf_sh`, an all-zero BRDF
    for `inverse_lighting`): either way the data carry no information about
    the unknowns. Pass the smallest per-channel sum to flag a channel
    without signal.
    """
    return Status.where(jnp.asarray(data_ss) > 0, Status.converged, Status.no_signal)


def check_int(value, name: str, lo: int = 1) -> int:
    """A static int option `>= lo` (a bool, float or string is a `ValueError` naming `name`)."""
    if isinstance(value, bool):
        raise ValueError(f"`{name}` must be an int >= {lo}, got {value!r}")
    try:
        v = operator.index(value)
    except TypeError:
        raise ValueError(f"`{name}` must be a static Python int >= {lo}, got {value!r}") from None
    if v < lo:
        raise ValueError(f"`{name}` must be an int >= {lo}, got {v}")
    return v


def check_bool(value, name: str, none: bool = False) -> bool | None:
    """A static bool flag (`None` too with `none`): anything else, e.g. the string "no", which is truthy, is a
    `ValueError` naming `name` (`fit_brdf(fresnel="no")` fitted mu)."""
    if value is None and none:
        return None
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"`{name}` must be True or False{' or None' if none else ''}, got {value!r}")
    return bool(value)


def check_float(value, name: str, lo: float = 0.0, strict: bool = False) -> float:
    """A finite float option `>= lo` (`> lo` with `strict`), else a `ValueError` naming `name`."""
    try:
        if isinstance(value, (bool, np.bool_, str, bytes)):  # float(True) is 1.0, float("0.5") is 0.5: not numbers given
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a finite number {'>' if strict else '>='} {lo:g}, got {value!r}") from None
    if not math.isfinite(v) or v < lo or (strict and v == lo):
        raise ValueError(f"`{name}` must be a finite number {'>' if strict else '>='} {lo:g}, got {v}")
    return v


def finish(result: Solution, throw: bool) -> Solution:
    """Apply `throw=`: raise `SolveError` (concrete status) or a run-time error (traced: `jaxsh.error_if`, which
    raises on every device of a sharded program) unless converged."""
    if not throw:
        return result
    st = result.status
    try:
        ok = status_name(st) == "converged"
    except jax.errors.ConcretizationTypeError:
        bad = st != Status.converged
        rms = jaxsh.error_if(result.rms, bad, "solver did not converge (throw=True); see result.status")
        return eqx.tree_at(lambda r: r.rms, result, rms)
    if not ok:
        raise SolveError(
            f"{type(result).__name__}: status {status_name(st)!r} ({Status[st]}); pass throw=False to get the result"
        )
    return result
