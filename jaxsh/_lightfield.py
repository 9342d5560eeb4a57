"""Isotropic BRDFs in spherical harmonics and the 4-D reflected light field.

R&H 2001 eqs. 8-13, with the paper's complex harmonics $Y_{lm}$
(`complex_sh`, Condon-Shortley phase). An isotropic transfer function
$\\hat\\rho = \\rho\\cos\\theta_i'$ expands as (eq. 8)
$$\\hat\\rho(\\omega_i', \\omega_o') = \\sum_{l,p,q}\\hat\\rho_{lpq}\\,
  \\overline{Y_{lq}(\\omega_i')}\\,Y_{pq}(\\omega_o'),\\qquad
  \\hat\\rho_{lpq} = \\hat\\rho_{lp(-q)},$$
and the reflected light field $B(\\alpha, \\beta, \\omega_o')$ of a surface with
normal $(\\alpha, \\beta)$ under distant lighting $L = \\sum L_{lm} Y_{lm}$ is
$B = \\sum B_{lmpq} C_{lmpq}$ with $B_{lmpq} = \\Lambda_l L_{lm}\\hat\\rho_{lpq}$
(eq. 10) and $C_{lmpq} = \\Lambda_l^{-1} D^l_{mq}(\\alpha)e^{im\\beta}Y_{pq}(\\omega_o')$
(eq. 9), $D^l$ the y-rotation block of `wigner_d_y`.

Array layouts (documented once, used everywhere here):

* BRDF coefficients `rho[l, p, q]`, shape `(lmax+1, lmax+1, lmax+1)` for
  $q = 0..l_{max}$ (the $q < 0$ entries equal $q > 0$ ones); zero where
  $q > \\min(l, p)$.
* Incident coefficients at a fixed view, `rho_i[(l, q)]` in the flat SH
  layout, shape `(n_coeffs,)`: $\\hat\\rho_{lq}(\\omega_o') =
  \\sum_p \\hat\\rho_{lpq}Y_{pq}(\\omega_o') = \\int\\hat\\rho\\,Y_{lq}(\\omega_i')\\,d\\omega_i'$.
* Light-field coefficients `B[(l, m), p, q + lmax]`, shape
  `(n_coeffs, lmax+1, 2 lmax + 1)`.

Transfer functions are given as callables `transfer(theta_i, theta_o, dphi)`
of local angles ($\\Delta\\phi = \\phi_o' - \\phi_i'$), vectorized, returning
$\\hat\\rho$; they must be even in $\\Delta\\phi$ (isotropy) and vanish below
the horizon (where they are never evaluated here: the quadratures cover
$\\theta_i', \\theta_o' \\in [0, \\pi/2]$ only).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Inexact, Real
from ._custom_types import SequenceLike

from ._checks import (as_float_array, as_float_scalar, check_dtype, check_lmax, check_nonzero_dirs,
                      check_positive_int, check_values, lmax_from_size)
from ._indexing import sh_degrees, sh_lambda, sh_orders
from ._rotation import wigner_d_y
from ._sh import complex_sh


def _expi(a):
    """$e^{ia}$ for real a, without mixing Python complex scalars into float arrays."""
    return jax.lax.complex(jnp.cos(a), jnp.sin(a))


def _default_dtype(dtype):
    return check_dtype(dtype)


def _zonal_table(theta, lmax, dtype):
    """$N_{lq}P_l^q(\\cos\\theta)$ = Y_lq(θ, φ=0) for q ≥ 0, as (len(theta), l, q)."""
    d = jnp.stack([jnp.sin(theta), jnp.zeros_like(theta), jnp.cos(theta)], axis=-1)
    y = jnp.real(complex_sh(d, lmax))  # (n, n_coeffs), real at phi = 0
    l_idx, q_idx = np.meshgrid(np.arange(lmax + 1), np.arange(lmax + 1), indexing="ij")
    valid = q_idx <= l_idx
    flat = np.where(valid, l_idx * l_idx + l_idx + q_idx, 0)
    return y[:, flat] * jnp.asarray(valid, dtype)[None]


def _hemisphere_nodes(n: int, dtype):
    """Gauss-Legendre nodes in cos θ on [0, 1] (θ ∈ [0, π/2]) and weights (sin θ dθ)."""
    x, w = np.polynomial.legendre.leggauss(n)
    u = 0.5 * (x + 1.0)
    return jnp.asarray(np.arccos(u), dtype), jnp.asarray(0.5 * w, dtype)


def _azimuth_spectrum(values, lmax, n_phi):
    """$\\int_0^{2\\pi} g(\\Delta)\\cos(q\\Delta)\\,d\\Delta$ for q = 0..lmax from samples at Δ_k = 2πk/K (last axis)."""
    spec = jnp.real(jnp.fft.rfft(values, axis=-1)) * (2 * jnp.pi / n_phi)
    q = np.arange(lmax + 1) % n_phi
    q = np.minimum(q, n_phi - q)  # cos(q D_k) = cos((K - q) D_k) on the K-point grid: fold, never clamp
    return spec[..., q]


def brdf_sh_coefficients(
    transfer: Callable, lmax: int, n_theta: int = 64, n_phi: int = 128, dtype=None
) -> Float[Array, "l p q"]:
    """The coefficients $\\hat\\rho_{lpq}$ of an isotropic transfer function (R&H eq. 8).

    $$\\hat\\rho_{lpq} = 2\\pi\\iint N_{lq}P_l^q(\\cos\\theta_i)\\,N_{pq}P_p^q(\\cos\\theta_o)\\,
      G_q(\\theta_i, \\theta_o)\\,\\sin\\theta_i\\sin\\theta_o\\,d\\theta_i\\,d\\theta_o,\\quad
      G_q = \\int_0^{2\\pi}\\hat\\rho(\\theta_i, \\theta_o, \\Delta)\\cos(q\\Delta)\\,d\\Delta,$$
    by `n_theta`-point Gauss-Legendre rules in $\\cos\\theta_i$ and $\\cos\\theta_o$ on
    the upper hemisphere and an FFT over `n_phi` uniform samples of Δφ.
    Layout `rho[l, p, q]`, q ≥ 0 (module docstring). For the reciprocal form
    $\\tilde\\rho = \\hat\\rho\\cos\\theta_o$ of eq. 13 pass that transfer function;
    reciprocity then reads $\\tilde\\rho_{lpq} = \\tilde\\rho_{plq}$.
    """
    lmax = check_lmax(lmax)
    nt = check_positive_int(n_theta, "n_theta")
    npf = check_positive_int(n_phi, "n_phi")
    dt = _default_dtype(dtype)
    th, w = _hemisphere_nodes(nt, dt)
    dphi = jnp.asarray(2 * np.pi * np.arange(npf) / npf, dt)
    vals = transfer(th[:, None, None], th[None, :, None], dphi[None, None, :])
    vals = jnp.broadcast_to(jnp.asarray(vals, dt), (nt, nt, npf))
    g = _azimuth_spectrum(vals, lmax, npf)  # (i, o, q)
    z = _zonal_table(th, lmax, dt) * w[:, None, None]  # (n, l, q)
    return 2 * jnp.pi * jnp.einsum("ilq,opq,ioq->lpq", z, z, g)


def brdf_incident_coefficients(
    transfer: Callable, theta_o: Real[ArrayLike, ""], lmax: int, n_theta: int = 96, n_phi: int = 128, dtype=None
) -> Float[Array, " n_coeffs"]:
    """$\\hat\\rho_{lq}(\\omega_o') = \\int \\hat\\rho(\\omega_i', \\omega_o')\\,Y_{lq}(\\omega_i')\\,d\\omega_i'$ at a fixed view.

    The view is at polar angle `theta_o` and azimuth $\\phi_o' = 0$ in the
    local frame. Equals $\\sum_p \\hat\\rho_{lpq} Y_{pq}(\\omega_o')$ without the
    truncation in $p$, so $B(\\alpha,\\beta,\\omega_o') = \\sum_{l,m,q} L_{lm}
    D^l_{mq}(\\alpha)e^{im\\beta}\\hat\\rho_{lq}(\\omega_o')$ exactly for lighting
    band-limited to `lmax` (see `reflect_sh`). Flat `(n_coeffs,)` layout,
    real (the transfer function is even in Δφ); $\\hat\\rho_{l,-q} = (-1)^q\\hat\\rho_{lq}$.

    **Arguments:** `transfer` as in the module docstring; `theta_o`: a
    scalar in $[0, \\pi/2]$ (another shape, or a view below the horizon, is a
    `ValueError` naming it: one view per call); `lmax` ≥ 0; `n_theta`, `n_phi`:
    quadrature sizes (orders $q > $ `n_phi`/2 get the `n_phi`-point rule's
    aliased value, that of $\\min(q, n_\\phi - q)$: take `n_phi` > 2·`lmax`);
    `dtype`: of the result (default: that of `theta_o` and the default float).
    """
    lmax = check_lmax(lmax)
    nt = check_positive_int(n_theta, "n_theta")
    npf = check_positive_int(n_phi, "n_phi")
    theta_o = as_float_scalar(theta_o, "theta_o")
    theta_o = check_values(theta_o, lambda a: (a < 0) | (a > jnp.pi / 2), "theta_o", "in [0, pi/2] (a view above the horizon)")
    dt = _default_dtype(dtype) if dtype is not None else jnp.result_type(_default_dtype(None), theta_o)
    theta_o = theta_o.astype(dt)
    th, w = _hemisphere_nodes(nt, dt)
    # Y_lq(θi, φi) with Δ = φo − φi = −φi: ∫ g(Δ) e^{iqφi} dφi = ∫ g(Δ) e^{-iqΔ} dΔ = G_q (g even).
    dphi = jnp.asarray(2 * np.pi * np.arange(npf) / npf, dt)
    vals = transfer(th[:, None], theta_o, dphi[None, :])
    vals = jnp.broadcast_to(jnp.asarray(vals, dt), (nt, npf))
    g = _azimuth_spectrum(vals, lmax, npf)  # (i, q)
    z = _zonal_table(th, lmax, dt) * w[:, None, None]  # (i, l, q)
    lq = jnp.einsum("ilq,iq->lq", z, g)
    ls, ms = sh_degrees(lmax), sh_orders(lmax)
    # Y_{l,-q} = (-1)^q conj(Y_lq) and G_q is real: rho_{l,-q} = (-1)^q rho_{lq}.
    sign = np.where(ms < 0, (-1.0) ** np.abs(ms), 1.0)
    return lq[ls, np.abs(ms)] * jnp.asarray(sign, dt)


def light_field_coefficients(
    L: Complex[ArrayLike, " n_coeffs"], rho: Real[ArrayLike, "l p q"]
) -> Complex[Array, "n_coeffs p q2"]:
    """$B_{lmpq} = \\Lambda_l L_{lm}\\hat\\rho_{lpq}$ (R&H eq. 10).

    `L`: complex lighting coefficients (`real_to_complex_coeffs` of a real
    expansion), `(n_coeffs,)`; `rho`: `(lmax+1, lmax+1, lmax+1)` from
    `brdf_sh_coefficients`. Returns `B[(l, m), p, q + lmax]`.
    """
    L = as_float_array(L, "L", complex_ok=True)
    rho = as_float_array(rho, "rho")
    if rho.ndim != 3:
        raise ValueError(f"`rho` must have shape (lmax+1, lmax+1, lmax+1), got {tuple(rho.shape)}")
    lmax = rho.shape[0] - 1
    if rho.shape != (lmax + 1,) * 3:
        raise ValueError(f"`rho` must have shape (lmax+1, lmax+1, lmax+1), got {tuple(rho.shape)}")
    if L.shape != ((lmax + 1) ** 2,):
        raise ValueError(f"`L` must have shape ({(lmax + 1) ** 2},) to match `rho`, got {tuple(L.shape)}")
    q = np.arange(-lmax, lmax + 1)
    full = rho[:, :, np.abs(q)]  # (l, p, q2)
    ls = sh_degrees(lmax)
    lam = jnp.asarray(sh_lambda(lmax), rho.dtype)
    lam_l = lam[ls].astype(L.dtype) * L
    return lam_l[:, None, None] * full[ls].astype(L.dtype)


def light_field_basis(
    alpha: Real[ArrayLike, ""], beta: Real[ArrayLike, ""], wo_local: Real[ArrayLike, "3"] | SequenceLike, lmax: int
) -> Complex[Array, "n_coeffs p q2"]:
    """$C_{lmpq}(\\alpha, \\beta, \\omega_o') = \\Lambda_l^{-1} D^l_{mq}(\\alpha) e^{im\\beta} Y_{pq}(\\omega_o')$ (R&H eq. 9).

    Same layout as `light_field_coefficients` (entries with |q| > l or |q| > p are 0).

    **Arguments:** `alpha`, `beta`: the normal's angles, scalars (shape
    `()`); `wo_local`: the local view direction `(3,)` (normalized by
    `complex_sh`); `lmax` ≥ 0. Another shape is a `ValueError` naming the
    argument.
    """
    lmax = check_lmax(lmax)
    alpha = as_float_scalar(alpha, "alpha")
    beta = as_float_scalar(beta, "beta")
    wo_local = check_nonzero_dirs(wo_local, "wo_local")
    if wo_local.shape != (3,):
        raise ValueError(f"`wo_local` must have shape (3,), got {tuple(wo_local.shape)}")
    d = wigner_d_y(alpha, lmax)  # (n, n) block-diagonal in the complex basis
    ls, ms = sh_degrees(lmax), sh_orders(lmax)
    q = np.arange(-lmax, lmax + 1)
    # D^l_{mq}: row (l, m), column (l, q) when |q| <= l.
    valid_lq = np.abs(q)[None, :] <= ls[:, None]
    col = np.where(valid_lq, ls[:, None] ** 2 + ls[:, None] + q[None, :], 0)
    dmq = jnp.take_along_axis(d, jnp.asarray(col), axis=1) * jnp.asarray(valid_lq, d.dtype)  # (n, q2)
    yo = complex_sh(wo_local, lmax)  # (n,)
    p = np.arange(lmax + 1)
    valid_pq = np.abs(q)[None, :] <= p[:, None]
    ycol = np.where(valid_pq, p[:, None] ** 2 + p[:, None] + q[None, :], 0)
    ypq = yo[ycol] * jnp.asarray(valid_pq, yo.dtype)  # (p, q2)
    lam_inv = jnp.asarray(1.0 / sh_lambda(lmax), d.dtype)[ls].astype(yo.dtype)
    phase = _expi(jnp.asarray(ms, beta.dtype) * beta).astype(yo.dtype)
    return (lam_inv * phase)[:, None, None] * dmq.astype(yo.dtype)[:, None, :] * ypq[None, :, :]


def factorize_light_field(Bt: Complex[ArrayLike, "n_coeffs p q2"]):
    """Lighting and BRDF from reciprocal light-field coefficients, up to scale (R&H sec. 5.1).

    With $\\tilde B_{lmpq} = \\Lambda_l L_{lm}\\tilde\\rho_{lpq}$ (eq. 13) and the
    scale fixed by $L_{00} = \\Lambda_0^{-1}$:
    $L_{lm} = \\Lambda_l^{-1}\\tilde B_{lm00}/\\tilde B_{00l0}$ and
    $\\tilde\\rho_{lpq} = \\tilde B_{lmpq}\\tilde B_{00l0}/\\tilde B_{lm00}$ (any m with
    $\\tilde B_{lm00} \\ne 0$; here the m of largest $|\\tilde B_{lm00}|$, the best
    conditioned). Returns `(L (n_coeffs,) complex, rho (l, p, q) real)`.
    Requires $\\tilde B_{00l0} \\ne 0$ and, for each l, some $L_{lm}\\ne 0$ — the
    paper's condition; orders that violate it come back as NaN, visibly.
    """
    Bt = as_float_array(Bt, "Bt", complex_ok=True)
    if Bt.ndim != 3:
        raise ValueError(f"`Bt` must have shape (n_coeffs, lmax+1, 2 lmax+1), got {tuple(Bt.shape)}")
    n, p1, q2 = Bt.shape
    lmax = p1 - 1
    if n != (lmax + 1) ** 2 or q2 != 2 * lmax + 1:
        raise ValueError(f"`Bt` must have shape (n_coeffs, lmax+1, 2 lmax+1), got {tuple(Bt.shape)}")
    lam = jnp.asarray(sh_lambda(lmax))
    ls = sh_degrees(lmax)
    b00l0 = Bt[0, :, lmax]  # B~_{00 l 0}, indexed by l (as p)
    blm00 = Bt[:, 0, lmax]  # B~_{lm00}
    L = blm00 / (lam[ls].astype(Bt.dtype) * b00l0[ls])
    rho = []
    for l in range(lmax + 1):
        rows = slice(l * l, (l + 1) ** 2)
        k = jnp.argmax(jnp.abs(blm00[rows]))
        num = Bt[rows][k]  # (p, q2)
        rho.append(num * b00l0[l] / blm00[rows][k])
    rho = jnp.stack(rho)  # (l, p, q2)
    return L, jnp.real(rho[:, :, lmax:])


def reflect_sh(
    L: Inexact[ArrayLike, " n_coeffs"],
    rho_i: Real[ArrayLike, " n_coeffs"],
    alpha: Real[ArrayLike, ""],
    beta: Real[ArrayLike, ""],
    phi_o: Real[ArrayLike, ""] = 0.0,
) -> Float[Array, ""]:
    r"""Reflected radiance from SH lighting and incident BRDF coefficients (R&H eqs. 5-10).

    $$B(\alpha, \beta, \theta_o', \phi_o') = \sum_{l,m,q} L_{lm}\,D^l_{mq}(\alpha)\,
      e^{im\beta}\,\hat\rho_{lq}(\theta_o', 0)\,e^{iq\phi_o'},$$
    for the normal $(\alpha, \beta)$ (local frame $R_{\alpha,\beta} = R_z(\beta)R_y(\alpha)$),
    with `rho_i` from `brdf_incident_coefficients(transfer, theta_o, lmax)` and
    `L` complex lighting coefficients of the same lmax. Exact for lighting
    band-limited to lmax. Returns the real radiance.

    **Arguments:** `L`, `rho_i`: `(n_coeffs,)` each (`L` complex; a real array is read as complex coefficients
    with zero imaginary parts, e.g. those of a lighting even in φ); `alpha`, `beta`,
    `phi_o`: scalars (shape `()`). One normal and view per call: an array
    of angles is a `ValueError` naming the argument (it is not summed or
    broadcast over; `jax.vmap` evaluates many).

    **Returns:** a scalar `()`.
    """
    L = as_float_array(L, "L", complex_ok=True)
    if not jnp.issubdtype(L.dtype, jnp.complexfloating):  # real-valued complex coefficients: keep the phases
        L = jax.lax.complex(L, jnp.zeros_like(L))
    rho_i = as_float_array(rho_i, "rho_i")
    if L.ndim != 1 or rho_i.shape != L.shape:
        raise ValueError(f"`L` and `rho_i` must both have shape (n_coeffs,), got {L.shape} and {rho_i.shape}")
    lmax = lmax_from_size(L.shape[0], "L")
    alpha = as_float_scalar(alpha, "alpha")
    beta = as_float_scalar(beta, "beta")
    phi_o = as_float_scalar(phi_o, "phi_o")
    ms = sh_orders(lmax)
    d = wigner_d_y(alpha, lmax).astype(L.dtype)  # d[(l,m),(l,q)]
    mf = jnp.asarray(ms, alpha.dtype)
    phase_m = _expi(mf * beta.astype(alpha.dtype)).astype(L.dtype)
    phase_q = _expi(mf * phi_o.astype(alpha.dtype)).astype(L.dtype)
    return jnp.real(jnp.sum((L * phase_m) * (d @ (rho_i.astype(L.dtype) * phase_q))))


def mirror_brdf_coefficients(lmax: int, dtype=None) -> Float[Array, "l p q"]:
    """$\\hat\\rho_{lpq} = (-1)^q\\delta_{lp}$: the mirror BRDF (R&H eq. 14), layout `rho[l, p, q]`.

    (The delta function cannot be projected numerically; this is its closed
    form. With it, the light field at view $\\omega_o'$ is the lighting in the
    mirror direction.)
    """
    lmax = check_lmax(lmax)
    out = np.zeros((lmax + 1,) * 3)
    for l in range(lmax + 1):
        for q in range(l + 1):
            out[l, l, q] = (-1.0) ** q
    return jnp.asarray(out, _default_dtype(dtype))
