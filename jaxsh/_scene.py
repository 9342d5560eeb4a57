"""Cameras, G-buffers and visibility: the geometry side of a capture.

**Cameras** (DESIGN.md, "Capture manifest") follow OpenCV: +x right, +y
down, +z forward; `cam_to_world` is the 4×4 matrix mapping camera to world
coordinates, $x_w = R\\,x_c + t$. Pixel $(i, j)$ = (row, column) has its
centre at image coordinates $(u, v) = (j + \\tfrac12, i + \\tfrac12)$.

- Pinhole: the ray of pixel $(i, j)$ leaves the camera centre $t$ along
  $R\\,((u - c_x)/f_x, (v - c_y)/f_y, 1)$, normalized.
- Orthographic: the ray of pixel $(i, j)$ leaves the camera-frame point
  $((j + \\tfrac12 - W/2)\\,s, (i + \\tfrac12 - H/2)\\,s, 0)$ along the camera
  +z axis, with $s$ = `scale` (world units per pixel).

**G-buffers** hold, per pixel, whether the ray hit the object (`mask`), the
hit point, the unit surface normal, the unit view direction $\\omega_o$
(from the surface *towards* the camera, i.e. minus the ray direction) and the
depth: the camera-frame $z$ of the hit point (the OpenCV depth-map
convention; the ray length times the cosine between ray and optical axis for
a pinhole camera, the ray length itself for an orthographic one). Pixels
that miss have `mask = False`, zero position, normal and depth, and still a
valid view direction.

`sphere_gbuffer` is analytic JAX (jitted, differentiable in the camera and
the sphere). `mesh_gbuffer` and the visibility functions are **NumPy /
trimesh ray casting, not jitted and not differentiable**: they are meant to
be run once per capture and their outputs (arrays) fed to the jitted
solvers.

**Ray-casting engines** (`engine=`): `"embree"` — Intel Embree through
`embreex` and `trimesh.ray.ray_pyembree` (fast; the traversal is in
float32, hit points are recomputed in float64 by trimesh); `"triangle"` —
trimesh's pure-Python intersector `trimesh.ray.ray_triangle` (needs
`rtree`); `"numpy"` — a brute-force vectorized Möller–Trumbore intersector
of this module (float64, $O(\\text{rays}\\times\\text{faces})$ work, no
dependencies; for small meshes and as a reference); `"auto"` (default) picks
the first available of embree, triangle, numpy.

**Visibility** (R&H 2001 sec. 6.4): with self-shadowing the practical model
needs (i) whether each directional source is visible from a surface point
($B_{s,fast}$), (ii) whether the reflected ray is visible ($B_{s,slow}$),
and (iii) the irradiance integrated "in the conventional angular-space way
... considering visibility" ($B_d$). These depend on geometry only and are
precomputed here. For (iii) `visibility_sh` returns the transfer vector
$T_{lm}(x) = \\int V_x(\\omega)\\max(\\omega\\cdot n, 0)\\,Y_{lm}(\\omega)\\,d\\omega$,
so that $E(x) = \\sum_{lm} L_{lm}T_{lm}(x)$ is still linear in the lighting
coefficients, as sec. 6.4 requires for inverse lighting (eq. 25). For an
unoccluded point $T_{lm} = A_l Y_{lm}(n)$ ($A_l$ = `lambertian_spectrum`),
and $E$ reduces to eq. 21.

Shadow rays start at $x + \\varepsilon n$ (default
$\\varepsilon = 10^{-4}\\times$ `mesh.scale`) so that the surface does not
shadow itself; a direction below the horizon of the normal
($\\omega\\cdot n \\le 0$) is reported as not visible ("attached shadow")
without casting a ray.

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

    Möller, T., Trumbore, B. (1997). Fast, minimum storage ray-triangle
    intersection. J. Graphics Tools 2(1), 21–28.
    doi:10.1080/10867651.1997.10487468

    Hartley, R., Zisserman, A. (2004). *Multiple View Geometry in Computer
    Vision*, 2nd ed., sec. 6.1 (the pinhole camera).
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Real
from ._custom_types import SequenceLike

from ._checks import as_float_array, check_lmax, check_positive_int, coeff_layout
from ._reflectance import reflect, tangent_frame
from ._rotation import rotate_sh
from ._sh import real_sh

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
        return jnp.asarray(float(x))
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


def _matrix4(m, name: str = "cam_to_world"):
    m = as_float_array(m, name)
    if m.shape != (4, 4):
        raise ValueError(f"`{name}` must have shape (4, 4), got {tuple(m.shape)}")
    return m


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


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

    All arrays are converted to one float dtype (the widest given). A
    non-positive focal length raises `ValueError` at construction (or, when
    the camera is built from traced values, an error at run time of
    `camera_rays`).
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

    Jitted; differentiable in the camera's array fields.

    **Arguments:** `camera`: a `PinholeCamera` or `OrthographicCamera`.

    **Returns:** `(origins, directions)`, each `(height, width, 3)`;
    directions are unit vectors.
    """
    return _camera_rays(_check_camera(camera))


