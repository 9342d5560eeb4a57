"""Factorization with the dual angular / frequency-space lighting (R&H 2001 sec. 6.3, "Results").

The paper factors its spheres "with the dual angular and frequency-space
algorithm for inverse lighting": the inner inverse-lighting step of the
simplex objective `ObjFun(K_s, mu)` is the method of fig. 8
(`inverse_lighting_dual`), not the SH solve of eq. 25.

**The profiled objective in closed form.** For given $(\\mu, K_s)$,
$K_d = 1 - K_s$, phase 1 of fig. 8 gives each covered lat-long texel $t$ the
least-squares value $\\mathrm{img}_t = (A_t - K_d M_t L^1)/K_s$ with
$A_t = \\sum_{i\\in t} w_i F_i B_i / S_t$, $M_t = \\sum_{i\\in t} w_i F_i d_i / S_t$,
$S_t = \\sum_{i\\in t} w_i F_i^2$ ($d_i$ the 9 diffuse rows of eq. 21, $F_i$ the
Fresnel factor at $\\theta_o$); uncovered texels hold the $l \\le 2$ field
$Y_9(t) L^1$. Phase 2 projects the image to 9 coefficients with the
quadrature $P$; the consistency condition $L^1 = L^2$ becomes, per channel,

$$\\big(K_s (I - P_{unc} Y_9) + K_d P_{cov} M\\big) L^1 = P_{cov} A ,$$

and the residual of pixel $i$ is $K_d E_i L^1 - q_i$ with
$E_i = d_i - F_i M_{t(i)}$ and $q_i = B_i - F_i A_{t(i)}$. So for one
$\\mu$ every moment ($P_{cov}M$, $P_{unc}Y_9$, $P_{cov}A$, $E^T W E$,
$E^T W q$, $q^T W q$) is formed once, over the pixels, and each step of the
per-channel search over $K_s$ is a 9×9 solve and a quadratic form — the same
RSS as `inverse_lighting_dual(..., nonneg=False)` at that $(K_s, \\mu)$
(tested). The search over $(\\mu, K_s)$ is the one of `factorize` (module
`_factorize`): a grid in $\\log(\\mu - 1)$, then the polynomial through 9 Chebyshev points on its best bracket, and
per channel `optimistix.GoldenSearch` over $K_s$.

**Roughness (eq. 26) from the angular image.** The image is the lighting
filtered by the specular lobe, without a band limit; near a directional
source of energy $L_{tot}$ it is $L_{tot}\\,e^{-\\theta^2/(4\\sigma^2)}/(4\\pi\\sigma^2)$
(the small-σ form of $\\sum_l \\frac{2l+1}{4\\pi} e^{-(\\sigma l)^2} P_l$), so
eq. 26 applies to it directly. The peak, the cap and its background annulus
are found as in `find_source`, and σ solves the same cap/annulus ratio with
that lobe (`optimistix.Bisection`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array

import jaxsh

from ._data import Observations
from ._lighting import _dual_pieces
from ._normal_equations import solve_spd_small


class _DualMoments(eqx.Module):
    """The moments of the dual model for one mu (module docstring): shared by every K_s."""

    pm: Array  # (9, 9)  P_cov M
    qu: Array  # (9, 9)  P_unc Y9
    pa: Array  # (9, C)  P_cov A
    g: Array  # (9, 9)  E^T W E
    h: Array  # (9, C)  E^T W q
    qq: Array  # (C,)    q^T W q
    bb: Array  # (C,)    B^T W B


def _dual_moments(o: Observations, mu, height: int) -> _DualMoments:
    f, tex, d, wv, y9, omega, b = _dual_pieces(o, None, None, mu, height)
    t_count = height * 2 * height

    def seg(x):
        return jax.ops.segment_sum(x, tex, num_segments=t_count)

    sff = seg(wv * f * f)  # (T,)
    cov = sff > 0
    s = jnp.where(cov, sff, 1.0)
    a = jnp.where(cov[:, None], seg((wv * f)[:, None] * b) / s[:, None], 0.0)  # (T, C)
    m = jnp.where(cov[:, None], seg((wv * f)[:, None] * d) / s[:, None], 0.0)  # (T, 9)
    p = (omega[:, None] * y9).T  # (9, T)
    pc = jnp.where(cov[None, :], p, 0.0)
    pu = p - pc
    e = d - f[:, None] * m[tex]  # (N, 9)
    q = b - f[:, None] * a[tex]  # (N, C)
    we = wv[:, None] * e
    return _DualMoments(pm=pc @ m, qu=pu @ y9, pa=pc @ a, g=e.T @ we, h=we.T @ q,
                        qq=jnp.sum(wv[:, None] * q * q, 0), bb=jnp.sum(wv[:, None] * b * b, 0))


def _dual_rss_one(mo: _DualMoments, c: int | Array, ks):
    """RSS of channel `c` of the dual model at `ks` (kd = 1 - ks), and its L^1 (9,)."""
    kd = 1.0 - ks
    eye = jnp.eye(9, dtype=mo.g.dtype)
    mat = ks * (eye - mo.qu) + kd * mo.pm
    rhs = mo.pa[:, c]
    # the 9x9 consistency system by its normal equations: `solve_spd_small`, no LAPACK in the loop
    l1 = solve_spd_small(mat.T @ mat, mat.T @ rhs)
    rss = kd**2 * (l1 @ mo.g @ l1) - 2 * kd * (l1 @ mo.h[:, c]) + mo.qq[c]
    return jnp.maximum(rss, 0.0), l1


def _golden_ks_dual(mo: _DualMoments, rtol: float, atol: float, max_steps: int):
    """Per channel, the K_s in [1e-6, 1] minimizing the dual RSS (`optimistix.GoldenSearch`, vmapped)."""
    dt = mo.g.dtype

    def one(c):
        return golden_ks_unit(lambda ks, _: _dual_rss_one(mo, c, ks)[0], dt, rtol, atol, max_steps)

    return jax.vmap(one)(jnp.arange(mo.bb.shape[0]))


def golden_ks_unit(rss, dt, rtol: float, atol: float, max_steps: int):
    """The $K_s \\in [10^{-6}, 1]$ minimizing the scalar `rss(ks, None)`: `optimistix.GoldenSearch`, and the
    end point $K_s = 1$ (a pure mirror) checked as well. Returns `ks`, `rss(ks)`, `num_steps`."""
    # searched in u in [0, 1], K_s = 1e-6 + u (1 - 1e-6): optimistix 0.1.0's GoldenSearch places its first point at
    # (upper - lower) / phi^2 without adding `lower` (optimistix issue #236); from lower = 1e-6 that broke the golden
    # ratio of the bracket, and the search ran to `max_steps` (100 steps against 51 at tolerance 1e-11, measured)
    lo = 1e-6
    sol = optx.minimise(lambda u, a: rss(lo + u * (1.0 - lo), a), optx.GoldenSearch(rtol=rtol, atol=atol),
                        jnp.asarray(0.5, dt), options=dict(lower=0.0, upper=1.0), max_steps=max_steps, throw=False)
    ks = lo + jnp.clip(sol.value, 0.0, 1.0) * (1.0 - lo)
    # the estimate and the end point in one batched evaluation: one copy of `rss` in the program, not two
    # (each copy of `factorize`'s eliminating RSS costs ~0.15 s of XLA compilation)
    f, f_hi = jax.vmap(lambda k: rss(k, None))(jnp.stack([ks, jnp.ones((), dt)]))
    return jnp.where(f_hi < f, 1.0, ks), jnp.minimum(f_hi, f), sol.stats["num_steps"]


@jaxsh.jit
def _mu_candidates_dual(sub: Observations, t, height: int):
    """Profiled relative dual RSS (best K_s per channel) for each candidate log(mu - 1)."""

    def one(ti):
        mo = _dual_moments(sub, 1.0 + jnp.exp(ti), height)
        _, rss, _ = _golden_ks_dual(mo, 1e-9, 1e-9, 100)
        return jnp.sum(rss) / jnp.sum(mo.bb)

    return jax.lax.map(one, t)


@jaxsh.jit
def _stage1_final_dual(obs: Observations, mu, height: int):
    """K_s per channel at the chosen mu, on all pixels: `ks (C,)`, `num_steps (C,)`."""
    mo = _dual_moments(obs, mu, height)
    ks, _, steps = _golden_ks_dual(mo, 1e-11, 1e-11, 100)
    return ks, steps


def _check_region_arg(region):
    """`region` = `(direction (3,), radius)` with a finite non-zero direction and a radius in (0, pi], or None."""
    if region is None:
        return
    try:
        d, r = region
        d = np.asarray(d, np.float64)
        r = float(r)
    except (TypeError, ValueError):
        raise ValueError(f"`region` must be (direction (3,), radius in radians) or None, got {region!r}") from None
    if d.shape != (3,) or not np.all(np.isfinite(d)) or not np.any(d != 0):
        raise ValueError(f"`region`'s direction must be a finite non-zero 3-vector, got {region[0]!r}")
    if not (np.isfinite(r) and 0 < r <= np.pi):
        raise ValueError(f"`region`'s radius must be in (0, pi] radians, got {r}")



def check_region(region, height: int, dt):
    """The user's `region` as jnp arrays, checked (`_check_region_arg`) and to contain a texel of the `height` grid
    (or None)."""
    if region is None:
        return None
    _check_region_arg(region)
    rdir = np.asarray(region[0], np.float64)
    rdir = rdir / np.linalg.norm(rdir)
    if not np.any(np.asarray(jaxsh.latlong_directions(height, 2 * height)) @ rdir >= np.cos(float(region[1]))):
        raise ValueError("`region` contains no lat-long sample; enlarge its radius")
    return (jnp.asarray(rdir, dt), jnp.asarray(region[1], dt))
