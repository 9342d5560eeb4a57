"""Inputs and results of the inverse-rendering solvers (R&H 2001 sec. 6).

* `Observations`: the valid pixels of one or more calibrated views, flattened
  to `N` samples (normal, view, radiance, weight, optional visibility terms
  and texel index). Build it with `observations(gbuffers, images, ...)`,
  which validates the images and drops or rejects bad pixels.
* `Lighting`, `TorranceSparrow`: `jaxsh.Lighting` and `jaxsh.TorranceSparrow`
  (the same objects, re-exported): the lighting of R&H sec. 5.3 and the BRDF
  parameters of sec. 5.2.
* `Status`: the outcome of a solve. Every solver result carries one; a
  failed solve is a status, never a silent NaN.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, Real

import jaxsh
from jaxsh import Lighting as Lighting, TorranceSparrow as TorranceSparrow  # the domain types live in jaxsh

from ._pixel_sums import map_over_pixels, pixel_sharding
from ._pixel_threads import map_in_threads
from ._results import Status as Status, status_name as status_name  # re-exported for older imports
from ._results import check_int


@jaxsh.jit
def _take(fields, index):
    """`a[index]` for every array of `fields` (None stays None)."""
    return jax.tree_util.tree_map(lambda a: a[index], fields)


class Observations(eqx.Module):
    """`N` valid pixel samples of one or more views (see `observations`).

    **Fields:** `normals`, `views` `(N, 3)`; `values` `(N, C)` linear
    radiance; `weights` `(N,)` (least-squares weights, 1 by default);
    `transfer` `(N, 9)`, `fast_visibility` `(N, J)`,
    `reflected_visibility` `(N,)`: the visibility terms of R&H sec. 6.4 or
    `None` (convex object); `texel` `(N,)` int texel index or `None`;
    `view_index`, `pixel_index` `(N,)`: where each sample came from, and
    `image_shapes` (static) the `(H, W)` of each view, for `to_images`.
    """

    normals: Float[Array, "N 3"]
    views: Float[Array, "N 3"]
    values: Float[Array, "N C"]
    weights: Float[Array, " N"]
    transfer: Float[Array, "N 9"] | None
    fast_visibility: Float[Array, "N J"] | None
    reflected_visibility: Float[Array, " N"] | None
    texel: Int[Array, " N"] | None
    view_index: Int[Array, " N"]
    pixel_index: Int[Array, " N"]
    image_shapes: tuple = eqx.field(static=True)
    n_texels: int = eqx.field(static=True, default=0)

    @property
    def n_samples(self) -> int:
        return self.values.shape[0]

    @property
    def n_channels(self) -> int:
        return self.values.shape[1]

    def subset(self, index) -> "Observations":
        """The samples at integer `index` (outside jit): one compiled gather for every field."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.nonzero(index)[0]
        if index.size and (index.min() < -self.n_samples or index.max() >= self.n_samples):
            raise ValueError(f"`index` must be in [-{self.n_samples}, {self.n_samples}), got {index.min()}..{index.max()}")
        fields = (self.normals, self.views, self.values, self.weights, self.transfer, self.fast_visibility,
                  self.reflected_visibility, self.texel, self.view_index, self.pixel_index)
        return Observations(*_take(fields, jnp.asarray(index)), self.image_shapes, self.n_texels)

    def to_images(self, values: Real[ArrayLike, "N C"], fill: float = 0.0) -> list[np.ndarray]:
        """Scatter per-sample `values` `(N, C)` back into one `(H, W, C)` image per view."""
        values = np.asarray(values)
        if values.ndim != 2 or values.shape[0] != self.n_samples:
            raise ValueError(f"`values` must have shape ({self.n_samples}, C), got {values.shape}")
        vi = np.asarray(self.view_index)
        pi = np.asarray(self.pixel_index)
        out = []
        for k, (h, w) in enumerate(self.image_shapes):
            img = np.full((h * w, values.shape[1]), fill, values.dtype)
            sel = vi == k
            img[pi[sel]] = values[sel]
            out.append(img.reshape(h, w, values.shape[1]))
        return out


