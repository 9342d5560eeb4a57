"""Cameras: pinhole and orthographic models, `look_at`, and the rays of a view (jitted JAX).

**Conventions** (docs/conventions.md, "Cameras"; docs/manifest.md) follow OpenCV: +x right,
+y down, +z forward; `cam_to_world` is the 4×4 matrix mapping camera to
world coordinates, $x_w = R\\,x_c + t$. Pixel $(i, j)$ = (row, column) has
its centre at image coordinates $(u, v) = (j + \\tfrac12, i + \\tfrac12)$.

- Pinhole: the ray of pixel $(i, j)$ leaves the camera centre $t$ along
  $R\\,((u - c_x)/f_x, (v - c_y)/f_y, 1)$, normalized.
- Orthographic: the ray of pixel $(i, j)$ leaves the camera-frame point
  $((j + \\tfrac12 - W/2)\\,s, (i + \\tfrac12 - H/2)\\,s, 0)$ along the camera
  +z axis, with $s$ = `scale` (world units per pixel).

Everything here is jitted and differentiable in the cameras' array fields.
This module also holds the small argument helpers shared by the scene
modules (`_gbuffer.py`, jitted; `_raycast.py`, NumPy / trimesh).

??? cite "References"
    Hartley, R., Zisserman, A. (2004). *Multiple View Geometry in Computer
    Vision*, 2nd ed., sec. 6.1 (the pinhole camera).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real
from ._compile import jit
from ._custom_types import SequenceLike

from ._checks import error_if_any, as_float_array, as_jax, check_positive_int, is_traced

# --------------------------------------------------------------------------- helpers


def _widest(arrays):
    """The common float dtype of `arrays` (strict promotion refuses f32+f64: take the widest)."""
    try:
        return jnp.result_type(*arrays)
    except jax.dtypes.TypePromotionError:
        return max((a.dtype for a in arrays), key=lambda d: jnp.dtype(d).itemsize)


def _scalar(x, name: str):
    """A scalar float parameter; Python numbers stay weakly typed."""
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        return as_jax(float(x))
    a = as_float_array(x, name)
    if a.shape != ():
        raise ValueError(f"`{name}` must be a scalar (shape ()), got shape {tuple(a.shape)}")
    return a


def _require_positive(a, name: str) -> None:
    """Raise a ValueError if a concrete scalar is not > 0 (traced values are checked later)."""
    try:
        v = np.asarray(a)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"`{name}` must be a finite positive number, got {v}")


def _require_finite(a, name: str) -> None:
    """Raise a ValueError if a concrete array holds NaN or inf (traced values are checked later)."""
    if is_traced(a):
        return
    if not bool(np.all(np.isfinite(np.asarray(a)))):
        raise ValueError(f"`{name}` must be finite (no NaN or inf), got {np.asarray(a)}")


def _rotation_tol(dtype) -> float:
    """Tolerance of the orthonormality check: 1e-6 in float64, 1e-4 in float32."""
    return 1e-6 if jnp.dtype(dtype).itemsize >= 8 else 1e-4


def _pose_error(m):
    """(max |RᵀR − I|, det R, max |last row − [0,0,0,1]|) of a 4×4 pose (JAX, traceable; NumPy for a concrete pose)."""
    xp = jnp if is_traced(m) else np
    if xp is np:
        m = np.asarray(m)
    rot = m[:3, :3]
    orth = xp.max(xp.abs(rot.T @ rot - xp.eye(3, dtype=m.dtype)))
    row = xp.max(xp.abs(m[3] - xp.asarray([0.0, 0.0, 0.0, 1.0], m.dtype)))
    return orth, xp.linalg.det(rot), row


def _matrix4(m, name: str = "cam_to_world"):
    """A camera-to-world pose: (4, 4), finite, rotation block orthonormal with det +1, last row [0, 0, 0, 1].

    Checked here for concrete matrices (ValueError); a traced matrix is
    checked at run time by `camera_rays` (`_check_pose`).
    """
    m = as_float_array(m, name)
    if m.shape != (4, 4):
        raise ValueError(f"`{name}` must have shape (4, 4), got {tuple(m.shape)}")
    if is_traced(m):
        return m
    _require_finite(m, name)
    orth, det, row = (float(v) for v in _pose_error(m))
    tol = _rotation_tol(m.dtype)
    if row > tol:
        raise ValueError(f"`{name}` must have last row [0, 0, 0, 1], got {np.asarray(m[3]).tolist()}")
    if orth > tol or det < 0:
        raise ValueError(
            f"`{name}` must hold a rotation in its upper 3x3 block (orthonormal within {tol:g}, det +1); "
            f"max |R^T R - I| = {orth:.3g}, det = {det:.6g}"
        )
    return m


def _check_pose(m, who: str):
    """Run-time form of the `_matrix4` check (for cameras built from traced values)."""
    orth, det, row = _pose_error(m)
    tol = _rotation_tol(m.dtype)
    bad = ~jnp.all(jnp.isfinite(m)) | ~(orth <= tol) | ~(det > 0) | ~(row <= tol)
    return error_if_any(
        m, bad, f"{who}: `cam_to_world` must be finite with a rotation block (orthonormal, det +1) and last row [0, 0, 0, 1]"
    )


# --------------------------------------------------------------------------- cameras


class PinholeCamera(eqx.Module):
    """A pinhole camera in the OpenCV convention (see the module docstring).

    **Arguments / fields:**

    - `fx`, `fy`: focal lengths in pixels (traced scalars, > 0).
    - `cx`, `cy`: principal point in pixels (traced scalars); the image
      centre is `(width/2, height/2)`.
    - `width`, `height`: image size in pixels (static ints).
    - `cam_to_world`: `(4, 4)` camera-to-world matrix (traced); its upper
      3×3 block should be a rotation (see `look_at`).

    All arrays are converted to one float dtype (the widest given).
    Validation (`ValueError` naming the argument at construction; when the
    camera is built from traced values, an error at run time of
    `camera_rays`): `fx`, `fy` finite and > 0; `cx`, `cy` finite;
    `width`, `height` positive Python ints (16.7 is an error, not 16);
    `cam_to_world` finite, its 3×3 block a rotation (orthonormal within
    1e-6 in float64, 1e-4 in float32, det +1), its last row [0, 0, 0, 1].
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    cam_to_world: Float[Array, "4 4"]
    model: ClassVar[str] = "pinhole"

    def __init__(self, fx, fy, cx, cy, width, height, cam_to_world):
        self.width = check_positive_int(width, "width")
        self.height = check_positive_int(height, "height")
        m = _matrix4(cam_to_world)
        params = [_scalar(fx, "fx"), _scalar(fy, "fy"), _scalar(cx, "cx"), _scalar(cy, "cy")]
        _require_positive(params[0], "fx")
        _require_positive(params[1], "fy")
        _require_finite(params[2], "cx")
        _require_finite(params[3], "cy")
        dt = _widest([m] + params)
        self.fx, self.fy, self.cx, self.cy = (p.astype(dt) for p in params)
        self.cam_to_world = m.astype(dt)


