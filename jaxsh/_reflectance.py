"""Angular BRDF models, Fresnel terms and half/difference coordinates.

Conventions (docs/conventions.md): all directions are unit 3-vectors pointing *away*
from the surface — `wi` towards the light ($\\omega_i$, "L"), `wo` towards the
viewer ($\\omega_o$) — and `n` is the unit surface normal. Every model returns
the BRDF value $\\rho(\\omega_i, \\omega_o)$ itself (not multiplied by the
cosine); the transfer function of R&H 2001 is $\\hat\\rho = \\rho\\cos\\theta_i$.

Every function takes one sample with arbitrary leading batch dimensions:
vectors `(..., 3)`, scalar parameters `(...)`; the leading dimensions of all
arguments are broadcast together explicitly (no implicit rank promotion), and
the result has the broadcast batch shape. The dtype follows the inputs
(float32 stays float32; Python scalars adopt the dtype of the arrays). The
continuous parameters are traced arrays: they can be differentiated and
vmapped, and a new value never triggers a new trace. Directions are *not*
normalized here: pass unit vectors.

**Invalid parameters and NaN.** A parameter outside its domain — a
roughness $\\sigma \\le 0$ (Torrance–Sparrow), $m \\le 0$ (Cook–Torrance),
$\\alpha \\le 0$ (Ward), $\\sigma < 0$ (Oren–Nayar), a Phong exponent
$s \\le -1$, a relative index $\\mu < 1$ in a BRDF or $\\mu \\le 0$ in
`fresnel_*` — is an error, never a finite number: `ValueError` naming the
parameter when its value is concrete, `equinox.error_if` when it is traced
(under `jit`, `vmap`, `grad`). NaN parameters are not checked: they
propagate to NaN outputs, as in `jax.numpy` (a NaN $\\mu$ gave the value
without Fresnel, its test read as total internal reflection). A NaN
*direction* fails the horizon test like one below it: the value is 0.

**Below the horizon.** Every model returns exactly 0 when
$\\omega_i\\cdot n \\le 0$ or $\\omega_o\\cdot n \\le 0$. The model is then
evaluated at a harmless substitute configuration ($\\omega_i = \\omega_o = n =
+z$: $n$ too, since a G-buffer miss has a zero normal) and discarded (the
"double `where`"), so gradients with respect to directions and parameters
are finite — and zero — there too (with $n$ the normal's substitute was $n$
itself, and a zero normal gave NaN gradients).

**Singular configurations** inside the domain (the half vector along the
normal, $\\theta_h = 0$; light and view directions equal, $\\theta_d = 0$; a
direction along the normal, where its azimuth is undefined) are handled by
safe norms and safe `atan2`s that return finite values and finite
gradients: an undefined azimuth is reported as 0.

??? cite "References"
    Ramamoorthi, R., Hanrahan, P. (2001). A signal-processing framework for
    inverse rendering. SIGGRAPH 2001, 117–128. doi:10.1145/383259.383271
    (sec. 5.2: Lambertian, normalized Phong, microfacet BRDFs).

    Ramamoorthi, R. (2002). A signal-processing framework for forward and
    inverse rendering. PhD thesis, Stanford University, ch. 3
    (eqs. 3.34 Phong, 3.42 microfacet).

    Zickler, T., Ramamoorthi, R., Enrique, S., Belhumeur, P. N. (2006).
    Reflectance sharing: predicting appearance from a sparse set of images
    of a known shape. IEEE TPAMI 28(8), 1287–1302. doi:10.1109/TPAMI.2006.170
    (sec. 2.2 and eq. 7: the $(u, v, w)$ parameterization).

    Rusinkiewicz, S. (1998). A new change of variables for efficient BRDF
    representation. Rendering Techniques '98, 11–22.
    doi:10.1007/978-3-7091-6453-2_2

    Cook, R. L., Torrance, K. E. (1982). A reflectance model for computer
    graphics. ACM TOG 1(1), 7–24. doi:10.1145/357290.357293

    Walter, B., Marschner, S. R., Li, H., Torrance, K. E. (2007). Microfacet
    models for refraction through rough surfaces. EGSR 2007, 195–206.
    doi:10.2312/EGWR/EGSR07/195-206 (normalization of the Beckmann $D$ and
    the $1/(4\\cos\\theta_i\\cos\\theta_o)$ factor).

    Ward, G. J. (1992). Measuring and modeling anisotropic reflection.
    SIGGRAPH 1992, 265–272. doi:10.1145/133994.134078

    Oren, M., Nayar, S. K. (1994). Generalization of Lambert's reflectance
    model. SIGGRAPH 1994, 239–246. doi:10.1145/192161.192213

    Lafortune, E. P. F., Foo, S.-C., Torrance, K. E., Greenberg, D. P. (1997).
    Non-linear approximation of reflectance functions. SIGGRAPH 1997,
    117–126. doi:10.1145/258734.258801

    Duff, T. et al. (2017). Building an orthonormal basis, revisited.
    JCGT 6(1), 1–8 (the tangent frame of `tangent_frame`).

    Born, M., Wolf, E. *Principles of Optics*, 7th ed., sec. 1.5.2 (Fresnel
    formulae).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

from ._compile import jit
from ._checks import error_if_any, as_float_array, check_dirs, common_dtype

_PI = math.pi
_TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------- input handling


def _as_param(x, name: str):
    """A float parameter; Python scalars stay weakly typed (adopt the arrays' dtype)."""
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return jnp.asarray(float(x))
    return as_float_array(x, name)


def _common_dtype(arrays):
    return common_dtype(*arrays)  # Python scalars adopt the arrays' dtype; strict promotion: the widest


def _prepare(args):
    """Convert, check and broadcast arguments.

    `args` is a list of `(name, value, kind)` with kind "dir" (shape (..., 3)),
    "scalar" (shape (...)) or "lobes" (shape (..., K, 3)). Returns the arrays,
    all of one dtype, with their batch parts broadcast to a common shape.
    """
    arrays, cores = [], []
    for name, value, kind in args:
        if kind == "dir":
            a = check_dirs(value, name)
            core = 1
        elif kind == "lobes":
            a = as_float_array(value, name)
            if a.ndim < 2 or a.shape[-1] != 3:
                raise ValueError(
                    f"`{name}` must have shape (K, 3) or (..., K, 3) with rows (Cx, Cz, n), "
                    f"got {tuple(a.shape)}"
                )
            core = 2
        else:
            a = _as_param(value, name)
            core = 0
        arrays.append(a)
        cores.append(core)
    batch = ()
    for (name, _, _), a, core in zip(args, arrays, cores):
        part = a.shape[: a.ndim - core]
        try:
            batch = jnp.broadcast_shapes(batch, part)
        except ValueError:
            raise ValueError(
                f"the leading (batch) dimensions of `{name}`, {part}, do not broadcast "
                f"with those of the previous arguments, {batch}"
            ) from None
    dtype = _common_dtype(arrays)
    out = []
    for a, core in zip(arrays, cores):
        a = a.astype(dtype)
        out.append(jnp.broadcast_to(a, batch + a.shape[a.ndim - core :]))
    return out


def _require(x, bad, name: str, expected: str):
    """`x`, with entries where `bad(x)` an error: `ValueError` when concrete, `equinox.error_if` when traced.

    NaN is not "bad" (it propagates, module docstring): `bad` compares, and comparisons with NaN are False.
    """
    if isinstance(x, jax.core.Tracer):
        return error_if_any(x, bad(x), f"`{name}` must be {expected}")
    a = np.asarray(x)
    m = np.asarray(bad(a))
    if m.any():
        raise ValueError(f"`{name}` must be {expected}, got {a[m].ravel()[0] if a.ndim else a[()]}")
    return x


def _positive(x, name):
    return _require(x, lambda a: a <= 0, name, "> 0")


def _index(x, name, lo=1.0):
    return _require(x, lambda a: a < lo, name, f">= {lo:g} (a relative index of refraction)")


def _phong_exponent(x, name):
    return _require(x, lambda a: a <= -1, name, "> -1 (the Phong exponent)")


def _nonnegative_roughness(x, name):
    return _require(x, lambda a: a < 0, name, ">= 0 (0: Lambertian)")


def _brdf_args(wi, wo, n, params: dict, checks: dict | None = None):
    """The BRDF arguments: directions `wi`, `wo`, `n` and the named parameters, converted, checked, broadcast.

    `params` maps a parameter name to its value (`None` values, e.g.
    `mu=None`, are left out; `lobes` is `(..., K, 3)`, the others scalars
    `(...)`); `checks` maps a name to its range check `check(array, name)`
    (`_positive`, `_index`, ...: a `ValueError` or `equinox.error_if`).
    Returns `(wi, wo, n, {name: array})`, all of one dtype (`_prepare`).
    """
    names = [k for k, v in params.items() if v is not None]
    out = _prepare([("wi", wi, "dir"), ("wo", wo, "dir"), ("n", n, "dir")]
                   + [(k, params[k], "lobes" if k == "lobes" else "scalar") for k in names])
    checks = checks or {}
    vals = {k: checks[k](a, k) if k in checks else a for k, a in zip(names, out[3:])}
    return out[0], out[1], out[2], vals


def _fresnel_args(cos_theta, mu):
    """`(cos_theta, mu)` converted and broadcast, `mu > 0` checked (`fresnel_dielectric`, `fresnel_normalized`)."""
    c, mu = _prepare([("cos_theta", cos_theta, "scalar"), ("mu", mu, "scalar")])
    return c, _positive(mu, "mu")


# --------------------------------------------------------------------------- safe primitives


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _safe_sqrt(x):
    """sqrt(max(x, 0)) with a finite (zero) gradient at x <= 0."""
    ok = x > 0.0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def _safe_normalize(v, fallback):
    """v/|v|, or `fallback` where |v| = 0 (finite gradients everywhere)."""
    n2 = _dot(v, v)[..., None]
    ok = n2 > 0.0
    inv = jax.lax.rsqrt(jnp.where(ok, n2, 1.0))
    return jnp.where(ok, v * inv, fallback)


def _safe_atan2(y, x):
    """atan2(y, x), with 0 (and zero gradient) at the undefined point x = y = 0."""
    ok = (x * x + y * y) > 0.0
    return jnp.arctan2(jnp.where(ok, y, 0.0), jnp.where(ok, x, 1.0))


def _wrap_2pi(phi):
    """Map atan2 output (-π, π] to [0, 2π)."""
    phi = jnp.where(phi < 0.0, phi + _TWO_PI, phi)
    return jnp.where(phi >= _TWO_PI, phi - _TWO_PI, phi)


def _reflect(v, n):
    return 2.0 * _dot(n, v)[..., None] * n - v


_reflect_jit = jit(_reflect)


def _frame(n):
    """Right-handed orthonormal (t, b) with t × b = n (Duff et al. 2017, listing 3)."""
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    sign = jnp.where(nz >= 0.0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    t = jnp.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], axis=-1)
    bb = jnp.stack([b, sign + ny * ny * a, -ny], axis=-1)
    return t, bb


