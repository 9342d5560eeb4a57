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

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

import jaxsh
from jaxsh import Lighting as Lighting, TorranceSparrow as TorranceSparrow  # the domain types live in jaxsh

from ._results import Status as Status, status_name as status_name  # re-exported for older imports


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
        """The samples at integer `index` (outside jit)."""
        index = np.asarray(index)

        def take(a):
            return None if a is None else a[index]

        return Observations(
            take(self.normals), take(self.views), take(self.values), take(self.weights), take(self.transfer),
            take(self.fast_visibility), take(self.reflected_visibility), take(self.texel), take(self.view_index),
            take(self.pixel_index), self.image_shapes, self.n_texels,
        )

    def to_images(self, values: Float[Array, "N C"], fill: float = 0.0) -> list[np.ndarray]:
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
    images: Sequence[Float[Array, "H W C"]],
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
      `(H, W, C)` (or `(H, W)`) linear radiance images.
    - `masks`, `weights`: optional per-view `(H, W)` bool / float arrays.
    - `transfer` `(H, W, 9)`, `fast_visibility` `(H, W, J)`,
      `reflected_visibility` `(H, W)`: optional per-view visibility terms
      (`jaxsh.visibility_sh`, `jaxsh.directional_visibility`,
      `jaxsh.reflected_visibility`).
    - `texel`: optional per-view `(H, W)` int texel indices in
      `[0, n_texels)` for textured $K_d(x)$ (R&H sec. 6.4).

    **Returns:** `Observations` (float dtype of the G-buffers). Raises
    `ValueError` if no valid pixel remains, or on mismatched shapes.
    """
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
        j = np.asarray(fast_visibility[0]).shape[-1]
        fv = _per_view(fast_visibility, len(gbuffers), "fast_visibility", (j,), hw)
    if tx is not None:
        if n_texels is None:
            n_texels = int(max(int(t.max()) for t in tx)) + 1
        for k, t in enumerate(tx):
            if not np.issubdtype(t.dtype, np.integer):
                raise ValueError(f"`texel[{k}]` must be an integer array, got {t.dtype}")
    dt = np.asarray(gbuffers[0].normal).dtype
    cols = {k: [] for k in ("n", "v", "b", "w", "t", "fv", "rv", "tx", "vi", "pi")}
    for k, gb in enumerate(gbuffers):
        sel = np.asarray(gb.mask).reshape(-1).astype(bool)
        if m_user is not None:
            sel &= m_user[k].astype(bool)
        w = np.ones(sel.shape, dt) if w_user is None else w_user[k].astype(dt)
        if w_user is not None and not np.all(np.isfinite(w[sel]) & (w[sel] >= 0)):
            raise ValueError(f"`weights[{k}]` must be finite and >= 0 inside the mask (0 drops a pixel)")
        sel &= w > 0
        vals = imgs[k]
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
        cols["b"].append(vals[idx].astype(dt))
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
        return jnp.asarray(a if dtype is None else a.astype(dtype))

    return Observations(
        cat("n", dt), cat("v", dt), cat("b", dt), cat("w", dt), cat("t", dt), cat("fv", dt), cat("rv", dt),
        cat("tx", np.int32), cat("vi"), cat("pi"), tuple(hw), int(n_texels or 0),
    )


def practical_terms_for(obs: Observations, lighting: Lighting, chunk: int = 8192) -> jaxsh.PracticalTerms:
    """`jaxsh.practical_terms` of the observed pixels under `lighting`, with the visibility terms of `obs`.

    The visibility terms of a lighting part that `lighting` lacks are not used.
    """
    return jaxsh.practical_terms(
        obs.normals, obs.views, lighting, chunk=chunk,
        transfer=None if lighting.slow_sh is None else obs.transfer,
        fast_visibility=None if lighting.fast_directions is None else obs.fast_visibility,
        reflected_visibility=None if lighting.slow_sh is None else obs.reflected_visibility,
    )


def predict(
    brdf: TorranceSparrow,
    lighting: Lighting,
    normals: Float[Array, "*batch 3"],
    views: Float[Array, "*batch 3"],
    **visibility,
) -> Float[Array, "*batch C"]:
    """Radiance of `brdf` under `lighting` at new normals / views: `jaxsh.render_practical(normals, views, brdf, lighting).total`.

    For novel lighting and views from any solver result
    (`predict(result.brdf, new_lighting, gb.normal, gb.view, mask=gb.mask)`).
    Extra keyword arguments (`transfer`, `fast_visibility`,
    `reflected_visibility`, `mask`) go to `render_practical`.
    """
    return jaxsh.render_practical(normals, views, brdf, lighting, **visibility).total