@eqx.filter_jit
def _camera_rays(camera):
    h, w = camera.height, camera.width
    m = camera.cam_to_world
    dt = m.dtype
    rot, t = m[:3, :3], m[:3, 3]
    u = jnp.broadcast_to((jnp.arange(w, dtype=dt) + 0.5)[None, :], (h, w))
    v = jnp.broadcast_to((jnp.arange(h, dtype=dt) + 0.5)[:, None], (h, w))
    if isinstance(camera, PinholeCamera):
        fx = eqx.error_if(camera.fx, ~(camera.fx > 0.0), "PinholeCamera: `fx` must be positive")
        fy = eqx.error_if(camera.fy, ~(camera.fy > 0.0), "PinholeCamera: `fy` must be positive")
        d_cam = jnp.stack([(u - camera.cx) / fx, (v - camera.cy) / fy, jnp.ones_like(u)], axis=-1)
        d = jnp.einsum("ij,hwj->hwi", rot, d_cam)
        d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
        o = jnp.broadcast_to(t[None, None, :], (h, w, 3))
    else:
        s = eqx.error_if(camera.scale, ~(camera.scale > 0.0), "OrthographicCamera: `scale` must be positive")
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
    direction another world axis (the one least aligned with $z$) is used.

    **Arguments:** `eye`, `target`, `up`: `(..., 3)` (broadcast; traced,
    differentiable). `up` defaults to world +z.

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
    dt = _widest([eye, target, up])
    eye, target, up = (jnp.broadcast_to(a.astype(dt), batch + (3,)) for a in (eye, target, up))
    try:
        gap = np.linalg.norm(np.asarray(target) - np.asarray(eye), axis=-1)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        gap = None
    if gap is not None and np.any(gap == 0.0):
        raise ValueError("`look_at`: `eye` and `target` coincide, the viewing direction is undefined")
    return _look_at(eye, target, up)