def _frame_from_tangent(n, t):
    t = t - _dot(t, n)[..., None] * n
    t0, _ = _frame(n)
    t = _safe_normalize(t, t0)
    return t, jnp.cross(n, t)


def _to_local(w, t, b, n):
    return jnp.stack([_dot(w, t), _dot(w, b), _dot(w, n)], axis=-1)


# --------------------------------------------------------------------------- geometry


def reflect(v: Real[ArrayLike, "*#batch 3"], n: Real[ArrayLike, "*#batch 3"]) -> Float[Array, "*batch 3"]:
    """Mirror a direction about the normal: $R = 2(n\\cdot v)\\,n - v$.

    With `v` the view direction $\\omega_o$ this is the reflection vector
    $\\vec R$ of R&H 2001 sec. 5.2 (Phong) and the direction a mirror BRDF
    reflects into.

    **Arguments:** `v`, `n`: shape `(..., 3)` (broadcast); `n` must be unit.

    **Returns:** `(..., 3)`.
    """
    v, n = _prepare([("v", v, "dir"), ("n", n, "dir")])
    return _reflect_jit(v, n)


def mirror_direction(wo: Real[ArrayLike, "*#batch 3"], n: Real[ArrayLike, "*#batch 3"]) -> Float[Array, "*batch 3"]:
    """The incident direction seen by a perfect mirror: `reflect(wo, n)`.

    The mirror BRDF is a delta, $\\rho = \\delta(\\omega_i - R(\\omega_o))/\\cos\\theta_i$
    (R&H 2001 eq. 14; thesis eqs. 3.23–3.27), so its transfer function is
    $\\delta(\\omega_i - R)$ and $B(\\omega_o) = L(R(\\omega_o))$. It cannot be
    evaluated pointwise; render a mirror by looking the lighting up in this
    direction.
    """
    v, n = _prepare([("wo", wo, "dir"), ("n", n, "dir")])
    return _reflect_jit(v, n)


def half_vector(wi: Real[ArrayLike, "*#batch 3"], wo: Real[ArrayLike, "*#batch 3"]) -> Float[Array, "*batch 3"]:
    """The half-way vector $\\omega_h = (\\omega_i + \\omega_o)/\\|\\omega_i + \\omega_o\\|$.

    Undefined when $\\omega_i = -\\omega_o$; the zero vector is returned
    there (with finite gradients).

    **Returns:** `(..., 3)`.
    """
    wi, wo = _prepare([("wi", wi, "dir"), ("wo", wo, "dir")])
    return _half_vector(wi, wo)


@jit
def _half_vector(wi, wo):
    s = wi + wo
    return _safe_normalize(s, jnp.zeros_like(s))


def _epsilon(dtype) -> float:
    """Threshold of the small-angle (Taylor) branches, by precision.

    As jaxlie's `get_epsilon` (`jaxlie/utils/_utils.py`, commit 0b6655fb):
    1e-5 for 32-bit floats and below, 1e-10 for float64.
    """
    return 1e-10 if jnp.finfo(dtype).bits >= 64 else 1e-5


