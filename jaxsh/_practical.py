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
simplex and Levenberg–Marquardt loops. It equals `render_practical(...,
method="exact")` (same conventions, same visibility terms, exact diffuse term of
fast sources; the default method's table agrees within its documented bound):
that is `practical_terms(...).components(brdf)` reshaped to the image, so eq. 24
is written once, here: `_eq24_terms` (the per-pixel terms)
and `PracticalTerms.components` (their combination with the BRDF).
"""


from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Real
from ._compile import jit, on_row_shards, rows_sharding
from ._custom_types import SequenceLike

from ._checks import as_jax, check_dirs, check_lmax_range, check_positive_int
from ._indexing import sh_degrees
from ._model import Lighting, TorranceSparrow
from ._reflectance import _fresnel_normalized_jit, _half_angle_pairs, _index, _safe_sqrt, _theta_h_sq, fresnel_normalized
from ._sh import REAL_SH_MAX_LMAX, _band_sums_scan, _real_sh_flat, _sh2, _unit_vectors, _z_features
from ._spectra import _check_sigma, _microfacet_filter, lambertian_spectrum, microfacet_spectrum
from ._transforms import _synthesize

_LIGHT_KW = ("slow_sh", "fast_directions", "fast_energy")


class Components(NamedTuple):
    """The three terms of R&H eq. 24 and their sum, each `(..., C)`."""

    diffuse: Array
    specular_slow: Array
    specular_fast: Array
    total: Array


def _rows(x, dt):
    """A `(C,)` / `(N, C)` parameter as a 2-D `(1 or N, C)` array (no rank promotion)."""
    x = jnp.asarray(x, dt)
    return x.reshape((1,) * (2 - x.ndim) + x.shape)


class PracticalTerms(eqx.Module):
    """Per-pixel precomputed terms of R&H eq. 24 (see the module docstring).

    **Fields** (`N` pixels, `C` channels, `J` fast sources):

    - `visible`: `(N,)` bool, $\\cos\\theta_o > 0$.
    - `cos_o`: `(N,)` $\\cos\\theta_o$ (1 where not visible).
    - `irradiance`: `(N, C)` $E$: the 9-term (or transfer-vector) irradiance of
      the slow lighting plus the shadowed cosine of the fast sources (exact,
      or with `exact_fast_diffuse=False` their 9-term irradiance, each times
      its visibility `fast_visibility`).
    - `bands`: `(N, C, lmax+1)` $P_l(R)$, reflected-ray visibility included
      (the band axis last and contiguous: $L_{slow}(R) = $ `bands @ filter`
      is then a matrix-vector product: 4.4–5.6 ms against 57 ms on XLA:CPU for a
      contraction over a middle axis at 127,584 samples, lmax 40; docs/performance.md).
    - `theta_h`: `(N, J)` half-angle of each fast source (`jaxsh.half_angle`).
    - `fast_weight`: `(N, J)` $V_j\\,[\\cos\\theta_{i,j} > 0]$.
    - `fast_energy`: `(J, C)` $L_j$.

    Call it as `terms(brdf)` with a `jaxsh.TorranceSparrow`, or as
    `terms(kd, ks, mu, sigma)`, for `B` `(N, C)`; `kd`, `ks` are `(C,)` or
    per-pixel `(N, C)`; `mu=None` means $F = 1$. `terms.components(...)`
    gives the three terms of eq. 24 (what `render_practical` returns).

    **Checks.** $\\sigma \\le 0$ or infinite and $\\mu < 1$ are errors, as in the BRDF models ($\\mu$ is
    the relative index into the surface; $0 < \\mu < 1$ passed until session 29): a
    `ValueError` for concrete values, `equinox.error_if` under `jit`; NaN
    propagates. `fresnel`, `specular_unit` and `components` take
    `check=False` for callers whose parametrization guarantees the ranges
    (`solvers.fit_brdf` evaluates the model at $\\mu = 1 + e^{u}$,
    $\\sigma = e^{v}$): the values are the same, and the traced checks (a
    conditional and a host callback per call) are left out of the compiled
    program. Measured on 2 cores: `solvers.fit_brdf`'s program lost 12
    conditionals and 24 host callbacks, and XLA compiled it in about 10 %
    less CPU time (docs/performance.md, "Sixth round").
    """

    visible: Bool[Array, " N"]
    cos_o: Float[Array, " N"]
    irradiance: Float[Array, "N C"]
    bands: Float[Array, "N C L"]
    theta_h: Float[Array, "N J"]
    fast_weight: Float[Array, "N J"]
    fast_energy: Float[Array, "J C"]

    @property
    def lmax(self) -> int:
        return self.bands.shape[2] - 1

    def fresnel(self, mu, *, check: bool = True):
        """$F(\\mu, \\theta_o)$ normalized to 1 at normal incidence, `(N,)` (`check`: see the class docstring)."""
        if mu is None:
            return jnp.ones_like(self.cos_o)
        mu = jnp.asarray(mu, self.cos_o.dtype)
        return fresnel_normalized(self.cos_o, _index(mu, "mu")) if check else _fresnel_normalized_jit(self.cos_o, mu)

    def _specular(self, mu, sigma, check: bool = True):
        """$F L_{slow}(R)$ and $F/(4\\cos\\theta_o)\\sum_j T_j(\\sigma)$ of eq. 24 for $K_s = 1$, each `(N, C)`."""
        dt = self.cos_o.dtype
        sigma = jnp.asarray(sigma, dt)
        if check:
            sigma = _check_sigma(sigma)  # a ValueError, or equinox.error_if under jit (as `microfacet_spectrum`)
        slow = _filtered_bands(self.bands, sigma)  # eq. 22 with the filter of eq. 20: (N, C, L) @ (L,)
        tj = jnp.exp(-((self.theta_h / sigma) ** 2)) / (jnp.pi * sigma**2) * self.fast_weight  # eq. 23
        fast = (tj @ self.fast_energy) / (4 * self.cos_o)[:, None]
        f = self.fresnel(mu, check=check)[:, None]
        vis = self.visible[:, None]
        return jnp.where(vis, f * slow, 0.0), jnp.where(vis, f * fast, 0.0)

    def specular_unit(self, mu, sigma, *, check: bool = True):
        """The bracket of eq. 24 times $F$: the radiance for $K_s = 1$, `(N, C)` (`check`: see the class docstring)."""
        slow, fast = self._specular(mu, sigma, check)
        return slow + fast

    def diffuse_unit(self):
        """$E$ for $K_d = 1$, `(N, C)` (0 where not visible)."""
        return jnp.where(self.visible[:, None], self.irradiance, 0.0)

    def components(self, kd, ks=None, mu=None, sigma=None, *, check: bool = True) -> Components:
        """The terms of eq. 24 for a BRDF (`TorranceSparrow`, or `kd, ks, mu, sigma`), each `(N, C)` (`check`: see
        the class docstring)."""
        if isinstance(kd, TorranceSparrow):
            kd, ks, mu, sigma = kd.kd, kd.ks, kd.mu, kd.sigma
        elif ks is None or sigma is None:
            raise TypeError("give a TorranceSparrow, or kd, ks, mu and sigma")
        dt = self.cos_o.dtype
        kd, ks = _rows(kd, dt), _rows(ks, dt)
        slow, fast = self._specular(mu, sigma, check)
        parts = (kd * self.diffuse_unit(), ks * slow, ks * fast)
        shape = jnp.broadcast_shapes(*(p.shape for p in parts))
        d, s, f = (jnp.broadcast_to(p, shape) for p in parts)
        return Components(d, s, f, d + s + f)

    def __call__(self, kd, ks=None, mu=None, sigma=None) -> Float[Array, "N C"]:
        return self.components(kd, ks, mu, sigma).total


@jax.custom_jvp
def _filtered_bands(bands, sigma):
    """$\\sum_l e^{-(\\sigma l)^2} P_l$ (R&H eqs. 20, 22): `bands` `(N, C, L)` times the filter, `(N, C)`;
    `sigma` a scalar.

    Its derivative in $\\sigma$ is the product with
    $\\partial_\\sigma e^{-(\\sigma l)^2} = -2\\sigma l^2 e^{-(\\sigma l)^2}$, made from the primal values (a second
    matrix-vector product) and scaled by the tangent. Without this rule, forward mode over several tangents at
    once (the fits' Jacobians: a `vmap` of `jvp`) contracted the table with a batched `(T, L)` filter, a matrix
    product whose output XLA:CPU lays out with the batch first: `solvers.fit_brdf`'s residual and 2-column
    Jacobian took 33–35 ms at 127,584 samples, lmax 40, against 19–22 ms with it (docs/performance.md,
    twenty-sixth round). Tangents of `bands` (a derivative through the lighting or the geometry) are contracted
    with the filter as before.
    """
    return bands @ _microfacet_filter(sigma, bands.shape[-1] - 1)


def _filtered_bands_jvp(primals, tangents):
    bands, sigma = primals
    dbands, dsigma = tangents
    filt = _microfacet_filter(sigma, bands.shape[-1] - 1)
    out = bands @ filt
    tangent = None
    if type(dsigma) is not jax.custom_derivatives.SymbolicZero:
        l2 = jnp.arange(bands.shape[-1], dtype=filt.dtype) ** 2
        tangent = (bands @ (-2.0 * sigma * l2 * filt)) * dsigma
    if type(dbands) is not jax.custom_derivatives.SymbolicZero:
        tb = dbands @ filt
        tangent = tb if tangent is None else tangent + tb
    if tangent is None:
        tangent = jnp.zeros_like(out)
    return out, tangent


_filtered_bands.defjvp(_filtered_bands_jvp, symbolic_zeros=True)


def _sh_bands(dirs, coeffs, lmax: int, chunk: int):
    """$P_l = \\sum_m c_{lm} Y_{lm}$ per band at (N, 3) unit directions: (N, C, lmax+1), in pixel chunks.

    The SH recurrence with each band contracted against the coefficients as it is made
    (`jaxsh._sh._band_sums_scan`): $O(N\\,(l_{max}+1)^2\\,C)$ multiply-adds, one small scan body to compile.
    """
    feat = _z_features(dirs)

    def one(f):
        z = tuple(f[:, i] for i in range(2, f.shape[1]))
        return _band_sums_scan(f[:, 0], f[:, 1], z[0] if len(z) == 1 else z, coeffs, lmax).transpose(2, 1, 0)

    npx = dirs.shape[0]
    if npx <= chunk:
        return one(feat)
    pad = (-npx) % chunk
    f = jnp.pad(feat, ((0, pad), (0, 0)))
    f = f.at[npx:, 2].set(1.0)  # padding rows: +z (float64 features) or sigma = +1, w = 0 (below float64): valid
    out = jax.lax.map(one, f.reshape(-1, chunk, f.shape[1]))
    return out.reshape((-1,) + out.shape[2:])[:npx]


# --------------------------------------------------------------------------- the slow specular term by table
#
# `render_practical` (`method="table"`) evaluates L_slow(R) = sum_lm e^{-(sigma l)^2} L_lm Y_lm(R) (eq. 22)
# once per call on a lat-long grid and interpolates it at the mirror directions, instead of summing
# (lmax+1)^2 harmonics per pixel. The grid and its error bound (docs/conventions.md, "The slow specular
# term by table"):
#
# * rows theta_i = (i + 1/2) h, i < H, columns phi_j = (j + 1/2) h, j < W = 2H, h = pi/H (the lat-long
#   layout, filled by `synthesize_latlong`'s Legendre sums and FFT: O(lmax^2 H + H W log W));
# * the double Fourier sphere extension f(-theta, phi) = f(theta, phi + pi) (and the same about
#   theta = pi) continues every meridian across the poles: two padding rows at each pole are rows 0, 1
#   (H-1, H-2) shifted by W/2 columns, two padding columns at each end wrap phi. A band-l function is
#   then a trigonometric polynomial of degree <= l in theta and in phi on the whole torus: the poles
#   are ordinary points of the interpolation;
# * 4-point (cubic) Lagrange interpolation in phi on the 4 rows around theta, then in theta.
#
# Bound: 4-point Lagrange interpolation on a uniform grid of step h errs by at most (3/128) h^4 max|g^(4)|,
# its weights sum in absolute value to at most 5/4 (Lebesgue constant), and Bernstein's inequality bounds
# the 4th derivative of a degree-l trigonometric polynomial by l^4 times its maximum, which for band l of
# the lighting is at most a_l = sqrt((2l+1)/(4 pi)) ||L_l||_2 (Cauchy-Schwarz and the addition theorem).
# So, per channel and everywhere on the sphere,
#
#     |table - exact| <= (27/512) h^4 sum_l l^4 e^{-(sigma l)^2} a_l,      27/512 = (3/128)(1 + 5/4),
#
# plus rounding (at most 25/16 times the rounding of the tabulated values). `_table_rows` picks the
# smallest grid of `_TABLE_LADDER` for which this bound is at most `_TABLE_TOL * sum_l a_l` for ANY
# lighting of that lmax (the worst case puts all of it in the band that maximizes l^4 e^{-(sigma l)^2}),
# from sigma when it is concrete, else from lmax alone.

_TABLE_TOL = 1e-6
_TABLE_CONST = 27.0 / 512.0
_TABLE_LADDER = (16, 24, 32, 48, 64, 96, 128, 192, 256, 384, 512, 768, 1024)


def _table_rows(lmax: int, sigma: float | None, tol: float = _TABLE_TOL) -> int | None:
    """Rows H of the table (W = 2H) whose bound is `<= tol * sum_l a_l` for any lighting; None beyond the ladder."""
    l = np.arange(lmax + 1, dtype=np.float64)
    if sigma is None:
        m4 = float(lmax) ** 4
    else:
        m4 = float(np.max(l**4 * np.exp(-((float(sigma) * l) ** 2))))
    need = np.pi * (_TABLE_CONST * m4 / tol) ** 0.25
    for h in _TABLE_LADDER:
        if h >= need:
            return h
    return None


def _slow_table(slow_sh, sigma, rows: int):
    """The filtered slow lighting (eqs. 20, 22) on the padded `(rows + 4, 2 rows + 4)` grid, flattened to `(P, C)`."""
    lmax = int(round(np.sqrt(slow_sh.shape[0]))) - 1
    filt = microfacet_spectrum(sigma, lmax)[sh_degrees(lmax)]
    t = _synthesize(slow_sh * filt[:, None], lmax, rows, 2 * rows)  # (H, W, C)
    across = jnp.roll(t, rows, axis=1)  # column j -> phi_j + pi
    t = jnp.concatenate([across[1::-1], t, across[:-3:-1]], axis=0)  # theta rows -2, -1 | 0..H-1 | H, H+1
    t = jnp.concatenate([t[:, -2:], t, t[:, :2]], axis=1)  # phi columns -2, -1 | 0..W-1 | W, W+1
    return t.reshape(-1, t.shape[-1])


def _cubic_weights(t):
    """4-point Lagrange weights at the nodes -1, 0, 1, 2 for t in [0, 1)."""
    return (
        -t * (t - 1.0) * (t - 2.0) / 6.0,
        (t + 1.0) * (t - 1.0) * (t - 2.0) / 2.0,
        -(t + 1.0) * t * (t - 2.0) / 2.0,
        (t + 1.0) * t * (t - 1.0) / 6.0,
    )


def _table_lookup(table, rows: int, r):
    """Bicubic interpolation of a `_slow_table` at unit directions `r` `(N, 3)`: `(N, C)`.

    Gradient-safe: at the poles (r_x = r_y = 0) the angles are computed from substituted values
    (double `where`), so the value is the interpolant's and the gradient finite there (its
    tangential part is 0 exactly at the two poles, and that of the interpolant everywhere else).
    """
    rx, ry, rz = r[:, 0], r[:, 1], r[:, 2]
    w = 2 * rows
    wp = w + 4
    rho2 = rx * rx + ry * ry
    ok = rho2 > 0.0
    rho = jnp.sqrt(jnp.where(ok, rho2, 1.0))
    theta = jnp.arctan2(jnp.where(ok, rho, 0.0), rz)
    phi = jnp.arctan2(jnp.where(ok, ry, 0.0), jnp.where(ok, rx, 1.0))
    phi = jnp.where(phi < 0.0, phi + 2.0 * np.pi, phi)
    u = theta * (rows / np.pi) - 0.5  # row coordinate in [-1/2, H - 1/2]
    v = phi * (w / (2.0 * np.pi)) - 0.5  # column coordinate in [-1/2, W - 1/2]
    i0 = jnp.clip(jnp.floor(u), -1.0, rows - 1.0)
    j0 = jnp.clip(jnp.floor(v), -1.0, w - 1.0)
    wu = _cubic_weights(u - i0)
    wv = _cubic_weights(v - j0)
    base = (i0.astype(jnp.int32) + 1) * wp + j0.astype(jnp.int32) + 1  # padded index of (i0 - 1, j0 - 1)
    out = 0.0
    for a in range(4):
        acc = 0.0
        for b in range(4):
            acc = acc + wv[b][:, None] * table[base + (a * wp + b)]
        out = out + wu[a][:, None] * acc
    return out


# --------------------------------------------------------------------------- per-pixel kernels, component-wise
# (XLA on CPU vectorizes (N,) columns far better than (N, 3) rows with a minor axis of 3.)


def _sh2_dot(n, coeffs):
    """`real_sh(n, l) @ coeffs` for the first (l+1)^2 ≤ 9 coefficients, without forming the basis: `(N, C)`."""
    ys = _sh2(n[:, 0], n[:, 1], n[:, 2], coeffs.shape[0])
    out = ys[0][:, None] * coeffs[0][None, :]
    for yk, ck in zip(ys[1:], coeffs[1:]):
        out = out + yk[:, None] * ck[None, :]
    return out


def _half_angles(d, v, n):
    """θh `(N, J)` of unit sources `d` `(J, 3)` at unit views / normals `(N, 3)` (`jaxsh.half_angle`'s formula)."""
    return _safe_sqrt(_theta_h_sq(*_half_angle_pairs(d, n, v)))


def _eq24_terms(
    n, v, slow_sh, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse: bool, chunk: int, table=None
) -> PracticalTerms:
    """THE kernel of R&H eq. 24: the per-pixel terms at flat `(N, 3)` normals / views.

    Inputs are validated and cast (`_prepare_lighting`, `_prepare_visibility`):
    `slow_sh` `(n_coeffs, C)`, `fdir` `(J, 3)`, `fen` `(J, C)` or None;
    `transfer` `(N, k)`, `fvis` `(N, J)`, `rvis` `(N,)` or None.

    `table=(flat, rows)` (a `_slow_table` of the slow lighting already filtered
    for σ) replaces the per-band SH evaluation at the mirror direction by its
    interpolation: `bands` is then `(N, C, 1)`, the filtered $L_{slow}(R)$
    itself, whose filter $e^{-(\\sigma\\cdot 0)^2} = 1$ in `components` leaves it as is.
    """
    dt = n.dtype
    npx = n.shape[0]
    c = (slow_sh if slow_sh is not None else fen).shape[1]
    n = _unit_vectors(n, "normals")
    v = _unit_vectors(v, "views")
    cos_o = jnp.sum(n * v, -1)
    visible = cos_o > 0
    r = 2.0 * cos_o[:, None] * n - v  # the mirror direction R (`jaxsh.reflect`)
    cos_o = jnp.where(visible, cos_o, 1.0)
    irr = jnp.zeros((npx, c), dt)
    if slow_sh is not None:
        # Slow lighting: 9-term irradiance (eq. 21) and its bands at the mirror direction (eq. 22).
        lmax = int(round(np.sqrt(slow_sh.shape[0]))) - 1
        l2 = min(lmax, 2)
        k = (l2 + 1) ** 2
        if transfer is not None:
            irr = irr + transfer[:, :k] @ slow_sh[:k]
        else:
            a = lambertian_spectrum(l2, dt)[sh_degrees(l2)]
            irr = irr + _sh2_dot(n, slow_sh[:k] * a[:, None])
        r = _unit_vectors(r, check=False)  # |R| = |v| = 1: n and v were checked above
        if table is None:
            bands = _sh_bands(r, slow_sh, lmax, chunk)
        else:
            bands = _table_lookup(table[0], table[1], r)[:, :, None]
        if rvis is not None:
            bands = bands * rvis[:, None, None]
    else:
        bands = jnp.zeros((npx, c, 1), dt)
    if fdir is not None:
        # Fast sources: eq. 23 (half angles) and their diffuse term.
        d = _unit_vectors(fdir)
        cos_i = n[:, 0:1] * d[None, :, 0] + n[:, 1:2] * d[None, :, 1] + n[:, 2:3] * d[None, :, 2]  # (N, J)
        lit = cos_i > 0
        vis = jnp.ones_like(cos_i) if fvis is None else fvis
        weight = jnp.where(lit, vis, 0.0)
        theta_h = _half_angles(d, v, n)
        if exact_fast_diffuse:
            irr = irr + (jnp.where(lit, cos_i, 0.0) * vis) @ fen
        else:  # the letter of eq. 21: each fast source's 9-term irradiance, times its shadow visibility (sec. 6.4)
            a = lambertian_spectrum(2, dt)[sh_degrees(2)]
            if fvis is None:
                irr = irr + _sh2_dot(n, (_real_sh_flat(d, 2) * a[None, :]).T @ fen)
            else:  # (was unshadowed: a source fully in shadow still lit the diffuse term)
                irr = irr + (_sh2_dot(n, (_real_sh_flat(d, 2) * a[None, :]).T) * fvis) @ fen
        energy = fen
    else:
        theta_h = jnp.zeros((npx, 0), dt)
        weight = jnp.zeros((npx, 0), dt)
        energy = jnp.zeros((0, c), dt)
    return PracticalTerms(visible, cos_o, irr, bands, theta_h, weight, energy)


def practical_lighting(lighting, light_kw: dict) -> Lighting:
    """The `Lighting` of a practical-model call: `lighting`, or one built from the keyword form."""
    given = {k: x for k, x in light_kw.items() if x is not None}
    if lighting is None:
        if not given:
            raise ValueError("give the lighting: a `jaxsh.Lighting`, or `slow_sh` and/or `fast_directions` with `fast_energy`")
        lighting = Lighting(**given)
    elif given:
        raise TypeError(f"give the lighting either as a `Lighting` or as keywords, not both ({sorted(given)})")
    if not isinstance(lighting, Lighting):
        raise ValueError(f"`lighting` must be a jaxsh.Lighting, got {type(lighting).__name__}")
    if lighting.has_disks:
        raise ValueError(
            "`lighting` has disk sources: the practical model needs the slow/fast split of R&H sec. 5.3 first, "
            "`lighting.split_disks(sigma, lmax)` (or `jaxsh.split_disk_sources`)"
        )
    return lighting


def _prepare_lighting(lighting: Lighting, dt):
    """`(slow_sh (n, C), fast_directions (J, 3), fast_energy (J, C))` in dtype `dt`, channels broadcast."""
    c = lighting.n_channels
    slow = None if lighting.slow_sh is None else jnp.broadcast_to(lighting.slow_sh.astype(dt), (lighting.slow_sh.shape[0], c))
    if lighting.fast_directions is None:
        return slow, None, None
    fen = jnp.broadcast_to(lighting.fast_energy.astype(dt), (lighting.fast_energy.shape[0], c))
    return slow, lighting.fast_directions.astype(dt), fen


def _broadcasts_to(shape, want) -> bool:
    try:
        return jnp.broadcast_shapes(tuple(shape), tuple(want)) == tuple(want)
    except ValueError:
        return False


def _broadcast_to_batch(x, batch, core, name, dt):
    """`x` of shape `(..., *core)` broadcast to `batch + core` and flattened to `(N, *core)`."""
    x = as_jax(x)  # placed without a program (`jnp.asarray` compiles one per new NumPy shape)
    want = tuple(batch) + tuple(core)
    if x.ndim < len(core) or x.shape[x.ndim - len(core):] != tuple(core) or not _broadcasts_to(x.shape, want):
        what = {"transfer": " (the batch of `normals`/`views` + 9 transfer coefficients)",
                "fast_visibility": f" (the batch of `normals`/`views` + one column per source of `lighting.fast_directions`, J = {core[0] if core else 0})",
                }.get(name, " (the batch of `normals`/`views`)")
        raise ValueError(f"`{name}` must have shape {want}{what}, got {tuple(x.shape)}")
    return jnp.broadcast_to(x.astype(dt), want).reshape((-1,) + tuple(core))


def _prepare_visibility(lighting: Lighting, batch, transfer, fast_visibility, reflected_visibility, dt, strict: bool):
    """The visibility terms of R&H sec. 6.4, checked against `batch` and flattened to `(N, ...)`.

    A term whose lighting part is absent is dropped (`strict=False`,
    `render_practical`) or is an error (`strict=True`, `practical_terms`).
    """

    if lighting.slow_sh is None:
        if strict and transfer is not None:
            raise ValueError("`transfer` needs `slow_sh`")
        if strict and reflected_visibility is not None and not _broadcasts_to(jnp.shape(reflected_visibility), batch):
            raise ValueError(f"`reflected_visibility` must have shape {tuple(batch)}, got {tuple(jnp.shape(reflected_visibility))}")
        transfer = reflected_visibility = None
    j = 0 if lighting.fast_directions is None else lighting.fast_directions.shape[0]
    if j == 0:
        if strict and fast_visibility is not None and tuple(jnp.shape(fast_visibility)) != tuple(batch) + (0,):
            raise ValueError(f"`fast_visibility` must have shape {tuple(batch) + (0,)}, got {tuple(jnp.shape(fast_visibility))}")
        fast_visibility = None
    if transfer is not None:
        t = as_jax(transfer)
        k = (min(lighting.lmax, 2) + 1) ** 2
        if t.ndim < 1 or t.shape[-1] < k:
            raise ValueError(f"`transfer` must have shape {tuple(batch) + (9,)}, got {tuple(t.shape)}")
        transfer = _broadcast_to_batch(t, batch, (t.shape[-1],), "transfer", dt)
    if fast_visibility is not None:
        fast_visibility = _broadcast_to_batch(fast_visibility, batch, (j,), "fast_visibility", dt)
    if reflected_visibility is not None:
        reflected_visibility = _broadcast_to_batch(reflected_visibility, batch, (), "reflected_visibility", dt)
    return transfer, fast_visibility, reflected_visibility


def practical_terms(
    normals: Real[ArrayLike, "N 3"],
    views: Real[ArrayLike, "N 3"],
    lighting: Lighting | None = None,
    *,
    slow_sh: Real[ArrayLike, "n_coeffs C"] | None = None,
    fast_directions: Real[ArrayLike, "J 3"] | SequenceLike | None = None,
    fast_energy: Real[ArrayLike, "J C"] | SequenceLike | None = None,
    transfer: Real[ArrayLike, "N 9"] | None = None,
    fast_visibility: Real[ArrayLike, "N J"] | None = None,
    reflected_visibility: Real[ArrayLike, " N"] | None = None,
    exact_fast_diffuse: bool = True,
    chunk: int = 256,
) -> PracticalTerms:
    """Precompute the terms of R&H eq. 24 for `N` pixels (module docstring).

    **Arguments:**

    - `normals`, `views`: flat `(N, 3)` unit vectors (the samples of one or
      several views).
    - `lighting`: a `jaxsh.Lighting` with a slow and/or fast part (no disks:
      `Lighting.split_disks` first). The keyword form `slow_sh=`,
      `fast_directions=`, `fast_energy=` (as in `render_practical`) is the same.
    - `transfer` `(N, 9)`, `fast_visibility` `(N, J)`, `reflected_visibility`
      `(N,)`: the visibility terms of sec. 6.4, as in `render_practical`.
    - `exact_fast_diffuse`: as in `render_practical`.
    - `chunk`: pixels per block of the SH band sums (memory `chunk × n_coeffs`).
      The default 256 keeps the recurrence's working set in cache: at 127,584
      samples and lmax 40, 0.49–0.53 s against 0.64–0.80 s with 8,192 (lmax 8:
      38 ms against 88 ms; float64, docs/performance.md).

    **Returns:** a `PracticalTerms`; `terms(brdf)` equals
    `render_practical(normals, views, brdf, lighting, ..., method="exact").total`
    (the default method's table agrees within its error bound: 2.5e-7 relative
    measured at 5,000 pixels, lmax 16, σ 0.2). Slow lighting beyond the degree
    the dtype evaluates (`real_sh`'s `REAL_SH_MAX_LMAX`: 170 below float64) is a
    `ValueError`: the per-pixel harmonics come out NaN near the poles there.
    Pixels split over several devices (`normals`, `views` and the visibility
    terms with the same `NamedSharding` along their first axis, evenly) are
    processed on their devices, and the per-pixel fields stay split
    (docs/howto_scale.md).
    """
    lighting = practical_lighting(
        lighting, dict(slow_sh=slow_sh, fast_directions=fast_directions, fast_energy=fast_energy)
    )
    n = check_dirs(normals, "normals")
    v = check_dirs(views, "views")
    if n.ndim != 2 or v.shape != n.shape:
        raise ValueError(f"`normals` and `views` must both have shape (N, 3), got {tuple(n.shape)} and {tuple(v.shape)}")
    chunk = check_positive_int(chunk, "chunk")
    dt = jnp.result_type(n.dtype, v.dtype)
    if lighting.slow_sh is not None:  # the per-pixel band sums: NaN near the poles in float32 from lmax ~186
        check_lmax_range(lighting.lmax, dt, REAL_SH_MAX_LMAX, "`practical_terms` (per-pixel SH band sums)")
    slow, fdir, fen = _prepare_lighting(lighting, dt)
    vis = _prepare_visibility(lighting, n.shape[:1], transfer, fast_visibility, reflected_visibility, dt, strict=True)
    n, v = n.astype(dt), v.astype(dt)
    where = rows_sharding(n, v, *vis)
    if where is not None:  # each device's pixels on that device (`jaxsh._compile.row_sharding`)
        return _practical_terms_rows(n, v, slow, fdir, fen, *vis, bool(exact_fast_diffuse), chunk, where)
    return _practical_terms(n, v, slow, fdir, fen, *vis, bool(exact_fast_diffuse), chunk)


@jit
def _practical_terms(n, v, slow_sh, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, chunk):
    return _eq24_terms(n, v, slow_sh, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, chunk)


@jit
def _practical_terms_rows(n, v, slow_sh, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, chunk, where):
    def local(n, v, transfer, fvis, rvis, slow_sh, fdir, fen):
        return _eq24_terms(n, v, slow_sh, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, chunk)

    return on_row_shards(local, where, (n, v, transfer, fvis, rvis), (slow_sh, fdir, fen), replicated=("fast_energy",))
