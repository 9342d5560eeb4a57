"""Independent references for the tests (scipy, explicit formulas), and a counter of compiled programs."""

import logging

import jax
import numpy as np
import scipy.special as sp


def scipy_complex_sh(dirs, lmax):
    """Complex SH from scipy.special.sph_harm_y, flat layout (..., (lmax+1)**2)."""
    dirs = np.asarray(dirs, dtype=np.float64)
    dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    theta = np.arctan2(np.hypot(dirs[..., 0], dirs[..., 1]), dirs[..., 2])  # accurate near the poles
    phi = np.arctan2(dirs[..., 1], dirs[..., 0])
    return np.stack(
        [sp.sph_harm_y(l, m, theta, phi) for l in range(lmax + 1) for m in range(-l, l + 1)],
        axis=-1,
    )


def scipy_real_sh(dirs, lmax):
    """Real SH built from scipy's complex SH with the convention of docs/conventions.md.

    Y_{l,m} = sqrt2 (-1)^m Re Y_l^m, Y_{l,-m} = sqrt2 (-1)^m Im Y_l^m (m > 0).
    """
    yc = scipy_complex_sh(dirs, lmax)
    out = np.empty(yc.shape, dtype=np.float64)
    for l in range(lmax + 1):
        base = l * l + l
        out[..., base] = yc[..., base].real
        for m in range(1, l + 1):
            s = np.sqrt(2.0) * (-1.0) ** m
            out[..., base + m] = s * yc[..., base + m].real
            out[..., base - m] = s * yc[..., base + m].imag
    return out


def tol(dtype, x64=1e-10, x32=1e-4):
    """Tolerance by precision (docs/design.md, "Tests")."""
    return x64 if np.dtype(dtype) == np.float64 else x32


def accelerator_branches(monkeypatch):
    """Trace `jaxsh._compile.by_platform` as for a GPU: its `other` branch (a CPU program never lowers it)."""
    import jax

    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(jax.lax, "platform_dependent", lambda *args, default, **branches: default(*args))


def random_dirs(rng, shape):
    d = rng.normal(size=tuple(shape) + (3,))
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def random_rotation(rng, shape=()):
    """Uniform random rotations (QR of a Gaussian matrix, det +1)."""
    a = rng.normal(size=tuple(shape) + (3, 3))
    q, r = np.linalg.qr(a)
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[..., None, :]
    det = np.linalg.det(q)
    q[..., :, 0] *= det[..., None]
    return q


def is_x64(x):
    return np.dtype(x.dtype) in (np.float64, np.complex128)


def write_png16(path, img):
    """Write `img` (values in [0, 1]) as a 16-bit PNG of linear code values (as machine-vision cameras do)."""
    import OpenImageIO as oiio

    code = np.round(np.clip(img, 0.0, 1.0) * 65535.0).astype(np.uint16)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(code.shape[1], code.shape[0], code.shape[2], "uint16"))
    assert out.write_image(code)
    out.close()


def hemisphere_normals(size=8):
    """Normals `(size, size, 3)` of a hemisphere seen from +z and its `(size, size)` mask (+z outside it)."""
    y, x = np.mgrid[-1 : 1 : size * 1j, -1 : 1 : size * 1j] * 0.9
    r2 = x * x + y * y
    mask = r2 < 0.8
    z = np.sqrt(np.clip(1 - r2, 0, None))
    normal = np.stack([x, y, z], -1)
    normal[~mask] = [0.0, 0.0, 1.0]
    return normal / np.linalg.norm(normal, axis=-1, keepdims=True), mask


def primitives(jaxpr) -> set:
    """Every primitive name in a closed jaxpr, sub-jaxprs (jit, cond, while, custom rules) included."""
    out = set()
    for eqn in jaxpr.eqns:
        out.add(eqn.primitive.name)
        for p in eqn.params.values():
            for sub in p if isinstance(p, (tuple, list)) else (p,):
                if isinstance(sub, jax.extend.core.ClosedJaxpr):
                    out |= primitives(sub.jaxpr)
                elif isinstance(sub, jax.extend.core.Jaxpr):
                    out |= primitives(sub)
    return out


class Compiles:
    """Counts the XLA programs compiled inside a `with` block (JAX's own log, `jax.log_compiles`)."""

    def __init__(self):
        self.names = []
        outer = self

        class _H(logging.Handler):
            def emit(self, record):
                msg = record.getMessage()
                if msg.startswith("Compiling "):
                    outer.names.append(msg.split(" with ")[0][len("Compiling "):])

        self._handler, self._logger = _H(), logging.getLogger("jax")

    def __enter__(self):
        self._ctx = jax.log_compiles()
        self._ctx.__enter__()
        self._logger.addHandler(self._handler)
        return self

    def __exit__(self, *exc):
        self._logger.removeHandler(self._handler)
        self._ctx.__exit__(*exc)


def quadrature_images(gbs, brdf, lightings, lmax, n_theta=16, n_phi=32):
    """Images of the views `gbs` by brute-force quadrature of the reflection equation (`jaxsh.reflect_quadrature`,
    R&H eq. 2) of a world-frame `brdf(wi, wo, n) -> (..., C)` under band-limited lighting: `lightings[k]` real SH
    `(num_coeffs(lmax), C)` for view k. Exact to rounding when the integrand is a polynomial of low degree in the
    incident direction (Gauss-Legendre in cos(theta_i), uniform azimuths). No SH BRDF coefficients are involved, so
    fits of `fit_brdf_sh` / `predict_brdf_sh` (eqs. 9, 10) are checked against something they do not share."""
    import jaxsh

    imgs = []
    for g, sh in zip(gbs, lightings):
        m = np.asarray(g.mask)
        sh = np.asarray(sh)
        img = np.zeros(m.shape + (sh.shape[1],))

        def light(d, sh=sh):
            return jaxsh.real_sh(d, lmax) @ sh

        img[m] = np.asarray(jaxsh.reflect_quadrature(light, brdf, np.asarray(g.normal)[m], np.asarray(g.view)[m],
                                                     n_theta=n_theta, n_phi=n_phi))
        imgs.append(img)
    return imgs
