"""The spatial/angular trade-off of Zickler 2006 sec. 3, measured on synthetic spheres.

`sharing_tradeoff` fits the SBRDF of eq. 13 with $M = \\mathrm{diag}(m_{xy}, m_{xy}, 1, 1, m_w)$
for each spatial scale $m_{xy}$ and each number of input images, and returns the held-out
prediction error. Sec. 3.3 (eqs. 5-6): from few images (large light spacing
$\\Delta\\theta$) only low spatial frequencies are recoverable, so strong sharing (small
$m_{xy}$: basis functions elongated over the surface, sec. 7) is best; more images allow
less sharing (larger $m_{xy}$) and resolve more texture; a very large $m_{xy}$ gives a
near-Lambertian per-point model (sec. 7) that cannot hold a highlight.
"""

from __future__ import annotations

import numpy as np

from ._results import status_name
from ._sharing import fit_sbrdf, reflectance_samples
from .synthetic import _sharing_scenes as _Z


def sharing_tradeoff(
    brdf,
    n_images=(2, 4, 8),
    m_xy=(0.03, 0.1, 0.3, 1.0, 3.0),
    n_px: int = 24,
    n_centers: int = 150,
    n_out: int = 8,
    max_angle: float = 0.9,
    m_w: float = 0.5,
    min_cos: float = 0.1,
    key=None,
) -> dict:
    """Held-out error of the eq. 13 SBRDF vs spatial scale $m_{xy}$ and number of images (Zickler 2006 sec. 3).

    The scene is the camera-facing hemisphere of `Z.sphere_geometry(n_px)` (surface
    coordinates $(x, y) \\in [0, 1]^2$ = image plane, sec. 7), seen from $+z$; inputs are
    `n` images under `cone_lights(n, max_angle)` for each `n` in `n_images`, held-out
    images are `n_out` other lights in the same cone (`phase=1.3`). For each pair
    (`n`, $m_{xy}$) the SBRDF is fitted with `fit_sbrdf` (`min(n_centers, N)` greedy
    centres, $m_w$ = `m_w`) to the samples with $\\cos\\theta_i, \\cos\\theta_o >$ `min_cos`.

    **Arguments:** `brdf(wi, wo, n, xy)` -> `(..., C)` (the truth; ignore `xy` for a
    homogeneous surface); the rest as above.

    **Returns:** a dict with `"error"` `(len(n_images), len(m_xy))` relative RMS
    radiance error over the held-out pixels with both cosines $>$ `min_cos`,
    `"n_images"`, `"m_xy"`, `"n_samples"` (per image count) and `"best_m_xy"`
    (the $m_{xy}$ of least error, per image count). A fit `fit_sbrdf` reports
    `ill_conditioned` has a NaN error (and a count whose every fit is so, a NaN
    `best_m_xy`): with one image and the fixed view, $\\theta_d$ and so $w$ are
    constant and eq. 13's degree-1 system is singular (every $m_{xy}$ gave the
    same error, and the tie went to the first one).
    """
    n_images = tuple(int(n) for n in n_images)
    m_xy = tuple(float(m) for m in m_xy)
    if not n_images or min(n_images) < 1:
        raise ValueError(f"`n_images` must be a non-empty sequence of counts >= 1, got {n_images}")
    if not m_xy or min(m_xy) <= 0:
        raise ValueError(f"`m_xy` must be a non-empty sequence of positive scales, got {m_xy}")
    if isinstance(n_out, bool) or not isinstance(n_out, (int, np.integer)) or n_out < 1:
        raise ValueError(f"`n_out` must be an integer >= 1 (held-out images), got {n_out!r}")
    normal, mask, xy = _Z.sphere_geometry(n_px)
    l_out = _Z.cone_lights(n_out, max_angle, phase=1.3)
    i_out = _Z.render_images(brdf, normal, mask, l_out, xy=xy)
    vmask = _Z.valid_masks(normal, mask, l_out, min_cos)
    err = np.full((len(n_images), len(m_xy)), np.nan)
    n_samples = []
    for a, n in enumerate(n_images):
        l_in = _Z.cone_lights(n, max_angle)
        i_in = _Z.render_images(brdf, normal, mask, l_in, xy=xy)
        smp = reflectance_samples(i_in, normal, _Z.VIEW, l_in, mask=mask, xy=xy, min_cos=min_cos)
        n_samples.append(int(smp.points.shape[0]))
        for b, m in enumerate(m_xy):
            model = fit_sbrdf(smp, min(n_centers, smp.points.shape[0]), m_xy=m, m_w=m_w, key=key)
            if status_name(model.fit.status) == "ill_conditioned":  # e.g. one image: w is constant (eq. 13 singular)
                continue  # NaN: no model, not a tie broken by the first m_xy
            pred = np.stack([np.asarray(model.render(normal, _Z.VIEW, li, mask=mask, xy=xy)) for li in l_out])
            err[a, b] = _Z.relative_rms(pred, i_out, vmask)
    best = [m_xy[int(np.nanargmin(row))] if np.any(np.isfinite(row)) else float("nan") for row in err]
    return {"error": err, "n_images": n_images, "m_xy": m_xy, "n_samples": n_samples, "best_m_xy": best}