def _half_angle_parts(h, n):
    """$(|h\\times n|^2,\\ h\\cdot n)$ for a half vector $h$ of any length (θh is scale-free in h).

    THE half-angle geometry of every model here: $\\tan^2\\theta_h = s_2/c^2$
    (`cook_torrance`, `ward_isotropic`) and $\\theta_h^2$ (`_theta_h_sq`:
    `torrance_sparrow`, `half_angle`, hence the renderers of R&H eq. 23).
    """
    shape = jnp.broadcast_shapes(h.shape, n.shape)
    h = jnp.broadcast_to(h, shape)
    n = jnp.broadcast_to(n, shape)
    x = jnp.cross(h, n)
    return _dot(x, x), _dot(h, n)


def _pair_component(d, k: int):
    """Component `k` of directions shared by every pixel, `(J, 3)` -> `(1, J)`, or per pixel, given as the tuple of
    their three components `(N, J)` -> `(N, J)` (XLA:CPU vectorizes those, not a minor axis of 3)."""
    return d[k] if isinstance(d, tuple) else d[None, :, k]


def _half_angle_pairs(d, n, v=None):
    """`_half_angle_parts` of every pair of a direction `d` `(J, 3)` and a pixel (normal `n`, view `v` `(N, 3)`):
    $(|h\\times n|^2,\\ h\\cdot n)$ `(N, J)` with $h = d_j + v_i$ ($h = d_j$ with `v=None`), by components, with no
    `(N, J, 3)` array (the fast sources of the practical model, the reference renderer's pairs). `d` may also be
    per pixel, the tuple of its components `(N, J)` (the reference renderer's disk nodes clipped at each pixel's
    horizon)."""
    h = [_pair_component(d, k) if v is None else _pair_component(d, k) + v[:, k : k + 1] for k in range(3)]
    nx, ny, nz = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    cx = h[1] * nz - h[2] * ny
    cy = h[2] * nx - h[0] * nz
    cz = h[0] * ny - h[1] * nx
    return cx * cx + cy * cy + cz * cz, h[0] * nx + h[1] * ny + h[2] * nz


def _theta_h_sq(s2, c):
    """$\\theta_h^2 = \\operatorname{atan2}(\\sqrt{s_2}, c)^2$, smooth and gradient-safe everywhere.

    $\\theta_h$ itself is a cone at $\\theta_h = 0$ ($|x|$-like: no
    derivative there) but $\\theta_h^2$ is smooth. With $t = s_2/c^2 =
    \\tan^2\\theta_h$ below a dtype-dependent epsilon (and $c > 0$) it is
    the Taylor series $\\arctan^2\\sqrt t = t - \\tfrac23 t^2 + O(t^3)$ (no
    square root: exact derivatives of all orders at 0, and relative error
    $\\tfrac{23}{45}t^2 < 10^{-10}$); elsewhere the atan2 form, accurate near
    0 where arccos of a dot product loses half the digits. Each branch sees
    inputs substituted by `where` so that the other branch's singularities
    (√0, atan2(0, 0)) never reach the gradient: the double-`where` trick of
    jaxlie `_so3.py` (`SO3.log`, commit 0b6655fb). $h = 0$ gives 0.
    """
    small = (c > 0.0) & (s2 < _epsilon(c.dtype) * c * c)
    c_small = jnp.where(small, c, 1.0)
    t = jnp.where(small, s2, 0.0) / (c_small * c_small)
    taylor = t * (1.0 - (2.0 / 3.0) * t)
    theta = _safe_atan2(_safe_sqrt(jnp.where(small, 1.0, s2)), jnp.where(small, 1.0, c))
    return jnp.where(small, taylor, theta * theta)


def _half_angle(wi, wo, n):
    """θh of unit `wi`, `wo`, `n` (broadcast): the renderers' kernel, see `half_angle`."""
    return _safe_sqrt(_theta_h_sq(*_half_angle_parts(wi + wo, n)))


_half_angle_jit = jit(_half_angle)


def half_angle(wi: Real[ArrayLike, "*#batch 3"], wo: Real[ArrayLike, "*#batch 3"], n: Real[ArrayLike, "*#batch 3"]) -> Float[Array, "*batch"]:
    """The half angle $\\theta_h = \\angle(\\omega_i + \\omega_o, n)$ of R&H eq. 23, gradient-safe.

    Computed as $\\sqrt{\\theta_h^2}$ with $\\theta_h^2$ from
    $\\operatorname{atan2}(|h \\times n|, h \\cdot n)$, $h = \\omega_i + \\omega_o$,
    and a Taylor branch near 0 (`_theta_h_sq`): exact to rounding (also
    at and near $\\theta_h = 0$, where the specular lobe of eq. 23 is
    evaluated), and finite gradients everywhere: at $\\theta_h = 0$, where
    $\\theta_h$ is a cone with no derivative, the gradient is 0 (so the
    gradient of $e^{-(\\theta_h/\\sigma)^2}$ is its true value, 0). `wi`,
    `wo`, `n` are unit vectors broadcasting against each other (no
    normalization: this is the inner kernel of `render_practical`,
    `practical_terms`, `torrance_sparrow` and `solvers.factorize`); 0 where
    $\\omega_i = -\\omega_o$.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`, validated as in
    `torrance_sparrow`: another last axis, or leading (batch) dimensions that
    do not broadcast, are a `ValueError` naming the argument; integer input
    goes to the default float, float16/bfloat16 and complex input are a
    `ValueError`; float32 stays float32 (several dtypes: the widest).

    **Returns:** `(...)`, the broadcast batch shape.
    """
    wi, wo, n = _prepare([("wi", wi, "dir"), ("wo", wo, "dir"), ("n", n, "dir")])
    return _half_angle_jit(wi, wo, n)


def tangent_frame(
    n: Real[ArrayLike, "*#batch 3"], t: Real[ArrayLike, "*#batch 3"] | None = None
) -> tuple[Float[Array, "*batch 3"], Float[Array, "*batch 3"]]:
    """A right-handed orthonormal frame $(t, b, n)$ around a unit normal.

    With `t=None` the tangent is the branch-free construction of Duff et al.
    (2017), continuous except across $n_z = 0$ (fine for isotropic BRDFs,
    which do not depend on it). A given `t` is made orthogonal to `n`
    (Gram–Schmidt) and normalized; $b = n \\times t$.

    **Returns:** `(t, b)`, each `(..., 3)`, with $t \\times b = n$.
    """
    if t is None:
        (n,) = _prepare([("n", n, "dir")])
    else:
        n, t = _prepare([("n", n, "dir"), ("t", t, "dir")])
    return _tangent_frame(n, t)


@jit
def _tangent_frame(n, t):
    return _frame(n) if t is None else _frame_from_tangent(n, t)


