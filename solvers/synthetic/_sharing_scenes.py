"""Synthetic scenes and parametric baselines for the reflectance-sharing protocols (Zickler 2006 secs. 6.1, 7.1, 8.4).

* `sphere_geometry(n)`: orthographic view of a unit sphere (or the
  hemisphere facing the camera) from $+z$: normals, mask, surface
  coordinates $(x, y)$ = image-plane coordinates in $[0, 1]^2$ (pixel $(i, j)$
  at $((j + \\frac12)/n, (i + \\frac12)/n)$; the surface as a graph over the
  image plane, sec. 7).
* `theta_d_lights(thetas)`: directional lights making the difference angle
  $\\theta_d$ with the fixed view $+z$ (light at $2\\theta_d$ from the view),
  azimuths advancing by the golden angle.
* `cone_lights(n, max_angle)`: quasi-uniform (Fibonacci) lights in a cone
  about the view.
* `render_images(brdf, normal, mask, lights, irradiance)`: $I = \\rho\\,E\\cos\\theta_i$
  (attached shadows only — the scenes are convex), `(L, n, n, C)`.
* BRDFs of the protocols: `metallic_brdf` (a measured-like coloured metal:
  two Cook–Torrance lobes with a Fresnel term plus a weak coloured diffuse
  term — a stand-in for the MERL "metallic-blue" data, which is not
  bundled), `oren_nayar_brdf`, `varying_cook_torrance` (roughness linear
  in $x$, sec. 7.1), `albedo_texture` and `dichromatic_components`
  (the textured dichromatic scenes of sec. 8).
* Baselines of figs. 7–9: `fit_ward` (isotropic Ward) and `fit_lafortune`
  (isotropic Lafortune, $3N + 1$ parameters a channel), fitted by
  Levenberg–Marquardt (optimistix) to the radiance residuals
  $(\\rho_\\theta - f_i)\\cos\\theta_i$ of the same samples the RBF sees.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

import jaxsh

from .._lm import LevenbergMarquardt

VIEW = np.array([0.0, 0.0, 1.0])


def sphere_geometry(n: int, dtype=np.float64):
    """`(normal (n, n, 3), mask (n, n), xy (n, n, 2))` of a unit sphere seen orthographically from +z."""
    c = (np.arange(n) + 0.5) / n
    x = 2.0 * c[None, :] - 1.0 + 0.0 * c[:, None]
    y = 1.0 - 2.0 * c[:, None] + 0.0 * c[None, :]
    r2 = x * x + y * y
    mask = r2 < 1.0
    z = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    normal = np.where(mask[..., None], np.stack([x, y, z], -1), 0.0)
    xy = np.stack([np.broadcast_to(c[None, :], (n, n)), np.broadcast_to(c[:, None], (n, n))], -1)
    return normal.astype(dtype), mask, xy.astype(dtype)


def theta_d_lights(theta_d, phase: float = 0.0):
    """Lights at angle $2\\theta_d$ from the view +z; azimuth $\\phi_j = $ phase + j·golden angle."""
    t = np.asarray(theta_d, dtype=np.float64)
    phi = phase + np.arange(t.size) * math.pi * (3.0 - math.sqrt(5.0))
    a = 2.0 * t
    return np.stack([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)], -1)


def cone_lights(n: int, max_angle: float, phase: float = 0.0):
    """`n` Fibonacci directions, uniform in solid angle within `max_angle` of +z."""
    k = np.arange(n) + 0.5
    cmin = math.cos(max_angle)
    cz = 1.0 - (1.0 - cmin) * k / n
    s = np.sqrt(1.0 - cz * cz)
    phi = phase + k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([s * np.cos(phi), s * np.sin(phi), cz], -1)


def render_images(brdf, normal, mask, lights, irradiance=1.0, xy=None):
    """Radiance images $I = \\rho\\,E\\max(\\cos\\theta_i, 0)$, `(L, H, W, C)` (0 off the mask)."""
    normal = jnp.asarray(normal)
    out = []
    view = jnp.broadcast_to(jnp.asarray(VIEW, normal.dtype), normal.shape)
    e = np.broadcast_to(np.asarray(irradiance, dtype=np.float64), (len(lights),))
    for l_dir, el in zip(np.asarray(lights), e):
        wi = jnp.broadcast_to(jnp.asarray(l_dir, normal.dtype), normal.shape)
        rho = brdf(wi, view, normal) if xy is None else brdf(wi, view, normal, jnp.asarray(xy))
        cos = jnp.maximum(jnp.sum(wi * normal, -1), 0.0)
        img = rho * (el * cos)[..., None]
        out.append(np.where(mask[..., None], np.asarray(img), 0.0))
    return np.stack(out)


def relative_rms(pred, true, mask=None):
    """$\\sqrt{\\sum (p - t)^2 / \\sum t^2}$ over the masked pixels of all images and channels."""
    pred, true = np.asarray(pred), np.asarray(true)
    if mask is not None:
        m = np.broadcast_to(np.asarray(mask)[..., None], true.shape)
        pred, true = pred[m], true[m]
    return float(np.sqrt(np.sum((pred - true) ** 2) / np.sum(true**2)))


# --------------------------------------------------------------------------- BRDFs of the protocols

_METAL_KD = (0.02, 0.04, 0.12)
_METAL_KS1 = (0.6, 0.8, 1.3)
_METAL_KS2 = (0.2, 0.25, 0.45)


def metallic_brdf(wi, wo, n):
    """A measured-like coloured specular BRDF, RGB `(..., 3)`.

    $\\rho_k = k_{d,k}/\\pi + \\sum_{j=1,2} \\mathrm{CT}(k_{s,jk}, m_j, \\mu)$:
    Cook–Torrance lobes with $m = 0.2$ and $0.45$ and a Fresnel term of
    index $\\mu = 3.0$, blue-tinted (`_METAL_KD`, `_METAL_KS1`, `_METAL_KS2`).
    """
    chans = []
    for c in range(3):
        rho = jaxsh.cook_torrance(wi, wo, n, _METAL_KD[c], _METAL_KS1[c], 0.2, 3.0)
        rho = rho + jaxsh.cook_torrance(wi, wo, n, 0.0, _METAL_KS2[c], 0.45, 3.0)
        chans.append(rho)
    return jnp.stack(chans, -1)


def oren_nayar_brdf(wi, wo, n, albedo=(0.85, 0.65, 0.45), sigma=0.6):
    """Oren–Nayar (rough diffuse, retro-reflective), RGB `(..., 3)`."""
    return jnp.stack([jaxsh.oren_nayar(wi, wo, n, a, sigma) for a in albedo], -1)


def varying_cook_torrance(wi, wo, n, xy, m_left=0.45, m_right=0.12, kd=(0.15, 0.12, 0.1), ks=0.8, mu=1.5):
    """Cook–Torrance with roughness linear in x (sec. 7.1): $m = m_l + (m_r - m_l)x$, RGB `(..., 3)`."""
    m = m_left + (m_right - m_left) * xy[..., 0]
    return jnp.stack([jaxsh.cook_torrance(wi, wo, n, k, ks, m, mu) for k in kd], -1)


def albedo_texture(xy):
    """A smooth-but-busy RGB albedo map on $[0, 1]^2$ (for the dichromatic scenes)."""
    x, y = xy[..., 0], xy[..., 1]
    r = 0.55 + 0.35 * jnp.sin(9.0 * x) * jnp.cos(7.0 * y)
    g = 0.45 + 0.25 * jnp.cos(11.0 * x + 3.0 * y)
    b = 0.35 + 0.2 * jnp.sin(5.0 * y - 4.0 * x)
    return jnp.stack([r, g, b], -1)


def dichromatic_components(wi, wo, n, xy, sigma=0.4, ks=0.5, m_left=0.4, m_right=0.15, mu=1.5):
    """(diffuse BRDF `(..., 3)` = albedo·Oren–Nayar shape, specular BRDF `(...)` = CT with varying roughness)."""
    shape = jaxsh.oren_nayar(wi, wo, n, 1.0, sigma)
    diffuse = albedo_texture(xy) * shape[..., None]
    m = m_left + (m_right - m_left) * xy[..., 0]
    spec = jaxsh.cook_torrance(wi, wo, n, 0.0, ks, m, mu)
    return diffuse, spec


# --------------------------------------------------------------------------- parametric baselines


def _lm_fit(model, theta0, wi, wo, n, f, cos, max_steps):
    """Per-channel Levenberg–Marquardt on r = (model(θ) − f) cos θi; theta0 (R, C, P) restarts; best kept.

    One compiled program per (model, shapes, `max_steps`): the samples are arguments, not constants
    of a program made per call, so a second fit of the same size (another BRDF, another image count
    after `max_samples`) reuses it.
    """
    return _lm_fit_jit(model, theta0, wi, wo, n, f, cos, max_steps)


@jaxsh.jit
def _lm_fit_jit(model, theta0, wi, wo, n, f, cos, max_steps):
    def residual(theta, fc):
        return (model(theta, wi, wo, n) - fc) * cos

    solver = LevenbergMarquardt(rtol=1e-7, atol=1e-9)  # not optimistix's: its lineax.QR step races on CPU (solvers._lm)

    def one(theta, fc):
        sol = optx.least_squares(residual, solver, theta, args=fc, max_steps=max_steps, throw=False)
        r = residual(sol.value, fc)
        loss = jnp.sum(r * r)
        return sol.value, jnp.where(jnp.isfinite(loss), loss, jnp.inf)

    thetas, losses = jax.vmap(jax.vmap(one, in_axes=(0, 1)), in_axes=(0, None))(theta0, f)
    best = jnp.argmin(losses, axis=0)
    return jnp.take_along_axis(thetas, best[None, :, None], axis=0)[0], jnp.min(losses, axis=0)


def _ward_model(theta, wi, wo, n):
    return jaxsh.ward_isotropic(wi, wo, n, jnp.exp(theta[0]), jnp.exp(theta[1]), jnp.exp(theta[2]))


def _laf_model(theta, wi, wo, n):
    lobes = theta[1:].reshape(-1, 3)
    lobes = jnp.stack([lobes[:, 0], lobes[:, 1], jnp.exp(lobes[:, 2])], -1)
    return jaxsh.lafortune(wi, wo, n, jnp.exp(theta[0]), jnp.broadcast_to(lobes, wi.shape[:-1] + lobes.shape))


class ParametricBRDF(eqx.Module):
    """A fitted per-channel parametric BRDF (baseline); `brdf(wi, wo, n)` -> `(..., C)`."""

    theta: jax.Array
    kind: str = eqx.field(static=True)
    loss: jax.Array

    def brdf(self, wi, wo, n):
        model = _ward_model if self.kind == "ward" else _laf_model
        wi, wo, n = (jnp.asarray(a) for a in (wi, wo, n))
        shape = jnp.broadcast_shapes(wi.shape, wo.shape, n.shape)
        wi, wo, n = (jnp.broadcast_to(a, shape).reshape(-1, 3) for a in (wi, wo, n))
        out = jax.vmap(lambda th: model(th, wi, wo, n))(self.theta)
        return out.T.reshape(shape[:-1] + (self.theta.shape[0],))

    @property
    def n_params(self) -> int:
        return int(self.theta.shape[1])


def _subsample(samples, max_samples, seed=0):
    wi, wo, n, f, cos = samples
    if f.shape[0] > max_samples:
        sel = np.random.default_rng(seed).choice(f.shape[0], max_samples, replace=False)
        wi, wo, n, f, cos = (np.asarray(a)[sel] for a in (wi, wo, n, f, cos))
    return tuple(jnp.asarray(a) for a in (wi, wo, n, f, cos))


def fit_ward(samples, max_samples=20000, max_steps=300):
    """Fit per-channel isotropic Ward $(\\rho_d, \\rho_s, \\alpha)$ to `(wi, wo, n, f (N, C), cos (N,))`."""
    wi, wo, n, f, cos = _subsample(samples, max_samples)
    c = f.shape[1]
    inits = np.log(np.array([[0.3, 0.3, 0.1], [0.1, 0.6, 0.3], [0.5, 0.05, 0.05], [0.3, 0.3, 0.5]]))
    theta0 = jnp.asarray(np.broadcast_to(inits[:, None, :], (4, c, 3)), dtype=f.dtype)
    theta, loss = _lm_fit(_ward_model, theta0, wi, wo, n, f, cos, max_steps)
    return ParametricBRDF(theta, "ward", loss)


def fit_lafortune(samples, n_lobes, restarts=4, max_samples=20000, max_steps=300, seed=0):
    """Fit a per-channel isotropic Lafortune model with `n_lobes` lobes ($3N + 1$ parameters a channel).

    Restarts: lobes initialised as specular ($C_x = -C_z$), retro-reflective
    and off-specular lobes of random width; the best fit is kept (the
    problem has local minima, Zickler 2006 sec. 6.1).
    """
    wi, wo, n, f, cos = _subsample(samples, max_samples)
    c = f.shape[1]
    rng = np.random.default_rng(seed)
    th = np.empty((restarts, c, 1 + 3 * n_lobes))
    for r in range(restarts):
        th[r, :, 0] = np.log(0.3)
        for j in range(n_lobes):
            expo = rng.uniform(1.0, 60.0)
            amp = rng.uniform(0.5, 1.2)
            kind = (j + r) % 3
            cx = -amp if kind != 1 else amp
            cz = amp if kind != 2 else 0.5 * amp
            th[r, :, 1 + 3 * j : 4 + 3 * j] = (cx, cz, np.log(expo))
    theta, loss = _lm_fit(_laf_model, jnp.asarray(th, dtype=f.dtype), wi, wo, n, f, cos, max_steps)
    return ParametricBRDF(theta, "lafortune", loss)


# --------------------------------------------------------------------------- "no sharing" (fig. 11)


def _solve_pivoted(a, b):
    """$x = A^{-1}b$ for one small system `a` `(n, n)`, `b` `(n,)`: Gaussian elimination with partial pivoting
    (LAPACK's `getrf`/`getrs` algorithm) in plain array operations.

    `no_sharing_predict` solves one tiny system per pixel and channel under a `vmap`. `jnp.linalg.solve` there
    is one batched LAPACK call, which on a CPU can deadlock when calls run at once (`solvers._lapack`), and a
    loop of unbatched calls took 0.69 s against 0.012 s (48 × 48 pixels, 8 lights). Written out, the `vmap`
    stays elementwise over the systems. A zero pivot (a singular matrix) gives inf/NaN, as LAPACK's would."""
    n = a.shape[0]
    rows = jnp.arange(n)
    m = jnp.concatenate([a, b[:, None]], 1)

    def eliminate(j, m):
        p = jnp.argmax(jnp.where(rows >= j, jnp.abs(m[:, j]), -1.0))  # the largest entry on or below the diagonal
        m = m[jnp.where(rows == j, p, jnp.where(rows == p, j, rows))]  # rows j and p swapped
        f = jnp.where(rows > j, m[:, j] / m[j, j], 0.0)
        return m - f[:, None] * m[j][None, :]

    m = jax.lax.fori_loop(0, n, eliminate, m)

    def substitute(i, x):  # row k = n - 1 - i of the triangle; x is still 0 at indices <= k, solved at indices > k
        k = n - 1 - i
        return x.at[k].set((m[k, n] - m[k, :n] @ x) / m[k, k])

    return jax.lax.fori_loop(0, n, substitute, jnp.zeros_like(b))


@jax.jit
def _no_sharing_pixel(lights, f, ok, novel):
    """Linear-kernel RBF with a constant term over the light directions of one pixel (inactive rows decoupled)."""
    k = lights.shape[0]
    dt = lights.dtype
    diff = lights[:, None, :] - lights[None, :, :]
    r2 = jnp.sum(diff * diff, -1)
    psi = jnp.where(r2 > 0.0, jnp.sqrt(jnp.where(r2 > 0.0, r2, 1.0)), 0.0)
    am = ok.astype(dt)
    eye = jnp.eye(k, dtype=dt)
    psi = psi * am[:, None] * am[None, :] + eye * (1.0 - am)[None, :]
    a = jnp.block([[psi, am[:, None]], [am[None, :], jnp.zeros((1, 1), dt)]])
    any_ok = jnp.any(ok)
    a = a.at[k, k].set(jnp.where(any_ok, 0.0, 1.0))
    sol = _solve_pivoted(a, jnp.concatenate([f * am, jnp.zeros((1,), dt)]))
    dn = novel[:, None, :] - lights[None, :, :]
    rn2 = jnp.sum(dn * dn, -1)
    rn = jnp.where(rn2 > 0.0, jnp.sqrt(jnp.where(rn2 > 0.0, rn2, 1.0)), 0.0)
    return rn @ sol[:k] + sol[k]


def no_sharing_predict(images, normal, mask, lights, novel_lights, irradiance=1.0):
    """The "no sharing" baseline of Zickler 2006 fig. 11: interpolate each pixel's reflectance over lighting only.

    For a fixed view every pixel has its own angular samples $f_l = I_l/(E\\cos\\theta_{i,l})$
    (lit images only); they are interpolated over the light direction with a
    linear-kernel RBF plus a constant (the lowest degree for which $\\psi(r) = r$
    is well posed, so 1–3 samples are fine), independently per pixel and
    channel, and the prediction is $\\tilde f\\,E\\cos\\theta_i$. Pixels with
    no lit sample predict 0.

    **Returns:** `(L', H, W, C)` predicted images at `novel_lights` `(L', 3)`.
    """
    imgs = np.asarray(images, np.float64)
    nl, h, w, c = imgs.shape
    lt = np.asarray(lights, np.float64)
    nv = np.asarray(novel_lights, np.float64)
    nrm = np.asarray(normal, np.float64).reshape(-1, 3)
    cos = np.einsum("pk,lk->lp", nrm, lt)
    ok = (cos > 0.0) & np.asarray(mask).reshape(1, -1)
    f = np.where(ok[..., None], imgs.reshape(nl, -1, c) / np.where(ok, cos * irradiance, 1.0)[..., None], 0.0)
    pix = np.nonzero(np.asarray(mask).reshape(-1))[0]
    fn = jax.vmap(jax.vmap(_no_sharing_pixel, in_axes=(None, 1, None, None), out_axes=1), in_axes=(None, 1, 1, None),
                  out_axes=1)
    out = np.zeros((len(nv), h * w, c))
    for s in range(0, len(pix), 2048):
        p = pix[s : s + 2048]
        pred = fn(jnp.asarray(lt), jnp.asarray(f[:, p, :]), jnp.asarray(ok[:, p]), jnp.asarray(nv))
        cn = np.maximum(np.einsum("pk,lk->lp", nrm[p], nv), 0.0)
        out[:, p, :] = np.maximum(np.asarray(pred), 0.0) * (cn * irradiance)[..., None]
    return out.reshape(len(nv), h, w, c)


# --------------------------------------------------------------------------- the paper's protocols


def valid_masks(normal, mask, lights, min_cos):
    """`(L, H, W)` pixels with $\\cos\\theta_i, \\cos\\theta_o >$ `min_cos` (the sampled domain)."""
    nrm = np.asarray(normal)
    ci = np.einsum("hwk,lk->lhw", nrm, np.asarray(lights))
    return np.asarray(mask)[None] & (ci > min_cos) & (nrm[..., 2] > min_cos)[None]


def homogeneous_protocol(brdf, n_px=100, centers=(250, 500, 1000), m_w=0.5, min_cos=0.1, lafortune_lobes=(1, 3, 6),
                         n_in=10, n_out=21, key=None):
    """Zickler 2006 sec. 6.1 on synthetic data: a homogeneous sphere, `n_in` images with $\\theta_d$ uniform in $[0, \\pi/2]$.

    Fits the RBF BRDF (eq. 12) with each centre count, an isotropic Ward
    model and Lafortune models, to the samples with
    $\\cos\\theta_i, \\cos\\theta_o >$ `min_cos`, and predicts `n_out`
    held-out images (also uniform in $\\theta_d$, other azimuths). Returns a
    dict of relative RMS radiance errors: `"all"` over every lit pixel and
    `"valid"` over the pixels inside the sampled domain, per model, plus
    the per-image errors of the RBF models (`"per_image"`).
    """
    from .. import fit_homogeneous, reflectance_samples  # noqa: PLC0415

    normal, mask, _ = sphere_geometry(n_px)
    t_in = (np.arange(n_in) + 0.5) / n_in * (math.pi / 2)
    t_out = (np.arange(n_out) + 0.5) / n_out * (math.pi / 2)
    l_in, l_out = theta_d_lights(t_in), theta_d_lights(t_out, phase=0.7)
    i_in = render_images(brdf, normal, mask, l_in)
    i_out = render_images(brdf, normal, mask, l_out)
    smp = reflectance_samples(i_in, normal, VIEW, l_in, mask=mask, min_cos=min_cos)
    vmask = valid_masks(normal, mask, l_out, min_cos)
    res = {"theta_d_out": t_out, "n_samples": int(smp.points.shape[0]), "all": {}, "valid": {}, "per_image": {},
           "history": {}}

    def score(name, pred):
        res["all"][name] = relative_rms(pred, i_out, mask)
        res["valid"][name] = relative_rms(pred, i_out, vmask)

    for k in centers:
        m = fit_homogeneous(smp, k, m_w=m_w, key=key)
        pred = np.stack([np.asarray(m.render(normal, VIEW, light, mask=mask)) for light in l_out])
        score(f"rbf{k}", pred)
        res["per_image"][k] = [relative_rms(pred[j], i_out[j], vmask[j]) if vmask[j].any() else float("nan")
                               for j in range(n_out)]
        res["history"][k] = (np.asarray(m.fit.history_centers), np.asarray(m.fit.history_rms))
    wd = fit_ward(smp.baseline_data())
    score("ward", render_images(wd.brdf, normal, mask, l_out))
    for nl in lafortune_lobes:
        lf = fit_lafortune(smp.baseline_data(), nl)
        score(f"lafortune{nl}", render_images(lf.brdf, normal, mask, l_out))
    res["images"] = {"truth": i_out, "input": i_in, "mask": mask, "l_out": l_out}
    return res


def hemisphere_protocol(n_px=64, centers=(500, 1000, 2000), n_in=10, n_out=40, max_angle=1.0, m_xy=0.3, m_w=0.5,
                        min_cos=0.1, no_sharing=(5, 50, 150), sharing_images=5, sharing_centers=1000, key=None):
    """Zickler 2006 sec. 7.1 on synthetic data: a hemisphere with Cook–Torrance roughness linear in x.

    Error of the SBRDF (eq. 13) fitted to `n_in` images (lights in a cone of
    `max_angle` about the view) on `n_out` held-out lights vs centre count,
    and fig. 11: reflectance sharing from `sharing_images` images against
    per-pixel "no sharing" interpolation from each count in `no_sharing`.
    Errors are relative RMS over the held-out pixels with
    $\\cos\\theta_i, \\cos\\theta_o >$ `min_cos` (`"valid"`) and over all lit
    pixels (`"all"`).
    """
    from .. import fit_sbrdf, reflectance_samples  # noqa: PLC0415

    normal, mask, xy = sphere_geometry(n_px)
    l_out = cone_lights(n_out, max_angle, phase=1.3)
    i_out = render_images(varying_cook_torrance, normal, mask, l_out, xy=xy)
    vmask = valid_masks(normal, mask, l_out, min_cos)
    res = {"all": {}, "valid": {}, "history": {}, "pred": {}}

    def score(name, pred):
        res["all"][name] = relative_rms(pred, i_out, mask)
        res["valid"][name] = relative_rms(pred, i_out, vmask)
        res["pred"][name] = pred[:5]

    def sharing(n_img, k):
        l_in = cone_lights(n_img, max_angle)
        i_in = render_images(varying_cook_torrance, normal, mask, l_in, xy=xy)
        smp = reflectance_samples(i_in, normal, VIEW, l_in, mask=mask, xy=xy, min_cos=min_cos)
        m = fit_sbrdf(smp, min(k, smp.points.shape[0]), m_xy=m_xy, m_w=m_w, key=key)
        pred = np.stack([np.asarray(m.render(normal, VIEW, light, mask=mask, xy=xy)) for light in l_out])
        return m, pred

    for k in centers:
        m, pred = sharing(n_in, k)
        score(f"sharing{n_in}_rbf{k}", pred)
        res["history"][k] = (np.asarray(m.fit.history_centers), np.asarray(m.fit.history_rms))
    if sharing_images:
        _, pred = sharing(sharing_images, sharing_centers)
        score(f"sharing{sharing_images}_rbf{sharing_centers}", pred)
    for n_img in no_sharing:
        l_in = cone_lights(n_img, max_angle)
        i_in = render_images(varying_cook_torrance, normal, mask, l_in, xy=xy)
        score(f"nosharing{n_img}", no_sharing_predict(i_in, normal, mask, l_in, l_out))
    res["images"] = {"truth": i_out[:5], "mask": mask}
    return res


def one_image_protocol(n_px=64, n_centers=1000, light=(0.35, 0.2, 0.915), novel=(0.0, -0.3, 0.954), m_xy=0.3,
                       min_cos=0.1, key=None):
    """Zickler 2006 sec. 8.4 on synthetic data: eq. 15 fitted to one separated image, predicted under a novel light.

    The scene is `dichromatic_components` (textured Oren–Nayar diffuse +
    Cook–Torrance specular with varying roughness) on the hemisphere, white
    light. Returns the relative RMS error of the prediction (valid pixels
    and all lit pixels) and the images.
    """
    from .. import fit_one_image  # noqa: PLC0415

    normal, mask, xy = sphere_geometry(n_px)
    light = np.asarray(light) / np.linalg.norm(light)
    novel = np.asarray(novel) / np.linalg.norm(novel)
    dif = lambda wi, wo, n, q: dichromatic_components(wi, wo, n, q)[0]  # noqa: E731
    spec = lambda wi, wo, n, q: jnp.repeat(dichromatic_components(wi, wo, n, q)[1][..., None], 3, -1)  # noqa: E731
    d_in = render_images(dif, normal, mask, light[None], xy=xy)[0]
    s_in = render_images(spec, normal, mask, light[None], xy=xy)[0]
    m = fit_one_image(d_in, s_in, np.ones(3) / math.sqrt(3.0), normal, VIEW, light, xy, n_centers,
                      irradiance=math.sqrt(3.0), mask=mask, m_xy=m_xy, key=key, min_cos=min_cos)
    truth = render_images(dif, normal, mask, novel[None], xy=xy)[0] + render_images(spec, normal, mask, novel[None], xy=xy)[0]
    pred = np.asarray(m.render(normal, VIEW, novel, xy, mask=mask))
    vm = valid_masks(normal, mask, novel[None], min_cos)[0]
    # Lambertian-only baseline (albedo from the same image, no specular)
    lam = np.asarray(m.albedo) * np.maximum(np.einsum("hwk,k->hw", normal, novel), 0.0)[..., None] * mask[..., None]
    return {"valid": relative_rms(pred, truth, vm), "all": relative_rms(pred, truth, mask),
            "diffuse_only_valid": relative_rms(lam, truth, vm), "pred": pred, "truth": truth,
            "input": d_in + s_in, "status": m.specular.status}
