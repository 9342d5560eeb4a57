"""Inverse lighting with known BRDF (R&H 2001 sec. 6.2).

**Spherical-harmonic coefficients (eq. 25).** With the BRDF known, every
pixel is linear in the lighting coefficients $L_{lm}$, $l \\le l^*$:

$$B(x) = \\sum_{l \\le l^*}\\sum_m L_{lm}\\Big(K_d\\,\\Lambda_l\\hat\\rho_l\\,Y_{lm}(n)
   + K_s F(\\mu,\\theta_o)\\,Y_{lm}(R)\\Big),$$

the first term only for $l \\le 2$ (eq. 21; with shadows, the transfer
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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

import jaxsh

from ._threads import blas_single_thread
from ._data import Lighting, Observations, Status, TorranceSparrow


class LightingResult(eqx.Module):
    """Result of `inverse_lighting`.

    **Fields:**

    - `coeffs`: `(n_coeffs, C)` real SH lighting, world frame (+z up).
    - `std_errors`: `(n_coeffs, C)`; `inf` for undetermined coefficients.
    - `determined`: `(n_coeffs, C)` bool.
    - `singular_values`: `(C, n_coeffs)` of the weighted design matrix, descending.
    - `supported_lmax`: `(C,)` the largest $l$ for which every coefficient of
      degree $\\le l$ is determined by the data.
    - `band_snr`: `(lmax+1, C)` RMS over $m$ of $|L_{lm}|/\\mathrm{se}_{lm}$: where it
      drops below ~1, noise dominates (the $l^*$ of R&H sec. 6.2 in practice).
    - `status`, `rms`, `rel_rms`.
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

    @property
    def lmax(self) -> int:
        return int(round(np.sqrt(self.coeffs.shape[0]))) - 1

    @property
    def lighting(self) -> Lighting:
        return Lighting(self.coeffs)


# --------------------------------------------------------------------------- normal equations


class _Gram(eqx.Module):
    """Sums over pixels of the two row blocks d (diffuse, 9 columns) and s (specular, n columns)."""

    dd: Array  # (9, 9)
    ds: Array  # (9, n)
    ss: Array  # (n, n)
    db: Array  # (9, C)
    sb: Array  # (n, C)
    bb: Array  # (C,)
    count: Array  # ()


def _rows(n, v, transfer, rvis, mu, filt, lmax: int):
    """Diffuse rows (chunk, 9) and specular rows (chunk, n_coeffs) of eq. 25."""
    dt = n.dtype
    l2 = min(lmax, 2)
    if transfer is not None:
        d = transfer[:, : (l2 + 1) ** 2]
    else:
        a = jaxsh.lambertian_spectrum(l2, dt)[jaxsh.sh_degrees(l2)]
        d = jaxsh.real_sh(n, l2) * a[None, :]
    d = jnp.pad(d, ((0, 0), (0, 9 - d.shape[1])))
    cos_o = jnp.sum(n * v, -1)
    vis = cos_o > 0
    cos_o = jnp.where(vis, cos_o, 1.0)
    f = jnp.ones_like(cos_o) if mu is None else jaxsh.fresnel_normalized(cos_o, mu)
    r = jaxsh.reflect(v, n)
    y = jaxsh.real_sh(r, lmax)
    if filt is not None:
        y = y * filt[None, :]
    scale = f if rvis is None else f * rvis
    s = y * jnp.where(vis, scale, 0.0)[:, None]
    d = jnp.where(vis[:, None], d, 0.0)
    return d, s


def _gram(n, v, b, w, transfer, rvis, mu, filt, lmax: int, chunk: int) -> _Gram:
    """Accumulate the normal-equation blocks over pixel chunks (lax.scan; zero-weight padding)."""
    npx = n.shape[0]
    pad = (-npx) % chunk
    up = jnp.zeros((pad, 3), n.dtype).at[:, 2].set(1.0)
    n_p = jnp.concatenate([n, up]).reshape(-1, chunk, 3)
    v_p = jnp.concatenate([v, up]).reshape(-1, chunk, 3)
    b_p = jnp.pad(b, ((0, pad), (0, 0))).reshape(-1, chunk, b.shape[1])
    w_p = jnp.pad(w, (0, pad)).reshape(-1, chunk)
    t_p = None if transfer is None else jnp.pad(transfer, ((0, pad), (0, 0))).reshape(-1, chunk, transfer.shape[1])
    r_p = None if rvis is None else jnp.pad(rvis, (0, pad)).reshape(-1, chunk)
    nc = (lmax + 1) ** 2
    c = b.shape[1]
    dt = n.dtype
    init = _Gram(
        jnp.zeros((9, 9), dt), jnp.zeros((9, nc), dt), jnp.zeros((nc, nc), dt), jnp.zeros((9, c), dt),
        jnp.zeros((nc, c), dt), jnp.zeros((c,), dt), jnp.zeros((), dt),
    )

    def step(acc, xs):
        nn, vv, bb, ww, tt, rr = xs
        d, s = _rows(nn, vv, tt, rr, mu, filt, lmax)
        wd, ws = d * ww[:, None], s * ww[:, None]
        return _Gram(
            acc.dd + wd.T @ d, acc.ds + wd.T @ s, acc.ss + ws.T @ s, acc.db + wd.T @ bb, acc.sb + ws.T @ bb,
            acc.bb + jnp.sum(ww[:, None] * bb * bb, 0), acc.count + jnp.sum((ww > 0).astype(dt)),
        ), None

    out, _ = jax.lax.scan(step, init, (n_p, v_p, b_p, w_p, t_p, r_p))
    return out