class OrthographicCamera(eqx.Module):
    """An orthographic camera in the OpenCV convention (see the module docstring).

    **Arguments / fields:**

    - `scale`: world units per pixel (traced scalar, > 0).
    - `width`, `height`: image size in pixels (static ints).
    - `cam_to_world`: `(4, 4)` camera-to-world matrix (traced).

    Pixel $(i, j)$ looks along the camera +z axis from the camera-frame
    point $((j + \\tfrac12 - W/2)\\,s, (i + \\tfrac12 - H/2)\\,s, 0)$.

    Validated as `PinholeCamera`: `scale` finite and > 0, `width`/`height`
    positive ints, `cam_to_world` a finite rigid pose.
    """

    scale: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    cam_to_world: Float[Array, "4 4"]
    model: ClassVar[str] = "orthographic"

    def __init__(self, scale, width, height, cam_to_world):
        self.width = check_positive_int(width, "width")
        self.height = check_positive_int(height, "height")
        m = _matrix4(cam_to_world)
        s = _scalar(scale, "scale")
        _require_positive(s, "scale")
        dt = _widest([m, s])
        self.scale = s.astype(dt)
        self.cam_to_world = m.astype(dt)


Camera = PinholeCamera | OrthographicCamera


def _check_camera(camera):
    if not isinstance(camera, (PinholeCamera, OrthographicCamera)):
        raise ValueError(
            f"`camera` must be a PinholeCamera or an OrthographicCamera, got {type(camera).__name__}"
        )
    return camera


