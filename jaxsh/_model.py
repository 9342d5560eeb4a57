"""The domain types of the forward model: `Lighting` and `TorranceSparrow` (R&H 2001 secs. 5.2, 5.3).

`jaxsh.render_practical`, `jaxsh.practical_terms` and `jaxsh.render_reference`
take them (`render_practical(normals, views, brdf, lighting)`), and every
solver in `solvers` returns and accepts them. Both are final `equinox.Module`s
(pytrees: they pass through `jit`, `grad` and `vmap`); their constructors
convert the fields to float JAX arrays and check the shapes, raising
`ValueError` naming the field and the expected shape.

**Values** are checked too when they are concrete (outside `jit`/`vmap`):
a non-finite entry in any field, $\\sigma \\le 0$, $\\mu < 1$, a negative
$K_d$, $K_s$, source energy or disk radiance, a zero-length direction or a
disk radius outside $(0, \\pi]$ raise `ValueError` naming the field and the
offending value. Under a transformation the values are traced and these
checks are skipped (the public renderers and BRDF functions check σ and μ
again with `equinox.error_if`; a traced negative $K_d$ or $K_s$ is not
checked there: linear fits may produce one, and it renders as given). Solver *results* (standard
errors, the estimate of a failed solve) may hold `inf`/NaN: they are built
with `TorranceSparrow.unchecked(...)` / `Lighting.unchecked(...)`, the same
constructor without the value checks.
"""

from __future__ import annotations

import contextvars
from typing import final

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._compile import jit
from ._checks import as_float_array, lmax_from_size
from ._indexing import num_coeffs
from ._lighting import directional_light_sh, disk_light_sh, split_disk_sources


def _opt_float(name):
    """Converter of an optional float field: errors name the field (e.g. `Lighting.fast_directions`)."""
    return lambda x: None if x is None else as_float_array(x, name)


def _opt_channels(name):
    """Converter of an optional `(K, C)` field: `(K,)` -> `(K, 1)` (one channel, channels last)."""

    def convert(x):
        if x is None:
            return None
        x = as_float_array(x, name)
        return x[:, None] if x.ndim == 1 else x

    return convert


def _float(name):
    """Converter of a required float field."""
    return lambda x: as_float_array(x, name)


def _shape(x):
    return tuple(int(s) for s in x.shape)


_UNCHECKED = contextvars.ContextVar("jaxsh_model_unchecked", default=False)


def _concrete(x):
    """`x` as a NumPy array, or `None` when it is absent or traced (value checks are then skipped)."""
    if x is None or isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x)
    except (TypeError, jax.errors.ConcretizationTypeError):  # pragma: no cover - defensive
        return None


def check_values(x, name: str, *, lower=None, lower_open: bool = False, upper=None, owner: str = "") -> None:
    """Raise `ValueError` naming `name` if the concrete array `x` has a non-finite entry or one out of range.

    `lower` / `upper` bound the values (`lower_open`: strictly above `lower`). Traced values pass.
    """
    a = _concrete(x)
    if a is None or a.size == 0:
        return
    where = f"{owner}: " if owner else ""
    bad = ~np.isfinite(a)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{where}`{name}` must be finite, got {a[idx] if idx else a[()]} at index {idx}")
    rng = []
    if lower is not None:
        bad = (a <= lower) if lower_open else (a < lower)
        rng.append(f"{'>' if lower_open else '>='} {lower}")
    else:
        bad = np.zeros(a.shape, bool)
    if upper is not None:
        bad = bad | (a > upper)
        rng.append(f"<= {upper:.6g}")
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        v = a[idx] if idx else a[()]
        raise ValueError(f"{where}`{name}` must be {' and '.join(rng)}, got {v}" + (f" at index {idx}" if idx else ""))


def _check_directions(x, name: str, owner: str) -> None:
    check_values(x, name, owner=owner)
    a = _concrete(x)
    if a is not None and a.size:
        norm = np.linalg.norm(a, axis=-1)
        if (norm == 0).any():
            raise ValueError(f"{owner}: `{name}` must be non-zero directions, row {int(np.argmax(norm == 0))} is zero")


def _unchecked_init(cls, args, kwargs):
    token = _UNCHECKED.set(True)
    try:
        return cls(*args, **kwargs)
    finally:
        _UNCHECKED.reset(token)


