"""solvers.sharing_tradeoff: the spatial/angular trade-off of Zickler 2006 sec. 3 (eqs. 5-6, sec. 7).

Independent expectations (not values from the code): on a homogeneous sphere the held-out
error falls as images are added; on a surface whose roughness varies across it (sec. 7.1), a
spatial scale far above the paper's 0.2-0.4 (m_xy = 30: each point's reflectance from its own
few samples, near-Lambertian per point) predicts worse than a moderate m_xy = 0.3.
"""

import numpy as np
import pytest

import solvers
from solvers import synthetic as Z


def test_tradeoff_images_and_spatial_scale():
    kw = dict(n_images=(2, 8), n_px=16, n_centers=60, n_out=6)
    homo = solvers.sharing_tradeoff(lambda wi, wo, n, xy: Z.metallic_brdf(wi, wo, n), m_xy=(0.1,), **kw)
    e = homo["error"][:, 0]
    assert homo["error"].shape == (2, 1) and np.all(np.isfinite(e))
    assert e[1] < 0.95 * e[0]  # more images, smaller error (measured 0.056 vs 0.066 at 16 px, 60 centres)
    vary = solvers.sharing_tradeoff(Z.varying_cook_torrance, m_xy=(0.3, 30.0), **kw)
    err = vary["error"]
    assert err.shape == (2, 2) and vary["n_samples"][1] > vary["n_samples"][0]
    assert np.all(err[:, 1] > 1.5 * err[:, 0])  # too large m_xy: no sharing, worse
    assert vary["best_m_xy"] == [0.3, 0.3]


def test_tradeoff_bad_arguments():
    with pytest.raises(ValueError, match="m_xy"):
        solvers.sharing_tradeoff(Z.varying_cook_torrance, m_xy=(0.0,))
    with pytest.raises(ValueError, match="n_images"):
        solvers.sharing_tradeoff(Z.varying_cook_torrance, n_images=(0,))


def test_tradeoff_one_image_is_nan_not_a_tie():
    """One light and the fixed view: theta_d, so w, is constant and eq. 13's degree-1 system singular (fit_sbrdf:
    ill_conditioned). Every m_xy used to get the same error and `best_m_xy` the first value by tie-breaking, which
    looked like the paper's claim; now NaN, while two images give finite errors."""
    r = solvers.sharing_tradeoff(Z.varying_cook_torrance, n_images=(1, 2), m_xy=(0.03, 0.3), n_px=12, n_centers=30,
                                 n_out=4)
    assert np.all(np.isnan(r["error"][0])) and np.isnan(r["best_m_xy"][0])
    assert np.all(np.isfinite(r["error"][1])) and r["best_m_xy"][1] in (0.03, 0.3)


def test_view_cameras_check_n_views_and_azimuths():
    """`view_cameras(5, azimuths=[two values])` returned 2 cameras and n_views 0 or -2 one camera, silently."""
    with pytest.raises(ValueError, match="n_views"):
        solvers.view_cameras(0, 16)
    with pytest.raises(ValueError, match=r"`azimuths` must hold `n_views` = 5 values, got 2"):
        solvers.view_cameras(5, 16, azimuths=[0.3, 2.0])
    assert len(solvers.view_cameras(2, 16, azimuths=[0.3, 2.0])) == 2