def _per_view(arrs, n_views, name, shape_tail, hw):
    if arrs is None:
        return None
    if len(arrs) != n_views:
        raise ValueError(f"`{name}` must be a list of {n_views} arrays (one per view), got {len(arrs)}")
    out = []
    for k, a in enumerate(arrs):
        a = np.asarray(a)
        want = hw[k] + shape_tail
        if a.shape != want:
            raise ValueError(f"`{name}[{k}]` must have shape {want}, got {a.shape}")
        out.append(a.reshape((-1,) + shape_tail))
    return out


def observations(
    gbuffers: Sequence[jaxsh.GBuffer],
    images: Sequence[Real[ArrayLike, "H W C"]],
    *,
    masks: Sequence | None = None,
    weights: Sequence | None = None,
    saturation: float | None = None,
    invalid: str = "raise",
    transfer: Sequence | None = None,
    fast_visibility: Sequence | None = None,
    reflected_visibility: Sequence | None = None,
    texel: Sequence | None = None,
    n_texels: int | None = None,
) -> Observations:
    """Collect the valid pixels of calibrated views into `Observations`.

    A pixel is used when the G-buffer hit the object, the optional user
    `mask` is set, its weight is positive, and — if `saturation` is given —
    no channel reaches `saturation` (clipped pixels carry no radiance
    information and are dropped). Non-finite pixel values inside the mask
    raise `ValueError` naming the view (`invalid="raise"`, the default) or are
    dropped (`invalid="drop"`).

    **Arguments:**

    - `gbuffers`: one `jaxsh.GBuffer` per view; `images`: matching
      `(H, W, C)` (or `(H, W)`) linear radiance images, float (integer code
      values are a `ValueError`: decode them with `jaxsh.io.read_image`).
    - `masks`, `weights`: optional per-view `(H, W)` arrays. A mask keeps the
      pixels where it is nonzero (bool, integer) or above 0.5 (float: a
      coverage or a soft mask, as `jaxsh.io.read_mask` thresholds files; 0.1
      used to count as inside).
    - `transfer` `(H, W, 9)`, `fast_visibility` `(H, W, J)`,
      `reflected_visibility` `(H, W)`: optional per-view visibility terms
      (`jaxsh.visibility_sh`, `jaxsh.directional_visibility`,
      `jaxsh.reflected_visibility`).
    - `texel`: optional per-view `(H, W)` int texel indices in
      `[0, n_texels)` for textured $K_d(x)$ (R&H sec. 6.4).

    **Returns:** `Observations` (float dtype of the G-buffers). Raises
    `ValueError` if no valid pixel remains, or on mismatched shapes.
    """
    if saturation is not None and not (isinstance(saturation, (int, float, np.number)) and np.isfinite(saturation) and saturation > 0):
        raise ValueError(f"`saturation` must be a positive finite number or None, got {saturation!r}")
    if invalid not in ("raise", "drop"):
        raise ValueError(f"`invalid` must be 'raise' or 'drop', got {invalid!r}")
    gbuffers = list(gbuffers)
    images = list(images)
    if len(gbuffers) == 0:
        raise ValueError("`gbuffers` is empty: give at least one view")
    if len(images) != len(gbuffers):
        raise ValueError(f"`images` must have one image per G-buffer ({len(gbuffers)}), got {len(images)}")
    hw = [tuple(int(s) for s in gb.mask.shape) for gb in gbuffers]
    imgs = []
    chans = None
    for k, img in enumerate(images):
        img = np.asarray(img)
        if not np.issubdtype(img.dtype, np.floating):
            # 8/16-bit code values are not radiance: their encoding must be declared (`jaxsh.io.read_image`),
            # never guessed; a complex image lost its imaginary part with only NumPy's warning
            raise ValueError(f"`images[{k}]` must be a float array of linear radiance, got {img.dtype} (decode "
                             "integer images with `jaxsh.io.read_image(path, encoding=...)`)")
        if img.ndim == 2:
            img = img[..., None]
        if img.ndim != 3 or img.shape[:2] != hw[k]:
            raise ValueError(f"`images[{k}]` must have shape {hw[k]} + (C,), got {img.shape}")
        if chans is None:
            chans = img.shape[2]
        elif img.shape[2] != chans:
            raise ValueError(f"`images[{k}]` has {img.shape[2]} channels, `images[0]` has {chans}")
        imgs.append(img.reshape(-1, chans))
    m_user = _per_view(masks, len(gbuffers), "masks", (), hw)
    w_user = _per_view(weights, len(gbuffers), "weights", (), hw)
    tr = _per_view(transfer, len(gbuffers), "transfer", (9,), hw)
    rv = _per_view(reflected_visibility, len(gbuffers), "reflected_visibility", (), hw)
    tx = _per_view(texel, len(gbuffers), "texel", (), hw)
    fv = None
    if fast_visibility is not None:
        if len(fast_visibility) != len(gbuffers):  # before reading the first entry's sources (an empty list: IndexError)
            raise ValueError(f"`fast_visibility` must be a list of {len(gbuffers)} arrays (one per view), got "
                             f"{len(fast_visibility)}")
        j = np.asarray(fast_visibility[0]).shape[-1]
        fv = _per_view(fast_visibility, len(gbuffers), "fast_visibility", (j,), hw)
    if n_texels is not None:
        n_texels = check_int(n_texels, "n_texels", lo=1)  # (-5 was accepted, 2.7 truncated to 2)
    if tx is not None:
        if n_texels is None:
            inside = [t[np.asarray(gb.mask).reshape(-1).astype(bool)] for t, gb in zip(tx, gbuffers)]
            n_texels = int(max((int(t.max()) for t in inside if t.size), default=-1)) + 1
        for k, t in enumerate(tx):
            if not np.issubdtype(t.dtype, np.integer):
                raise ValueError(f"`texel[{k}]` must be an integer array, got {t.dtype}")
    dt = np.asarray(gbuffers[0].normal).dtype
    cols = {k: [] for k in ("n", "v", "b", "w", "t", "fv", "rv", "tx", "vi", "pi")}
    for k, gb in enumerate(gbuffers):
        sel = np.asarray(gb.mask).reshape(-1).astype(bool)
        if m_user is not None:  # bool / integer masks: nonzero; float masks: above 0.5 (as `jaxsh.io.read_mask`)
            mk = m_user[k]
            sel &= (mk > 0.5) if np.issubdtype(mk.dtype, np.floating) else mk.astype(bool)
        w = np.ones(sel.shape, dt) if w_user is None else w_user[k].astype(dt)
        if w_user is not None and not np.all(np.isfinite(w[sel]) & (w[sel] >= 0)):
            raise ValueError(f"`weights[{k}]` must be finite and >= 0 inside the mask (0 drops a pixel)")
        sel &= w > 0
        with np.errstate(over="ignore"):  # cast first: a float64 value beyond float32's range becomes inf, caught below
            vals = imgs[k].astype(dt)
        finite = np.all(np.isfinite(vals), axis=1)
        bad = sel & ~finite
        if bad.any():
            if invalid == "raise":
                raise ValueError(
                    f"`images[{k}]` has {int(bad.sum())} non-finite (NaN/inf) pixels inside the mask; "
                    "fix the image, mask them out, or pass invalid='drop'"
                )
            sel &= finite
        if saturation is not None:
            sel &= ~np.any(vals >= saturation, axis=1)
        if tx is not None:
            t = tx[k]
            if np.any((t[sel] < 0) | (t[sel] >= n_texels)):
                raise ValueError(f"`texel[{k}]` has indices outside [0, {n_texels}) inside the mask")
        idx = np.nonzero(sel)[0]
        cols["n"].append(np.asarray(gb.normal).reshape(-1, 3)[idx])
        cols["v"].append(np.asarray(gb.view).reshape(-1, 3)[idx])
        cols["b"].append(vals[idx])
        for key, src in (("transfer", tr), ("fast_visibility", fv), ("reflected_visibility", rv)):
            if src is not None and not np.all(np.isfinite(src[k][idx])):
                raise ValueError(f"`{key}[{k}]` has non-finite values inside the mask")
        cols["w"].append(w[idx])
        cols["vi"].append(np.full(idx.shape, k, np.int32))
        cols["pi"].append(idx.astype(np.int32))
        for key, src in (("t", tr), ("fv", fv), ("rv", rv), ("tx", tx)):
            if src is not None:
                cols[key].append(src[k][idx])
    total = sum(len(x) for x in cols["vi"])
    if total == 0:
        raise ValueError(
            "no valid pixel: every pixel is outside the G-buffer masks, masked out, saturated or non-finite"
        )

    def cat(key, dtype=None):
        if not cols[key]:
            return None
        a = np.concatenate(cols[key])
        # `device_put`, not `jnp.asarray`: the latter compiles a program per new NumPy shape (jax 0.10). `a` is a new
        # array no one else holds (`device_put` may alias it on the CPU)
        return jax.device_put(a if dtype is None else a.astype(dtype))

    return Observations(
        cat("n", dt), cat("v", dt), cat("b", dt), cat("w", dt), cat("t", dt), cat("fv", dt), cat("rv", dt),
        cat("tx", np.int32), cat("vi"), cat("pi"), tuple(hw), int(n_texels or 0),
    )