@eqx.filter_jit
def _look_at(eye, target, up):
    z = target - eye
    z = z / jnp.linalg.norm(z, axis=-1, keepdims=True)
    x = jnp.cross(z, up)
    nx = jnp.linalg.norm(x, axis=-1, keepdims=True)
    nup = jnp.linalg.norm(up, axis=-1, keepdims=True)
    degenerate = nx <= 1e-9 * nup
    # fallback up: the world axis least aligned with z
    k = jnp.argmin(jnp.abs(z), axis=-1)
    alt = jax.nn.one_hot(k, 3, dtype=z.dtype)
    x_alt = jnp.cross(z, alt)
    x = jnp.where(degenerate, x_alt, x)
    nx = jnp.linalg.norm(x, axis=-1, keepdims=True)
    x = x / nx
    y = jnp.cross(z, x)
    rot = jnp.stack([x, y, z], axis=-1)
    top = jnp.concatenate([rot, eye[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], dtype=eye.dtype), eye.shape[:-1] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


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

    `gb.position[gb.mask]` etc. give the `(N, 3)` samples of the object
    (outside `jit`).
    """

    mask: Bool[Array, "H W"]
    position: Float[Array, "H W 3"]
    normal: Float[Array, "H W 3"]
    view: Float[Array, "H W 3"]
    depth: Float[Array, "H W"]


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
    - `center`: `(3,)`; `radius`: scalar > 0 (traced).

    **Returns:** a `GBuffer` of `(height, width)` images.
    """
    camera = _check_camera(camera)
    center = as_float_array(center, "center")
    if center.shape != (3,):
        raise ValueError(f"`center` must have shape (3,), got {tuple(center.shape)}")
    radius = _scalar(radius, "radius")
    _require_positive(radius, "radius")
    dt = _widest([camera.cam_to_world, center, radius])
    if dt != camera.cam_to_world.dtype:
        camera = jax.tree_util.tree_map(lambda a: a.astype(dt), camera)
    return _sphere_gbuffer(camera, center.astype(dt), radius.astype(dt))


@eqx.filter_jit
def _sphere_gbuffer(camera, center, radius):
    radius = eqx.error_if(radius, ~(radius > 0.0), "sphere_gbuffer: `radius` must be positive")
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


# --------------------------------------------------------------------------- ray casting (NumPy / trimesh)

_ENGINES = ("auto", "embree", "triangle", "numpy")
_RAY_CHUNK = 1 << 18  # rays per call into a ray caster (bounds the memory)


def embree_available() -> bool:
    """Whether trimesh can use Embree (`embreex` importable) for ray casting."""
    try:
        import trimesh.ray

        if not trimesh.ray.has_embree:
            return False
        from trimesh.ray import ray_pyembree  # noqa: F401
    except Exception:  # pragma: no cover - depends on the installation
        return False
    return True


def _rtree_available() -> bool:
    try:
        import rtree  # noqa: F401
    except Exception:
        return False
    return True


def _check_mesh(mesh):
    try:
        import trimesh
    except ImportError as e:  # pragma: no cover - trimesh is a dependency
        raise ValueError("mesh ray casting needs trimesh") from e
    if isinstance(mesh, trimesh.Scene):
        raise ValueError("`mesh` is a trimesh.Scene; pass one mesh, e.g. `scene.to_geometry()`")
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"`mesh` must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise ValueError("`mesh` is empty (it has no faces)")
    return mesh


class _TrimeshCaster:
    def __init__(self, intersector):
        self.intersector = intersector

    def first(self, origins, directions):
        n = len(origins)
        tri = np.full(n, -1, dtype=np.int64)
        loc = np.zeros((n, 3))
        for s in range(0, n, _RAY_CHUNK):
            o, d = origins[s : s + _RAY_CHUNK], directions[s : s + _RAY_CHUNK]
            if len(o) == 0:
                continue
            locations, index_ray, index_tri = self.intersector.intersects_location(o, d, multiple_hits=False)
            if len(index_ray):
                tri[s + index_ray] = index_tri
                loc[s + index_ray] = locations
        return tri, loc

    def any(self, origins, directions):
        n = len(origins)
        out = np.zeros(n, dtype=bool)
        for s in range(0, n, _RAY_CHUNK):
            o, d = origins[s : s + _RAY_CHUNK], directions[s : s + _RAY_CHUNK]
            if len(o):
                out[s : s + len(o)] = np.asarray(self.intersector.intersects_any(o, d), dtype=bool)
        return out


class _NumpyCaster:
    """Brute-force Möller–Trumbore in float64 (all rays against all faces, in blocks)."""

    _PAIRS = 1 << 20  # ray-face pairs per block
    _TOL = 1e-10  # barycentric slack: rays through shared edges hit one of the faces

    def __init__(self, mesh):
        tri = np.asarray(mesh.triangles, dtype=np.float64)
        self.v0 = tri[:, 0]
        self.e1 = tri[:, 1] - tri[:, 0]
        self.e2 = tri[:, 2] - tri[:, 0]

    def _nearest(self, o, d):
        n = len(o)
        best_t = np.full(n, np.inf)
        best_f = np.full(n, -1, dtype=np.int64)
        nf = len(self.v0)
        rows = max(1, self._PAIRS // nf)
        fblock = min(nf, self._PAIRS)
        for s in range(0, n, rows):
            oo, dd = o[s : s + rows], d[s : s + rows]
            for f0 in range(0, nf, fblock):
                v0, e1, e2 = self.v0[f0 : f0 + fblock], self.e1[f0 : f0 + fblock], self.e2[f0 : f0 + fblock]
                p = np.cross(dd[:, None, :], e2[None, :, :])
                det = np.einsum("fk,rfk->rf", e1, p)
                ok = np.abs(det) > 1e-300
                inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
                sv = oo[:, None, :] - v0[None, :, :]
                u = np.einsum("rfk,rfk->rf", sv, p) * inv
                q = np.cross(sv, e1[None, :, :])
                v = np.einsum("rk,rfk->rf", dd, q) * inv
                t = np.einsum("fk,rfk->rf", e2, q) * inv
                tol = self._TOL
                hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1.0 + tol) & (t > 0.0)
                t = np.where(hit, t, np.inf)
                k = np.argmin(t, axis=1)
                tk = t[np.arange(len(oo)), k]
                better = tk < best_t[s : s + rows]
                best_t[s : s + rows] = np.where(better, tk, best_t[s : s + rows])
                best_f[s : s + rows] = np.where(better, f0 + k, best_f[s : s + rows])
        return best_f, best_t

    def first(self, origins, directions):
        d = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
        f, t = self._nearest(origins, d)
        hit = f >= 0
        loc = np.where(hit[:, None], origins + np.where(hit, t, 0.0)[:, None] * d, 0.0)
        return f, loc

    def any(self, origins, directions):
        d = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
        f, _ = self._nearest(origins, d)
        return f >= 0


def _caster(mesh, engine: str):
    if engine not in _ENGINES:
        raise ValueError(f"`engine` must be one of {_ENGINES}, got {engine!r}")
    if engine == "auto":
        engine = "embree" if embree_available() else ("triangle" if _rtree_available() else "numpy")
    if engine == "embree":
        if not embree_available():
            raise ValueError("engine='embree' needs the `embreex` package (not importable here)")
        from trimesh.ray import ray_pyembree

        ray = mesh.ray  # cached on the mesh; embree when trimesh found embreex
        if not isinstance(ray, ray_pyembree.RayMeshIntersector):  # pragma: no cover
            ray = ray_pyembree.RayMeshIntersector(mesh)
        return _TrimeshCaster(ray)
    if engine == "triangle":
        if not _rtree_available():
            raise ValueError("engine='triangle' (trimesh.ray.ray_triangle) needs the `rtree` package; use 'numpy'")
        from trimesh.ray import ray_triangle

        return _TrimeshCaster(ray_triangle.RayMeshIntersector(mesh))
    return _NumpyCaster(mesh)


def _unit_np(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0.0, n, 1.0)


def mesh_gbuffer(camera: Camera, mesh, smooth: bool = True, engine: str = "auto") -> GBuffer:
    """G-buffer of a triangle mesh by ray casting (NumPy / trimesh; not jitted).

    Casts the rays of `camera_rays(camera)` and keeps the first hit. The
    normal is the vertex normals (`mesh.vertex_normals`) interpolated with
    the barycentric coordinates of the hit (`smooth=True`; use it for
    tessellated smooth surfaces) or the face normal (`smooth=False`; use it
    for faceted objects such as boxes). Normals follow the mesh orientation
    (outward for a consistently wound closed mesh); they are not flipped
    towards the camera.

    Not differentiable (the result is data). Cost: one first-hit query per
    pixel, see the module docstring for `engine`.

    **Arguments:**

    - `camera`: `PinholeCamera` or `OrthographicCamera`.
    - `mesh`: a non-empty `trimesh.Trimesh`.
    - `smooth`: interpolated vertex normals (True) or face normals (False).
    - `engine`: `"auto"`, `"embree"`, `"triangle"` or `"numpy"`.

    **Returns:** a `GBuffer` (JAX arrays in the camera's dtype, backed by
    NumPy results).
    """
    import trimesh

    camera = _check_camera(camera)
    mesh = _check_mesh(mesh)
    if not isinstance(smooth, bool):
        raise ValueError(f"`smooth` must be a bool, got {smooth!r}")
    caster = _caster(mesh, engine)
    o, d = _camera_rays(camera)
    h, w = camera.height, camera.width
    o = np.asarray(o, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(d, dtype=np.float64).reshape(-1, 3)
    tri, loc = caster.first(o, d)
    mask = tri >= 0
    normal = np.zeros_like(loc)
    if mask.any():
        faces = tri[mask]
        if smooth:
            bary = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], loc[mask])
            vn = np.asarray(mesh.vertex_normals)[mesh.faces[faces]]
            normal[mask] = _unit_np(np.einsum("mk,mkj->mj", bary, vn))
        else:
            normal[mask] = np.asarray(mesh.face_normals)[faces]
    m = np.asarray(camera.cam_to_world, dtype=np.float64)
    zaxis = _unit_np(m[:3, 2])
    depth = np.where(mask, (loc - m[:3, 3][None, :]) @ zaxis, 0.0)
    position = np.where(mask[:, None], loc, 0.0)
    dt = camera.cam_to_world.dtype
    return GBuffer(
        mask=jnp.asarray(mask.reshape(h, w)),
        position=jnp.asarray(position.reshape(h, w, 3), dtype=dt),
        normal=jnp.asarray(normal.reshape(h, w, 3), dtype=dt),
        view=jnp.asarray(-d.reshape(h, w, 3), dtype=dt),
        depth=jnp.asarray(depth.reshape(h, w), dtype=dt),
    )