def _rusinkiewicz_local(wi, wo):
    """(θh, φh, θd, φd) of local-frame directions (normal +z, tangent +x).

    θd is the angle between ωi and the half vector h, taken from the two
    smooth quantities $\\cos\\theta_d = h\\cdot\\omega_i$ and
    $\\sin\\theta_d = |h\\times\\omega_i|$ (the z component and the length of the
    xy part of $d = R_y(-\\theta_h)R_z(-\\phi_h)\\,\\omega_i$, which the rotation
    preserves). No azimuth of h enters, so its gradient is right at
    θh = 0 (the mirror configuration): there φh is undefined, and the
    rotated frame used below for φd alone falls back to φh = 0, a frame
    that does not follow h (which made the old `dz` lose its derivative).
    """
    ez = jnp.zeros_like(wi).at[..., 2].set(1.0)
    h = _safe_normalize(wi + wo, ez)
    hx, hy, hz = h[..., 0], h[..., 1], h[..., 2]
    sin_h = _safe_sqrt(hx * hx + hy * hy)
    theta_h = jnp.arctan2(sin_h, hz)
    phi_h = _safe_atan2(hy, hx)
    # θd = atan2(|h × ωi|, h · ωi): smooth in (ωi, ωo) wherever θd > 0, θh = 0 included
    hxw = jnp.cross(h, wi)
    theta_d = jnp.arctan2(_safe_sqrt(_dot(hxw, hxw)), _dot(h, wi))
    # cos φh, sin φh; (1, 0) where φh is undefined (h along the normal).
    ok = sin_h > 0.0
    inv = 1.0 / jnp.where(ok, sin_h, 1.0)
    cph = jnp.where(ok, hx * inv, 1.0)
    sph = jnp.where(ok, hy * inv, 0.0)
    # the x, y components of d = R_y(-θh) R_z(-φh) ωi (Rusinkiewicz 1998, sec. 3), for φd
    x, y, z = wi[..., 0], wi[..., 1], wi[..., 2]
    a = cph * x + sph * y
    dy = -sph * x + cph * y
    dx = hz * a - sin_h * z
    phi_d = _safe_atan2(dy, dx)
    return theta_h, _wrap_2pi(phi_h), theta_d, _wrap_2pi(phi_d)


def rusinkiewicz_angles(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    t: Real[ArrayLike, "*#batch 3"] | None = None,
) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"], Float[Array, "*batch"], Float[Array, "*batch"]]:
    """Half/difference angles $(\\theta_h, \\phi_h, \\theta_d, \\phi_d)$ (Rusinkiewicz 1998).

    In the local frame $(t, b, n)$: $\\omega_h$ = `half_vector(wi, wo)` has
    spherical angles $(\\theta_h, \\phi_h)$, and the difference vector
    $d = R_b(-\\theta_h)\\,R_n(-\\phi_h)\\,\\omega_i$ (the light direction
    seen from a frame in which $\\omega_h$ is the pole) has angles
    $(\\theta_d, \\phi_d)$ (Zickler 2006 fig. 1b). Swapping `wi` and `wo`
    maps $\\phi_d \\mapsto \\phi_d + \\pi$ (reciprocity, Zickler 2006 sec. 2.2).
    Isotropic BRDFs depend on $(\\theta_h, \\phi_d, \\theta_d)$ only, and
    $\\phi_d$ does not depend on the choice of tangent (except at
    $\\theta_h = 0$, where it is measured from the tangent).

    Azimuths are in $[0, 2\\pi)$; where one is undefined ($\\theta_h = 0$ for
    $\\phi_h$, $\\theta_d = 0$ for $\\phi_d$) it is 0. Values and gradients
    are finite everywhere ($\\omega_i = -\\omega_o$ gives $\\omega_h = n$).
    Inverse: `rusinkiewicz_directions`.

    $\\theta_d$ is computed as $\\operatorname{atan2}(|\\omega_h\\times\\omega_i|,
    \\omega_h\\cdot\\omega_i)$ ($\\cos\\theta_d = \\omega_h\\cdot\\omega_i$ is the
    z component of $d$, $\\sin\\theta_d$ the length of its xy part), not
    through $\\phi_h$: it is smooth across the mirror configuration
    $\\theta_h = 0$ ($\\omega_i$ = `reflect(wo, n)`), and its gradient there
    is the true one (e.g. $\\partial\\theta_d/\\partial\\theta_o = 1/2$ for
    $\\omega_o$ moving in the plane of incidence), equal to a central
    difference. $\\theta_h$ itself is a cone at 0 (no derivative there; the
    gradient returned is finite, 0 at an exact zero, as for `half_angle`),
    and $\\phi_h$, $\\phi_d$ jump there.

    **Arguments:**

    - `wi`, `wo`: unit light and view directions `(..., 3)`.
    - `n`: unit normal `(..., 3)`.
    - `t`: optional tangent `(..., 3)` (the $\\phi = 0$ axis); by default
      `tangent_frame(n)`.

    **Returns:** `(theta_h, phi_h, theta_d, phi_d)`, each `(...)`.
    """
    if t is None:
        wi, wo, n = _prepare([("wi", wi, "dir"), ("wo", wo, "dir"), ("n", n, "dir")])
    else:
        wi, wo, n, t = _prepare([("wi", wi, "dir"), ("wo", wo, "dir"), ("n", n, "dir"), ("t", t, "dir")])
    return _rusinkiewicz_angles(wi, wo, n, t)


@jit
def _rusinkiewicz_angles(wi, wo, n, t):
    tt, bb = _frame(n) if t is None else _frame_from_tangent(n, t)
    return _rusinkiewicz_local(_to_local(wi, tt, bb, n), _to_local(wo, tt, bb, n))


def rusinkiewicz_directions(
    theta_h: Real[ArrayLike, "*#batch"],
    phi_h: Real[ArrayLike, "*#batch"],
    theta_d: Real[ArrayLike, "*#batch"],
    phi_d: Real[ArrayLike, "*#batch"],
) -> tuple[Float[Array, "*batch 3"], Float[Array, "*batch 3"]]:
    """Local-frame `(wi, wo)` from half/difference angles (inverse of `rusinkiewicz_angles`).

    $\\omega_h = (\\sin\\theta_h\\cos\\phi_h, \\sin\\theta_h\\sin\\phi_h, \\cos\\theta_h)$,
    $\\omega_i = R_z(\\phi_h) R_y(\\theta_h)\\,d(\\theta_d, \\phi_d)$ and
    $\\omega_o = 2(\\omega_h\\cdot\\omega_i)\\,\\omega_h - \\omega_i$, in the
    frame with normal $+z$ and tangent $+x$.

    **Returns:** `(wi, wo)`, each `(..., 3)`.
    """
    th, ph, td, pd = _prepare(
        [("theta_h", theta_h, "scalar"), ("phi_h", phi_h, "scalar"), ("theta_d", theta_d, "scalar"), ("phi_d", phi_d, "scalar")]
    )
    return _rusinkiewicz_directions(th, ph, td, pd)


@jit
def _rusinkiewicz_directions(th, ph, td, pd):
    st, ct = jnp.sin(td), jnp.cos(td)
    dx, dy, dz = st * jnp.cos(pd), st * jnp.sin(pd), ct
    sh, ch, sp, cp = jnp.sin(th), jnp.cos(th), jnp.sin(ph), jnp.cos(ph)
    # R_y(θh)
    x1 = ch * dx + sh * dz
    z1 = -sh * dx + ch * dz
    # R_z(φh)
    wi = jnp.stack([cp * x1 - sp * dy, sp * x1 + cp * dy, z1], axis=-1)
    h = jnp.stack([sh * cp, sh * sp, ch], axis=-1)
    return wi, _reflect(wi, h)


