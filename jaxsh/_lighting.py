"""Distant lighting: directional and disk (area) sources, environment maps, SH lighting.

All lighting is distant and expressed in the world frame (+z up). A
directional source is a direction `d` (unit, from the object towards the
light, the $\\omega_i$ of the papers) and an `energy` $L_j$: the irradiance it
delivers on a surface facing it — its radiance integrated over its solid
angle (R&H eq. 23's "total energy"). A disk source has a centre direction,
an angular radius $r$ and a uniform radiance; its energy is
$2\\pi(1-\\cos r)\\cdot$radiance.

Slow/fast split (R&H sec. 5.3): compact sources much narrower than the
BRDF lobe σ are "fast" (delta functions carrying their energy, rendered by
eq. 23); everything else is "slow" lighting, represented in SH, filtered by
the microfacet spectrum for $B_{s,slow}$ (eq. 22).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real
from ._custom_types import ScalarLike, SequenceLike

from ._checks import (as_float_array, as_float_scalar, check_dirs, check_lmax, check_nonzero_dirs, check_values,
                      coeff_layout, common_dtype)
from ._compile import jit
from ._convolution import convolve
from ._indexing import sh_degrees
from ._sh import _real_sh_flat, _unit_vectors
from ._spectra import legendre_p, microfacet_spectrum


def _non_negative(x, name: str):
    """Energy / radiance ≥ 0 and not +inf; NaN propagates (see `jaxsh._checks`)."""
    return check_values(x, lambda a: (a < 0) | (a == jnp.inf), name, "finite and >= 0")


def _check_radius(r, name: str = "angular_radius"):
    """A disk's angular radius in (0, π]; NaN propagates."""
    return check_values(r, lambda a: (a <= 0) | (a > jnp.pi), name, "in (0, pi] (radians)")


def _energy(energy, n_sources: int, name: str):
    energy = as_float_array(energy, name)
    if energy.ndim == 1:
        energy = energy[:, None]
    if energy.ndim != 2 or energy.shape[0] != n_sources:
        raise ValueError(f"`{name}` must have shape ({n_sources},) or ({n_sources}, C), got {tuple(energy.shape)}")
    return _non_negative(energy, name)


def directional_light_sh(directions: Real[ArrayLike, "J 3"] | SequenceLike, energy: Real[ArrayLike, "J *C"] | SequenceLike, lmax: int) -> Float[Array, "n_coeffs C"]:
    """SH coefficients of delta sources: $L_{lm} = \\sum_j L_j Y_{lm}(\\omega_j)$ (R&H sec. 5.2).

    **Arguments:** `directions` `(J, 3)`, towards the lights (normalized
    here; a zero or non-finite direction is an error); `energy` `(J,)` or
    `(J, C)`, ≥ 0 (a negative or infinite energy is an error: `ValueError`,
    or a run-time error under `jit`); `lmax` ≥ 0.
    **Returns:** `(n_coeffs, C)`. NaN in `energy` propagates.
    """
    directions = check_nonzero_dirs(directions, "directions")
    if directions.ndim != 2:
        raise ValueError(f"`directions` must have shape (J, 3), got {tuple(directions.shape)}")
    lmax = check_lmax(lmax)
    e = _energy(energy, directions.shape[0], "energy")
    return _directional_light_sh(directions, e, lmax)


# One compiled program per (shapes, dtypes, lmax): run eagerly, the loop over l of `_real_sh_flat` was
# traced and lowered again at every call (0.14 s a call at lmax 16, for microseconds of work).
@jit
def _directional_light_sh(directions, e, lmax: int):
    y = _real_sh_flat(_unit_vectors(directions), lmax)  # (J, n)
    return y.T @ e.astype(y.dtype)


