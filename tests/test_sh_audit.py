"""Audit of the SH core: band limits a dtype cannot evaluate, empty rotation batches, scalar roughness.

`real_sh` and the lat-long transforms seed their recurrences with $\\sin^m\\theta$. Below float64 the seeds left
the float range from about lmax 200, and every harmonic above them came out 0 where it is of order 1 (-1.44 at
l = 256); float64 does the same from about l = 1925. Such band limits are now a `ValueError`. The accuracy up to
the float32 limit is checked here against `scipy.special.sph_harm_y`.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
from jaxsh._sh import REAL_SH_MAX_LMAX
from jaxsh._transforms import TRANSFORM_MAX_LMAX

from .helpers import scipy_real_sh


def test_real_sh_float32_at_its_largest_band_limit_matches_scipy():
    """At the float32 limit (170) over a sweep of polar angles (where the seeds get smallest near the poles and at
    sin(theta) ~ 1/e), `real_sh` in float32 is within 2e-5 of scipy; one degree more is a ValueError."""
    lmax = REAL_SH_MAX_LMAX[0]
    assert lmax == 170
    th = np.linspace(0.02, np.pi / 2, 120)
    d = np.stack([np.sin(th) * np.cos(0.3), np.sin(th) * np.sin(0.3), np.cos(th)], -1)
    got = np.asarray(jaxsh.real_sh(d.astype(np.float32), lmax), np.float64)
    np.testing.assert_allclose(got, scipy_real_sh(d, lmax), atol=2e-5)
    with pytest.raises(ValueError, match=r"`lmax` = 171 .*`real_sh` .*float32: at most 170.*use float64"):
        jaxsh.real_sh(d.astype(np.float32), lmax + 1)
    with pytest.raises(ValueError, match=r"`lmax` = 171 .*`complex_sh`"):
        jaxsh.complex_sh(d.astype(np.float32), lmax + 1)
    with pytest.raises(ValueError, match=r"`lmax` = 1901 .*float64: at most 1900"):
        jaxsh.real_sh(d[:2], REAL_SH_MAX_LMAX[1] + 1)


def test_latlong_transforms_refuse_band_limits_their_dtype_cannot_evaluate():
    """float32 synthesis at lmax 256 erred 45 against an image RMS of 72 (seeds flushed to 0); now a ValueError
    beyond 200 naming the function, in both directions and both dtypes' limits."""
    lo, hi = TRANSFORM_MAX_LMAX
    c32 = np.zeros((lo + 2) ** 2, np.float32)
    with pytest.raises(ValueError, match=r"`lmax` = 201 .*`synthesize_latlong` .*float32"):
        jaxsh.synthesize_latlong(c32, 404, 404)
    with pytest.raises(ValueError, match=r"`lmax` = 201 .*`project_latlong` .*float32"):
        jaxsh.project_latlong(np.zeros((404, 808), np.float32), lo + 1)
    with pytest.raises(ValueError, match=r"`lmax` = 1901 .*`project_latlong` .*float64"):
        jaxsh.project_latlong(np.zeros((8, 16)), hi + 1, allow_aliasing=True)


def test_rotate_sh_of_an_empty_batch_of_rotations():
    """`R` of shape (0, 3, 3): an empty result, as `wigner_D` gives (was an IndexError naming nothing)."""
    c = np.ones(16)
    out = jaxsh.rotate_sh(c, np.zeros((0, 3, 3)))
    assert out.shape == (0, 16)
    assert jaxsh.wigner_D(np.zeros((0, 3, 3)), 3).shape == (0, 16, 16)


def test_filter_lighting_microfacet_takes_a_scalar_sigma():
    """A vector sigma was broadcast into a (k, n, C) result, against the docstring (scalar; the layout of
    `coeffs`); now a ValueError naming `sigma`. A scalar gives exp(-(sigma l)^2) per band (R&H eq. 20)."""
    coeffs = np.ones((16, 3))
    with pytest.raises(ValueError, match=r"`sigma` must be a scalar"):
        jaxsh.filter_lighting_microfacet(coeffs, np.array([0.1, 0.2]))
    got = np.asarray(jaxsh.filter_lighting_microfacet(coeffs, 0.2))
    deg = np.repeat(np.arange(4), 2 * np.arange(4) + 1)
    np.testing.assert_allclose(got, np.exp(-((0.2 * deg) ** 2))[:, None] * coeffs, rtol=1e-15)
    assert jnp.asarray(got).shape == coeffs.shape