def uvw(
    theta_h: Real[ArrayLike, "*#batch"], phi_d: Real[ArrayLike, "*#batch"], theta_d: Real[ArrayLike, "*#batch"]
) -> Float[Array, "*batch 3"]:
    """Zickler et al. 2006, eq. 7: the $(u, v, w)$ parameterization of isotropic BRDFs.

    $$(u, v, w) = \\left(\\sin\\theta_h\\cos 2\\phi_d,\\; \\sin\\theta_h\\sin 2\\phi_d,\\;
      \\frac{2\\theta_d}{\\pi}\\right).$$

    The factor $\\sin\\theta_h$ removes the singularity of the polar
    coordinates at $\\theta_h = 0$ (all $\\phi_d$ map to the $w$ axis, where
    specular peaks cluster), and $2\\phi_d$ makes $f(u, v, w)$ reciprocal
    ($\\phi_d \\mapsto \\phi_d + \\pi$ leaves it unchanged). As a function of
    the angles it is smooth everywhere; the one remaining singularity of the
    parameterization is at $\\theta_d = 0$ ($\\omega_i = \\omega_o$), where
    $\\phi_d$ itself is undefined (paper, below eq. 7) — see
    `uvw_from_directions`. Images sample planes of constant $w$.

    **Arguments:** angles `(...)` each (broadcast), radians.

    **Returns:** `(..., 3)`.
    """
    th, pd, td = _prepare([("theta_h", theta_h, "scalar"), ("phi_d", phi_d, "scalar"), ("theta_d", theta_d, "scalar")])
    return _uvw_jit(th, pd, td)


def _uvw(th, pd, td):
    s = jnp.sin(th)
    return jnp.stack([s * jnp.cos(2.0 * pd), s * jnp.sin(2.0 * pd), (2.0 / _PI) * td], axis=-1)


_uvw_jit = jit(_uvw)


def uvw_from_directions(
    wi: Real[ArrayLike, "*#batch 3"], wo: Real[ArrayLike, "*#batch 3"], n: Real[ArrayLike, "*#batch 3"]
) -> Float[Array, "*batch 3"]:
    """Zickler 2006 eq. 7 evaluated at directions: `uvw(θh, φd, θd)` of `rusinkiewicz_angles`.

    Symmetric in `wi` and `wo` and independent of the tangent. At
    $\\theta_d = 0$ ($\\omega_i = \\omega_o$), where $\\phi_d$ is undefined,
    $\\phi_d = 0$ is used where $\\omega_i = \\omega_o$ exactly in the local frame;
    where they are equal only up to rounding (a light at the camera, in
    general position) $\\phi_d$ is the azimuth of the rounding and the sample
    lands at an arbitrary point of the circle of radius $\\sin\\theta_h$
    (an isotropic BRDF does not depend on $\\phi_d$ at $\\theta_d = 0$; Zickler
    2006 sec. 4, after eq. 7, notes the singularity; `docs/sharing.md`). The
    value is finite (but $(u, v)$ is discontinuous there unless $\\theta_h =
    0$), and so are the gradients. $w = 2\\theta_d/\\pi$
    with $\\theta_d = \\operatorname{atan2}(|\\omega_h\\times\\omega_i|,
    \\omega_h\\cdot\\omega_i)$ (`rusinkiewicz_angles`): smooth, with its true
    gradient, at the mirror configuration $\\theta_h = 0$ too.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)` (broadcast).

    **Returns:** `(..., 3)`.
    """
    wi, wo, n = _prepare([("wi", wi, "dir"), ("wo", wo, "dir"), ("n", n, "dir")])
    return _uvw_from_directions(wi, wo, n)


@jit
def _uvw_from_directions(wi, wo, n):
    t, b = _frame(n)
    th, _, td, pd = _rusinkiewicz_local(_to_local(wi, t, b, n), _to_local(wo, t, b, n))
    return _uvw(th, pd, td)


def local_directions(
    theta_i: Real[ArrayLike, "*#batch"], theta_o: Real[ArrayLike, "*#batch"], delta_phi: Real[ArrayLike, "*#batch"]
) -> tuple[Float[Array, "*batch 3"], Float[Array, "*batch 3"]]:
    """Light and view directions from angles, in the frame with normal $n = +z$.

    $\\omega_i = (\\sin\\theta_i, 0, \\cos\\theta_i)$ (azimuth 0) and
    $\\omega_o = (\\sin\\theta_o\\cos\\Delta\\phi, \\sin\\theta_o\\sin\\Delta\\phi, \\cos\\theta_o)$,
    so an isotropic BRDF on an angle grid is
    `model(*local_directions(ti, to, dphi), jnp.array([0., 0., 1.]), ...)`.

    **Returns:** `(wi, wo)`, each `(..., 3)`.
    """
    ti, to, dp = _prepare([("theta_i", theta_i, "scalar"), ("theta_o", theta_o, "scalar"), ("delta_phi", delta_phi, "scalar")])
    return _local_directions(ti, to, dp)


@jit
def _local_directions(ti, to, dp):
    si = jnp.sin(ti)
    so = jnp.sin(to)
    wi = jnp.stack([si, jnp.zeros_like(si), jnp.cos(ti)], axis=-1)
    wo = jnp.stack([so * jnp.cos(dp), so * jnp.sin(dp), jnp.cos(to)], axis=-1)
    return wi, wo


# --------------------------------------------------------------------------- Fresnel


def _fresnel_parts(c, mu):
    """Cancellation-free Fresnel amplitudes divided by r0 = (μ-1)/(μ+1).

    With $g = \\sqrt{\\mu^2 - 1 + c^2} = \\mu\\cos\\theta_t$:
    $r_s = (c - g)/(c + g) = (1 - \\mu^2)/(c + g)^2$ and
    $r_p = (\\mu^2 c - g)/(\\mu^2 c + g) = (\\mu^2 - 1)((\\mu^2 + 1)c^2 - 1)/(\\mu^2 c + g)^2$,
    so $r_s/r_0 = -(\\mu + 1)^2/(c + g)^2$ and
    $r_p/r_0 = (\\mu + 1)^2((\\mu^2 + 1)c^2 - 1)/(\\mu^2 c + g)^2$.
    Returns (ratio = F/F0, ok) with ok False at total internal reflection
    (g² ≤ 0) or at the degenerate c = g = 0.
    """
    c = jnp.clip(c, 0.0, 1.0)
    mu2 = mu * mu
    g2 = mu2 - 1.0 + c * c
    g = _safe_sqrt(g2)
    d_s = c + g
    d_p = mu2 * c + g
    ok = ~((g2 <= 0.0) | (d_s <= 0.0) | (d_p <= 0.0))  # NaN (c or mu) stays on the formula branch: propagates
    d_s = jnp.where(ok, d_s, 1.0)
    d_p = jnp.where(ok, d_p, 1.0)
    k = (mu + 1.0) ** 2
    rs = k / (d_s * d_s)
    rp = k * ((mu2 + 1.0) * c * c - 1.0) / (d_p * d_p)
    return 0.5 * (rs * rs + rp * rp), ok


def _fresnel(c, mu):
    ratio, ok = _fresnel_parts(c, mu)
    r0 = (mu - 1.0) / (mu + 1.0)
    return jnp.where(ok, r0 * r0 * ratio, 1.0)


