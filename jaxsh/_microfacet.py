"""Fuller microfacet BRDFs in R&H's parameters: Cook–Torrance (Beckmann) and GGX, with Smith masking.

The simplified Torrance–Sparrow model of R&H 2001 sec. 5.2 (`torrance_sparrow`)
drops the geometric attenuation $G$, evaluates the Fresnel factor at the
exitant angle $\\theta_o$ and uses the lobe $e^{-(\\theta_h/\\sigma)^2}/(\\pi\\sigma^2)$
in the angle itself. The models here keep all three of the physics the paper
simplifies away, so data rendered with them (`render_reference(...,
brdf_model="cook_torrance" | "ggx")`) is *not* reproducible exactly by the
practical model and a fit against it can see model error:

$$\\rho = K_d + K_s\\,\\frac{F(\\mu, \\omega_i\\cdot h)}{F(\\mu, 0)}\\,
  \\frac{D(\\theta_h)\\,G(\\omega_i, \\omega_o)}{4\\cos\\theta_i\\cos\\theta_o},$$

with $h$ the half vector, $F$ the exact unpolarized dielectric Fresnel term
(`fresnel_dielectric`) at the *microfacet* angle $\\theta_d$
($\\cos\\theta_d = \\omega_i\\cdot h = \\omega_o\\cdot h$; Cook & Torrance 1982 eq. 8 ff.),
$D$ a normalized microfacet distribution, $\\int D\\cos\\theta_h\\,d\\omega_h = 1$,
and the separable Smith $G = G_1(\\omega_i)G_1(\\omega_o)$ (Walter et al. 2007
eq. 23). The parameters are those of `torrance_sparrow`, in the same
conventions, so that the same $(K_d, K_s, \\mu, \\sigma)$ describe "the same
material" in both models:

- $K_d$: the Lambertian part in the R&H convention (no $1/\\pi$; see `lambertian`).
- $K_s$: the specular scale, with Fresnel normalized by $F(\\mu, 0)$ as in
  R&H ($F/F_0 = 1$ at normal incidence); `mu=None` drops Fresnel ($F = 1$).
- $\\sigma$: the roughness, mapped to the distribution's width by
  **$m = \\sigma$ (Beckmann) and $\\alpha = \\sigma$ (GGX)**.

**The roughness mapping.** Beckmann's distribution (Cook & Torrance 1982 eq. 4,
normalized as in Walter et al. 2007 eq. 25) is
$D_B = \\exp(-\\tan^2\\theta_h/m^2)/(\\pi m^2\\cos^4\\theta_h)$. With
$\\tan^2\\theta = \\theta^2 + \\tfrac23\\theta^4 + O(\\theta^6)$ and
$\\cos^{-4}\\theta = 1 + 2\\theta^2 + O(\\theta^4)$,

$$\\frac{D_B}{S} = \\exp\\Big(-\\frac{\\theta_h^2}{m^2} + \\frac{\\theta_h^2}{\\sigma^2}\\Big)
  \\Big(\\frac{\\sigma}{m}\\Big)^2\\big(1 + 2\\theta_h^2 - \\tfrac{2}{3}\\theta_h^4/m^2 + \\dots\\big),$$

so $m = \\sigma$ is the unique choice that makes $D_B/S \\to 1$ over the
whole lobe ($\\theta_h \\sim \\sigma$) as $\\sigma \\to 0$, with relative
difference $O(\\sigma^2)$: R&H's $S$ *is* the small-angle form of the
normalized Beckmann distribution (their eq. 20 integrates to 1 for the same
reason). GGX (Trowbridge–Reitz; Walter et al. 2007 eq. 33)
$D_G = \\alpha^2/(\\pi\\cos^4\\theta_h(\\alpha^2 + \\tan^2\\theta_h)^2)$ is not a
Gaussian at any width; $\\alpha = \\sigma$ gives it the same peak
$D(0) = 1/(\\pi\\sigma^2)$ (and unit normalization), with the heavier
$\\theta_h^{-4}$ tails that make GGX data a harder test of the practical
model. This is also the identification of Walter et al. sec. 5.2, who
compare Beckmann and GGX at equal width parameter.

**Smith masking** (Walter et al. 2007 eqs. 27, 34), with
$a = 1/(m\\tan\\theta_v)$ for a direction $v$ at angle $\\theta_v$ to $n$:

$$G_1^{B} = \\frac{2}{1 + \\operatorname{erf}(a) + e^{-a^2}/(a\\sqrt\\pi)},\\qquad
  G_1^{GGX} = \\frac{2}{1 + \\sqrt{1 + \\alpha^2\\tan^2\\theta_v}}.$$

(The exact Beckmann form, not Walter's rational approximation.) Both are
in $(0, 1]$, equal 1 at $\\theta_v = 0$ and fall to 0 at grazing angles.
The positivity factors $\\chi^+(v\\cdot h/v\\cdot n)$ are 1 for reflection
above both horizons ($\\omega_i\\cdot h = \\omega_o\\cdot h = |\\omega_i + \\omega_o|/2 > 0$).

Both models are reciprocal ($D$, $G$ and $F(\\omega_i\\cdot h)$ are symmetric in
$\\omega_i, \\omega_o$), unlike the simplified Torrance–Sparrow with
$F(\\theta_o)$. Conventions as in `jaxsh._reflectance` (module docstring there):
unit directions pointing away from the surface, arbitrary broadcast batch
dimensions, traced parameters, 0 below either horizon with finite (zero)
gradients, `ValueError` (concrete) / `equinox.error_if` (traced) for
$\\sigma \\le 0$ or $\\mu < 1$.

??? cite "References"
    Cook, R. L., Torrance, K. E. (1982). A reflectance model for computer
    graphics. ACM TOG 1(1), 7–24. doi:10.1145/357290.357293 (eq. 4: the
    Beckmann distribution; the Fresnel term at the microfacet angle).

    Walter, B., Marschner, S. R., Li, H., Torrance, K. E. (2007). Microfacet
    models for refraction through rough surfaces. EGSR 2007, 195–206.
    doi:10.2312/EGWR/EGSR07/195-206 (eqs. 20, 23: the microfacet BRDF and the
    separable Smith $G$; eqs. 25–27 Beckmann $D$ and $G_1$; eqs. 33–34 GGX).

    Ramamoorthi, R., Hanrahan, P. (2001). A signal-processing framework for
    inverse rendering. SIGGRAPH 2001, 117–128 (sec. 5.2 and eq. 20: the
    simplified Torrance–Sparrow lobe these models reduce to for small $\\sigma$).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jax.scipy.special import erf
from jaxtyping import Array, ArrayLike, Float, Real

from ._compile import jit
from ._reflectance import _above, _dot, _fresnel_normalized, _half, _index, _positive, _prepare, _tan2_theta_h

_PI = math.pi
_SQRT_PI = math.sqrt(math.pi)
# a = 1/(m tan θ) above this: Λ(a) < e^{-a²}/a³ < 1e-29, G1 = 1 to every digit
_A_BIG = 8.0


def _beckmann_d(tan2, c, m):
    """Normalized Beckmann distribution $e^{-\\tan^2\\theta_h/m^2}/(\\pi m^2\\cos^4\\theta_h)$ (Walter eq. 25)."""
    m2 = m * m
    c2 = c * c
    return jnp.exp(-tan2 / m2) / (_PI * m2 * c2 * c2)


def _ggx_d(tan2, c, alpha):
    """Normalized GGX distribution $\\alpha^2/(\\pi\\cos^4\\theta_h(\\alpha^2 + \\tan^2\\theta_h)^2)$ (Walter eq. 33)."""
    a2 = alpha * alpha
    c2 = c * c
    s = a2 + tan2
    return a2 / (_PI * c2 * c2 * s * s)


def _tan2(v, n):
    """$\\tan^2\\theta_v$ of a unit direction above the horizon (finite, smooth at θ = 0)."""
    t2, _ = _tan2_theta_h(v, n)
    return t2


def _smith_g1_beckmann(tan2, m):
    """Exact Smith $G_1 = 1/(1 + \\Lambda(a))$, $\\Lambda = (\\operatorname{erf}(a) - 1)/2 + e^{-a^2}/(2a\\sqrt\\pi)$, $a = 1/(m\\tan\\theta)$ (Walter eq. 27)."""
    x = m * m * tan2  # 1/a²
    big = x < 1.0 / (_A_BIG * _A_BIG)  # near the normal: G1 = 1 (and no 1/0 in the gradient)
    a = 1.0 / jnp.sqrt(jnp.where(big, 1.0, x))
    lam = 0.5 * (erf(a) - 1.0) + jnp.exp(-a * a) / (2.0 * a * _SQRT_PI)
    return jnp.where(big, 1.0, 1.0 / (1.0 + lam))


def _smith_g1_ggx(tan2, alpha):
    """Smith $G_1 = 2/(1 + \\sqrt{1 + \\alpha^2\\tan^2\\theta})$ for GGX (Walter eq. 34)."""
    return 2.0 / (1.0 + jnp.sqrt(1.0 + alpha * alpha * tan2))


def _microfacet_specular(tan2h, ch, ti, to, cd, ci, co, mu, sigma, dist):
    """$F\\,D\\,G/(4\\cos\\theta_i\\cos\\theta_o)$ of the models here from their geometry: $\\tan^2\\theta_h$,
    $\\cos\\theta_h$, $\\tan^2\\theta_i$, $\\tan^2\\theta_o$, $\\cos\\theta_d = \\omega_i\\cdot h$ and the two cosines
    (all of a pair above both horizons). Written once, for `cook_torrance_smith`, `ggx` and the reference
    renderer's pairwise form (`_reference_pairs.py`)."""
    if dist == "beckmann":
        d = _beckmann_d(tan2h, ch, sigma)
        g = _smith_g1_beckmann(ti, sigma) * _smith_g1_beckmann(to, sigma)
    else:
        d = _ggx_d(tan2h, ch, sigma)
        g = _smith_g1_ggx(ti, sigma) * _smith_g1_ggx(to, sigma)
    f = 1.0 if mu is None else _fresnel_normalized(cd, mu)
    return f * d * g / (4.0 * ci * co)


