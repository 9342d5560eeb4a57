"""Direct recovery of the SH BRDF coefficients $\\hat\\rho_{lpq}$ under known lighting (R&H 2001 sec. 6.1).

On a sphere, a pixel with normal $(\\alpha, \\beta)$ and local view $\\omega_o'$
sees (eqs. 9, 10)

$$B = \\sum_{l,m,p,q} \\Lambda_l L_{lm}\\,\\hat\\rho_{lpq}\\,C_{lmpq}(\\alpha, \\beta, \\omega_o'),
  \\qquad C_{lmpq} = \\Lambda_l^{-1} D^l_{mq}(\\alpha)e^{im\\beta}Y_{pq}(\\omega_o'),$$

linear in the isotropic BRDF coefficients $\\hat\\rho_{lpq} = \\hat\\rho_{l,p,-q}$
(layout `rho[l, p, q]`, $q \\ge 0$, of `jaxsh.brdf_sh_coefficients`). The
paper "simply solves a linear system"; `fit_brdf_sh` does so per colour
channel by a minimum-norm SVD least-squares solve and reports the rank, so
coefficients the views and lighting do not excite are visible as such. As
the paper notes, a truncated SH BRDF rings; a low-frequency lighting only
needs, and only determines, its low orders.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, Real

import jaxsh

from ._data import Observations, Status
from ._threads import blas_single_thread


class BRDFSHResult(eqx.Module):
    """Result of `fit_brdf_sh`: `rho` `(lmax+1, lmax+1, lmax+1, C)`, `rank` `(C,)` of the design
    matrix, `n_unknowns` (entries with $q \\le \\min(l, p)$), `status`, `rms`, `rel_rms`."""

    rho: Float[Array, "l p q C"]
    rank: Int[Array, " C"]
    n_unknowns: int = eqx.field(static=True)
    status: Status
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]


def _frame_angles(n, v):
    """(alpha, beta) of the normal and the view in the local frame R_{alpha,beta} = Rz(beta) Ry(alpha)."""
    alpha = jnp.arccos(jnp.clip(n[..., 2], -1.0, 1.0))
    beta = jnp.arctan2(n[..., 1], n[..., 0])
    ca, sa, cb, sb = jnp.cos(alpha), jnp.sin(alpha), jnp.cos(beta), jnp.sin(beta)
    # R^T v with R = Rz(b) Ry(a): first Rz(-b), then Ry(-a)
    x1 = cb * v[..., 0] + sb * v[..., 1]
    y1 = -sb * v[..., 0] + cb * v[..., 1]
    z1 = v[..., 2]
    wo = jnp.stack([ca * x1 - sa * z1, y1, sa * x1 + ca * z1], -1)
    return alpha, beta, wo


def brdf_sh_design(normals, views, L_complex, lmax: int):
    """Design rows d B / d rho[l, p, q] for each pixel: `(N, lmax+1, lmax+1, lmax+1)` (eqs. 9, 10)."""
    alpha, beta, wo = _frame_angles(normals, views)
    dt = normals.dtype

    def one(a, b, w):
        basis = jaxsh.light_field_basis(a, b, w, lmax)

        def bval(rho):
            return jnp.real(jnp.sum(jaxsh.light_field_coefficients(L_complex, rho) * basis))

        return jax.grad(bval)(jnp.zeros((lmax + 1,) * 3, dt))

    return jax.vmap(one)(alpha, beta, wo)


@blas_single_thread
def fit_brdf_sh(obs: Observations, lighting_sh: Real[ArrayLike, "n_coeffs C"], lmax: int, *, rcond: float | None = None) -> BRDFSHResult:
    """Solve for $\\hat\\rho_{lpq}$, $l, p \\le$ `lmax`, from images of a sphere under known lighting (module docstring).

    **Arguments:** `obs` (convex object: no visibility terms); `lighting_sh`
    real SH lighting `(n_coeffs, C)` with at least `lmax`; `lmax` static;
    `rcond` for the SVD (default 1e-10 in float64, 1e-5 in float32).
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations, got {type(obs).__name__}")
    if obs.transfer is not None or obs.reflected_visibility is not None:
        raise ValueError("fit_brdf_sh: the SH light-field model (eqs. 9, 10) has no shadowing; use a convex object")
    lmax = int(lmax)
    L = jnp.asarray(lighting_sh, obs.values.dtype)
    if L.ndim == 1:
        L = L[:, None]
    n = jaxsh.num_coeffs(lmax)
    if L.ndim != 2 or L.shape[0] < n or L.shape[1] not in (1, obs.n_channels):
        raise ValueError(f"`lighting_sh` must have shape (>= {n}, {obs.n_channels}), got {tuple(L.shape)}")
    L = jnp.broadcast_to(L[:n], (n, obs.n_channels))
    dt = obs.values.dtype
    rcond = (1e-10 if dt == jnp.float64 else 1e-5) if rcond is None else float(rcond)
    ls, ps, qs = np.meshgrid(np.arange(lmax + 1), np.arange(lmax + 1), np.arange(lmax + 1), indexing="ij")
    valid = (qs <= np.minimum(ls, ps)).reshape(-1)
    return _fit_brdf_sh(obs, L, lmax, jnp.asarray(np.nonzero(valid)[0]), rcond)