@final
class Lighting(eqx.Module):
    """Distant lighting in the world frame (+z up), in the three forms of R&H sec. 5.3.

    - the **slow** part as real SH coefficients (eqs. 21, 22: filtered by the
      BRDF, rendered from its spherical-harmonic coefficients);
    - **fast** delta sources, each a direction and its total energy $L_j$
      (eq. 23; `jaxsh.directional_light_sh` for their SH);
    - **disk** (area) sources, each a centre direction, an angular radius $r$
      and a uniform radiance (energy $2\\pi(1-\\cos r)$·radiance, as
      `jaxsh.disk_light_sh` / `jaxsh.split_disk_sources` represent them).

    `render_reference` takes the fast sources exactly and the disks by
    quadrature (its `disk_nodes`);
    `render_practical` takes the slow and fast parts and asks for the
    slow/fast split of the disks first (`split_disks`).

    **Fields** (all optional, at least one part; `C` channels, 1 broadcasts):

    - `slow_sh`: `(n_coeffs, C)` real SH coefficients, $n_{coeffs} = (l_{max}+1)^2$
      (`(n_coeffs,)` is one channel).
    - `fast_directions`: `(J, 3)` unit directions towards the sources;
      `fast_energy`: `(J, C)` (or `(J,)`) total energy of each.
    - `disk_directions`: `(D, 3)` unit centre directions; `disk_radius`: `(D,)`
      angular radii in radians, in $(0, \\pi]$; `disk_radiance`: `(D, C)` (or `(D,)`).

    Positional order: `Lighting(slow_sh, fast_directions, fast_energy,
    disk_directions, disk_radius, disk_radiance)`.
    """

    slow_sh: Float[Array, "n_coeffs C"] | None = eqx.field(default=None, converter=_opt_channels("Lighting.slow_sh"))
    fast_directions: Float[Array, "J 3"] | None = eqx.field(default=None, converter=_opt_float("Lighting.fast_directions"))
    fast_energy: Float[Array, "J C"] | None = eqx.field(default=None, converter=_opt_channels("Lighting.fast_energy"))
    disk_directions: Float[Array, "D 3"] | None = eqx.field(default=None, converter=_opt_float("Lighting.disk_directions"))
    disk_radius: Float[Array, " D"] | None = eqx.field(default=None, converter=_opt_float("Lighting.disk_radius"))
    disk_radiance: Float[Array, "D C"] | None = eqx.field(default=None, converter=_opt_channels("Lighting.disk_radiance"))

    def __check_init__(self):
        fast = (self.fast_directions, self.fast_energy)
        disk = (self.disk_directions, self.disk_radius, self.disk_radiance)
        if self.slow_sh is None and all(x is None for x in fast + disk):
            raise ValueError(
                "Lighting needs `slow_sh`, `fast_directions` + `fast_energy` and/or `disk_directions` + "
                "`disk_radius` + `disk_radiance`: no lighting was given"
            )
        if any(x is None for x in fast) != all(x is None for x in fast):
            raise ValueError("Lighting: `fast_directions` and `fast_energy` go together")
        if any(x is None for x in disk) != all(x is None for x in disk):
            raise ValueError("Lighting: `disk_directions`, `disk_radius` and `disk_radiance` go together")
        chans = []
        if self.slow_sh is not None:
            s = _shape(self.slow_sh)
            if len(s) != 2:
                raise ValueError(f"`slow_sh` must have shape (n_coeffs, C), got {s}")
            lmax_from_size(s[0], "slow_sh")
            chans.append(("slow_sh", s[1]))
        if self.fast_directions is not None:
            j = self._directions("fast_directions")
            e = _shape(self.fast_energy)
            if len(e) != 2 or e[0] != j:
                raise ValueError(f"`fast_energy` must have shape ({j}, C) or ({j},), got {e}")
            chans.append(("fast_energy", e[1]))
        if self.disk_directions is not None:
            d = self._directions("disk_directions")
            if _shape(self.disk_radius) != (d,):
                raise ValueError(f"`disk_radius` must have shape ({d},), got {_shape(self.disk_radius)}")
            r = _shape(self.disk_radiance)
            if len(r) != 2 or r[0] != d:
                raise ValueError(f"`disk_radiance` must have shape ({d}, C) or ({d},), got {r}")
            chans.append(("disk_radiance", r[1]))
        c = max(k for _, k in chans)
        for name, k in chans:
            if k not in (1, c):
                raise ValueError(f"`{name}` has {k} channels, the rest of the lighting {c} (give C or 1)")
        if not _UNCHECKED.get():
            self._check_values()

    def _check_values(self):
        o = "Lighting"
        check_values(self.slow_sh, "slow_sh", owner=o)
        if self.fast_directions is not None:
            _check_directions(self.fast_directions, "fast_directions", o)
            check_values(self.fast_energy, "fast_energy", lower=0.0, owner=o)
        if self.disk_directions is not None:
            _check_directions(self.disk_directions, "disk_directions", o)
            check_values(self.disk_radius, "disk_radius", lower=0.0, lower_open=True, upper=float(np.pi), owner=o)
            check_values(self.disk_radiance, "disk_radiance", lower=0.0, owner=o)

    @classmethod
    def unchecked(cls, *args, **kwargs) -> "Lighting":
        """The constructor without the value checks (shapes are still checked): for solver results
        that may hold `inf`/NaN or negative estimates."""
        return _unchecked_init(cls, args, kwargs)

    def _directions(self, name):
        s = _shape(getattr(self, name))
        if len(s) != 2 or s[1] != 3:
            raise ValueError(f"`{name}` must have shape (J, 3), got {s}")
        return s[0]

    @property
    def lmax(self) -> int | None:
        """Band limit of `slow_sh` (`None` without a slow part)."""
        return None if self.slow_sh is None else lmax_from_size(self.slow_sh.shape[0], "slow_sh")

    @property
    def n_channels(self) -> int:
        """`C`: the channel count the parts broadcast to."""
        parts = (self.slow_sh, self.fast_energy, self.disk_radiance)
        return max(p.shape[1] for p in parts if p is not None)

    @property
    def has_disks(self) -> bool:
        return self.disk_directions is not None

    def total_sh(self, lmax: int) -> Float[Array, "n_coeffs C"]:
        """SH coefficients of all of the lighting to `lmax`: `slow_sh` (cut or zero-padded), the
        fast sources as deltas (`directional_light_sh`) and the disks in closed form (`disk_light_sh`).
        One compiled program per (`lmax`, shapes): the parts' values are checked when the `Lighting` is built."""
        return _total_sh(self, int(lmax))

    def _total_sh(self, lmax: int):
        n = num_coeffs(lmax)
        parts = []
        if self.slow_sh is not None:
            s = self.slow_sh
            parts.append(s[:n] if s.shape[0] >= n else jnp.pad(s, ((0, n - s.shape[0]), (0, 0))))
        if self.fast_directions is not None:
            parts.append(directional_light_sh(self.fast_directions, self.fast_energy, lmax))
        if self.disk_directions is not None:
            for k in range(self.disk_directions.shape[0]):
                d = self.disk_directions[k]
                parts.append(disk_light_sh(d / jnp.linalg.norm(d), self.disk_radius[k], self.disk_radiance[k], lmax))
        c = self.n_channels
        out = jnp.broadcast_to(parts[0], (n, c))
        for p in parts[1:]:
            out = out + jnp.broadcast_to(p.astype(out.dtype), (n, c))
        return out

    def split_disks(self, sigma: float, lmax: int, ratio: float = 0.25) -> "Lighting":
        """The slow/fast split of R&H sec. 5.3 applied to the disks (`jaxsh.split_disk_sources`).

        Disks with angular radius `< ratio·σ` become fast sources carrying
        their energy; the others are added to `slow_sh` (to `lmax`, or to
        the band limit of `slow_sh` if that is higher). Outside `jit`
        (the split is decided on concrete values). Returns a `Lighting`
        without disks, ready for `render_practical`; `self` if it has none.
        """
        if self.disk_directions is None:
            return self
        lmax = max(int(lmax), self.lmax or 0)
        slow, fd, fe = split_disk_sources(self.disk_directions, self.disk_radius, self.disk_radiance, sigma, lmax, ratio)
        dt, c = self.disk_radiance.dtype, self.n_channels
        n = num_coeffs(lmax)
        slow_parts = [] if slow is None else [jnp.asarray(slow, dt)]
        if self.slow_sh is not None:
            slow_parts.append(Lighting(self.slow_sh).total_sh(lmax))
        fast_dirs = [] if fd is None else [jnp.asarray(fd, dt)]
        fast_energy = [] if fe is None else [jnp.asarray(fe, dt)]
        if self.fast_directions is not None:
            fast_dirs.append(self.fast_directions)
            fast_energy.append(self.fast_energy)
        slow_sh = sum(jnp.broadcast_to(p.astype(dt), (n, c)) for p in slow_parts) if slow_parts else None
        if not fast_dirs:
            return Lighting(slow_sh)
        fe = jnp.concatenate([jnp.broadcast_to(e.astype(dt), (e.shape[0], c)) for e in fast_energy])
        return Lighting(slow_sh, jnp.concatenate([d.astype(dt) for d in fast_dirs]), fe)