def _microfacet(wi, wo, n, kd, ks, mu, sigma, dist):
    valid, wi, wo, n, ci, co = _above(wi, wo, n)
    h = _half(wi, wo)
    tan2h, ch = _tan2_theta_h(h, n)
    val = kd + ks * _microfacet_specular(tan2h, ch, _tan2(wi, n), _tan2(wo, n), _dot(wi, h), ci, co, mu, sigma, dist)
    return jnp.where(valid, val, 0.0)


_microfacet_jit = jit(_microfacet)


def _checked(wi, wo, n, kd, ks, mu, sigma):
    args = [("wi", wi, "dir"), ("wo", wo, "dir"), ("n", n, "dir"), ("kd", kd, "scalar"), ("ks", ks, "scalar")]
    if mu is not None:
        args.append(("mu", mu, "scalar"))
    args.append(("sigma", sigma, "scalar"))
    out = _prepare(args)
    if mu is None:
        wi, wo, n, kd, ks, sigma = out
    else:
        wi, wo, n, kd, ks, mu, sigma = out
        mu = _index(mu, "mu")
    return wi, wo, n, kd, ks, mu, _positive(sigma, "sigma")


def cook_torrance_smith(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    kd: Real[ArrayLike, "*#batch"],
    ks: Real[ArrayLike, "*#batch"],
    mu: Real[ArrayLike, "*#batch"] | None,
    sigma: Real[ArrayLike, "*#batch"],
) -> Float[Array, "*batch"]:
    """Cook–Torrance in R&H's parameters: Beckmann $D$ ($m = \\sigma$), Smith $G$, Fresnel at the half angle.

    $$\\rho = K_d + K_s\\frac{F(\\mu, \\omega_i\\cdot h)}{F(\\mu, 0)}
      \\frac{D_B(\\theta_h)\\,G_1^B(\\omega_i)\\,G_1^B(\\omega_o)}{4\\cos\\theta_i\\cos\\theta_o},\\quad
      D_B = \\frac{e^{-\\tan^2\\theta_h/\\sigma^2}}{\\pi\\sigma^2\\cos^4\\theta_h}$$

    (Cook & Torrance 1982 eq. 4; Walter et al. 2007 eqs. 20, 23, 25, 27; the
    module docstring derives $m = \\sigma$ from R&H eq. 20's lobe). The
    "physically fuller" counterpart of `torrance_sparrow`, with the same
    arguments and conventions; it tends to it as $\\sigma \\to 0$ at near-normal
    exitance. Not `jaxsh.cook_torrance`, which has the albedo
    convention $k_d/\\pi$, the V-cavity $G$, an unnormalized Fresnel term and
    the slope $m$ as argument. Reciprocal.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `kd`, `ks`,
    `mu` (relative index $\\ge 1$, or `None` for $F = 1$), `sigma`
    (roughness $> 0$, the Beckmann rms slope): `(...)`, traced.

    **Returns:** `(...)`; 0 below either horizon.
    """
    return _microfacet_jit(*_checked(wi, wo, n, kd, ks, mu, sigma), "beckmann")


