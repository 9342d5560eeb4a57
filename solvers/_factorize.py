"""Factorization: unknown lighting and BRDF (R&H 2001 sec. 6.3), and roughness from a source (eq. 26).

**Objective.** The global scale is unrecoverable, so $K_d + K_s = 1$ per
channel (each channel's lighting absorbs its own scale). As in the paper,
the BRDF parameters are searched with the lighting profiled out: for given
$(\\mu, K_s)$ the lighting is the eq.-25 least-squares solution, and the
objective is the residual sum of squares of that fit (relative to the
data's, summed over channels). The paper runs one simplex over
$(K_s, \\mu)$; here the same objective is minimized by two nested 1-D
searches (the channels decouple once $\\mu$ is fixed):

* **outer, over $t = \\log(\\mu - 1)$:** a grid of 9 values on
  $[\\log 0.05, \\log 2.5]$ ($\\mu \\in [1.05, 3.5]$), evaluated in one jitted
  call (`vmap`; `lax.map` on the direct path below); then 9 Chebyshev points on the bracket of the best
  value (its two neighbours, within the range), and the minimum of the polynomial through them gives the
  continuous minimum and, from its second derivative, the standard error of $\\mu$ (`_interpolant_minimum`:
  the profile is analytic in $t$, so the interpolant converges geometrically; it was 10-10,000 times closer to
  the profile's minimum than the two 7-point zooms and parabola it replaced). A minimum at the bracket's end
  inside the range centres one more bracket there. That is 18 evaluations and two host round trips (the
  bracket is chosen by `numpy.argmin` between the calls). Each
  evaluation forms the normal-equation blocks of eq. 25 for that $\\mu$ once,
  on a random subset of `search_pixels` pixels (drawn on the host by NumPy,
  seeded with `key`), and the pseudo-inverse of their $l > 2$ block (one
  batched eigendecomposition per round on one local device). The blocks of all
  candidates of a round come from one table of the subset's mirror-direction
  harmonics to $2l^*$, made once (`grams_at_mus`: the specular block by an
  exact quadrature of the projected point set, $O(N (2l^*+1)^2)$ per $\\mu$
  instead of the direct sum's $O(N (l^*+1)^4)$; the direct sum,
  `accumulate_gram`, where the table would exceed `_TABLE_BYTES`);
* **inner, over $K_s \\in [10^{-6}, 1]$ per channel** ($K_d = 1 - K_s$):
  `optimistix.GoldenSearch`, `vmap`ped over the channels inside the same jit
  (no host round trip), plus a check of the end point $K_s = 1$. Each step
  eliminates the $l > 2$ coefficients with that pseudo-inverse and solves the
  $9 \\times 9$ Schur complement of the $l \\le 2$ ones by Gaussian
  elimination (no LAPACK call inside the loop; see `_normal_equations`).

At the chosen $\\mu$ the search is repeated on all pixels and the lighting
is solved as in `inverse_lighting` (the filtered lighting of eq. 25). With the
table, that final solve runs the rounds' own compiled program (`_golden_batch`:
the blocks of all pixels enter as a batch like a round's), and the one pass over
all pixels (`_all_pixel_blocks`) also makes their eq.-25 rows for the refinement
and, with the subset's pixels taken first (`_subset_first`), the subset's blocks
for the refinement's search; the lighting and eq. 26 are one program
(`_lighting_and_source`). Fewer, shared programs are what a first call waits
for (XLA compilation; docs/performance.md). The two programs that run once and
for milliseconds but took 0.6-1.0 s each to compile (`_lighting_and_source`,
`_refine_final`) are compiled without XLA's backend optimizations
(`jaxsh.jit(optimize=False)`; docs/performance.md, "Eleventh round";
`_golden_batch`, which runs once per round, no longer: 12 ms a call at level 0,
2 ms optimized, "Twenty-second round").

**$\\mu$ on the joint model (`refine_mu`, the default; not in the paper).** Stage 1's objective models the
lighting as $l \\le l^*$ SH only. A bright compact source (a sun) is far from that model, and $\\mu$ absorbs
part of the misfit: on noise-free images of the refinement's own model (smooth lighting plus a sun), $\\mu$ 1.49
for 1.6 and $K_s$ 5-7 % low, with a standard error 140 times smaller than the error
(`tests/test_inverse.py::test_factorize_searches_mu_again_on_the_joint_model`). So once the source is found,
$\\mu$ is searched again with the refinement's model (slow SH plus the source as a delta, $(K_s, \\sigma)$
re-searched at each value: `_joint_mu_search`), and stage 1, eq. 26 and the refinement are redone at that
$\\mu$; its standard error comes from that profile's curvature.

**Roughness (eq. 26).** $\\sigma$ comes from the recovered (filtered)
lighting with $L_{cen} \\approx L_{tot}/(4\\pi\\sigma^2)$, evaluated with the
band limit taken into account: the brightest compact region is found
automatically (or given by the user), and $\\sigma$ solves
$\\frac{L_{cen} - b}{L_{tot} - b\\,\\Omega} = \\frac{f_\\sigma(0) - b_\\sigma}{\\int_{cap} f_\\sigma - b_\\sigma\\Omega}$,
where $f_\\sigma(\\theta) = \\sum_{l \\le l^*}\\frac{2l+1}{4\\pi}e^{-(\\sigma l)^2}P_l(\\cos\\theta)$ is
a unit delta source filtered by the lobe and truncated like the recovered
lighting, and $b$, $b_\\sigma$ the background levels measured on the same
annulus (radius to 1.5 × radius) around each. The root in $\\log\\sigma$,
$\\sigma \\in [10^{-3}, 2]$, is found by `optimistix.Bisection` (the ratio
decreases with $\\sigma$). For $l^* \\to \\infty$ this is eq. 26.

**Joint refinement (optional).** With the source found, the lighting is
modelled as slow SH up to $l^*$ (filtered by $e^{-(\\sigma l)^2}$, eq. 22) plus
the source as a delta of unknown energy (eq. 23); the model is linear in
the lighting given $(K_s, \\sigma)$, and the profiled residual (variable
projection) is minimized over $(K_s$ per channel$, \\sigma)$ on the search
subset, with $\\mu$ kept at its stage-1 value, by the nested searches of
stage 1: once $\\sigma$ is fixed the channels decouple, so each $K_s$ is
profiled out by `optimistix.GoldenSearch`, and $\\log\\sigma$ is searched by
grids of 16 values (two zooms, the first over eq. 26's range $[10^{-3}, 2]$,
the next between the best value's neighbours; then 16 Chebyshev points on that bracket and a last grid of
spacing within the tolerance around their interpolant's minimum), one batched pass over
the pixels per grid (`_refine_search`). The final solve uses all pixels; the standard errors
of $(K_s, \\sigma)$ come from the Hessian of the profiled RSS there (by central
differences, `_profiled_hessian`), that of $\\mu$ from the curvature of the interpolant of $\\mu$'s profile.

**The source direction** is the weighted centroid of the peak's texels on
the recovered lighting's lat-long map, refined by three mean-shift steps on
the band-limited SH lighting itself (`_mean_shift`: the centroid over a cap of
three texels, by quadrature in polar coordinates around the current centre),
so that it follows the scene and not the grid. It is then held fixed by the
refinement. On noise-free data made by the refinement's own model (slow SH to
$l = 8$ plus one delta, a 32 × 32 sphere, three views) the texel centroid
alone was 0.28° from the true source and 0.29-0.51° in four rotated copies of
the scene, which moved $K_s$ and $\\sigma$ by up to 1 % between the copies
and left a relative RMS of 0.4-1.1 %; with the mean shift it is 0.05° in all
five, the estimates agree to 3e-5 and the relative RMS is 0.15 %. What
remains is the background's slope under the peak, which shifts the peak
itself; a refinement of the direction along with $(K_s, \\sigma)$ would
remove it (not done: two more unknowns in every search of the refinement).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, Int, Real

import jaxsh

from ._brdf import _AT_BOUND_TOL
from ._data import Lighting, Observations, TorranceSparrow
from ._host_random import host_rng
from ._factorize_dual import _check_region_arg, _mu_candidates_dual, _stage1_final_dual, check_region, golden_ks_unit
from ._lighting import DualLightingResult, _dual, _dual_finish, default_dual_height, lighting_from_gram
from ._normal_equations import (Gram, MirrorTable, accumulate_gram, eq25_rows, grams_at_mus, inverse_spd_small,
                                mirror_table, pinv_psd, pixel_chunks, solve_spd_small)
from ._pixel_sums import map_over_pixels, pixel_sharding, sum_and_columns_over_pixels, sum_over_pixels
from ._results import Solution, Status, check_bool, check_float, check_int, finish, rms_pair, signal_status, worst
from ._threads import blas_single_thread

class SourceEstimate(eqx.Module):
    """A compact source found in a recovered lighting (R&H fig. 10).

    `direction` `(3,)`; `energy` `(C,)` = $L_{tot}$ above the background;
    `peak` `(C,)` = $L_{cen}$ above the background; `background` `(C,)`;
    `radius`: the region's angular radius; `sigma`: the roughness from eq. 26
    with the band-limit correction (module docstring); `sigma_eq26`: the
    plain $\\sqrt{L_{tot}/(4\\pi L_{cen})}$; `num_steps`: the bisection's steps.
    """

    direction: Float[Array, "3"]
    energy: Float[Array, " C"]
    peak: Float[Array, " C"]
    background: Float[Array, " C"]
    radius: Float[Array, ""]
    sigma: Float[Array, ""]
    sigma_eq26: Float[Array, ""]
    num_steps: Int[Array, ""]


class FactorizationResult(Solution):
    """Result of `factorize` (a `solvers.Solution`; `estimate` is `brdf`).

    - `brdf`: `TorranceSparrow` with $K_d + K_s = 1$ per channel.
    - `lighting`: the recovered lighting in the same scale — after the
      refinement, slow SH (unfiltered, to `lmax`) plus the source as a fast
      delta; without it, the filtered SH lighting of eq. 25.
    - `filtered_sh`: `(n_coeffs, C)` the eq.-25 (filtered) lighting of the
      first stage (at the final $\\mu$ with `refine_mu`), the input of eq. 26.
    - `source`: `SourceEstimate` (or None when `find_sigma=False`). With
      `lighting_method="dual"` and the refinement, its direction is the peak of
      `filtered_sh` (`_dual_source`), eq. 26 on the dual image around it.
    - `std_errors`: `TorranceSparrow` (from the Jacobian of the profiled
      residual of the final stage; `kd` errors equal `ks` errors; μ's from
      the curvature of the joint model's profile in the `refine_mu` search,
      or of stage 1's with `lighting_method="sh"`; inf with `"dual"` without
      `refine_mu`, whose stage-1 profile is of the dual model, not the refined one).
    - `status`: with the refinement, the worst of its search's outcome
      (`max_steps_reached` when the σ grids stop wider than the tolerance),
      `nonfinite`, `no_signal` and the status of stage 1's eq.-25 solve at the
      final μ (the same lighting unknowns: `ill_conditioned` when the pixels do
      not determine them; with `lighting_method="dual"`, the worse of the dual
      stage 1's status and that of eq. 25's solve from the refinement's blocks);
      without it, the status of that solve (as `inverse_lighting`; with
      `"dual"`, `inverse_lighting_dual`'s).
    - Bad options are `ValueError`s naming them: `search_pixels` below
      $(l^*+1)^2 + 4$, `rtol`/`atol` not finite ≥ 0, a `key` that is no PRNG
      key, a `region` that is not `(direction (3,), radius in (0, π])`.
    - `iterations`: the $\\mu$ candidates evaluated (18 with `fresnel`, 27 when stage 1's minimum fell on its
      bracket's end inside the range; 9 more with `refine_mu`: the joint model's, 18 when its minimum fell on the
      first window's edge) plus the $\\sigma$ values the final refinement evaluated.
    - `rms`, `rel_rms` (never NaN) of the final stage, on all pixels.
    - `stats`: `num_mu_candidates`, `num_sigma_candidates` (the refinement's
      $\\sigma$ values, 16 per grid; 0 without the refinement), `num_steps_golden` (the $K_s$ searches of the final
      stage-1 solve, per channel), `num_steps_bisection` (eq. 26; 0 without
      `find_sigma`), `n_obs`, `at_bound` (`{"mu": bool, "sigma": bool}`: the
      estimate stopped at an end of its search range, $\\mu \\in [1.05, 3.5]$
      (stage 1's grid, whose ends the searches reach exactly) or
      $\\sigma \\in [10^{-3}, 2]$ (within 0.1 %): the data do not place it inside;
      its standard error is then infinite and `status` stays `converged`, as
      `fit_brdf`'s `at_bound`).
    - `dual`: with `lighting_method="dual"`, the `DualLightingResult` of the
      first stage (the angular-space lighting image of fig. 8 at the stage-1
      BRDF, the input of eq. 26); otherwise None. `filtered_sh` is then that
      image projected to `lmax`.
    - `fitted`: `(N, C)` the model at the estimate for every sample of `obs`,
      the values the final residual compares with `obs.values`
      (`obs.to_images(result.fitted)`: re-renders of the views). After the
      refinement: eq. 24 with `brdf` and `lighting` (the filtered slow SH and
      the source); without it: eq. 25 at the first stage's $K_s$, $\\mu$ and
      `filtered_sh` (with `lighting_method="dual"`, the dual image's
      projection, so its residual is not the dual fit's `rms`).
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
    stats: dict
    dual: DualLightingResult | None = None
    fitted: Float[Array, "N C"] | None = None

    @property
    def estimate(self) -> TorranceSparrow:
        return self.brdf


# --------------------------------------------------------------------------- stage 1


class _Blocks(eqx.Module):
    """Normal-equation blocks of eq. 25 for one mu, split at the l <= 2 columns, with a factor of pinv(SS22)."""

    g: Gram
    h22: Array  # (n-9, n-9): pinv(SS22) = h22^T h22 (`_half_pinv`), for `_golden_ks`

    @property
    def p22(self) -> Array:
        """pinv(SS22) `(n-9, n-9)` (formed on demand: only `_schur_rss`, the tests' reference, reads it)."""
        return jnp.swapaxes(self.h22, -1, -2) @ self.h22


def _blocks(o: Observations, mu, lmax: int, chunk: int, rcond: float, where=None) -> _Blocks:
    """The eq.-25 blocks of `o` at `mu` (`accumulate_gram`), on each device's pixels when `where` (`pixel_sharding`)."""
    g = sum_over_pixels(lambda n, v, b, w, t, r, mu_: accumulate_gram(n, v, b, w, t, r, mu_, None, lmax, chunk), where,
                        _pixel_fields(o), (mu,))
    return _Blocks(g, _half_pinv(g.ss[9:, 9:], rcond))


def _pixel_fields(o: Observations) -> tuple:
    """The per-pixel fields of eq. 25's rows and sums: normals, views, values, weights, transfer, reflected visibility."""
    return o.normals, o.views, o.values, o.weights, o.transfer, o.reflected_visibility


def _half_pinv(a, rcond):
    """The factor $H = \\Lambda_+^{-1/2}V^T$ of `pinv_psd(a, rcond)` $= H^TH$, of `a` `(m, m)` or of each of a stack
    `(K, m, m)` (the pseudo-inverse itself is not formed: `_Blocks.p22`). A Cholesky factor instead ($H = L^{-1}$,
    4.2 against 16.0 ms for 9 × 160² alone) did not shorten `_mu_blocks`, whose program took as long without any
    factor (docs/performance.md, twenty-first and twenty-fourth rounds)."""
    return pinv_psd(a, rcond, half=True)[1]


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
    x1 = solve_spd_small(schur, rhs)
    x2 = y - jnp.einsum("cjk,ck->cj", yy, x1)
    rss = g.bb - jnp.sum(r1 * x1, -1) - jnp.sum(r2 * x2, -1)
    return rss, x1, x2


def _golden_ks(bl: _Blocks, filt, rtol: float, atol: float, max_steps: int):
    """Per channel, the $K_s \\in [0, 1]$ ($K_d = 1 - K_s$) minimizing the eq.-25 RSS: `optimistix.GoldenSearch`.

    The channels are independent problems (each its own right-hand side), so the scalar search is
    `vmap`ped over them, inside the caller's jit (one `while_loop`, no host round trip). The end point
    $K_s = 1$ (a pure mirror) is checked as well. Returns `ks (C,)`, `rss (C,)`, `num_steps (C,)`.

    Each evaluation is the elimination of `_schur_rss` with the $K_s$-independent parts formed once. With
    $P = \\mathrm{pinv}(SS_{22}) = H^TH$ (`_half_pinv`), $A_{22}^{-1} = D_2^{-1}PD_2^{-1}/K_s^2$ and
    $A_{12} = K_s(K_d\\,DS_{12} + K_s\\,F_1SS_{12})D_2$ ($D_2$, $F_1$: the filter's diagonal on the $l > 2$ and
    $l \\le 2$ columns), the filter $D_2$ and the powers of $K_s$ cancel:
    $A_{12}A_{22}^{-1}A_{12}^T = Z^TZ$ and $A_{12}A_{22}^{-1}r_2 = Z^Te_b$ with
    $Z = K_d\\,H DS_{12}^T + K_s\\,H SS_{12}^TF_1$ `(m, 9)`, $e_b = H\\,sb_2$, and the RSS is
    $bb - |e_b|^2 - h^TS^{-1}h$, $S = A_{11} - Z^TZ$, $h = r_1 - Z^Te_b$. $S$ and $h$ are quadratic and
    linear in $(K_d, K_s)$, so their parts are formed once (`_GoldenParts`) and a step costs one 9×9
    elimination ($O(81\\,m)$ before the parts were squared out, $O(9\\,m^2)$ for the blocks; $m = (l^*+1)^2 -
    9$), with no division by $K_s$. Tested against a dense NumPy solve (`tests/test_inverse.py`).
    """
    return _golden_search(_golden_parts(bl, filt), rtol, atol, max_steps)


def _golden_search(parts: _GoldenParts, rtol: float, atol: float, max_steps: int):
    """`golden_ks_unit` on `_reduced_rss` for every problem of `parts`, whose fields carry any leading batch axes
    (`(C,)` channels, `(K, C)` candidates and channels): `ks`, `rss`, `num_steps`, each of the leading shape.

    The leading axes are flattened into one and the search is `vmap`ped once: a `vmap` of a `vmap` of the
    search batched its `while_loop` twice at trace time (a fixpoint over the carry each time), and tracing
    the nested searches of `factorize` took about a third of a second per program."""
    lead = parts.base.shape
    flat = jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[len(lead):]), parts)
    dt = parts.base.dtype

    def one(p):
        return golden_ks_unit(lambda ks, _: _reduced_rss(p, ks), dt, rtol, atol, max_steps)

    return jax.tree_util.tree_map(lambda a: a.reshape(lead), jax.vmap(one)(flat))


class _GoldenParts(eqx.Module):
    """The $K_s$-independent parts of the eq.-25 RSS of one channel (`_golden_ks`); batched over channels.

    With $K_d = 1 - K_s$ the Schur complement and its right-hand side are quadratic and linear in
    $(K_d, K_s)$: $S = K_d^2 S_{dd} + K_dK_s S_{ds} + K_s^2 S_{ss}$, $h = K_d h_d + K_s h_s$, where
    $S_{dd} = A_{dd} - E_d^TE_d$, $S_{ds} = A_{ds} - (E_d^TE_s + E_s^TE_d)$, $S_{ss} = A_{ss} - E_s^TE_s$,
    $h_d = r_d - E_d^Te_b$, $h_s = r_s - E_s^Te_b$ (`_golden_ks`' $Z = K_dE_d + K_sE_s$ squared out), so a
    step of the search is one k×k elimination, with no product over the m columns. Measured on the
    benchmark capture's 48 problems (16 σ × 3 channels, k = 10, m = 160): the search 13.6 → 2.3 ms, the
    RSS at the same $K_s$ within 2e-13 relative of the form that combines $Z$ first, both within 3.3e-12 of
    an 80-bit evaluation of that form (its inputs rounded to float64 bound either)."""

    s_dd: Array  # (k, k): the K_d^2 part of S
    s_ds: Array  # (k, k): its K_d K_s part
    s_ss: Array  # (k, k): its K_s^2 part
    h_d: Array  # (k,): the K_d part of h
    h_s: Array  # (k,): its K_s part
    base: Array  # (): bb - |e_b|^2


def _quadratic_parts(a_dd, a_ds, a_ss, e_d, e_s, r_d, r_s, e_b, base) -> _GoldenParts:
    """`_GoldenParts` from the blocks of `_golden_ks`: `a_*` `(k, k)`, `e_d`, `e_s` `(m, k)` shared by the
    channels; `r_d`, `r_s` `(C, k)`, `e_b` `(C, m)`, `base` `(C,)` per channel."""
    c = base.shape[0]
    gd, gs = e_d.T @ e_d, e_s.T @ e_s
    gds = e_d.T @ e_s

    def each(a):
        return jnp.broadcast_to(a, (c,) + a.shape)

    return _GoldenParts(each(a_dd - gd), each(a_ds - (gds + gds.T)), each(a_ss - gs),
                        r_d - e_b @ e_d, r_s - e_b @ e_s, base)


def _golden_parts(bl: _Blocks, filt) -> _GoldenParts:
    """`_GoldenParts` of every channel (leading axis C)."""
    g = bl.g
    f1 = filt[:9]
    h = bl.h22
    ds1 = g.ds[:, :9] * f1[None, :]
    e_b = h @ g.sb[9:]  # (m, C)
    return _quadratic_parts(
        g.dd,
        ds1 + ds1.T,
        f1[:, None] * g.ss[:9, :9] * f1[None, :],
        h @ g.ds[:, 9:].T,
        (h @ g.ss[:9, 9:].T) * f1[None, :],
        g.db.T,
        (f1[:, None] * g.sb[:9]).T,
        e_b.T,
        g.bb - jnp.sum(e_b * e_b, 0),
    )


def _reduced_rss(p: _GoldenParts, ks):
    """The eq.-25 RSS of one channel at `ks` ($K_d = 1 - K_s$) from its `_GoldenParts`: one k×k elimination."""
    kd = 1.0 - ks
    schur = kd**2 * p.s_dd + kd * ks * p.s_ds + ks**2 * p.s_ss
    h = kd * p.h_d + ks * p.h_s
    return p.base - h @ solve_spd_small(schur, h)


# --------------------------------------------------------------------------- eq. 26


def _delta_weights(sigma, lmax: int, dt):
    """The Legendre coefficients `(lmax + 1,)` of the band-limited filtered unit source (module docstring)
    $f_\\sigma(\\theta) = \\sum_{l\\le l^*} \\tfrac{2l+1}{4\\pi} e^{-(\\sigma l)^2} P_l(\\cos\\theta)$."""
    l = jnp.arange(lmax + 1, dtype=dt)
    return (2 * l + 1) / (4 * jnp.pi) * jnp.exp(-((sigma * l) ** 2))


def _delta_moments(lmax: int):
    """`_source_on_map`'s `moments` for $f_\\sigma$ (`_delta_weights`): the functionals `m` `(K, T)` of the
    profile on the grid `theta` are linear in its Legendre coefficients, so `m @ P_l(cos theta)`
    `(K, lmax + 1)` is formed once and each evaluation inside the bisection is one dot with
    `_delta_weights` (no Legendre recurrence in the loop)."""

    def make(m, theta):
        mp = m @ jaxsh.legendre_p(jnp.cos(theta), lmax)
        return lambda sigma: mp @ _delta_weights(sigma, lmax, theta.dtype)

    return make


def _lobe_moments(m, theta):
    """`_source_on_map`'s `moments` for `_lobe` (no band limit): `m @ _lobe(sigma, theta)` per evaluation."""
    return lambda sigma: m @ _lobe(sigma, theta)


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
    `coeffs` (module docstring; the root in $\\log\\sigma \\in [\\log 10^{-3}, \\log 2]$ by
    `optimistix.Bisection`, the nearer end when the ratio lies outside),
    `sigma_eq26` is the paper's formula.
    """
    coeffs = jnp.asarray(coeffs)
    if coeffs.ndim == 1:
        coeffs = coeffs[:, None]
    lmax = int(round(np.sqrt(coeffs.shape[0]))) - 1
    if (lmax + 1) ** 2 != coeffs.shape[0] or lmax < 1:
        raise ValueError(f"`coeffs` must have shape (n_coeffs, C) with lmax >= 1, got {tuple(coeffs.shape)}")
    dt = coeffs.dtype
    h = check_int(height, "height", lo=4)
    return _find_source(coeffs, check_region(region, h, dt), h, lmax)


_SHIFT_STEPS = 3  # mean-shift steps of the source direction (`_mean_shift`)


@jaxsh.jit
def _find_source(coeffs, region, h: int, lmax: int) -> SourceEstimate:
    """`find_source` after its checks: one compiled program (`h`, `lmax` static)."""
    dt = coeffs.dtype
    w = 2 * h
    img = jaxsh.synthesize_latlong(coeffs, h, w)  # (H, W, C)
    def value_at(q):  # the band-limited map at any directions `(..., 3)`: `(..., C)`
        return jaxsh.real_sh(q, lmax) @ coeffs

    return _source_on_map(img, jnp.ones((h, w), bool), region, lambda d, k: value_at(d), _delta_moments(lmax),
                          value_at=value_at)


def _lobe(sigma, theta):
    """The filtered unit directional source without a band limit: $e^{-\\theta^2/(4\\sigma^2)}/(4\\pi\\sigma^2)$.

    (eq. 24 at normal exitance, $\\theta_h = \\theta/2$: $T(\\theta_h)/4$; the small-σ form of $f_\\sigma$,
    `_delta_weights`.)"""
    return jnp.exp(-(theta**2) / (4 * sigma**2)) / (4 * jnp.pi * sigma**2)


@jaxsh.jit
def _source_in_image(img, covered, region, direction=None) -> SourceEstimate:
    """eq. 26 on a dual lighting image `(H, W, C)` (`inverse_lighting_dual`): `_source_on_map` with the
    covered texels only (uncovered ones hold the l <= 2 field), the brightest texel's value as the peak,
    and the lobe without a band limit (`_lobe`); the source's `direction` `(3,)` when given (`_dual_source`)."""
    return _source_on_map(img, covered, region, lambda d, k: img.reshape(-1, img.shape[-1])[k], _lobe_moments,
                          direction=direction)


def _dual_source(dual, filtered, region, height: int, dt, sharpen: bool) -> SourceEstimate:
    """The source of the dual path: eq. 26 on the dual image (`_source_in_image`, its grid of `2 height` rows).

    With `sharpen` (the joint refinement follows, and holds the source's direction fixed), the direction is the
    peak of the image's SH projection `filtered` (to $l^*$), found by mean shift as on the SH path
    (`find_source`), and eq. 26 is taken on the image around it. The image's own direction is the centroid of
    its brightest texels, whose size bounds it: on 3-view spheres under a sun (`sphere_capture`, $l^*$ = 12,
    1 % noise) it was 0.082 rad off at 32² (16 rows in the search, 32 in the image) and 0.030 at 64², and the
    refined fit kept that error (`rel_rms` 0.17 and 0.067, against 0.017 and 0.018 on the SH path); from the
    projection 0.012 and 0.006 (`rel_rms` 0.023 and 0.019)."""
    reg = check_region(region, 2 * height, dt)
    if not sharpen:
        return _source_in_image(dual.image, dual.covered, reg)
    d = find_source.__wrapped__(filtered, region=region).direction
    return _source_in_image(dual.image, dual.covered, reg, d)


def _mean_shift(d, value_at, rho, steps: int = _SHIFT_STEPS, n_r: int = 12, n_phi: int = 24):
    """The centre of a peak of a map known at any direction: `steps` mean-shift steps from `d`, each to the
    centroid of $(f - \\min f)$ over the cap of radius `rho` around the current centre ($f$ the channel mean of
    `value_at`), by a midpoint rule in polar coordinates on the cap (`n_r` × `n_phi` nodes, weight
    $\\sin r$). For a radially symmetric peak the centroid is its centre, whatever the grid: this is what
    makes the source direction follow the scene, not the lat-long grid (`_source_on_map`)."""
    dt = d.dtype
    r = (jnp.arange(n_r, dtype=dt) + 0.5) * (rho / n_r)
    phi = (jnp.arange(n_phi, dtype=dt) + 0.5) * (2 * jnp.pi / n_phi)
    cr, sr = jnp.cos(r)[:, None, None], jnp.sin(r)[:, None, None]
    ring = jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1)[None]  # (1, n_phi, 2)

    def step(_, d):
        a = jnp.where(jnp.abs(d[2]) < 0.9, jnp.asarray([0.0, 0.0, 1.0], dt), jnp.asarray([1.0, 0.0, 0.0], dt))
        e1 = jnp.cross(d, a)
        e1 = e1 / jnp.linalg.norm(e1)
        e2 = jnp.cross(d, e1)
        q = cr * d[None, None] + sr * (ring[..., :1] * e1[None, None] + ring[..., 1:] * e2[None, None])  # (n_r, n_phi, 3)
        f = jnp.mean(value_at(q.reshape(-1, 3)), -1).reshape(n_r, n_phi)
        wq = sr[..., 0] * (f - jnp.min(f))
        c = jnp.sum(wq[..., None] * q, (0, 1))
        n = jnp.linalg.norm(c)
        return jnp.where(n > 0, c / jnp.where(n > 0, n, 1.0), d)

    return jax.lax.fori_loop(0, steps, step, d)


def _source_on_map(img, covered, region, peak_at, moments, value_at=None, direction=None) -> SourceEstimate:
    """eq. 26 on a lat-long lighting map `img` `(H, W, C)` (module docstring), inside the caller's jit.

    `covered` `(H, W)`: the texels that carry the lighting (all, for an SH map; the mirror-covered ones for
    the dual image); `peak_at(d, k)`: the map's value `(C,)` at the centre `d` (flat texel `k` is the
    brightest); `moments(m, theta)`: a function of sigma giving `m @ f_sigma(theta)` `(K,)` for the model
    `f_sigma` of a filtered unit source at the angles `theta` `(T,)` and fixed weights `m` `(K, T)`
    (`_delta_moments`, `_lobe_moments`). `value_at(q)`: the map at any directions `(..., 3)` (an SH map), or
    None (a texel image): with it, the texel centroid is refined by `_mean_shift` over a cap of three texels,
    so that the direction does not depend on where the grid's texels fall. `direction` `(3,)`: the source's
    direction, found elsewhere (the cap and annulus of eq. 26 are then centred on it), or None."""
    dt = img.dtype
    h, w = img.shape[:2]
    dirs = jaxsh.latlong_directions(h, w, dtype=dt)
    wts = jnp.where(covered, jaxsh.latlong_weights(h, w, dtype=dt), 0.0)
    lum = jnp.mean(img, -1)
    sel = covered if region is None else covered & ((dirs @ region[0]) >= jnp.cos(region[1]))
    k = jnp.argmax(jnp.where(sel, lum, -jnp.inf))
    d0 = dirs.reshape(-1, 3)[k]
    # refine the centre: weighted centroid of the top of the peak
    ang = jnp.arccos(jnp.clip(dirs @ d0, -1.0, 1.0))
    peak_val = lum.reshape(-1)[k]
    # radial profile around d0 (ring means of the covered texels) -> half-maximum radius and background
    edges = jnp.linspace(0.0, 1.2, 121, dtype=dt)
    ring = jnp.clip(jnp.searchsorted(edges, ang.reshape(-1)) - 1, 0, 119)
    wflat = wts.reshape(-1)
    within = ang.reshape(-1) < 1.2
    prof_w = jax.ops.segment_sum(jnp.where(within, wflat, 0.0), ring, 120)
    prof = jax.ops.segment_sum(jnp.where(within, wflat * lum.reshape(-1), 0.0), ring, 120)
    prof = jnp.where(prof_w > 0, prof / jnp.where(prof_w > 0, prof_w, 1.0), jnp.nan)  # empty rings: NaN
    far = jnp.nanmedian(prof[60:])
    half = far + 0.5 * (peak_val - far)
    below = jnp.where(jnp.isnan(prof), False, prof < half)
    r_half = edges[jnp.argmax(below) + 1]
    top = covered & (ang < 0.5 * r_half) & (lum > half)
    cen = jnp.sum(jnp.where(top[..., None], (wts * (lum - half))[..., None] * dirs, 0.0), axis=(0, 1))
    cen = jnp.where(jnp.linalg.norm(cen) > 0, cen, d0)
    d = cen / jnp.linalg.norm(cen)
    if value_at is not None:
        d = _mean_shift(d, value_at, jnp.asarray(3.0 * jnp.pi / h, dt))
    if direction is not None:
        d = direction / jnp.linalg.norm(direction)
    radius = region[1] if region is not None else jnp.clip(2.5 * r_half, 0.05, 1.0)
    ang = jnp.arccos(jnp.clip(dirs @ d, -1.0, 1.0))
    wc = jnp.where(ang <= radius, wts, 0.0)
    wa = jnp.where((ang > radius) & (ang <= 1.5 * radius), wts, 0.0)
    omega = jnp.sum(wc)
    bg = jnp.sum(wa[..., None] * img, (0, 1)) / jnp.maximum(jnp.sum(wa), jnp.finfo(dt).tiny)
    tot = jnp.sum(wc[..., None] * img, (0, 1)) - bg * omega
    peak = peak_at(d, k) - bg
    ratio = jnp.mean(peak) / jnp.mean(tot)
    sigma_plain = jnp.sqrt(1.0 / (4 * jnp.pi * ratio))
    # the model's ratio on the same cap/annulus, by 1-D quadrature in theta
    th = jnp.linspace(0.0, 1.5 * radius, 3001, dtype=dt)
    sin_w = jnp.sin(th) * (th[1] - th[0]) * 2 * jnp.pi
    cap_m = th <= radius
    ann_m = th > radius

    # the three functionals of the profile the ratio needs: its value at theta = 0, its integrals over the
    # annulus and over the cap (sin-weighted rectangle rule), made once outside the root find
    fm = moments(jnp.stack([jnp.zeros_like(th).at[0].set(1.0), jnp.where(ann_m, sin_w, 0.0),
                            jnp.where(cap_m, sin_w, 0.0)]), th)
    omega_ann, omega_cap = jnp.sum(jnp.where(ann_m, sin_w, 0.0)), jnp.sum(jnp.where(cap_m, sin_w, 0.0))

    def model_ratio(log_s):
        f0, f_ann, f_cap = fm(jnp.exp(log_s))
        bgm = f_ann / omega_ann
        return (f0 - bgm) / (f_cap - bgm * omega_cap)

    # model_ratio decreases with sigma: a root of model_ratio - ratio in log sigma in [log 1e-3, log 2]
    # by optimistix.Bisection (flip: positive at the lower end); outside the bracket, the nearer end.
    lo, hi = jnp.log(jnp.asarray(1e-3, dt)), jnp.log(jnp.asarray(2.0, dt))
    sol = optx.root_find(lambda ls, _: model_ratio(ls) - ratio, optx.Bisection(rtol=1e-12, atol=1e-12, flip=True),
                         0.5 * (lo + hi), options=dict(lower=lo, upper=hi), max_steps=100, throw=False)
    sigma = jnp.exp(sol.value)
    return SourceEstimate(d, tot, peak, bg, radius, sigma, sigma_plain, sol.stats["num_steps"])


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
    refine_mu: bool = True,
    search_pixels: int | None = 40000,
    key: jax.Array | None = None,
    max_steps: int = 200,
    rtol: float | None = None,
    atol: float | None = None,
    chunk: int = 4096,
    lighting_method: str = "sh",
    dual_height: int | None = None,
    throw: bool = False,
) -> FactorizationResult:
    """Recover BRDF and lighting together (R&H sec. 6.3; module docstring).

    Stage 1 minimizes the profiled eq.-25 residual over $\\mu$ by a 9-point
    grid in $\\log(\\mu - 1)$ and the polynomial through 9 Chebyshev points on the best value's bracket (18
    evaluations; none with `fresnel=False`), each evaluation running a
    per-channel `optimistix.GoldenSearch` over $K_s$; `find_source` then gives
    $\\sigma$ (eq. 26, `optimistix.Bisection`); `refine` minimizes the
    profiled residual of the joint model over $(K_s, \\sigma)$ with $\\mu$ fixed
    (zooming grids in $\\log\\sigma$, a `GoldenSearch` over $K_s$ per channel).

    **Arguments:**

    - `obs`: `Observations` of a homogeneous object. Visibility terms (R&H
      sec. 6.4) are used when present: `transfer` and `reflected_visibility`
      in every eq.-25 solve, and `fast_visibility` for the source of the
      refinement (its one column, or of several the one whose shadow fits
      the data best at the stage-1 parameters), so its rows are those of
      `jaxsh.practical_terms` with that shadow. Sharded pixels
      (`shard_observations`): the passes over all pixels run on each device's
      pixels (the blocks summed by a `psum`, the rows kept where the pixels
      are) and `fitted` is sharded like them; the searches' subset is gathered
      (docs/howto_scale.md).
    - `lmax`: the lighting cutoff $l^*$ (>= 3; R&H use 12).
    - `fresnel`: fit $\\mu$ (False: $F = 1$, metals).
    - `find_sigma`, `region`: estimate σ from the brightest compact source of
      the recovered lighting (or inside the user's `region = (direction,
      angular_radius)`), eq. 26.
    - `refine`: joint refinement of $(K_s, \\sigma)$ and the lighting, with the
      lighting modelled as slow SH + the found source (needs `find_sigma`).
    - `refine_mu`: with `refine` and Fresnel, $\\mu$ is searched again on the
      joint model (`_joint_mu_search`: 9 Chebyshev points of $\\log(\\mu - 1)$ within
      0.75 of the stage-1 value, $(K_s, \\sigma)$ re-searched at each, and their
      interpolant's minimum), then the first stage, the source and the refinement are
      redone at the new $\\mu$, and $\\mu$'s standard error comes from that
      profile. Stage 1 models the lighting as $l \\le l^*$ SH only, and a
      bright compact source (a sun) biases its $\\mu$: on
      `bench_inverse.py`'s capture (3 × 256², rendered by the reference
      renderer, 1 % noise) the errors of $K_s/(K_d+K_s)$, $\\mu$, $\\sigma$
      are 7.5 %, 9.5 %, 2.5 % without it and about 1 %, 0.5 %, 0.1 % with it;
      on noise-free images of the fitted model under a probe and a sun,
      stage 1 gives $\\mu$ 1.36 for 1.6 and $K_s$ 40 % low. It costs 9
      evaluations of the refinement's search on the subset (`docs/performance.md`),
      9 more when the minimum falls on the edge of their window (then centred
      there once).
      `False`: stage 1's $\\mu$ (R&H's algorithm). With `lighting_method="sh"`
      on either path (a `MirrorTable` of the search subset, or direct sums
      when the subset is too large for one); with `"dual"` the same (a table
      of the subset is then made for it), from the source found on the dual
      image (its direction from the image's SH projection, `_dual_source`),
      and stage 1 and the source are then redone on the dual image at the new
      $\\mu$. On 3-view spheres under a sun (`sphere_capture`,
      $K_s/(K_d+K_s)$ 0.6 / 0.7 / 0.8, μ 1.6, σ 0.12, $l^*$ = 12, 1 % noise)
      the dual path's μ was 1.21 at 32² and 1.45 at 64² with stage 1's, and
      1.589 and 1.594 with this search; on `bench_inverse.py`'s capture
      (3 × 256², truth μ 1.6) 1.329 and 1.590 ($K_s$ 15 % low and within 2 %),
      at 1.19 s against 0.58 s warm (first calls 11.1 s and 9.7 s).
    - `search_pixels`: the searches use a random subset of this many pixels
      (None: all); the final solve uses all pixels. `key`: PRNG key (default
      `jax.random.PRNGKey(0)`); the subset is NumPy's
      `default_rng(key data).choice(n, search_pixels, replace=False)` over the
      samples of positive weight, drawn on the host. Memory:
      with `fresnel`, the μ search holds the subset's harmonics to degree
      2·`lmax` and, contiguous, to `lmax` (8·((2·`lmax`+1)² + (`lmax`+1)²) bytes per sample: 254 MB for
      40,000 samples at `lmax` 12); where that would exceed 512 MB it forms each
      candidate's blocks by direct sums instead (same result, slower).
    - `max_steps`, `rtol`, `atol`: the refinement's search in
      $t = \\log\\sigma$: at most `max_steps` grids, until their spacing is
      within `atol + rtol |t|` (tolerances default to 1e-7).
    - `chunk`: pixels per chunk of the normal-equation accumulation.
    - `lighting_method`: the inverse lighting inside the first stage's
      objective. `"sh"` (default): the SH coefficients of eq. 25 to `lmax`,
      and σ from them (`find_source`). `"dual"`: the paper's choice for its
      spheres (sec. 6.3, "Results"): the dual angular / frequency-space
      method of fig. 8 (`inverse_lighting_dual`, without `nonneg`) on a
      `dual_height` × 2·`dual_height` lat-long grid, and σ from eq. 26 on
      its angular image (no band limit; module `_factorize_dual`). Convex
      objects only (`obs.transfer` must be None, as in the paper).
    - `dual_height`: the grid of the dual image inside the search. Each
      texel's value is a free unknown fitted to the pixels whose mirror
      direction falls in it, so a texel needs many pixels (a texel with one
      pixel fits it exactly and says nothing about the BRDF). Once the BRDF
      is found, the returned image (`dual`) and eq. 26 use a grid twice as
      fine (4 samples per texel: the source's direction and peak need the
      resolution, measured 0.08 rad off on the search grid, 0.02 on the
      finer one). Default (None): the largest height
      with at least 16 samples per texel, $\\lfloor\\sqrt{N/32}\\rfloor$ for
      $N$ samples of positive weight (used by the search: weight-0 padding does
      not move the grid), clipped to [8, 64] (7,980 samples:
      15; measured on a 64² 3-view sphere: $K_s$ 5–7 % low and $\\mu$ 6 %
      low, as the paper's fig. 11 finds under unknown lighting; at height 32,
      about 4 samples per texel, $K_s$ 13 % and $\\mu$ 19 % low). At least 5:
      the 4 × 8 grid's quadrature does not integrate the $l \\le 2$ harmonics
      exactly (max $|PY - I|$ 0.094; below 2e-15 from 5 on).
    - `throw`: raise `solvers.SolveError` unless the status is `converged`.

    **Returns:** `FactorizationResult` ($K_d + K_s = 1$ per channel; the
    lighting carries the scale). Float32 observations are solved in float64
    (which must be enabled) and the result is returned in float32.
    """
    if not isinstance(obs, Observations):
        raise ValueError(f"`obs` must be an Observations, got {type(obs).__name__}")
    lmax = check_int(lmax, "lmax", lo=0)
    max_steps, chunk = check_int(max_steps, "max_steps"), check_int(chunk, "chunk")
    fresnel, find_sigma = check_bool(fresnel, "fresnel"), check_bool(find_sigma, "find_sigma")
    refine, refine_mu = check_bool(refine, "refine"), check_bool(refine_mu, "refine_mu")
    search_pixels = None if search_pixels is None else check_int(search_pixels, "search_pixels")
    if lmax < 3:
        raise ValueError(f"`lmax` must be >= 3 for factorization, got {lmax}")
    if search_pixels is not None and search_pixels < jaxsh.num_coeffs(lmax) + 4:
        # fewer samples than the search's unknowns (the lighting's coefficients, K_s, mu, sigma, the source):
        # search_pixels=5 gave K_s 0.94 for 0.3 with status converged
        raise ValueError(f"`search_pixels` must be at least (lmax + 1)^2 + 4 = {jaxsh.num_coeffs(lmax) + 4} (the "
                         f"search's unknowns at lmax {lmax}), or None, got {search_pixels}")
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if tol is not None:
            check_float(tol, name)
    if key is not None and not (isinstance(key, (jax.Array, np.ndarray)) and (
            jnp.issubdtype(key.dtype, jax.dtypes.prng_key) or (key.dtype == np.uint32 and key.shape == (2,)))):
        raise ValueError(f"`key` must be a JAX PRNG key (jax.random.key or PRNGKey) or None, got {key!r}")
    _check_region_arg(region)
    if refine and not find_sigma:
        raise ValueError("`refine=True` needs `find_sigma=True` (the refinement models the found source)")
    if lighting_method not in ("sh", "dual"):
        raise ValueError(f"`lighting_method` must be 'sh' or 'dual', got {lighting_method!r}")
    if dual_height is not None:
        dual_height = check_int(dual_height, "dual_height", lo=5)
    if lighting_method == "dual" and obs.transfer is not None:
        raise ValueError("factorize(lighting_method='dual'): concave objects (`obs.transfer` given) are not supported "
                         "(R&H sec. 6.4: the diffuse term no longer depends on 9 coefficients); use 'sh'")
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
                                    refine_mu=refine_mu, search_pixels=search_pixels, key=key, max_steps=max_steps, rtol=rtol, atol=atol,
                                    chunk=chunk, lighting_method=lighting_method, dual_height=dual_height)
        down = obs.values.dtype
        return finish(jax.tree_util.tree_map(lambda a: a.astype(down) if a.dtype == jnp.float64 else a, res), throw)
    dt = obs.values.dtype
    f64 = dt == jnp.float64
    rcond = 1e-12 if f64 else 1e-6
    # sharded pixels (`shard_observations`): the passes over all pixels run on each device's pixels, their rows stay
    # there (the search subset, at most `search_pixels`, is gathered: docs/howto_scale.md)
    where = pixel_sharding(obs.normals)
    rtol = (1e-7 if f64 else 1e-5) if rtol is None else float(rtol)
    atol = (1e-7 if f64 else 1e-5) if atol is None else float(atol)
    sub = obs
    # samples of positive weight (weight-0 padding, e.g. `shard_observations`, is never drawn nor counted)
    # (on the host when the weights are: each eager jnp op here was a compilation of its own, ~1 s in all)
    w_host = np.asarray(obs.weights) if getattr(obs.weights, "is_fully_addressable", True) else None
    n_pos = int(np.count_nonzero(w_host > 0)) if w_host is not None else int(jnp.sum(obs.weights > 0))
    if search_pixels is not None and n_pos > int(search_pixels):
        pos = np.flatnonzero(w_host > 0) if w_host is not None else np.asarray(jnp.nonzero(obs.weights > 0, size=n_pos)[0])
        idx = np.sort(pos[_draw_without_replacement(key, n_pos, int(search_pixels))])
        sub = obs.subset(idx)
    if lighting_method == "dual" and dual_height is None:
        # from the samples of positive weight: padding (`shard_observations`, `pad_observations`) must not move the
        # grid (one padding sample took the height from 22 to 24: mu 1.454 for 1.561 on 2 devices)
        dual_height = default_dual_height(n_pos if sub is obs else sub.n_samples)
    # Stage 1: nested 1-D searches over mu (batched grid, then Chebyshev points on the best value's bracket) and
    # ks (golden, per channel).
    curv_rss = None
    tab = None
    if fresnel:
        if lighting_method == "sh" and _table_fits(sub, lmax):
            tab = _mirror_table_jit(sub, lmax)

        def evaluate(t):  # the profiled relative RSS at the 9 values of `t`: one batch, one compiled program
            if lighting_method == "dual":
                return np.asarray(_mu_candidates_dual(sub, jnp.asarray(t, dt), dual_height))
            if tab is not None:
                return np.asarray(_golden_batch(_mu_blocks(tab, jnp.asarray(1.0 + np.exp(t), dt), lmax, rcond))[0])
            return np.asarray(_mu_candidates(sub, jnp.asarray(t, dt), lmax, chunk, rcond))

        t = np.linspace(*_MU_T_RANGE, 9)
        vals = evaluate(t)
        its1 = 9
        # all-NaN when the data carry no signal (black images): keep the centre, the status says no_signal
        centre = t[int(np.nanargmin(vals))] if np.any(np.isfinite(vals)) else t[4]
        step = t[1] - t[0]
        for _ in range(2):
            # the bracket of the grid's best value (its neighbours), kept inside stage 1's range (a zoom once reached
            # mu = 5.8 past its edge); the minimum of the interpolant through 9 Chebyshev points on it
            lo, hi = max(centre - step, _MU_T_RANGE[0]), min(centre + step, _MU_T_RANGE[1])
            t = _chebyshev_points(lo, hi)
            vals = evaluate(t)
            its1 += 9
            best, c2 = _interpolant_minimum(t, vals)
            if c2 is not None or best in _MU_T_RANGE or best not in (lo, hi):
                break
            centre = best  # the minimum at an end of the bracket inside the range: once more, centred there
        if c2 is not None and lighting_method == "sh":
            # curvature of the profiled RSS in t = log(mu - 1), scaled from the subset to all pixels (not of the dual
            # search's profile: that is another model's RSS than the refined one's whose residual scales it; the
            # error came out 9-12x the spread of mu over noise draws, so with "dual" std_errors.mu is inf)
            bb_sub = float(_weighted_energy(sub.weights, sub.values))
            curv_rss = c2 * bb_sub * n_pos / (n_pos if sub is obs else sub.n_samples)
        mu = jax.device_put(np.asarray(1.0 + np.exp(best), dt))  # (`jnp.asarray` would compile a conversion)
    else:
        mu, its1, best = None, 0, None
    dual = None
    rows_obs = None  # the eq.-25 rows at the final mu of the pixels outside the search subset, for the refinement
    perm = None  # the orders of the all-pixel pass and of the refinement (`_subset_first`), with those rows
    win = None  # the joint mu search's first window's blocks when stage 1 takes its blocks from them
    blocks = (None, None)  # the eq.-25 blocks at the stage-1 mu on all pixels and on the subset, for the refinement
    if lighting_method == "dual":
        ks, golden_steps = _stage1_final_dual(obs, mu, dual_height)
        dual, res1 = _dual_stage1(obs, ks, mu, 2 * dual_height, lmax, rcond)
    elif tab is not None:
        # The final stage-1 solve reuses the compiled programs of the mu rounds: the blocks at mu (9 copies, the
        # rounds' batch) from the table when it holds all pixels, else from one pass over all pixels, which also
        # makes their rows for the refinement; then the same batched golden search. The subset's blocks at mu,
        # for the refinement, come from the rounds' program too.
        mu9 = _nine(mu)
        # with the joint mu search to come, stage 1 and its source are redone on all pixels at the mu it finds:
        # here they only start it, from the subset's blocks (the all-pixel pass at this mu was 0.23 s, wasted)
        joint_mu = refine and find_sigma and refine_mu and mu is not None
        ts_win = _joint_window(best) if joint_mu else None
        if joint_mu and ts_win[4] == best:
            # the joint search's first window holds this mu in its middle: its batch (this mu first, the rest after)
            # serves stage 1 here and the search later (a batch of 9 copies of this mu was 61 ms more)
            win = _mu_blocks(tab, jax.device_put((1.0 + np.exp(ts_win[_WINDOW_ORDER])).astype(dt)), lmax, rcond)
            bl_obs = bl_sub = win
        elif sub is obs or joint_mu:
            bl_obs = bl_sub = _mu_blocks(tab, mu9, lmax, rcond)
        elif where is not None:
            # sharded pixels: the pass in the pixels' order on each device's pixels (their rows stay there, for the
            # refinement: `_joint_from_rows`), the subset's blocks at mu from its table
            bl_obs, rows_obs, _ = _all_pixel_blocks(obs, mu, lmax, chunk, rcond, refine and find_sigma, where=where)
            bl_sub = _mu_blocks(tab, mu9, lmax, rcond) if refine and find_sigma else None
        else:
            if refine and find_sigma:  # the subset's blocks from the same pass (`_subset_first`)
                perm = _subset_first(obs.n_samples, idx, chunk)
                bl_obs, rows_obs, bl_sub = _all_pixel_blocks(obs, mu, lmax, chunk, rcond, True, perm[0], perm[1],
                                                             tab)
            else:
                bl_obs, _, bl_sub = _all_pixel_blocks(obs, mu, lmax, chunk, rcond, False)
        _, ks, golden_steps = _golden_batch(bl_obs)
        blocks = (bl_obs, bl_sub)
        region_c = None if region is None else check_region(region, 128, dt)
        res1, src = _lighting_and_source(bl_obs, ks, lmax, rcond, region_c, find_sigma)
    else:
        ks, res1, golden_steps, bl_obs = _stage1_final(obs, mu, lmax, chunk, rcond, where)
        blocks = (bl_obs, bl_obs if sub is obs else None)
    filtered = res1.coeffs
    # constants made on the host and sent (`jnp.full_like`, `jnp.asarray` each compile a small program at first use)
    inf = jax.device_put(np.full(ks.shape, np.inf, ks.dtype))
    inf0 = jax.device_put(np.asarray(np.inf, dt))
    std_inf = TorranceSparrow.unchecked(inf, inf, None if mu is None else inf0, inf0)
    zero = jax.device_put(0)
    stats = {"num_mu_candidates": jax.device_put(its1), "num_sigma_candidates": zero, "num_steps_golden": golden_steps,
             "num_steps_bisection": zero, "n_obs": res1.stats["n_obs"]}

    def result(brdf, lighting, source, std, status, iterations, rms, rel, stats, fitted=None):
        if fitted is None:  # eq. 25 of the first stage
            fitted = _stage1_fitted(obs, mu, ks, filtered, lmax, chunk, where)
        # a parameter stopped at its search range's end: flagged, and its standard error infinite (as `fit_brdf`)
        bound = _at_bound(best, None if source is None else brdf.sigma)
        stats["at_bound"] = {k_: jax.device_put(np.bool_(v)) for k_, v in bound.items()}
        if bound["mu"] or bound["sigma"]:
            std = TorranceSparrow.unchecked(std.kd, std.ks, inf0 if bound["mu"] else std.mu,
                                            inf0 if bound["sigma"] else std.sigma)
        res = FactorizationResult(brdf=brdf, lighting=lighting, filtered_sh=filtered, source=source, std_errors=std,
                                  status=status, iterations=jnp.asarray(iterations), rms=rms, rel_rms=rel, stats=stats,
                                  dual=dual, fitted=fitted)
        return finish(res, throw)

    if not find_sigma:
        brdf = TorranceSparrow.unchecked(1.0 - ks, ks, mu, jnp.asarray(jnp.nan, dt))
        return result(brdf, res1.lighting, None, std_inf, res1.status, jnp.asarray(its1), res1.rms, res1.rel_rms, stats)
    if dual is None and tab is None:
        src = find_source.__wrapped__(filtered, region=region)
    elif dual is not None:
        src = _dual_source(dual, filtered, region, dual_height, dt, refine)
    stats["num_steps_bisection"] = src.num_steps
    if not refine:
        brdf = TorranceSparrow.unchecked(1.0 - ks, ks, mu, src.sigma)
        return result(brdf, res1.lighting, src, std_inf, res1.status, jnp.asarray(its1), res1.rms, res1.rel_rms, stats)
    if refine_mu and mu is not None and tab is not None and blocks[1] is not None:
        # mu again, on the joint model (`_joint_mu_search`; log(sigma) by at most `_MU_JOINT_SIGMA_GRIDS` grids inside
        # it, the final refinement keeps rtol, atol), then the first stage, the source and the blocks at the new mu
        jt1 = _joint_from_table(sub, tab, blocks[1], mu, lmax, _K0())
        column = _source_column(jt1, sub.fast_visibility, mu, ks, src.direction, src.sigma, lmax)
        t2, c2, n_mu = _joint_mu_search(sub, tab, lmax, best, ks, src.direction, src.sigma,
                                        min(int(max_steps), _MU_JOINT_SIGMA_GRIDS), rtol, atol, rcond, column,
                                        first=win)
        # the profile's curvature in t: of RSS / data energy on the subset (`_refine_search`'s value), so times
        # the subset's energy, then scaled to all positive samples (as stage 1's; it lacked the energy: se_mu was
        # sqrt(data energy) times too large, 126x in a Monte Carlo, and counted weight-0 samples of `sub is obs`)
        curv_rss = None if c2 is None else c2 * float(_weighted_energy(sub.weights, sub.values)) * n_pos / (
            n_pos if sub is obs else sub.n_samples)
        its1 += n_mu
        stats["num_mu_candidates"] = jax.device_put(its1)
        best = t2
        mu = jax.device_put(np.asarray(1.0 + np.exp(t2), dt))
        mu9 = _nine(mu)
        if sub is obs:
            blocks = (_mu_blocks(tab, mu9, lmax, rcond),) * 2
        elif where is not None:  # sharded pixels (as in stage 1 above)
            bl_obs, rows_obs, _ = _all_pixel_blocks(obs, mu, lmax, chunk, rcond, True, where=where)
            blocks = (bl_obs, _mu_blocks(tab, mu9, lmax, rcond))
        else:
            perm = _subset_first(obs.n_samples, idx, chunk)
            bl_obs, rows_obs, bl_sub = _all_pixel_blocks(obs, mu, lmax, chunk, rcond, True, perm[0], perm[1], tab)
            blocks = (bl_obs, bl_sub)
        _, ks, golden_steps = _golden_batch(blocks[0])
        res1, src = _lighting_and_source(blocks[0], ks, lmax, rcond, region_c, True)
        filtered = res1.coeffs
        stats["num_steps_golden"], stats["n_obs"] = golden_steps, res1.stats["n_obs"]
        stats["num_steps_bisection"] = src.num_steps
    elif refine_mu and mu is not None and tab is None:
        # the same search by direct sums (a search subset too large for a `MirrorTable`, or the dual path, whose
        # source came from the dual image), then stage 1 and the source again at the new mu (`_stage1_final` and
        # `find_source`, or the dual stage 1 and eq. 26 on its image, as above on each path)
        if dual is not None and _table_fits(sub, lmax):
            # the dual path's search on the joint model from the subset's `MirrorTable`, as on the SH path (by
            # direct sums it took 1.45 s of a warm 2.5 s call on `bench_inverse.py`'s capture)
            tab = _mirror_table_jit(sub, lmax)
            jt1 = _joint_from_table(sub, tab, _mu_blocks(tab, _nine(mu), lmax, rcond), mu, lmax, _K0())
        else:
            jt1 = _joint_jit(sub, None, mu, lmax, chunk, rcond, None)
        column = _source_column(jt1, sub.fast_visibility, mu, ks, src.direction, src.sigma, lmax)
        t2, c2, n_mu = _joint_mu_search(sub, tab, lmax, best, ks, src.direction, src.sigma,
                                        min(int(max_steps), _MU_JOINT_SIGMA_GRIDS), rtol, atol, rcond, column, chunk)
        curv_rss = None if c2 is None else c2 * float(_weighted_energy(sub.weights, sub.values)) * n_pos / (
            n_pos if sub is obs else sub.n_samples)  # (as on the table path above)
        its1 += n_mu
        stats["num_mu_candidates"] = jax.device_put(its1)
        best = t2
        mu = jax.device_put(np.asarray(1.0 + np.exp(t2), dt))
        if dual is None:
            ks, res1, golden_steps, bl_obs = _stage1_final(obs, mu, lmax, chunk, rcond, where)
            blocks = (bl_obs, bl_obs if sub is obs else None)
            filtered = res1.coeffs
            src = find_source.__wrapped__(filtered, region=region)
        else:
            ks, golden_steps = _stage1_final_dual(obs, mu, dual_height)
            dual, res1 = _dual_stage1(obs, ks, mu, 2 * dual_height, lmax, rcond)
            filtered = res1.coeffs
            src = _dual_source(dual, filtered, region, dual_height, dt, True)
            if tab is not None:  # the refinement's subset rows from the table too, at the new mu
                blocks = (None, _mu_blocks(tab, _nine(mu), lmax, rcond))
        stats["num_steps_golden"], stats["n_obs"] = golden_steps, res1.stats["n_obs"]
        stats["num_steps_bisection"] = src.num_steps
    out = _refine(sub, obs, lmax, mu, ks, src.direction, src.sigma, int(max_steps), rtol, atol, chunk, rcond, blocks, tab,
                  rows_obs, perm, where)
    ks, sigma, lighting, se_ks, se_sigma, st_nm, its2, rms, rel, data_ss, fitted, bl_final = out
    st1 = res1.status
    if dual is not None:
        # the refinement solves for the eq.-25 lighting (plus the source), whose determinacy the dual stage 1's
        # status does not report (its texels are free unknowns, the uncovered ones the l <= 2 field): one valid
        # pixel came back `converged`
        st1 = _eq25_status(bl_final, ks, lmax, rcond, st1)
    kd, status, iterations = _final_status(ks, sigma, rms, data_ss, st_nm, its1, its2, st1)
    brdf = TorranceSparrow.unchecked(kd, ks, mu, sigma)
    se_mu = None
    if mu is not None:
        se_mu = jnp.asarray(jnp.inf, dt)
        if curv_rss is not None:
            # profile curvature: var(t) = s^2 / (RSS''/2), s^2 = RSS / (n - p); mu = 1 + e^t
            nobs = n_pos * obs.n_channels
            s2 = float(rms) ** 2 * nobs / max(nobs - (jaxsh.num_coeffs(lmax) + 1) * obs.n_channels - 2 * obs.n_channels - 2, 1)
            se_mu = jnp.asarray(np.sqrt(s2 / (0.5 * curv_rss)) * (float(mu) - 1.0), dt)
    std = TorranceSparrow.unchecked(se_ks, se_ks, se_mu, se_sigma)
    stats["num_sigma_candidates"] = its2
    return result(brdf, lighting, src, std, status, iterations, rms, rel, stats, fitted)


@jaxsh.jit
def _final_status(ks, sigma, rms, data_ss, st_nm, its1, its2, st1):
    """K_d, the status and the step count of a refined factorization (one program: eagerly, each op compiled).
    `st1`: the status of stage 1's eq.-25 solve at the final mu: the refinement solves for the same lighting
    (plus the source), so lighting the data do not determine there is not determined by it either (6 valid
    pixels: stage 1 `ill_conditioned`, the refinement `converged` with rms 0 and zero standard errors)."""
    finite = jnp.all(jnp.isfinite(ks)) & jnp.isfinite(sigma) & jnp.isfinite(rms)
    status = worst(Status.where(finite, Status.converged, Status.nonfinite), signal_status(data_ss), st_nm, st1)
    return 1.0 - ks, status, its1 + its2


def _draw_without_replacement(key, n: int, m: int) -> np.ndarray:
    """`m` distinct indices of `range(n)`, drawn on the host (`host_rng`: NumPy seeded with the key's data).

    `jax.random.choice(key, n, (m,), replace=False)` compiled its shuffle (sorts of `n` random keys) into a
    program of its own, ~0.5 s of a first call for a draw that takes milliseconds in NumPy. Deterministic for a
    given key (and NumPy's `Generator.choice`)."""
    return host_rng(key).choice(n, m, replace=False)


@jaxsh.jit
def _weighted_energy(w, b):
    return jnp.sum(w[:, None] * b * b)


class _Stage1(eqx.Module):
    """What the rest of `factorize` reads of the first stage's lighting (a `LightingResult`'s fields)."""

    coeffs: Array
    lighting: Lighting
    status: Status
    rms: Array
    rel_rms: Array
    stats: dict


def _dual_stage1(obs, ks, mu, h, lmax, rcond):
    """The dual lighting at the stage-1 BRDF (`inverse_lighting_dual`, no `nonneg`) and its SH projection."""
    kd = 1.0 - ks
    img, l9, cov, iters, error, lin = _dual(obs, kd, ks, mu, h, False, 0, 0.0, rcond)
    dual = _dual_finish(obs, kd, ks, mu, img, l9, cov, iters, error, lin, h, False, 0, 0.0)
    coeffs = jaxsh.project_latlong(dual.image, lmax, allow_aliasing=True)
    return dual, _Stage1(coeffs, Lighting(coeffs), dual.status, dual.rms, dual.rel_rms, {"n_obs": dual.stats["n_obs"]})


@jaxsh.jit
def _mu_candidates(sub, t, lmax, chunk, rcond):
    """Profiled relative RSS (best ks per channel) for each candidate log(mu - 1)."""
    dt = sub.values.dtype
    ones = jnp.ones(((lmax + 1) ** 2,), dt)

    def one(ti):
        bl = _blocks(sub, 1.0 + jnp.exp(ti), lmax, chunk, rcond)
        _, rss, _ = _golden_ks(bl, ones, 1e-11, 1e-11, 100)  # the tolerances of the table path (`_golden_batch`)
        return jnp.sum(rss) / jnp.sum(bl.g.bb)

    return jax.lax.map(one, t)


# `factorize` searches mu on a `MirrorTable` of the subset when it takes at most this many bytes (40,000 samples at
# l* = 12: 254 MB), otherwise by `accumulate_gram` per candidate (`_mu_candidates`)
_TABLE_BYTES = 512 * 2**20


def _nine(mu):
    """Nine copies of `mu` on the device: the batch of `_mu_blocks`' μ rounds, so that one μ reuses their program."""
    return jax.device_put(np.full((9,), np.asarray(mu)))


def _table_fits(o: Observations, lmax: int) -> bool:
    """Whether the `MirrorTable` of `o` (harmonics to degree 2 `lmax` and, contiguous, to `lmax`) fits
    `_TABLE_BYTES`."""
    return o.n_samples * ((2 * lmax + 1) ** 2 + (lmax + 1) ** 2) * 8 <= _TABLE_BYTES


@jaxsh.jit
def _mirror_table_jit(o: Observations, lmax: int) -> MirrorTable:
    return mirror_table(o.normals, o.views, o.values, o.weights, o.transfer, o.reflected_visibility, lmax)


@jaxsh.jit
def _mu_blocks(tab: MirrorTable, mus, lmax, rcond) -> _Blocks:
    """The eq.-25 blocks at each Fresnel index of `mus` `(K,)` from a `MirrorTable` (`grams_at_mus`), with the
    pseudo-inverses of their l > 2 blocks: a `_Blocks` whose fields have a leading K."""
    g = grams_at_mus(tab, mus, lmax)
    return _Blocks(g, _half_pinv(g.ss[:, 9:, 9:], rcond))


@jaxsh.jit
def _golden_batch(bl: _Blocks):
    """`_golden_ks` (tolerances 1e-11) for each of a batch of `_Blocks` (leading K): the profiled relative RSS
    of each `(K,)`, and K_s `(C,)` and the golden steps `(C,)` of the first. One program serves the mu rounds
    and the final stage-1 solve (`factorize`; the final blocks come batched like the rounds')."""
    ones = jnp.ones((bl.g.ss.shape[-1],), bl.g.ss.dtype)
    ks, rss, steps = _golden_search(jax.vmap(lambda b: _golden_parts(b, ones))(bl), 1e-11, 1e-11, 100)
    return jnp.sum(rss, -1) / jnp.sum(bl.g.bb, -1), ks[0], steps[0]


@jaxsh.jit
def _all_pixel_blocks(obs: Observations, mu, lmax: int, chunk: int, rcond, rows: bool, order=None,
                      split: int | None = None, tab: MirrorTable | None = None, where=None):
    """The eq.-25 blocks at `mu` on all pixels (`accumulate_gram`, one pass), with pinv, repeated to the batch
    of 9 that `_golden_batch` was compiled for (`_mu_blocks`' layout), and with `rows` the pixels' eq.-25 rows
    `((9, N + pad), (n, N + pad))` from the same pass (else None). With `order` and `split` (`_subset_first`: the
    search subset first, padded to `split` chunks), the pixels are taken in that order, the subset's blocks come
    from the same pass (else None), batched alike (the refinement's search needs them at the final mu, and a
    `_mu_blocks` call for that one mu took 61 ms at 3 × 256², 40,000 samples), and the rows are those of the
    chunks after the subset's (`_joint_padded` takes the subset's from its table; at 3 × 256², the pass alone took
    216-219 ms so, 239-245 ms with every chunk's rows, 157-166 ms without rows). With `tab`, the subset's
    `MirrorTable` (at least `chunk` pixels), the subset chunks' rows are taken from it, not evaluated
    (`accumulate_gram`'s `known`; `_all_pixel_blocks` 226 against 252 ms at 3 × 256², min of 9).
    With `where` (`pixel_sharding` of sharded pixels; no `order`, `split` or `tab`), each device makes the blocks
    and rows of its own pixels (`sum_and_columns_over_pixels`): the blocks added over the devices, the rows
    `((9, N), (n, N))` left sharded, in the pixels' order and without padding columns (`_joint_from_rows`).
    Returns `(blocks, rows or None, subset blocks or None)`."""

    def batched(g):
        bl = _Blocks(g, _half_pinv(g.ss[9:, 9:], rcond))
        return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (9,) + jnp.shape(a)), bl)

    if where is not None:
        if order is not None or split is not None or tab is not None:
            raise ValueError("`_all_pixel_blocks(where=...)` takes the pixels in their order: no `order`, `split`, `tab`")

        def local(n, v, b, w, t, r, mu_):
            out = accumulate_gram(n, v, b, w, t, r, mu_, None, lmax, chunk, rows)
            if not rows:
                return out, ()
            g, (rd, rs) = out
            return g, (rd[:, : n.shape[0]], rs[:, : n.shape[0]])  # the chunk padding's columns cut: the device's pixels

        g, cols = sum_and_columns_over_pixels(local, where, _pixel_fields(obs), (mu,))
        return batched(g), (cols if rows else None), None
    o = obs if order is None else _permuted(obs, order)
    known = None
    if tab is not None and split is not None and tab.ys.shape[1] >= chunk:
        npx = tab.ys.shape[1]
        known = (tab.d[:npx], tab.ys, _table_factor(tab, npx, mu))
    out = accumulate_gram(o.normals, o.views, o.values, o.weights, o.transfer, o.reflected_visibility,
                          mu, None, lmax, chunk, rows, split, split if rows and split is not None else 0, known)
    out = out if isinstance(out, tuple) else (out,)
    g, rows_obs, g_sub = out[0], (out[1] if rows else None), (out[-1] if split is not None else None)
    return batched(g), rows_obs, (None if g_sub is None else batched(g_sub))