@eqx.filter_jit
def _fit_brdf_sh(obs, L, lmax, cols, rcond):
    lc = jaxsh.real_to_complex_coeffs(L, channels=True)  # (n, C) complex
    sw = jnp.sqrt(obs.weights)

    def channel(lcc, b):
        a = brdf_sh_design(obs.normals, obs.views, lcc, lmax).reshape(obs.n_samples, -1)[:, cols]
        a = a * sw[:, None]
        u, s, vt = jnp.linalg.svd(a, full_matrices=False)
        keep = s > rcond * s[0]
        x = vt.T @ (jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0) * (u.T @ (sw * b)))
        r = a @ x - sw * b
        return x, jnp.sum(keep), jnp.sum(r * r)

    x, rank, rss = jax.vmap(channel, in_axes=(1, 1))(lc, obs.values)
    c = L.shape[1]
    rho = jnp.zeros(((lmax + 1) ** 3, c), obs.values.dtype).at[cols].set(x.T).reshape((lmax + 1,) * 3 + (c,))
    nobs = jnp.sum((obs.weights > 0).astype(rss.dtype)) * c
    rms = jnp.sqrt(jnp.sum(rss) / nobs)
    rel = rms / jnp.sqrt(jnp.sum(obs.weights[:, None] * obs.values**2) / nobs)
    status = Status.where(jnp.all(jnp.isfinite(rho)), Status.converged, Status.nonfinite)
    return BRDFSHResult(rho, rank, int(cols.shape[0]), status, rms, rel)


def predict_brdf_sh(rho, lighting_sh, normals, views):
    """Radiance of SH BRDF coefficients `rho` `(l, p, q, C)` under SH lighting at pixels `(N, 3)` (eqs. 9, 10)."""
    rho = jnp.asarray(rho)
    lmax = rho.shape[0] - 1
    L = jnp.asarray(lighting_sh, rho.dtype)[: jaxsh.num_coeffs(lmax)]
    lc = jaxsh.real_to_complex_coeffs(L, channels=True)
    alpha, beta, wo = _frame_angles(jnp.asarray(normals, rho.dtype), jnp.asarray(views, rho.dtype))

    def one(a, b, w):
        basis = jaxsh.light_field_basis(a, b, w, lmax)
        return jax.vmap(lambda lcc, r: jnp.real(jnp.sum(jaxsh.light_field_coefficients(lcc, r) * basis)),
                        in_axes=(1, 3))(lc, rho)

    return jax.vmap(one)(alpha, beta, wo)
