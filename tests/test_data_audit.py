"""The solvers' data layer on inputs the first tests missed (audit, session 28): values that overflow the
G-buffers' dtype, shadowing a model cannot hold, texel counts read off the background, out-of-range indices,
malformed options. Each case was silently wrong or an unnamed error before."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxsh
import solvers


@pytest.fixture(scope="module")
def gb32():
    cam = solvers.view_cameras(1, 8, dtype=np.float32)[0]
    return jaxsh.sphere_gbuffer(cam, np.zeros(3, np.float32), np.float32(1.0))


def _ones(gb):
    return np.where(np.asarray(gb.mask)[..., None], 1.0, 0.0) * np.ones(np.asarray(gb.mask).shape + (3,))


def test_a_value_beyond_the_gbuffers_dtype_is_a_named_error(gb32):
    """1e39 is finite in float64 and inf in float32: it passed the finite check made before the cast, and
    `fit_brdf` ended `nonfinite`."""
    img = _ones(gb32)
    i, j = (x[0] for x in np.nonzero(np.asarray(gb32.mask)))
    img[i, j] = 1e39
    with pytest.raises(ValueError, match=r"images\[0\]"):
        solvers.observations([gb32], [img])


def test_options_are_checked(gb32):
    img = _ones(gb32)
    for s in (np.nan, -1.0, 0.0, "abc"):
        with pytest.raises(ValueError, match="`saturation`"):
            solvers.observations([gb32], [img], saturation=s)
    for nt in (-5, 2.7):
        with pytest.raises(ValueError, match="`n_texels`"):
            solvers.observations([gb32], [img], texel=[np.zeros((8, 8), int)], n_texels=nt)
    with pytest.raises(ValueError, match="`fast_visibility`"):
        solvers.observations([gb32], [img], fast_visibility=[])
    bad = np.ones((8, 8, 9))
    bad[np.nonzero(np.asarray(gb32.mask))[0][0], np.nonzero(np.asarray(gb32.mask))[1][0], 4] = np.nan
    with pytest.raises(ValueError, match=r"`transfer\[0\]`"):
        solvers.observations([gb32], [img], transfer=[bad])
    with pytest.raises(ValueError, match="`size`"):
        solvers.view_cameras(1, 0)
    with pytest.raises(ValueError, match="`n_out`"):
        solvers.sharing_tradeoff(None, n_out=0)


def test_the_texel_count_comes_from_the_pixels_inside_the_mask(gb32):
    """A background of 10^6 outside the mask made `n_texels` 1,000,001 (the size of every per-texel array)."""
    m = np.asarray(gb32.mask)
    tex = np.zeros((8, 8), np.int64)
    tex[m] = np.arange(m.sum()) % 5
    tex[~m] = 10**6
    o = solvers.observations([gb32], [_ones(gb32)], texel=[tex])
    assert o.n_texels == 5


def test_subset_rejects_indices_outside_the_samples_and_takes_a_boolean_mask(gb32):
    """JAX's gather clamps: `subset([N + 5])` returned the last sample."""
    o = solvers.observations([gb32], [_ones(gb32)])
    n = o.n_samples
    with pytest.raises(ValueError, match="`index`"):
        o.subset([n + 5])
    keep = np.zeros(n, bool)
    keep[[1, 3]] = True
    np.testing.assert_array_equal(np.asarray(o.subset(keep).pixel_index), np.asarray(o.pixel_index)[[1, 3]])


def test_fit_brdf_sh_refuses_shadowed_sources(gb32):
    """The SH light-field model has no shadowing: a view in full shadow fitted its all-ones images 'converged'."""
    img = _ones(gb32)
    o = solvers.observations([gb32], [img], fast_visibility=[np.zeros((8, 8, 1))])
    lit = solvers.Lighting(fast_directions=np.array([[0.0, 0.0, 1.0]]), fast_energy=np.ones((1, 3)))
    with pytest.raises(ValueError, match="shadowing"):
        solvers.fit_brdf_sh(o, lit, 2)


def test_lighting_channels_must_match_the_data(gb32):
    o = solvers.observations([gb32], [_ones(gb32)])
    two = solvers.Lighting(np.ones((9, 2)))
    with pytest.raises(ValueError, match="`lighting` has 2 channels"):
        solvers.practical_terms_for(o, two)
    solvers.practical_terms_for(o, solvers.Lighting(np.ones((9, 1))))  # grey lighting lights every channel


def test_predict_does_not_take_a_per_texel_result_for_a_map_of_columns(gb32):
    """A `(T, C)` `kd` with T equal to the image width broadcast as a map over the columns of an (H, W) image."""
    w = np.asarray(gb32.mask).shape[1]
    brdf = solvers.TorranceSparrow(np.full((w, 3), 0.5), np.full(3, 0.2), 1.5, 0.2)
    with pytest.raises(ValueError, match="texel="):
        solvers.predict(brdf, solvers.Lighting(np.ones((9, 3))), gb32.normal, gb32.view, mask=gb32.mask)


def test_integer_and_complex_images_are_refused(gb32):
    """uint8 code values were read as linear radiance (200 for a pixel of 200/255 in sRGB) and a complex image lost
    its imaginary part with only NumPy's warning: an encoding is declared, never guessed."""
    for img in (np.full((8, 8, 3), 200, np.uint8), np.ones((8, 8, 3), np.complex128)):
        with pytest.raises(ValueError, match=r"`images\[0\]` must be a float array"):
            solvers.observations([gb32], [img])
