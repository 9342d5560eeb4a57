"""G-buffers: per-pixel geometry of a view, and shading with precomputed transfer (jitted JAX).

**G-buffers** hold, per pixel, whether the ray hit the object (`mask`), the
hit point, the unit surface normal, the unit view direction $\\omega_o$
(from the surface *towards* the camera, i.e. minus the ray direction) and the
depth: the camera-frame $z$ of the hit point (the OpenCV depth-map
convention; the ray length times the cosine between ray and optical axis for
a pinhole camera, the ray length itself for an orthographic one). Pixels
that miss have `mask = False`, zero position, normal and depth, and still a
valid view direction. Camera conventions: `jaxsh._camera`.

`sphere_gbuffer` is analytic JAX (jitted, differentiable in the camera and
the sphere). The G-buffer of a triangle mesh, `mesh_gbuffer`, is ray cast in
NumPy / trimesh (`jaxsh._raycast`). `normal_map_gbuffer` builds one from a
measured normal map (photometric stereo, structured light, light stages):
normals and view directions only, no positions (`GBuffer.has_position` is
False), hence no shadows.

`visibility_weighted_irradiance` is the jitted consumer of the transfer
vectors that `visibility_sh` (`jaxsh._raycast`) precomputes:
$E(x) = \\sum_{lm} L_{lm}T_{lm}(x)$, linear in the lighting coefficients as
R&H 2001 sec. 6.4 requires for inverse lighting with shadows (eq. 25); for
an unoccluded point it reduces to eq. 21.

??? cite "References"
    Ramamoorthi, R., Hanrahan, P. (2001). A signal-processing framework for
    inverse rendering. SIGGRAPH 2001, 117–128. doi:10.1145/383259.383271
    (sec. 6.4: textures and shadowing).

    Sloan, P.-P., Kautz, J., Snyder, J. (2002). Precomputed radiance transfer
    for real-time rendering in dynamic, low-frequency lighting environments.
    SIGGRAPH 2002, 527–536. doi:10.1145/566570.566612 (the transfer vector).

    Haines, E., Günther, J., Akenine-Möller, T. (2019). Precision
    improvements for ray/sphere intersection. Ray Tracing Gems, ch. 7,
    87–94. doi:10.1007/978-1-4842-4427-2_7
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Real
from ._compile import jit
from ._custom_types import SequenceLike

from ._camera import Camera, _camera_rays, _check_camera, _require_finite, _require_positive, _scalar, _widest
from ._checks import error_if_any, as_float_array, coeff_layout, is_traced


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


# --------------------------------------------------------------------------- G-buffers


class GBuffer(eqx.Module):
    """Per-pixel geometry of a view (see the module docstring for conventions).

    **Fields:**

    - `mask`: `(H, W)` bool, the ray hit the object.
    - `position`: `(H, W, 3)` world-space hit point (0 where `mask` is False).
    - `normal`: `(H, W, 3)` unit surface normal (0 where `mask` is False).
    - `view`: `(H, W, 3)` unit direction from the surface towards the camera
      ($\\omega_o$; minus the ray direction, defined for every pixel).
    - `depth`: `(H, W)` camera-frame $z$ of the hit point (0 where `mask` is
      False).
    - `has_position`: static bool, True when `position` and `depth` hold the
      surface (`sphere_gbuffer`, `mesh_gbuffer`). False for a G-buffer built
      from a normal map (`normal_map_gbuffer`): the surface points are not
      known, `position` and `depth` are then all zeros and must not be used
      (no shadows or visibility can be computed from it).

    `gb.position[gb.mask]` etc. give the `(N, 3)` samples of the object
    (outside `jit`).
    """

    mask: Bool[Array, "H W"]
    position: Float[Array, "H W 3"]
    normal: Float[Array, "H W 3"]
    view: Float[Array, "H W 3"]
    depth: Float[Array, "H W"]
    has_position: bool = eqx.field(static=True, default=True)


def sphere_gbuffer(
    camera: Camera, center: Real[ArrayLike, "3"] | SequenceLike, radius: Real[ArrayLike, ""]
) -> GBuffer:
    """Analytic G-buffer of a sphere: ray–sphere intersection for every pixel.

    For a ray $o + t d$ ($|d| = 1$) and $f = o - c$: $b = f\\cdot d$, and the
    discriminant is computed as $r^2 - |f - b\\,d|^2$ (the squared distance
    from the centre to the ray, Haines et al. 2019 eq. 7.5; free of the
    cancellation in $b^2 - (|f|^2 - r^2)$ for distant cameras). The roots are
    $q = -b - \\mathrm{sign}(b)\\sqrt{\\Delta}$ and $(|f|^2 - r^2)/q$ (the
    stable quadratic formula); the pixel keeps the nearest positive one. A
    camera inside the sphere sees its inside (normals still point outwards).

    Normal $(p - c)/r$, view $-d$, depth $(p - t_{cam})\\cdot z_{cam}$.
    Jitted; differentiable with respect to `center`, `radius` and the
    camera's array fields (the mask is piecewise constant; the square root is
    guarded so that gradients stay finite at the silhouette).

    **Arguments:**

    - `camera`: `PinholeCamera` or `OrthographicCamera`.
    - `center`: `(3,)`, finite; `radius`: scalar, finite and > 0 (traced).
      Invalid values are a `ValueError` naming the argument (traced values:
      a run-time error).

    **Returns:** a `GBuffer` of `(height, width)` images.
    """
    camera = _check_camera(camera)
    center = as_float_array(center, "center")
    if center.shape != (3,):
        raise ValueError(f"`center` must have shape (3,), got {tuple(center.shape)}")
    _require_finite(center, "center")
    radius = _scalar(radius, "radius")
    _require_positive(radius, "radius")
    dt = _widest([camera.cam_to_world, center, radius])
    if dt != camera.cam_to_world.dtype:
        camera = jax.tree_util.tree_map(lambda a: a.astype(dt), camera)
    return _sphere_gbuffer(camera, center.astype(dt), radius.astype(dt))


@jit
def _sphere_gbuffer(camera, center, radius):
    radius = error_if_any(radius, ~((radius > 0.0) & jnp.isfinite(radius)), "sphere_gbuffer: `radius` must be finite and positive")
    center = error_if_any(center, ~jnp.all(jnp.isfinite(center)), "sphere_gbuffer: `center` must be finite")
    o, d = _camera_rays(camera)
    f = o - center[None, None, :]
    b = _dot(f, d)
    h = f - b[..., None] * d
    r2 = radius * radius
    disc = r2 - _dot(h, h)
    c = _dot(f, f) - r2
    hit = disc >= 0.0
    sq = jnp.sqrt(jnp.where(hit, disc, 0.0))
    sign = jnp.where(b >= 0.0, 1.0, -1.0).astype(b.dtype)
    q = -b - sign * sq
    q_ok = q != 0.0
    q_safe = jnp.where(q_ok, q, 1.0)
    t1 = q
    t2 = jnp.where(q_ok, c / q_safe, 0.0)
    t_near = jnp.minimum(t1, t2)
    t_far = jnp.maximum(t1, t2)
    t = jnp.where(t_near > 0.0, t_near, t_far)
    mask = hit & (t > 0.0)
    t = jnp.where(mask, t, 0.0)
    p = o + t[..., None] * d
    m3 = mask[..., None]
    position = jnp.where(m3, p, 0.0)
    normal = jnp.where(m3, (p - center[None, None, :]) / radius, 0.0)
    eye = camera.cam_to_world[:3, 3]
    zaxis = camera.cam_to_world[:3, 2]
    zaxis = zaxis / jnp.linalg.norm(zaxis)
    depth = jnp.where(mask, _dot(p - eye[None, None, :], zaxis[None, None, :]), 0.0)
    return GBuffer(mask=mask, position=position, normal=normal, view=-d, depth=depth)


# Normals whose length is within this of 1 are accepted (and renormalized) by `normal_map_gbuffer`.
_NORMAL_TOL = 1e-3


def normal_map_gbuffer(camera: Camera, normals: Real[ArrayLike, "H W 3"], mask: Bool[ArrayLike, "H W"] | None = None) -> GBuffer:
    """G-buffer of a measured normal map: normals and view directions, no positions.

    For captures whose geometry is a normal map in the camera's pixel grid
    (photometric stereo, structured light, light stages) rather than a mesh.
    A pixel is on the object where its normal is non-zero (and `mask`, if
    given, is True); elsewhere the normal is the zero vector, as in the other
    G-buffers. The view direction of every pixel is computed from the camera
    (`camera_rays`): $\\omega_o = -d$, from the surface towards the camera —
    per pixel for a pinhole camera, constant (minus the optical axis) for an
    orthographic one. Within the tolerance below this is the view direction
    of the true surface point, since for a pinhole camera it depends only on
    the pixel, not on the unknown depth.

    **No positions and no shadows.** The surface points are not known, so
    the result has `has_position=False` and `position`, `depth` all zeros
    (never fake points): visibility, cast shadows and the transfer vectors of
    `directional_visibility` / `visibility_sh` / `reflected_visibility` need
    a mesh (`mesh_gbuffer`). Rendering and fitting from this G-buffer assume
    every pixel sees the whole upper hemisphere of its normal (R&H eq. 21
    without the visibility of sec. 6.4).

    **Arguments:**

    - `camera`: `PinholeCamera` or `OrthographicCamera`.
    - `normals`: `(camera.height, camera.width, 3)` world-frame normals, in
      the camera's pixel grid (row $i$, column $j$ as in `camera_rays`).
      Each must be finite and either of norm 1 within 1e-3 (it is
      renormalized) or exactly zero (off the object).
    - `mask`: optional `(height, width)` bool, an extra restriction of the
      object (pixels where it is False are off the object even with a
      non-zero normal; their normal is set to zero).

    Invalid input is a `ValueError` naming the argument (shape, NaN/inf,
    norms); traced normals are checked at run time (`equinox.error_if`).
    Jitted; differentiable in `normals` (on the mask) and the camera.

    **Returns:** a `GBuffer` with `has_position=False`, in the widest float
    dtype of the camera and `normals`.
    """
    camera = _check_camera(camera)
    h, w = camera.height, camera.width
    n = as_float_array(normals, "normals")
    if n.shape != (h, w, 3):
        raise ValueError(
            f"`normals` must have shape (height, width, 3) = ({h}, {w}, 3) to match the camera, got {tuple(n.shape)}"
        )
    if mask is not None:
        mask = jnp.asarray(mask)
        if mask.dtype != jnp.bool_:
            raise ValueError(f"`mask` must be a bool array, got dtype {mask.dtype}")
        if mask.shape != (h, w):
            raise ValueError(f"`mask` must have shape (height, width) = ({h}, {w}), got {tuple(mask.shape)}")
    if not is_traced(n):
        _require_finite(n, "normals")
        norm = np.linalg.norm(np.asarray(n, dtype=np.float64), axis=-1)
        bad = (norm != 0) & (np.abs(norm - 1) > _NORMAL_TOL)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise ValueError(
                f"`normals` must be unit vectors (norm 1 within {_NORMAL_TOL:g}) or exactly zero (off the object); "
                f"{int(bad.sum())} pixels are not, e.g. pixel ({i}, {j}) has norm {norm[i, j]:.6g}"
            )
    dt = _widest([camera.cam_to_world, n])
    if dt != camera.cam_to_world.dtype:
        camera = jax.tree_util.tree_map(lambda a: a.astype(dt), camera)
    return _normal_map_gbuffer(camera, n.astype(dt), mask)


@jit
def _normal_map_gbuffer(camera, n, mask):
    raw2 = jnp.sum(n * n, axis=-1)
    raw = jnp.sqrt(jnp.where(raw2 > 0, raw2, 1.0))
    bad = ~jnp.all(jnp.isfinite(n)) | jnp.any((raw2 > 0) & (jnp.abs(raw - 1) > _NORMAL_TOL))
    n = error_if_any(n, bad, "normal_map_gbuffer: `normals` must be finite, unit (within 1e-3) or exactly zero")
    norm2 = jnp.sum(n * n, axis=-1)  # from the checked array, so that the mask carries the check too
    norm = jnp.sqrt(jnp.where(norm2 > 0, norm2, 1.0))  # double-where: finite gradients at the zero vectors
    on = norm2 > 0
    if mask is not None:
        on = on & mask
    normal = jnp.where(on[..., None], n / norm[..., None], 0.0)
    _, d = _camera_rays(camera)
    zeros = jnp.zeros_like(norm)
    return GBuffer(mask=on, position=jnp.zeros_like(normal), normal=normal, view=-d, depth=zeros, has_position=False)


# --------------------------------------------------------------------------- shading with precomputed transfer (R&H 2001 sec. 6.4)


def visibility_weighted_irradiance(
    transfer: Real[ArrayLike, "*batch n_T"], lighting_coeffs: Real[ArrayLike, "n_L *C"]
) -> Float[Array, "*batch_channels"]:
    """Irradiance with visibility, $E(x) = \\sum_{lm} L_{lm} T_{lm}(x)$.

    A contraction of transfer vectors (`visibility_sh`) with real SH lighting
    coefficients, over the common band limit (the coefficient axis of the
    longer one is truncated: the product integral of a band-limited transfer
    and lighting involves only their common bands). Without occlusion and
    with lmax = 2 it equals `irradiance(lighting_coeffs, normals)` (R&H
    eq. 21). Jitted; differentiable (linear) in both arguments.

    **Arguments:**

    - `transfer`: `(..., n_coeffs_T)`.
    - `lighting_coeffs`: `(n_coeffs_L,)` or `(n_coeffs_L, C)` (channels last).

    **Returns:** `(...)` or `(..., C)` (the batch shape of `transfer`, then
    the channels of `lighting_coeffs`; annotated `*batch_channels` because an
    annotation holds one variadic axis group).
    """
    transfer = as_float_array(transfer, "transfer")
    light = as_float_array(lighting_coeffs, "lighting_coeffs")
    if transfer.ndim < 1:
        raise ValueError("`transfer` must have shape (..., n_coeffs), got ()")
    coeff_layout(transfer.shape[-1:], "transfer", channels=False)
    if light.ndim not in (1, 2):
        raise ValueError(
            f"`lighting_coeffs` must have shape (n_coeffs,) or (n_coeffs, C), got {tuple(light.shape)}"
        )
    coeff_layout(light.shape, "lighting_coeffs", channels=light.ndim == 2)
    dt = _widest([transfer, light])
    return _contract(transfer.astype(dt), light.astype(dt))


@jit
def _contract(transfer, light):
    n = min(transfer.shape[-1], light.shape[0])
    return jnp.tensordot(transfer[..., :n], light[:n], axes=([-1], [0]))