def disk_light_sh(
    direction: Real[ArrayLike, "3"] | SequenceLike, angular_radius: Real[ArrayLike, ""], radiance: Real[ArrayLike, "*C"] | ScalarLike | SequenceLike, lmax: int
) -> Float[Array, "n_coeffs *C"]:
    """SH coefficients of a uniform disk (spherical cap) source, in closed form.

    About its own axis the cap is zonal: $L^{z}_{l} = 2\\pi\\,\\mathrm{rad}\\int_{\\cos r}^1
    Y_{l0}\\,du = \\mathrm{rad}\\,\\sqrt{\\pi/(2l+1)}\\,[P_{l-1}(\\cos r) - P_{l+1}(\\cos r)]$
    ($l \\ge 1$; $L^z_0 = \\mathrm{rad}\\,2\\pi(1-\\cos r)/\\sqrt{4\\pi}$), and a zonal
    function rotated to axis $d$ has $L_{lm} = \\Lambda_l L^z_l Y_{lm}(d)$.
    Differentiable in the direction, radius and radiance.

    **Arguments:** `direction` `(3,)`, the disk's centre (normalized here; a
    zero or non-finite direction is an error); `angular_radius` scalar in
    $(0, \\pi]$ ($\\pi$: the whole sphere); `radiance` scalar or `(C,)`, ≥ 0;
    `lmax` ≥ 0. An out-of-range radius or radiance is an error
    (`ValueError`, or a run-time error under `jit`); NaN propagates.

    **Returns:** `(n_coeffs,)` for a scalar radiance, else `(n_coeffs, C)`,
    in the dtype of the array arguments (Python scalars adopt it: a float32
    `direction` with Python-float radius and radiance gives float32; float32
    with float64 arrays gives float64).
    """
    direction = check_nonzero_dirs(direction, "direction")
    if direction.shape != (3,):
        raise ValueError(f"`direction` must have shape (3,), got {tuple(direction.shape)}")
    r = as_float_array(angular_radius, "angular_radius")
    rad = as_float_array(radiance, "radiance")
    if r.shape != ():
        raise ValueError(f"`angular_radius` must be a scalar (shape ()), got shape {tuple(r.shape)}")
    if rad.ndim > 1:
        raise ValueError(f"`radiance` must be a scalar or have shape (C,), got shape {tuple(rad.shape)}")
    lmax = check_lmax(lmax)
    r = _check_radius(r)
    rad = _non_negative(rad, "radiance")
    dt = common_dtype(direction, r, rad)  # of the arrays, not their dtypes: Python scalars stay weak
    return _disk_light_sh(direction.astype(dt), r.astype(dt), rad.astype(dt), lmax)


@jit  # as `_directional_light_sh`: eagerly, each call traced the loop of `_real_sh_flat` again (0.13-0.17 s)
def _disk_light_sh(direction, r, rad, lmax: int):
    dt = r.dtype
    u = jnp.cos(r)
    p = legendre_p(u, lmax + 1)  # P_0 .. P_{lmax+1}
    l = np.arange(lmax + 1)
    pm1 = jnp.concatenate([jnp.ones((1,), dt), p[: lmax]])  # P_{l-1}, with a dummy for l = 0
    zon = jnp.sqrt(jnp.pi / (2 * l + 1.0)).astype(dt) * _cap_difference(pm1 - p[1 : lmax + 2], p[: lmax + 1], u, r, lmax)
    zon = zon.at[0].set(2 * jnp.pi * (2 * jnp.sin(r / 2) ** 2) / jnp.sqrt(4 * jnp.pi))  # 1 - cos r without cancellation
    lam = jnp.sqrt(4 * jnp.pi / (2 * l + 1.0)).astype(dt)
    y = _real_sh_flat(_unit_vectors(direction[None]), lmax)[0]
    coef = (lam * zon)[sh_degrees(lmax)] * y  # per unit radiance
    if rad.ndim == 0:
        return coef * rad
    return coef[:, None] * rad[None, :]