def view_lightings(obs: Observations, lighting, name: str = "lighting", allow_disks: bool = False) -> list[Lighting] | None:
    """`None` for one `Lighting`; for a sequence, the list of one `Lighting` per view of `obs`, checked.

    The sequence must have `len(obs.image_shapes)` entries (one per view,
    indexed by `obs.view_index`), each a `Lighting` without disk sources
    (unless `allow_disks`: a caller that uses each lighting as `total_sh`),
    with `C` or 1 channels. Raises `ValueError` naming `name`.
    """
    if isinstance(lighting, Lighting):
        return None
    if isinstance(lighting, (str, bytes)) or not isinstance(lighting, Sequence):
        raise ValueError(
            f"`{name}` must be a solvers.Lighting or a sequence of one Lighting per view, got {type(lighting).__name__}"
        )
    lights = list(lighting)
    n_views = len(obs.image_shapes)
    if len(lights) != n_views:
        raise ValueError(f"`{name}` must have one Lighting per view ({n_views}, matching `obs.view_index`), got {len(lights)}")
    for k, lit in enumerate(lights):
        if not isinstance(lit, Lighting):
            raise ValueError(f"`{name}[{k}]` must be a solvers.Lighting, got {type(lit).__name__}")
        if lit.has_disks and not allow_disks:
            raise ValueError(f"`{name}[{k}]` has disk sources: split them first (`Lighting.split_disks(sigma, lmax)`)")
    c = max(lit.n_channels for lit in lights)
    for k, lit in enumerate(lights):
        if lit.n_channels not in (1, c):
            raise ValueError(f"`{name}[{k}]` has {lit.n_channels} channels, other views {c}: all views must share C (or 1)")
    return lights