def ggx(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    kd: Real[ArrayLike, "*#batch"],
    ks: Real[ArrayLike, "*#batch"],
    mu: Real[ArrayLike, "*#batch"] | None,
    sigma: Real[ArrayLike, "*#batch"],
) -> Float[Array, "*batch"]:
    """GGX (Trowbridge–Reitz) microfacet BRDF in R&H's parameters, $\\alpha = \\sigma$, Smith $G$, Fresnel at the half angle.

    $$\\rho = K_d + K_s\\frac{F(\\mu, \\omega_i\\cdot h)}{F(\\mu, 0)}
      \\frac{D_G(\\theta_h)\\,G_1(\\omega_i)\\,G_1(\\omega_o)}{4\\cos\\theta_i\\cos\\theta_o},\\quad
      D_G = \\frac{\\sigma^2}{\\pi\\cos^4\\theta_h(\\sigma^2 + \\tan^2\\theta_h)^2},\\quad
      G_1 = \\frac{2}{1 + \\sqrt{1 + \\sigma^2\\tan^2\\theta_v}}$$

    (Walter et al. 2007 eqs. 20, 23, 33, 34). $\\alpha = \\sigma$ matches the
    peak of R&H's lobe, $D_G(0) = 1/(\\pi\\sigma^2)$ (module docstring); the
    tails are much heavier than the Gaussian's. Arguments and conventions
    as `cook_torrance_smith`. Reciprocal.

    **Returns:** `(...)`; 0 below either horizon.
    """
    return _microfacet_jit(*_checked(wi, wo, n, kd, ks, mu, sigma), "ggx")
