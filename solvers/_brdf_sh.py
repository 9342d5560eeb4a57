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
from jaxtyping import Array, Float, Int

import jaxsh

from ._data import Lighting, Observations, view_lightings
from ._lapack import map_lapack
from ._results import Solution, Status, check_float, check_int, finish, rms_pair, signal_status, worst
from ._threads import blas_single_thread


def _is_number_list(x) -> bool:
    """A nested list of numbers (an SH array given as lists), not a sequence of `Lighting`."""
    return isinstance(x, (list, tuple)) and len(x) > 0 and not isinstance(x[0], Lighting)


class BRDFSHResult(Solution):
    """Result of `fit_brdf_sh` (a `solvers.Solution`; `estimate` is `rho`).

    - `rho`: `(lmax+1, lmax+1, lmax+1, C)` the coefficients $\\hat\\rho_{lpq}$.
    - `rank`: `(C,)` numerical rank of the weighted design matrix.
    - `n_unknowns`: entries with $q \\le \\min(l, p)$ (static).
    - `status`: `converged`, `nonfinite` or `no_signal` (all-zero data, or
      all-zero lighting in some channel: a zero design; a rank below
      `n_unknowns` is reported by `rank`, the solution being minimum-norm).
    - `iterations`: 0 (a direct solve); `rms`, `rel_rms` (never NaN).
    - `stats`: `singular_values` `(C, n_unknowns)` of the design matrix
      (descending; zero-padded when there are fewer samples than unknowns),
      `n_obs` (weighted samples × channels).
    """

    rho: Float[Array, "l p q C"]
    rank: Int[Array, " C"]
    n_unknowns: int = eqx.field(static=True)
    status: Status
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    iterations: Int[Array, ""]
    stats: dict

    @property
    def estimate(self) -> Float[Array, "l p q C"]:
        return self.rho


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


def brdf_sh_design(normals, views, L_complex, lmax: int, view_index=None):
    """Design rows d B / d rho[l, p, q] for each pixel: `(N, lmax+1, lmax+1, lmax+1)` (eqs. 9, 10).

    `L_complex` `(n,)` is one lighting for all pixels, or `(K, n)` one per view with `view_index` `(N,)`.
    """
    alpha, beta, wo = _frame_angles(normals, views)
    dt = normals.dtype
    def one(a, b, w, L_complex=L_complex):
        basis = jaxsh.light_field_basis(a, b, w, lmax)

        def bval(rho):
            return jnp.real(jnp.sum(jaxsh.light_field_coefficients(L_complex, rho) * basis))

        return jax.grad(bval)(jnp.zeros((lmax + 1,) * 3, dt))

    if view_index is not None:
        return jax.vmap(lambda a, b, w, k: one(a, b, w, L_complex[k]))(alpha, beta, wo, view_index)
    return jax.vmap(one)(alpha, beta, wo)