def _subset_first(n: int, idx: np.ndarray, chunk: int):
    """The pixel order of `_all_pixel_blocks` that puts the search subset first, and that of the refinement's
    `_Joint` on all pixels: `(order, split, joint, pos)`.

    `order` `(split · chunk + N - len(idx),)`: the subset's indices `idx` filling `split` whole chunks, the index `n`
    (a weight-0 pixel, `_permuted`) first in the last of them (where the subset does not fill it: so its pixels
    are the last columns of the subset's table, `accumulate_gram`'s `known`), then the other pixels in their
    order; `split` the subset's chunks;
    `joint` `(N,)`: `order` without that filler (the subset, whose rows come from its table, then the other
    pixels, whose rows come from the pass: `_joint_padded`); `pos` `(n,)`: where each pixel is in `joint`
    (`joint[pos] = arange(n)`). The arrays are device arrays."""
    split = -(-len(idx) // chunk)
    others = np.ones(n, bool)
    others[idx] = False
    rest = np.flatnonzero(others)
    full = len(idx) // chunk * chunk
    order = np.concatenate([idx[:full], np.full(split * chunk - len(idx), n), idx[full:], rest]).astype(np.int32)
    joint = np.concatenate([idx, rest]).astype(np.int32)
    pos = np.empty(n, np.int32)
    pos[joint] = np.arange(n, dtype=np.int32)
    return jax.device_put(order), split, jax.device_put(joint), jax.device_put(pos)


def _permuted(o: Observations, order) -> Observations:
    """`o`'s samples in the order `order` (`_subset_first`); the index `o.n_samples` is a sample of weight 0 with
    +z normal and view (valid unit vectors) and zero data, visibility and transfer."""
    up = np.zeros(3)
    up[2] = 1.0

    def take(a, fill=0.0):
        if a is None:
            return None
        one = jnp.broadcast_to(jnp.asarray(fill, a.dtype), (1,) + a.shape[1:])
        return jnp.concatenate([a, one])[order]

    return Observations(take(o.normals, up), take(o.views, up), take(o.values), take(o.weights), take(o.transfer),
                        take(o.fast_visibility), take(o.reflected_visibility), take(o.texel, 0), take(o.view_index, 0),
                        take(o.pixel_index, 0), o.image_shapes, o.n_texels)


@jaxsh.jit(optimize=False)
def _lighting_and_source(bl: _Blocks, ks, lmax: int, rcond, region, source: bool):
    """The eq.-25 lighting at the stage-1 BRDF from the first of the batched blocks `bl`, and (with `source`)
    the source and sigma of eq. 26 in it (`find_source` on a 128 x 256 map): one program. Only what `factorize`
    reads of the lighting leaves the program (`_Stage1`), so XLA drops the rest of `LightingResult` (standard
    errors, singular values, band SNR): 122 -> 107 fusions."""
    g = _first(bl).g
    res = lighting_from_gram(g, 1.0 - ks, ks, lmax, 0.0, rcond)
    stage1 = _Stage1(res.coeffs, res.lighting, res.status, res.rms, res.rel_rms, {"n_obs": res.stats["n_obs"]})
    return stage1, (_find_source(res.coeffs, region, 128, lmax) if source else None)


def _first(bl: _Blocks) -> _Blocks:
    """The first of batched `_Blocks` (leading K, `_mu_blocks`), or `bl` itself when it is not batched."""
    return jax.tree_util.tree_map(lambda a: a[0], bl) if bl.g.dd.ndim == 3 else bl


@jaxsh.jit
def _stage1_final(obs, mu, lmax, chunk, rcond, where=None):
    """K_s per channel at the chosen mu on all pixels, the eq.-25 lighting there and the blocks at mu, by direct
    sums (`factorize` without a `MirrorTable`: `fresnel=False`, or a search subset too large for one); `where`:
    `pixel_sharding` (the sums on each device's pixels)."""
    ones = jnp.ones(((lmax + 1) ** 2,), obs.values.dtype)
    bl = _blocks(obs, mu, lmax, chunk, rcond, where)
    ks, _, steps = _golden_ks(bl, ones, 1e-11, 1e-11, 100)
    return ks, lighting_from_gram(bl.g, 1.0 - ks, ks, lmax, 0.0, rcond), steps, bl


class _Joint(eqx.Module):
    """Everything the refinement objective needs for one pixel set (mu fixed)."""

    bl: _Blocks
    # The diffuse rows `rows_d` (9, N) and the (unfiltered) specular rows `rows_s` (n, N) of eq. 25, pixels last:
    # `rows_s @ x` is a plain matrix-vector product (`rows.T @ x` on an (N, 9 + n) array made XLA copy a transpose
    # per evaluation inside the former Nelder-Mead loop, 57 MB at 40,000 samples: 10.5 ms per step against 3.7 ms
    # for its two evaluations). `f` (N,) or None: a factor of every specular row's pixel, applied to the vectors
    # they multiply (`_rows_dot`, `_coef_rows`): on the search subset the specular rows are the `MirrorTable`'s
    # harmonics `ys`, shared by every mu, and `f` is mu's Fresnel factor times the visibility (a copy of the rows
    # per mu was 57 MB written, 19-25 ms, eleven times in a call). `rows_d2`, `rows_s2` `(9, N2)`, `(n, N2)` or
    # None: the rows of a second segment of pixels, without a factor, after the first segment's `N1` columns (the
    # per-pixel fields span both, `N = N1 + N2`): on all pixels, the search subset's rows come from its table
    # (`_joint_padded`), and only the other pixels' from the all-pixel pass.
    rows_d: Array
    rows_s: Array
    f: Array | None
    w: Array
    b: Array
    normals: Array
    views: Array
    fvis: Array | None  # (N,) visibility of the found source (a column of `fast_visibility`), or None
    rows_d2: Array | None = None
    rows_s2: Array | None = None

    @property
    def rows(self) -> Array:
        """The rows of eq. 25 `(9 + n, N)`, stacked and with `f` applied (a new array: for checks, not for the search)."""
        first = jnp.concatenate([self.rows_d, self.rows_s if self.f is None else self.rows_s * self.f[None, :]], 0)
        if self.rows_d2 is None:
            return first
        return jnp.concatenate([first, jnp.concatenate([self.rows_d2, self.rows_s2], 0)], 1)


def _segments(jt: _Joint, x):
    """`x` `(..., N)` cut at the first segment's end: `(x1, x2)`, `x2` None without a second segment."""
    if jt.rows_d2 is None:
        return x, None
    n1 = jt.rows_d.shape[1]
    return x[..., :n1], x[..., n1:]


def _rows_dot(jt: _Joint, x):
    """`jt.rows @ x` for `x` `(N,)`, without forming the rows: `(9 + n,)`."""
    x1, x2 = _segments(jt, x)
    out = jnp.concatenate([jt.rows_d @ x1, jt.rows_s @ (x1 if jt.f is None else jt.f * x1)])
    return out if x2 is None else out + jnp.concatenate([jt.rows_d2 @ x2, jt.rows_s2 @ x2])


def _rows_dot_many(jt: _Joint, x):
    """`jt.rows @ x[t]` for each row of `x` `(T, N)`: `(T, 9 + n)`, as two `dot_general`s of the rows with `x`, the
    pixels contracted, rows first (per segment). XLA:CPU runs the product with `x` first (what `vmap` of a
    matrix-vector product, or `x @ rows.T`, or `rows @ x.T` became here) 2-3× slower: 16 vectors against
    178 × 40,000 rows, 11.7-13.3 ms against 4.8-5.4 ms (measured)."""
    x1, x2 = _segments(jt, x)
    xs = x1 if jt.f is None else x1 * jt.f[None, :]
    dims = (((1,), (1,)), ((), ()))
    out = jnp.concatenate([jax.lax.dot_general(jt.rows_d, x1, dims), jax.lax.dot_general(jt.rows_s, xs, dims)], 0)
    if x2 is not None:
        out = out + jnp.concatenate([jax.lax.dot_general(jt.rows_d2, x2, dims),
                                     jax.lax.dot_general(jt.rows_s2, x2, dims)], 0)
    return out.T


def _coef_rows(jt: _Joint, coef):
    """`coef @ jt.rows` for `coef` `(C, 9 + n)`, without forming the rows: `(C, N)`."""
    spec = coef[:, 9:] @ jt.rows_s
    out = coef[:, :9] @ jt.rows_d + (spec if jt.f is None else spec * jt.f[None, :])
    if jt.rows_d2 is None:
        return out
    return jnp.concatenate([out, coef[:, :9] @ jt.rows_d2 + coef[:, 9:] @ jt.rows_s2], 1)


def _joint(o: Observations, bl, mu, lmax, chunk, rcond, column) -> _Joint:
    """`_Joint` of `o`; `bl`: its eq.-25 blocks at `mu` when already formed (else None: formed here)."""
    bl = _blocks(o, mu, lmax, chunk, rcond) if bl is None else _first(bl)
    d, s = eq25_rows(o.normals, o.views, o.transfer, o.reflected_visibility, mu, None, lmax, coeffs_first=True)
    fvis = None if column is None else o.fast_visibility[:, column]
    return _Joint(bl, d, s, None, o.weights, o.values, o.normals, o.views, fvis)


class _SourceParts(eqx.Module):
    """The rows of a unit-energy delta source at `d` (eqs. 23, 24), in the parts that stay fixed in the refinement.

    `fvis` `(N,)` (`_Joint`): the source's visibility $V$ at each pixel (R&H sec. 6.4: "we check if these
    sources are shadowed"), or None (convex object, $V = 1$). Diffuse row `fd` $= V[\\cos\\theta_i > 0]\\cos\\theta_i$;
    specular row `amp * exp(-th2 / sigma^2) / (pi sigma^2)` $= F V [\\cos\\theta_i > 0]\\,T(\\theta_h)/(4\\cos\\theta_o)$;
    both zero where $\\cos\\theta_o \\le 0$: the rows of `jaxsh.practical_terms` for one fast source of unit
    energy with `fast_visibility=fvis[:, None]` (`tests/test_inverse.py`). With $\\mu$, `d` and the shadow fixed,
    only the specular row's lobe depends on σ, so `fd`, its sums with the slow rows and the data, `amp` and
    $\\theta_h^2$ are formed once per compiled call, and so are the σ- and $K_s$-free factors of the elimination
    (`_joint_rss`): with $P = \\mathrm{pinv}(SS_{22}) = H^TH$ (`_Blocks.h22`), `e_d` $= H\\,DS_{12}^T$,
    `e_s` $= H\\,SS_{12}^T$, `e_b` $= H\\,sb_2$ and `h_fd` $= H$ (the source's diffuse row against the
    $l > 2$ columns)."""

    fd: Array  # (N,)
    amp: Array  # (N,)
    th2: Array  # (N,) theta_h^2
    rows_fd: Array  # (9 + n,) rows @ (w fd)
    fd_fd: Array  # ()
    fd_b: Array  # (C,)
    e_d: Array  # (m, 9), m = n - 9
    e_s: Array  # (m, 9)
    e_b: Array  # (m, C)
    h_fd: Array  # (m,)


def _source_lobe(sp: _SourceParts, sigma):
    """The source's specular row at σ, `(N,)`: `amp` times the lobe $e^{-\\theta_h^2/\\sigma^2}/(\\pi\\sigma^2)$ (eq. 23)."""
    return sp.amp * (jnp.exp(-sp.th2 / sigma**2) / (jnp.pi * sigma**2))


def _source_parts(jt: _Joint, mu, d) -> _SourceParts:
    n, v = jt.normals, jt.views
    cos_o = jnp.sum(n * v, -1)
    vis = cos_o > 0
    cos_o = jnp.where(vis, cos_o, 1.0)
    f = jnp.ones_like(cos_o) if mu is None else jaxsh.fresnel_normalized(cos_o, mu)
    cos_i = n @ d
    lit = (cos_i > 0) & vis
    v_d = jnp.ones_like(cos_o) if jt.fvis is None else jt.fvis
    fd = jnp.where(lit, cos_i * v_d, 0.0)
    amp = jnp.where(lit, f * v_d / (4 * cos_o), 0.0)
    th2 = jaxsh.half_angle(d[None, :], v, n) ** 2
    wfd = jt.w * fd
    rows_fd = _rows_dot(jt, wfd)
    g, h = jt.bl.g, jt.bl.h22
    return _SourceParts(fd, amp, th2, rows_fd, jnp.sum(wfd * fd), wfd @ jt.b, h @ g.ds[:, 9:].T, h @ g.ss[:9, 9:].T,
                        h @ g.sb[9:], h @ rows_fd[18:])


def _joint_rss(jt: _Joint, sp: _SourceParts, ks, sigma, lmax, rows_fs=None):
    """RSS per channel of [slow SH filtered by sigma + delta source at d] for kd = 1 - ks (the source's rows
    from the precomputed `sp`: one pass over the rows per evaluation). Returns `rss (C,)`, `x1 (C, 10)` (the
    $l \\le 2$ lighting and the source's energy), `x2 (C, n - 9)` (the $l > 2$ lighting, unfiltered).

    The elimination of `_schur_rss` with the source's column, in the factored form of `_golden_ks`: the unknowns
    $l > 2$ enter through $A_{22}^{-1} = F_2^{-1}PF_2^{-1}/K_s^2$, and with $P = H^TH$ the filter $F_2$ and the
    powers of $K_s$ cancel: $A_{12}A_{22}^{-1}A_{12}^T = Z^TZ$, $A_{12}A_{22}^{-1}r_2 = Z^Te_b$ with
    $Z = [K_d e_d + K_s e_sF_1,\\; K_d h_{fd} + K_s H s_{fs}]$ `(m, 10)` ($s_{fs}$: the source's unfiltered
    specular row against the $l > 2$ columns, the one σ-dependent product), the RSS is
    $bb - |e_b|^2 - h^TS^{-1}h$ with $S = A_{11} - Z^TZ$, $h = r_1 - Z^Te_b$, and
    $x_2 = F_2^{-1}H^T(e_b - Zx_1)/K_s$. $O(10\\,m)$ per channel and one 10×10 elimination instead of the
    $(C, m, m)$ products of `_schur_rss` (tested equal to it, `tests/test_inverse.py`). `rows_fs`: the rows'
    product with the source's weighted specular row at σ when already formed (`_rows_dot_many`), else None."""
    filt = jaxsh.microfacet_spectrum(sigma, lmax)[jaxsh.sh_degrees(lmax)]
    kd = 1.0 - ks
    fs = _source_lobe(sp, sigma)
    wfs = jt.w * fs
    rows_fs = _rows_dot(jt, wfs) if rows_fs is None else rows_fs
    # cross terms with the (filtered) slow columns
    dfd, dfs = sp.rows_fd[:9], rows_fs[:9]  # (9,)
    sfd, sfs = sp.rows_fd[9:] * filt, rows_fs[9:] * filt  # (n,)
    a_d = (kd**2)[None, :] * dfd[:, None] + (kd * ks)[None, :] * (dfs[:, None] + sfd[:9, None]) + (ks**2)[None, :] * sfs[:9, None]
    a_s = (ks * kd)[None, :] * sfd[9:, None] + (ks**2)[None, :] * sfs[9:, None]
    a_ss = kd**2 * sp.fd_fd + 2 * kd * ks * jnp.sum(wfs * sp.fd) + ks**2 * jnp.sum(wfs * fs)
    r_s = kd * sp.fd_b + ks * (wfs @ jt.b)
    g = jt.bl.g
    f1, f2 = filt[:9], filt[9:]
    kd_, ks_ = kd[:, None, None], ks[:, None, None]
    ds1 = g.ds[:, :9] * f1[None, :]
    a11 = kd_**2 * g.dd[None] + kd_ * ks_ * (ds1 + ds1.T)[None] + ks_**2 * (f1[:, None] * g.ss[:9, :9] * f1[None, :])[None]
    a11 = jnp.concatenate(
        [jnp.concatenate([a11, a_d.T[:, :, None]], 2), jnp.concatenate([a_d.T[:, None, :], a_ss[:, None, None]], 2)], 1
    )  # (C, 10, 10)
    r1 = jnp.concatenate([(kd[None, :] * g.db + ks[None, :] * f1[:, None] * g.sb[:9]).T, r_s[:, None]], 1)  # (C, 10)
    z = jnp.concatenate([kd_ * sp.e_d[None] + ks_ * (sp.e_s * f1[None, :])[None],
                         (kd[:, None] * sp.h_fd[None, :] + ks[:, None] * (jt.bl.h22 @ rows_fs[18:])[None, :])[:, :, None]],
                        2)  # (C, m, 10)
    e_b = sp.e_b.T  # (C, m)
    h = r1 - jnp.einsum("cmk,cm->ck", z, e_b)
    schur = a11 - jnp.einsum("cmk,cml->ckl", z, z)
    x1 = solve_spd_small(schur, h)
    rss = g.bb - jnp.sum(e_b * e_b, -1) - jnp.sum(h * x1, -1)
    x2 = ((e_b - jnp.einsum("cmk,ck->cm", z, x1)) @ jt.bl.h22) / f2[None, :] / ks[:, None]
    return rss, x1, x2


def _refine(sub, obs, lmax, mu, ks0, d, sigma0, max_steps, rtol, atol, chunk, rcond, blocks=(None, None), tab=None,
            rows_obs=None, perm=None, where=None):
    """The joint refinement (`_refine_final`'s values, then the all-pixel blocks it used); `blocks`: the eq.-25
    blocks at `mu` on `obs` and on `sub` (None: formed here);
    `tab`: the subset's `MirrorTable` (its rows then come from the table's harmonics), or None; `rows_obs`: the
    eq.-25 rows at `mu` of the pixels outside the subset (`_all_pixel_blocks` with the subset first), or None (all
    rows formed here); `perm`: `_subset_first`'s orders, given with `rows_obs` (the refinement on all pixels then
    takes the subset's rows from `tab`: `_joint_padded`), or None with `rows_obs` of every pixel in its order;
    `where`: `pixel_sharding(obs.normals)` (sharded pixels: the rows of all pixels made on each device's pixels,
    `_all_pixel_blocks`, and the refinement on all pixels run where they are, `_joint_from_rows`)."""
    bl_obs, bl_sub = blocks
    if tab is not None and bl_sub is not None:
        jt_sub = _joint_from_table(sub, tab, bl_sub, mu, lmax, _K0())
    else:
        jt_sub = _joint_jit(sub, bl_sub, mu, lmax, chunk, rcond, None)  # the Gram blocks once, whatever the shadow
    column = _source_column(jt_sub, sub.fast_visibility, mu, ks0, d, sigma0, lmax)
    if column is not None:
        jt_sub = dataclasses.replace(jt_sub, fvis=sub.fast_visibility[:, column])
    ks, sigma, status, its, _ = _refine_search(jt_sub, mu, ks0, d, sigma0, lmax, *_limits(max_steps, rtol, atol))
    if sub is obs:
        jt = jt_sub
    elif where is not None:
        if rows_obs is None:
            bl_pass, rows_obs, _ = _all_pixel_blocks(obs, mu, lmax, chunk, rcond, True, where=where)
            bl_obs = bl_pass if bl_obs is None else bl_obs
        jt = _joint_from_rows(obs, bl_obs, rows_obs, column)
        perm = None
    elif rows_obs is not None and bl_obs is not None:
        jt = _joint_padded(obs, bl_obs, rows_obs, column, perm[2], jt_sub)
    else:
        jt = _joint_jit(obs, bl_obs, mu, lmax, chunk, rcond, column)
        perm = None
    out = _refine_final(jt, ks, sigma, mu, d, lmax, status, its, obs.n_samples, None if perm is None else perm[3])
    return out + (jt.bl,)


@jaxsh.jit
def _eq25_status(bl: _Blocks, ks, lmax: int, rcond, status):
    """The worse of `status` and that of eq. 25's lighting solve (`lighting_from_gram`) from the blocks `bl` (the
    first of a batch) at the BRDF `ks` ($K_d = 1 - K_s$): `ill_conditioned` where the pixels do not determine the
    lighting."""
    g = (_first(bl) if bl.g.dd.ndim == 3 else bl).g
    return worst(status, lighting_from_gram(g, 1.0 - ks, ks, lmax, 0.0, rcond).status)


def _joint_window(t1):
    """The joint μ search's 9 values of $\\log(\\mu - 1)$: the Chebyshev points (`_chebyshev_points`) of an
    interval of width $2w$ around `t1` (`_MU_JOINT_HALF_WIDTH`), shifted (not shrunk) to lie inside stage 1's
    range. Unshifted, the middle value is `t1` itself, bitwise (`factorize` then takes stage 1's blocks at `t1`
    from the window's batch)."""
    lo = min(max(t1 - _MU_JOINT_HALF_WIDTH, _MU_T_RANGE[0]), _MU_T_RANGE[1] - 2 * _MU_JOINT_HALF_WIDTH)
    ts = _chebyshev_points(lo, lo + 2 * _MU_JOINT_HALF_WIDTH)
    if lo == t1 - _MU_JOINT_HALF_WIDTH:
        ts[4] = t1
    return ts


# the window's values in the order of their `_mu_blocks` batch when stage 1 shares it: the middle one (stage 1's
# mu) first, where `_golden_batch` and `_lighting_and_source` read a batch's blocks
_WINDOW_ORDER = np.array([4, 0, 1, 2, 3, 5, 6, 7, 8])
_WINDOW_SLOT = np.argsort(_WINDOW_ORDER)  # the batch index of each window value


def _joint_mu_search(sub, tab, lmax, t1, ks0, d, sigma0, max_steps, rtol, atol, rcond, column, chunk=None,
                     first=None):
    """$t = \\log(\\mu - 1)$ that minimizes the joint model's profiled RSS on the subset (its $(K_s, \\sigma)$
    re-searched at each $\\mu$ by `_refine_search`): 9 Chebyshev points on $[t_1 - w, t_1 + w]$
    (`_joint_window`, within stage 1's range) around the stage-1 value $t_1$, their blocks in one batch
    (`_mu_blocks`), then the minimum of their interpolant (`_interpolant_minimum`). The parabola through the best
    of 9 evenly spaced values and its neighbours, which this replaced, was 1.2e-3 to 1.1e-2 off the profile's
    minimum on three captures (1.2 to 2.1 standard errors of $t$), the interpolant 2.5e-7 to 5e-7
    (docs/performance.md, "Twenty-third round"). Stage 1 chooses $\\mu$ with the
    lighting as $l \\le l^*$ SH only; a bright compact source (a sun) is far from that model, and $\\mu$ then
    absorbs the misfit (measured: $\\mu$ 1.36 for 1.6 on noise-free images, $K_s$ 40 % low, status converged).
    The joint model holds the source as a delta, so its $\\mu$ is not biased that way. Reuses the compiled
    programs of stage 1 and the refinement (`_mu_blocks`, `_joint_from_table`, `_refine_search`). Without a
    table (`tab` None: a subset too large for one) each value's blocks and rows come from direct sums over the
    subset (`_joint_jit`, in chunks of `chunk` pixels), the refinement's program on that path. `first`: the
    first window's blocks when already formed (`factorize`: a batch in the order `_WINDOW_ORDER`), or None.
    Returns `(t, the profile's curvature in t on the subset or None, evaluations)`."""
    dt = sub.values.dtype
    window = _joint_window

    def profile(ts, bl=None):
        slot = np.arange(len(ts)) if bl is None else _WINDOW_SLOT
        if bl is None and tab is not None:
            bl = _mu_blocks(tab, jax.device_put((1.0 + np.exp(ts)).astype(dt)), lmax, rcond)
        vals = []
        for k, t in enumerate(ts):
            mu = jax.device_put(np.asarray(1.0 + np.exp(t), dt))
            if tab is None:
                jt = _joint_jit(sub, None, mu, lmax, chunk, rcond, column)
            else:
                jt = _joint_from_table(sub, tab, bl, mu, lmax, jax.device_put(np.int32(slot[k])))
                if column is not None:
                    jt = dataclasses.replace(jt, fvis=sub.fast_visibility[:, column])
            vals.append(float(_refine_search(jt, mu, ks0, d, sigma0, lmax, *_limits(max_steps, rtol, atol))[4]))
        return np.where(np.isfinite(vals), vals, np.inf)

    ts = window(t1)
    vals = profile(ts, None if first is None or tab is None else first)
    n = len(ts)
    if not np.any(np.isfinite(vals)):
        return t1, None, n
    best, c2 = _interpolant_minimum(ts, vals)
    inner = c2 is None and ((best == ts[0] and ts[0] > _MU_T_RANGE[0]) or (best == ts[-1] and ts[-1] < _MU_T_RANGE[1]))
    if inner:  # the minimum at a window edge inside the range: once more, centred there (9 evaluations more)
        ts2 = window(best)
        vals2 = profile(ts2)
        n += len(ts2)
        if np.min(vals2) <= np.min(vals):
            best, c2 = _interpolant_minimum(ts2, vals2)
    return best, c2, n


def _at_bound(t_mu, sigma) -> dict:
    """`{"mu": bool, "sigma": bool}`: the final $t = \\log(\\mu - 1)$ (a host float, None without Fresnel) at an end of
    `_MU_T_RANGE` (the grids hold the ends exactly), and $\\log\\sigma$ (None without `find_sigma`) within
    `_AT_BOUND_TOL` (`fit_brdf`'s, in log units) of an end of `_SIGMA_RANGE` (the σ grids approach an end by
    their spacing only)."""
    mu_b = t_mu is not None and not _MU_T_RANGE[0] + 1e-9 < float(t_mu) < _MU_T_RANGE[1] - 1e-9
    sigma_b = False
    if sigma is not None:
        ls = float(np.log(np.asarray(sigma, np.float64)))
        sigma_b = bool(np.isfinite(ls)) and not np.log(_SIGMA_RANGE[0]) + _AT_BOUND_TOL < ls < np.log(_SIGMA_RANGE[1]) - _AT_BOUND_TOL
    return {"mu": bool(mu_b), "sigma": bool(sigma_b)}



def _chebyshev_points(lo: float, hi: float, n: int = 9) -> np.ndarray:
    """The `n` Chebyshev points of the second kind on `[lo, hi]`, ascending, the ends included exactly."""
    x = lo + (hi - lo) * (1.0 - np.cos(np.pi * np.arange(n) / (n - 1))) / 2
    x[0], x[-1] = lo, hi
    return x


def _interpolant_minimum(t, vals):
    """The minimum over `[t[0], t[-1]]` of the polynomial interpolating `vals` at the Chebyshev points `t`
    (`_chebyshev_points`): `(t_min, c2)`, $c_2$ the interpolant's second derivative there, or None where the
    minimum is at an end of the interval or not convex (no curvature: the standard error is then inf). With a
    non-finite value, the best finite point and None (the best is the middle one when none is finite).

    Stage 1's profile $\\mathrm{RSS}(t)$, $t = \\log(\\mu - 1)$, is analytic near the real axis: the blocks of
    eq. 25 depend on $t$ through $F(\\mu, \\theta_o)$ and $F^2$, whose singularities ($\\mu = -1$ and the branch
    points of $g = \\sqrt{\\mu^2 - 1 + \\cos^2\\theta_o}$) lie at $\\mathrm{Im}\\,t = \\pm\\pi$, and the profiling over
    the lighting and $K_s$ keeps that where the minima are interior. So the interpolant converges geometrically
    in the number of points. Measured (docs/performance.md, "Twenty-third round"): on six captures with three BRDF
    models, the minimum on the first grid's bracket (half-width 0.49) from 9 points fell within 8e-8 of the
    profile's minimum, where two zooms of 7 points and a parabola through the last three were 2e-7 to 6e-4 off."""
    t = np.asarray(t, np.float64)
    vals = np.asarray(vals, np.float64)
    if not np.all(np.isfinite(vals)):
        return t[int(np.nanargmin(vals)) if np.any(np.isfinite(vals)) else len(t) // 2], None
    lo, hi = float(t[0]), float(t[-1])
    p = np.polynomial.Chebyshev.fit(t, vals, len(t) - 1, domain=[lo, hi])
    d1, d2 = p.deriv(), p.deriv(2)
    # the real roots of p' inside, each polished by a Newton step (the companion matrix's roots are good to ~1e-10)
    inner = [float(z.real) for z in d1.roots() if abs(z.imag) <= 1e-6 * (hi - lo) and lo < z.real < hi]
    inner = [float(np.clip(x - d1(x) / d2(x), lo, hi)) if d2(x) != 0 else x for x in inner]
    t_min = min([lo, hi, *inner], key=lambda x: float(p(x)))
    c2 = float(d2(t_min))
    if t_min in (lo, hi) or not c2 > 0:
        return t_min, None
    return t_min, c2


_MU_T_RANGE = (float(np.log(0.05)), float(np.log(2.5)))  # stage 1's range of log(mu - 1)
_MU_JOINT_HALF_WIDTH = 0.75  # the joint search's bracket around the stage-1 log(mu - 1): 1.5 first-round steps
# (wide for stage 1's bias, 9.5 % in mu on `bench_inverse.py`'s capture; mu's standard error is
# far smaller, 8.6e-4 at mu = 1.6 on 3 x 48^2 views with 1 % noise, against a Monte Carlo spread of 7.5e-4). The
# window is shifted, not shrunk, to stay inside `_MU_T_RANGE`, and centred again once on a minimum at its edge.
# log(sigma)'s grids inside the joint mu search: two zooms, then the Chebyshev grid, whose interpolant's minimum is
# the value the profile over mu reads (`_refine_search`); the final refinement runs to its tolerance
_MU_JOINT_SIGMA_GRIDS = 3


def _source_column(jt, fv, mu, ks0, d, sigma0, lmax):
    """The column of `fast_visibility` `fv` that is the found source's visibility (None: no such terms).

    One column: that one. Several (candidate sources, e.g. the lights of the capture): the one whose
    profiled RSS at the stage-1 $(K_s, \\sigma)$ is smallest, i.e. whose shadow the data show. `jt`: the
    joint system without a shadow (its Gram blocks are shared by every candidate).
    """
    if fv is None or fv.shape[1] == 0:
        return None
    if fv.shape[1] == 1:
        return 0
    rss = [float(_column_rss(jt, fv[:, j], mu, ks0, d, sigma0, lmax)) for j in range(fv.shape[1])]
    return int(np.nanargmin(rss)) if np.any(np.isfinite(rss)) else 0


@jaxsh.jit
def _column_rss(jt, fvis, mu, ks, d, sigma, lmax):
    jt = dataclasses.replace(jt, fvis=fvis)
    return jnp.sum(_joint_rss(jt, _source_parts(jt, mu, d), ks, sigma, lmax)[0])


@jaxsh.jit
def _K0():
    """The index 0 as a device scalar, for `_joint_from_table` (one compiled program for every index)."""
    return jax.device_put(np.int32(0))


def _joint_from_table(o: Observations, tab: MirrorTable, bl, mu, lmax: int, k) -> _Joint:
    """`_joint` of the subset `o` from its `MirrorTable` (the same rows as `eq25_rows`, without evaluating the SH),
    with the `k`-th of the batched blocks `bl` (`_mu_blocks`; `k` a traced index: one program for every index), or
    `bl` itself when it is not batched. The specular rows are the table's `ys` itself (not a copy: `f` carries
    mu's Fresnel factor), so the `_Joint` is assembled here, outside the program (`_table_parts`) that makes the
    rest: an input returned by a program comes back as a copy."""
    bl_k, rows_d, f = _table_parts(o, tab, bl, mu, lmax, k)
    if tab.ys.shape != ((lmax + 1) ** 2, o.n_samples):
        raise ValueError(f"the table holds {tab.ys.shape} specular rows, not those of lmax {lmax} at {o.n_samples} samples")
    return _Joint(bl_k, rows_d, tab.ys, f, o.weights, o.values, o.normals, o.views, None)


@jaxsh.jit
def _table_parts(o: Observations, tab: MirrorTable, bl, mu, lmax: int, k):
    """`_joint_from_table`'s blocks (the `k`-th of `bl`), diffuse rows `(9, N)` and specular factor `(N,)`: one
    program (run eagerly, these few operations were a compilation each at the first call)."""
    bl = jax.tree_util.tree_map(lambda a: a[k], bl) if bl.g.dd.ndim == 3 else bl
    npx = o.n_samples  # the table's first columns (its last ones are quadrature nodes)
    f = _table_factor(tab, npx, mu)
    return _first(bl), tab.d[:npx].T, f


def _table_factor(tab: MirrorTable, npx: int, mu):
    """The factor of the table's specular rows at its first `npx` columns (its pixels): $F(\\mu, \\theta_o)\\,V$, the
    reflected-ray visibility `s_scale` (0 where seen from behind) times the Fresnel factor (none with `mu` None), so
    that `tab.ys * factor` are `eq25_rows`' specular rows `(npx,)`."""
    scale = tab.s_scale[:npx]
    return scale if mu is None else scale * jaxsh.fresnel_normalized(tab.cos_o[:npx], mu)


def _joint_padded(o: Observations, bl, rows, column, joint, first: _Joint) -> _Joint:
    """`_Joint` of all pixels in two segments: the search subset's rows as `first` holds them (its `MirrorTable`'s,
    `_joint_from_table`), then the other pixels' rows `((9, N2 + pad), (n, N2 + pad))` from the all-pixel pass
    (`_all_pixel_blocks`, rows after the subset's chunks). The pixels are taken in the order `joint`
    (`_subset_first`) and padded to the rows' width with weight 0 (up normals and views, zero data), which adds
    nothing to any sum.

    The rows go into the `_Joint` as they are, outside any program (an input array returned by a jitted
    function comes back as a copy: 182 MB at 3 × 256², 0.06-0.2 s measured)."""
    rows_d, rows_s = rows
    b1, w, b, n, v, fvis = _pad_joint(o, bl, first.rows_d.shape[1] + rows_d.shape[1], column, joint)
    return _Joint(b1, first.rows_d, first.rows_s, first.f, w, b, n, v, fvis, rows_d, rows_s)


def _joint_from_rows(o: Observations, bl, rows, column) -> _Joint:
    """`_Joint` of all pixels in their order, one segment, from the all-pixel pass's rows `((9, N), (n, N))`
    (`_all_pixel_blocks` with `where`: sharded pixels, each device's rows on that device). Assembled outside a
    program, as `_joint_padded`: the rows and the pixels' fields go in as they are, sharded."""
    b1, fvis = _first_and_column(o, bl, column)
    return _Joint(b1, rows[0], rows[1], None, o.weights, o.values, o.normals, o.views, fvis)


@jaxsh.jit
def _first_and_column(o: Observations, bl, column):
    """The first of the batched blocks `bl`, and the source's shadow column of `o.fast_visibility` (or None)."""
    return _first(bl), (None if column is None else o.fast_visibility[:, column])


@jaxsh.jit
def _pad_joint(o: Observations, bl, width: int, column, order):
    """The fields of `_joint_padded`'s `_Joint` but its rows, in the order `order` (or None), padded to `width` pixels."""
    o = o if order is None else _permuted(o, order)
    pad = width - o.n_samples
    up = jnp.zeros((pad, 3), o.normals.dtype).at[:, 2].set(1.0)
    fvis = None if column is None else jnp.pad(o.fast_visibility[:, column], (0, pad))
    return (_first(bl), jnp.pad(o.weights, (0, pad)), jnp.pad(o.values, ((0, pad), (0, 0))),
            jnp.concatenate([o.normals, up]), jnp.concatenate([o.views, up]), fvis)


@jaxsh.jit
def _joint_jit(o, bl, mu, lmax, chunk, rcond, column):
    return _joint(o, bl, mu, lmax, chunk, rcond, column)


def _joint_golden_parts(jt: _Joint, sp: _SourceParts, sigma, lmax, rows_fs=None) -> _GoldenParts:
    """The $K_s$-independent parts of the joint RSS of `_joint_rss` at one σ, per channel (leading axis C), in
    the form of `_golden_ks`'s `_GoldenParts` with the source's energy as a tenth unknown: `_reduced_rss` of
    channel c at $K_s$ is `_joint_rss(jt, sp, ks, sigma)[0][c]` for `ks[c]` $= K_s$ (`tests/test_inverse.py`).

    Every term of `_joint_rss` is a quadratic form in $(K_d, K_s)$: $A_{11} = K_d^2 a_{dd} + K_dK_s a_{ds} +
    K_s^2 a_{ss}$ (its tenth row and column from the source's rows), $Z = K_d e_d + K_s e_s$ `(m, 10)`,
    $r_1 = K_d r_d + K_s r_s$; only the source's specular row depends on σ (one product with the rows; `rows_fs`:
    that product when already formed, `_rows_dot_many`, else None)."""
    filt = jaxsh.microfacet_spectrum(sigma, lmax)[jaxsh.sh_degrees(lmax)]
    f1 = filt[:9]
    fs = _source_lobe(sp, sigma)
    wfs = jt.w * fs
    rows_fs = _rows_dot(jt, wfs) if rows_fs is None else rows_fs
    g = jt.bl.g
    dfd, dfs = sp.rows_fd[:9], rows_fs[:9]
    sfd, sfs = sp.rows_fd[9:18] * f1, rows_fs[9:18] * f1  # the source against the filtered l <= 2 columns
    ds1 = g.ds[:, :9] * f1[None, :]

    def bordered(a, col, corner):  # [[a, col], [col^T, corner]]: (10, 10)
        return jnp.concatenate([jnp.concatenate([a, col[:, None]], 1),
                                jnp.concatenate([col, corner[None]])[None, :]], 0)

    return _quadratic_parts(
        bordered(g.dd, dfd, sp.fd_fd),
        bordered(ds1 + ds1.T, dfs + sfd, 2.0 * jnp.sum(wfs * sp.fd)),
        bordered(f1[:, None] * g.ss[:9, :9] * f1[None, :], sfs, jnp.sum(wfs * fs)),
        jnp.concatenate([sp.e_d, sp.h_fd[:, None]], 1),
        jnp.concatenate([sp.e_s * f1[None, :], (jt.bl.h22 @ rows_fs[18:])[:, None]], 1),
        jnp.concatenate([g.db.T, sp.fd_b[:, None]], 1),
        jnp.concatenate([(f1[:, None] * g.sb[:9]).T, (wfs @ jt.b)[:, None]], 1),
        sp.e_b.T,
        g.bb - jnp.sum(sp.e_b * sp.e_b, 0),
    )


# The refinement's search in log σ: the range of eq. 26's bisection (`find_source`), `_SIGMA_POINTS` values a zoom.
_SIGMA_RANGE = (1e-3, 2.0)
_SIGMA_POINTS = 16


def _profiled_sigmas(jt: _Joint, sp: _SourceParts, ts, lmax):
    """The joint RSS at each σ = exp(t) of `ts` `(T,)` with each channel's $K_s$ profiled out (`golden_ks_unit`
    per channel, as in stage 1), relative to the data's: `(rel (T,), ks (T, C))`. The parts of every σ come
    from one `vmap`, and the searches of all σ and channels run as one batch (`_golden_search`)."""
    rows_fs = _rows_dot_many(jt, jax.vmap(lambda t: jt.w * _source_lobe(sp, jnp.exp(t)))(ts))  # (T, 9 + n)
    parts = jax.vmap(lambda t, r: _joint_golden_parts(jt, sp, jnp.exp(t), lmax, r))(ts, rows_fs)
    ks, rss, _ = _golden_search(parts, 1e-11, 1e-11, 100)
    return jnp.sum(rss, -1) / jnp.sum(jt.bl.g.bb), ks


class _Zoom(eqx.Module):
    t: Array  # () the best log sigma so far
    val: Array  # () its profiled relative RSS
    ks: Array  # (C,) its K_s
    h: Array  # () half the width of the bracket around `c`
    n: Array  # () grids done
    c: Array  # () the centre of the next grid's bracket: `t`, or the interpolant's minimum after the Chebyshev grid
    cheb: Array  # () bool: the Chebyshev grid is done
    pm: Array  # () the minimum of its interpolant (inf before it, or where it was not inside)
    fine: Array  # () bool: the next grid is the one around that minimum


# After the zooms bring the bracket to this half-width in log σ (two zooms from `_SIGMA_RANGE`: 0.053), the next grid
# is `_SIGMA_POINTS` Chebyshev points on it, and the minimum of their interpolant centres one last grid of spacing
# 1/16 of the tolerance (`_refine_search`).
_SIGMA_CHEB_WIDTH = 0.1


def _cheb_tables(n: int, m: int):
    """Host constants for the interpolant through `n` Chebyshev points of the second kind on [-1, 1] (`x` `(n,)`,
    ascending): `coef` `(n, n)` maps the values at `x` to the Chebyshev coefficients, `dense` `(m, n)` maps them
    to the interpolant at `m` evenly spaced points of [-1, 1], and `d1`, `d2` `(n, n)` map coefficients to those of
    the first and second derivatives (padded with zeros)."""
    x = -np.cos(np.pi * np.arange(n) / (n - 1))
    coef = np.linalg.inv(np.polynomial.chebyshev.chebvander(x, n - 1))
    dense = np.polynomial.chebyshev.chebvander(np.linspace(-1.0, 1.0, m), n - 1) @ coef
    eye = np.eye(n)
    d1 = np.stack([np.pad(np.polynomial.chebyshev.chebder(eye[k]), (0, 1)) for k in range(n)], 1)
    d2 = np.stack([np.pad(np.polynomial.chebyshev.chebder(eye[k], 2), (0, 2)) for k in range(n)], 1)
    return x, coef, dense, d1, d2


def _cheb_values(coef, x):
    """$\\sum_k$ `coef[k]` $T_k(x)$ at a scalar `x` (the three-term recurrence, unrolled)."""
    t0, t1 = jnp.ones_like(x), x
    out = coef[0] * t0 + coef[1] * t1
    for k in range(2, coef.shape[0]):
        t0, t1 = t1, 2 * x * t1 - t0
        out = out + coef[k] * t1
    return out


def _interpolant_argmin(vals, dt):
    """The minimum on [-1, 1] of the interpolant through `vals` `(n,)` at `_cheb_tables`' points: the best of 257
    evenly spaced values, then three Newton steps on its derivative where it is convex there (kept inside).
    Returns `(x, inner, the interpolant there)`: inner is False where the minimum is at an end (the true one may lie
    outside)."""
    x, coef, dense, d1, d2 = (jnp.asarray(a, dt) for a in _cheb_tables(vals.shape[0], 257))
    c = coef @ vals
    c1, c2 = d1 @ c, d2 @ c
    xs = jnp.linspace(-1.0, 1.0, 257, dtype=dt)
    k = jnp.argmin(dense @ vals)
    z = xs[k]
    for _ in range(3):
        g, h = _cheb_values(c1, z), _cheb_values(c2, z)
        z = jnp.where(h > 0, jnp.clip(z - g / jnp.where(h > 0, h, 1.0), -1.0, 1.0), z)
    inner = (k > 0) & (k < 256) & (_cheb_values(c2, z) > 0)
    return z, inner, _cheb_values(c, z)


def _limits(max_steps, rtol, atol):
    """`_refine_search`'s limits as device scalars, so that every limit runs one compiled program (Python numbers
    are static arguments of `jaxsh.jit`: the joint mu search's 3 grids would compile a second copy, ~1 s)."""
    return (jax.device_put(np.int32(max_steps)), jax.device_put(np.float64(rtol)), jax.device_put(np.float64(atol)))


@jaxsh.jit
def _refine_search(jt, mu, ks0, d, sigma0, lmax, max_steps, rtol, atol):
    """Minimize the joint RSS (`_joint_rss`) over $(K_s, \\sigma)$ on the search subset.

    Once σ is fixed the channels decouple, so each channel's $K_s$ is profiled out (`_profiled_sigmas`:
    `optimistix.GoldenSearch` over $K_s \\in [10^{-6}, 1]$ and the end point 1, as in stage 1), and
    $t = \\log\\sigma$ is searched like stage 1's $\\mu$: by zooming grids of `_SIGMA_POINTS` evenly spaced values
    inside the bracket, first all of `_SIGMA_RANGE` (eq. 26's range), then the best point's neighbours (the
    bracket shrinks 8.5× a zoom); once the bracket's half-width is within `_SIGMA_CHEB_WIDTH` (after two zooms),
    by `_SIGMA_POINTS` Chebyshev points on it, whose interpolant's minimum (`_interpolant_argmin`; the profile is
    analytic in $t$) centres one more grid, of spacing 1/16 of the tolerance (a last grid of spacing near the
    tolerance let rounding move σ by a whole spacing, 2.7e-7, between one device and four: `tests/test_scale.py`).
    The search stops when the spacing is within `atol + rtol |t|` (four grids where the 8.5-fold zooms took eight or
    nine) or after `max_steps` grids. Where the interpolant's minimum falls on the bracket's end, or a value is not
    finite, the zooms go on from the best point; where the fine grid's best is at its edge, one more grid of twice
    its width is centred there. Each grid evaluates its values in one batch (one pass over the rows for all of
    them, `vmap`); the loop holds one copy of the objective. Where no value is finite (data without signal) the search stops after
    the first grid and returns the stage-1 `ks0`, `sigma0` (clipped to the ranges) with the status `nonfinite`.
    Returns `ks (C,)`, `sigma`, the status, the values evaluated and the profiled RSS reached: the least value
    evaluated, or the interpolant's minimum where that is less (the joint μ search stops after the Chebyshev grid,
    `_MU_JOINT_SIGMA_GRIDS`, and reads this value: on `bench_inverse.py`'s capture within 3e-12 of the profile's
    minimum, relative, where the best of the Chebyshev points was up to 2.7e-3 above it)."""
    dt = jt.b.dtype
    c = jt.b.shape[1]
    sp = _source_parts(jt, mu, d)
    lo, hi = np.log(_SIGMA_RANGE[0]), np.log(_SIGMA_RANGE[1])
    frac = jnp.arange(1, _SIGMA_POINTS + 1, dtype=dt) / (_SIGMA_POINTS + 1)
    prof = lambda ts: _profiled_sigmas(jt, sp, ts, lmax)  # noqa: E731

    def tol(z):
        return atol + rtol * jnp.abs(z.t)

    def cond(z):
        # (the fine grid runs whatever its width: it is narrower than the tolerance)
        return ((z.h > tol(z)) | z.fine) & (z.n < max_steps) & ((z.n == 0) | jnp.isfinite(z.val))

    xc = jnp.asarray(_cheb_tables(_SIGMA_POINTS, 2)[0], dt)

    def body(z):
        a, b = jnp.maximum(z.c - z.h, lo), jnp.minimum(z.c + z.h, hi)
        use_cheb = ~z.cheb & (z.h <= _SIGMA_CHEB_WIDTH)
        ts = jnp.where(use_cheb, 0.5 * (a + b) + 0.5 * (b - a) * xc, a + (b - a) * frac)
        vals, ks = prof(ts)
        vals = jnp.where(jnp.isnan(vals), jnp.inf, vals)
        k = jnp.argmin(vals)
        better = vals[k] < z.val
        t = jnp.where(better, ts[k], z.t)
        # the fine grid's best at its edge: the interpolant's minimum was off; one more grid of twice its width there
        edge = (k == 0) | (k == _SIGMA_POINTS - 1)
        h = jnp.where(z.fine & edge, b - a, (b - a) / (_SIGMA_POINTS + 1))
        # after the Chebyshev grid: the fine grid, spacing 1/16 of the tolerance, centred on the interpolant's minimum
        # (where it is inside the bracket and all values are finite; else a zoom on the best value, as before)
        xm, inner, pm = _interpolant_argmin(jnp.where(jnp.isfinite(vals), vals, 0.0), dt)
        ok = use_cheb & inner & jnp.all(jnp.isfinite(vals))
        tm = 0.5 * (a + b) + 0.5 * (b - a) * xm
        h_fine = (_SIGMA_POINTS + 1) / 32 * (atol + rtol * jnp.abs(tm))
        return _Zoom(t, jnp.where(better, vals[k], z.val), jnp.where(better, ks[k], z.ks),
                     jnp.where(ok, h_fine, h), z.n + 1, jnp.where(ok, tm, t), z.cheb | use_cheb, jnp.where(ok, pm, z.pm),
                     ok)

    z0 = _Zoom(jnp.asarray(0.5 * (lo + hi), dt), jnp.asarray(jnp.inf, dt), jnp.zeros((c,), dt),
               jnp.asarray(0.5 * (hi - lo), dt), jnp.asarray(0), jnp.asarray(0.5 * (lo + hi), dt), jnp.asarray(False),
               jnp.asarray(jnp.inf, dt), jnp.asarray(False))
    z = jax.lax.while_loop(cond, body, z0)
    # no finite value: the stage-1 estimate (finite where it is)
    t_fb = jnp.clip(jnp.where(jnp.isfinite(sigma0) & (sigma0 > 0), jnp.log(jnp.abs(sigma0)), 0.5 * (lo + hi)), lo, hi)
    ks_fb = jnp.clip(jnp.where(jnp.isfinite(ks0), ks0, 0.5), 1e-6, 1.0)
    found = jnp.isfinite(z.val)
    z = _Zoom(jnp.where(found, z.t, t_fb), z.val, jnp.where(found, z.ks, ks_fb), z.h, z.n, z.c, z.cheb, z.pm, z.fine)
    done = (z.h <= tol(z)) & ~z.fine  # (stopped before the fine grid: not converged)
    status = Status.where(jnp.isfinite(z.val), Status.where(done, Status.converged, Status.max_steps_reached),
                          Status.nonfinite)
    return z.ks, jnp.exp(z.t), status, z.n * _SIGMA_POINTS, jnp.minimum(z.val, z.pm)


_FD_STEP = 1e-3  # relative step of the central differences in `_profiled_hessian`


def _profiled_hessian(jt, sp, ks, sigma, lmax):
    """Hessian of the profiled RSS $\\sum_c \\mathrm{rss}_c(K_{s,c}, \\sigma)$ over $(K_s, \\sigma)$, `(C+1, C+1)`.

    Channel c's RSS depends on its own $K_{s,c}$ and on σ only, so the $K_s$ block is diagonal and a 9-point
    central-difference stencil in $(K_s, \\sigma)$ (all channels' $K_s$ moved together, steps `_FD_STEP`
    relative) gives every entry, from 9 evaluations of `_joint_rss` in one `vmap`; its centre is `_joint_rss` at
    `(ks, sigma)` itself, returned as well (`(hess, (rss, x1, x2))`: one copy of the objective in the
    compiled program instead of two). The exact second
    derivative through the (then unrolled) eliminations of `_schur_rss` (`jax.hessian`) took 7-10 s to compile;
    measured against it: the Hessian and the variances agree to 9e-7 on a 3-view 48² sphere
    (`tests/test_inverse.py` checks 1e-5).
    """
    c = ks.shape[0]
    hk = _FD_STEP * jnp.maximum(jnp.minimum(ks, 1.0 - ks), 1e-3)  # (C,): stays inside (0, 1)
    hs = _FD_STEP * sigma
    a, b = np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0], indexing="ij")
    a, b = jnp.asarray(a.ravel(), ks.dtype), jnp.asarray(b.ravel(), ks.dtype)

    # the rows against the source's row at the stencil's three σ, in one product (`_rows_dot_many`)
    steps = jnp.asarray([-1.0, 0.0, 1.0], ks.dtype)
    rows_fs = _rows_dot_many(jt, jax.vmap(lambda bi: jt.w * _source_lobe(sp, sigma + bi * hs))(steps))

    def rss_at(ai, bi, r):
        return _joint_rss(jt, sp, ks + ai * hk, sigma + bi * hs, lmax, r)

    rss, x1, x2 = jax.vmap(rss_at)(a, b, rows_fs[b.astype(jnp.int32) + 1])
    r = rss.reshape(3, 3, c)  # [ks step, sigma step, channel]
    h_kk = (r[2, 1] - 2.0 * r[1, 1] + r[0, 1]) / hk**2
    h_ss = jnp.sum(r[1, 2] - 2.0 * r[1, 1] + r[1, 0]) / hs**2
    h_ks = (r[2, 2] - r[2, 0] - r[0, 2] + r[0, 0]) / (4.0 * hk * hs)
    top = jnp.concatenate([jnp.diag(h_kk), h_ks[:, None]], 1)
    hess = jnp.concatenate([top, jnp.concatenate([h_ks, h_ss[None]])[None, :]], 0)
    return hess, (rss[4], x1[4], x2[4])  # the stencil's centre (steps 0, 0) is `_joint_rss` at (ks, sigma)