def _channel_system(g: _Gram, kd, ks):
    """Per-channel normal matrix and right-hand side for A_c = kd_c d + ks_c s: (C, n, n), (C, n)."""
    nc = g.ss.shape[0]
    k = min(9, nc)
    dd = jnp.zeros((nc, nc), g.ss.dtype).at[:k, :k].set(g.dd[:k, :k])
    ds = jnp.zeros((nc, nc), g.ss.dtype).at[:k, :].set(g.ds[:k, :])
    db = jnp.zeros((nc, g.db.shape[1]), g.ss.dtype).at[:k].set(g.db[:k])
    ata = (kd**2)[:, None, None] * dd[None] + (kd * ks)[:, None, None] * (ds + ds.T)[None] + (ks**2)[:, None, None] * g.ss[None]
    atb = (kd[None, :] * db + ks[None, :] * g.sb).T  # (C, n)
    return ata, atb


def _solve_channels(ata, atb, bb, count, rcond, ridge):
    """Eigen-solve each channel; returns x (C, n), se (C, n), determined (C, n), sv (C, n), rss (C,), bad."""
    evals, evecs = jnp.linalg.eigh(ata)  # ascending
    top = evals[:, -1:]
    keep = evals > rcond * top
    inv = jnp.where(keep, 1.0 / (jnp.where(keep, evals, 1.0) + ridge), 0.0)
    proj = jnp.einsum("cji,cj->ci", evecs, atb)
    x = jnp.einsum("cij,cj->ci", evecs, inv * proj)
    # rss = b'b - 2 x'A'b + x'A'A x (exact for any x)
    rss = bb - 2 * jnp.sum(x * atb, -1) + jnp.einsum("ci,cij,cj->c", x, ata, x)
    rss = jnp.maximum(rss, 0.0)
    n_free = jnp.sum(keep, -1).astype(rss.dtype)
    s2 = rss / jnp.maximum(count - n_free, 1.0)
    var = jnp.einsum("cij,cj->ci", evecs**2, inv**2 * jnp.where(keep, evals, 0.0))
    null_weight = jnp.einsum("cij,cj->ci", evecs**2, (~keep).astype(evecs.dtype))
    determined = null_weight < 1e-6
    se = jnp.where(determined, jnp.sqrt(s2[:, None] * var), jnp.inf)
    sv = jnp.sqrt(jnp.clip(evals[:, ::-1], 0.0))
    return x, se, determined, sv, rss


def _check_brdf(brdf, name="brdf"):
    if not isinstance(brdf, TorranceSparrow):
        raise ValueError(f"`{name}` must be a solvers.TorranceSparrow, got {type(brdf).__name__}")
    if jnp.ndim(brdf.kd) != 1 or jnp.ndim(brdf.ks) != 1:
        raise ValueError(
            f"`{name}.kd` and `{name}.ks` must be homogeneous (C,) arrays for inverse lighting "
            f"(R&H sec. 6.4: texture and lighting cannot be factored), got shapes {jnp.shape(brdf.kd)}, {jnp.shape(brdf.ks)}"
        )


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

    **Returns:** `LightingResult` (module docstring).
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations, got {type(obs).__name__}")
    _check_brdf(brdf)
    lmax = int(lmax)
    if lmax < 0:
        raise ValueError(f"`lmax` must be a non-negative int, got {lmax}")
    c = obs.n_channels
    dt = obs.values.dtype
    kd = jnp.broadcast_to(jnp.asarray(brdf.kd, dt), (c,))
    ks = jnp.broadcast_to(jnp.asarray(brdf.ks, dt), (c,))
    if rcond is None:
        rcond = 1e-12 if dt == jnp.float64 else 1e-6
    return _inverse_lighting(obs, kd, ks, None if brdf.mu is None else jnp.asarray(brdf.mu, dt),
                             jnp.asarray(brdf.sigma, dt), lmax, deconvolve, float(ridge), float(rcond), int(chunk))


