"""Sampling grids on the sphere, with quadrature weights.

Conventions (docs/conventions.md): polar angle θ from +z, azimuth φ from +x towards +y.

| grid | rows (θ) | columns (φ) | exact for |
|---|---|---|---|
| lat-long, H×W | θ_i = π(i+½)/H (Fejér's first rule, ducc0 "F1") | φ_j = 2π(j+½)/W | products of band-limited functions of total degree < H in θ and < W in φ (analysis of lmax < H/2, W > 2 lmax) |
| Gauss-Legendre, n×W | cos θ_i = Gauss-Legendre nodes (θ ascending) | φ_j = 2πj/W | total degree ≤ 2n-1 in cos θ |
| angular map, S×S | Debevec light-probe layout, see `angular_map_directions` | | pixel-centre rule |

Sizes are static Python ints; every grid is built in NumPy float64 at trace
time and returned in `dtype` (default: JAX's default float; float32 or
float64, float16 is a `ValueError` — see `jaxsh._checks`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._checks import check_dtype, check_positive_int


def _out(x, dtype):
    return jnp.asarray(x, dtype=check_dtype(dtype))


def latlong_angles(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre angles of an `(height, width)` lat-long map (NumPy float64).

    Row `i` ↔ θ = π(i+½)/H (row 0 next to +z), column `j` ↔ φ = 2π(j+½)/W.
    Returns `(theta (H,), phi (W,))`.
    """
    h = check_positive_int(height, "height")
    w = check_positive_int(width, "width")
    return np.pi * (np.arange(h) + 0.5) / h, 2 * np.pi * (np.arange(w) + 0.5) / w


def _dirs_from_angles(theta, phi):
    st = np.sin(theta)[:, None]
    return np.stack(
        np.broadcast_arrays(st * np.cos(phi)[None, :], st * np.sin(phi)[None, :], np.cos(theta)[:, None]),
        axis=-1,
    )


def latlong_directions(height: int, width: int, dtype=None) -> Float[Array, "H W 3"]:
    """Unit directions of the pixel centres of a lat-long (equirectangular) map.

    Row `i` ↔ θ = π(i+½)/H (row 0 at +z), column `j` ↔ φ = 2π(j+½)/W, and
    $\\omega = (\\sin\\theta\\cos\\phi, \\sin\\theta\\sin\\phi, \\cos\\theta)$.

    **Returns:** shape `(height, width, 3)`.
    """
    theta, phi = latlong_angles(height, width)
    return _out(_dirs_from_angles(theta, phi), dtype)


