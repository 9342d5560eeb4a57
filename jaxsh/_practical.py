"""The practical model of R&H 2001 eq. 24, factored for fitting: `practical_terms`.

For fixed geometry (normals, views, visibility) and fixed lighting, every
pixel's radiance in eq. 24 is an explicit, cheap function of the BRDF
parameters:

$$B = K_d\\,E + K_s\\,F(\\mu, \\theta_o)\\Big[\\sum_{l=0}^{l_{max}} e^{-(\\sigma l)^2} P_l(R)
   + \\frac{1}{4\\cos\\theta_o}\\sum_j \\frac{e^{-(\\theta_{h,j}/\\sigma)^2}}{\\pi\\sigma^2} V_j L_j\\Big],$$

with $P_l(R) = V_R\\sum_m L_{lm} Y_{lm}(R)$ the band-$l$ part of the slow
lighting at the mirror direction (the filter of eq. 20 acts per band, so
$L_{slow}(R)$ of eq. 22 is $\\sum_l e^{-(\\sigma l)^2} P_l$). `practical_terms`
computes $E$, $P_l$, $\\cos\\theta_o$ and $\\theta_{h,j}$ once; evaluating the
model for new $(K_d, K_s, \\mu, \\sigma)$ then costs $O(N\\,l_{max})$ and no SH
evaluation, which is what the BRDF solvers of sec. 6.1 need inside their
simplex and Levenberg–Marquardt loops. It equals `render_practical` (same
conventions, same visibility terms, exact diffuse term of fast sources).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Real
from ._custom_types import SequenceLike

from ._checks import as_float_array, check_dirs
from ._indexing import sh_degrees
from ._reflectance import fresnel_normalized, half_angle, reflect
from ._sh import _real_sh_flat, _unit_vectors
from ._spectra import lambertian_spectrum, microfacet_spectrum


class PracticalTerms(eqx.Module):
    """Per-pixel precomputed terms of R&H eq. 24 (see the module docstring).

    **Fields** (`N` pixels, `C` channels, `J` fast sources):

    - `visible`: `(N,)` bool, $\\cos\\theta_o > 0$.
    - `cos_o`: `(N,)` $\\cos\\theta_o$ (1 where not visible).
    - `irradiance`: `(N, C)` $E$: the 9-term (or transfer-vector) irradiance of
      the slow lighting plus the exact shadowed cosine of the fast sources.
    - `bands`: `(N, lmax+1, C)` $P_l(R)$, reflected-ray visibility included.
    - `theta_h`: `(N, J)` half-angle of each fast source.
    - `fast_weight`: `(N, J)` $V_j\\,[\\cos\\theta_{i,j} > 0]$.
    - `fast_energy`: `(J, C)` $L_j$.

    Call it as `terms(kd, ks, mu, sigma)` for `B` `(N, C)`; `kd`, `ks` are
    `(C,)` or per-pixel `(N, C)`; `mu=None` means $F = 1$.
    """

    visible: Bool[Array, " N"]
    cos_o: Float[Array, " N"]
    irradiance: Float[Array, "N C"]
    bands: Float[Array, "N L C"]
    theta_h: Float[Array, "N J"]
    fast_weight: Float[Array, "N J"]
    fast_energy: Float[Array, "J C"]

    @property
    def lmax(self) -> int:
        return self.bands.shape[1] - 1

    def fresnel(self, mu):
        """$F(\\mu, \\theta_o)$ normalized to 1 at normal incidence, `(N,)`."""
        if mu is None:
            return jnp.ones_like(self.cos_o)
        return fresnel_normalized(self.cos_o, jnp.asarray(mu, self.cos_o.dtype))

    def specular_unit(self, mu, sigma):
        """The bracket of eq. 24 times $F$: the radiance for $K_s = 1$, `(N, C)`."""
        dt = self.cos_o.dtype
        sigma = jnp.asarray(sigma, dt)
        filt = microfacet_spectrum(sigma, self.lmax)  # (L+1,)
        slow = jnp.einsum("nlc,l->nc", self.bands, filt)
        tj = jnp.exp(-((self.theta_h / sigma) ** 2)) / (jnp.pi * sigma**2) * self.fast_weight
        fast = (tj @ self.fast_energy) / (4 * self.cos_o)[:, None]
        spec = self.fresnel(mu)[:, None] * (slow + fast)
        return jnp.where(self.visible[:, None], spec, 0.0)

    def diffuse_unit(self):
        """$E$ for $K_d = 1$, `(N, C)` (0 where not visible)."""
        return jnp.where(self.visible[:, None], self.irradiance, 0.0)

    def __call__(self, kd, ks, mu, sigma) -> Float[Array, "N C"]:
        dt = self.cos_o.dtype
        kd, ks = jnp.asarray(kd, dt), jnp.asarray(ks, dt)
        kd = kd.reshape((1,) * (2 - kd.ndim) + kd.shape)
        ks = ks.reshape((1,) * (2 - ks.ndim) + ks.shape)
        return kd * self.diffuse_unit() + ks * self.specular_unit(mu, sigma)


def practical_terms(
    normals: Real[ArrayLike, "N 3"],
    views: Real[ArrayLike, "N 3"],
    *,
    slow_sh: Real[ArrayLike, "n_coeffs C"] | None = None,
    fast_directions: Real[ArrayLike, "J 3"] | SequenceLike | None = None,
    fast_energy: Real[ArrayLike, "J C"] | SequenceLike | None = None,
    transfer: Real[ArrayLike, "N 9"] | None = None,
    fast_visibility: Real[ArrayLike, "N J"] | None = None,
    reflected_visibility: Real[ArrayLike, " N"] | None = None,
    chunk: int = 8192,
) -> PracticalTerms:
    """Precompute the terms of R&H eq. 24 for `N` pixels (module docstring).

    **Arguments:** as `render_practical`, for flat `(N, 3)` pixel arrays (the
    samples of one or several views); at least one of `slow_sh` and
    `fast_directions` + `fast_energy`. `chunk` bounds the memory of the SH
    evaluation (`chunk × n_coeffs`).

    **Returns:** a `PracticalTerms`; `terms(kd, ks, mu, sigma)` equals
    `render_practical(normals, views, kd, ks, mu, sigma, ...).total`.
    """
    n = check_dirs(normals, "normals")
    v = check_dirs(views, "views")
    if n.ndim != 2 or v.shape != n.shape:
        raise ValueError(f"`normals` and `views` must both have shape (N, 3), got {tuple(n.shape)} and {tuple(v.shape)}")
    npx = n.shape[0]
    dt = jnp.result_type(n.dtype, v.dtype)
    if slow_sh is None and fast_directions is None:
        raise ValueError("give the lighting: `slow_sh` and/or `fast_directions` with `fast_energy`")
    if (fast_directions is None) != (fast_energy is None):
        raise ValueError("`fast_directions` and `fast_energy` go together")
    c = None
    if slow_sh is not None:
        slow_sh = as_float_array(slow_sh, "slow_sh")
        if slow_sh.ndim == 1:
            slow_sh = slow_sh[:, None]
        nc = slow_sh.shape[0] if slow_sh.ndim == 2 else -1
        if slow_sh.ndim != 2 or nc < 1 or int(round(np.sqrt(nc))) ** 2 != nc:
            raise ValueError(f"`slow_sh` must have shape (n_coeffs, C), got {tuple(slow_sh.shape)}")
        c = slow_sh.shape[1]
    if fast_directions is not None:
        fast_directions = check_dirs(fast_directions, "fast_directions")
        if fast_directions.ndim != 2:
            raise ValueError(f"`fast_directions` must have shape (J, 3), got {tuple(fast_directions.shape)}")
        fast_energy = as_float_array(fast_energy, "fast_energy")
        if fast_energy.ndim == 1:
            fast_energy = fast_energy[:, None]
        if fast_energy.ndim != 2 or fast_energy.shape[0] != fast_directions.shape[0]:
            raise ValueError(
                f"`fast_energy` must have shape ({fast_directions.shape[0]}, C), got {tuple(fast_energy.shape)}"
            )
        if c is not None and fast_energy.shape[1] not in (1, c) and c != 1:
            raise ValueError(f"`fast_energy` has {fast_energy.shape[1]} channels but `slow_sh` has {c}")
        c = max(c or 1, fast_energy.shape[1])
    for name, arr, shape in (
        ("transfer", transfer, (npx, 9)),
        ("fast_visibility", fast_visibility, (npx, 0 if fast_directions is None else fast_directions.shape[0])),
        ("reflected_visibility", reflected_visibility, (npx,)),
    ):
        if arr is not None and tuple(jnp.shape(arr)) != shape:
            raise ValueError(f"`{name}` must have shape {shape}, got {tuple(jnp.shape(arr))}")
    if transfer is not None and slow_sh is None:
        raise ValueError("`transfer` needs `slow_sh`")
    chunk = int(chunk)
    if chunk < 1:
        raise ValueError(f"`chunk` must be a positive int, got {chunk}")
    return _practical_terms(
        n.astype(dt), v.astype(dt), None if slow_sh is None else jnp.broadcast_to(slow_sh.astype(dt), (slow_sh.shape[0], c)),
        None if fast_directions is None else fast_directions.astype(dt),
        None if fast_energy is None else jnp.broadcast_to(fast_energy.astype(dt), (fast_energy.shape[0], c)),
        None if transfer is None else jnp.asarray(transfer, dt),
        None if fast_visibility is None else jnp.asarray(fast_visibility, dt),
        None if reflected_visibility is None else jnp.asarray(reflected_visibility, dt),
        c, chunk,
    )


def _bands_chunked(dirs, coeffs, lmax: int, chunk: int):
    """$P_l = \\sum_m c_{lm} Y_{lm}$ per band at (N, 3) unit directions: (N, lmax+1, C)."""

    def one(x):
        y = _real_sh_flat(x, lmax)  # (n, nc)
        return jnp.stack(
            [y[:, l * l : (l + 1) ** 2] @ coeffs[l * l : (l + 1) ** 2] for l in range(lmax + 1)], axis=1
        )

    npx = dirs.shape[0]
    if npx <= chunk:
        return one(dirs)
    pad = (-npx) % chunk
    d = jnp.pad(dirs, ((0, pad), (0, 0))).at[npx:, 2].set(1.0)
    out = jax.lax.map(one, d.reshape(-1, chunk, 3))
    return out.reshape((-1,) + out.shape[2:])[:npx]


@eqx.filter_jit
def _practical_terms(n, v, slow_sh, fdir, fen, transfer, fvis, rvis, c: int, chunk: int):
    dt = n.dtype
    npx = n.shape[0]
    n = _unit_vectors(n, "normals")
    v = _unit_vectors(v, "views")
    cos_o = jnp.sum(n * v, -1)
    visible = cos_o > 0
    cos_o = jnp.where(visible, cos_o, 1.0)
    irr = jnp.zeros((npx, c), dt)
    if slow_sh is not None:
        lmax = int(round(np.sqrt(slow_sh.shape[0]))) - 1
        l2 = min(lmax, 2)
        if transfer is not None:
            irr = irr + transfer[:, : (l2 + 1) ** 2] @ slow_sh[: (l2 + 1) ** 2]
        else:
            a = lambertian_spectrum(l2, dt)[sh_degrees(l2)]
            irr = irr + _real_sh_flat(n, l2) @ (slow_sh[: (l2 + 1) ** 2] * a[:, None])
        r = _unit_vectors(reflect(v, n))
        bands = _bands_chunked(r, slow_sh, lmax, chunk)
        if rvis is not None:
            bands = bands * rvis[:, None, None]
    else:
        bands = jnp.zeros((npx, 1, c), dt)
    if fdir is not None:
        d = _unit_vectors(fdir)
        cos_i = n @ d.T
        lit = cos_i > 0
        vis = jnp.ones_like(cos_i) if fvis is None else fvis
        weight = jnp.where(lit, vis, 0.0)
        theta_h = half_angle(d[None, :, :], v[:, None, :], n[:, None, :])
        irr = irr + (jnp.where(lit, cos_i, 0.0) * vis) @ fen
        energy = fen
    else:
        theta_h = jnp.zeros((npx, 0), dt)
        weight = jnp.zeros((npx, 0), dt)
        energy = jnp.zeros((0, c), dt)
    return PracticalTerms(visible, cos_o, irr, bands, theta_h, weight, energy)
