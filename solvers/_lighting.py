"""Inverse lighting with known BRDF (R&H 2001 sec. 6.2).

**Spherical-harmonic coefficients (eq. 25).** With the BRDF known, every
pixel is linear in the lighting coefficients $L_{lm}$, $l \\le l^*$:

$$B(x) = \\sum_{l \\le l^*}\\sum_m L_{lm}\\Big(K_d\\,\\Lambda_l\\hat\\rho_l\\,Y_{lm}(n)
   + K_s F(\\mu,\\theta_o)\\,Y_{lm}(R)\\Big),$$

the first term only for $l \\le 2$ by default (eq. 21; with shadows, the transfer
vector $T_{lm}(x)$ of sec. 6.4 replaces $\\Lambda_l\\hat\\rho_l Y_{lm}(n)$, and
the reflected-ray visibility multiplies the second). `inverse_lighting`
solves this weighted least-squares problem per colour channel from the
normal equations, accumulated over pixel chunks (memory $O(n_{coeffs}^2)$),
with an eigendecomposition that exposes the singular values: coefficients
in the null space (for a Lambertian object every $l > 2$) are reported as
undetermined with infinite standard error, never as silent numbers. As in
the paper, the recovered lighting is the lighting *filtered* by the specular
lobe (the roughness is not used); `deconvolve=True` includes the filter
$e^{-(\\sigma l)^2}$ (eq. 20) in the model and recovers the unfiltered
lighting up to $l^*$ instead.

**The literal eq. 25.** As printed, eq. 25 sums the diffuse term
$K_d\\Lambda_l\\hat\\rho_l Y_{lm}(n)$ up to $l^*$, not 2. With
`diffuse_bands="literal"` the diffuse rows run over every $l \\le l^*$, with
the clamped-cosine coefficients of thesis eq. 3.32; then nothing about the
Lambertian low-pass is built in and the solve *finds* it (thesis ch. 3,
around eq. 3.33): the columns of odd $l > 1$ vanish identically
($\\Lambda_l\\hat\\rho_l = 0$: ill-posed, zero singular values), those of even
$l > 2$ are multiplied by $|\\Lambda_l\\hat\\rho_l| \\le 0.131$, decaying like
$l^{-5/2}$ (ill-conditioned: tiny but nonzero singular values). The default
`"l2"` is the paper's practical form (eq. 21).

**Dual angular / frequency-space lighting (sec. 6.2, fig. 8).**
`inverse_lighting_dual` subtracts the diffuse part predicted by 9
coefficients $L^1_{lm}$, divides by $K_s F$ to get the lighting at the
mirror directions, bins it into a lat-long image, projects that image back
to 9 coefficients $L^2_{lm}$, and solves the 9 linear consistency equations
$L^1 = L^2$ per channel. With `nonneg=True` the lat-long lighting is then
refined by a box-constrained solve ($L \\ge 0$, jaxopt L-BFGS-B) of the same
model, in which the diffuse term is driven by the image's own $l \\le 2$
projection, so consistency holds by construction.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

import lineax as lx

import jaxsh

from ._data import Lighting, Observations, TorranceSparrow
from ._lapack import map_lapack
from ._normal_equations import Gram, accumulate_gram, channel_system, eig_solve, eq25_rows, pixel_chunks
from ._pixel_sums import pixel_sharding, sum_over_pixels
from ._results import (Solution, Status, check_float, check_int, finish, rms_pair, signal_status, status_from_lbfgsb,
                       status_from_optimistix, worst, worst_batched)
from ._threads import blas_single_thread


class LightingResult(Solution):
    """Result of `inverse_lighting` (a `solvers.Solution`; `estimate` is `coeffs`).

    **Fields:**

    - `coeffs`: `(n_coeffs, C)` real SH lighting, world frame (+z up).
    - `std_errors`: `(n_coeffs, C)`, $\\sqrt{s^2[(A^TWA)^+]_{ii}}$ with
      $s^2 = \\mathrm{RSS}/(n_{obs} - \\mathrm{rank})$, the RSS summed over the
      pixels' residuals (`inverse_lighting`; not from the normal equations,
      whose rounding made float32 errors wrong); `inf` for undetermined
      coefficients, and for every coefficient when the samples leave no
      degree of freedom ($n_{obs} \\le$ rank: the noise cannot be estimated).
    - `determined`: `(n_coeffs, C)` bool.
    - `singular_values`: `(C, n_coeffs)` of the weighted design matrix, descending.
    - `supported_lmax`: `(C,)` the largest $l$ for which every coefficient of
      degree $\\le l$ is determined by the data.
    - `band_snr`: `(lmax+1, C)` RMS over $m$ of $|L_{lm}|/\\mathrm{se}_{lm}$: where it
      drops below ~1, noise dominates (the $l^*$ of R&H sec. 6.2 in practice).
    - `status`: `converged`; `ill_conditioned` when some coefficient is
      undetermined (see `determined`, `singular_values`); `nonfinite`;
      `no_signal` for all-zero data, or an all-zero BRDF ($K_d = K_s = 0$)
      in some channel.
    - `iterations`: 0 (a direct solve); `rms`, `rel_rms` (never NaN), from
      the residual of every pixel (a second pass over the pixels, in float32
      always, in float64 where the normal equations' form falls below
      $10^{-6}$ of the data: `_residual_ss`).
    - `stats`: `rank` `(C,)` (eigenvalues kept), `n_obs` (weighted samples × channels).
    """

    coeffs: Float[Array, "n_coeffs C"]
    std_errors: Float[Array, "n_coeffs C"]
    determined: Bool[Array, "n_coeffs C"]
    singular_values: Float[Array, "C n_coeffs"]
    supported_lmax: Int[Array, " C"]
    band_snr: Float[Array, "L C"]
    status: Status
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    iterations: Int[Array, ""]
    stats: dict

    @property
    def estimate(self) -> Float[Array, "n_coeffs C"]:
        return self.coeffs

    @property
    def lmax(self) -> int:
        return int(round(np.sqrt(self.coeffs.shape[0]))) - 1

    @property
    def lighting(self) -> Lighting:
        return Lighting.unchecked(self.coeffs)


def _check_brdf(brdf, channels: int, name="brdf"):
    if not isinstance(brdf, TorranceSparrow):
        raise ValueError(f"`{name}` must be a solvers.TorranceSparrow, got {type(brdf).__name__}")
    if jnp.ndim(brdf.kd) != 1 or jnp.ndim(brdf.ks) != 1:
        raise ValueError(
            f"`{name}.kd` and `{name}.ks` must be homogeneous (C,) arrays for inverse lighting "
            f"(R&H sec. 6.4: texture and lighting cannot be factored), got shapes {jnp.shape(brdf.kd)}, {jnp.shape(brdf.ks)}"
        )
    for field in ("kd", "ks"):
        k = jnp.shape(getattr(brdf, field))[0]
        if k not in (1, channels):
            raise ValueError(f"`{name}.{field}` has {k} channels, the images in `obs` {channels} "
                             f"(give {channels if channels == 1 else f'{channels} or 1'})")


@blas_single_thread
def inverse_lighting(
    obs: Observations,
    brdf: TorranceSparrow,
    lmax: int,
    *,
    deconvolve: bool = False,
    ridge: float = 0.0,
    rcond: float | None = None,
    chunk: int = 4096,
    diffuse_bands: str = "l2",
    throw: bool = False,
) -> LightingResult:
    """Recover SH lighting coefficients $L_{lm}$, $l \\le$ `lmax`, for a known BRDF (R&H eq. 25).

    **Arguments:**

    - `obs`: `Observations`; `transfer` and `reflected_visibility` are used
      when present (sec. 6.4).
    - `brdf`: homogeneous `TorranceSparrow` (`kd`, `ks` `(C,)`; `sigma` used
      only with `deconvolve`).
    - `lmax`: the cutoff $l^*$ (static); R&H suggest $l^* \\sim 1/\\sigma$.
    - `deconvolve`: include the microfacet filter $e^{-(\\sigma l)^2}$ and
      return the unfiltered lighting (default: the paper's filtered lighting).
    - `ridge`: Tikhonov term added to the normal equations (0: none).
    - `rcond`: eigenvalues below `rcond × largest` are treated as zero
      (default 1e-12 in float64, 1e-6 in float32).
    - `chunk`: pixels per chunk of the normal-equation accumulation.
    - `diffuse_bands`: `"l2"` (default: the diffuse term for $l \\le 2$ only,
      eq. 21) or `"literal"` (eq. 25 as printed: the diffuse term up to
      `lmax`; module docstring). `"literal"` needs a convex object
      (`obs.transfer` holds $l \\le 2$ only).
    - `throw`: raise `solvers.SolveError` unless the status is `converged`.

    **Returns:** `LightingResult` (module docstring).
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations, got {type(obs).__name__}")
    _check_brdf(brdf, obs.n_channels)
    lmax = check_int(lmax, "lmax", lo=0)
    ridge = check_float(ridge, "ridge")
    rcond = None if rcond is None else check_float(rcond, "rcond")
    chunk = check_int(chunk, "chunk")
    if diffuse_bands not in ("l2", "literal"):
        raise ValueError(f"`diffuse_bands` must be 'l2' or 'literal', got {diffuse_bands!r}")
    if diffuse_bands == "literal" and obs.transfer is not None:
        raise ValueError("`diffuse_bands='literal'` needs a convex object: `obs.transfer` holds the l <= 2 "
                         "transfer vector only (give obs without transfer, or diffuse_bands='l2')")
    c = obs.n_channels
    dt = obs.values.dtype
    kd = jnp.broadcast_to(jnp.asarray(brdf.kd, dt), (c,))
    ks = jnp.broadcast_to(jnp.asarray(brdf.ks, dt), (c,))
    if rcond is None:
        rcond = 1e-12 if dt == jnp.float64 else 1e-6
    res = _inverse_lighting(obs, kd, ks, None if brdf.mu is None else jnp.asarray(brdf.mu, dt),
                            jnp.asarray(brdf.sigma, dt), lmax, deconvolve, float(ridge), float(rcond), int(chunk),
                            diffuse_bands == "literal", pixel_sharding(obs.normals))
    return finish(res, throw)


@jaxsh.jit
def _inverse_lighting(obs, kd, ks, mu, sigma, lmax, deconvolve, ridge, rcond, chunk, literal=False, where=None):
    """`where`: `pixel_sharding(obs.normals)` (static): the pixel sums run on each device's pixels (`_pixel_sums`)."""
    filt = None
    if deconvolve:
        filt = jaxsh.microfacet_spectrum(sigma, lmax)[jaxsh.sh_degrees(lmax)]
    pixels = (obs.normals, obs.views, obs.values, obs.weights, obs.transfer, obs.reflected_visibility)
    rss_of = functools.partial(_residual_ss, pixels, kd, ks, mu, filt, lmax, chunk, literal, where)
    if literal:
        ata, atb, bb, count = sum_over_pixels(functools.partial(_literal_system, lmax=lmax, chunk=chunk), where,
                                              pixels, (kd, ks, mu, filt))
        return _lighting_from_system(ata, atb, bb, count, kd, lmax, ridge, rcond, rss_of)
    g = sum_over_pixels(lambda n, v, b, w, t, r, mu_, filt_: accumulate_gram(n, v, b, w, t, r, mu_, filt_, lmax, chunk),
                        where, pixels, (mu, filt))
    ata, atb = channel_system(g, kd, ks)
    return _lighting_from_system(ata, atb, g.bb, g.count, kd, lmax, ridge, rcond, rss_of)


def _residual_ss(pixels, kd, ks, mu, filt, lmax, chunk, literal, where, x, rss_normal, bb):
    """$\\sum_i w_i (A_c x_c - b_c)_i^2$ per channel `(C,)`, summed over pixel chunks (`lax.scan`), for `eig_solve`.

    The normal equations' form $b^Tb - 2x^TA^Tb + x^TA^TAx$ cancels: its rounding is about $\\epsilon\\,b^Tb$.
    In float32 that is most of the RSS of any well-fitting capture (rms 1.18× the residual's at 1 % noise, 50× at
    0.01 %), so the pass always runs there. In float64 it runs only where that form is below $10^{-6}\\,b^Tb$
    (a relative rms under 0.1 %, e.g. noise-free images, where it gave an RSS of exactly 0 and infinite band SNRs)
    (`lax.cond`); above, its rounding is under $10^{-9}$ of the RSS."""

    def exact():
        return sum_over_pixels(exact_local, where, pixels, (kd, ks, mu, filt, x, rss_normal))

    def exact_local(n, v, b, w, t, r, kd, ks, mu, filt, x, rss_normal):
        n_p, v_p, b_p, w_p, t_p, r_p = pixel_chunks(n, v, chunk, b, w, t, r)

        def step(acc, xs):
            nn, vv, bb_, ww, tt, rr = xs
            d, s = eq25_rows(nn, vv, tt, rr, mu, filt, lmax, coeffs_first=True)  # (9, P), (n, P)
            if literal:  # the diffuse rows of every band (`_literal_system`)
                lam = jaxsh.lambertian_spectrum(lmax, d.dtype)[jaxsh.sh_degrees(lmax)]
                vis = jnp.sum(nn * vv, -1) > 0
                d = jnp.where(vis[None, :], jaxsh.real_sh(nn, lmax, coeffs_first=True) * lam[:, None], 0.0)
            k = min(d.shape[0], x.shape[1])  # the diffuse rows are padded to 9 below l* = 2
            pred = kd[:, None] * (x[:, :k] @ d[:k]) + ks[:, None] * (x @ s)  # (C, P)
            r = pred - bb_.T
            return acc + jnp.sum(ww[None, :] * r * r, 1), None

        return jax.lax.scan(step, jnp.zeros_like(rss_normal), (n_p, v_p, b_p, w_p, t_p, r_p))[0]

    if x.dtype != jnp.float64:
        return exact()
    # `bb`: the data's weighted sum of squares per channel, accumulated with the normal equations
    return jax.lax.cond(jnp.any(rss_normal < 1e-6 * bb), exact, lambda: rss_normal)


def _literal_system(n, v, b, w, transfer, rvis, kd, ks, mu, filt, *, lmax, chunk):
    """Normal equations of eq. 25 as printed: diffuse rows $\\Lambda_l\\hat\\rho_l Y_{lm}(n)$ for every $l \\le l^*$.

    Per channel $A_c = K_{d,c}D + K_{s,c}S$, with $D$ and $S$ both `(N, n_coeffs)`; the sums
    $D^TWD$, $D^TWS$, $S^TWS$, $D^TWb$, $S^TWb$ are accumulated over pixel chunks (`lax.scan`).
    Returns `ata (C, n, n)`, `atb (C, n)`, `bb (C,)`, `count ()`: sums over the pixels (`transfer` unused: the
    literal system needs a convex object).
    """
    del transfer
    npx = n.shape[0]
    pad = (-npx) % chunk
    up = jnp.zeros((pad, 3), n.dtype).at[:, 2].set(1.0)
    dt = n.dtype
    nc = (lmax + 1) ** 2
    c = b.shape[1]
    xs = (jnp.concatenate([n, up]).reshape(-1, chunk, 3), jnp.concatenate([v, up]).reshape(-1, chunk, 3),
          jnp.pad(b, ((0, pad), (0, 0))).reshape(-1, chunk, c), jnp.pad(w, (0, pad)).reshape(-1, chunk),
          None if rvis is None else jnp.pad(rvis, (0, pad)).reshape(-1, chunk))
    lam = jaxsh.lambertian_spectrum(lmax, dt)[jaxsh.sh_degrees(lmax)]  # thesis eq. 3.32

    def step(acc, x):
        nn, vv, bb_, ww, rr = x
        _, s = eq25_rows(nn, vv, None, rr, mu, filt, lmax)
        vis = jnp.sum(nn * vv, -1) > 0
        d = jnp.where(vis[:, None], jaxsh.real_sh(nn, lmax) * lam[None, :], 0.0)
        wd, ws = d * ww[:, None], s * ww[:, None]
        dd, ds, ss, db, sb, sq, cnt = acc
        return (dd + wd.T @ d, ds + wd.T @ s, ss + ws.T @ s, db + wd.T @ bb_, sb + ws.T @ bb_,
                sq + jnp.sum(ww[:, None] * bb_ * bb_, 0), cnt + jnp.sum((ww > 0).astype(dt))), None

    z = jnp.zeros((nc, nc), dt)
    init = (z, z, z, jnp.zeros((nc, c), dt), jnp.zeros((nc, c), dt), jnp.zeros((c,), dt), jnp.zeros((), dt))
    (dd, ds, ss, db, sb, sq, cnt), _ = jax.lax.scan(step, init, xs)
    ata = (kd**2)[:, None, None] * dd[None] + (kd * ks)[:, None, None] * (ds + ds.T)[None] + (ks**2)[:, None, None] * ss[None]
    atb = (kd[None, :] * db + ks[None, :] * sb).T
    return ata, atb, sq, cnt


def lighting_from_gram(g: Gram, kd, ks, lmax, ridge, rcond) -> LightingResult:
    """The eq.-25 solve from accumulated Gram blocks (stage 1 of `factorize`: its RSS from the normal equations)."""
    ata, atb = channel_system(g, kd, ks)
    return _lighting_from_system(ata, atb, g.bb, g.count, kd, lmax, ridge, rcond)


def _lighting_from_system(ata, atb, bb, count, kd, lmax, ridge, rcond, rss_of=None) -> LightingResult:
    x, se, det, sv, rss, rank = eig_solve(ata, atb, bb, count, rcond, ridge, rss_of)
    # per-band reductions over the (n, L+1) band indicator (a NumPy constant): one kernel each, where a slice and
    # a reduction per band were 2 (L+1) kernels to compile (a masked sum, not a product with the indicator:
    # an infinite SNR times 0 would be NaN in the other bands)
    band = jnp.asarray(jaxsh.sh_degrees(lmax)[:, None] == np.arange(lmax + 1)[None, :])  # (n, L+1)
    width = jnp.asarray(2.0 * np.arange(lmax + 1) + 1.0, x.dtype)  # coefficients per band
    # supported l*: largest l with all coefficients of degree <= l determined.
    band_ok = jnp.all(det[:, :, None] | ~band[None], axis=1)  # (C, L+1)
    prefix = jnp.cumprod(band_ok.astype(jnp.int32), -1)
    supported = jnp.sum(prefix, -1) - 1
    snr2 = jnp.where(det, (x / jnp.where(det, se, 1.0)) ** 2, 0.0)
    band_snr = jnp.sqrt(jnp.sum(jnp.where(band[None], snr2[:, :, None], 0.0), axis=1) / width[None, :]).T  # (L+1, C)
    nobs = count * kd.shape[0]
    data_ss = jnp.sum(bb)
    rms, rel = rms_pair(jnp.sum(rss), data_ss, nobs)
    finite = jnp.all(jnp.isfinite(x)) & jnp.isfinite(rms)
    # trace(A^T W A) per channel: 0 for an all-zero BRDF (kd = ks = 0), whose images carry no lighting information
    design_ss = jnp.min(jnp.trace(ata, axis1=1, axis2=2))
    status = worst(
        Status.where(finite, Status.converged, Status.nonfinite),
        signal_status(data_ss),
        signal_status(design_ss),
        Status.where(jnp.all(det), Status.converged, Status.ill_conditioned),
    )
    return LightingResult(coeffs=x.T, std_errors=se.T, determined=det.T, singular_values=sv, supported_lmax=supported,
                          band_snr=band_snr, status=status, rms=rms, rel_rms=rel, iterations=jnp.asarray(0),
                          stats={"rank": rank, "n_obs": nobs})


# --------------------------------------------------------------------------- the dual method (fig. 8)


class DualLightingResult(Solution):
    """Result of `inverse_lighting_dual` (a `solvers.Solution`; `estimate` is `image`).

    - `image`: `(H, W, C)` lat-long lighting in angular space (the filtered
      lighting seen in the mirror directions; texels no mirror direction
      reaches hold the $l \\le 2$ field of the phase-1 `coeffs9` without
      `nonneg`; with it they are tied to that field clipped at 0 (curvature
      1 % of a seen texel's) and `coeffs9` is the refined image's
      projection; in a channel with $K_s = 0$ the whole image is that field).
    - `coeffs9`: `(9, C)` the frequency-space coefficients $L_{lm}$, $l \\le 2$,
      solving the consistency condition $L^1 = L^2$.
    - `covered`: `(H, W)` bool, texels reached by a mirror direction (in the
      channels with $K_s > 0$; all False when $K_s = 0$ everywhere).
    - `consistency`: `(C,)` $|L^1 - L^2| / |L^1|$ of the returned image
      (0 up to round-off without `nonneg`; small with it).
    - `status`: the worst of the consistency solve's (lineax LU, via
      `status_from_optimistix`: `singular` for a singular system), the
      L-BFGS-B refinement's (`status_from_lbfgsb`: `max_steps_reached` when
      its projected-gradient error is still above its tolerance after
      `maxiter` iterations), `nonfinite`, `no_signal` (all-zero data, or
      $K_d = K_s = 0$ in some channel) and `ill_conditioned` for a channel
      with $K_s = 0$ (Lambertian: only $l \\le 2$ is determined, R&H sec. 3;
      see `inverse_lighting_dual`).
    - `rms`, `rel_rms` (never NaN), `iterations` (of the non-negative refinement; 0 without it).
    - `stats`: `lbfgsb_error` (final projected-gradient norm; 0 without
      `nonneg`), `lbfgsb_tol` (the tolerance used: `tol` raised to 256 ε of
      the dtype), `n_obs`.
    """

    image: Float[Array, "H W C"]
    coeffs9: Float[Array, "9 C"]
    covered: Bool[Array, "H W"]
    consistency: Float[Array, " C"]
    status: Status
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    iterations: Int[Array, ""]
    stats: dict

    @property
    def estimate(self) -> Float[Array, "H W C"]:
        return self.image


@blas_single_thread
def inverse_lighting_dual(
    obs: Observations,
    brdf: TorranceSparrow,
    height: int | None = None,
    *,
    nonneg: bool = True,
    maxiter: int = 300,
    tol: float = 1e-8,
    throw: bool = False,
) -> DualLightingResult:
    """The dual angular / frequency-space inverse lighting of R&H sec. 6.2 (fig. 8).

    Phase 1 turns 9 coefficients $L^1$ into a high-resolution lighting image:
    each lat-long texel $t$ takes the least-squares value of
    $(B - K_d E(L^1))/(K_s F)$ over the pixels whose mirror direction falls in
    it (eq. 22 with $B_{s,fast} = 0$). Phase 2 projects that image to 9
    coefficients $L^2$. Both are affine in $L^1$, so the consistency
    condition $L^1 = L^2$ is 9 linear equations per channel, solved
    directly (`lineax.LU`). With `nonneg=True` the image is then refined by
    jaxopt's L-BFGS-B under $L \\ge 0$ (at most `maxiter` iterations),
    minimizing the image residual of the same model with the diffuse term
    driven by the image's own $l \\le 2$ projection (consistency by
    construction): the loss is the weighted residual sum of squares over the
    data's ($\\mathrm{rel\\_rms}^2$), plus a tie of each texel no pixel sees to
    the phase-1 field (clipped at 0) with a curvature of 1 % of the median
    seen texel's, so the minimizer is unique (left free, those texels bend
    to fit the diffuse term). `coeffs9` is then the image's $l \\le 2$
    projection. `tol` is L-BFGS-B's test on the largest component of the
    projected gradient (absolute, jaxopt's) in preconditioned unknowns:
    each texel scaled by the root of its curvature, so a component is about
    that texel's Newton step, and moving the texel alone would lower the
    loss by about its square / 2 — the same at any radiometric scale and
    any number of pixels per texel. `tol` is raised to 256 eps of the
    dtype (3.1e-5 in float32, 5.7e-14 in float64: the gradient's
    round-off); `stats["lbfgsb_tol"]` is the tolerance used. At the default
    `height` it converged in 50-69 iterations on the spheres measured
    (`sphere_capture`, 3 views, 32²-128²; finer grids need more, below), and
    the result does not depend on `maxiter` once the status is `converged`.
    `throw`: raise `solvers.SolveError` unless the status is `converged`.

    `height`: the lat-long grid `(height, 2·height)`, at least 4. Default
    (None): `default_dual_height` of the samples of positive weight,
    $\\lfloor\\sqrt{n/32}\\rfloor$ clipped to [8, 64] (about 16 pixels per
    texel; 64 from about 131,000 samples). A finer grid than the pixels
    support leaves texels that no mirror direction reaches and slows
    L-BFGS-B down: on `sphere_capture`s of 3 views, 1 % noise, 1,968 and
    7,980 pixels (32² and 64²), height 64 stopped at `max_steps_reached`
    (300 iterations) with 22 % and 64 % of the texels seen and relative
    errors of 0.82 and 0.59 against the true filtered lighting; the default
    heights 8 and 15 converged in 50 and 52 iterations with all texels seen
    and errors 0.21 and 0.15. (64 was the default before.)

    Convex objects only (the paper: with shadows $B_d$ no longer depends on
    9 coefficients); `obs.transfer` must be None. `brdf`: homogeneous.
    Returns `DualLightingResult`.

    **Lambertian channels ($K_s = 0$).** There is no mirror term to carry
    the image, and a Lambertian surface determines the lighting only up to
    $l = 2$ (R&H sec. 3). In such a channel `coeffs9` is the weighted
    least-squares fit of the diffuse term alone (eq. 21, minimum norm:
    as `inverse_lighting(obs, brdf, 2)`), `image` its $l \\le 2$ field
    (with `nonneg` refined under $L \\ge 0$, tied to that field clipped at
    0 as above; that clipped field itself when no channel has $K_s > 0$), and the
    status is `ill_conditioned` (the angular detail is undetermined), never
    an exception. With $K_d = K_s = 0$ the status is `no_signal`.
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations, got {type(obs).__name__}")
    _check_brdf(brdf, obs.n_channels)
    if obs.transfer is not None:
        raise ValueError("inverse_lighting_dual: concave objects (`obs.transfer` given) are not supported (R&H sec. 6.4)")
    h = default_dual_height(_positive_samples(obs)) if height is None else check_int(height, "height", lo=4)
    maxiter = check_int(maxiter, "maxiter")
    tol = check_float(tol, "tol")
    c = obs.n_channels
    dt = obs.values.dtype
    kd = jnp.broadcast_to(jnp.asarray(brdf.kd, dt), (c,))
    ks = jnp.broadcast_to(jnp.asarray(brdf.ks, dt), (c,))
    mu = None if brdf.mu is None else jnp.asarray(brdf.mu, dt)
    rcond = 1e-12 if dt == jnp.float64 else 1e-6
    img, l9, cov, iters, error, lin = _dual(obs, kd, ks, mu, h, nonneg, int(maxiter), float(tol), rcond)
    res = _dual_finish(obs, kd, ks, mu, img, l9, cov, iters, error, lin, h, nonneg, int(maxiter), float(tol))
    return finish(res, throw)


def default_dual_height(n_samples: int) -> int:
    """The default lat-long grid of the dual method for `n_samples` samples of positive weight:
    $\\lfloor\\sqrt{n/32}\\rfloor$ clipped to [8, 64], so the `(h, 2h)` grid has about 16 samples per texel
    (`inverse_lighting_dual`'s `height`, `factorize`'s `dual_height`)."""
    return int(np.clip(np.floor(np.sqrt(int(n_samples) / 32.0)), 8, 64))


def _positive_samples(obs: Observations) -> int:
    """The samples of positive weight (weight-0 padding, e.g. `shard_observations`, is not counted); on the host
    when the weights are (an eager `jnp` reduction compiles a program of its own)."""
    w = obs.weights
    if getattr(w, "is_fully_addressable", True):
        return int(np.count_nonzero(np.asarray(w) > 0))
    return int(jnp.sum(w > 0))


def _dual_pieces(obs, kd, ks, mu, h):
    w_ = 2 * h
    dt = obs.values.dtype
    n, v, b, wts = obs.normals, obs.views, obs.values, obs.weights
    cos_o = jnp.sum(n * v, -1)
    vis = cos_o > 0
    cos_o = jnp.where(vis, cos_o, 1.0)
    f = jnp.ones_like(cos_o) if mu is None else jaxsh.fresnel_normalized(cos_o, mu)
    r = jaxsh.reflect(v, n)
    theta = jnp.arccos(jnp.clip(r[:, 2], -1.0, 1.0))
    phi = jnp.mod(jnp.arctan2(r[:, 1], r[:, 0]), 2 * jnp.pi)
    row = jnp.clip(jnp.floor(theta / jnp.pi * h).astype(jnp.int32), 0, h - 1)
    col = jnp.clip(jnp.floor(phi / (2 * jnp.pi) * w_).astype(jnp.int32), 0, w_ - 1)
    tex = row * w_ + col
    a9 = jaxsh.lambertian_spectrum(2, dt)[jaxsh.sh_degrees(2)]
    d = jaxsh.real_sh(n, 2) * a9[None, :]  # (N, 9)
    wv = jnp.where(vis, wts, 0.0)
    dirs = jaxsh.latlong_directions(h, w_, dtype=dt).reshape(-1, 3)
    omega = jaxsh.latlong_weights(h, w_, dtype=dt).reshape(-1)
    y9 = jaxsh.real_sh(dirs, 2)  # (T, 9)
    return f, tex, d, wv, y9, omega, b


def _diffuse_l2(d, wv, b, kd, rcond):
    """Per channel, the minimum-norm weighted LSQ $L_{lm}$, $l \\le 2$, of $K_d\\,d\\,L = B$ (eq. 21): `(9, C)` (0 where $K_d = 0$)."""
    dw = d * wv[:, None]
    evals, evecs = jnp.linalg.eigh(d.T @ dw)  # (9,), (9, 9): one system for every channel, scaled by kd^2
    keep = evals > rcond * jnp.maximum(evals[-1], 0.0)
    inv = jnp.where(keep, 1.0 / jnp.where(keep, evals, 1.0), 0.0)
    x = evecs @ (inv[:, None] * (evecs.T @ (dw.T @ b)))  # (9, C) for unit kd
    ok = kd > 0
    return jnp.where(ok[None, :], x / jnp.where(ok, kd, 1.0)[None, :], 0.0)


@jaxsh.jit
def _dual(obs, kd, ks, mu, h, nonneg, maxiter, tol, rcond):
    t_count = h * 2 * h
    f, tex, d, wv, y9, omega, b = _dual_pieces(obs, kd, ks, mu, h)
    c = b.shape[1]
    g = ks[None, :] * f[:, None]  # (N, C) the mirror-term gain K_s F

    def seg(x):
        return jax.ops.segment_sum(x, tex, num_segments=t_count)

    den = seg(wv[:, None] * g * g)  # (T, C)
    cov_c = den > 0  # (T, C): the same texels in every channel with ks > 0, none where ks = 0
    covered = jnp.any(cov_c, axis=1)
    lambertian = ks == 0  # (C,): no mirror term; the l <= 2 diffuse fit instead of the consistency solve
    den_s = jnp.where(cov_c, den, 1.0)
    a = jnp.where(cov_c, seg(wv[:, None] * g * b) / den_s, 0.0)  # (T, C)
    # L_map = a - M L1 on covered texels, M[t, c, :] = sum w g kd d / den; uncovered: L_map = y9 L1
    m = seg((wv[:, None] * g * kd[None, :])[:, :, None] * d[:, None, :]) / den_s[:, :, None]  # (T, C, 9)
    m = jnp.where(cov_c[:, :, None], m, -y9[:, None, :])
    p = (omega[:, None] * y9).T  # (9, T) projection to l <= 2
    pa = p @ a  # (9, C)
    pm = jnp.einsum("it,tcj->cij", p, m)  # (C, 9, 9)
    eye = jnp.eye(9, dtype=b.dtype)

    def consistency_solve(mat, rhs):  # (I + P M_c) L1_c = P a_c, one 9x9 LU solve per channel (outside loops)
        sol = lx.linear_solve(lx.MatrixLinearOperator(mat), rhs, lx.LU(), throw=False)
        return sol.value, status_from_optimistix(sol.result)

    # a Lambertian channel's consistency matrix is I - P Y9 ~ 0: solve I x = 0 there and use the diffuse fit
    mats = jnp.where(lambertian[:, None, None], eye[None], eye[None] + pm)
    # one channel at a time on a CPU (`map_lapack`: a batched CPU LU can deadlock, `solvers._lapack`)
    l1, lin = map_lapack(consistency_solve, mats, jnp.where(lambertian[:, None], 0.0, pa.T))
    l1 = jnp.where(lambertian[None, :], _diffuse_l2(d, wv, b, kd, rcond), l1.T)  # (9, C)
    # only l <= 2 is determined in a Lambertian channel (R&H sec. 3)
    lin = jax.vmap(lambda lam, st: Status.where(lam, Status.ill_conditioned, st))(lambertian, lin)
    img = a - jnp.einsum("tcj,jc->tc", m, l1)  # (T, C)
    iters = jnp.asarray(0)
    error = jnp.zeros((), b.dtype)
    if nonneg:
        from ._jaxopt import minimize_nonnegative

        # The loss is the weighted residual sum of squares over the data's (rel_rms^2: scale-free) plus a tie of the
        # texels no pixel sees to the phase-1 field (clipped at 0), with a curvature of 1 % of the median seen
        # texel's. A seen texel's curvature is 2 sum(w g^2) / sum(w b^2) (the Hessian's diagonal up to the diffuse
        # coupling, ~1e-3 of it). The old tie (1e-6 / T, ~1e-7 of a seen texel's curvature) left near-null
        # directions (40 of 512 texels at h = 16): no convergence in 3000 iterations, and its optimum (scipy BVLS)
        # 3x further from the true l <= 2 lighting, the unseen texels bent to fit the diffuse term. Fixing them
        # (no tie) is as well-posed but 1.1-1.5x further from the truth on the captures measured; 1 % is as close
        # or closer at every h measured (16-64), in 13-161 iterations.
        fixed = jnp.maximum(img, 0.0)
        raw_ss = jnp.sum(wv[:, None] * b * b)
        data_ss = jnp.where(raw_ss > 0, raw_ss, 1.0)  # black images: the plain RSS (a tiny floor made inf curvatures)
        curv = jnp.where(cov_c, 2.0 * den_s / data_ss, jnp.nan)
        seen_any = jnp.any(cov_c)
        tie = jnp.where(cov_c, 0.0, jnp.where(seen_any, 0.01 * jnp.nanmedian(curv), 0.0))  # (T, C)
        free = cov_c | seen_any  # nothing seen anywhere (K_s = 0): the field, clipped, is the image
        # Preconditioned: x = scale * y, each free texel scaled by the root of its curvature, so a projected-gradient
        # component of L-BFGS-B is about the texel's own Newton step in these units (moving it alone lowers the loss
        # by about its square / 2): `tol` means the same at any radiometric scale and pixels per texel.
        scale = jnp.where(free, 1.0 / jnp.sqrt(jnp.where(cov_c, curv, jnp.where(free, tie, 1.0))), 0.0)

        def image_of(y):
            return jnp.where(free, scale * y, fixed)

        def loss(y):
            x = image_of(y)
            l9 = p @ x  # (9, C): the image's own l <= 2 part drives the diffuse term
            pred = kd[None, :] * (d @ l9) + g * x[tex]
            return jnp.sum(wv[:, None] * (pred - b) ** 2) / data_ss + 0.5 * jnp.sum(tie * (x - fixed) ** 2)

        ok = free & (scale > 0)
        y0 = jnp.where(ok, fixed / jnp.where(ok, scale, 1.0), 0.0)
        y, iters, error = minimize_nonnegative(loss, y0, maxiter=maxiter, tol=tol)
        img = image_of(y)
        l1 = p @ img
    return img, l1, covered, iters, error, lin


def _dual_finish(obs, kd, ks, mu, img, l1, covered, iters, error, lin, h, nonneg, maxiter, tol):
    f, tex, d, wv, y9, omega, b = _dual_pieces(obs, kd, ks, mu, h)
    g = ks[None, :] * f[:, None]
    pred = kd[None, :] * (d @ l1) + g * img[tex]
    rss = jnp.sum(wv[:, None] * (pred - b) ** 2)
    nobs = jnp.sum((wv > 0).astype(b.dtype)) * b.shape[1]
    data_ss = jnp.sum(wv[:, None] * b * b)
    design_ss = jnp.min(kd**2 * jnp.sum(wv * jnp.sum(d * d, -1)) + jnp.sum(wv[:, None] * g * g, 0))  # 0: kd = ks = 0
    rms, rel = rms_pair(rss, data_ss, nobs)
    p = (omega[:, None] * y9).T
    l2 = p @ img
    n1 = jnp.linalg.norm(l1, axis=0)
    n21 = jnp.linalg.norm(l2 - l1, axis=0)
    consistency = jnp.where(n1 > 0, n21 / jnp.where(n1 > 0, n1, 1.0), jnp.where(n21 > 0, jnp.inf, 0.0))
    finite = jnp.all(jnp.isfinite(img)) & jnp.isfinite(rms)
    st_lin = worst_batched(lin)
    if nonneg:
        from ._jaxopt import effective_tol

        tol = effective_tol(tol, b.dtype)  # the tolerance the run stopped at (raised to 256 eps of the dtype)
    st_lbfgsb = status_from_lbfgsb(iters, error, maxiter, tol) if nonneg else Status.converged
    status = worst(Status.where(finite, Status.converged, Status.nonfinite), signal_status(data_ss),
                   signal_status(design_ss), st_lin, st_lbfgsb)
    return DualLightingResult(image=img.reshape(h, 2 * h, -1), coeffs9=l1, covered=covered.reshape(h, 2 * h),
                              consistency=consistency, status=status, rms=rms, rel_rms=rel, iterations=jnp.asarray(iters),
                              stats={"lbfgsb_error": error, "lbfgsb_tol": jnp.asarray(tol, b.dtype), "n_obs": nobs})