def practical_terms_for(obs: Observations, lighting, chunk: int = 256) -> jaxsh.PracticalTerms:
    """`jaxsh.practical_terms` of the observed pixels under `lighting`, with the visibility terms of `obs`.

    `lighting` is one `Lighting` for every view, or a sequence of one
    `Lighting` per view (`obs.view_index`; photometric stereo, light stages).
    Per view, the terms are computed with that view's lighting and the rows
    concatenated (where no view's lighting has a slow part, every pixel's from its own view's sources at once:
    `_fast_terms_by_view`), so memory stays $O(N)$ (not $O(N \\times$ views$)$): the slow
    bands are zero-padded to the largest $l_{max}$, and the fast sources (a
    view has $J_k \\le J$ of them) are stored per pixel: `theta_h` and
    `fast_weight` get $J\\,C$ columns (source $j$, channel $c$), `fast_weight`
    holding $V_j L_{j,c}$, and `fast_energy` is the $(J C, C)$ channel
    selector, so that `specular_unit`, `diffuse_unit` and `components` are
    R&H eq. 24 under each pixel's own lighting. `obs.fast_visibility` columns
    are the view's sources in order (extra columns are ignored).

    The visibility terms of a lighting part that `lighting` lacks are not used.

    Where it runs: pixels sharded over devices (`shard_observations`), each device makes its own pixels' terms
    (`solvers._pixel_sums`; lightings per view with a slow part are made view by view and replicated); many
    pixels on one CPU device (at least 16,384 a core), with slow lighting, the pixels are cut into one part per
    core, each made in its own host thread, and joined: XLA:CPU runs the band sums' loop on one core
    (`solvers._pixel_threads`; the same values, bitwise). Inside a caller's `jit`, one call.
    """
    lights = view_lightings(obs, lighting)
    for k, lit in enumerate([lighting] if lights is None else lights):
        # grey (1-channel) lighting lights every channel; other counts must be the data's (2 on RGB data gave
        # (N, 2) terms without a word)
        if isinstance(lit, Lighting) and lit.n_channels not in (1, obs.n_channels):
            where = "`lighting`" if lights is None else f"`lighting[{k}]`"
            raise ValueError(f"{where} has {lit.n_channels} channels; `obs` has {obs.n_channels} (give 1 or "
                             f"{obs.n_channels})")
    if lights is None:
        return _terms_one(obs, lighting, chunk)
    vi = np.asarray(obs.view_index)
    dt = obs.normals.dtype
    c = max(lit.n_channels for lit in lights)
    lmax = max((lit.lmax for lit in lights if lit.slow_sh is not None), default=0)
    jmax = max((0 if lit.fast_directions is None else lit.fast_directions.shape[0]) for lit in lights)
    if obs.fast_visibility is not None and jmax > obs.fast_visibility.shape[1]:
        raise ValueError(
            f"`obs.fast_visibility` has {obs.fast_visibility.shape[1]} columns, `lighting` has up to {jmax} fast sources per view"
        )
    if all(lit.slow_sh is None for lit in lights):
        # one light (or a few) per image and no slow part: every pixel's terms from its own view's sources, in one
        # program, on the devices that hold the pixels (view by view, `obs.subset` gathers sharded pixels)
        return _fast_terms_by_view(obs, lights, c, jmax)
    fold = jmax > 0 and c > 1
    jc = jmax * c if fold else jmax
    parts, order = [], []
    for k, lit in enumerate(lights):
        idx = np.nonzero(vi == k)[0]
        if idx.size == 0:
            continue
        sub = obs.subset(idx)
        j = 0 if lit.fast_directions is None else lit.fast_directions.shape[0]
        if sub.fast_visibility is not None and j > 0 and sub.fast_visibility.shape[1] != j:
            sub = eqx.tree_at(lambda o: o.fast_visibility, sub, sub.fast_visibility[:, :j])
        t = _terms_one(sub, lit, chunk)
        n = idx.size
        irr = jnp.broadcast_to(t.irradiance, (n, c))
        bands = jnp.broadcast_to(t.bands, (n, c, t.bands.shape[2]))
        bands = jnp.pad(bands, ((0, 0), (0, 0), (0, lmax + 1 - bands.shape[2])))
        th, fw = _source_columns(t.theta_h, t.fast_weight, jnp.broadcast_to(t.fast_energy, (j, c))[None], fold)
        pad = ((0, 0), (0, jc - th.shape[1]))
        parts.append((t.visible, t.cos_o, irr, bands, jnp.pad(th, pad), jnp.pad(fw, pad)))
        order.append(idx)
    perm = np.concatenate(order)
    cols = [jnp.concatenate([p[i] for p in parts]) for i in range(6)]
    if not np.array_equal(perm, np.arange(perm.size)):
        inv = jnp.asarray(np.argsort(perm))
        cols = [x[inv] for x in cols]
    energy = jnp.tile(jnp.eye(c, dtype=dt), (jmax, 1)) if fold else jnp.ones((jmax, 1), dt)
    return jaxsh.PracticalTerms(*cols, energy)