# --------------------------------------------------------------------------- visibility (R&H 2001 sec. 6.4)


def _points_normals(points, normals):
    p = as_float_array(points, "points")
    n = as_float_array(normals, "normals")
    if p.ndim != 2 or p.shape[-1] != 3:
        raise ValueError(f"`points` must have shape (N, 3), got {tuple(p.shape)}")
    if n.shape != p.shape:
        raise ValueError(f"`normals` must have the shape of `points`, {tuple(p.shape)}, got {tuple(n.shape)}")
    dt = _widest([p, n])
    return np.asarray(p, dtype=np.float64), _unit_np(np.asarray(n, dtype=np.float64)), dt


def _eps(mesh, eps) -> float:
    if eps is None:
        return 1e-4 * float(mesh.scale)
    try:
        e = float(eps)
    except (TypeError, ValueError):
        raise ValueError(f"`eps` must be a non-negative float or None, got {eps!r}") from None
    if not (math.isfinite(e) and e >= 0.0):
        raise ValueError(f"`eps` must be a non-negative float or None, got {eps!r}")
    return e


def _visible_pairs(caster, origins, normals, dirs):
    """Visibility (N, K) of per-point directions `dirs` (N, K, 3) from `origins` (N, 3)."""
    n, k = dirs.shape[:2]
    cos = np.einsum("nj,nkj->nk", normals, dirs)
    above = cos > 0.0
    vis = np.zeros((n, k))
    if above.any():
        pi, ki = np.nonzero(above)
        hit = caster.any(origins[pi], dirs[pi, ki])
        vis[pi, ki] = np.where(hit, 0.0, 1.0)
    return vis


