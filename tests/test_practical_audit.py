"""The practical model's per-pixel SH band sums at band limits float32 cannot evaluate (audit, session 28).

In float32 the exact path's harmonics come out NaN near the poles from lmax ~186 (25 of 2,000 directions at 190,
84 at 200), where `real_sh` already refuses degrees beyond 170; `render_practical`'s default fell back to that path
for fewer than 4,096 pixels. The reference is the float64 exact path on the same float32 inputs.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh


def _scene(lmax, n=500, seed=8):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d[:20] = np.array([0.0, 0.0, 1.0], np.float32) + 1e-3 * rng.normal(size=(20, 3)).astype(np.float32)  # poles
    c = (rng.normal(size=((lmax + 1) ** 2, 1)) * 0.01).astype(np.float32)
    return d, c


def test_float32_exact_band_sums_beyond_their_range_are_errors():
    d, c = _scene(200)
    with pytest.raises(ValueError, match="`lmax` = 200.*float32"):
        jaxsh.practical_terms(d, d, slow_sh=c)
    with pytest.raises(ValueError, match="`lmax` = 200.*float32"):
        jaxsh.render_practical(d, d, np.zeros(1, np.float32), np.ones(1, np.float32), None, 0.3, slow_sh=c,
                               method="exact")


def test_float32_auto_takes_the_table_beyond_the_exact_range():
    """`"auto"` with 500 pixels used the exact sums (NaN); it now takes the table, whose error bound holds."""
    d, c = _scene(200)
    r = jaxsh.render_practical(d, d, np.zeros(1, np.float32), np.ones(1, np.float32), None, 0.3, slow_sh=c)
    got = np.asarray(r.total)
    assert got.dtype == np.float32 and np.all(np.isfinite(got))
    ref = np.asarray(jaxsh.render_practical(d.astype(np.float64), d.astype(np.float64), np.zeros(1), np.ones(1), None,
                                            0.3, slow_sh=c.astype(np.float64), method="exact").total)
    assert np.abs(got - ref).max() < 1e-4 * np.abs(ref).max()


def test_float32_exact_band_sums_inside_their_range_stay_accurate():
    d, c = _scene(170)
    got = np.asarray(jaxsh.render_practical(d, d, np.zeros(1, np.float32), np.ones(1, np.float32), None, 0.3,
                                            slow_sh=c, method="exact").total)
    ref = np.asarray(jaxsh.render_practical(d.astype(np.float64), d.astype(np.float64), np.zeros(1), np.ones(1), None,
                                            0.3, slow_sh=c.astype(np.float64), method="exact").total)
    assert np.all(np.isfinite(got)) and np.abs(got - ref).max() < 1e-4 * np.abs(ref).max()


def test_practical_terms_refuse_an_index_below_one_as_the_brdfs_do():
    """0 < mu < 1 passed `PracticalTerms` (its Fresnel check was fresnel_normalized's mu > 0) while
    `jaxsh.torrance_sparrow` and `render_practical` refuse mu < 1; now the terms do too, concrete and under jit.
    mu = 1 (the limit) and mu > 1 stay accepted; `check=False` leaves the check to the caller."""
    import equinox as eqx
    import jax

    d, c = _scene(4, n=50)
    d, c = d.astype(np.float64), c.astype(np.float64)
    terms = jaxsh.practical_terms(d, d, slow_sh=c)
    kd, ks = np.array([0.5]), np.array([0.3])
    for bad in (0.5, 0.999):
        with pytest.raises(ValueError, match="`mu` must be >= 1"):
            terms(kd, ks, bad, 0.2)
        with pytest.raises(eqx.EquinoxRuntimeError, match="`mu` must be >= 1"):
            jax.block_until_ready(eqx.filter_jit(lambda m: terms.fresnel(m))(jnp.asarray(bad)))
        with pytest.raises(ValueError, match="`mu` must be >= 1"):
            jaxsh.torrance_sparrow(d, d, d, 0.5, 0.3, bad, 0.2)  # the BRDF itself: the rule this follows
    for ok in (1.0, 1.5):
        assert np.all(np.isfinite(np.asarray(terms(kd, ks, ok, 0.2))))
    assert np.all(np.isfinite(np.asarray(terms.fresnel(0.5, check=False))))  # unchecked: the caller's range