def _source_columns(theta_h, weight, energy, fold: bool):
    """The fast sources' columns of `practical_terms_for`'s terms from `theta_h`, `weight` `(N, J)` and the sources'
    energies `energy` `(N or 1, J, C)`: with `fold` (C > 1), column `j C + c'` holds $\theta_{h,j}$ and
    $V_j L_{j,c'}$ (`(N, J C)` each); without, `theta_h` and $V_j L_j$."""
    if fold:
        return jnp.repeat(theta_h, energy.shape[-1], axis=1), (weight[:, :, None] * energy).reshape(weight.shape[0], -1)
    return theta_h, weight * energy[..., 0]


def _fast_tables(lights: list[Lighting], c: int, jmax: int, dt):
    """The per-view fast sources as tables indexed by view: directions `(V, J, 3)`, energies `(V, J, C)` (a grey
    lighting broadcast to the C channels), and whether each entry is a source `(V, J)` (from the shapes). A view
    with fewer than `jmax` sources is padded with +z of zero energy. Made in NumPy and placed once when the
    lightings are concrete (eager `jnp` operations compile a small program per shape), else traced."""
    xp = jnp if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(lights)) else np
    real = np.zeros((len(lights), jmax), bool)
    dirs = xp.zeros((len(lights), jmax, 3), dt)
    if xp is np:
        dirs[..., 2] = 1.0
    else:
        dirs = dirs.at[..., 2].set(1.0)
    energy = xp.zeros((len(lights), jmax, c), dt)
    for k, lit in enumerate(lights):
        j = 0 if lit.fast_directions is None else lit.fast_directions.shape[0]
        real[k, :j] = True
        if j == 0:
            continue
        d, e = xp.asarray(lit.fast_directions, dt), xp.broadcast_to(xp.asarray(lit.fast_energy, dt), (j, c))
        if xp is np:
            dirs[k, :j], energy[k, :j] = d, e
        else:
            dirs, energy = dirs.at[k, :j].set(d), energy.at[k, :j].set(e)
    if xp is np:
        dirs, energy = jax.device_put(dirs), jax.device_put(energy)
    return dirs, energy, jax.device_put(real)


