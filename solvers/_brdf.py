"""Inverse BRDF with known lighting (R&H 2001 sec. 6.1): the parametric model of eq. 24.

The practical model (eq. 24) is linear in $K_d$ and $K_s$ once $\\mu$ and
$\\sigma$ are fixed:

$$B(x) = K_d\\,E(x) + K_s\\,S_{\\mu,\\sigma}(x),\\qquad
  S_{\\mu,\\sigma} = F(\\mu,\\theta_o)\\Big[L_{slow}(R) + \\tfrac{1}{4\\cos\\theta_o}\\sum_j T_j(\\sigma)\\Big].$$

`fit_brdf` follows the paper's nested procedure: an outer simplex
(`optimistix.NelderMead`) over $(\\mu, \\sigma)$ in the unconstrained
coordinates $(\\log(\\mu - 1), \\log\\sigma)$, and an inner weighted linear
least-squares solve for $K_d, K_s$ per channel — per texel for textured
objects (sec. 6.4) — so the simplex minimizes the *profiled* residual
(variable projection). It is started from the best point of a small grid
(both on at most `search_pixels` samples). When they ran on a subset, the
estimate is refined on all samples by
Levenberg-Marquardt (`optimistix`'s, with a trust region that also accepts a step whose loss changed only by
rounding: `solvers._lm`) on the same profiled residual, with its
exact autodiff Jacobian through the inner solves (homogeneous BRDFs; Golub &
Pereyra 1973: its minimizer is the joint one over all parameters, measured
equal to 1e-13 on 3×256², and the Jacobian has 2 columns instead of
$2C + 2$). When the grid and the simplex already saw every sample, they
minimized that very objective, to the simplex's stopping tolerance on the
parameters (`rtol`, `atol`: about 1e-8 relative), and the refinement is left
out by default (`refine=None`), with its compilation: about 1.2 s of a first
call. Standard errors come from the
Jacobian of the residual at the solution: $\\mathrm{cov} = s^2 (J^TJ)^{-1}$,
$s^2 = \\mathrm{RSS}/(n - p)$; for textured fits the Jacobian is that of the
profiled residual (Golub & Pereyra), so $\\mu$, $\\sigma$ errors account for the
texture being re-fitted. All per-pixel work is vmapped arithmetic on the
precomputed `jaxsh.PracticalTerms`.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

import jaxsh

from ._data import Lighting, Observations, TorranceSparrow, practical_terms_for, view_lightings
from ._jacobian import explicit_jacobian
from ._lm import LevenbergMarquardt
from ._normal_equations import (covariance_from_gram, covariance_from_jacobian, inverse_sym2_diag, nonneg_sym2,
                                solve_grouped_shared_nonneg, solve_sym2_min_norm)
from ._pixel_sums import pixel_sharding
from ._results import Solution, Status, check_bool, check_float, check_int, finish, rms_pair, signal_status, status_from_optimistix, worst
from ._threads import blas_single_thread


class BRDFResult(Solution):
    """Result of `fit_brdf` (a `solvers.Solution`; `estimate` is `brdf`).

    **Fields:**

    - `brdf`: the estimate (`TorranceSparrow`).
    - `std_errors`: a `TorranceSparrow` of one-sigma standard errors (`inf`
      where the data do not determine a parameter). They are statistical:
      they measure how well the pixels determine a parameter under the
      practical model (noise, conditioning), not the model's own error
      against real reflection, which can be larger (measured: with an area source only,
      sigma was off by ~9 standard errors; docs/results.md).
    - `covariance`: `(p, p)` covariance of `(kd..., ks..., mu, sigma)`
      (homogeneous fits; the `(mu, sigma)` block for textured fits).
    - `status`: `Status`: the worst of non-finite values, a singular inner
      $(K_d, K_s)$ system (`ill_conditioned`), all-zero data or all-zero
      lighting in some channel (`no_signal`),
      and the simplex's and LM's own outcomes (`status_from_optimistix`).
    - `iterations`: simplex + LM steps.
    - `rms`: weighted RMS residual; `rel_rms`: `rms` / RMS of the data (never NaN).
    - `texel_count`: `(T,)` samples of positive weight per texel (textured fits), else `None`.
    - `fitted`: `(N, C)` the model at the estimate for every sample of `obs`,
      $K_d E + K_s S_{\\mu,\\sigma}$ (eq. 24; per-texel $K_d$, $K_s$ for
      textured fits), the values the residual compares with `obs.values`:
      `obs.to_images(result.fitted)` are re-renders of the views.
    - `stats`: `num_steps_simplex`, `num_steps_lm` (0 without refinement),
      `grid_points` (starting grid size), `search_pixels` (the samples the grid
      and the simplex used), `n_obs` (weighted samples × channels),
      `at_bound`: `{"mu": bool, "sigma": bool}` the parameter stopped at its
      bound of the search box (`MU_BOUNDS`, `SIGMA_BOUNDS`; the data do not
      determine it: its standard error is `inf`), `undetermined`: the same
      dict, also True where the one-sigma error exceeds $\\mu - 1$ (resp. $\\sigma$),
      and both True, their errors `inf` and the search's `max_steps_reached`
      reported as `converged`, when no channel carries a specular signal (no
      $K_s$ above 3 standard errors: a matte object; `_no_specular_signal`);
      with `textured="kd_ks"` also `"ks"`: `(T, C)` True where a texel's $K_s$
      is not determined (no sample, or its one-sigma error not below the
      texture's reflectance level: `_undetermined_texel_ks`). Their values are
      returned as the least-squares solution gives them, which far from every
      highlight is noise over a vanishing specular term (up to $10^{55}$
      measured); `jaxsh fit` writes them as 0 in `ks.exr`.
    """

    brdf: TorranceSparrow
    std_errors: TorranceSparrow
    covariance: Float[Array, "p p"]
    status: Status
    iterations: Int[Array, ""]
    rms: Float[Array, ""]
    rel_rms: Float[Array, ""]
    texel_count: Int[Array, " T"] | None
    fitted: Float[Array, "N C"]
    stats: dict

    @property
    def estimate(self) -> TorranceSparrow:
        return self.brdf


# --------------------------------------------------------------------------- inner linear problems


def _inner(D, S, b, w, texel, n_texels: int, textured: str | None):
    """Weighted LSQ for kd, ks >= 0 given the unit diffuse D and specular S images (N, C).

    Returns kd, ks ((C,) or (T, C)) and a flag for a singular system. Every form is the nonnegative least-squares
    solution (`nonneg_sym2`; `solve_grouped_shared_nonneg` for one shared ks): a `TorranceSparrow` has
    kd, ks >= 0, and data that an unconstrained solve fits with a negative albedo (negative or offset radiance)
    get the best physical fit and its residual instead. A singular per-texel system (one sample, a texel in
    shadow, a specular image that is 0 there) gets the minimum-norm solution, as the homogeneous one: the kd a
    texel's diffuse samples determine is kept (before, both were set to 0, and the residual of those texels
    pulled sigma towards values where no specular term underflows).
    """
    # grey terms `(N, 1)` light every channel of `b`: the same image per channel (a broadcast the sums fuse; the
    # per-texel solve's loop needs the channels' shapes to agree)
    D, S = (jnp.broadcast_to(x, b.shape) for x in (D, S))
    wd, ws = w[:, None] * D, w[:, None] * S
    if textured is None:
        a = jnp.sum(wd * D, 0), jnp.sum(wd * S, 0), jnp.sum(ws * S, 0), jnp.sum(wd * b, 0), jnp.sum(ws * b, 0)
        kd, ks, bad = solve_sym2_min_norm(*a)
        kd, ks = nonneg_sym2(kd, ks, a[0], a[2], a[3], a[4])
        return kd, ks, jnp.any(bad)

    def seg(x):
        return jax.ops.segment_sum(x, texel, num_segments=n_texels)

    dd, ds, ss, db, sb = seg(wd * D), seg(wd * S), seg(ws * S), seg(wd * b), seg(ws * b)
    observed = seg(w) > 0
    if textured == "kd_ks":
        kd, ks, bad = solve_sym2_min_norm(dd, ds, ss, db, sb)
        kd, ks = nonneg_sym2(kd, ks, dd, ss, db, sb)
        return kd, ks, jnp.any(bad & observed[:, None])
    # textured == "kd": one ks per channel, kd per texel, both >= 0 (the Schur complement on the active set).
    kd, ks, bad = solve_grouped_shared_nonneg(dd, ds, ss, db, sb)
    return kd, jnp.broadcast_to(ks, kd.shape), jnp.any(bad)


def _undetermined_texel_ks(kd, se_ks, seen):
    """`(T, C)` True where a texel's $K_s$ is not determined by its samples (`fit_brdf(textured="kd_ks")`): the
    texel has no sample, or the one-sigma error of its $K_s$ is not below the texture's reflectance level, the
    larger of the texel's own $K_d$ and the median over observed texels (each the largest over the channels).
    Far from every highlight the specular image is tiny, and the least-squares $K_s$ is noise divided by it
    (measured: $10^{12}$ at σ = 0.2, $10^{55}$ at σ = 0.1, status `converged`); such a value says nothing about the
    surface. The rule scales with the images (a brighter capture scales $K_d$, $K_s$ and their errors alike), and
    keeps a dark texel's well-observed $K_s$ (the median level, not the texel's own $K_d$, bounds it from below).
    A texture with $K_d = 0$ everywhere has no level, and every $K_s$ is then reported undetermined."""
    level = jnp.max(kd, -1)
    ref = jnp.nanmedian(jnp.where(seen, level, jnp.nan))
    scale = jnp.maximum(level, jnp.where(jnp.isfinite(ref), ref, 0.0))[:, None]
    return ~seen[:, None] | ~(se_ks < scale)


def _no_specular_signal(ks, se_ks, s_unit, b, w, texel, und_ks=None):
    """True when no channel carries a specular signal, so that $\\mu$ and $\\sigma$ are not determined.

    A channel carries one when its $K_s$ (some texel's, for textured fits; with `"kd_ks"` only texels whose
    $K_s$ is determined, `und_ks`) exceeds three times its standard error (two let one channel of 16-bit
    quantization noise through at 2.2 standard errors) and the specular term $K_s S$ holds more
    than $\\epsilon$ of the channel's data energy (noise-free Lambertian images leave $K_s$ at rounding,
    3e-9, with a rounding-sized error). On Lambertian data the Jacobian's columns for $\\mu, \\sigma$ are
    $K_s\\,\\partial S$, at rounding level; scaled to unit norm (`covariance_from_jacobian`) they looked
    determined: σ from 0.018 to 0.67 across noise draws of one capture, each with a finite error and
    `undetermined` False."""
    dt = b.dtype
    if ks.ndim == 1:
        ks_pix, sig = ks[None, :], ks > 3.0 * se_ks
    else:
        ks_pix = ks[texel]
        ok = ks > 3.0 * se_ks
        sig = jnp.any(ok if und_ks is None else ok & ~und_ks, axis=0)
    spec = jnp.sum(w[:, None] * (ks_pix * s_unit) ** 2, 0)
    data = jnp.sum(w[:, None] * b * b, 0)
    return ~jnp.any(sig & (spec > jnp.finfo(dt).eps * data))


def _gram_homogeneous(terms, D, S, ks, w, mu, sigma, fresnel: bool):
    """$J^TJ$ `(2C + 2, 2C + 2)` of the weighted residual $\\sqrt{w}\\,(K_d D + K_s S_{\\mu,\\sigma} - b)$ in
    $(K_d, K_s, \\mu, \\sigma)$ (homogeneous fits; the μ row and column are 0 without Fresnel), summed from
    the `(N, C)` images without forming the `(N C, 2C + 2)` Jacobian.

    Its columns are $\\sqrt{w}\\,D_c$ and $\\sqrt{w}\\,S_c$ on channel $c$'s rows, and
    $\\sqrt{w}\\,K_{s,c}\\,\\partial S_c$ for μ and σ, whose two derivatives come from one forward-mode pass
    over `terms.specular_unit` (its band table contracted once per derivative). Forming the Jacobian by
    `jax.jacfwd` of the residual (eight tangents, a 24 MB `(N C, 8)` array at 3 × 256²) and multiplying it took
    40–47 ms with the covariance; these sums take 13–15 ms (docs/performance.md, twenty-sixth round).
    """
    dt = D.dtype
    c = ks.shape[-1]
    # grey terms `(N, 1)` (a one-channel lighting lights every channel) against C-channel data: each channel's
    # columns are the same image (a broadcast, fused into the sums below; before, `kk` came out 2 x 2 against
    # `kp`'s 2C x 2 and every grey-lit fit raised a TypeError)
    D, S = (jnp.broadcast_to(x, (x.shape[0], c)) for x in (D, S))
    m0 = mu if fresnel else jnp.ones((), dt)

    def spec(m, s_):
        return terms.specular_unit(m if fresnel else None, s_, check=False)

    eye = jnp.eye(2, dtype=dt)
    dS = jax.vmap(lambda t: jax.jvp(spec, (m0, sigma), (t[0], t[1]))[1])(eye)  # (2, N, C): d/dmu, d/dsigma
    ws = w[:, None]
    a_mu, a_sig = ks[None, :] * dS[0], ks[None, :] * dS[1]
    dd, ds, ss = jnp.sum(ws * D * D, 0), jnp.sum(ws * D * S, 0), jnp.sum(ws * S * S, 0)
    cross = jnp.stack([jnp.sum(ws * D * a_mu, 0), jnp.sum(ws * S * a_mu, 0),
                       jnp.sum(ws * D * a_sig, 0), jnp.sum(ws * S * a_sig, 0)])  # (4, C)
    mm, ms_, qq = jnp.sum(ws * a_mu * a_mu), jnp.sum(ws * a_mu * a_sig), jnp.sum(ws * a_sig * a_sig)
    diag = jnp.diag
    kk = jnp.block([[diag(dd), diag(ds)], [diag(ds), diag(ss)]])  # (2C, 2C)
    kp = jnp.stack([jnp.concatenate([cross[0], cross[1]]), jnp.concatenate([cross[2], cross[3]])], 1)  # (2C, 2)
    pp = jnp.stack([jnp.stack([mm, ms_]), jnp.stack([ms_, qq])])
    g = jnp.block([[kk, kp], [kp.T, pp]])
    if not fresnel:
        g = g.at[2 * c, :].set(0.0).at[:, 2 * c].set(0.0)
    return g


def _model(terms, kd, ks, mu, sigma, texel):
    return _combine(terms.diffuse_unit(), terms.specular_unit(mu, sigma, check=False), kd, ks, texel)


def _combine(D, S, kd, ks, texel):
    """$K_d D + K_s S$ with homogeneous `(C,)` or per-texel `(T, C)` parameters: `(N, C)`."""
    if kd.ndim == 2:
        kd, ks = kd[texel], ks[texel]
    else:
        kd, ks = kd[None, :], ks[None, :]
    return kd * D + ks * S


# --------------------------------------------------------------------------- parameterization


def _to_natural(u, fresnel: bool):
    if fresnel:
        return 1.0 + jnp.exp(u[0]), jnp.exp(u[1])
    return None, jnp.exp(u[0])


# Box of the simplex / LM in the coordinates u = (log(mu - 1), log sigma): mu in [1.001, 10], sigma in
# [1e-3, 1.5] rad. A parameter the data do not determine (directional lights and near-normal views leave
# F(mu) flat) would otherwise run off towards mu -> 1 or mu -> inf until max_steps; it stops at the box
# instead, flagged in `stats["at_bound"]` with an infinite standard error.
MU_BOUNDS = (1.0 + 1e-3, 10.0)
SIGMA_BOUNDS = (1e-3, 1.5)
_AT_BOUND_TOL = 1e-3  # in log units


def _u_bounds(fresnel: bool, dt):
    lo = [np.log(MU_BOUNDS[0] - 1.0), np.log(SIGMA_BOUNDS[0])]
    hi = [np.log(MU_BOUNDS[1] - 1.0), np.log(SIGMA_BOUNDS[1])]
    if not fresnel:
        lo, hi = lo[1:], hi[1:]
    return jnp.asarray(lo, dt), jnp.asarray(hi, dt)


def _to_u(mu, sigma, fresnel: bool, dt):
    s = jnp.log(jnp.asarray(sigma, dt))
    if fresnel:
        return jnp.stack([jnp.log(jnp.asarray(mu, dt) - 1.0), s])
    return s[None]


# --------------------------------------------------------------------------- the solver


@blas_single_thread
def fit_brdf(
    obs: Observations,
    lighting: Lighting | Sequence[Lighting],
    *,
    fresnel: bool = True,
    textured: str | None = None,
    init: tuple[float, float] | None = None,
    refine: bool | None = None,
    search_pixels: int | None = 40000,
    max_steps: int = 400,
    rtol: float | None = None,
    atol: float | None = None,
    throw: bool = False,
) -> BRDFResult:
    """Recover $K_d, K_s, \\mu, \\sigma$ under known lighting (R&H sec. 6.1, eq. 24; module docstring).

    **Arguments:**

    - `obs`: `Observations` (any number of views; visibility terms are used
      when present, R&H sec. 6.4).
    - `lighting`: the known `Lighting` (slow SH to $l \\gtrsim 3/\\sigma$ plus
      fast sources), or a sequence of one `Lighting` per view of `obs`
      (`obs.view_index`; e.g. one directional light per image, photometric
      stereo). Memory stays $O(N)$ (`practical_terms_for`).
    - `fresnel`: fit $\\mu$ (True) or use $F = 1$ (False; `brdf.mu` is None).
    - `textured`: `None` (homogeneous), `"kd"` ($K_d$ per texel, one $K_s$)
      or `"kd_ks"` (both per texel); needs `obs.texel`.
    - `init`: starting `(mu, sigma)` inside `MU_BOUNDS` x `SIGMA_BOUNDS` (`mu` unused, may be None, with
      `fresnel=False`); default: the best of a small grid.
    - `refine`: Levenberg–Marquardt refinement on all samples (homogeneous;
      on the profiled residual, whose minimizer is the joint one). `None`
      (default): only when the grid and the simplex ran on a subset
      (`search_pixels` below); with every sample they minimized the same
      objective, to the simplex's stopping tolerance, and the refinement (about
      1.2 s of compilation at the first call) is left out (measured on a
      3×96² capture, 15,072 samples: $\\mu$ and $\\sigma$ within 2e-9 of the
      refined estimate, both within 2e-9 of the truth). `True`: always; `False`:
      never.
    - `search_pixels`: unless `refine=False`, on a homogeneous fit, the start grid and
      the simplex (which only have to find the basin) use at most this many
      samples, evenly spaced over the samples of positive weight; the
      Levenberg–Marquardt refinement, the estimate, its standard errors and
      the status use all of them (None: every stage uses all samples).
      Measured on 3×256² (127,584 samples, `benchmarks/bench_inverse.py`):
      the estimate equal to 2e-11 to that of an all-sample search, the warm
      fit 2.8 s → 1.5 s.
    - `max_steps`, `rtol`, `atol`: simplex / LM limits (tolerances default to
      1e-8 in float64 and 1e-5 in float32). The simplex minimizes the weighted
      RSS over the data's mean weighted square, and LM its residual over the
      root of that: `atol` is relative to the data, so the fit and its status
      do not depend on the radiometric units (within float32's range,
      docs/conventions.md).
    - `throw`: raise `solvers.SolveError` unless the status is `converged`
      (default False: check `result.status`).

    **Returns:** `BRDFResult`. $K_d, K_s \\ge 0$: at each $(\\mu, \\sigma)$ they are
    the nonnegative least-squares solution (homogeneous, per texel, and with one
    $K_s$ shared by the texels), so data that a negative albedo would fit better
    (negative or offset radiance) get the best physical fit and its residual.
    Non-convergence and singular inner systems are reported in `status`. $\\mu$ and $\\sigma$ are searched in the box
    `MU_BOUNDS` = [1.001, 10], `SIGMA_BOUNDS` = [1e-3, 1.5] rad: when the data
    do not determine one (e.g. only directional lights and near-normal views:
    $F(\\mu, \\theta_o) \\approx 1$ for every $\\mu$), the fit converges with it at
    the bound, `stats["at_bound"][name]` True and an infinite standard error,
    instead of running to `max_steps_reached`.
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations (see solvers.observations), got {type(obs).__name__}")
    lights = view_lightings(obs, lighting)  # one Lighting, or one per view: checked here, ValueError naming `lighting`
    for lit in [lighting] if lights is None else lights:
        if lit.n_channels not in (1, obs.n_channels):
            raise ValueError(f"`lighting` has {lit.n_channels} channels, the images in `obs` {obs.n_channels} (give the same C, or 1)")
    max_steps = check_int(max_steps, "max_steps")
    fresnel = check_bool(fresnel, "fresnel")
    search_pixels = None if search_pixels is None else check_int(search_pixels, "search_pixels")
    rtol = None if rtol is None else check_float(rtol, "rtol")
    atol = None if atol is None else check_float(atol, "atol")
    if textured not in (None, "kd", "kd_ks"):
        raise ValueError(f"`textured` must be None, 'kd' or 'kd_ks', got {textured!r}")
    refine = check_bool(refine, "refine", none=True)
    if textured is not None and (obs.texel is None or obs.n_texels < 1):
        raise ValueError("`textured` fits need `obs.texel` (pass `texel=` to solvers.observations)")
    dt = obs.values.dtype
    f64 = dt == jnp.float64
    rtol = (1e-8 if f64 else 1e-5) if rtol is None else float(rtol)
    atol = (1e-8 if f64 else 1e-5) if atol is None else float(atol)
    terms = practical_terms_for(obs, lighting)
    if init is None:
        sig_grid = np.exp(np.linspace(np.log(0.02), np.log(0.6), 12))
        mu_grid = np.array([1.2, 1.5, 2.2]) if fresnel else np.array([1.5])
        mg, sg = np.meshgrid(mu_grid, sig_grid, indexing="ij")
        u_grid = jnp.asarray(
            np.stack([np.log(mg.ravel() - 1), np.log(sg.ravel())], 1) if fresnel else np.log(sg.ravel())[:, None], dt
        )
    else:
        mu0, sigma0 = check_init(init, fresnel)
        u_grid = _to_u(mu0, sigma0, fresnel, dt)[None, :]
    search = None
    if search_pixels is not None and refine is not False and textured is None:
        search = _search_samples(obs.weights, search_pixels)
    # None: the refinement only when the search ran on a subset (with all samples it would minimize what the
    # simplex just minimized)
    refine = (search is not None) if refine is None else refine
    # samples sharded over several devices: the refinement's QR runs on each device's rows (`solvers._lm`)
    where = pixel_sharding(obs.weights)
    blocks = 1 if where is None else int(where[0].shape[where[1]])
    res = _fit_brdf(terms, obs.values, obs.weights, obs.texel, u_grid, obs.n_texels, fresnel, textured, refine,
                    int(max_steps), rtol, atol, search, blocks)
    return finish(res, throw)


