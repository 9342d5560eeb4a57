"""Brute-force reference integrator of the reflection equation (for tests and notebooks).

Slow and simple on purpose: it shares no code path with the frequency-space
machinery it checks (no SH, no rotations).
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

from ._checks import check_dirs, check_positive_int
from ._reflectance import tangent_frame


def reflect_quadrature(
    lighting: Callable,
    brdf: Callable,
    normals: Real[ArrayLike, "*#batch 3"],
    views: Real[ArrayLike, "*#batch 3"],
    n_theta: int = 64,
    n_phi: int = 128,
) -> Float[Array, "..."]:
    """$B(n, \\omega_o) = \\int_{\\Omega^+} L(\\omega_i)\\,\\rho(\\omega_i, \\omega_o, n)\\,(\\omega_i\\cdot n)\\,d\\omega_i$ by quadrature.

    The reflection equation (R&H 2001 eq. 2) over the hemisphere about each
    normal: Gauss-Legendre in $\\cos\\theta_i$ on [0, 1] (`n_theta` nodes) ×
    `n_phi` uniform azimuths. Converges spectrally for smooth integrands;
    sharp lobes need nodes finer than the lobe in both angles (`n_theta` ≳ 10/σ
    and `n_phi` likewise: a grazing lobe at σ 0.1 came out 35 % low with
    `n_theta=100` and the default `n_phi=128`, and converged at (400, 2048)).

    **Arguments:**

    - `lighting(dirs (..., 3)) -> (...) or (..., C)`: distant radiance.
    - `brdf(wi, wo, n) -> (...)`: BRDF value (not times cosine) with
      broadcasting batch dims.
    - `normals`, `views`: unit vectors `(..., 3)`, broadcast together.

    **Returns:** `(...)` or `(..., C)`.
    """
    normals = check_dirs(normals, "normals")
    views = check_dirs(views, "views")
    nt = check_positive_int(n_theta, "n_theta")
    npf = check_positive_int(n_phi, "n_phi")
    dt = jnp.result_type(normals.dtype, views.dtype)
    batch = jnp.broadcast_shapes(normals.shape[:-1], views.shape[:-1])
    n = jnp.broadcast_to(normals, batch + (3,)).astype(dt)
    v = jnp.broadcast_to(views, batch + (3,)).astype(dt)
    x, w = np.polynomial.legendre.leggauss(nt)
    u = 0.5 * (x + 1.0)
    wts = np.outer(0.5 * w, np.full(npf, 2 * np.pi / npf)).reshape(-1)
    phi = 2 * np.pi * (np.arange(npf) + 0.5) / npf
    s = np.sqrt(1 - u * u)
    local = np.stack(np.broadcast_arrays(s[:, None] * np.cos(phi), s[:, None] * np.sin(phi), u[:, None]), -1)
    local = jnp.asarray(local.reshape(-1, 3), dt)  # (K, 3)
    t, b = tangent_frame(n)
    lead = (1,) * len(batch)
    wi = (
        local[:, 0].reshape((-1,) + lead + (1,)) * t[None]
        + local[:, 1].reshape((-1,) + lead + (1,)) * b[None]
        + local[:, 2].reshape((-1,) + lead + (1,)) * n[None]
    )  # (K, *batch, 3)
    cos_i = local[:, 2].reshape((-1,) + lead)
    rho = brdf(wi, v[None], n[None])
    li = jnp.asarray(lighting(wi), dt)
    f = rho * cos_i
    wk = jnp.asarray(wts, dt).reshape((-1,) + lead)
    if li.ndim == f.ndim + 1:
        return jnp.sum((wk * f)[..., None] * li, axis=0)
    return jnp.sum(wk * f * li, axis=0)