def _fresnel_normalized(c, mu):
    ratio, ok = _fresnel_parts(c, mu)
    r0 = (mu - 1.0) / (mu + 1.0)
    f0 = r0 * r0
    safe_f0 = jnp.where(f0 > 0.0, f0, 1.0)
    return jnp.where(ok, ratio, jnp.where(f0 > 0.0, 1.0 / safe_f0, 1.0))


_fresnel_jit = jit(_fresnel)
_fresnel_normalized_jit = jit(_fresnel_normalized)


def fresnel_dielectric(cos_theta: Real[ArrayLike, "*#batch"], mu: Real[ArrayLike, "*#batch"]) -> Float[Array, "*batch"]:
    """Unpolarized Fresnel reflectance of a dielectric interface, exact.

    $F = \\tfrac12(r_s^2 + r_p^2)$ with, for relative index $\\mu$ and
    $c = \\cos\\theta$, $g = \\sqrt{\\mu^2 - 1 + c^2}$ ($= \\mu\\cos\\theta_t$),
    $r_s = (c - g)/(c + g)$, $r_p = (\\mu^2 c - g)/(\\mu^2 c + g)$ — the same
    as Cook & Torrance's
    $F = \\frac{(g - c)^2}{2(g + c)^2}\\left[1 + \\frac{(c(g + c) - 1)^2}{(c(g - c) + 1)^2}\\right]$
    (Born & Wolf sec. 1.5.2). Evaluated in a cancellation-free factored form
    (accurate for $\\mu \\to 1$). $F(\\mu, 0°) = ((\\mu-1)/(\\mu+1))^2$,
    $F \\to 1$ at grazing incidence. For $\\mu < 1$ (light leaving the denser
    medium) $F = 1$ beyond the critical angle (total internal reflection).
    No Schlick approximation.

    **Arguments:**

    - `cos_theta`: cosine of the angle of incidence, `(...)`, clipped to [0, 1].
    - `mu`: relative refractive index $n_t/n_i > 0$, `(...)` (traced).

    **Returns:** `(...)`, broadcast shape.

    Comparable to `mitsuba.fresnel` (its `r` output).
    """
    return _fresnel_jit(*_fresnel_args(cos_theta, mu))


def fresnel_normalized(cos_theta: Real[ArrayLike, "*#batch"], mu: Real[ArrayLike, "*#batch"]) -> Float[Array, "*batch"]:
    """The Fresnel term of R&H 2001 sec. 5.2: $F(\\mu, \\theta)/F(\\mu, 0)$, 1 at normal incidence.

    Computed without the cancellation of the ratio of two small numbers,
    $F/F_0 = \\tfrac12(\\mu + 1)^4\\left[(c + g)^{-4} + ((\\mu^2 + 1)c^2 - 1)^2(\\mu^2 c + g)^{-4}\\right]$,
    so it is finite at $\\mu = 1$ (its limit $(1 + (2c^2 - 1)^2)/(2c^4)$)
    and its gradient in $\\mu$ is smooth there. It grows to $1/F(\\mu, 0)$ at
    grazing incidence. See `fresnel_dielectric` for the formula.

    **Arguments:** as `fresnel_dielectric`.

    **Returns:** `(...)`.
    """
    return _fresnel_normalized_jit(*_fresnel_args(cos_theta, mu))


# --------------------------------------------------------------------------- BRDF models


def _above(wi, wo, n):
    """(valid mask, safe wi, safe wo, cos θi, cos θo) — the double-where substitution."""
    ci = _dot(wi, n)
    co = _dot(wo, n)
    valid = (ci > 0.0) & (co > 0.0)
    vm = valid[..., None]
    ez = jnp.zeros_like(n).at[..., 2].set(1.0)  # a unit substitute: n itself may be 0 (a G-buffer miss)
    n_s = jnp.where(vm, n, ez)
    wi_s = jnp.where(vm, wi, ez)
    wo_s = jnp.where(vm, wo, ez)
    return valid, wi_s, wo_s, n_s, _dot(wi_s, n_s), _dot(wo_s, n_s)


def _half(wi, wo):
    # |wi + wo| > 0 above the horizon (and at the substitute wi = wo = n).
    s = wi + wo
    return s * jax.lax.rsqrt(_dot(s, s))[..., None]


def _tan2_theta_h(h, n):
    """$(\\tan^2\\theta_h, \\cos\\theta_h)$ of a unit half vector (finite above both horizons)."""
    s2, c = _half_angle_parts(h, n)
    return s2 / (c * c), c


def lambertian(
    wi: Real[ArrayLike, "*#batch 3"], wo: Real[ArrayLike, "*#batch 3"], n: Real[ArrayLike, "*#batch 3"], kd: Real[ArrayLike, "*#batch"]
) -> Float[Array, "*batch"]:
    """Lambertian BRDF in the convention of R&H 2001: $\\rho = K_d$ (no $1/\\pi$).

    So the radiance is $B_d = K_d E$ with $E$ the irradiance (R&H eqs. 21–24)
    and the albedo $\\int\\rho\\cos\\theta_i\\,d\\omega_i = \\pi K_d$; a
    surface of albedo $a$ has $K_d = a/\\pi$. (`cook_torrance`, `ward_isotropic`,
    `oren_nayar` and `lafortune` use the albedo convention $k_d/\\pi$.)

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `kd`: `(...)`.

    **Returns:** `(...)`; 0 below either horizon.
    """
    wi, wo, n, p = _brdf_args(wi, wo, n, {"kd": kd})
    return _lambertian(wi, wo, n, p["kd"])


@jit
def _lambertian(wi, wo, n, kd):
    valid = (_dot(wi, n) > 0.0) & (_dot(wo, n) > 0.0)
    return jnp.where(valid, kd, 0.0)


def phong_transfer(
    wi: Real[ArrayLike, "*#batch 3"], wo: Real[ArrayLike, "*#batch 3"], n: Real[ArrayLike, "*#batch 3"], s: Real[ArrayLike, "*#batch"]
) -> Float[Array, "*batch"]:
    """Normalized Phong transfer function (R&H 2001 sec. 5.2; thesis eq. 3.34).

    $\\hat\\rho = \\frac{s + 1}{2\\pi}\\max(\\vec R\\cdot\\vec L, 0)^s$, with
    $\\vec R$ = `reflect(wo, n)` and $\\vec L$ = `wi`. The normalization
    gives the lobe unit energy over the hemisphere about $\\vec R$. Unlike
    the paper (which ignores the horizon), 0 is returned when either
    direction is below the horizon. Symmetric in `wi` and `wo`, since
    $\\vec R\\cdot\\vec L = 2(n\\cdot\\omega_i)(n\\cdot\\omega_o) - \\omega_i\\cdot\\omega_o$.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `s`: Phong
    exponent `(...)` (traced, any real $s > -1$).

    **Returns:** `(...)`.
    """
    wi, wo, n, p = _brdf_args(wi, wo, n, {"s": s}, {"s": _phong_exponent})
    return _phong(wi, wo, n, p["s"], False)