def check_init(init, fresnel: bool) -> tuple[float, float]:
    """`fit_brdf`'s `init`: a pair `(mu, sigma)` of numbers inside the search box (`MU_BOUNDS`, `SIGMA_BOUNDS`;
    `mu` is not read without Fresnel and may be None); a `ValueError` naming `init` otherwise (before, a value
    outside the box started the search at NaN and the fit stopped at iteration 0 with status `nonfinite`)."""
    try:
        mu, sigma = init
    except (TypeError, ValueError):
        raise ValueError(f"`init` must be a pair (mu, sigma), got {init!r}") from None
    try:
        sigma = float(sigma)
        mu = float(mu) if fresnel else (None if mu is None else float(mu))
    except (TypeError, ValueError):
        raise ValueError(f"`init` must be a pair of numbers (mu, sigma), got {init!r}") from None
    if not SIGMA_BOUNDS[0] <= sigma <= SIGMA_BOUNDS[1]:
        raise ValueError(f"`init`: sigma must be in [{SIGMA_BOUNDS[0]}, {SIGMA_BOUNDS[1]}] (SIGMA_BOUNDS), got {sigma!r}")
    if fresnel and not MU_BOUNDS[0] <= mu <= MU_BOUNDS[1]:
        raise ValueError(f"`init`: mu must be in [{MU_BOUNDS[0]}, {MU_BOUNDS[1]}] (MU_BOUNDS) with Fresnel, got {mu!r}")
    return mu, sigma


