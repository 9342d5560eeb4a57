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