@final
class TorranceSparrow(eqx.Module):
    """R&H sec. 5.2 BRDF: $\\rho = K_d + K_s F(\\mu,\\theta_o) S / (4\\cos\\theta_i\\cos\\theta_o)$,
    $S = e^{-(\\theta_h/\\sigma)^2}/(\\pi\\sigma^2)$ (`jaxsh.torrance_sparrow`).

    **Fields:**

    - `kd`, `ks`: `(C,)` homogeneous (a scalar is one channel), `(..., C)`
      textures matching the pixels of the renderers, or `(T, C)` per texel
      (with `solvers.Observations.texel`, R&H sec. 6.4); their shapes broadcast.
    - `mu`: scalar relative index of refraction $\\ge 1$, or `None` for no
      Fresnel term ($F = 1$, metals in R&H fig. 11).
    - `sigma`: scalar roughness (radians), $> 0$.

    `kd`, `ks` $\\ge 0$; every value finite (checked when concrete, module docstring).

    Positional order: `TorranceSparrow(kd, ks, mu, sigma)`.
    """

    kd: Float[Array, "*T C"] | Float[Array, ""] = eqx.field(converter=_float("TorranceSparrow.kd"))
    ks: Float[Array, "*T C"] | Float[Array, ""] = eqx.field(converter=_float("TorranceSparrow.ks"))
    mu: Float[Array, ""] | None = eqx.field(converter=_opt_float("TorranceSparrow.mu"))
    sigma: Float[Array, ""] = eqx.field(converter=_float("TorranceSparrow.sigma"))

    def __check_init__(self):
        try:
            jnp.broadcast_shapes(self.kd.shape, self.ks.shape)
        except ValueError:
            raise ValueError(
                f"`kd` and `ks` must have broadcasting shapes (C,) or (..., C), got {_shape(self.kd)} and {_shape(self.ks)}"
            ) from None
        if self.mu is not None and self.mu.ndim != 0:
            raise ValueError(f"`mu` must be a scalar (shape ()) or None, got shape {_shape(self.mu)}")
        if self.sigma.ndim != 0:
            raise ValueError(f"`sigma` must be a scalar (shape ()), got shape {_shape(self.sigma)}")
        if not _UNCHECKED.get():
            o = "TorranceSparrow"
            check_values(self.kd, "kd", lower=0.0, owner=o)
            check_values(self.ks, "ks", lower=0.0, owner=o)
            check_values(self.mu, "mu", lower=1.0, owner=o)
            check_values(self.sigma, "sigma", lower=0.0, lower_open=True, owner=o)

    @classmethod
    def unchecked(cls, *args, **kwargs) -> "TorranceSparrow":
        """The constructor without the value checks (shapes are still checked): for solver results
        (standard errors, the estimate of a failed solve) that may hold `inf`/NaN."""
        return _unchecked_init(cls, args, kwargs)

    @property
    def n_channels(self) -> int:
        return max(1 if x.ndim == 0 else x.shape[-1] for x in (self.kd, self.ks))