def _search_samples(weights, m: int):
    """`m` indices evenly spaced over the samples of positive weight, or None when there are at most `m`.

    Weight-0 padding (`shard_observations`) is never drawn, so a sharded capture searches the same samples
    as the unsharded one. Weights spread over several processes (`jax.distributed`) are not fetched to the
    host: the indices are computed by XLA (replicated)."""
    local = getattr(weights, "is_fully_addressable", True)
    pos = np.flatnonzero(np.asarray(weights) > 0) if local else None
    n_pos = pos.size if local else int(jnp.sum(weights > 0))
    if n_pos <= m:
        return None
    k = np.round(np.linspace(0, n_pos - 1, m)).astype(np.int64)
    return jnp.asarray(pos[k]) if local else jnp.nonzero(weights > 0, size=n_pos)[0][jnp.asarray(k)]


def _rows_of(terms, idx):
    """The samples `idx` of a `PracticalTerms` (the per-sample fields; `fast_energy` is shared)."""
    return jaxsh.PracticalTerms(*(x[idx] for x in (terms.visible, terms.cos_o, terms.irradiance, terms.bands,
                                                   terms.theta_h, terms.fast_weight)), terms.fast_energy)


@jaxsh.jit
def _fit_brdf(terms, b, w, texel, u_grid, n_texels, fresnel, textured, refine, max_steps, rtol, atol, search=None,
              blocks: int = 1):
    dt = b.dtype
    nobs = jnp.sum((w > 0).astype(dt)) * b.shape[1]
    sw = jnp.sqrt(w)[:, None]

    def profiled_on(terms, b, w, sw, u):
        mu, sigma = _to_natural(u, fresnel)
        D = terms.diffuse_unit()
        S = terms.specular_unit(mu, sigma, check=False)  # once per evaluation: the inner solve and the residual share it
        kd, ks, bad = _inner(D, S, b, w, texel, n_texels, textured)
        r = sw * (_combine(D, S, kd, ks, texel) - b)
        return r, (kd, ks, bad, D, S)

    def profiled(u):
        return profiled_on(terms, b, w, sw, u)

    # the grid and the simplex (homogeneous fits with the LM refinement): on the `search` samples
    if search is None:
        s_terms, s_b, s_w, s_sw = terms, b, w, sw
    else:
        s_terms, s_b, s_w, s_sw = _rows_of(terms, search), b[search], w[search], sw[search]

    # The optimizers run in the default float dtype (optimistix's simplex mixes its own scalars into the
    # state: a float32 problem with x64 enabled would not trace); the model runs in the data's dtype.
    pdt = jnp.asarray(0.0).dtype

    lo, hi = _u_bounds(fresnel, dt)
    # outside the box: the value at the box plus a quadratic wall scaled by the data energy
    wall = jnp.maximum(jnp.sum(w[:, None] * b * b), jnp.finfo(dt).tiny)
    s_wall = wall if search is None else jnp.maximum(jnp.sum(s_w[:, None] * s_b * s_b), jnp.finfo(dt).tiny)

    # The searches run in units of the data: the objective over the mean weighted square of the data, the LM
    # residual over its root, so that the absolute tolerances `atol` mean the same at every radiometric scale
    # (before, noise-free images x1e30 in float64, x1e10 in float32, stopped at `max_steps_reached`).
    s_unit = s_wall / jnp.maximum(jnp.sum((s_w > 0).astype(dt)) * b.shape[1], 1.0)
    unit = wall / jnp.maximum(nobs, 1.0)

    def objective(u, _):
        u = u.astype(dt)
        uc = jnp.clip(u, lo, hi)
        r, _aux = profiled_on(s_terms, s_b, s_w, s_sw, uc)
        return ((jnp.sum(r * r) + s_wall * jnp.sum((u - uc) ** 2)) / s_unit).astype(pdt)

    # Start: best grid point (evaluated one at a time), then the simplex of R&H sec. 6.1. Memory O(N): `lax.map`, not a vmap over the grid.
    grid_vals = jax.lax.map(lambda u: objective(u, None), u_grid.astype(pdt))
    u0 = u_grid.astype(pdt)[jnp.argmin(jnp.where(jnp.isfinite(grid_vals), grid_vals, jnp.inf))]
    nm = optx.minimise(objective, optx.NelderMead(rtol=rtol, atol=atol), u0, max_steps=max_steps, throw=False)
    u = jnp.clip(nm.value.astype(dt), lo, hi)
    # a parameter at the box after the simplex is held there by the joint refinement
    at_lo, at_hi = u <= lo + _AT_BOUND_TOL, u >= hi - _AT_BOUND_TOL
    pinned = at_lo | at_hi
    steps_nm = nm.stats["num_steps"]
    steps_lm = jnp.zeros_like(steps_nm)
    st_nm = status_from_optimistix(nm.result)
    st_lm = Status.converged
    if refine and textured is None:
        # Levenberg-Marquardt on the profiled residual over (mu, sigma) with (kd, ks) re-solved inside: variable
        # projection (Golub & Pereyra 1973), whose minimizer is the joint one over all parameters; the Jacobian
        # (autodiff through the 2x2 inner solves) has 2 columns, not 2C + 2.
        def resid(p, _):
            uu = jnp.where(pinned, u, p.astype(dt))
            uc = jnp.clip(uu, lo, hi)
            r, _aux = profiled(uc)
            # the samples' (N, C) and the box's wall (2,) as two leaves: on sharded samples a concatenation would
            # gather every residual to one device at every step
            scale = jnp.sqrt(unit)
            return (r / scale).astype(pdt), (jnp.sqrt(wall) * (uu - uc) / scale).astype(pdt)

        p0 = u.astype(pdt)
        # `explicit_jacobian`: the solver's state then holds the Jacobian ((N, C, 2) and (2, 2)), not the residual's
        # intermediates
        lm = optx.least_squares(explicit_jacobian(resid), LevenbergMarquardt(rtol=rtol, atol=atol, blocks=blocks), p0,
                                max_steps=max_steps, throw=False)
        p1 = lm.value
        # both ends in one batched evaluation, which is also the final evaluation (the estimate, the residual and the
        # design energy below): one copy of the model in the program instead of three (`resid`'s own at each end and
        # a final one), ~0.3 s of a first call's compilation
        uu = jnp.where(pinned[None, :], u[None, :], jnp.stack([p0, p1]).astype(dt))  # as in `resid`
        ends = jnp.clip(uu, lo[None, :], hi[None, :])
        r_ends, aux_ends = jax.vmap(profiled)(ends)
        rss_ends = jnp.sum(r_ends**2, axis=(1, 2)) + wall * jnp.sum((uu - ends) ** 2, 1)  # `resid`'s squares
        pick = (rss_ends[1] <= rss_ends[0]) & jnp.all(jnp.isfinite(p1))
        u = ends[jnp.where(pick, 1, 0)]
        r, (kd, ks, bad, d_fin, s_fin) = jax.tree_util.tree_map(lambda a: jnp.where(pick, a[1], a[0]), (r_ends, aux_ends))
        steps_lm = lm.stats["num_steps"]
        st_lm = status_from_optimistix(lm.result)
    else:
        # the final evaluation serves the estimate, the residual and the design energy below (one copy of the model)
        r, (kd, ks, bad, d_fin, s_fin) = profiled(u)
    mu, sigma = _to_natural(u, fresnel)
    rss = jnp.sum(r * r)
    at_bound = (u <= lo + _AT_BOUND_TOL) | (u >= hi - _AT_BOUND_TOL)
    bound_mu = at_bound[0] if fresnel else jnp.asarray(False)
    bound_sigma = at_bound[-1]

    # Standard errors from the Jacobian in natural parameters (K_d, K_s, mu, sigma).
    if textured is None:
        c = b.shape[1]
        g = _gram_homogeneous(terms, d_fin, s_fin, ks, w, mu, sigma, fresnel)
        # a parameter held at its bound is not estimated: zero column -> infinite standard error
        keep = jnp.ones(2 * c + 2, dt).at[2 * c].set(jnp.where(bound_mu | (not fresnel), 0.0, 1.0))
        keep = keep.at[2 * c + 1].set(jnp.where(bound_sigma, 0.0, 1.0))
        cov, se = covariance_from_gram(g * keep[:, None] * keep[None, :], rss, nobs, 2 * c + (2 if fresnel else 1))
        std = TorranceSparrow(se[:c], se[c : 2 * c], se[2 * c] if fresnel else None, se[2 * c + 1])
        counts = None
    else:
        def resid_prof(th2):
            mu_ = th2[0] if fresnel else None
            sigma_ = th2[1]
            D = terms.diffuse_unit()
            S = terms.specular_unit(mu_, sigma_, check=False)
            kd_, ks_, _ = _inner(D, S, b, w, texel, n_texels, textured)
            return (sw * (_model(terms, kd_, ks_, mu_, sigma_, texel) - b)).reshape(-1)

        th2 = jnp.stack([mu if fresnel else jnp.zeros((), dt), sigma])
        J = jax.jacfwd(resid_prof)(th2)
        if not fresnel:
            J = J.at[:, 0].set(0.0)
        J = J.at[:, 0].multiply(jnp.where(bound_mu, 0.0, 1.0)).at[:, 1].multiply(jnp.where(bound_sigma, 0.0, 1.0))
        D, S = (jnp.broadcast_to(x, b.shape) for x in (d_fin, s_fin))  # grey terms: as in `_gram_homogeneous`

        def seg(x):
            return jax.ops.segment_sum(x, texel, num_segments=n_texels)

        dd = seg(w[:, None] * D * D)
        # samples of positive weight: weight-0 samples (invalid pixels, `pad_observations`' padding) observe nothing
        counts = jax.ops.segment_sum((w > 0).astype(jnp.int32), texel, num_segments=n_texels)
        # the parameters the samples fit: K_d (and K_s) of the observed texels only (a texel without a sample has
        # no parameter in the residual; counting all T of them made n - p <= 0 and s2 = RSS, standard errors
        # ~100x too large, whenever the texels outnumber the samples per texel, e.g. a camera's pixels)
        seen = jnp.sum((counts > 0).astype(dt))
        n_par = seen * kd.shape[-1] * (2 if textured == "kd_ks" else 1) + (ks.shape[-1] if textured == "kd" else 0) + (2 if fresnel else 1)
        cov, se2 = covariance_from_jacobian(J, rss, nobs, n_par)
        # Texel K_d (and K_s) errors, conditional on mu, sigma: diagonal of the per-texel 2x2 inverse.
        s2 = rss / jnp.maximum(nobs - n_par, 1.0)
        if textured == "kd_ks":
            ds, ss = seg(w[:, None] * D * S), seg(w[:, None] * S * S)
            v_kd, v_ks, _ = inverse_sym2_diag(dd, ds, ss)  # inf where undetermined (a texel without specular
            # sums keeps its K_d's error)
            se_kd = jnp.sqrt(s2 * v_kd)
            se_ks = jnp.sqrt(s2 * v_ks)
            und_ks = _undetermined_texel_ks(kd, se_ks, counts > 0)
        else:
            # one K_s per channel: its variance is s2 over the Schur complement of the K_d block, and each K_d's
            # is s2 (1/dd + (ds/dd)^2 / schur) (the inverse of the bordered normal matrix), both given mu, sigma
            ds = seg(w[:, None] * D * S)
            has = dd > 0
            dd_s = jnp.where(has, dd, 1.0)
            schur = jnp.sum(seg(w[:, None] * S * S), 0) - jnp.sum(jnp.where(has, ds * ds / dd_s, 0.0), 0)
            okk = schur > 1e3 * jnp.finfo(dt).eps * jnp.sum(seg(w[:, None] * S * S), 0)
            inv_schur = jnp.where(okk, 1.0 / jnp.where(okk, schur, 1.0), jnp.inf)
            se_kd = jnp.where(has, jnp.sqrt(s2 * (1.0 / dd_s + (ds / dd_s) ** 2 * inv_schur[None, :])), jnp.inf)
            se_ks = jnp.broadcast_to(jnp.sqrt(s2 * inv_schur), ks.shape)
        std = TorranceSparrow(se_kd, se_ks, se2[0] if fresnel else None, se2[1])

    # mu and sigma act only through K_s S: without a specular signal they are not determined, whatever the
    # Jacobian's scaled columns say (`_no_specular_signal`); the simplex then wanders on a flat objective
    no_spec = _no_specular_signal(ks, std.ks, s_fin, b, w, texel, None if textured != "kd_ks" else und_ks)
    inf = jnp.asarray(jnp.inf, dt)
    std = TorranceSparrow.unchecked(std.kd, std.ks, jnp.where(no_spec, inf, std.mu) if fresnel else None,
                                    jnp.where(no_spec, inf, std.sigma))
    st_nm = Status.where(no_spec & (st_nm == Status.max_steps_reached), Status.converged, st_nm)
    st_lm = Status.where(no_spec & (st_lm == Status.max_steps_reached), Status.converged, st_lm)

    finite = jnp.isfinite(rss) & jnp.all(jnp.isfinite(kd)) & jnp.isfinite(sigma)
    data_ss = jnp.sum(w[:, None] * b * b)
    # the model's own energy per channel: 0 under all-zero lighting (no pixel carries information on kd, ks)
    design_ss = jnp.min(jnp.sum(w[:, None] * (d_fin * d_fin + s_fin * s_fin), 0))
    status = worst(
        Status.where(finite, Status.converged, Status.nonfinite),
        signal_status(data_ss),
        signal_status(design_ss),
        Status.where(bad, Status.ill_conditioned, Status.converged),
        st_nm,
        st_lm,
    )
    rms, rel = rms_pair(rss, data_ss, nobs)
    brdf = TorranceSparrow(kd, ks, mu, sigma)
    at_bound_d = {"mu": bound_mu, "sigma": bound_sigma}
    # undetermined: at the box, or a one-sigma error larger than the distance to the limit (mu - 1, sigma)
    undetermined = {
        "mu": bound_mu | (~(std.mu < mu - 1.0) if fresnel else jnp.asarray(False)),
        "sigma": bound_sigma | ~(std.sigma < sigma),
    }  # (`no_spec`: both, their errors are inf)
    if textured == "kd_ks":
        undetermined["ks"] = und_ks
    n_search = jnp.sum((w > 0).astype(jnp.int32)) if search is None else jnp.asarray(search.shape[0])
    stats = {"num_steps_simplex": steps_nm, "num_steps_lm": steps_lm, "grid_points": jnp.asarray(u_grid.shape[0]),
             "search_pixels": n_search,
             "n_obs": nobs, "at_bound": at_bound_d, "undetermined": undetermined}
    return BRDFResult(brdf=brdf, std_errors=std, covariance=cov, status=status, iterations=steps_nm + steps_lm, rms=rms,
                      rel_rms=rel, texel_count=counts, fitted=_combine(d_fin, s_fin, kd, ks, texel), stats=stats)