def camera_rays(camera: Camera) -> tuple[Float[Array, "H W 3"], Float[Array, "H W 3"]]:
    """World-space rays through the pixel centres of a camera.

    Pinhole: origin = camera centre $t$ (all pixels), direction
    $R\\,((u - c_x)/f_x, (v - c_y)/f_y, 1)$ normalized, with
    $(u, v) = (j + \\tfrac12, i + \\tfrac12)$ for pixel (row $i$, column $j$).
    Orthographic: origin $R\\,((u - W/2)s, (v - H/2)s, 0) + t$, direction
    the camera +z axis $R e_z$. ($R$, $t$ are the blocks of `cam_to_world`.)

    Jitted; differentiable in the camera's array fields. The camera's
    fields are checked again here (at run time, `equinox.error_if`): a
    camera whose fields were replaced by invalid values (e.g. with
    `eqx.tree_at`, or built from traced values) is an error, not a NaN ray.

    **Arguments:** `camera`: a `PinholeCamera` or `OrthographicCamera`.

    **Returns:** `(origins, directions)`, each `(height, width, 3)`;
    directions are unit vectors.
    """
    return _camera_rays(_check_camera(camera))


@jit
def _camera_rays(camera):
    h, w = camera.height, camera.width
    # Every check is attached to the pose matrix, which feeds both outputs: a caller that keeps only
    # the directions (or only the origins) still gets the error.
    m = _check_pose(camera.cam_to_world, type(camera).__name__)
    if isinstance(camera, PinholeCamera):
        intr = jnp.stack([camera.fx, camera.fy, camera.cx, camera.cy])
        m = error_if_any(m, ~((camera.fx > 0.0) & jnp.isfinite(camera.fx)), "PinholeCamera: `fx` must be finite and positive")
        m = error_if_any(m, ~((camera.fy > 0.0) & jnp.isfinite(camera.fy)), "PinholeCamera: `fy` must be finite and positive")
        m = error_if_any(m, ~jnp.all(jnp.isfinite(intr)), "PinholeCamera: `cx`, `cy` must be finite")
    else:
        m = error_if_any(m, ~((camera.scale > 0.0) & jnp.isfinite(camera.scale)), "OrthographicCamera: `scale` must be finite and positive")
    dt = m.dtype
    rot, t = m[:3, :3], m[:3, 3]
    u = jnp.broadcast_to((jnp.arange(w, dtype=dt) + 0.5)[None, :], (h, w))
    v = jnp.broadcast_to((jnp.arange(h, dtype=dt) + 0.5)[:, None], (h, w))
    if isinstance(camera, PinholeCamera):
        d_cam = jnp.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, jnp.ones_like(u)], axis=-1)
        d = jnp.einsum("ij,hwj->hwi", rot, d_cam)
        d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        o = jnp.broadcast_to(t[None, None, :], (h, w, 3))
    else:
        s = camera.scale
        p_cam = jnp.stack([(u - 0.5 * w) * s, (v - 0.5 * h) * s, jnp.zeros_like(u)], axis=-1)
        o = jnp.einsum("ij,hwj->hwi", rot, p_cam) + t[None, None, :]
        axis = rot[:, 2] / jnp.linalg.norm(rot[:, 2])
        d = jnp.broadcast_to(axis[None, None, :], (h, w, 3))
    return o, d