def directional_visibility(
    mesh,
    points: Real[ArrayLike, "N 3"],
    normals: Real[ArrayLike, "N 3"],
    directions: Real[ArrayLike, "J 3"],
    eps: float | None = None,
    engine: str = "auto",
) -> Float[Array, "N J"]:
    """Visibility of directional sources from surface points (R&H 2001 sec. 6.4).

    $V_{nj} = 1$ if the ray from $x_n + \\varepsilon n_n$ towards source
    $j$ leaves the mesh without hitting it and $\\omega_j\\cdot n_n > 0$, else
    0 (cast shadows and attached shadows). Used to switch off a source's
    specular and diffuse contributions ($B_{s,fast}$, and $B_d$ for
    directional lighting) at shadowed points. NumPy / trimesh, not jitted.

    **Arguments:**

    - `mesh`: non-empty `trimesh.Trimesh` (the occluder, usually the object).
    - `points`, `normals`: `(N, 3)` surface points and normals (normalized
      here), e.g. `gb.position[gb.mask]`, `gb.normal[gb.mask]`.
    - `directions`: `(J, 3)` directions from the surface towards the sources
      (normalized here).
    - `eps`: origin offset along the normal (default 1e-4·`mesh.scale`).
    - `engine`: see the module docstring.

    **Returns:** `(N, J)` float array of 0 and 1 (dtype of `points`).
    """
    mesh = _check_mesh(mesh)
    p, n, dt = _points_normals(points, normals)
    d = as_float_array(directions, "directions")
    if d.ndim != 2 or d.shape[-1] != 3:
        raise ValueError(f"`directions` must have shape (J, 3), got {tuple(d.shape)}")
    d = np.asarray(d, dtype=np.float64)
    if np.any(np.linalg.norm(d, axis=-1) == 0.0):
        raise ValueError("`directions` contains a zero vector")
    d = _unit_np(d)
    e = _eps(mesh, eps)
    caster = _caster(mesh, engine)
    dirs = np.broadcast_to(d[None, :, :], (len(p), len(d), 3))
    vis = _visible_pairs(caster, p + e * n, n, dirs)
    return jnp.asarray(vis, dtype=dt)