def phong(
    wi: Real[ArrayLike, "*#batch 3"], wo: Real[ArrayLike, "*#batch 3"], n: Real[ArrayLike, "*#batch 3"], s: Real[ArrayLike, "*#batch"]
) -> Float[Array, "*batch"]:
    """Normalized Phong BRDF: $\\rho = \\hat\\rho/\\cos\\theta_i$ with $\\hat\\rho$ of `phong_transfer`.

    $\\rho = \\frac{s + 1}{2\\pi}\\frac{\\max(\\vec R\\cdot\\vec L, 0)^s}{\\cos\\theta_i}$
    (R&H 2001 sec. 5.2; thesis eq. 3.34). This BRDF is *not* reciprocal
    (the transfer function $\\hat\\rho$ is symmetric, so
    $\\rho(\\omega_i,\\omega_o)\\cos\\theta_i = \\rho(\\omega_o,\\omega_i)\\cos\\theta_o$),
    and it grows like $1/\\cos\\theta_i$ at grazing light where
    $\\vec R\\cdot\\vec L > 0$.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `s`: Phong
    exponent `(...)` (traced, any real $s > -1$).

    **Returns:** `(...)`; 0 below either horizon.
    """
    wi, wo, n, p = _brdf_args(wi, wo, n, {"s": s}, {"s": _phong_exponent})
    return _phong(wi, wo, n, p["s"], True)


@jit
def _phong(wi, wo, n, s, divide):
    valid, wi, wo, n, ci, co = _above(wi, wo, n)
    rl = 2.0 * ci * co - _dot(wi, wo)
    pos = rl > 0.0
    lobe = jnp.where(pos, jnp.where(pos, rl, 1.0) ** s, 0.0)
    val = (s + 1.0) / _TWO_PI * lobe
    if divide:
        val = val / ci
    return jnp.where(valid, val, 0.0)


def torrance_sparrow(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    kd: Real[ArrayLike, "*#batch"],
    ks: Real[ArrayLike, "*#batch"],
    mu: Real[ArrayLike, "*#batch"] | None,
    sigma: Real[ArrayLike, "*#batch"],
) -> Float[Array, "*batch"]:
    """The simplified Torrance–Sparrow model of R&H 2001 sec. 5.2 (docs/conventions.md, "BRDFs").

    $$\\rho = K_d + K_s\\frac{F\\,S}{4\\cos\\theta_i\\cos\\theta_o},\\quad
      S = \\frac{1}{\\pi\\sigma^2}\\exp\\left[-(\\theta_h/\\sigma)^2\\right],\\quad
      F = \\frac{F(\\mu, \\theta_o)}{F(\\mu, 0)},$$

    $\\theta_h$ the angle between the half vector and the normal (computed as
    `atan2(|n×h|, n·h)`, accurate near 0). As in the paper the Fresnel factor
    uses the *exitant* angle $\\theta_o$, not the angle to the half vector
    ("in practice, this angle is usually very close to $\\theta_o$"), and
    the geometric attenuation $G$ is omitted; with $F(\\theta_o)$ the model
    is not exactly reciprocal. `mu=None` drops the Fresnel factor ($F = 1$,
    as R&H do for metals). Lambertian part in the R&H convention (see
    `lambertian`). For small $\\sigma$ and normal exitance the specular lobe
    has unit energy, $\\int K_s F S/(4\\cos\\theta_o)\\,d\\omega_i \\approx K_s$
    (the basis of R&H eq. 20).

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `kd`, `ks`,
    `mu` (relative index), `sigma` (roughness, radians): `(...)`, traced.

    **Returns:** `(...)`; 0 below either horizon.
    """
    wi, wo, n, p = _brdf_args(wi, wo, n, {"kd": kd, "ks": ks, "mu": mu, "sigma": sigma}, {"mu": _index, "sigma": _positive})
    return _torrance_sparrow(wi, wo, n, p["kd"], p["ks"], p.get("mu"), p["sigma"])


def _ts_specular(theta_h_sq, ci, co, f, sigma):
    """$F\\,S/(4\\cos\\theta_i\\cos\\theta_o)$ of `torrance_sparrow` from its geometry: $\\theta_h^2$, the two
    cosines (positive) and the Fresnel factor `f` (`_fresnel_normalized(co, mu)`, or 1). Written once, for
    `torrance_sparrow` and the reference renderer's pairwise form (`_reference_pairs.py`)."""
    s = jnp.exp(-theta_h_sq / (sigma * sigma)) / (_PI * sigma * sigma)
    return f * s / (4.0 * ci * co)


@jit
def _torrance_sparrow(wi, wo, n, kd, ks, mu, sigma):
    valid, wi, wo, n, ci, co = _above(wi, wo, n)
    theta_h_sq = _theta_h_sq(*_half_angle_parts(wi + wo, n))
    f = 1.0 if mu is None else _fresnel_normalized(co, mu)
    val = kd + ks * _ts_specular(theta_h_sq, ci, co, f, sigma)
    return jnp.where(valid, val, 0.0)


def cook_torrance(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    kd: Real[ArrayLike, "*#batch"],
    ks: Real[ArrayLike, "*#batch"],
    m: Real[ArrayLike, "*#batch"],
    mu: Real[ArrayLike, "*#batch"],
) -> Float[Array, "*batch"]:
    """Cook–Torrance microfacet BRDF with Beckmann $D$, V-cavity $G$ and exact Fresnel.

    $$\\rho = \\frac{k_d}{\\pi} + k_s\\frac{D\\,G\\,F}{4\\cos\\theta_i\\cos\\theta_o},\\quad
      D = \\frac{\\exp(-\\tan^2\\theta_h/m^2)}{\\pi m^2\\cos^4\\theta_h},$$
    $$G = \\min\\left(1, \\frac{2(n\\cdot h)(n\\cdot\\omega_o)}{\\omega_o\\cdot h},
      \\frac{2(n\\cdot h)(n\\cdot\\omega_i)}{\\omega_o\\cdot h}\\right),\\quad
      F = F_{\\rm dielectric}(\\mu, \\omega_i\\cdot h).$$

    Normalization: $D$ is the normalized Beckmann distribution,
    $\\int D\\cos\\theta_h\\,d\\omega_h = 1$, with the
    $1/(4\\cos\\theta_i\\cos\\theta_o)$ Jacobian of Walter et al. 2007 (Cook &
    Torrance 1982 write $D/(\\pi\\cos\\theta_i\\cos\\theta_o)$ with an
    unnormalized $D$; the two differ by a constant absorbed in $k_s$). $F$
    is the unnormalized exact dielectric Fresnel term at the microfacet
    angle $\\omega_i\\cdot h = \\omega_o\\cdot h$, so $k_s$ is the specular
    scale and $k_d$ the diffuse albedo. Reciprocal. With $k_d + k_s \\le 1$
    the directional albedo stays $\\le 1$ (checked by quadrature in the tests
    for $m \\in [0.2, 0.8]$ up to $\\theta_o = 1.5$; $G$ is what keeps it
    bounded at grazing view).

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `kd`, `ks`,
    `m` (rms slope), `mu` (relative index): `(...)`, traced.

    **Returns:** `(...)`; 0 below either horizon.
    """
    wi, wo, n, p = _brdf_args(wi, wo, n, {"kd": kd, "ks": ks, "m": m, "mu": mu}, {"m": _positive, "mu": _index})
    return _cook_torrance(wi, wo, n, p["kd"], p["ks"], p["m"], p["mu"])