def _cap_difference(direct, p, u, r, lmax: int):
    """$P_{l-1}(u) - P_{l+1}(u)$, $u = \\cos r$, without the cancellation of a small cap.

    For a small radius both terms are close to 1 and their difference, of
    order $l^2 r^2$, loses $\\log_{10}(1/r^2)$ digits (a 0.27° sun: 11).
    Above $u = 1/2$ it is taken from the identity
    $(1-u^2)P_l'(u) = \\tfrac{l(l+1)}{2l+1}[P_{l-1}(u) - P_{l+1}(u)]$ with
    $1-u^2 = \\sin^2 r$ and $P_l' = \\sum_{k<l,\\ l-k \\text{ odd}} (2k+1) P_k$ (a sum
    of positive terms near $u = 1$); below, `direct` is accurate.
    """
    l = np.arange(lmax + 1)
    k = np.arange(lmax + 1)
    gain = np.where((k[None, :] < l[:, None]) & ((l[:, None] - k[None, :]) % 2 == 1), 2.0 * k[None, :] + 1.0, 0.0)
    dp = jnp.asarray(gain, p.dtype) @ p  # P_l'(u)
    scale = np.where(l > 0, (2.0 * l + 1.0) / np.maximum(l * (l + 1.0), 1.0), 0.0)
    via_derivative = jnp.asarray(scale, p.dtype) * jnp.sin(r) ** 2 * dp
    return jnp.where(u > 0.5, via_derivative, direct)


def disk_energy(angular_radius, radiance):
    """Total energy of a disk source: $2\\pi(1-\\cos r)$ × radiance.

    `angular_radius` in $(0, \\pi]$, `radiance` ≥ 0 (broadcast); out-of-range
    values are an error, NaN propagates.
    """
    r = _check_radius(as_float_array(angular_radius, "angular_radius"))
    rad = _non_negative(as_float_array(radiance, "radiance"), "radiance")
    return 4 * jnp.pi * jnp.sin(r / 2) ** 2 * rad  # 2 pi (1 - cos r), without cancellation


def is_fast_source(angular_radius, sigma, ratio: float = 0.25):
    """R&H sec. 5.3: a compact source is "fast" when its angular radius is ≪ σ (here `< ratio·σ`)."""
    return as_float_array(angular_radius, "angular_radius") < ratio * as_float_array(sigma, "sigma")


def filter_lighting_microfacet(coeffs: Real[ArrayLike, "n_coeffs *C"], sigma: Real[ArrayLike, ""]) -> Float[Array, "n_coeffs *C"]:
    """$L^{slow}_{lm} = e^{-(\\sigma l)^2} L_{lm}$: the lighting a microfacet lobe sees (R&H eqs. 17, 20, 22).

    `coeffs` `(n_coeffs,)` or `(n_coeffs, C)`; `sigma` > 0 (σ ≤ 0 is an
    error: `ValueError`, or a run-time error under `jit`). NaN in, NaN out.

    **Returns:** the layout of `coeffs`, in its dtype when `sigma` is a
    Python scalar (float32 stays float32); float32 with a float64 `sigma`
    array gives float64.
    """
    coeffs = as_float_array(coeffs, "coeffs")
    if coeffs.ndim not in (1, 2):
        raise ValueError(f"`coeffs` must have shape (n_coeffs,) or (n_coeffs, C), got {tuple(coeffs.shape)}")
    lmax, _ = coeff_layout(coeffs.shape, "coeffs", channels=coeffs.ndim == 2)
    sigma = as_float_scalar(sigma, "sigma")  # a vector sigma broadcast into (k, n, C) silently
    dt = common_dtype(coeffs, sigma)  # a Python-scalar sigma (weakly typed) adopts the dtype of `coeffs`
    a = microfacet_spectrum(sigma.astype(dt), lmax)
    return convolve(coeffs.astype(dt), a, channels=coeffs.ndim == 2)