def reflected_visibility(
    mesh,
    points: Real[ArrayLike, "N 3"],
    normals: Real[ArrayLike, "N 3"],
    views: Real[ArrayLike, "N 3"],
    eps: float | None = None,
    engine: str = "auto",
) -> Float[Array, " N"]:
    """Visibility of the reflected ray $R = 2(n\\cdot\\omega_o)n - \\omega_o$ (R&H 2001 sec. 6.4).

    $B_{s,slow}$ depends on $L_{slow}(\\vec R)$; with self-shadowing it is
    switched off where the reflected ray hits the object. Same ray test as
    `directional_visibility`, with one direction per point (`reflect(views,
    normals)`); 0 when the view is below the horizon. NumPy / trimesh.

    **Arguments:** `mesh`; `points`, `normals`, `views` (unit, towards the
    camera, e.g. `gb.view[gb.mask]`): `(N, 3)`; `eps`, `engine` as in
    `directional_visibility`.

    **Returns:** `(N,)` float array of 0 and 1 (dtype of `points`).
    """
    mesh = _check_mesh(mesh)
    p, n, dt = _points_normals(points, normals)
    v = as_float_array(views, "views")
    if v.shape != p.shape:
        raise ValueError(f"`views` must have the shape of `points`, {p.shape}, got {tuple(v.shape)}")
    r = _unit_np(np.asarray(reflect(jnp.asarray(np.asarray(v, np.float64)), jnp.asarray(n)), dtype=np.float64))
    e = _eps(mesh, eps)
    caster = _caster(mesh, engine)
    vis = _visible_pairs(caster, p + e * n, n, r[:, None, :])
    return jnp.asarray(vis[:, 0], dtype=dt)


def hemisphere_quadrature(n_dirs: int, lmax: int = 0) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """The local-frame hemisphere rule used by `visibility_sh` (NumPy float64).

    Gauss–Legendre nodes in $\\cos\\theta \\in (0, 1)$ (`n_theta` of them)
    times `n_phi` = 4·`n_theta` uniform azimuths $\\phi_j = 2\\pi(j + \\tfrac12)/n_\\phi$,
    with `n_theta` = max(⌈√(n_dirs/4)⌉, ⌈(lmax+2)/2⌉), so at least `n_dirs`
    directions. The rule integrates $\\cos\\theta\\,Y_{lm}$ over the upper
    hemisphere exactly for $l \\le l_{max}$ (a polynomial of degree
    $l + 1 \\le 2n_\\theta - 1$ in $\\cos\\theta$ after the $\\phi$ integral,
    which is exact for $n_\\phi > l + 1$).

    **Returns:** `(dirs (K, 3), weights (K,), (n_theta, n_phi))`, weights
    summing to 2π.
    """
    n_dirs = check_positive_int(n_dirs, "n_dirs")
    lmax = check_lmax(lmax)
    nt = max(math.ceil(math.sqrt(n_dirs / 4.0)), math.ceil((lmax + 2) / 2))
    nphi = max(4 * nt, lmax + 2)
    x, w = np.polynomial.legendre.leggauss(nt)
    z = 0.5 * (x + 1.0)
    wz = 0.5 * w
    phi = 2.0 * np.pi * (np.arange(nphi) + 0.5) / nphi
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    dirs = np.stack(
        np.broadcast_arrays(s[:, None] * np.cos(phi)[None, :], s[:, None] * np.sin(phi)[None, :], z[:, None]),
        axis=-1,
    ).reshape(-1, 3)
    weights = np.repeat(wz * (2.0 * np.pi / nphi), nphi)
    return dirs, weights, (nt, nphi)