@eqx.filter_jit
def _inverse_lighting(obs, kd, ks, mu, sigma, lmax, deconvolve, ridge, rcond, chunk):
    filt = None
    if deconvolve:
        filt = jaxsh.microfacet_spectrum(sigma, lmax)[jaxsh.sh_degrees(lmax)]
    g = _gram(obs.normals, obs.views, obs.values, obs.weights, obs.transfer, obs.reflected_visibility, mu, filt,
              lmax, chunk)
    return _finish(g, kd, ks, lmax, ridge, rcond)


def _finish(g: _Gram, kd, ks, lmax, ridge, rcond) -> LightingResult:
    ata, atb = _channel_system(g, kd, ks)
    x, se, det, sv, rss = _solve_channels(ata, atb, g.bb, g.count, rcond, ridge)
    degrees = jnp.asarray(jaxsh.sh_degrees(lmax))
    # supported l*: largest l with all coefficients of degree <= l determined.
    band_ok = jnp.stack([jnp.all(det[:, l * l : (l + 1) ** 2], -1) for l in range(lmax + 1)], -1)  # (C, L+1)
    prefix = jnp.cumprod(band_ok.astype(jnp.int32), -1)
    supported = jnp.sum(prefix, -1) - 1
    snr2 = jnp.where(det, (x / jnp.where(det, se, 1.0)) ** 2, 0.0)
    band_snr = jnp.stack([jnp.sqrt(jnp.mean(snr2[:, l * l : (l + 1) ** 2], -1)) for l in range(lmax + 1)], 0)
    del degrees
    nobs = g.count * kd.shape[0]
    rms = jnp.sqrt(jnp.sum(rss) / nobs)
    rel = rms / jnp.sqrt(jnp.sum(g.bb) / nobs)
    finite = jnp.all(jnp.isfinite(x)) & jnp.isfinite(rms)
    status = Status.where(jnp.all(det), Status.converged, Status.ill_conditioned)
    status = Status.where(finite, status, Status.nonfinite)
    return LightingResult(x.T, se.T, det.T, sv, supported, band_snr, status, rms, rel)


# --------------------------------------------------------------------------- the dual method (fig. 8)


class DualLightingResult(eqx.Module):
    """Result of `inverse_lighting_dual`.

    - `image`: `(H, W, C)` lat-long lighting in angular space (the filtered
      lighting seen in the mirror directions; texels no mirror direction
      reaches hold the $l \\le 2$ field of `coeffs9`).
    - `coeffs9`: `(9, C)` the frequency-space coefficients $L_{lm}$, $l \\le 2$,
      solving the consistency condition $L^1 = L^2$.
    - `covered`: `(H, W)` bool, texels reached by a mirror direction.
    - `consistency`: `(C,)` $|L^1 - L^2| / |L^1|$ of the returned image
      (0 up to round-off without `nonneg`; small with it).
    - `status`, `rms`, `rel_rms`, `iterations` (of the non-negative refinement).
    """

    image: Float[Array, "H W C"]
    coeffs9: Float[Array, "9 C"]
    covered: Bool[Array, "H W"]
    consistency: Float[Array, " C"]
    status: Status
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    iterations: Int[Array, ""]