def split_disk_sources(
    directions: Real[ArrayLike, "K 3"] | SequenceLike,
    angular_radii: Real[ArrayLike, " K"] | SequenceLike,
    radiance: Real[ArrayLike, "K *C"] | SequenceLike,
    sigma: float,
    lmax: int,
    ratio: float = 0.25,
):
    """The slow/fast split of R&H sec. 5.3 for a set of disk sources.

    Sources with angular radius `< ratio·σ` become delta functions carrying
    their total energy (`fast_directions`, `fast_energy`, for eq. 23); the
    others are summed into slow SH lighting up to `lmax` (for eqs. 21, 22).
    The split is decided on concrete values (a Python-level choice), so
    call it outside `jit`.

    **Arguments:**

    - `directions`: `(K, 3)`, the disks' centres (normalized here; a zero or
      non-finite direction is an error).
    - `angular_radii`: `(K,)`, in $(0, \\pi]$.
    - `radiance`: `(K, C)` (or `(K,)`, one channel), ≥ 0.
    - `sigma`: the roughness σ (radians); `lmax` ≥ 0; `ratio` > 0.

    Any other shape is a `ValueError` naming the argument and the expected
    shape: a transposed `(3, K)` or `(C, K)` array is not reinterpreted.
    Integer input goes to the default float; float16 and complex input are
    a `ValueError`.

    **Returns:** `(slow_sh (n_coeffs, C) or None, fast_directions (J, 3) or None, fast_energy (J, C) or None)`,
    in the float dtype of the arrays (float32 stays float32; float32 with
    float64 gives float64). `slow_sh` is a JAX array (the sum of
    `disk_light_sh`), `fast_directions` and `fast_energy` are NumPy arrays
    (computed on the host: their count varies with σ, and eager JAX
    operations on each new shape would compile a program).
    """
    d = _host_float(directions, "directions")
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"`directions` must have shape (K, 3), got {d.shape}")
    k = d.shape[0]
    r = _host_float(angular_radii, "angular_radii")
    if r.shape != (k,):
        raise ValueError(f"`angular_radii` must have shape ({k},) (one per direction), got {r.shape}")
    rad = _host_float(radiance, "radiance")
    if rad.ndim not in (1, 2) or rad.shape[0] != k:
        raise ValueError(f"`radiance` must have shape ({k}, C) or ({k},) (one row per direction), got {rad.shape}")
    dt = np.result_type(d.dtype, r.dtype, rad.dtype)  # float32 or float64 (NumPy: float32 + float64 -> float64)
    d, r, rad = d.astype(dt, copy=False), r.astype(dt, copy=False), rad.reshape(k, -1).astype(dt, copy=False)
    n2 = np.einsum("ki,ki->k", d, d)
    if n2.size and not (n2.min() > 0 and n2.max() < np.inf):
        raise ValueError("`directions` contains a zero-length or non-finite direction (directions are normalized, so they must be finite and non-zero)")
    d = d / np.sqrt(n2)[:, None]
    _check_radius(r, "angular_radii")
    fast = r < ratio * float(sigma)
    slow_sh = None
    for j in np.nonzero(~fast)[0]:
        c = disk_light_sh(d[j], r[j], rad[j], lmax)
        slow_sh = c if slow_sh is None else slow_sh + c
    if not np.any(fast):
        return slow_sh, None, None
    fd = d[fast]
    # `disk_energy` in NumPy: the count of fast sources varies with sigma, and eager JAX operations on a new
    # shape each compile a small program (5 of them, 0.15 s a call)
    rf = _non_negative(rad[fast], "radiance")
    fe = (4 * np.pi) * np.sin(r[fast][:, None] / 2) ** 2 * rf
    return slow_sh, fd, fe.astype(dt, copy=False)


def _host_float(x, name: str) -> np.ndarray:
    """`x` as a NumPy float array on the host, by the dtype rule of `as_float_array` (integers to the default
    float, float16 and complex a `ValueError`), without a JAX array for NumPy input (no device round trip)."""
    if isinstance(x, (np.ndarray, np.generic)) and x.dtype in (np.float32, np.float64):
        return np.asarray(x)
    return np.asarray(as_float_array(x, name))
