"""Reflection as spherical convolution (R&H 2001 sec. 4-5).

Radially symmetric transfer functions: $B_{lm} = A_l L_{lm}$ with
$A_l = \\Lambda_l\\hat\\rho_l$ (eq. 15, 17). Isotropic BRDFs: the 4-D light
field $B_{lmpq} = \\Lambda_l L_{lm}\\hat\\rho_{lpq}$ (eq. 10) in the basis
$C_{lmpq} = \\Lambda_l^{-1} D^l_{mq}(\\alpha) e^{im\\beta} Y_{pq}(\\theta_o', \\phi_o')$
(eq. 9), with complex harmonics as the paper writes them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Inexact, Num, Real

from ._compile import jit
from ._checks import as_float_array, check_dirs, check_nonzero_dirs, check_lmax, coeff_layout
from ._indexing import real_to_complex_matrix, sh_degrees
from ._sh import _real_sh_flat, _unit_vectors
from ._spectra import lambertian_spectrum


def convolve(
    coeffs: Num[ArrayLike, "..."], A: Real[ArrayLike, "... L"], channels: bool | None = None
) -> Inexact[Array, "..."]:
    """$B_{lm} = A_l L_{lm}$: filter an SH expansion by a radially symmetric kernel.

    R&H 2001 eqs. 15 and 17: reflection of lighting $L$ by a transfer function
    radially symmetric about the normal (or the reflection vector) with
    spectrum $A_l = \\Lambda_l\\hat\\rho_l$ (see `lambertian_spectrum`,
    `phong_spectrum`, `microfacet_spectrum`). Also "blur the lighting by the
    BRDF" of eq. 17 / thesis eq. 3.41: the blurred lighting $L'$ seen in a mirror
    equals the real lighting seen through the BRDF.

    **Arguments:**

    - `coeffs`: real (or complex) SH coefficients `(..., n_coeffs)` or `(..., n_coeffs, C)`.
    - `A`: spectrum `(..., lmax_A + 1)` with `lmax_A ≥ lmax`; batch dims broadcast.
    - `channels`: see `rotate_sh` (layout inference).

    **Returns:** the filtered coefficients, same layout. NaN in, NaN out
    (a pure array kernel, see `jaxsh._checks`).
    """
    coeffs = as_float_array(coeffs, "coeffs", complex_ok=True)
    A = as_float_array(A, "A")
    lmax, axis = coeff_layout(coeffs.shape, "coeffs", channels)
    if A.ndim < 1 or A.shape[-1] < lmax + 1:
        raise ValueError(f"`A` must have shape (..., L) with L >= lmax + 1 = {lmax + 1}, got {tuple(A.shape)}")
    gain = A[..., sh_degrees(lmax)]  # (..., n)
    if axis == -2:
        gain = gain[..., None]
    nd = max(gain.ndim, coeffs.ndim)
    gain = gain.reshape((1,) * (nd - gain.ndim) + gain.shape)
    c = coeffs.reshape((1,) * (nd - coeffs.ndim) + coeffs.shape)
    if jnp.issubdtype(c.dtype, jnp.complexfloating):
        gain = gain.astype(c.dtype)
    else:
        dt = jnp.result_type(c.dtype, gain.dtype)
        gain, c = gain.astype(dt), c.astype(dt)
    return c * gain


def irradiance(coeffs: Real[ArrayLike, "n_coeffs *C"], normals: Real[ArrayLike, "*batch 3"]) -> Float[Array, "..."]:
    """Irradiance $E(n) = \\sum_{l\\le 2} A_l \\sum_m L_{lm} Y_{lm}(n)$ (R&H 2001 eq. 21).

    $A_l$ are the Lambertian values π, 2π/3, π/4 (eq. 16). Only the first 9
    coefficients are used (a lighting with lmax < 2 is zero-padded); this is
    the 9-term approximation whose error is below 1 % of the irradiance for
    typical lighting (Ramamoorthi & Hanrahan 2001, "An efficient
    representation for irradiance environment maps"), and it equals that
    paper's closed form with constants $c_1..c_5$.

    **Arguments:**

    - `coeffs`: real SH lighting `(n_coeffs,)` or `(n_coeffs, C)`.
    - `normals`: `(..., 3)` (normalized here, so their length does not
      matter; a zero-length or non-finite normal is an error at run time).

    **Returns:** `(...)` or `(..., C)`. NaN in `coeffs` propagates.
    """
    coeffs = as_float_array(coeffs, "coeffs")
    if coeffs.ndim not in (1, 2):
        raise ValueError(f"`coeffs` must have shape (n_coeffs,) or (n_coeffs, C), got {tuple(coeffs.shape)}")
    lmax, _ = coeff_layout(coeffs.shape, "coeffs", channels=coeffs.ndim == 2)
    normals = check_nonzero_dirs(normals, "normals")
    dt = jnp.result_type(coeffs.dtype, normals.dtype)
    return _irradiance(coeffs.astype(dt), normals.astype(dt), lmax)


@jit
def _irradiance(coeffs, normals, lmax):
    c = coeffs if coeffs.ndim == 2 else coeffs[:, None]
    if lmax < 2:
        c = jnp.pad(c, ((0, 9 - c.shape[0]), (0, 0)))
    c = c[:9] * lambertian_spectrum(2, c.dtype)[sh_degrees(2)][:, None]
    batch = normals.shape[:-1]
    y = _real_sh_flat(_unit_vectors(normals.reshape(-1, 3)), 2)  # (N, 9)
    e = (y @ c).reshape(batch + (c.shape[1],))
    return e if coeffs.ndim == 2 else e[..., 0]


def real_to_complex_coeffs(coeffs: Real[ArrayLike, "..."], channels: bool | None = None) -> Complex[Array, "..."]:
    """Complex SH coefficients $a = \\bar U c$ of a real expansion (same function).

    With `U = real_to_complex_matrix(lmax)`. For a real function
    $a_{l,-m} = (-1)^m \\overline{a_{lm}}$.
    """
    coeffs = as_float_array(coeffs, "coeffs")
    lmax, axis = coeff_layout(coeffs.shape, "coeffs", channels)
    cdt = jnp.complex128 if coeffs.dtype == jnp.float64 else jnp.complex64
    ub = jnp.asarray(np.conj(real_to_complex_matrix(lmax)), cdt)
    c = coeffs.astype(cdt)
    if axis == -2:
        return jnp.einsum("ij,...jc->...ic", ub, c)
    return jnp.einsum("ij,...j->...i", ub, c)


def complex_to_real_coeffs(coeffs: Num[ArrayLike, "..."], channels: bool | None = None) -> Float[Array, "..."]:
    """Real SH coefficients $c = U^{\\mathsf T} a$ of a complex expansion (the real part of the function's coefficients).

    Exact inverse of `real_to_complex_coeffs` for coefficients of real functions.

    **Arguments:** `coeffs`: complex (or real) coefficients `(..., n_coeffs)`
    or `(..., n_coeffs, C)`; `channels`: see `rotate_sh` (layout inference).
    Integer and bool input go to the default float (float64 under
    `jax_enable_x64`, so no digits are lost), float16/bfloat16 and
    non-numeric input are a `ValueError` (`jaxsh._checks`).

    **Returns:** real coefficients, same layout: float64 for complex128 or
    float64 input, float32 for complex64 or float32 input.
    """
    coeffs = as_float_array(coeffs, "coeffs", complex_ok=True)
    lmax, axis = coeff_layout(coeffs.shape, "coeffs", channels)
    cdt = jnp.complex128 if coeffs.dtype in (jnp.complex128, jnp.float64) else jnp.complex64
    ut = jnp.asarray(real_to_complex_matrix(lmax).T, cdt)
    c = coeffs.astype(cdt)
    out = jnp.einsum("ij,...jc->...ic", ut, c) if axis == -2 else jnp.einsum("ij,...j->...i", ut, c)
    return jnp.real(out)
