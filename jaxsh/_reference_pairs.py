"""The reference renderer's integrand over (pixel, light direction) pairs: the BRDF from per-pair scalars.

`render_reference` sums $L_j w_j\\,\\rho(\\omega_j, \\omega_o, n)\\max(n\\cdot\\omega_j, 0)$ over
every quadrature node or source $j$ for every pixel. Written as the BRDF of broadcast
`(pixels, nodes, 3)` vectors (`torrance_sparrow(wi[None], wo[:, None], n[:, None], ...)`), XLA:CPU
evaluates the cross products, the double-`where` substitutions of `_above` and the per-pixel Fresnel
factor once per pair, on arrays whose minor axis has 3 elements: 1.29 s for 2,624 pixels × 9,217 nodes
(docs/performance.md, "Fourteenth round"). Here the geometry is formed from the components instead:

- per pair, by products and outer sums of `(P, 1)` and `(1, M)` operands:
  $\\cos\\theta_i = n\\cdot\\omega_i$ (one matrix product), $|h\\times n|^2$ and $h\\cdot n$ for
  $h = \\omega_i + \\omega_o$ (`_half_angle_pairs`, shared with the practical model's fast sources), and
  for the microfacet models $|\\omega_i\\times n|^2$ and $\\omega_i\\cdot\\omega_o$;
- per pixel: $\\cos\\theta_o$, $\\tan^2\\theta_o$ and, for `torrance_sparrow`, the Fresnel factor
  $F(\\mu, \\theta_o)$.

The model formulas are the models' own (`_ts_specular`, `_microfacet_specular`, `_theta_h_sq`),
evaluated on these scalars, so the pairwise form equals the public BRDF functions to rounding (tested
at random and grazing pairs, both dtypes, and against NumPy references in `tests/test_microfacet.py`).
Pairs below either horizon get safe substitutes (those of `_above`: $\\omega_i = \\omega_o = n$) and a
zero value, so gradients stay finite.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._microfacet import _microfacet_specular
from ._reflectance import (
    _fresnel_normalized,
    _half_angle_pairs,
    _half_angle_parts,
    _pair_component,
    _theta_h_sq,
    _ts_specular,
)


def _pair_dots(a, sd):
    """$a_p\\cdot\\omega_{pm}$ `(P, M)` of per-pixel vectors `a` `(P, 3)` and directions `sd`, shared `(M, 3)` (one
    matrix product) or per pixel (the tuple of the three components `(P, M)`)."""
    if not isinstance(sd, tuple):
        return a @ sd.T
    return a[:, 0:1] * sd[0] + a[:, 1:2] * sd[1] + a[:, 2:3] * sd[2]


class _Pairs:
    """Per-pair `(P, M)` and per-pixel `(P, 1)` geometry of `P` pixels (`n`, `v` `(P, 3)`) and `M` directions
    `sd`, shared `(M, 3)` or per pixel (the tuple of its components `(P, M)`; plain container, built and used inside
    one trace)."""

    def __init__(self, n, v, sd):
        self.ci = _pair_dots(n, sd)  # (P, M)
        co = jnp.sum(n * v, -1)[:, None]  # (P, 1)
        self.cos_o = co
        self.pixel_ok = co > 0.0
        self.valid = (self.ci > 0.0) & self.pixel_ok
        self.co = jnp.where(self.pixel_ok, co, 1.0)  # substituted: 1 where the pixel is seen from behind
        s2, c = _half_angle_pairs(sd, n, v)  # |(w + v) x n|^2, (w + v) . n
        self.s2 = jnp.where(self.valid, s2, 0.0)
        self.c = jnp.where(self.valid, c, 2.0)
        self.ci_s = jnp.where(self.valid, self.ci, 1.0)
        self.n, self.v, self.sd = n, v, sd


def _ts_pairs(p: _Pairs, mu, sigma):
    """`torrance_sparrow`'s specular part $F S/(4\\cos\\theta_i\\cos\\theta_o)$ at every pair (0 below a horizon)."""
    f = 1.0 if mu is None else _fresnel_normalized(p.co, mu)  # (P, 1): F(mu, theta_o) once per pixel
    val = _ts_specular(_theta_h_sq(p.s2, p.c), p.ci_s, p.co, f, sigma)
    return jnp.where(p.valid, val, 0.0)


def _microfacet_pairs(p: _Pairs, mu, sigma, dist: str):
    """`cook_torrance_smith`'s (`dist="beckmann"`) or `ggx`'s specular part at every pair (0 below a horizon)."""
    sdn = sum(_pair_component(p.sd, k) ** 2 for k in range(3))  # |w|^2 (1, M) or (P, M)
    vn = jnp.sum(p.v * p.v, -1)[:, None]  # |v|^2 (P, 1)
    wv = _pair_dots(p.v, p.sd)  # (P, M)
    hh = jnp.where(p.valid, sdn + 2.0 * wv + vn, 4.0)  # |w + v|^2 (n + n at the substitute)
    rs = jax.lax.rsqrt(hh)
    tan2h = p.s2 / (p.c * p.c)
    ch = p.c * rs
    ti = jnp.where(p.valid, _half_angle_pairs(p.sd, p.n)[0], 0.0) / (p.ci_s * p.ci_s)  # |w x n|^2 / cos^2
    to = jnp.where(p.pixel_ok, _half_angle_parts(p.v, p.n)[0][:, None], 0.0) / (p.co * p.co)
    cd = jnp.where(p.valid, (sdn + wv) * rs, 1.0)  # w . h
    val = _microfacet_specular(tan2h, ch, ti, to, cd, p.ci_s, p.co, mu, sigma, dist)
    return jnp.where(p.valid, val, 0.0)


PAIR_MODELS = {
    "torrance_sparrow": _ts_pairs,
    "cook_torrance": lambda p, mu, sigma: _microfacet_pairs(p, mu, sigma, "beckmann"),
    "ggx": lambda p, mu, sigma: _microfacet_pairs(p, mu, sigma, "ggx"),
}


def specular_pairs(n, v, sd, mu, sigma, model: str):
    """$\\rho_s(\\omega_j, \\omega_o, n)$ (the specular part at $K_s = 1$) for every pixel of `n`, `v` `(P, 3)` and
    direction of `sd` (`(M, 3)`, or per pixel: the tuple of its components `(P, M)`): `(P, M)`, and
    $\\cos\\theta_i$ `(P, M)`, $\\cos\\theta_o$ `(P, 1)`."""
    p = _Pairs(n, v, sd)
    return PAIR_MODELS[model](p, mu, sigma), p.ci, p.cos_o
