"""Spherical-harmonic spectra of reflectance: $A_l = \\Lambda_l \\hat\\rho_l$.

For a transfer function that is radially symmetric about a pole (the normal
for Lambertian, the reflection vector for Phong and, approximately,
microfacet lobes), reflection is the convolution $B_{lm} = A_l L_{lm}$ with
$A_l = \\Lambda_l\\hat\\rho_l = 2\\pi\\int_{-1}^{1} f(u) P_l(u)\\,du$
(R&H 2001 eqs. 15, 17; $\\Lambda_l = \\sqrt{4\\pi/(2l+1)}$). Spectra are returned
as $A_l$, shape `(..., lmax+1)`, so Lambertian gives π, 2π/3, π/4, 0, −π/24, ...
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

from ._compile import jit
from ._checks import as_float_array, check_dtype, check_lmax, check_positive_int, check_values, common_dtype


def _default_dtype(dtype):
    return check_dtype(dtype)


def _check_sigma(sigma, name: str = "sigma"):
    """σ in (0, ∞); NaN propagates (see `jaxsh._checks`)."""
    return check_values(sigma, lambda a: (a <= 0) | (a == jnp.inf), name, "in (0, inf) (a lobe width)")


def lambertian_spectrum(lmax: int, dtype=None) -> Float[Array, " {lmax}+1"]:
    """$A_l$ of the clamped cosine $\\max(\\cos\\theta, 0)$ (thesis eq. 3.32; R&H eq. 16).

    $A_0 = \\pi$, $A_1 = 2\\pi/3$, $A_l = 0$ for odd $l > 1$, and for even $l$
    $$A_l = 2\\pi\\,\\frac{(-1)^{l/2-1}}{(l+2)(l-1)}\\,\\frac{l!}{2^l\\,((l/2)!)^2}.$$
    Evaluated with log-factorials (stable to any l). `lmax` static.
    """
    lmax = check_lmax(lmax)
    out = np.zeros(lmax + 1)
    out[0] = np.pi
    if lmax >= 1:
        out[1] = 2 * np.pi / 3
    for l in range(2, lmax + 1, 2):
        logbinom = math.lgamma(l + 1) - l * math.log(2) - 2 * math.lgamma(l // 2 + 1)
        out[l] = 2 * np.pi * (-1) ** (l // 2 - 1) / ((l + 2) * (l - 1)) * math.exp(logbinom)
    return jnp.asarray(out, _default_dtype(dtype))


def phong_spectrum(s: Real[ArrayLike, "*batch"], lmax: int) -> Float[Array, "*batch {lmax}+1"]:
    """Exact $A_l = \\Lambda_l\\hat\\rho_l$ of the normalized Phong lobe, any real $s > -1$.

    $A_l = (s+1)\\int_0^1 u^s P_l(u)\\,du$ (R&H eq. 18, thesis eq. 3.36), in the
    Gamma-function form of that integral (MacRobert ch. 5; Gradshteyn &
    Ryzhik 7.126.2):
    $$A_l = \\frac{(s+1)\\sqrt\\pi\\,\\Gamma(s+1)}{2^{s+1}\\,\\Gamma\\big(1+\\tfrac{s-l}{2}\\big)\\,
          \\Gamma\\big(\\tfrac{s+l+3}{2}\\big)},$$
    which reduces to the products of thesis eq. 3.37 for integer $s$ and
    vanishes for $l > s$ of the parity of $s$. Evaluated by the ratio of
    consecutive terms of the same parity that this form gives,
    $A_{l+2} = A_l\\,\\frac{s-l}{s+l+3}$, from $A_0 = 1$ and
    $A_1 = \\frac{s+1}{s+2}$ (a cumulative product): no cancellation, so
    the relative error grows only like $l\\cdot\\varepsilon$. Measured
    against the Gamma form in float64: float32 within 1.2e-7 for
    $s \\le 10^4$, $l \\le 40$ (the log-Gamma evaluation it replaces lost
    1e-5 at s = 50 and 8e-3 at s = 10⁴ in float32); float64 within 1e-15.
    Any real $s > -1$, any $l$; differentiable in $s$.

    **Arguments:** `s` shininess, any shape (traced), $s > -1$; `lmax` static.
    **Returns:** `(..., lmax+1)`.

    $s \\le -1$ (or $s = \\infty$) is an error: a `ValueError` for concrete
    values, a run-time error under `jit`. NaN in, NaN out.
    """
    s = as_float_array(s, "s")
    lmax = check_lmax(lmax)
    s = check_values(s, lambda a: (a <= -1) | (a == jnp.inf), "s", "> -1 and finite (a Phong exponent)")
    return _phong_spectrum(s, lmax)


@jit
def _phong_spectrum(s, lmax):
    l = jnp.arange(lmax + 1, dtype=s.dtype).reshape((1,) * s.ndim + (-1,))
    sb = s[..., None]
    ratio = (sb - l) / (sb + l + 3)  # A_{l+2} / A_l
    one = jnp.where(jnp.isnan(sb), sb, jnp.ones_like(sb))  # A_0 = 1; NaN in, NaN out
    even = jnp.concatenate([one, jnp.cumprod(ratio[..., 0::2], axis=-1)], axis=-1)  # A_0, A_2, ...
    odd = (sb + 1) / (sb + 2) * jnp.concatenate([one, jnp.cumprod(ratio[..., 1::2], axis=-1)], axis=-1)  # A_1, A_3, ...
    n2 = (lmax + 2) // 2
    return jnp.stack([even[..., :n2], odd[..., :n2]], axis=-1).reshape(s.shape + (2 * n2,))[..., : lmax + 1]


def phong_spectrum_gaussian(s: Real[ArrayLike, "*batch"], lmax: int) -> Float[Array, "*batch {lmax}+1"]:
    """Gaussian approximation $A_l \\approx \\exp(-l^2/2s)$ (R&H eq. 19, thesis eq. 3.40).

    Good for large $s$ and $l \\ll s$; use `phong_spectrum` for exact values.
    $s \\le 0$ is an error (`ValueError`, or a run-time error under `jit`);
    NaN in, NaN out.
    """
    s = as_float_array(s, "s")
    lmax = check_lmax(lmax)
    s = check_values(s, lambda a: a <= 0, "s", "> 0 (a Phong exponent)")
    l = jnp.arange(lmax + 1, dtype=s.dtype).reshape((1,) * s.ndim + (-1,))
    return jnp.exp(-(l * l) / (2 * s[..., None]))


def microfacet_spectrum(sigma: Real[ArrayLike, "*batch"], lmax: int) -> Float[Array, "*batch {lmax}+1"]:
    """$A_l \\approx \\exp(-(\\sigma l)^2)$ of the Torrance-Sparrow lobe at normal exitance (R&H eq. 20).

    Multiply by $F(\\mu,\\theta_o)$ for other exitant angles (R&H sec. 5.2); the
    exact numerical spectrum is `torrance_sparrow_spectrum` (it deviates from
    this form by about 0.45σ for l ≤ 1/σ, and is closer to $e^{-\\sigma^2 l(l+1)}$,
    the lobe being a gaussian in θ/2).

    $\\sigma \\le 0$ (or infinite) is an error: a `ValueError` for concrete
    values, a run-time error under `jit` (σ = −0.2 is not σ = 0.2). NaN in,
    NaN out.
    """
    sigma = as_float_array(sigma, "sigma")
    lmax = check_lmax(lmax)
    return _microfacet_filter(_check_sigma(sigma), lmax)


def _microfacet_filter(sigma, lmax: int):
    """`microfacet_spectrum` without its checks: `sigma` an array, `lmax` a checked int."""
    l = jnp.arange(lmax + 1, dtype=sigma.dtype).reshape((1,) * sigma.ndim + (-1,))
    return jnp.exp(-((sigma[..., None] * l) ** 2))


def mirror_spectrum(lmax: int, dtype=None) -> Float[Array, " {lmax}+1"]:
    """$A_l = 1$: the mirror BRDF reparameterized by the reflection vector (R&H eq. 17)."""
    lmax = check_lmax(lmax)
    return jnp.ones(lmax + 1, _default_dtype(dtype))


def legendre_p(u: Real[ArrayLike, "*batch"], lmax: int) -> Float[Array, "*batch {lmax}+1"]:
    """Legendre polynomials $P_0..P_{l_{max}}$ at `u` by the three-term recurrence."""
    u = as_float_array(u, "u")
    lmax = check_lmax(lmax)
    p = [jnp.ones_like(u), u]
    for l in range(1, lmax):
        p.append(((2 * l + 1) * u * p[l] - l * p[l - 1]) / (l + 1))
    return jnp.stack(p[: lmax + 1], axis=-1)


def radial_spectrum(
    f: Callable, lmax: int, n_nodes: int = 256, support: tuple[float, float] = (-1.0, 1.0), dtype=None
) -> Float[Array, " {lmax}+1"]:
    """Numerical $A_l = 2\\pi\\int f(u) P_l(u)\\,du$ of a radially symmetric transfer function.

    `f(u)` is a JAX-traceable function of $u = \\cos\\theta$ (angle from the
    pole) returning the transfer function $\\hat\\rho$ (BRDF × cosine) and is
    integrated by `n_nodes`-point Gauss-Legendre quadrature over `support`
    (pass the interval where $f$ is smooth, e.g. `(0, 1)` for a clamped
    lobe, so the rule converges exponentially). Exact for polynomial $f$ of
    degree ≤ 2·n_nodes − 1 − l. Comparable to `scipy.integrate.quad` per l.
    """
    lmax = check_lmax(lmax)
    n = check_positive_int(n_nodes, "n_nodes")
    a, b = float(support[0]), float(support[1])
    if not (-1.0 <= a < b <= 1.0):
        raise ValueError(f"`support` must satisfy -1 <= a < b <= 1, got {support}")
    x, w = np.polynomial.legendre.leggauss(n)
    u = 0.5 * (b - a) * x + 0.5 * (b + a)
    w = 0.5 * (b - a) * w
    dt = _default_dtype(dtype)
    u = jnp.asarray(u, dt)
    fu = jnp.asarray(f(u), dt)
    if fu.shape != u.shape:
        raise ValueError(f"`f` must map an array of shape {u.shape} to the same shape, got {fu.shape}")
    return 2 * jnp.pi * jnp.einsum("n,nl->l", jnp.asarray(w, dt) * fu, legendre_p(u, lmax))


def recoverable_orders(A: Real[ArrayLike, " L"], noise: float) -> tuple[np.ndarray, int]:
    """Which orders $l$ of the lighting a BRDF spectrum lets inverse lighting recover.

    Inverse lighting divides by $A_l$ (R&H eq. 12): a relative noise level
    $\\epsilon$ in the reflected light is amplified by $\\max|A|/|A_l|$, so order
    $l$ is well-conditioned when $|A_l| > \\epsilon\\max_k|A_k|$. Returns the
    boolean mask per $l$ and $l^*$, the largest $l$ such that every order
    $\\le l$ is recoverable (−1 if none). The papers' predictions follow:
    Lambertian → $l^* = 2$ (for any $\\epsilon < 0.25$, since $A_3 = 0$), Phong →
    $l^* \\approx \\sqrt{2s\\ln(1/\\epsilon)} \\sim \\sqrt s$, microfacet →
    $l^* \\approx \\sqrt{\\ln(1/\\epsilon)}/\\sigma \\sim 1/\\sigma$.
    """
    a = np.abs(np.asarray(A, dtype=np.float64))
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"`A` must have shape (lmax+1,) with lmax >= 0, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"`A` must be finite, got {a[~np.isfinite(a)][:4]}")
    if not noise > 0:
        raise ValueError(f"`noise` must be > 0, got {noise}")
    ok = a > noise * a.max()
    bad = np.nonzero(~ok)[0]
    lstar = (len(a) if bad.size == 0 else int(bad[0])) - 1
    return ok, lstar


def torrance_sparrow_spectrum(
    sigma: Real[ArrayLike, ""],
    lmax: int,
    theta_o: Real[ArrayLike, ""] = 0.0,
    mu: Real[ArrayLike, ""] | None = None,
    n_theta: int = 192,
    n_phi: int = 128,
) -> Float[Array, " {lmax}+1"]:
    """Numerical $A_l$ of the Torrance-Sparrow specular lobe about the reflection vector.

    The specular transfer function of R&H sec. 5.2,
    $\\hat\\rho_s = F\\,S(\\theta_h)/(4\\cos\\theta_o)$ with
    $S = e^{-(\\theta_h/\\sigma)^2}/(\\pi\\sigma^2)$ (zero below the horizon),
    for a view at exitant angle `theta_o`, projected onto the zonal harmonics
    about the reflection vector $R$: $A_l = \\int \\hat\\rho_s(\\omega)
    P_l(\\omega\\cdot R)\\,d\\omega$ (the m = 0 part; the lobe is exactly symmetric
    about $R$ only at normal exitance). Quadrature: Gauss-Legendre in
    $\\cos$ of the angle from $R$ on $[\\cos(\\min(\\pi, 12\\sigma)), 1]$ ×
    the lit arc of azimuth, both split where the horizon starts to cut the lobe
    (`n_theta` nodes on each side, `n_phi` on the arc), so every part is
    smooth: against a brute-force integral in the normal frame, σ = 0.3,
    errors ≤ 1e-12 at $\\theta_o$ = 0, 1.0 and 1.4 (a uniform azimuth over the
    horizon's jump gave 1.9e-4 and 1.4e-3 at 1.0 and 1.4). R&H eq. 20
    approximates this by $\\exp(-(\\sigma l)^2)$ (times $F(\\mu, \\theta_o)$ if
    `mu` is given).

    **Arguments:** `sigma` > 0; `theta_o` in $[0, \\pi/2)$; `mu` ≥ 1 (the
    index of refraction) or None; all scalars. Out-of-range values are an
    error (`ValueError`, or a run-time error under `jit`); NaN in, NaN out.

    **Returns:** `(lmax+1,)`, in the dtype of the array arguments: Python
    scalars (the default `theta_o=0.0` included) adopt it, so a float32
    `sigma` gives float32; float32 with float64 gives float64.
    """
    from ._reflectance import fresnel_normalized  # local import: optional coupling

    sigma = as_float_array(sigma, "sigma")
    theta_o = as_float_array(theta_o, "theta_o")
    lmax = check_lmax(lmax)
    for name, a in (("sigma", sigma), ("theta_o", theta_o)):
        if a.shape != ():
            raise ValueError(f"`{name}` must be a scalar (shape ()), got shape {tuple(a.shape)}")
    sigma = _check_sigma(sigma)
    theta_o = check_values(theta_o, lambda a: (a < 0) | (a >= jnp.pi / 2), "theta_o", "in [0, pi/2) (an exitant angle)")
    if mu is not None:
        mu = as_float_array(mu, "mu")
        if mu.shape != ():
            raise ValueError(f"`mu` must be a scalar (shape ()) or None, got shape {tuple(mu.shape)}")
        mu = check_values(mu, lambda a: (a < 1) | (a == jnp.inf), "mu", "in [1, inf) (an index of refraction)")
    nt = check_positive_int(n_theta, "n_theta")
    npf = check_positive_int(n_phi, "n_phi")
    # of the arrays, not of their dtypes: a Python scalar (weakly typed) adopts the others' dtype
    dt = common_dtype(sigma, theta_o) if mu is None else common_dtype(sigma, theta_o, mu)
    sigma, theta_o = sigma.astype(dt), theta_o.astype(dt)
    if mu is not None:
        mu = mu.astype(dt)
    x, wx = np.polynomial.legendre.leggauss(nt)
    xp, wp = np.polynomial.legendre.leggauss(npf)
    st, ct = jnp.sin(theta_o), jnp.cos(theta_o)
    # cos of the angle from R: [umin, 1], split where the horizon starts to cut the cone about R (angle
    # pi/2 - theta_o, u = sin theta_o): inside it every azimuth is lit, outside only |phi| < phi*(u), so each
    # part is smooth and gets its own Gauss-Legendre rule (one rule across the kink converged like 1/n)
    umin = jnp.cos(jnp.minimum(12.0 * sigma, jnp.pi)).astype(dt)  # the lobe beyond 12σ is below e^-36
    umin = jnp.maximum(umin, -st)  # beyond the angle pi/2 + theta_o from R no direction is above the horizon
    uc = jnp.clip(st, umin, 1.0)
    xs, ws = jnp.asarray(x, dt), jnp.asarray(wx, dt)
    # on the cut part the arc's half-width phi* goes like sqrt(distance) at both ends (pi - c sqrt(uc - u) at
    # uc; c sqrt(u + sin theta_o) where the cone leaves the hemisphere): u = umin + (uc - umin)(1 - cos pi t)/2
    # makes it smooth in t (errors 1e-12, against 3e-6 at theta_o = 1.4 with the rule in u)
    t = 0.5 * (xs + 1.0)
    u_cut = umin + 0.5 * (uc - umin) * (1.0 - jnp.cos(jnp.pi * t))
    w_cut = 0.5 * ws * 0.5 * (uc - umin) * jnp.pi * jnp.sin(jnp.pi * t)
    u = jnp.concatenate([u_cut, 0.5 * (1 - uc) * xs + 0.5 * (1 + uc)])
    wu = jnp.concatenate([w_cut, 0.5 * (1 - uc) * ws])
    # Frame: normal n = +z, view in the xz plane at theta_o; R = reflect(view) = (-sin, 0, cos); about R,
    # w = u R + sqrt(1-u^2) (cos phi e1 + sin phi e2) has cos_i = u ct + sqrt(1-u^2) st cos phi, lit for
    # |phi| < phi* = arccos(-u ct / (sqrt(1-u^2) st)): the azimuthal rule covers that arc only (exactly, no
    # jump inside it; the integrand is even in phi)
    wo = jnp.stack([st, jnp.zeros_like(st), ct])
    r = jnp.stack([-st, jnp.zeros_like(st), ct])
    e1 = jnp.stack([ct, jnp.zeros_like(st), st])  # ⟂ R, in the plane
    e2 = jnp.array([0.0, 1.0, 0.0], dt)
    sv = jnp.sqrt(jnp.clip(1 - u * u, 0.0))
    tiny = jnp.finfo(dt).tiny
    phi_max = jnp.arccos(jnp.clip(-u * ct / jnp.maximum(sv * st, tiny), -1.0, 1.0))  # (2 nt,)
    phi = phi_max[:, None] * jnp.asarray(xp, dt)[None, :]
    cp, sp = jnp.cos(phi), jnp.sin(phi)
    sv = sv[:, None]
    wi = u[:, None, None] * r[None, None, :] + (sv * cp)[..., None] * e1[None, None, :] + (sv * sp)[..., None] * e2[None, None, :]  # (2 nt, np, 3)
    cos_i = wi[..., 2]
    h = wi + wo[None, None, :]  # the half vector, unnormalized: its angle from n by atan2 (no arccos near 1)
    theta_h = jnp.arctan2(jnp.sqrt(h[..., 0] ** 2 + h[..., 1] ** 2), h[..., 2])
    s = jnp.exp(-((theta_h / sigma) ** 2)) / (jnp.pi * sigma**2)
    f = jnp.where(cos_i > 0, s / (4 * ct), 0.0)
    if mu is not None:
        f = f * fresnel_normalized(ct, mu)
    fz = jnp.sum(f * jnp.asarray(wp, dt)[None, :], axis=1) * phi_max  # azimuthal integral over the lit arc, (2 nt,)
    return jnp.einsum("n,nl->l", wu * fz, legendre_p(u, lmax))
