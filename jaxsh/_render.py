"""Forward rendering: the practical reflected-light-field model and a reference integrator.

Per pixel, with unit normal $n$, unit view $\\omega_o$ (towards the camera),
diffuse and specular albedos $K_d, K_s$ (RGB, may be textures), Fresnel
index μ and roughness σ, the practical model of R&H 2001 eq. 24 is

$$B = K_d E(n) + K_s F(\\mu,\\theta_o)\\Big[L_{slow}(R) + \\frac{1}{4\\cos\\theta_o}\\sum_j T_j(\\sigma)\\Big],\\quad
  T_j = e^{-(\\theta_{h,j}/\\sigma)^2}\\frac{L_j}{\\pi\\sigma^2},$$

with $E$ the irradiance (eq. 21), $R$ the mirror direction of the view,
$L_{slow}$ the slow lighting filtered by $e^{-(\\sigma l)^2}$ (eqs. 20, 22) and
$j$ over the fast (compact) sources (eq. 23). With the visibility terms of
sec. 6.4 for concave objects: $E$ from visibility-weighted transfer vectors,
$T_j$ and the fast sources' diffuse term times their shadow visibility
$V_j(x)$, and $L_{slow}(R)$ times the visibility of $R$.

Deviation from the letter of eq. 21 (default `exact_fast_diffuse=True`): the
fast sources' diffuse contribution is computed exactly in angular space,
$K_d\\sum_j L_j V_j\\max(n\\cdot\\omega_j, 0)$, and the 9-term irradiance is
used for the slow lighting only. A compact source is cheap to treat exactly,
and the 9-term clamped cosine is its worst case (docs/performance.md: measured 2.0 %
vs 0.4 % RMS for a probe plus a sun). `exact_fast_diffuse=False` gives the
paper's form.

The model itself (the terms and their combination with the BRDF) is written
once, in `_practical.py`; `render_practical` validates, broadcasts to the
image and reshapes. On large images it evaluates $L_{slow}(R)$ by a table:
the filtered lighting synthesized once on a lat-long grid and interpolated
bicubically at the mirror directions, within a documented error bound
(`method`; docs/conventions.md, "The slow specular term by table").
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Real
from ._compile import jit, on_row_shards, row_sharding
from ._custom_types import ScalarLike, SequenceLike

from ._checks import error_if_any, as_float_array, check_dirs, check_lmax_range, check_positive_int
from ._grids import latlong_directions, latlong_weights
from ._model import Lighting, TorranceSparrow, model_args
from ._practical import (
    _LIGHT_KW,
    Components as Components,
    _broadcasts_to,
    _eq24_terms,
    _prepare_lighting,
    _prepare_visibility,
    _slow_table,
    _table_rows,
    practical_lighting,
)
from ._reference_pairs import PAIR_MODELS as _REFERENCE_BRDFS, specular_pairs
from ._reflectance import tangent_frame
from ._sh import REAL_SH_MAX_LMAX


def _channels(x, name):
    x = as_float_array(x, name)
    if x.ndim == 0:
        x = x[None]
    return x


def _bcast(x, batch, c):
    """Broadcast a (..., C) or (C,) array to batch + (C,)."""
    if x.ndim == 1:
        x = x.reshape((1,) * len(batch) + x.shape)
    return jnp.broadcast_to(x, batch + (c,))


def _texture(x, batch, name):
    """A `(C,)` parameter as `(1, C)`, a `(..., C)` texture broadcast to `batch` and flattened to `(N, C)`."""
    if x.ndim == 1:
        return x[None]
    want = tuple(batch) + (x.shape[-1],)
    if not _broadcasts_to(x.shape, want):
        raise ValueError(f"`{name}` must have shape (C,) or {tuple(batch)} + (C,) (a texture), got {tuple(x.shape)}")
    return jnp.broadcast_to(x, want).reshape(-1, x.shape[-1])


def _concrete(x):
    """`x` as a NumPy array, or `None` when traced (the checks inside jit take over)."""
    if isinstance(x, jax.core.Tracer):
        return None
    return np.asarray(x)


def _check_geometry(x, name, batch, mask, allow_zero=False):
    """A concrete `normals` / `views` array: finite and non-zero at every pixel of `mask` (all pixels without one).

    `allow_zero=True` accepts exact zero vectors (a G-buffer's misses, which render as 0) but not NaN/inf.
    """
    a = _concrete(x)
    if a is None or a.size == 0:
        return
    norm2 = np.einsum("...i,...i->...", a, a)  # on the array as given (a broadcast view is checked once)
    bad = ~np.isfinite(norm2) if allow_zero else ~np.isfinite(norm2) | (norm2 == 0)
    if not bad.any():
        return
    bad = np.broadcast_to(bad, tuple(batch))
    where = "without a `mask`"
    if mask is not None:
        m = _concrete(mask)
        if m is None:
            return
        bad = bad & np.broadcast_to(m.astype(bool), bad.shape)
        where = "inside the `mask`"
    if bad.any():
        i = tuple(int(k) for k in np.argwhere(bad)[0])
        what = "finite directions (zero vectors mark misses)" if allow_zero else "finite, non-zero directions"
        shown = np.broadcast_to(a, tuple(batch) + (3,))[i] if a.ndim > 1 else a
        raise ValueError(f"`{name}` must be {what} {where}; pixel {i} is {shown}")


def _check_channels(pairs):
    """Channel counts `[(name, C), ...]` must agree (or be 1): `ValueError` naming the two that disagree."""
    pairs = [(n, int(k)) for n, k in pairs]
    first = next(((n, k) for n, k in pairs if k != 1), None)
    if first is None:
        return 1
    for n, k in pairs:
        if k not in (1, first[1]):
            raise ValueError(
                f"channel mismatch: {first[0]} has {first[1]} channels but {n} has {k} (give the same C, or 1)"
            )
    return first[1]


def _brdf_channels(kd, ks):
    return [("`kd`", kd.shape[-1]), ("`ks`", ks.shape[-1])]


def _lighting_channels(lighting):
    out = []
    for f in ("slow_sh", "fast_energy", "disk_radiance"):
        x = getattr(lighting, f)
        if x is not None:
            out.append((f"`lighting.{f}`", x.shape[-1]))
    return out


def _check_sigma_traced(sigma, mu):
    """Inside jit: σ ≤ 0 or infinite or μ < 1 is an error (`equinox.error_if`); concrete values were checked by
    `TorranceSparrow`. (`_combine` relies on it: it evaluates the terms with `check=False`.)"""
    if not isinstance(sigma, jax.core.Tracer) and not isinstance(mu, jax.core.Tracer):
        return sigma, mu
    sigma = error_if_any(sigma, (sigma <= 0) | (sigma == jnp.inf), "`sigma` must be > 0 and finite")
    if mu is not None:
        mu = error_if_any(mu, mu < 1, "`mu` must be >= 1")
    return sigma, mu


def _batch(normals, views):
    try:
        return jnp.broadcast_shapes(normals.shape[:-1], views.shape[:-1])
    except ValueError:
        raise ValueError(
            f"the batch shapes of `normals` {tuple(normals.shape)} and `views` {tuple(views.shape)} do not broadcast"
        ) from None


def render_practical(
    normals: Real[ArrayLike, "*#batch 3"],
    views: Real[ArrayLike, "*#batch 3"],
    brdf: TorranceSparrow | Real[ArrayLike, "*#batch C"] | ScalarLike | SequenceLike | None = None,
    lighting: Lighting | Real[ArrayLike, "*#batch C"] | ScalarLike | SequenceLike | None = None,
    *legacy,
    transfer: Real[ArrayLike, "*#batch 9"] | None = None,
    fast_visibility: Real[ArrayLike, "*#batch J"] | None = None,
    reflected_visibility: Real[ArrayLike, "*#batch"] | None = None,
    exact_fast_diffuse: bool = True,
    mask: Bool[ArrayLike, "*#batch"] | None = None,
    method: str = "auto",
    **legacy_kw,
) -> Components:
    """The practical model of R&H 2001 eq. 24 per pixel (module docstring).

    `render_practical(normals, views, brdf, lighting, ...)`, or in the keyword
    form `render_practical(normals, views, kd, ks, mu, sigma, slow_sh=...,
    fast_directions=..., fast_energy=..., ...)` (the same model; the
    arguments are the fields of `brdf` and `lighting`).

    **Arguments:**

    - `normals`, `views`: directions `(..., 3)`, normalized here; views point towards the camera.
    - `brdf`: a `jaxsh.TorranceSparrow`: `kd`, `ks` `(C,)` or `(..., C)`
      (textures over the pixels), R&H's $K_d$ (ρ = Kd + ...); `mu` relative
      index (None: F = 1); `sigma` roughness (radians). Traced.
    - `lighting`: a `jaxsh.Lighting` with a slow part `slow_sh` (world frame,
      unfiltered; its lmax should reach ~3/σ for $B_{s,slow}$) and/or fast
      delta sources (`fast_directions` `(J, 3)`, `fast_energy` `(J, C)`).
      Disks need the slow/fast split first (`Lighting.split_disks`).
    - `transfer`: optional `(..., 9)` visibility-weighted clamped-cosine
      transfer vectors (sec. 6.4); replaces the unshadowed irradiance.
    - `fast_visibility` `(..., J)`, `reflected_visibility` `(...)`: optional.
      Visibility terms of an absent lighting part are ignored.
    - `exact_fast_diffuse`: the fast sources' diffuse term in angular space
      (default) or, `False`, by the 9-term irradiance of eq. 21.
    - `mask`: optional `(...)` bool, e.g. `GBuffer.mask`: pixels outside it
      render as 0 and their normals/views are not read (a G-buffer's misses
      carry zero normals). Without a mask, a zero or non-finite normal or
      view is an error.
    - `method`: how $L_{slow}(R)$ is evaluated. `"exact"`: the
      $(l_{max}+1)^2$ harmonics at every pixel. `"table"`: the filtered
      lighting synthesized once on a lat-long grid and interpolated
      (bicubic, across the poles) at the mirror directions; the grid is
      chosen from `lmax` and σ (from `lmax` alone when σ is traced) so that
      the interpolation error is at most $10^{-6}\\sum_l a_l$,
      $a_l = \\sqrt{(2l+1)/4\\pi}\\,\\|L_l\\|_2$ (a bound on the lighting's
      maximum; docs/conventions.md gives the bound), or a `ValueError` when
      that needs more than 1024 rows. `"auto"` (default): the table when such
      a grid exists and is cheaper than the per-pixel sum (large images:
      $N (l_{max}+1)^2 \\ge 8 H W$ and at least 4096 pixels), else exact.

    **Returns:** `Components(diffuse, specular_slow, specular_fast, total)`,
    each `(..., C)`.

    **Compiled programs:** one per shape, dtype and static option. Called
    outside `jit`, the pixels are padded to a bucket of sizes
    (`_pixel_bucket`: N rounded up to three significant bits, at least 1,024)
    so that renders of other pixel counts in the bucket compile nothing
    (docs/performance.md, fifteenth round). Normals split over several devices
    along their first (pixel) axis (a `NamedSharding`, evenly) are not padded:
    each device renders its own pixels and the outputs stay split
    (docs/howto_scale.md).
    """
    brdf, lighting, light_kw = model_args("render_practical", brdf, lighting, legacy, legacy_kw, _LIGHT_KW)
    lighting = practical_lighting(lighting, light_kw)
    normals = check_dirs(normals, "normals")
    views = check_dirs(views, "views")
    batch = _batch(normals, views)
    if mask is not None and not _broadcasts_to(jnp.shape(mask), batch):
        raise ValueError(f"`mask` must have shape {tuple(batch)} (the batch of `normals` and `views`), got {tuple(jnp.shape(mask))}")
    _check_geometry(normals, "normals", batch, mask)
    _check_geometry(views, "views", batch, mask)
    kd = _channels(brdf.kd, "kd")
    ks = _channels(brdf.ks, "ks")
    _check_channels(_brdf_channels(kd, ks) + _lighting_channels(lighting))
    # on the arrays, not their dtypes: a Python scalar's weak type must not widen float32 geometry (conventions.md)
    dt = jnp.result_type(normals, views, kd, ks)
    n = jnp.broadcast_to(normals, batch + (3,)).astype(dt).reshape(-1, 3)
    v = jnp.broadcast_to(views, batch + (3,)).astype(dt).reshape(-1, 3)
    kd = _texture(kd.astype(dt), batch, "kd")
    ks = _texture(ks.astype(dt), batch, "ks")
    slow, fdir, fen = _prepare_lighting(lighting, dt)
    vis = _prepare_visibility(lighting, batch, transfer, fast_visibility, reflected_visibility, dt, strict=False)
    if mask is not None:
        mask = jnp.broadcast_to(jnp.asarray(mask, bool), batch).reshape(-1)
    mu = None if brdf.mu is None else jnp.asarray(brdf.mu, dt)
    sigma, mu = _check_sigma_traced(jnp.asarray(brdf.sigma, dt), mu)
    npx = n.shape[0]
    rows = _choose_table(method, lighting, brdf.sigma, npx, dt)
    where = row_sharding(n)
    if where is not None:  # each device's pixels on that device (`jaxsh._compile.row_sharding`), without padding
        (n, v, kd, ks, *vis), mask = _on_rows(where, npx, (n, v, kd, ks, *vis), mask)
        terms = _terms_rows(n, v, mask, slow, sigma, fdir, fen, *vis, bool(exact_fast_diffuse), rows, where)
    else:
        (n, v, kd, ks, *vis), mask = _pad_pixels(npx, (n, v, kd, ks, *vis), mask, (slow, sigma, mu, fdir, fen))
        terms = _terms(n, v, mask, slow, sigma, fdir, fen, *vis, bool(exact_fast_diffuse), rows)
    out = _combine(terms, mask, kd, ks, mu, sigma)
    c = out.total.shape[-1]
    if out.total.shape[0] != npx:  # padded: the pixels' own rows, copied on the host (no program per count)
        out = Components(*(jax.device_put(np.asarray(x)[:npx]) for x in out))
    return Components(*(x.reshape(batch + (c,)) for x in out))


# `render_practical` pads the pixel count N to a bucket, so that renders of views with different pixel counts
# (flat pixel lists, e.g. `solvers.Observations`) share compiled programs: N rounded up to three significant
# bits (less than 25 % more rows), at least `_MIN_PIXELS`. Compiling `_terms` and `_combine` takes 0.5-0.7 s;
# rendering 5,000 pixels a few ms.
_MIN_PIXELS = 1024


def _pixel_bucket(npx: int) -> int:
    if npx <= _MIN_PIXELS:
        return _MIN_PIXELS
    step = 1 << max(0, (npx - 1).bit_length() - 3)
    return -(-npx // step) * step


def _pad_pixels(npx: int, arrays, mask, others=()):
    """The per-pixel arrays (leading axis `npx`) padded to `_pixel_bucket(npx)` rows outside `mask` (made if None).

    On the host, in NumPy: an eager JAX operation on a new shape would itself compile. Only when nothing of the
    render (`arrays`, `mask`, the other inputs `others`) is traced: under the caller's own `jit`, `grad` or
    `vmap` the shapes are fixed by the trace, padding would only add work, and the rows could not be cut on the
    host. Arrays of another leading size (a `(1, C)` parameter) and None pass unchanged.
    """
    size = _pixel_bucket(npx)
    leaves = jax.tree_util.tree_leaves((arrays, mask, others))
    if size == npx or any(isinstance(x, jax.core.Tracer) for x in leaves):
        return arrays, mask
    pad = size - npx

    def grow(x):
        if x is None or x.shape[0] != npx:
            return x
        x = np.asarray(x)
        return np.concatenate([x, np.zeros((pad,) + x.shape[1:], x.dtype)])

    keep = np.ones(npx, bool) if mask is None else np.asarray(mask, bool)
    return tuple(grow(x) for x in arrays), np.concatenate([keep, np.zeros(pad, bool)])


def _on_rows(where, npx: int, arrays, mask):
    """The per-pixel arrays (leading axis `npx`, and `mask`) split over the devices as the normals are
    (`row_sharding`'s `where`); arrays of another leading size (a `(1, C)` parameter) and None pass unchanged."""
    mesh, axis = where

    def put(x):
        if x is None or x.shape[0] != npx:
            return x
        spec = jax.sharding.PartitionSpec(axis, *(None,) * (x.ndim - 1))
        return jax.device_put(x, jax.sharding.NamedSharding(mesh, spec))

    return tuple(put(x) for x in arrays), put(mask)


# `method="auto"` takes the table when N (lmax+1)^2 >= _TABLE_COST * H * W and N >= _TABLE_MIN_PIXELS:
# building the table costs about as much as the exact sum at _TABLE_COST / (lmax+1)^2 pixels per texel.
_TABLE_COST = 8
_TABLE_MIN_PIXELS = 4096


def _choose_table(method, lighting, sigma, npx: int, dt=jnp.float64) -> int | None:
    """The rows of the slow-lighting table for `method` (None: the exact per-pixel sum).

    The exact sum evaluates the harmonics per pixel, which below float64 give NaN near the poles from lmax ~186
    (`REAL_SH_MAX_LMAX`): there `"auto"` takes the table whenever one meets the error bound, and otherwise, like
    `"exact"`, it is a `ValueError`."""
    if method not in ("auto", "table", "exact"):
        raise ValueError(f"`method` must be 'auto', 'table' or 'exact', got {method!r}")
    if lighting.slow_sh is None:
        return None
    lmax = lighting.lmax
    what = "`render_practical(method='exact')` (per-pixel SH band sums)"
    if method == "exact":
        check_lmax_range(lmax, dt, REAL_SH_MAX_LMAX, what)
        return None
    s = _concrete(sigma)
    rows = _table_rows(lmax, None if s is None else float(s))
    exact_ok = lmax <= REAL_SH_MAX_LMAX[1 if jnp.dtype(dt) == jnp.float64 else 0]
    if method == "auto" and not exact_ok:
        if rows is None:
            check_lmax_range(lmax, dt, REAL_SH_MAX_LMAX, what + " (no table meets the error bound here)")
        return rows
    if method == "table":
        if rows is None:
            what = f"sigma = {float(s):g}" if s is not None else "a traced sigma (the grid is then chosen from lmax alone)"
            raise ValueError(
                f"method='table': with lmax = {lmax} and {what} the interpolation error bound needs a lat-long "
                "table of more than 1024 rows; use method='exact' (or 'auto')"
            )
        return rows
    if rows is None or npx < _TABLE_MIN_PIXELS or npx * (lmax + 1) ** 2 < _TABLE_COST * rows * 2 * rows:
        return None
    return rows


# Two programs, not one: with the terms materialized by the first, XLA does not re-fuse (and
# recompute) the table lookup and the shared per-pixel terms into each of the four outputs.
@jit
def _terms(n, v, mask, slow_sh, sigma, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, rows):
    return _terms_body(n, v, mask, slow_sh, sigma, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, rows)


@jit
def _terms_rows(n, v, mask, slow_sh, sigma, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, rows, where):
    def local(n, v, mask, transfer, fvis, rvis, slow_sh, sigma, fdir, fen):
        return _terms_body(n, v, mask, slow_sh, sigma, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, rows)

    return on_row_shards(local, where, (n, v, mask, transfer, fvis, rvis), (slow_sh, sigma, fdir, fen),
                         replicated=("fast_energy",))


def _terms_body(n, v, mask, slow_sh, sigma, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, rows):
    if mask is not None:  # pixels outside the mask look along +z (a valid direction) and render as 0
        up = jnp.asarray([0.0, 0.0, 1.0], n.dtype)
        n = jnp.where(mask[:, None], n, up)
        v = jnp.where(mask[:, None], v, up)
    table = None if rows is None else (_slow_table(slow_sh, sigma, rows), rows)
    return _eq24_terms(n, v, slow_sh, fdir, fen, transfer, fvis, rvis, exact_fast_diffuse, 256, table)


@jit
def _combine(terms, mask, kd, ks, mu, sigma):
    # mu, sigma were checked: concrete by `TorranceSparrow`, traced by `_check_sigma_traced`
    out = terms.components(kd, ks, mu, sigma, check=False)
    if mask is not None:
        out = Components(*(jnp.where(mask[:, None], x, 0.0) for x in out))
    return out


def _disk_azimuths(n, direction, radius, n_phi, dt):
    """The azimuths of the quadrature of one disk (centre `direction`, angular `radius`) clipped at the horizons of
    the unit normals `n` `(P, 3)`: `(P, 7, n_φ)`, for each azimuth $\\cos m$, $\\sin m$ and $h$ of its radial interval
    $[m - h, m + h]$, the three components of $e_\\varphi$ and the azimuth's weight (`_disk_nodes_at` makes the nodes).

    The rule is polar about the centre $c$: `n_theta` Gauss-Legendre nodes in $r$, the angle from the centre
    ($d\\omega = \\sin r\\,dr\\,d\\varphi$), on each of `n_phi` azimuths. Along the ray of azimuth φ,
    $\\omega(r) = \\cos r\\,c + \\sin r\\,e_\\varphi$, the cosine $n\\cdot\\omega(r) = A\\cos r + B_\\varphi\\sin r$
    ($A = n\\cdot c$, $B_\\varphi = n\\cdot e_\\varphi$) is a sinusoid in $r$ whose zeros are π apart: on $[0, R]$
    ($R \\le π$) it changes sign at most once, at $r^* = \\operatorname{atan2}(-A, B_\\varphi) \\bmod π$, and the
    part above the horizon is one interval, $[0, R]$, $[0, r^*]$, $[r^*, R]$ or empty. The nodes in $r$ span
    that interval, so the integrand has no jump between nodes. (In $q = 1 - \\cos r$, the variable of the former
    rule, the integrand has a $\\sqrt q$ term at the centre that only a full circle of uniform azimuths cancels.)
    The radial integral is then smooth in φ except at the two azimuths where the horizon crosses the disk's rim
    ($r^* = R$: $B_\\varphi = -A\\cot R$); where it does, the azimuths are Gauss-Legendre nodes on the two arcs
    between them ($\\lfloor n_φ/2 \\rfloor$ and $\\lceil n_φ/2 \\rceil$), elsewhere $n_φ$ uniform ones
    (docs/conventions.md, "The reference renderer"). Gradient-safe: every `sqrt`, `arccos` and `atan2` sees
    substituted inputs where its value is not used.
    """
    t, b = tangent_frame(direction)
    a = (n @ direction)[:, None]  # A (P, 1)
    nt_, nb_ = (n @ t)[:, None], (n @ b)[:, None]  # B_phi = nt cos(phi) + nb sin(phi) = rho cos(phi - phi0)
    # the azimuths: uniform, or Gauss-Legendre on the two arcs between the rim crossings phi0 -+ hw
    rho2 = nt_ * nt_ + nb_ * nb_
    rho = jnp.sqrt(jnp.where(rho2 > 0, rho2, 1.0))
    rim = -a * jnp.cos(radius) / jnp.sin(radius)  # B_phi where r* = R
    crosses = (rho2 > 0) & (jnp.abs(rim) < rho) & (n_phi >= 2)
    hw = jnp.arccos(jnp.where(crosses, rim / rho, 0.0))  # in (0, pi)
    phi0 = jnp.arctan2(nb_, jnp.where(rho2 > 0, nt_, 1.0))
    arcs = []
    for k, start, length in ((n_phi // 2, phi0 - hw, 2.0 * hw),
                             (n_phi - n_phi // 2, phi0 + hw, 2.0 * (np.pi - hw))):
        xk, wk = np.polynomial.legendre.leggauss(k) if k else (np.zeros(0), np.zeros(0))
        arcs.append((start + 0.5 * length * jnp.asarray(xk + 1.0, dt)[None, :],
                     0.5 * length * jnp.asarray(wk, dt)[None, :]))
    phi = jnp.where(crosses, jnp.concatenate([arcs[0][0], arcs[1][0]], 1),
                    jnp.asarray(2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi, dt)[None, :])  # (P, n_phi)
    wphi = jnp.where(crosses, jnp.concatenate([arcs[0][1], arcs[1][1]], 1), jnp.asarray(2 * np.pi / n_phi, dt))
    cph, sph = jnp.cos(phi), jnp.sin(phi)
    bb = nt_ * cph + nb_ * sph  # B_phi (P, n_phi)
    inside, end_in = a > 0, a * jnp.cos(radius) + bb * jnp.sin(radius) > 0  # above the horizon at r = 0, r = R
    # r*, used only where the sign changes (so A and B_phi are not both 0 there)
    flat = (a == 0) & (bb == 0)
    r_cut = jnp.mod(jnp.arctan2(jnp.where(flat, -1.0, -a), jnp.where(flat, 0.0, bb)), np.pi)
    r_cut = jnp.clip(r_cut, 0.0, radius)
    r_lo = jnp.where(inside, 0.0, jnp.where(end_in, r_cut, radius))
    r_hi = jnp.where(end_in, radius, jnp.where(inside, r_cut, radius))
    m, h = 0.5 * (r_lo + r_hi), 0.5 * (r_hi - r_lo)
    e = [cph * t[k] + sph * b[k] for k in range(3)]  # e_phi per component
    return jnp.stack([jnp.cos(m), jnp.sin(m), h, *e, wphi], axis=1)  # (P, 7, n_phi)


def _disk_nodes_at(az, direction, n_theta, dt):
    """The nodes on the azimuths `az` of `_disk_azimuths` (`(P, 7, n_φ)`), `n_theta` Gauss-Legendre nodes on each
    one's radial interval: the directions' three components and the solid-angle weights, each `(P, n_θ n_φ)`."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    cm, sm, h, ex, ey, ez, wphi = (az[:, i] for i in range(7))
    e = (ex, ey, ez)
    # r = m + h x at the Gauss-Legendre node x in (-1, 1): cos r and sin r by the addition theorem from cos m,
    # sin m (per azimuth) and cos(hx), sin(hx) by their Taylor series (|hx| <= R/2 <= pi/2: the terms to degree
    # 20 and 21 leave < 2e-17). XLA:CPU's cosine and sine take ~6 ns each in float64, and it fuses them into each
    # consumer (and drops `optimization_barrier`s first): as `jnp.cos(r)`, `jnp.sin(r)` the nodes took 4x the
    # time of the whole render before (docs/performance.md, twenty-fifth round).
    cm, sm = cm[:, None, :], sm[:, None, :]  # (P, 1, n_phi)
    u = h[:, None, :] * jnp.asarray(x, dt)[None, :, None]  # (P, n_theta, n_phi)
    cu, su = _cos_sin_small(u)
    cr, sr = cm * cu - sm * su, sm * cu + cm * su
    p = h.shape[0]
    dirs = tuple((cr * direction[k] + sr * e[k][:, None, :]).reshape(p, -1) for k in range(3))
    wts = h[:, None, :] * sr * jnp.asarray(w, dt)[None, :, None] * wphi[:, None, :]  # d omega = sin r dr dphi
    return dirs, wts.reshape(p, -1)


def _cos_sin_small(u):
    """$\\cos u$, $\\sin u$ for $|u| \\le π/2$ by their Taylor series in $u^2$ (Horner; to degrees 20 and 21: the
    remainders are below 2e-17 and 1.2e-18), multiply-adds only."""
    u2 = u * u
    c = s = jnp.zeros_like(u)
    for k in range(10, -1, -1):  # cos: sum (-1)^k u^2k / (2k)!; sin: u sum (-1)^k u^2k / (2k+1)!
        c = c * u2 + (-1) ** k / math.factorial(2 * k)
        s = s * u2 + (-1) ** k / math.factorial(2 * k + 1)
    return c, u * s


def _reference_lighting(lighting, light_kw) -> Lighting | None:
    """The `Lighting` of a `render_reference` call (keyword form: `directional=`, `disks=` tuples)."""
    directional, disks = light_kw.get("directional"), light_kw.get("disks")
    if lighting is not None:
        if lighting.slow_sh is not None:
            raise ValueError(
                "`render_reference` integrates the lighting itself, not its SH: `lighting.slow_sh` must be None; "
                "give the slow part as `envmap=` (e.g. `jaxsh.synthesize_latlong(slow_sh, H, W)`) and the compact "
                "sources as disks / fast sources of the `Lighting`"
            )
        return lighting
    if directional is None and disks is None:
        return None
    parts = {}
    if disks is not None:
        ddir, drad, dl = disks
        ddir = check_dirs(ddir, "disks[0]").reshape(-1, 3)
        parts.update(
            disk_directions=ddir,
            disk_radius=as_float_array(drad, "disks[1]").reshape(-1),
            disk_radiance=_per_source(dl, ddir.shape[0], "disks[2]"),
        )
    if directional is not None:
        jd, je = directional
        jd = check_dirs(jd, "directional[0]").reshape(-1, 3)
        parts.update(fast_directions=jd, fast_energy=_per_source(je, jd.shape[0], "directional[1]"))
    return Lighting(**parts)


def _per_source(x, j: int, name: str):
    """A keyword form's radiance for `j` sources: a scalar (every source, one channel) or as given, `(J,)` or
    `(J, C)`, for `Lighting`'s shape check (a reshape to `(J, -1)` here used to turn an energy `(2, 3)` of one
    source into 6 channels, and an RGB `(1, 3)` of three sources into one scalar each)."""
    x = as_float_array(x, name)
    return jnp.broadcast_to(x, (j,)) if x.ndim == 0 else x


def render_reference(
    normals: Real[ArrayLike, "*#batch 3"],
    views: Real[ArrayLike, "*#batch 3"],
    brdf: TorranceSparrow | Real[ArrayLike, "*#batch C"] | ScalarLike | SequenceLike | None = None,
    lighting: Lighting | Real[ArrayLike, "*#batch C"] | ScalarLike | SequenceLike | None = None,
    *legacy,
    envmap: Real[ArrayLike, "H W C"] | None = None,
    disk_nodes: tuple[int, int] = (48, 96),
    mesh=None,
    points: Real[ArrayLike, "*#batch 3"] | None = None,
    chunk: int | None = None,
    brdf_model: str = "torrance_sparrow",
    **legacy_kw,
) -> Float[Array, "*batch C"]:
    """Reference renderer: the reflection equation with the full Torrance-Sparrow BRDF (or a fuller one).

    $B = \\int L(\\omega_i)\\,\\rho(\\omega_i, \\omega_o)\\max(n\\cdot\\omega_i, 0)\\,V\\,d\\omega_i$
    with $\\rho$ = `torrance_sparrow` (R&H sec. 5.2), integrated exactly for
    delta sources, by a polar Gauss-Legendre rule over each disk source made
    for each pixel and clipped at its horizon (`disk_nodes` = (n_θ, n_φ) per
    disk: the integrand has no jump between nodes, so the
    rule converges spectrally once the nodes resolve the lobe: within 1e-10 of
    scipy's adaptive quadrature at (48, 192) where the lobe meets the horizon
    inside the disk, against 1e-3 with one rule shared by every pixel, as
    before; the nodes should still be finer than the lobe, which at grazing
    views is thin: 7.7 % low at $\\cos\\theta_o$ = 0.021, σ 0.15, with the
    default nodes; docs/conventions.md, "The reference renderer"), and texel by texel over a lat-long
    environment map (exact Fejér weights; accurate only where the lobe is
    wider than a texel). Memory-bounded (pixels in chunks), no SH
    anywhere: the ground truth the practical model is checked against. The
    BRDF is evaluated over all (pixel, direction) pairs from per-pair scalars
    (`jaxsh._reference_pairs`), with the models' own formulas: equal to
    `torrance_sparrow` / `cook_torrance_smith` / `ggx` of each pair to rounding.

    `render_reference(normals, views, brdf, lighting, envmap=..., ...)`, or
    in the keyword form `render_reference(normals, views, kd, ks, mu, sigma,
    envmap=..., directional=(directions (J, 3), energy (J, C)),
    disks=(directions (K, 3), angular_radii (K,), radiance (K, C)))`.

    **Arguments:**

    - `normals`, `views`, `brdf`: as `render_practical` (normalized here); zero
      normals or views (a G-buffer's misses) render as 0, NaN/inf is a `ValueError`.
    - `lighting`: a `jaxsh.Lighting` with fast sources (exact) and/or disks
      (quadrature), and no `slow_sh` (SH lighting is not integrated here;
      pass it as `envmap`). Optional when `envmap` is given.
    - `envmap`: `(H, W, C)` lat-long map (world frame, docs/conventions.md layout).
    - For concave objects pass the occluding `mesh` (trimesh) and the surface
      `points` `(..., 3)`: every quadrature direction of every pixel is then
      ray-cast (`directional_visibility`; NumPy/embree, N × M rays) and the
      integrand multiplied by its visibility (R&H sec. 6.4 shadowing; each
      direction's visibility is exact, but a shadow edge across a disk makes the
      integrand jump: 0.5–1.3 % at the default `disk_nodes`, ≤ 2e-4 at (192, 384), measured with the former
      rule shared by every pixel).
    - `chunk` (static): pixels per step of the loop over pixels; each step holds a few
      `(chunk, M)` arrays for the `M` directions (quadrature nodes, texels, sources). Default:
      $\\max(16, \\min(4096, 2^{19}/M))$ (about 4 MB per array; docs/performance.md, "Fourteenth round").
    - `brdf_model` (static): the BRDF of the integrand, in the parameters of
      `brdf`: `"torrance_sparrow"` (default, the practical model's BRDF),
      `"cook_torrance"` (`jaxsh.cook_torrance_smith`: Beckmann, Smith $G$,
      Fresnel at the half angle) or `"ggx"` (`jaxsh.ggx`) — data the practical
      model cannot reproduce exactly (docs/conventions.md, "fuller reference BRDFs").

    **Returns:** `(..., C)` radiance.
    """
    if brdf_model not in _REFERENCE_BRDFS:
        raise ValueError(f"`brdf_model` must be one of {sorted(_REFERENCE_BRDFS)}, got {brdf_model!r}")
    brdf, lighting, light_kw = model_args("render_reference", brdf, lighting, legacy, legacy_kw, ("directional", "disks"))
    lighting = _reference_lighting(lighting, light_kw)
    if (mesh is None) != (points is None):
        raise ValueError("`mesh` and `points` go together (visibility needs both)")
    normals = check_dirs(normals, "normals")
    views = check_dirs(views, "views")
    batch = _batch(normals, views)
    # zero normals/views (a G-buffer's misses) render as 0, as before; NaN/inf is an error
    _check_geometry(normals, "normals", batch, None, allow_zero=True)
    _check_geometry(views, "views", batch, None, allow_zero=True)
    kd = _channels(brdf.kd, "kd")
    ks = _channels(brdf.ks, "ks")
    mu, sigma = brdf.mu, brdf.sigma
    # on the arrays, not their dtypes: a Python scalar's weak type must not widen float32 geometry (conventions.md)
    dt = jnp.result_type(normals, views, kd, ks)
    dirs_all, rad_all = [], []
    chans = _brdf_channels(kd, ks) + ([] if lighting is None else _lighting_channels(lighting))
    env = None
    if envmap is not None:
        env = as_float_array(envmap, "envmap")
        if env.ndim != 3:
            raise ValueError(f"`envmap` must have shape (H, W, C), got {tuple(env.shape)}")
        chans.append(("`envmap`", env.shape[-1]))
        ce = _concrete(env)
        if ce is not None and not np.all(np.isfinite(ce)):
            i = tuple(int(k) for k in np.argwhere(~np.isfinite(ce))[0])
            raise ValueError(f"`envmap` must be finite, got {ce[i]} at texel {i}")
    _check_channels(chans)
    for name, x in (("kd", kd), ("ks", ks)):
        if x.ndim > 1 and not _broadcasts_to(x.shape, tuple(batch) + (x.shape[-1],)):
            raise ValueError(f"`{name}` must have shape (C,) or {tuple(batch)} + (C,) (a texture), got {tuple(x.shape)}")
    if points is not None and not _broadcasts_to(jnp.shape(points), tuple(batch) + (3,)):
        raise ValueError(f"`points` must have shape {tuple(batch) + (3,)} (the batch of `normals`), got {tuple(jnp.shape(points))}")
    c = max(kd.shape[-1], ks.shape[-1])
    if env is not None:
        h, w, ce = env.shape
        c = max(c, ce)
        dirs_all.append(latlong_directions(h, w, dtype=dt).reshape(-1, 3))
        rad_all.append((env.astype(dt) * latlong_weights(h, w, dtype=dt)[..., None]).reshape(-1, ce))
    disks = None
    nodes = tuple(check_positive_int(disk_nodes[k], f"disk_nodes[{k}]") for k in range(2))
    if lighting is not None and lighting.disk_directions is not None:
        # each disk's nodes are made per pixel, clipped at its horizon (`_disk_azimuths`, `_disk_nodes_at`)
        ddir = lighting.disk_directions.astype(dt)
        disks = (ddir / jnp.linalg.norm(ddir, axis=-1, keepdims=True), lighting.disk_radius.astype(dt),
                 lighting.disk_radiance.astype(dt))
        c = max(c, disks[2].shape[1])
    if lighting is not None and lighting.fast_directions is not None:
        jd = lighting.fast_directions.astype(dt)
        je = lighting.fast_energy.astype(dt)
        dirs_all.append(jd / jnp.linalg.norm(jd, axis=-1, keepdims=True))
        rad_all.append(je)
        c = max(c, je.shape[1])
    if not dirs_all and disks is None:
        raise ValueError("give the lighting: a `Lighting` with fast sources / disks and/or `envmap` (keyword form: `envmap`, `disks` and/or `directional`)")
    sd = sl = None
    if dirs_all:  # directions shared by every pixel: texels, delta sources
        sd = jnp.concatenate(dirs_all, axis=0)
        sl = jnp.concatenate([jnp.broadcast_to(x, (x.shape[0], c)) for x in rad_all], axis=0)  # radiance x weight
    if disks is not None:
        disks = (disks[0], disks[1], jnp.broadcast_to(disks[2], (disks[2].shape[0], c)))
    # unit normals and views, as `render_practical` (a zero one, a G-buffer's miss, stays 0 and renders 0): |n| = 2
    # doubled the diffuse term and halved the specular one
    n = _unit_or_zero(jnp.broadcast_to(normals, batch + (3,)).astype(dt).reshape(-1, 3))
    v = _unit_or_zero(jnp.broadcast_to(views, batch + (3,)).astype(dt).reshape(-1, 3))
    kd = _bcast(kd.astype(dt), batch, c).reshape(-1, c)
    ks = _bcast(ks.astype(dt), batch, c).reshape(-1, c)
    vis = vis_disk = None
    if mesh is not None:
        from ._raycast import directional_visibility

        pts = np.asarray(jnp.broadcast_to(jnp.asarray(points, dt), batch + (3,)).reshape(-1, 3))
        if sd is not None:
            vis = jnp.asarray(directional_visibility(mesh, pts, np.asarray(n), np.asarray(sd)), dt)
        if disks is not None:  # every pixel's own disk nodes
            nodes_at = np.asarray(_disk_nodes_jit(n, disks, nodes))
            vis_disk = jnp.asarray(directional_visibility(mesh, pts, np.asarray(n), nodes_at), dt)
    sigma, mu = _check_sigma_traced(jnp.asarray(sigma, dt), None if mu is None else jnp.asarray(mu, dt))
    m = (0 if sd is None else sd.shape[0]) + (0 if disks is None else disks[0].shape[0] * nodes[0] * nodes[1])
    chunk = _reference_chunk(m) if chunk is None else check_positive_int(chunk, "chunk")
    out = _reference(n, v, kd, ks, mu, sigma, sd, sl, vis, chunk, brdf_model, disks, vis_disk, nodes)
    return out.reshape(batch + (c,))


def _unit_or_zero(a):
    n2 = jnp.sum(a * a, -1, keepdims=True)
    return jnp.where(n2 > 0, a * jax.lax.rsqrt(jnp.where(n2 > 0, n2, 1.0)), 0.0)


def _reference_chunk(m: int) -> int:
    """`render_reference`'s default pixels per loop step for `m` directions: `(chunk, m)` arrays of ~2^19 elements."""
    return max(16, min(4096, (1 << 19) // m))


def _azimuths(n, disks, nodes):
    """Every disk's `_disk_azimuths` at the pixels `n` `(P, 3)`: `(P, K, 7, n_φ)`."""
    return jnp.stack([_disk_azimuths(n, disks[0][k], disks[1][k], nodes[1], n.dtype)
                      for k in range(disks[0].shape[0])], axis=1)


def _disk_nodes(az, disks, nodes):
    """Every disk's `_disk_nodes_at` side by side: the directions' components and the weights, each
    `(P, K n_θ n_φ)`."""
    parts = [_disk_nodes_at(az[:, k], disks[0][k], nodes[0], az.dtype) for k in range(az.shape[1])]
    dirs = tuple(jnp.concatenate([d[i] for d, _ in parts], axis=1) for i in range(3))
    return dirs, jnp.concatenate([w for _, w in parts], axis=1)


@jit
def _disk_nodes_jit(n, disks, nodes):
    """The directions of `_disk_nodes` at every pixel, `(P, K n_θ n_φ, 3)` (for the ray caster)."""
    return jnp.stack(_disk_nodes(_azimuths(n, disks, nodes), disks, nodes)[0], axis=-1)


def _disk_shared_nodes(disks, nodes):
    """The rule of `_disk_azimuths` / `_disk_nodes_at` where no pixel's horizon cuts the disk (the same for every
    pixel there: radial nodes on [0, R], uniform azimuths), made by them at the normal along the disk's centre:
    directions `(K n_θ n_φ, 3)` and the radiance times the weight `(K n_θ n_φ, C)`, in the order of `_disk_nodes`.
    (A disk of radius ≥ π/2 is cut by every seen pixel's horizon, `_horizon_cuts_a_disk`, so its shared rule, then
    clipped at the centre's own horizon, is never used.)"""
    dirs, wts = [], []
    for k in range(disks[0].shape[0]):
        c = disks[0][k]
        az = _disk_azimuths(c[None], c, disks[1][k], nodes[1], c.dtype)
        d, w = _disk_nodes_at(az, c, nodes[0], c.dtype)
        dirs.append(jnp.stack([x[0] for x in d], axis=-1))
        wts.append(w[0][:, None] * disks[2][k][None, :])
    return jnp.concatenate(dirs, 0), jnp.concatenate(wts, 0)


def _horizon_cuts_a_disk(n, v, disks):
    """`(P,)` True where a seen pixel's horizon crosses some disk ($|n\\cdot c| < \\sin R$, or $R \\ge π/2$) with a
    margin of 1e-6 for rounding: only there do its nodes differ from `_disk_shared_nodes`."""
    seen = jnp.sum(n * v, -1) > 0
    dots = jnp.abs(n @ disks[0].T)  # (P, K)
    r = disks[1][None, :]
    cut = (r >= 0.5 * np.pi) | (dots < jnp.sin(jnp.minimum(r, 0.5 * np.pi)) + 1e-6)
    return seen & jnp.any(cut, axis=-1)


@jit
def _reference(n, v, kd, ks, mu, sigma, sd, sl, vis, chunk, model="torrance_sparrow", disks=None, vis_disk=None,
               nodes=(48, 96)):
    npx = n.shape[0]
    pad = (-npx) % chunk if npx > chunk else 0
    size = chunk if npx > chunk else npx
    # each disk node's radiance (its weight is per pixel)
    disk_l = None if disks is None else jnp.repeat(disks[2], nodes[0] * nodes[1], axis=0)
    shared = None if disks is None or vis_disk is not None else _disk_shared_nodes(disks, nodes)

    def one_chunk(args):
        nn, vv, kkd, kks, vv_is, vv_disk, az_, cut_ = args

        def part(dirs, wts, rad, vis_):
            # rho_s at K_s = 1 for every (pixel, direction) pair: F S / (4 cos cos) (or F D G / ...), 0 below horizons
            spec, ci, cos_o = specular_pairs(nn, vv, dirs, mu, sigma, model)
            cos_i = jnp.maximum(ci, 0.0) if vis_ is None else jnp.maximum(ci, 0.0) * vis_
            if wts is not None:
                cos_i = cos_i * wts
            diff = jnp.where(cos_o > 0, cos_i, 0.0) @ rad  # (n, C)
            spc = (spec * cos_i) @ rad
            return kkd * diff + kks * spc

        def per_pixel():
            dd, ww = _disk_nodes(az_.reshape(az_.shape[0], disks[0].shape[0], 7, nodes[1]), disks, nodes)
            return part(dd, ww, disk_l, vv_disk)

        out = 0.0
        if sd is not None:  # shared directions: the weights are in `sl`
            out = out + part(sd, None, sl, vv_is)
        if disks is not None:
            if shared is None:  # with visibility, every pixel's own nodes were ray-cast
                out = out + per_pixel()
            else:  # a chunk where no horizon cuts a disk takes the shared nodes (one matrix product, no trigonometry)
                out = out + jax.lax.cond(jnp.any(cut_), per_pixel, lambda: part(shared[0], None, shared[1], None))
        return out

    # the disks' per-azimuth arrays of every pixel, made here, before the loop over chunks: inside it, XLA:CPU
    # would fuse them (arctangents and all) into each node's computation
    az = cut = order = None
    if disks is not None:
        az = _azimuths(n, disks, nodes).reshape(npx, -1)
        if shared is not None:  # the pixels whose horizon cuts a disk first, so that most chunks have none or all
            cut = _horizon_cuts_a_disk(n, v, disks)
            order = jnp.argsort(~cut, stable=True)
            cut = cut[order][:, None]
    arrs = [None if a is None else (a if order is None else a[order]) for a in (n, v, kd, ks, vis, vis_disk, az)]
    arrs = [None if a is None else jnp.pad(a, ((0, pad), (0, 0))) for a in arrs + [cut]]
    if pad == 0 and npx <= chunk:
        res = one_chunk(arrs)
    else:
        nch = arrs[0].shape[0] // size
        res = jax.lax.map(one_chunk, tuple(None if a is None else a.reshape(nch, size, -1) for a in arrs))
        res = res.reshape(-1, res.shape[-1])[:npx]
    return res if order is None else jnp.zeros_like(res).at[order].set(res)