def _fast_terms_by_view(obs: Observations, lights: list[Lighting], c: int, jmax: int) -> jaxsh.PracticalTerms:
    """`practical_terms_for` with one `Lighting` per view, none with a slow part (photometric stereo, light stages:
    one light per image): each pixel's terms under its own view's fast sources (`_fast_tables`, gathered by
    `obs.view_index`), `jaxsh.practical_terms` `vmap`ped over the pixels, in one compiled program whatever the
    number of views or their sizes (view by view: a program per distinct view size, and `obs.subset` gathers
    sharded pixels). Measured on one device (`bench_capture.py`'s capture, RGB energies, warm): 24 views of
    153 × 128, 38 against 96 ms; 96 views of 306 × 256 (4.5 M pixels), 0.47 against 1.25 s and 221 against
    493 MiB of peak memory. The values equal the view-by-view path's to the last bit or so (`theta_h` and the
    irradiance are rounded differently; docs/performance.md, "Thirty-fifth round"). The columns are the
    view-by-view path's: with C > 1, `theta_h` and `fast_weight` hold column `j C + c'` for source j and
    channel c' ($V_j L_{j,c'}$ in `fast_weight`) and `fast_energy` is the `(J C, C)` channel selector; a padding
    source's columns are 0. Pixels sharded over devices (`shard_observations`) stay where they are."""
    dt = obs.normals.dtype
    dirs, energy, real = _fast_tables(lights, c, jmax, dt)
    fvis = None if obs.fast_visibility is None else obs.fast_visibility[:, :jmax]
    pixels = (obs.normals, obs.views, obs.view_index, fvis)
    cols = _fast_terms_jit(pixels, (dirs, energy, real), pixel_sharding(obs.normals))
    sel = np.tile(np.eye(c, dtype=dt), (jmax, 1)) if c > 1 else np.ones((jmax, 1), dt)  # placed without a program
    return jaxsh.PracticalTerms(*cols, jax.device_put(sel))


