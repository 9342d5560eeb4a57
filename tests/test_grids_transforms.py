"""Grids, quadrature weights, lat-long analysis/synthesis and scattered fits."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, strategies as st

import jaxsh

from .helpers import accelerator_branches, random_dirs


# ---------------------------------------------------------------- grids


def test_latlong_directions_convention():
    """Row 0 next to +z, column j at phi = 2 pi (j + 1/2) / W from +x towards +y."""
    d = np.asarray(jaxsh.latlong_directions(4, 8))
    assert d.shape == (4, 8, 3)
    theta = np.pi * 0.5 / 4
    np.testing.assert_allclose(d[0, 0], [np.sin(theta) * np.cos(np.pi / 8), np.sin(theta) * np.sin(np.pi / 8), np.cos(theta)])
    assert d[0, :, 2].min() > 0.9 and d[-1, :, 2].max() < -0.9
    # Column W/4 - 1/2 ... phi increases towards +y.
    assert d[2, 1, 1] > 0 and d[2, 5, 1] < 0
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-15)


@pytest.mark.parametrize("n", [1, 2, 5, 16, 33])
def test_fejer1_exact_for_polynomials(n):
    """Exact for z^k, k < n (independent closed form: 2/(k+1) for even k, 0 odd)."""
    w = jaxsh.fejer1_weights(n)
    z = np.cos(np.pi * (np.arange(n) + 0.5) / n)
    for k in range(n):
        want = 2.0 / (k + 1) if k % 2 == 0 else 0.0
        assert abs(np.dot(w, z**k) - want) < 1e-13


def test_fejer1_matches_ducc0_if_installed():
    ducc0 = pytest.importorskip("ducc0")
    for h in (7, 64):
        w = ducc0.sht.experimental.get_gridweights("F1", h) if hasattr(ducc0.sht, "experimental") else ducc0.sht.get_gridweights("F1", h)
        np.testing.assert_allclose(np.asarray(jaxsh.latlong_weights(h, 1))[:, 0], w, rtol=1e-12)


def test_latlong_weights_integrate_sh_exactly():
    h, w, lmax = 24, 48, 11
    d = jaxsh.latlong_directions(h, w)
    wt = np.asarray(jaxsh.latlong_weights(h, w))
    assert abs(wt.sum() - 4 * np.pi) < 1e-12
    y = np.asarray(jaxsh.real_sh(d, lmax)).reshape(-1, jaxsh.num_coeffs(lmax))
    gram = (y * wt.reshape(-1, 1)).T @ y
    np.testing.assert_allclose(gram, np.eye(jaxsh.num_coeffs(lmax)), atol=1e-13)


def test_plain_sin_weights_are_not_exact():
    """The reason for Fejér weights: sin(theta) dtheta dphi leaves O(1/H^2) errors."""
    h, w = 24, 48
    theta, _ = jaxsh.latlong_angles(h, w)
    plain = np.sin(theta) * (np.pi / h)
    assert abs(plain.sum() - 2.0) > 1e-4
    assert abs(jaxsh.fejer1_weights(h).sum() - 2.0) < 1e-14


def test_gauss_legendre_grid_exact():
    lmax = 9
    d, w = jaxsh.gauss_legendre_grid(lmax + 1, 2 * lmax + 2)
    assert d.shape == (lmax + 1, 2 * lmax + 2, 3) and w.shape == d.shape[:2]
    y = np.asarray(jaxsh.real_sh(d, lmax)).reshape(-1, jaxsh.num_coeffs(lmax))
    gram = (y * np.asarray(w).reshape(-1, 1)).T @ y
    np.testing.assert_allclose(gram, np.eye(jaxsh.num_coeffs(lmax)), atol=1e-13)
    assert float(d[0, 0, 2]) > float(d[-1, 0, 2])  # theta ascending


def test_angular_map_convention_and_solid_angle():
    s = 257
    d, sa, inside = jaxsh.angular_map_directions(s)
    d, sa, inside = np.asarray(d), np.asarray(sa), np.asarray(inside)
    c = s // 2
    np.testing.assert_allclose(d[c, c], [0, 0, -1], atol=1e-12)  # centre looks along -z
    assert d[c, -1, 0] > 0.99 * np.sin(np.pi * (1 - 1 / s)) - 1e-3  # right edge of the midline: u=1 -> +x side, near +z
    assert d[0, c, 1] >= 0 and d[-1, c, 1] <= 0  # top row is +y (v up)
    # right-most midline pixel: r ~ 1 - 1/s, angle ~ pi: direction close to +z
    assert d[c, -1, 2] > 0.99
    # solid angles: total 4 pi (pixel-centre rule, converges at O(1/S)).
    assert abs(sa.sum() - 4 * np.pi) / (4 * np.pi) < 2e-2
    # integrate z^2 (exact 4 pi / 3) and a band-limited function
    f = d[..., 2] ** 2
    assert abs((sa * f).sum() - 4 * np.pi / 3) / (4 * np.pi / 3) < 2e-2
    assert not inside[0, 0] and sa[0, 0] == 0
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1, atol=1e-12)


@pytest.mark.parametrize("bad", [0, -3, 2.5])
def test_grid_size_errors(bad):
    with pytest.raises(ValueError, match="height"):
        jaxsh.latlong_directions(bad, 4)
    with pytest.raises(ValueError, match="n_theta"):
        jaxsh.gauss_legendre_grid(bad, 4)


# ---------------------------------------------------------------- transforms


def _naive_synthesis(c, h, w):
    d = jaxsh.latlong_directions(h, w)
    y = np.asarray(jaxsh.real_sh(d, jaxsh.sh_degrees(0).size * 0 + int(np.sqrt(c.shape[0])) - 1))
    return np.einsum("hwn,n...->hw...", y, c)


@pytest.mark.parametrize("h,w,lmax", [(20, 40, 8), (17, 18, 8), (12, 7, 5), (1, 5, 3), (41, 84, 20), (9, 16, 12)])
def test_synthesis_equals_pointwise_evaluation(rng, h, w, lmax):
    c = rng.normal(size=(jaxsh.num_coeffs(lmax), 3))
    img = jaxsh.synthesize_latlong(c, h, w)
    assert img.shape == (h, w, 3)
    np.testing.assert_allclose(img, _naive_synthesis(c, h, w), atol=1e-12)
    img1 = jaxsh.synthesize_latlong(c[:, 0], h, w)
    assert img1.shape == (h, w)
    np.testing.assert_allclose(img1, np.asarray(img)[..., 0], atol=1e-13)


@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 3, 24]), st.integers(0, 1), st.integers(0, 3))
def test_round_trip_is_identity(seed, lmax, extra_h, extra_w):
    """analysis o synthesis = identity for lmax < H/2, W > 2 lmax."""
    rng = np.random.default_rng(seed)
    h, w = 2 * lmax + 1 + extra_h, 2 * lmax + 1 + extra_w
    c = rng.normal(size=(jaxsh.num_coeffs(lmax), 2))
    back = jaxsh.project_latlong(jaxsh.synthesize_latlong(c, h, w), lmax)
    np.testing.assert_allclose(back, c, atol=1e-12)


def test_projection_equals_quadrature(rng):
    """project_latlong = sum over pixels of f Y w (independent dense computation)."""
    h, w, lmax = 16, 24, 10
    img = rng.normal(size=(h, w))
    y = np.asarray(jaxsh.real_sh(jaxsh.latlong_directions(h, w), lmax))
    wt = np.asarray(jaxsh.latlong_weights(h, w))
    want = np.einsum("hwn,hw->n", y, img * wt)
    np.testing.assert_allclose(jaxsh.project_latlong(img, lmax, allow_aliasing=True), want, atol=1e-12)
    # also above the exact range (lmax > W/2 uses the full FFT with aliasing)
    want = np.einsum("hwn,hw->n", np.asarray(jaxsh.real_sh(jaxsh.latlong_directions(h, w), 14)), img * wt)
    np.testing.assert_allclose(jaxsh.project_latlong(img, 14, allow_aliasing=True), want, atol=1e-12)


def test_projection_of_smooth_function_converges():
    """A non-band-limited map: exp(z); its Y_00 coefficient is sqrt(4 pi) sinh(1)/1 ... closed form."""
    h, w = 64, 128
    d = np.asarray(jaxsh.latlong_directions(h, w))
    c = np.asarray(jaxsh.project_latlong(np.exp(d[..., 2]), 2))
    # int exp(z) Y00 = 2 pi * (e - 1/e) / sqrt(4 pi)
    assert abs(c[0] - 2 * np.pi * (np.e - 1 / np.e) / np.sqrt(4 * np.pi)) < 1e-12
    # int exp(z) Y10 = sqrt(3/4pi) 2 pi int z e^z dz = sqrt(3/4pi) 2 pi (2/e)
    assert abs(c[2] - np.sqrt(3 / (4 * np.pi)) * 2 * np.pi * 2 / np.e) < 1e-12
    np.testing.assert_allclose(c[[1, 3, 4, 5, 7, 8]], 0, atol=1e-13)


def test_transforms_float32(rng):
    lmax = 16
    c = rng.normal(size=(jaxsh.num_coeffs(lmax), 3)).astype(np.float32)
    img = jaxsh.synthesize_latlong(c, 40, 80)
    assert img.dtype == jnp.float32
    back = jaxsh.project_latlong(img, lmax)
    assert back.dtype == jnp.float32
    assert np.abs(np.asarray(back) - c).max() < 1e-4


def test_transforms_jit_grad(rng):
    lmax = 4
    img = jnp.asarray(rng.normal(size=(10, 20)))
    f = jax.jit(lambda x: jnp.sum(jaxsh.project_latlong(x, lmax) ** 2))
    g = jax.grad(f)(img)
    # d/dx sum c^2 = 2 sum_n c_n dc_n/dx, and dc_n/dx = Y_n w
    y = np.asarray(jaxsh.real_sh(jaxsh.latlong_directions(10, 20), lmax))
    wt = np.asarray(jaxsh.latlong_weights(10, 20))
    c = np.asarray(jaxsh.project_latlong(img, lmax))
    np.testing.assert_allclose(g, 2 * np.einsum("hwn,n->hw", y, c) * wt, atol=1e-12)


@pytest.mark.parametrize("shape", [(4,), (2, 3, 4, 5), ()])
def test_image_shape_errors(shape):
    with pytest.raises(ValueError, match=r"image.*\(H, W\) or \(H, W, C\)"):
        jaxsh.project_latlong(np.ones(shape), 2)


def test_synthesis_shape_errors():
    with pytest.raises(ValueError, match="coeffs"):
        jaxsh.synthesize_latlong(np.ones(8), 4, 4)
    with pytest.raises(ValueError, match="width"):
        jaxsh.synthesize_latlong(np.ones(9), 4, 0)


# ---------------------------------------------------------------- fit_sh


def test_fit_sh_recovers_band_limited(rng):
    lmax = 6
    d = random_dirs(rng, (400,))
    c = rng.normal(size=(jaxsh.num_coeffs(lmax), 3))
    v = np.asarray(jaxsh.real_sh(d, lmax)) @ c
    np.testing.assert_allclose(jaxsh.fit_sh(d, v, lmax), c, atol=1e-11)
    np.testing.assert_allclose(jaxsh.fit_sh(d, v[:, 0], lmax), c[:, 0], atol=1e-11)


def test_fit_sh_weights_and_ridge_against_normal_equations(rng):
    lmax = 3
    d = random_dirs(rng, (60,))
    v = rng.normal(size=60)
    w = rng.uniform(0.1, 2.0, size=60)
    lam = 0.3
    y = np.asarray(jaxsh.real_sh(d, lmax))
    want = np.linalg.solve(y.T @ (w[:, None] * y) + lam * np.eye(16), y.T @ (w * v))
    np.testing.assert_allclose(jaxsh.fit_sh(d, v, lmax, weights=w, ridge=lam), want, atol=1e-12)


def test_fit_sh_underdetermined_is_min_norm(rng):
    d = random_dirs(rng, (5,))
    v = rng.normal(size=5)
    c = np.asarray(jaxsh.fit_sh(d, v, 3))
    assert np.all(np.isfinite(c))
    np.testing.assert_allclose(np.asarray(jaxsh.real_sh(d, 3)) @ c, v, atol=1e-10)


def test_fit_sh_errors(rng):
    d = random_dirs(rng, (10,))
    with pytest.raises(ValueError, match=r"values.*\(10,\)"):
        jaxsh.fit_sh(d, np.ones(9), 2)
    with pytest.raises(ValueError, match=r"weights.*\(10,\)"):
        jaxsh.fit_sh(d, np.ones(10), 2, weights=np.ones(3))
    with pytest.raises(ValueError, match=r"dirs.*\(N, 3\)"):
        jaxsh.fit_sh(d[None], np.ones(10), 2)
    with pytest.raises(Exception, match="ridge"):
        jaxsh.fit_sh(d, np.ones(10), 2, ridge=-1.0).block_until_ready()


@pytest.mark.parametrize("shape,lmax", [((33, 60, 2), 12), ((8, 16, 1), 12), ((16, 2048, 3), 32)])
def test_row_dft_products_match_numpy_fft(shape, lmax):
    """The matrix-product row DFT of `project_latlong` against NumPy's FFT (an independent transform).

    Row j sits at phi_j = 2 pi (j + 1/2) / W, so the wanted sum is rfft(f)[m] e^{-i pi m / W};
    m beyond W/2 (8x16 at lmax 12) folds by aliasing, as the full FFT does.
    """
    from jaxsh._transforms import _row_dft_matmul

    f = np.random.default_rng(3).normal(size=shape)
    w = shape[1]
    m = np.arange(lmax + 1)
    want = np.fft.fft(f, axis=1)[:, m % w, :] * np.exp(-1j * np.pi * m / w)[None, :, None]
    re, im = (np.asarray(a) for a in _row_dft_matmul(jnp.asarray(f), lmax))
    scale = np.abs(f).sum(axis=1).max()
    np.testing.assert_allclose(re, want.real, atol=1e-14 * scale)
    np.testing.assert_allclose(im, want.imag, atol=1e-14 * scale)


def test_fft_row_path_agrees_with_the_product_path(monkeypatch):
    """Above 16 log2 W orders `project_latlong` takes an FFT per row instead: both paths, one answer."""
    import jaxsh._transforms as tr

    img = np.random.default_rng(4).normal(size=(24, 48, 3))
    a = np.asarray(jaxsh.project_latlong(img, 10))
    jax.clear_caches()
    monkeypatch.setattr(tr, "_use_dft_matmul", lambda lmax, w: False)
    b = np.asarray(jaxsh.project_latlong(img, 10))
    jax.clear_caches()
    np.testing.assert_allclose(a, b, atol=1e-13 * np.abs(a).max())
    assert not np.array_equal(a, b)  # two different programs ran (else the test compared one path with itself)


def test_project_latlong_accelerator_branch(monkeypatch, rng):
    """Off the CPU, the row DFT of `project_latlong` runs all rows as one batched product instead of a loop over
    the rows (an H200: 13.6 ms → 0.63 ms at 1024 × 2048 × 3, lmax 32). Same coefficients, and the exact round
    trip of a band-limited map."""
    from jaxsh._transforms import _row_dft_matmul

    c = rng.normal(size=(17**2, 2))
    img = np.asarray(jaxsh.synthesize_latlong(c, 64, 128))
    cpu = [np.asarray(a) for a in jax.jit(lambda f: _row_dft_matmul(f, 16))(img)]
    accelerator_branches(monkeypatch)
    acc = [np.asarray(a) for a in jax.jit(lambda f: _row_dft_matmul(f, 16))(img)]
    for a, b in zip(acc, cpu):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())
    got = np.asarray(jax.jit(lambda f: jaxsh._transforms._project.__wrapped__(f, 16))(img))  # un-jitted body
    np.testing.assert_allclose(got, c, rtol=0, atol=1e-12)