@jit
def _cook_torrance(wi, wo, n, kd, ks, m, mu):
    valid, wi, wo, n, ci, co = _above(wi, wo, n)
    h = _half(wi, wo)
    tan2, ch = _tan2_theta_h(h, n)
    m2 = m * m
    ch2 = ch * ch
    d = jnp.exp(-tan2 / m2) / (_PI * m2 * ch2 * ch2)
    oh = _dot(wo, h)
    g = jnp.minimum(1.0, jnp.minimum(2.0 * ch * co / oh, 2.0 * ch * ci / oh))
    f = _fresnel(_dot(wi, h), mu)
    val = kd / _PI + ks * d * g * f / (4.0 * ci * co)
    return jnp.where(valid, val, 0.0)


def ward_isotropic(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    rho_d: Real[ArrayLike, "*#batch"],
    rho_s: Real[ArrayLike, "*#batch"],
    alpha: Real[ArrayLike, "*#batch"],
) -> Float[Array, "*batch"]:
    """Ward's isotropic Gaussian BRDF (Ward 1992; used by Zickler 2006 fig. 8).

    $$\\rho = \\frac{\\rho_d}{\\pi} + \\rho_s\\frac{\\exp(-\\tan^2\\theta_h/\\alpha^2)}
      {4\\pi\\alpha^2\\sqrt{\\cos\\theta_i\\cos\\theta_o}}.$$

    $\\rho_d$ is the diffuse albedo; the specular lobe is normalized to
    $\\approx\\rho_s$ for small $\\alpha$. Reciprocal.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `rho_d`,
    `rho_s`, `alpha` (rms slope): `(...)`, traced.

    **Returns:** `(...)`; 0 below either horizon.
    """
    wi, wo, n, p = _brdf_args(wi, wo, n, {"rho_d": rho_d, "rho_s": rho_s, "alpha": alpha}, {"alpha": _positive})
    return _ward(wi, wo, n, p["rho_d"], p["rho_s"], p["alpha"])


@jit
def _ward(wi, wo, n, rd, rs, al):
    valid, wi, wo, n, ci, co = _above(wi, wo, n)
    tan2, _ = _tan2_theta_h(_half(wi, wo), n)
    a2 = al * al
    val = rd / _PI + rs * jnp.exp(-tan2 / a2) / (4.0 * _PI * a2 * jnp.sqrt(ci * co))
    return jnp.where(valid, val, 0.0)


def oren_nayar(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    albedo: Real[ArrayLike, "*#batch"],
    sigma: Real[ArrayLike, "*#batch"],
) -> Float[Array, "*batch"]:
    """The qualitative Oren–Nayar model of rough diffuse surfaces (Oren & Nayar 1994).

    $$\\rho = \\frac{a}{\\pi}\\left(A + B\\max(0, \\cos(\\phi_i - \\phi_o))\\sin\\alpha\\tan\\beta\\right),\\quad
      A = 1 - \\frac{0.5\\sigma^2}{\\sigma^2 + 0.33},\\quad B = \\frac{0.45\\sigma^2}{\\sigma^2 + 0.09},$$

    $\\alpha = \\max(\\theta_i, \\theta_o)$, $\\beta = \\min(\\theta_i, \\theta_o)$,
    $\\sigma$ the slope-angle standard deviation (radians); $\\sigma = 0$ is
    Lambertian with albedo $a$. Evaluated without angles or azimuths: with
    $p_i, p_o$ the projections of $\\omega_i, \\omega_o$ on the tangent plane,
    $\\cos(\\phi_i - \\phi_o)\\sin\\theta_i\\sin\\theta_o = p_i\\cdot p_o =
    \\omega_i\\cdot\\omega_o - \\cos\\theta_i\\cos\\theta_o$, hence
    $\\max(0,\\cos\\Delta\\phi)\\sin\\alpha\\tan\\beta = \\max(0, p_i\\cdot p_o)/\\max(\\cos\\theta_i, \\cos\\theta_o)$ —
    a polynomial expression, so the term vanishes smoothly when either
    direction is along the normal and there is no NaN. Reciprocal.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `albedo`,
    `sigma`: `(...)`, traced.

    **Returns:** `(...)`; 0 below either horizon.
    """
    wi, wo, n, p = _brdf_args(wi, wo, n, {"albedo": albedo, "sigma": sigma}, {"sigma": _nonnegative_roughness})
    return _oren_nayar(wi, wo, n, p["albedo"], p["sigma"])


@jit
def _oren_nayar(wi, wo, n, a, sg):
    valid, wi, wo, n, ci, co = _above(wi, wo, n)
    s2 = sg * sg
    big_a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    big_b = 0.45 * s2 / (s2 + 0.09)
    pp = jnp.maximum(_dot(wi, wo) - ci * co, 0.0)
    val = a / _PI * (big_a + big_b * pp / jnp.maximum(ci, co))
    return jnp.where(valid, val, 0.0)


def lafortune(
    wi: Real[ArrayLike, "*#batch 3"],
    wo: Real[ArrayLike, "*#batch 3"],
    n: Real[ArrayLike, "*#batch 3"],
    kd: Real[ArrayLike, "*#batch"],
    lobes: Real[ArrayLike, "*#batch K 3"],
) -> Float[Array, "*batch"]:
    """Isotropic Lafortune generalized-cosine-lobe BRDF (Lafortune et al. 1997).

    $$\\rho = \\frac{k_d}{\\pi} + \\sum_k \\max\\left(0,\\;
      C_{x,k}(\\omega_{i,x}\\omega_{o,x} + \\omega_{i,y}\\omega_{o,y}) + C_{z,k}\\,\\omega_{i,z}\\omega_{o,z}\\right)^{n_k}$$

    in the local frame (isotropic: $C_x = C_y$); the tangential part is
    $\\omega_i\\cdot\\omega_o - \\cos\\theta_i\\cos\\theta_o$, so no tangent
    is needed. $C_x = -1, C_z = 1$ is a Phong-like lobe about the mirror
    direction, $C_x = 1$ a retro-reflective one. Used with $N$ lobes
    ($3N + 1$ parameters) by Zickler 2006 figs. 7–9. Reciprocal.

    **Arguments:** `wi`, `wo`, `n`: unit vectors `(..., 3)`; `kd`: `(...)`;
    `lobes`: `(K, 3)` or `(..., K, 3)`, rows $(C_x, C_z, n)$ (traced).

    **Returns:** `(...)`; 0 below either horizon.
    """
    wi, wo, n, p = _brdf_args(wi, wo, n, {"kd": kd, "lobes": lobes})
    return _lafortune(wi, wo, n, p["kd"], p["lobes"])


@jit
def _lafortune(wi, wo, n, kd, lobes):
    valid, wi, wo, n, ci, co = _above(wi, wo, n)
    zz = ci * co
    xy = _dot(wi, wo) - zz
    base = lobes[..., 0] * xy[..., None] + lobes[..., 1] * zz[..., None]
    pos = base > 0.0
    terms = jnp.where(pos, jnp.where(pos, base, 1.0) ** lobes[..., 2], 0.0)
    val = kd / _PI + jnp.sum(terms, axis=-1)
    return jnp.where(valid, val, 0.0)