@jaxsh.jit
def _fast_terms_jit(pixels, tables, where):
    """The per-pixel fields of `_fast_terms_by_view` (`where`: `pixel_sharding`, or None for one device)."""
    dirs, energy, real = tables
    c = energy.shape[2]

    def local(n, v, vi, fvis):
        def one(n1, v1, d, e, fv):
            return jaxsh.practical_terms(n1[None], v1[None], fast_directions=d, fast_energy=e,
                                         fast_visibility=None if fv is None else fv[None])

        e = energy[vi]  # (N, J, C)
        t = jax.vmap(one)(n, v, dirs[vi], e, fvis)
        th = jnp.where(real[vi], t.theta_h[:, 0], 0.0)  # (N, J): a padding source's half angle 0, as the general path's
        th, w = _source_columns(th, t.fast_weight[:, 0], e, c > 1)
        return t.visible[:, 0], t.cos_o[:, 0], t.irradiance[:, 0], t.bands[:, 0], th, w

    return map_over_pixels(local, where, pixels)


def _terms_one(obs: Observations, lighting: Lighting, chunk: int) -> jaxsh.PracticalTerms:
    if not isinstance(lighting, Lighting):
        raise ValueError(f"`lighting` must be a solvers.Lighting, got {type(lighting).__name__}")
    pixels = (obs.normals, obs.views, None if lighting.slow_sh is None else obs.transfer,
              None if lighting.fast_directions is None else obs.fast_visibility,
              None if lighting.slow_sh is None else obs.reflected_visibility)
    terms = functools.partial(_practical_terms_of, lighting, chunk)
    where = pixel_sharding(obs.normals)
    if where is None and lighting.slow_sh is not None:
        # one CPU device: the band sums (one core's loop) on every core, the pixels in parts (`_pixel_threads`)
        key = ("practical_terms", chunk, jax.tree.structure(lighting),
               tuple((np.shape(x), str(getattr(x, "dtype", type(x).__name__))) for x in jax.tree.leaves(lighting)))
        return map_in_threads(terms, pixels, key, replicated=("fast_energy",), align=chunk)
    if where is None:
        return terms(*pixels)
    # sharded pixels (`shard_observations`): each device its own pixels' terms (`_pixel_sums`), in one program
    return _terms_on_devices(pixels, lighting, chunk, where)


@jaxsh.jit
def _terms_on_devices(pixels, lighting: Lighting, chunk: int, where):
    """`jaxsh.practical_terms` of sharded `pixels`, each device its own (`map_over_pixels`), as one compiled program.
    Called eagerly, `jax.shard_map` of the closure was compiled again at every call (a new function each time): a
    warm `fit_brdf` of 3,008 pixels on 2 forced host devices took 1.05-1.13 s against 0.04 s on one device, 0.8 s
    of it that compilation (`benchmarks/bench_scale.py`, `tests/test_scale.py`)."""
    return map_over_pixels(functools.partial(_practical_terms_of, lighting, chunk), where, pixels,
                           replicated=("fast_energy",))


def _practical_terms_of(lighting: Lighting, chunk: int, n, v, transfer, fast_visibility, reflected_visibility):
    """`jaxsh.practical_terms` of the pixels `n, v` and their visibility terms under `lighting` (`_terms_one`)."""
    return jaxsh.practical_terms(n, v, lighting, chunk=chunk, transfer=transfer, fast_visibility=fast_visibility,
                                 reflected_visibility=reflected_visibility)


def _per_view_arg(x, k: int, n_views: int, name: str):
    """Entry `k` of a per-view keyword: a list/tuple of `n_views` arrays, or one array for every view."""
    if isinstance(x, (list, tuple)):
        if len(x) != n_views:
            raise ValueError(f"`{name}` must be one array for every view or a list of {n_views} (one per lighting), got {len(x)}")
        return x[k]
    return x


