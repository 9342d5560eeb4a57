"""Factorization: unknown lighting and BRDF (R&H 2001 sec. 6.3), and roughness from a source (eq. 26).

**Algorithm (the paper's, restructured for speed, same minimum).** The
global scale is unrecoverable, so $K_d + K_s = 1$ per channel (each
channel's lighting absorbs its own scale). The paper's simplex over
$(K_s, \\mu)$ with an inner inverse-lighting solve is run as two nested
searches with the same objective, the RMS of the eq.-25 fit:

* outer: `optimistix.NelderMead` over $\\log(\\mu - 1)$; each evaluation forms
  the normal-equation blocks of eq. 25 for that $\\mu$ once (the expensive
  part, $O(N n^2)$, optionally on a random pixel subset);
* inner: per channel, a golden-section search over $K_s \\in [0, 1]$
  ($K_d = 1 - K_s$), each step an $n \\times n$ Cholesky solve for $L_{lm}$.

Then $\\sigma$ from the recovered (filtered) lighting with eq. 26,
$L_{cen} \\approx L_{tot}/(4\\pi\\sigma^2)$, evaluated with the band limit
taken into account: the brightest compact region is found automatically
(or given by the user), and $\\sigma$ solves
$\\frac{L_{cen} - b}{L_{tot} - b\\,\\Omega} = \\frac{f_\\sigma(0) - b_\\sigma}{\\int_{cap} f_\\sigma - b_\\sigma\\Omega}$,
where $f_\\sigma(\\theta) = \\sum_{l \\le l^*}\\frac{2l+1}{4\\pi}e^{-(\\sigma l)^2}P_l(\\cos\\theta)$ is
a unit delta source filtered by the lobe and truncated like the recovered
lighting, and $b$, $b_\\sigma$ the background levels measured on the same
annulus around each. For $l^* \\to \\infty$ this is eq. 26.

**Joint refinement (optional).** With the source found, the lighting is
modelled as slow SH up to $l^*$ (filtered by $e^{-(\\sigma l)^2}$, eq. 22) plus
the source as a delta of unknown energy (eq. 23); the model is linear in
the lighting given $(K_s, \\mu, \\sigma)$, and a simplex over those
(variable projection) refines all of them together.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, Int, Real

import jaxsh

from ._threads import blas_single_thread
from ._data import Lighting, Observations, Status, TorranceSparrow
from ._lighting import _finish, _gram, _Gram

_GOLDEN = float(0.5 * (np.sqrt(5.0) - 1.0))  # a Python float: weakly typed, keeps float32


class SourceEstimate(eqx.Module):
    """A compact source found in a recovered lighting (R&H fig. 10).

    `direction` `(3,)`; `energy` `(C,)` = $L_{tot}$ above the background;
    `peak` `(C,)` = $L_{cen}$ above the background; `background` `(C,)`;
    `radius`: the region's angular radius; `sigma`: the roughness from eq. 26
    with the band-limit correction (module docstring); `sigma_eq26`: the
    plain $\\sqrt{L_{tot}/(4\\pi L_{cen})}$.
    """

    direction: Float[Array, "3"]
    energy: Float[Array, " C"]
    peak: Float[Array, " C"]
    background: Float[Array, " C"]
    radius: Float[Array, ""]
    sigma: Float[Array, ""]
    sigma_eq26: Float[Array, ""]


class FactorizationResult(eqx.Module):
    """Result of `factorize`.

    - `brdf`: `TorranceSparrow` with $K_d + K_s = 1$ per channel.
    - `lighting`: the recovered lighting in the same scale — after the
      refinement, slow SH (unfiltered, to `lmax`) plus the source as a fast
      delta; without it, the filtered SH lighting of eq. 25.
    - `filtered_sh`: `(n_coeffs, C)` the eq.-25 (filtered) lighting of the
      first stage, the input of eq. 26.
    - `source`: `SourceEstimate` (or None when `find_sigma=False`).
    - `std_errors`: `TorranceSparrow` (from the Jacobian of the profiled
      residual of the final stage; `kd` errors equal `ks` errors).
    - `status`, `iterations`, `rms`, `rel_rms`.
    """

    brdf: TorranceSparrow
    lighting: Lighting
    filtered_sh: Float[Array, "n_coeffs C"]
    source: SourceEstimate | None
    std_errors: TorranceSparrow
    status: Status
    iterations: Int[Array, ""]
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]


# --------------------------------------------------------------------------- stage 1


def _small_spd_solve(m, r):
    """Solve SPD systems m x = r, batched over leading axes, by Gaussian elimination unrolled in Python.

    For the 9x9 / 10x10 Schur complements inside the searches: plain XLA ops, no LAPACK
    custom call (those deadlock or stall on re-execution inside XLA:CPU loops, measured)."""
    k = m.shape[-1]
    scale = jnp.maximum(jnp.max(jnp.abs(jnp.diagonal(m, axis1=-2, axis2=-1)), -1), jnp.finfo(m.dtype).tiny)
    m = m + (jnp.finfo(m.dtype).eps * 16) * scale[..., None, None] * jnp.eye(k, dtype=m.dtype).reshape((1,) * (m.ndim - 2) + (k, k))
    a = jnp.concatenate([m, r[..., None]], -1)
    for i in range(k):
        piv = a[..., i, i]
        piv = jnp.where(jnp.abs(piv) > 0, piv, jnp.finfo(m.dtype).tiny)
        row = a[..., i, :] / piv[..., None]
        a = a - a[..., :, i : i + 1] * row[..., None, :]
        a = a.at[..., i, :].set(row)
    return a[..., :, -1]


def _pinv_psd(a, rcond):
    """Pseudo-inverse of a symmetric PSD matrix by eigendecomposition (eigenvalues < rcond·max dropped)."""
    evals, evecs = jnp.linalg.eigh(a)
    keep = evals > rcond * jnp.max(evals)
    inv = jnp.where(keep, 1.0 / jnp.where(keep, evals, 1.0), 0.0)
    return (evecs * inv[..., None, :]) @ jnp.swapaxes(evecs, -1, -2)


class _Blocks(eqx.Module):
    """Normal-equation blocks of eq. 25 for one mu, split at the l <= 2 columns, with pinv(SS22)."""

    g: _Gram
    p22: Array  # (n-9, n-9)


def _blocks(o: Observations, mu, lmax: int, chunk: int, rcond: float) -> _Blocks:
    g = _gram(o.normals, o.views, o.values, o.weights, o.transfer, o.reflected_visibility, mu, None, lmax, chunk)
    return _Blocks(g, _pinv_psd(g.ss[9:, 9:], rcond))


def _schur_rss(bl: _Blocks, kd, ks, filt, src=None):
    """RSS of the eq.-25 least-squares fit per channel by block elimination (no LAPACK).

    Unknowns: L_lm (filtered by `filt` in the specular rows) and, with `src`, one
    delta-source energy. `kd`, `ks`: (C,). `src` = (a_d (9,C), a_s (n-9,C), a_ss (C,), r_s (C,))
    holds A_1s, A_2s (already combined for each channel), A_ss and A_s^T b.
    Returns rss (C,), x1 (C, 9[+1]), x2 (C, n-9)."""
    g = bl.g
    f1, f2 = filt[:9], filt[9:]
    kd_, ks_ = kd[:, None, None], ks[:, None, None]
    ds1 = g.ds[:, :9] * f1[None, :]
    a11 = kd_**2 * g.dd[None] + kd_ * ks_ * (ds1 + ds1.T)[None] + ks_**2 * (f1[:, None] * g.ss[:9, :9] * f1[None, :])[None]
    a12 = kd_ * ks_ * (g.ds[:, 9:] * f2[None, :])[None] + ks_**2 * (f1[:, None] * g.ss[:9, 9:] * f2[None, :])[None]
    r1 = (kd[None, :] * g.db + ks[None, :] * f1[:, None] * g.sb[:9]).T  # (C, 9)
    r2 = (ks[None, :] * f2[:, None] * g.sb[9:]).T  # (C, m)
    if src is not None:
        a_d, a_s, a_ss, r_s = src
        a11 = jnp.concatenate(
            [jnp.concatenate([a11, a_d.T[:, :, None]], 2), jnp.concatenate([a_d.T[:, None, :], a_ss[:, None, None]], 2)], 1
        )
        a12 = jnp.concatenate([a12, a_s.T[:, None, :]], 1)
        r1 = jnp.concatenate([r1, r_s[:, None]], 1)
    # A22^-1 = diag(1/f2) pinv(SS22) diag(1/f2) / ks^2
    inv_f2 = 1.0 / f2
    q = bl.p22[None] * (inv_f2[:, None] * inv_f2[None, :])[None] / (ks**2)[:, None, None]
    y = jnp.einsum("cij,cj->ci", q, r2)
    yy = jnp.einsum("cij,ckj->cik", q, a12)  # (C, m, k)
    schur = a11 - jnp.einsum("ckj,cjl->ckl", a12, yy)
    rhs = r1 - jnp.einsum("ckj,cj->ck", a12, y)
    x1 = _small_spd_solve(schur, rhs)
    x2 = y - jnp.einsum("cjk,ck->cj", yy, x1)
    rss = g.bb - jnp.sum(r1 * x1, -1) - jnp.sum(r2 * x2, -1)
    return rss, x1, x2


def _golden_ks(fn, c: int, dt, iters: int):
    """Golden-section search of fn(ks (C,)) -> (C,) over [0, 1] per channel; endpoints checked."""
    lo, hi = jnp.full((c,), 1e-6, dt), jnp.ones((c,), dt)
    x1 = hi - _GOLDEN * (hi - lo)
    x2 = lo + _GOLDEN * (hi - lo)
    f1, f2 = fn(x1), fn(x2)

    def body(_, st):
        lo, hi, x1, x2, f1, f2 = st
        left = f1 < f2
        nlo = jnp.where(left, lo, x1)
        nhi = jnp.where(left, x2, hi)
        nx1 = jnp.where(left, nhi - _GOLDEN * (nhi - nlo), x2)
        nx2 = jnp.where(left, x1, nlo + _GOLDEN * (nhi - nlo))
        fnew = fn(jnp.where(left, nx1, nx2))
        return nlo, nhi, nx1, nx2, jnp.where(left, fnew, f2), jnp.where(left, f1, fnew)

    lo, hi, x1, x2, f1, f2 = jax.lax.fori_loop(0, iters, body, (lo, hi, x1, x2, f1, f2))
    ks = jnp.where(f1 < f2, x1, x2)
    fk = jnp.minimum(f1, f2)
    f_hi = fn(jnp.ones_like(ks))
    return jnp.where(f_hi < fk, 1.0, ks), jnp.minimum(f_hi, fk)


# --------------------------------------------------------------------------- eq. 26


def _delta_profile(sigma, lmax: int, theta):
    """$f_\\sigma(\\theta) = \\sum_{l\\le l^*} (2l+1)/(4\\pi) e^{-(\\sigma l)^2} P_l(\\cos\\theta)$."""
    dt = theta.dtype
    l = jnp.arange(lmax + 1, dtype=dt)
    a = (2 * l + 1) / (4 * jnp.pi) * jnp.exp(-((sigma * l) ** 2))
    p = jaxsh.legendre_p(jnp.cos(theta), lmax)  # (..., L+1)
    return p @ a


@blas_single_thread
def find_source(
    coeffs: Real[ArrayLike, "n_coeffs C"],
    *,
    region: tuple | None = None,
    height: int = 128,
    lmax_filter: int | None = None,
) -> SourceEstimate:
    """Locate the brightest compact source in SH lighting and estimate σ from it (R&H fig. 10, eq. 26).

    **Arguments:**

    - `coeffs`: `(n_coeffs, C)` recovered (filtered) lighting, e.g. from
      `inverse_lighting` or the first stage of `factorize`.
    - `region`: optional `(direction (3,), angular_radius)`: the user's box of
      fig. 10 as a spherical cap. Default: a cap around the brightest point
      whose radius is 2.5× the half-maximum radius of the peak.
    - `height`: lat-long resolution used for the search (width = 2·height).

    **Returns:** `SourceEstimate`; `sigma` accounts for the band limit of
    `coeffs` (module docstring), `sigma_eq26` is the paper's formula.
    """
    coeffs = jnp.asarray(coeffs)
    if coeffs.ndim == 1:
        coeffs = coeffs[:, None]
    lmax = int(round(np.sqrt(coeffs.shape[0]))) - 1
    if (lmax + 1) ** 2 != coeffs.shape[0] or lmax < 1:
        raise ValueError(f"`coeffs` must have shape (n_coeffs, C) with lmax >= 1, got {tuple(coeffs.shape)}")
    dt = coeffs.dtype
    h, w = int(height), 2 * int(height)
    img = jaxsh.synthesize_latlong(coeffs, h, w)  # (H, W, C)
    dirs = jaxsh.latlong_directions(h, w, dtype=dt)
    wts = jaxsh.latlong_weights(h, w, dtype=dt)
    lum = jnp.mean(img, -1)
    if region is not None:
        rdir = jnp.asarray(region[0], dt)
        rdir = rdir / jnp.linalg.norm(rdir)
        inside = (dirs @ rdir) >= jnp.cos(jnp.asarray(region[1], dt))
        if not bool(jnp.any(inside)):
            raise ValueError("`region` contains no lat-long sample; enlarge its radius")
        lum_sel = jnp.where(inside, lum, -jnp.inf)
    else:
        lum_sel = lum
    k = jnp.argmax(lum_sel)
    d0 = dirs.reshape(-1, 3)[k]
    # refine the centre: weighted centroid of the top of the peak
    ang = jnp.arccos(jnp.clip(dirs @ d0, -1.0, 1.0))
    peak_val = lum.reshape(-1)[k]
    # radial profile around d0 (ring means) -> half-maximum radius and background
    edges = jnp.linspace(0.0, 1.2, 121, dtype=dt)
    ring = jnp.clip(jnp.searchsorted(edges, ang.reshape(-1)) - 1, 0, 119)
    wflat = wts.reshape(-1)
    within = ang.reshape(-1) < 1.2
    prof_w = jax.ops.segment_sum(jnp.where(within, wflat, 0.0), ring, 120)
    prof = jax.ops.segment_sum(jnp.where(within, wflat * lum.reshape(-1), 0.0), ring, 120) / jnp.where(prof_w > 0, prof_w, 1.0)
    prof = jnp.where(prof_w > 0, prof, peak_val)
    far = jnp.median(prof[60:])
    half = far + 0.5 * (peak_val - far)
    below = prof < half
    r_half = edges[jnp.argmax(below) + 1]
    top = (ang < 0.5 * r_half) & (lum > half)
    cen = jnp.sum(jnp.where(top[..., None], (wts * (lum - half))[..., None] * dirs, 0.0), axis=(0, 1))
    cen = jnp.where(jnp.linalg.norm(cen) > 0, cen, d0)
    d = cen / jnp.linalg.norm(cen)
    radius = jnp.asarray(region[1], dt) if region is not None else jnp.clip(2.5 * r_half, 0.05, 1.0)
    ang = jnp.arccos(jnp.clip(dirs @ d, -1.0, 1.0))
    cap = ang <= radius
    ann = (ang > radius) & (ang <= 1.5 * radius)
    wc = jnp.where(cap, wts, 0.0)
    wa = jnp.where(ann, wts, 0.0)
    omega = jnp.sum(wc)
    bg = jnp.sum(wa[..., None] * img, (0, 1)) / jnp.sum(wa)
    tot = jnp.sum(wc[..., None] * img, (0, 1)) - bg * omega
    cen_val = jaxsh.real_sh(d, lmax) @ coeffs
    peak = cen_val - bg
    ratio = jnp.mean(peak) / jnp.mean(tot)
    sigma_plain = jnp.sqrt(1.0 / (4 * jnp.pi * ratio))
    # band-limited model ratio on the same cap/annulus, by 1-D quadrature in theta
    th = jnp.linspace(0.0, 1.5 * radius, 3001, dtype=dt)
    sin_w = jnp.sin(th) * (th[1] - th[0]) * 2 * jnp.pi
    cap_m = th <= radius
    ann_m = th > radius

    def model_ratio(log_s):
        f = _delta_profile(jnp.exp(log_s), lmax, th)
        bgm = jnp.sum(jnp.where(ann_m, f * sin_w, 0.0)) / jnp.sum(jnp.where(ann_m, sin_w, 0.0))
        totm = jnp.sum(jnp.where(cap_m, f * sin_w, 0.0)) - bgm * jnp.sum(jnp.where(cap_m, sin_w, 0.0))
        return (f[0] - bgm) / totm

    lo, hi = jnp.log(jnp.asarray(1e-3, dt)), jnp.log(jnp.asarray(2.0, dt))

    def bis(_, st):
        lo, hi = st
        mid = 0.5 * (lo + hi)
        big = model_ratio(mid) > ratio  # model too peaked: sigma larger
        return jnp.where(big, mid, lo), jnp.where(big, hi, mid)

    lo, hi = jax.lax.fori_loop(0, 60, bis, (lo, hi))
    sigma = jnp.exp(0.5 * (lo + hi))
    return SourceEstimate(d, tot, peak, bg, radius, sigma, sigma_plain)


# --------------------------------------------------------------------------- the solver


@blas_single_thread
def factorize(
    obs: Observations,
    lmax: int = 12,
    *,
    fresnel: bool = True,
    find_sigma: bool = True,
    region: tuple | None = None,
    refine: bool = True,
    search_pixels: int | None = 40000,
    key: jax.Array | None = None,
    max_steps: int = 200,
    rtol: float | None = None,
    atol: float | None = None,
    chunk: int = 4096,
) -> FactorizationResult:
    """Recover BRDF and lighting together (R&H sec. 6.3; module docstring).

    **Arguments:**

    - `obs`: `Observations` of a homogeneous object (visibility terms used
      when present).
    - `lmax`: the lighting cutoff $l^*$ (>= 3; R&H use 12).
    - `fresnel`: fit $\\mu$ (False: $F = 1$, metals).
    - `find_sigma`, `region`: estimate σ from the brightest compact source of
      the recovered lighting (or inside the user's `region = (direction,
      angular_radius)`), eq. 26.
    - `refine`: joint refinement of $(K_s, \\sigma)$ and the lighting, with the
      lighting modelled as slow SH + the found source (needs `find_sigma`).
    - `search_pixels`: the searches use a random subset of this many pixels
      (None: all); the final solve uses all pixels. `key`: PRNG key.
    - `max_steps`, `rtol`, `atol`: the refinement simplex.

    **Returns:** `FactorizationResult` ($K_d + K_s = 1$ per channel; the
    lighting carries the scale). Float32 observations are solved in float64
    (which must be enabled) and the result is returned in float32.
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations, got {type(obs).__name__}")
    lmax = int(lmax)
    if lmax < 3:
        raise ValueError(f"`lmax` must be >= 3 for factorization, got {lmax}")
    if refine and not find_sigma:
        raise ValueError("`refine=True` needs `find_sigma=True` (the refinement models the found source)")
    if obs.texel is not None:
        raise ValueError(
            "factorize assumes a homogeneous BRDF (R&H sec. 6.4: texture and lighting cannot be factored); "
            "build the observations without `texel`"
        )
    if obs.values.dtype != jnp.float64:
        # The nested searches work on normal equations whose condition numbers reach 1e6-1e8: float32
        # cannot resolve them (measured: non-finite results). Solve in float64, return float32.
        if not jax.config.jax_enable_x64:
            raise ValueError(
                "factorize needs float64 arithmetic (its normal equations are too ill-conditioned for float32); "
                "enable the jax_enable_x64 flag (in your script or notebook) or call it inside `with jax.enable_x64(True):`"
            )
        up = jax.tree_util.tree_map(lambda a: a.astype(jnp.float64) if a.dtype == obs.values.dtype else a, obs)
        res = factorize.__wrapped__(up, lmax, fresnel=fresnel, find_sigma=find_sigma, region=region, refine=refine,
                                    search_pixels=search_pixels, key=key, max_steps=max_steps, rtol=rtol, atol=atol,
                                    chunk=chunk)
        down = obs.values.dtype
        return jax.tree_util.tree_map(lambda a: a.astype(down) if a.dtype == jnp.float64 else a, res)
    dt = obs.values.dtype
    f64 = dt == jnp.float64
    rcond = 1e-12 if f64 else 1e-6
    rtol = (1e-7 if f64 else 1e-5) if rtol is None else float(rtol)
    atol = (1e-7 if f64 else 1e-5) if atol is None else float(atol)
    sub = obs
    if search_pixels is not None and obs.n_samples > int(search_pixels):
        key = jax.random.PRNGKey(0) if key is None else key
        idx = np.sort(np.asarray(jax.random.choice(key, obs.n_samples, (int(search_pixels),), replace=False)))
        sub = obs.subset(idx)
    # Stage 1: nested 1-D searches over mu (batched grid, then two zooms) and ks (golden, per channel).
    curv_rss = None
    if fresnel:
        t = np.linspace(np.log(0.05), np.log(2.5), 9)
        for rnd in range(3):
            vals = np.asarray(_mu_candidates(sub, jnp.asarray(t, dt), lmax, chunk, rcond))
            k = int(np.nanargmin(vals))
            best = t[k]
            if rnd < 2:
                step = t[1] - t[0]
                t = np.linspace(best - step, best + step, 7)
        # continuous minimum: the parabola through the best point of the last grid and its neighbours
        if 0 < k < len(t) - 1 and np.all(np.isfinite(vals[k - 1 : k + 2])):
            h = t[1] - t[0]
            y0, y1, y2 = vals[k - 1 : k + 2]
            c2 = (y0 - 2 * y1 + y2) / h**2
            if c2 > 0:
                best = t[k] + float(np.clip(-(y2 - y0) / (2 * h * c2), -h, h))
                # curvature of the profiled RSS in t = log(mu - 1), scaled from the subset to all pixels
                bb_sub = float(jnp.sum(sub.weights[:, None] * sub.values**2))
                curv_rss = c2 * bb_sub * obs.n_samples / sub.n_samples
        mu = jnp.asarray(1.0 + np.exp(best), dt)
        its1 = 9 + 7 + 7
    else:
        mu, its1 = None, 0
    ks, res1 = _stage1_final(obs, mu, lmax, chunk, rcond)
    filtered = res1.coeffs
    inf = jnp.full_like(ks, jnp.inf)
    std_inf = TorranceSparrow(inf, inf, None if mu is None else jnp.asarray(jnp.inf, dt), jnp.asarray(jnp.inf, dt))
    if not find_sigma:
        brdf = TorranceSparrow(1.0 - ks, ks, mu, jnp.asarray(jnp.nan, dt))
        return FactorizationResult(brdf, res1.lighting, filtered, None, std_inf, res1.status, jnp.asarray(its1),
                                   res1.rms, res1.rel_rms)
    src = find_source.__wrapped__(filtered, region=region)
    if not refine:
        brdf = TorranceSparrow(1.0 - ks, ks, mu, src.sigma)
        return FactorizationResult(brdf, res1.lighting, filtered, src, std_inf, res1.status, jnp.asarray(its1),
                                   res1.rms, res1.rel_rms)
    out = _refine(sub, obs, lmax, mu, ks, src.direction, src.sigma, int(max_steps), rtol, atol, chunk, rcond)
    ks, sigma, lighting, se_ks, se_sigma, ok, its2, rms, rel = out
    brdf = TorranceSparrow(1.0 - ks, ks, mu, sigma)
    se_mu = None
    if mu is not None:
        se_mu = jnp.asarray(jnp.inf, dt)
        if curv_rss is not None:
            # profile curvature: var(t) = s^2 / (RSS''/2), s^2 = RSS / (n - p); mu = 1 + e^t
            nobs = obs.n_samples * obs.n_channels
            s2 = float(rms) ** 2 * nobs / max(nobs - (jaxsh.num_coeffs(lmax) + 1) * obs.n_channels - 2 * obs.n_channels - 2, 1)
            se_mu = jnp.asarray(np.sqrt(s2 / (0.5 * curv_rss)) * (float(mu) - 1.0), dt)
    std = TorranceSparrow(se_ks, se_ks, se_mu, se_sigma)
    status = Status.where(ok, Status.converged, Status.max_steps_reached)
    finite = jnp.all(jnp.isfinite(ks)) & jnp.isfinite(sigma) & jnp.isfinite(rms)
    status = Status.where(finite, status, Status.nonfinite)
    return FactorizationResult(brdf, lighting, filtered, src, std, status, its1 + its2, rms, rel)


@eqx.filter_jit
def _mu_candidates(sub, t, lmax, chunk, rcond):
    """Profiled relative RSS (best ks per channel) for each candidate log(mu - 1)."""
    dt = sub.values.dtype
    ones = jnp.ones(((lmax + 1) ** 2,), dt)

    def one(ti):
        bl = _blocks(sub, 1.0 + jnp.exp(ti), lmax, chunk, rcond)
        _, rss = _golden_ks(lambda ks: _schur_rss(bl, 1.0 - ks, ks, ones)[0], sub.n_channels, dt, 40)
        return jnp.sum(rss) / jnp.sum(bl.g.bb)

    return jax.lax.map(one, t)


@eqx.filter_jit
def _stage1_final(obs, mu, lmax, chunk, rcond):
    dt = obs.values.dtype
    ones = jnp.ones(((lmax + 1) ** 2,), dt)
    bl = _blocks(obs, mu, lmax, chunk, rcond)
    ks, _ = _golden_ks(lambda k: _schur_rss(bl, 1.0 - k, k, ones)[0], obs.n_channels, dt, 50)
    return ks, _finish(bl.g, 1.0 - ks, ks, lmax, 0.0, rcond)


def _fast_column(n, v, mu, sigma, d):
    """Diffuse and specular rows of a unit-energy delta source at d (eqs. 23, 24): (N,), (N,)."""
    cos_o = jnp.sum(n * v, -1)
    vis = cos_o > 0
    cos_o = jnp.where(vis, cos_o, 1.0)
    f = jnp.ones_like(cos_o) if mu is None else jaxsh.fresnel_normalized(cos_o, mu)
    cos_i = n @ d
    lit = (cos_i > 0) & vis
    th = jaxsh.half_angle(d[None, :], v, n)
    t = jnp.exp(-((th / sigma) ** 2)) / (jnp.pi * sigma**2)
    return jnp.where(lit, cos_i, 0.0), jnp.where(lit, f * t / (4 * cos_o), 0.0)


class _Joint(eqx.Module):
    """Everything the refinement objective needs for one pixel set (mu fixed)."""

    bl: _Blocks
    drows: Array  # (N, 9)  weighted by sqrt(w)? no: raw rows
    srows: Array  # (N, n)
    w: Array
    b: Array
    normals: Array
    views: Array


def _joint(o: Observations, mu, lmax, chunk, rcond) -> _Joint:
    from ._lighting import _rows

    bl = _blocks(o, mu, lmax, chunk, rcond)
    d, s = _rows(o.normals, o.views, o.transfer, o.reflected_visibility, mu, None, lmax)
    return _Joint(bl, d, s, o.weights, o.values, o.normals, o.views)


def _joint_rss(jt: _Joint, ks, sigma, mu, d, lmax):
    """RSS per channel of [slow SH filtered by sigma + delta source at d] for kd = 1 - ks."""
    dt = jt.b.dtype
    filt = jaxsh.microfacet_spectrum(sigma, lmax)[jaxsh.sh_degrees(lmax)]
    kd = 1.0 - ks
    fd, fs = _fast_column(jt.normals, jt.views, mu, sigma, d)
    w = jt.w
    # cross terms with the (filtered) slow columns
    dfd, dfs = jt.drows.T @ (w * fd), jt.drows.T @ (w * fs)  # (9,)
    sfd, sfs = (jt.srows.T @ (w * fd)) * filt, (jt.srows.T @ (w * fs)) * filt  # (n,)
    a_d = (kd**2)[None, :] * dfd[:, None] + (kd * ks)[None, :] * (dfs[:, None] + sfd[:9, None]) + (ks**2)[None, :] * sfs[:9, None]
    a_s = (ks * kd)[None, :] * sfd[9:, None] + (ks**2)[None, :] * sfs[9:, None]
    a_ss = kd**2 * jnp.sum(w * fd * fd) + 2 * kd * ks * jnp.sum(w * fd * fs) + ks**2 * jnp.sum(w * fs * fs)
    r_s = kd * ((w * fd) @ jt.b) + ks * ((w * fs) @ jt.b)
    del dt
    return _schur_rss(jt.bl, kd, ks, filt, (a_d, a_s, a_ss, r_s))


def _refine(sub, obs, lmax, mu, ks0, d, sigma0, max_steps, rtol, atol, chunk, rcond):
    jt_sub = _joint_jit(sub, mu, lmax, chunk, rcond)
    p, ok, its = _refine_search(jt_sub, mu, ks0, d, sigma0, lmax, max_steps, rtol, atol)
    jt = jt_sub if sub is obs else _joint_jit(obs, mu, lmax, chunk, rcond)
    return _refine_final(jt, p, mu, d, lmax, ok, its)


@eqx.filter_jit
def _joint_jit(o, mu, lmax, chunk, rcond):
    return _joint(o, mu, lmax, chunk, rcond)


def _unpack(p, c):
    return jax.nn.sigmoid(p[:c]), jnp.exp(p[c])


@eqx.filter_jit
def _refine_search(jt, mu, ks0, d, sigma0, lmax, max_steps, rtol, atol):
    c = ks0.shape[0]

    dt = jt.b.dtype
    pdt = jnp.asarray(0.0).dtype  # optimistix's simplex state uses the default float dtype

    def objective(p, _):
        ks, sigma = _unpack(p.astype(dt), c)
        rss, _, _ = _joint_rss(jt, ks, sigma, mu, d, lmax)
        return (jnp.sum(rss) / jnp.sum(jt.bl.g.bb)).astype(pdt)

    ks_c = jnp.clip(ks0, 1e-4, 1 - 1e-4)
    p0 = jnp.concatenate([jnp.log(ks_c / (1 - ks_c)), jnp.log(sigma0)[None]]).astype(pdt)
    sol = optx.minimise(objective, optx.NelderMead(rtol=rtol, atol=atol), p0, max_steps=max_steps, throw=False)
    return sol.value.astype(dt), sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


@eqx.filter_jit
def _refine_final(jt, p, mu, d, lmax, ok, its):
    c = jt.b.shape[1]
    ks, sigma = _unpack(p, c)
    rss, x1, x2 = _joint_rss(jt, ks, sigma, mu, d, lmax)
    nobs = jt.bl.g.count * c
    rms = jnp.sqrt(jnp.sum(rss) / nobs)
    rel = rms / jnp.sqrt(jnp.sum(jt.bl.g.bb) / nobs)
    slow = jnp.concatenate([x1[:, :9], x2], 1).T  # (n, C), unfiltered slow lighting
    lighting = Lighting(slow, d[None, :], x1[:, 9][None, :])
    # standard errors of (ks, sigma): Hessian of the profiled RSS (Gauss-Newton: J'J = H/2)
    theta = jnp.concatenate([ks, sigma[None]])

    def rss_nat(th):
        return jnp.sum(_joint_rss(jt, th[:c], th[c], mu, d, lmax)[0])

    hess = jax.hessian(rss_nat)(theta)
    n_par = x1.size + x2.size + theta.size
    s2 = jnp.sum(rss) / jnp.maximum(nobs - n_par, 1.0)
    h2 = 0.5 * (hess + hess.T)
    # small dense inverse by the unrolled elimination (no LAPACK): columns of the identity
    eye = jnp.eye(theta.size, dtype=h2.dtype)
    hinv = jax.vmap(lambda e: _small_spd_solve(0.5 * h2, e))(eye)
    var = jnp.diag(hinv) * s2
    se = jnp.where((var > 0) & jnp.isfinite(var), jnp.sqrt(jnp.abs(var)), jnp.inf)
    return ks, sigma, lighting, se[:c], se[c], ok, its, rms, rel