@blas_single_thread
def fit_brdf_sh(
    obs: Observations,
    lighting_sh,
    lmax: int,
    *,
    rcond: float | None = None,
    throw: bool = False,
) -> BRDFSHResult:
    """Solve for $\\hat\\rho_{lpq}$, $l, p \\le$ `lmax`, from images of a sphere under known lighting (module docstring).

    **Arguments:** `obs` (convex object: no visibility terms); `lighting_sh`
    real SH lighting `(n_coeffs, C)` with at least `lmax`, a `solvers.Lighting`
    (all of it, as SH to `lmax`: `Lighting.total_sh`), or a sequence of one
    `Lighting` per view of `obs` (`obs.view_index`; each view's design rows use
    its own lighting, memory $O(N)$); `lmax` static;
    `rcond` for the SVD, a finite number >= 0 (default 1e-10 in float64, 1e-5 in float32);
    `throw`: raise `solvers.SolveError` unless the status is `converged`.
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations, got {type(obs).__name__}")
    if obs.transfer is not None or obs.reflected_visibility is not None or obs.fast_visibility is not None:
        raise ValueError("fit_brdf_sh: the SH light-field model (eqs. 9, 10) has no shadowing; use a convex object")
    lmax = check_int(lmax, "lmax", lo=0)
    rcond = None if rcond is None else check_float(rcond, "rcond")
    n = jaxsh.num_coeffs(lmax)
    # disks are fine here: each view's lighting enters as `total_sh` (disks in closed form), no sigma to split by
    lights = view_lightings(obs, lighting_sh, "lighting_sh", allow_disks=True) if not isinstance(lighting_sh, (Lighting, jax.Array, np.ndarray)) and not _is_number_list(lighting_sh) else None
    if isinstance(lighting_sh, Lighting):
        lighting_sh = lighting_sh.total_sh(lmax)
    if lights is not None:
        c = obs.n_channels
        for k, lit in enumerate(lights):
            if lit.n_channels not in (1, c):
                raise ValueError(f"`lighting_sh[{k}]` has {lit.n_channels} channels, the images {c}")
        L = jnp.stack([jnp.broadcast_to(lit.total_sh(lmax).astype(obs.values.dtype), (n, c)) for lit in lights])
        dt = obs.values.dtype
        rcond = (1e-10 if dt == jnp.float64 else 1e-5) if rcond is None else float(rcond)
        ls, ps, qs = np.meshgrid(np.arange(lmax + 1), np.arange(lmax + 1), np.arange(lmax + 1), indexing="ij")
        valid = (qs <= np.minimum(ls, ps)).reshape(-1)
        return finish(_fit_brdf_sh(obs, L, lmax, jnp.asarray(np.nonzero(valid)[0]), rcond), throw)
    L = jnp.asarray(lighting_sh, obs.values.dtype)
    if L.ndim == 1:
        L = L[:, None]
    if L.ndim != 2 or L.shape[0] < n or L.shape[1] not in (1, obs.n_channels):
        raise ValueError(f"`lighting_sh` must have shape (>= {n}, {obs.n_channels}), got {tuple(L.shape)}")
    L = jnp.broadcast_to(L[:n], (n, obs.n_channels))
    dt = obs.values.dtype
    rcond = (1e-10 if dt == jnp.float64 else 1e-5) if rcond is None else float(rcond)
    ls, ps, qs = np.meshgrid(np.arange(lmax + 1), np.arange(lmax + 1), np.arange(lmax + 1), indexing="ij")
    valid = (qs <= np.minimum(ls, ps)).reshape(-1)
    return finish(_fit_brdf_sh(obs, L, lmax, jnp.asarray(np.nonzero(valid)[0]), rcond), throw)


@jaxsh.jit
def _fit_brdf_sh(obs, L, lmax, cols, rcond):
    per_view = L.ndim == 3  # (K, n, C): one lighting per view
    if per_view:
        lc = jax.vmap(lambda x: jaxsh.real_to_complex_coeffs(x, channels=True))(L)  # (K, n, C)
    else:
        lc = jaxsh.real_to_complex_coeffs(L, channels=True)  # (n, C) complex
    sw = jnp.sqrt(obs.weights)

    def channel(lcc, b):
        vi = obs.view_index if per_view else None
        a = brdf_sh_design(obs.normals, obs.views, lcc, lmax, vi).reshape(obs.n_samples, -1)[:, cols]
        a = a * sw[:, None]
        u, s, vt = jnp.linalg.svd(a, full_matrices=False)
        keep = s > rcond * s[0]
        x = vt.T @ (jnp.where(keep, 1.0 / jnp.where(keep, s, 1.0), 0.0) * (u.T @ (sw * b)))
        r = a @ x - sw * b
        # (n_unknowns,) whatever the pixel count: the SVD gives min(N, n_unknowns) values, the rest are 0
        return x, jnp.sum(keep), jnp.sum(r * r), jnp.pad(s, (0, cols.shape[0] - s.shape[0]))

    # one channel at a time on a CPU (`map_lapack`: a batched CPU SVD can deadlock, `solvers._lapack`)
    x, rank, rss, sv = map_lapack(channel, jnp.moveaxis(lc, 2 if per_view else 1, 0), jnp.moveaxis(obs.values, 1, 0))
    c = L.shape[-1]
    rho = jnp.zeros(((lmax + 1) ** 3, c), obs.values.dtype).at[cols].set(x.T).reshape((lmax + 1,) * 3 + (c,))
    nobs = jnp.sum((obs.weights > 0).astype(rss.dtype)) * c
    data_ss = jnp.sum(obs.weights[:, None] * obs.values**2)
    rms, rel = rms_pair(jnp.sum(rss), data_ss, nobs)
    # sv[:, 0]: the largest singular value of each channel's design, 0 under all-zero lighting (no signal)
    # a residual or data energy that overflowed (float32 data beyond ~1e15, docs/conventions.md) is not converged
    finite = jnp.all(jnp.isfinite(rho)) & jnp.isfinite(rms) & jnp.isfinite(data_ss)
    status = worst(Status.where(finite, Status.converged, Status.nonfinite), signal_status(data_ss),
                   signal_status(jnp.min(sv[:, 0])))
    return BRDFSHResult(rho=rho, rank=rank, n_unknowns=int(cols.shape[0]), status=status, rms=rms, rel_rms=rel,
                        iterations=jnp.asarray(0), stats={"singular_values": sv, "n_obs": nobs})


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