def fejer1_weights(n: int) -> np.ndarray:
    """Fejér's first quadrature rule on [-1, 1] in $\\cos\\theta$, nodes θ_k = π(k+½)/n.

    $$w_k = \\frac{2}{n}\\Big(1 - 2\\sum_{j=1}^{\\lfloor n/2\\rfloor}
         \\frac{\\cos(2j\\theta_k)}{4j^2-1}\\Big),$$

    exact for polynomials in $\\cos\\theta$ of degree < n (on the sphere:
    $\\int_0^\\pi f(\\theta)\\sin\\theta\\,d\\theta$ for cosine polynomials
    $f = \\sum_{k<n} a_k\\cos k\\theta$; not for sine terms: n = 8 gives
    1.56988 for $\\int_0^\\pi \\sin^2\\theta\\,d\\theta = \\pi/2$).
    The weights sum to 2. Returned as NumPy float64, shape `(n,)`. Comparable
    to `ducc0.sht.get_gridweights("F1", n) / (2π)` (ducc0's weights include
    the longitude step and sum to 4π).

    ??? cite "References"
        Waldvogel, J. (2006). Fast construction of the Fejér and Clenshaw–Curtis
        quadrature rules. BIT 46, 195–202. doi:10.1007/s10543-006-0045-4
    """
    n = check_positive_int(n, "n")
    theta = np.pi * (np.arange(n) + 0.5) / n
    j = np.arange(1, n // 2 + 1)
    s = np.cos(2 * np.outer(theta, j)) / (4.0 * j * j - 1.0)
    return (2.0 / n) * (1.0 - 2.0 * s.sum(axis=1))


def latlong_weights(height: int, width: int, dtype=None) -> Float[Array, "H W"]:
    """Solid-angle quadrature weights of the lat-long grid (they sum to 4π).

    $w_{ij} = w^{F1}_i \\cdot 2\\pi/W$ with Fejér's first-rule weights in θ:
    $\\sum_{ij} w_{ij} f(\\omega_{ij}) = \\int_{S^2} f\\,d\\omega$ exactly for
    band-limited $f$ of degree < H in θ and < W in φ — unlike the plain
    $\\sin\\theta\\,\\Delta\\theta\\,\\Delta\\phi$ weights, which are only
    second-order accurate.

    **Returns:** shape `(height, width)`.
    """
    h = check_positive_int(height, "height")
    w = check_positive_int(width, "width")
    return _out(np.repeat((fejer1_weights(h) * (2 * np.pi / w))[:, None], w, axis=1), dtype)


def gauss_legendre_grid(n_theta: int, n_phi: int, dtype=None) -> tuple[Float[Array, "T P 3"], Float[Array, "T P"]]:
    """Gauss-Legendre grid: `n_theta` nodes in $\\cos\\theta$, `n_phi` uniform in φ.

    θ increases with the row (row 0 nearest +z); φ_j = 2πj/n_phi. The weights
    (summing to 4π) integrate exactly every polynomial of degree
    ≤ 2·n_theta − 1 in $\\cos\\theta$ times trigonometric polynomials of degree
    < n_phi in φ; so SH products up to $l + l' \\le 2 n_\\theta - 1$ with
    $n_\\phi > l + l'$.

    **Returns:** `(dirs (n_theta, n_phi, 3), weights (n_theta, n_phi))`.
    """
    nt = check_positive_int(n_theta, "n_theta")
    npf = check_positive_int(n_phi, "n_phi")
    z, w = np.polynomial.legendre.leggauss(nt)
    z, w = z[::-1], w[::-1]
    theta = np.arccos(z)
    phi = 2 * np.pi * np.arange(npf) / npf
    dirs = _dirs_from_angles(theta, phi)
    dirs[..., 2] = z[:, None]
    weights = np.repeat((w * 2 * np.pi / npf)[:, None], npf, axis=1)
    return _out(dirs, dtype), _out(weights, dtype)


def angular_map_directions(
    size: int, dtype=None
) -> tuple[Float[Array, "S S 3"], Float[Array, "S S"], Bool[Array, "S S"]]:
    """Directions and pixel solid angles of a Debevec angular map (light probe).

    Pixel `(i, j)` (row, column) of a `size × size` map has image coordinates
    $u = 2(j+\\tfrac12)/S - 1$ (right) and $v = 1 - 2(i+\\tfrac12)/S$ (up),
    $r = \\sqrt{u^2+v^2}$. The angle from the map's central direction is
    $\\pi r$, so the centre of the image looks along $-z$ and the rim of the
    disk ($r = 1$) along $+z$:

    $$\\omega = (\\sin(\\pi r)\\,u/r,\\ \\sin(\\pi r)\\,v/r,\\ -\\cos(\\pi r)).$$

    These are the file's own axes (x right, y up, the centre looking along
    −z, as Debevec's probes); convert to the library's +z-up world with an
    explicit rotation (`jaxsh.io.read_envmap(..., up="+y")`).

    The solid angle of a pixel is $(2/S)^2\\,\\pi\\sin(\\pi r)/r$ (the Jacobian of
    the map; $\\pi^2$ at the centre) inside the disk and 0 outside it.

    **Returns:** `(dirs (S, S, 3), solid_angle (S, S), inside (S, S) bool)`;
    outside the disk `dirs` is $+z$ (a valid direction) and the weight 0.

    ??? cite "References"
        Debevec, P. (1998). Rendering synthetic objects into real scenes.
        SIGGRAPH 98, 189–198. doi:10.1145/280814.280864 (angular map format
        of the light probe gallery).
    """
    s = check_positive_int(size, "size")
    c = 2 * (np.arange(s) + 0.5) / s - 1
    u = np.broadcast_to(c[None, :], (s, s))
    v = np.broadcast_to(-c[:, None], (s, s))
    r = np.hypot(u, v)
    inside = r <= 1.0
    t = np.pi * r
    sinc = np.sinc(r)  # sin(pi r) / (pi r)
    dirs = np.stack([np.pi * sinc * u, np.pi * sinc * v, -np.cos(t)], axis=-1)
    dirs = np.where(inside[..., None], dirs, np.array([0.0, 0.0, 1.0]))
    solid = np.where(inside, (2.0 / s) ** 2 * np.pi * np.pi * sinc, 0.0)
    return _out(dirs, dtype), _out(solid, dtype), jnp.asarray(inside)