@jaxsh.jit(optimize=False)
def _refine_final(jt, ks, sigma, mu, d, lmax, status, its, n: int, pos=None):
    """The refinement's estimate at `(ks, sigma)`: lighting, standard errors, rms, and the model at the first `n`
    pixels of `jt` (`jt` may carry weight-0 padding after them), or at its pixels `pos` `(n,)` (`_subset_first`)."""
    c = jt.b.shape[1]
    sp = _source_parts(jt, mu, d)
    hess, (rss, x1, x2) = _profiled_hessian(jt, sp, ks, sigma, lmax)
    nobs = jt.bl.g.count * c
    data_ss = jnp.sum(jt.bl.g.bb)
    rms, rel = rms_pair(jnp.sum(rss), data_ss, nobs)
    slow = jnp.concatenate([x1[:, :9], x2], 1).T  # (n, C), unfiltered slow lighting
    lighting = Lighting(slow, d[None, :], x1[:, 9][None, :])
    # standard errors of (ks, sigma): Hessian of the profiled RSS (Gauss-Newton: J'J = H/2)
    theta = jnp.concatenate([ks, sigma[None]])

    n_par = x1.size + x2.size + theta.size
    s2 = jnp.sum(rss) / jnp.maximum(nobs - n_par, 1.0)
    h2 = 0.5 * (hess + hess.T)
    # small dense inverse by Gaussian elimination in plain XLA ops (no LAPACK)
    hinv = inverse_spd_small(0.5 * h2)
    var = jnp.diag(hinv) * s2
    se = jnp.where((var > 0) & jnp.isfinite(var), jnp.sqrt(jnp.abs(var)), jnp.inf)
    # the model at the estimate (`_joint_rss`'s): K_d (diffuse rows . L_{l<=2} + f_d E) + K_s (specular rows . filtered
    # L + f_s E), as one product of the rows with the combined coefficients (C, 9 + n) (rows `(9 + n, N)` as stored)
    kd = 1.0 - ks
    # eq. 20's filter written out: `jaxsh.microfacet_spectrum`'s checks are not needed for a σ of the search's range,
    # and their two host callbacks cost ~0.1 s of tracing and lowering here (measured)
    filt = jnp.exp(-((sigma * jnp.asarray(jaxsh.sh_degrees(lmax), sigma.dtype)) ** 2))
    coef = jnp.concatenate([kd[:, None] * x1[:, :9], ks[:, None] * slow.T * filt[None, :]], 1)
    fs = _source_lobe(sp, sigma)
    src = (kd[:, None] * sp.fd[None, :] + ks[:, None] * fs[None, :]) * x1[:, 9][:, None]  # (C, N)
    full = _coef_rows(jt, coef) + src
    fitted = (full[:, :n] if pos is None else full[:, pos]).T
    return ks, sigma, lighting, se[:c], se[c], status, its, rms, rel, data_ss, fitted


@jaxsh.jit
def _stage1_fitted(o: Observations, mu, ks, coeffs, lmax: int, chunk: int, where=None):
    """Eq. 25 at `(ks, mu)` with the lighting `coeffs` `(n, C)` (the first stage's model: one set of coefficients
    for the diffuse l <= 2 and the specular rows), `(N, C)`, in chunks of `chunk` pixels (`lax.map`: the rows of
    one chunk at a time, as `accumulate_gram` forms them); `where`: `pixel_sharding` (each device its pixels)."""
    def one(x):
        n, v, t, r = x
        d, s = eq25_rows(n, v, t, r, mu, None, lmax, coeffs_first=True)
        return ((1.0 - ks)[:, None] * (coeffs[:9].T @ d) + ks[:, None] * (coeffs.T @ s)).T

    def local(n, v, t, r):
        out = jax.lax.map(one, pixel_chunks(n, v, chunk, t, r))
        return out.reshape(-1, out.shape[-1])[: n.shape[0]]

    return map_over_pixels(local, where, (o.normals, o.views, o.transfer, o.reflected_visibility))