def _texel_brdf(brdf: TorranceSparrow, texel, batch: tuple, mask) -> TorranceSparrow:
    """A per-texel `(T, C)` BRDF gathered into maps `(*batch, C)` by the int map `texel` `batch`."""
    kd, ks = jnp.asarray(brdf.kd), jnp.asarray(brdf.ks)
    if texel is None:
        for name, x in (("kd", kd), ("ks", ks)):
            if x.ndim >= 2:
                # a map has the pixels' rank (a (T, C) per-texel result with T equal to the image width broadcast
                # as a map of columns)
                try:
                    ok = x.ndim == len(batch) + 1 and (
                        jnp.broadcast_shapes(x.shape, tuple(batch) + (x.shape[-1],)) == tuple(batch) + (x.shape[-1],))
                except ValueError:
                    ok = False
                if not ok:
                    raise ValueError(
                        f"`brdf.{name}` has shape {tuple(x.shape)}, which is not a map over the pixels {tuple(batch)}: "
                        f"for a per-texel result (T, C) pass `texel=` the {tuple(batch)} int texel map"
                    )
        return brdf
    t = np.asarray(texel)
    if not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"`texel` must be an integer array of shape {tuple(batch)}, got dtype {t.dtype}")
    if t.shape != tuple(batch):
        raise ValueError(f"`texel` must have shape {tuple(batch)} (the pixels), got {t.shape}")
    n_t = max(x.shape[0] if x.ndim == 2 else 1 for x in (kd, ks))
    if kd.ndim != 2 and ks.ndim != 2:
        raise ValueError(f"`texel` needs a per-texel BRDF (`brdf.kd` of shape (T, C)), got kd {tuple(kd.shape)}")
    inside = np.ones(t.shape, bool) if mask is None else np.broadcast_to(np.asarray(mask, bool), t.shape)
    if np.any((t[inside] < 0) | (t[inside] >= n_t)):
        raise ValueError(f"`texel` has indices outside [0, {n_t}) inside the mask")
    ti = jnp.asarray(np.clip(t, 0, n_t - 1))

    def gather(x):
        return x[ti] if x.ndim == 2 else x

    return TorranceSparrow(gather(kd), gather(ks), brdf.mu, brdf.sigma)


def predict(
    brdf: TorranceSparrow,
    lighting,
    normals,
    views,
    *,
    texel=None,
    **visibility,
):
    """Radiance of `brdf` under `lighting` at new normals / views: `jaxsh.render_practical(normals, views, brdf, lighting).total`.

    For novel lighting and views from any solver result
    (`predict(result.brdf, new_lighting, gb.normal, gb.view, mask=gb.mask)`).
    Extra keyword arguments (`transfer`, `fast_visibility`,
    `reflected_visibility`, `mask`) go to `render_practical`.

    - `lighting`: one `Lighting`, or a sequence of `K` (one per image, e.g.
      one light each). Then `normals`, `views`, `texel` and every keyword are
      one array for all images or a list of `K`; the result is a list of `K`
      images if `normals` is a list, else an array `(K, *batch, C)`.
    - `texel`: the `(*batch)` int texel map of a per-texel result
      (`fit_brdf(..., textured="kd")`, `brdf.kd` of shape `(T, C)`): each
      pixel takes its texel's $K_d$ (and $K_s$). Without it a `(T, C)` BRDF
      that is not a pixel map is a `ValueError` naming `texel`.
    """
    if isinstance(lighting, Lighting):
        n = jnp.asarray(normals)
        b = _texel_brdf(brdf, texel, tuple(n.shape[:-1]), visibility.get("mask"))
        return jaxsh.render_practical(n, views, b, lighting, **visibility).total
    if isinstance(lighting, (str, bytes)) or not isinstance(lighting, Sequence) or len(lighting) == 0:
        raise ValueError(f"`lighting` must be a solvers.Lighting or a non-empty sequence of them, got {type(lighting).__name__}")
    lights = list(lighting)
    kk = len(lights)
    out = []
    for k, lit in enumerate(lights):
        if not isinstance(lit, Lighting):
            raise ValueError(f"`lighting[{k}]` must be a solvers.Lighting, got {type(lit).__name__}")
        vis = {key: _per_view_arg(x, k, kk, key) for key, x in visibility.items()}
        n = jnp.asarray(_per_view_arg(normals, k, kk, "normals"))
        v = _per_view_arg(views, k, kk, "views")
        b = _texel_brdf(brdf, _per_view_arg(texel, k, kk, "texel"), tuple(n.shape[:-1]), vis.get("mask"))
        out.append(jaxsh.render_practical(n, v, b, lit, **vis).total)
    if isinstance(normals, (list, tuple)):
        return out
    return jnp.stack(out)