def look_at(
    eye: Real[ArrayLike, "*#batch 3"] | SequenceLike,
    target: Real[ArrayLike, "*#batch 3"] | SequenceLike,
    up: Real[ArrayLike, "*#batch 3"] | SequenceLike = (0.0, 0.0, 1.0),
) -> Float[Array, "*batch 4 4"]:
    """A camera-to-world matrix looking from `eye` at `target` (OpenCV convention).

    Camera axes in world coordinates: $z = (\\text{target} - \\text{eye})/\\|\\cdot\\|$
    (forward), $x = z \\times \\text{up}$ normalized (right), $y = z \\times x$
    (down, the component of $-\\text{up}$ orthogonal to $z$); the matrix is
    $\\begin{pmatrix} x & y & z & \\text{eye} \\\\ 0 & 0 & 0 & 1\\end{pmatrix}$,
    a proper rotation. So the target is imaged at the principal point and
    `up` points up in the image. When `up` is parallel to the viewing
    direction (within $\\sqrt{\\epsilon}$ of the dtype: 3.5e-4 rad in float32,
    1.5e-8 in float64) another world axis (the one least aligned with $z$)
    is used.

    **Arguments:** `eye`, `target`, `up`: `(..., 3)` (broadcast; traced,
    differentiable). `up` defaults to world +z; it is a direction and need
    not be a unit vector (only its component orthogonal to the viewing
    direction is used, normalized). Concrete NaN/inf in any of them, a zero
    `up`, or `eye == target` is a `ValueError` naming the argument (traced
    values: the resulting matrix is checked by the cameras and `camera_rays`).

    **Returns:** `(..., 4, 4)`.
    """
    eye = as_float_array(eye, "eye")
    target = as_float_array(target, "target")
    up = as_float_array(up, "up")
    batch = ()
    for name, a in (("eye", eye), ("target", target), ("up", up)):
        if a.ndim < 1 or a.shape[-1] != 3:
            raise ValueError(f"`{name}` must have shape (..., 3), got {tuple(a.shape)}")
        try:
            batch = jnp.broadcast_shapes(batch, a.shape[:-1])
        except ValueError:
            raise ValueError(f"the batch shape of `{name}`, {a.shape[:-1]}, does not broadcast with {batch}") from None
    for name, a in (("eye", eye), ("target", target), ("up", up)):
        _require_finite(a, name)
    if not is_traced(up) and bool(jnp.any(jnp.all(up == 0, axis=-1))):
        raise ValueError("`look_at`: `up` is a zero vector")
    dt = _widest([eye, target, up])
    eye, target, up = (jnp.broadcast_to(a.astype(dt), batch + (3,)) for a in (eye, target, up))
    try:
        gap = np.linalg.norm(np.asarray(target) - np.asarray(eye), axis=-1)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        gap = None
    if gap is not None and np.any(gap == 0.0):
        raise ValueError("`look_at`: `eye` and `target` coincide, the viewing direction is undefined")
    return _look_at(eye, target, up)


@jit
def _look_at(eye, target, up):
    z = target - eye
    z = z / jnp.linalg.norm(z, axis=-1, keepdims=True)
    x = jnp.cross(z, up)
    nx = jnp.linalg.norm(x, axis=-1, keepdims=True)
    nup = jnp.linalg.norm(up, axis=-1, keepdims=True)
    # `up` within sqrt(eps) of the viewing direction: z x up is mostly rounding (in float32, up = (1, 2, 3) along z
    # gave a matrix 1 % from a rotation with the former 1e-9 test); the fallback up is the world axis least aligned
    # with z
    degenerate = nx <= float(np.sqrt(np.finfo(z.dtype).eps)) * nup
    k = jnp.argmin(jnp.abs(z), axis=-1)
    alt = jax.nn.one_hot(k, 3, dtype=z.dtype)
    x_alt = jnp.cross(z, alt)
    x = jnp.where(degenerate, x_alt, x)
    x = x - jnp.sum(x * z, axis=-1, keepdims=True) * z  # orthogonal to z to rounding, whatever the angle to up
    x = x / jnp.linalg.norm(x, axis=-1, keepdims=True)
    y = jnp.cross(z, x)
    rot = jnp.stack([x, y, z], axis=-1)
    top = jnp.concatenate([rot, eye[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], dtype=eye.dtype), eye.shape[:-1] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)