@blas_single_thread
def inverse_lighting_dual(
    obs: Observations,
    brdf: TorranceSparrow,
    height: int = 64,
    *,
    nonneg: bool = True,
    maxiter: int = 300,
) -> DualLightingResult:
    """The dual angular / frequency-space inverse lighting of R&H sec. 6.2 (fig. 8).

    Phase 1 turns 9 coefficients $L^1$ into a high-resolution lighting image:
    each lat-long texel $t$ takes the least-squares value of
    $(B - K_d E(L^1))/(K_s F)$ over the pixels whose mirror direction falls in
    it (eq. 22 with $B_{s,fast} = 0$). Phase 2 projects that image to 9
    coefficients $L^2$. Both are affine in $L^1$, so the consistency
    condition $L^1 = L^2$ is 9 linear equations per channel, solved
    directly. With `nonneg=True` the image is then refined by jaxopt's
    L-BFGS-B under $L \\ge 0$, minimizing the image residual of the same
    model with the diffuse term driven by the image's own $l \\le 2$
    projection (consistency by construction).

    Convex objects only (the paper: with shadows $B_d$ no longer depends on
    9 coefficients); `obs.transfer` must be None. `brdf`: homogeneous, with
    $K_s > 0$. Returns `DualLightingResult`.
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations, got {type(obs).__name__}")
    _check_brdf(brdf)
    if obs.transfer is not None:
        raise ValueError("inverse_lighting_dual: concave objects (obs.transfer given) are not supported (R&H sec. 6.4)")
    h = int(height)
    if h < 4:
        raise ValueError(f"`height` must be >= 4, got {h}")
    c = obs.n_channels
    dt = obs.values.dtype
    kd = jnp.broadcast_to(jnp.asarray(brdf.kd, dt), (c,))
    ks = jnp.broadcast_to(jnp.asarray(brdf.ks, dt), (c,))
    if not bool(jnp.all(ks > 0)):
        raise ValueError("inverse_lighting_dual needs `brdf.ks` > 0 in every channel (the mirror term carries the image)")
    mu = None if brdf.mu is None else jnp.asarray(brdf.mu, dt)
    x, l9, cov, iters = _dual(obs, kd, ks, mu, h, nonneg, int(maxiter))
    res = _dual_finish(obs, kd, ks, mu, x, l9, cov, iters, h)
    if nonneg and int(iters) >= int(maxiter) and _status_ok(res.status):
        res = eqx.tree_at(lambda r: r.status, res, Status.max_steps_reached)
    return res


def _status_ok(status) -> bool:
    return bool(status == Status.converged)


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


@eqx.filter_jit
def _dual(obs, kd, ks, mu, h, nonneg, maxiter):
    t_count = h * 2 * h
    f, tex, d, wv, y9, omega, b = _dual_pieces(obs, kd, ks, mu, h)
    c = b.shape[1]
    g = ks[None, :] * f[:, None]  # (N, C) the mirror-term gain K_s F

    def seg(x):
        return jax.ops.segment_sum(x, tex, num_segments=t_count)

    den = seg(wv[:, None] * g * g)  # (T, C)
    covered = den[:, 0] > 0
    den_s = jnp.where(den > 0, den, 1.0)
    a = jnp.where(den > 0, seg(wv[:, None] * g * b) / den_s, 0.0)  # (T, C)
    # L_map = a - M L1 on covered texels, M[t, c, :] = sum w g kd d / den; uncovered: L_map = y9 L1
    m = seg((wv[:, None] * g * kd[None, :])[:, :, None] * d[:, None, :]) / den_s[:, :, None]  # (T, C, 9)
    m = jnp.where(covered[:, None, None], m, -y9[:, None, :])
    p = (omega[:, None] * y9).T  # (9, T) projection to l <= 2
    pa = p @ a  # (9, C)
    pm = jnp.einsum("it,tcj->cij", p, m)  # (C, 9, 9)
    eye = jnp.eye(9, dtype=b.dtype)
    l1 = jnp.linalg.solve(eye[None] + pm, pa.T[:, :, None])[:, :, 0].T  # (9, C)
    img = a - jnp.einsum("tcj,jc->tc", m, l1)  # (T, C)
    iters = jnp.asarray(0)
    if nonneg:
        from ._jaxopt import minimize_nonnegative

        sw = jnp.sqrt(wv)

        def loss(x):
            l9 = p @ x  # (9, C): the image's own l <= 2 part drives the diffuse term
            pred = kd[None, :] * (d @ l9) + g * x[tex]
            r = sw[:, None] * (pred - b)
            # texels no pixel sees are tied (weakly) to the consistent phase-1 field
            tie = jnp.where(covered[:, None], 0.0, x - img)
            return jnp.sum(r * r) / jnp.sum(wv) + 1e-6 * jnp.sum(tie * tie) / t_count

        x, iters, _ = minimize_nonnegative(loss, jnp.maximum(img, 0.0), maxiter=maxiter)
        img = x
        l1 = p @ img
    return img, l1, covered, iters


def _dual_finish(obs, kd, ks, mu, img, l1, covered, iters, h):
    f, tex, d, wv, y9, omega, b = _dual_pieces(obs, kd, ks, mu, h)
    g = ks[None, :] * f[:, None]
    pred = kd[None, :] * (d @ l1) + g * img[tex]
    rss = jnp.sum(wv[:, None] * (pred - b) ** 2)
    nobs = jnp.sum((wv > 0).astype(b.dtype)) * b.shape[1]
    rms = jnp.sqrt(rss / nobs)
    rel = rms / jnp.sqrt(jnp.sum(wv[:, None] * b * b) / nobs)
    p = (omega[:, None] * y9).T
    l2 = p @ img
    consistency = jnp.linalg.norm(l2 - l1, axis=0) / jnp.linalg.norm(l1, axis=0)
    finite = jnp.all(jnp.isfinite(img)) & jnp.isfinite(rms)
    status = Status.where(finite, Status.converged, Status.nonfinite)
    return DualLightingResult(img.reshape(h, 2 * h, -1), l1, covered.reshape(h, 2 * h), consistency, status, rms, rel,
                              jnp.asarray(iters))