def model_args(fname: str, brdf, lighting, legacy: tuple, legacy_kw: dict, light_names: tuple):
    """Dispatch between `f(..., brdf, lighting, ...)` and the keyword form `f(..., kd, ks, mu, sigma, slow_sh=...)`.

    Returns `(TorranceSparrow, Lighting or None, leftover legacy lighting keywords)`; the
    keyword-form lighting arguments are collected from `legacy_kw` (names in `light_names`).
    """
    if isinstance(brdf, TorranceSparrow):
        if legacy:
            raise TypeError(f"{fname}(normals, views, brdf, lighting) takes no further positional arguments")
        bad = [k for k in legacy_kw if k in ("kd", "ks", "mu", "sigma") or k in light_names]
        if bad:
            raise TypeError(f"{fname}: with a TorranceSparrow, give the lighting as a Lighting, not {bad}")
        if legacy_kw:
            raise TypeError(f"{fname}() got unexpected keyword arguments {sorted(legacy_kw)}")
        if lighting is not None and not isinstance(lighting, Lighting):
            raise ValueError(f"`lighting` must be a jaxsh.Lighting, got {type(lighting).__name__}")
        return brdf, lighting, {}
    names = ("kd", "ks", "mu", "sigma")
    pos = [] if brdf is None else ([brdf] if lighting is None and not legacy else [brdf, lighting])
    pos += list(legacy)
    if len(pos) > 4:
        raise TypeError(f"{fname}() takes at most 4 BRDF arguments (kd, ks, mu, sigma), got {len(pos)}")
    vals = dict(zip(names, pos))
    for k in names:
        if k in legacy_kw:
            if k in vals:
                raise TypeError(f"{fname}() got multiple values for argument '{k}'")
            vals[k] = legacy_kw.pop(k)
    missing = [k for k in names if k not in vals]
    if missing:
        raise TypeError(f"{fname}() missing BRDF arguments {missing} (or pass a jaxsh.TorranceSparrow)")
    light = {k: legacy_kw.pop(k) for k in light_names if k in legacy_kw}
    if legacy_kw:
        raise TypeError(f"{fname}() got unexpected keyword arguments {sorted(legacy_kw)}")
    if vals["kd"] is None or vals["ks"] is None or vals["sigma"] is None:
        raise ValueError("`kd`, `ks` and `sigma` must be arrays, got None")
    return TorranceSparrow(vals["kd"], vals["ks"], vals["mu"], vals["sigma"]), None, light


@jit
def _total_sh(lighting: Lighting, lmax: int):
    """`Lighting.total_sh` as one program (`lmax` static)."""
    return lighting._total_sh(lmax)