def visibility_sh(
    mesh,
    points: Real[ArrayLike, "N 3"],
    normals: Real[ArrayLike, "N 3"],
    lmax: int,
    n_dirs: int = 1024,
    eps: float | None = None,
    engine: str = "auto",
) -> Float[Array, "N n_coeffs"]:
    """Transfer vectors: real SH coefficients of $V_x(\\omega)\\max(\\omega\\cdot n, 0)$.

    $$T_{lm}(x) = \\int_{S^2} V_x(\\omega)\\,\\max(\\omega\\cdot n_x, 0)\\,Y_{lm}(\\omega)\\,d\\omega,$$

    so the visibility-weighted irradiance is $E(x) = \\sum_{lm} L_{lm}T_{lm}(x)$
    (`visibility_weighted_irradiance`), linear in the lighting as R&H 2001
    sec. 6.4 needs for inverse lighting with shadows. For an unoccluded point
    $T_{lm} = A_l Y_{lm}(n)$ with $A_l$ = `lambertian_spectrum(lmax)`.

    Computed by casting rays over the hemisphere of each normal with the rule
    of `hemisphere_quadrature(n_dirs, lmax)` in the local frame $(t, b, n)$
    of `tangent_frame`: the local coefficients
    $\\sum_k w_k V_k \\cos\\theta_k Y_{lm}(\\omega_k)$ are then rotated to
    the world frame with `rotate_sh` (so the SH basis is evaluated once, on
    the fixed local directions). Unoccluded points are exact to rounding;
    occluded ones carry the quadrature error of a discontinuous integrand
    (roughly the fraction of the $n_\\theta \\times n_\\phi$ cells cut by the
    shadow boundary). NumPy / trimesh for the rays; not differentiable.

    **Arguments:**

    - `mesh`: non-empty `trimesh.Trimesh`.
    - `points`, `normals`: `(N, 3)` (normals normalized here).
    - `lmax`: band limit of the transfer vectors (static int).
    - `n_dirs`: minimum number of rays per point (see `hemisphere_quadrature`).
    - `eps`, `engine`: as in `directional_visibility`.

    **Returns:** `(N, (lmax+1)**2)` (dtype of `points`).
    """
    mesh = _check_mesh(mesh)
    lmax = check_lmax(lmax)
    p, n, dt = _points_normals(points, normals)
    local, weights, _ = hemisphere_quadrature(n_dirs, lmax)
    e = _eps(mesh, eps)
    caster = _caster(mesh, engine)
    nc = (lmax + 1) ** 2
    if len(p) == 0:
        return jnp.zeros((0, nc), dtype=dt)
    t, b = tangent_frame(jnp.asarray(n))
    rot = np.stack([np.asarray(t, np.float64), np.asarray(b, np.float64), n], axis=-1)  # columns t, b, n
    k = len(local)
    vis = np.empty((len(p), k))
    step = max(1, _RAY_CHUNK // k)
    for s in range(0, len(p), step):
        r = rot[s : s + step]
        dirs = np.einsum("nij,kj->nki", r, local)
        hit = caster.any(np.repeat(p[s : s + step] + e * n[s : s + step], k, axis=0), dirs.reshape(-1, 3))
        vis[s : s + step] = np.where(hit.reshape(len(r), k), 0.0, 1.0)
    y_local = np.asarray(real_sh(jnp.asarray(local), lmax), dtype=np.float64)  # (K, nc)
    t_local = (vis * (weights * local[:, 2])[None, :]) @ y_local
    out = rotate_sh(jnp.asarray(t_local), jnp.asarray(rot), channels=False)
    return jnp.asarray(out, dtype=dt)


def visibility_weighted_irradiance(
    transfer: Real[ArrayLike, "*batch n_T"], lighting_coeffs: Real[ArrayLike, "n_L *C"]
) -> Float[Array, "..."]:
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

    **Returns:** `(...)` or `(..., C)`.
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


@eqx.filter_jit
def _contract(transfer, light):
    n = min(transfer.shape[-1], light.shape[0])
    return jnp.tensordot(transfer[..., :n], light[:n], axes=([-1], [0]))
