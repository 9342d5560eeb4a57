"""`factorize`'s passes over the pixels (session 29): the stacked Gram product, the search subset's blocks from the
all-pixel pass (`_subset_first`, `accumulate_gram(split=...)`), and the refinement's rows kept apart from their
Fresnel factor (`_Joint.f`, `_rows_dot_many`, `_coef_rows`). References: NumPy sums over the design rows, the
`MirrorTable` quadrature the subset's blocks came from before, and the renderer (`solvers.predict`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import solvers
from solvers import _factorize as F
from solvers._normal_equations import accumulate_gram, eq25_rows


def _directions(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _observations(rng, n_px, transfer=False, rvis=False):
    n, v = _directions(rng, n_px), _directions(rng, n_px)
    v = np.where(np.sum(n * v, 1, keepdims=True) < -0.5, -v, v)  # most pixels seen from the front, some not
    w = rng.uniform(0.5, 1.5, n_px) * (rng.uniform(size=n_px) > 0.1)  # some zero weights
    f = lambda a: None if a is None else jnp.asarray(a)  # noqa: E731
    return solvers.Observations(f(n), f(v), f(rng.uniform(size=(n_px, 3))), f(w),
                                f(rng.normal(size=(n_px, 9)) if transfer else None), None,
                                f(rng.uniform(size=n_px) if rvis else None), None,
                                jnp.zeros(n_px, jnp.int32), jnp.arange(n_px), ((1, n_px),))


def _numpy_blocks(o, mu, lmax, sel=slice(None)):
    """dd, ds, ss, db, sb, bb, count of eq. 25 by NumPy sums over the rows of the pixels `sel` (one shot, no chunks)."""
    d, s = (np.asarray(a) for a in jax.jit(eq25_rows, static_argnums=(6, 7))(
        o.normals, o.views, o.transfer, o.reflected_visibility, mu, None, lmax, True))
    w, b = np.asarray(o.weights)[sel], np.asarray(o.values)[sel]
    d, s = d[:, sel], s[:, sel]
    return {"dd": (d * w) @ d.T, "ds": (d * w) @ s.T, "ss": (s * w) @ s.T, "db": (d * w) @ b, "sb": (s * w) @ b,
            "bb": np.sum(w[:, None] * b * b, 0), "count": float(np.count_nonzero(w > 0))}, (d, s)


@pytest.mark.parametrize("transfer, rvis", [(False, False), (True, True)])
def test_accumulate_gram_stacked_product_and_split_equal_numpy_sums(rng, transfer, rvis):
    """Every block of the one stacked product per chunk, the first `split` chunks' blocks from the same pass, and
    the rows (diffuse, specular) against NumPy sums of the design rows; the padding's columns are the +z pixel's
    rows (finite), and `split` outside the chunks is an error naming it."""
    o = _observations(rng, 2900, transfer, rvis)
    mu, lmax, chunk, split = jnp.asarray(1.7), 4, 512, 3
    run = jax.jit(accumulate_gram, static_argnums=(8, 9, 10, 11))
    g, (rows_d, rows_s), first = run(o.normals, o.views, o.values, o.weights, o.transfer, o.reflected_visibility,
                                     mu, None, lmax, chunk, True, split)
    ref, (d, s) = _numpy_blocks(o, mu, lmax)
    ref_first, _ = _numpy_blocks(o, mu, lmax, slice(0, split * chunk))
    for got, want in ((g, ref), (first, ref_first)):
        for field, r in want.items():
            x = np.asarray(getattr(got, field))
            assert np.max(np.abs(x - r)) <= 1e-13 * max(np.max(np.abs(r)), 1.0), field
    assert float(first.count) < float(g.count)  # the first chunks alone, not every pixel
    pad = (-2900) % chunk
    assert rows_d.shape == (9, 2900 + pad) and rows_s.shape == ((lmax + 1) ** 2, 2900 + pad)
    np.testing.assert_allclose(np.asarray(rows_d)[:, :2900], d, rtol=1e-13, atol=1e-14)  # chunked against one shot
    np.testing.assert_allclose(np.asarray(rows_s)[:, :2900], s, rtol=1e-13, atol=1e-14)
    assert np.all(np.isfinite(np.asarray(rows_s)[:, 2900:]))
    for bad in (0, -1, 7):  # 2900 pixels: 6 chunks of 512
        with pytest.raises(ValueError, match="split"):
            run(o.normals, o.views, o.values, o.weights, None, None, mu, None, lmax, chunk, False, bad)
    # the rows of the chunks from `rows_from` on only (skipped chunks write nothing), the sums unchanged
    run_from = jax.jit(accumulate_gram, static_argnums=(8, 9, 10, 11, 12))
    g2, (rows_d2, rows_s2), first2 = run_from(o.normals, o.views, o.values, o.weights, o.transfer,
                                              o.reflected_visibility, mu, None, lmax, chunk, True, split, split)
    assert rows_d2.shape == (9, 2900 + pad - split * chunk) and rows_s2.shape[1] == rows_d2.shape[1]
    np.testing.assert_array_equal(np.asarray(rows_d2), np.asarray(rows_d)[:, split * chunk:])
    np.testing.assert_array_equal(np.asarray(rows_s2), np.asarray(rows_s)[:, split * chunk:])
    for field in ("ss", "sb", "count"):
        np.testing.assert_array_equal(np.asarray(getattr(g2, field)), np.asarray(getattr(g, field)))
        np.testing.assert_array_equal(np.asarray(getattr(first2, field)), np.asarray(getattr(first, field)))
    for bad in (-1, 6):
        with pytest.raises(ValueError, match="rows_from"):
            run_from(o.normals, o.views, o.values, o.weights, None, None, mu, None, lmax, chunk, True, None, bad)
    for width in (chunk - 1, split * chunk + 1):  # known rows narrower than a chunk, or wider than the chunks skipped
        known = (jnp.zeros((width, 9)), jnp.zeros(((lmax + 1) ** 2, width)), jnp.zeros(width))
        with pytest.raises(ValueError, match="known"):
            run_from(o.normals, o.views, o.values, o.weights, None, None, mu, None, lmax, chunk, True, split, split,
                     known)


def test_subset_first_order_puts_the_subset_in_whole_chunks_first():
    n, chunk = 23, 4
    idx = np.array([2, 3, 5, 11, 17, 22])
    order, split, joint, pos = F._subset_first(n, idx, chunk)
    order, joint, pos = np.asarray(order), np.asarray(joint), np.asarray(pos)
    rest = np.setdiff1d(np.arange(n), idx)
    assert split == 2 and order.shape == (2 * 4 + n - 6,)
    np.testing.assert_array_equal(order[:4], idx[:4])
    # the weight-0 pixel fills the subset's last chunk, first: its pixels are then the table's last columns
    np.testing.assert_array_equal(order[4:6], [n, n])
    np.testing.assert_array_equal(order[6:8], idx[4:])
    np.testing.assert_array_equal(order[8:], rest)
    # the refinement's order: the subset (rows from its table), then the pixels of the chunks after it
    np.testing.assert_array_equal(joint, np.concatenate([idx, rest]))
    np.testing.assert_array_equal(joint[pos], np.arange(n))
    # a subset of whole chunks needs no filler
    order2, split2, _, _ = F._subset_first(n, idx[:4], chunk)
    assert split2 == 1 and n not in np.asarray(order2)


def test_permuted_filler_is_a_weightless_valid_sample(rng):
    o = _observations(rng, 50, transfer=True, rvis=True)
    p = F._permuted(o, jnp.asarray([3, 50, 7]))
    np.testing.assert_array_equal(np.asarray(p.normals)[1], [0, 0, 1])
    np.testing.assert_array_equal(np.asarray(p.views)[1], [0, 0, 1])
    assert float(p.weights[1]) == 0 and np.all(np.asarray(p.values)[1] == 0)
    np.testing.assert_array_equal(np.asarray(p.values)[[0, 2]], np.asarray(o.values)[[3, 7]])
    np.testing.assert_array_equal(np.asarray(p.transfer)[[0, 2]], np.asarray(o.transfer)[[3, 7]])


def test_pad_joint_keeps_every_field_with_its_pixel(rng):
    """The all-pixel `_Joint`'s fields (weights, data, normals, views, the source's shadow column) follow the rows'
    subset-first order: position `pos[i]` holds pixel i's values, and the filler and padding weigh nothing."""
    o = _observations(rng, 300, transfer=True, rvis=True)
    o = solvers.Observations(o.normals, o.views, o.values, o.weights, o.transfer, jnp.asarray(rng.uniform(size=(300, 2))),
                             o.reflected_visibility, None, o.view_index, o.pixel_index, o.image_shapes)
    idx = np.sort(rng.choice(300, 70, replace=False))
    _, _, joint, pos = F._subset_first(300, idx, 64)
    width = 70 + 256  # the subset's columns, then the other 230 pixels' chunks
    bl9 = F._all_pixel_blocks(o, jnp.asarray(1.5), 4, 64, 1e-12, False)[0]
    bl, w, b, n, v, fvis = F._pad_joint(o, bl9, width, 1, joint)
    p = np.asarray(pos)
    for got, want in ((w, o.weights), (b, o.values), (n, o.normals), (v, o.views), (fvis, o.fast_visibility[:, 1])):
        assert got.shape[0] == width
        np.testing.assert_array_equal(np.asarray(got)[p], np.asarray(want))
    others = np.setdiff1d(np.arange(width), p)
    assert others.size == width - 300 and np.all(np.asarray(w)[others] == 0)


def _subset_of(rng, n_px, n_sub):
    """Observations of `n_px` pixels (some seen from behind, some of weight 0), a sorted search subset of `n_sub`
    of them, and that subset: `(o, idx, sub)`."""
    o = _observations(rng, n_px, rvis=True)
    idx = np.sort(rng.choice(n_px, n_sub, replace=False))
    return o, idx, o.subset(idx)


def _pass_with_subset_first(o, idx, mu, lmax, chunk, tab=None):
    """The all-pixel pass with the subset first (`_subset_first`, rows after the subset's chunks; with `tab`, the
    subset's `MirrorTable`, the subset chunks' rows taken from it): `(blocks, rows, subset blocks, joint, pos)`."""
    order, split, joint, pos = F._subset_first(o.n_samples, idx, chunk)
    return (*F._all_pixel_blocks(o, mu, lmax, chunk, 1e-12, True, order, split, tab), joint, pos)


@pytest.mark.parametrize("table_rows", [False, True])
def test_all_pixel_pass_gives_the_subset_blocks_the_table_gave(rng, table_rows):
    """The refinement's blocks on the search subset at the final mu come from the all-pixel pass (the subset's
    pixels first); they used to come from the subset's `MirrorTable` (`_mu_blocks`): equal to rounding, and
    the all-pixel blocks equal a pass in the original order. With `table_rows` the subset chunks' rows are the
    table's (`accumulate_gram`'s `known`; 1800 pixels: three whole chunks of 512 and a partial one, filler first),
    not evaluated: the same blocks and rows."""
    o, idx, sub, mu, lmax, chunk = *_subset_of(rng, 5000, 1800), jnp.asarray(1.45), 6, 512
    tab = F._mirror_table_jit(sub, lmax)
    bl, rows, bl_sub, _, _ = _pass_with_subset_first(o, idx, mu, lmax, chunk, tab if table_rows else None)
    via_table = F._mu_blocks(tab, jnp.full((9,), mu), lmax, 1e-12)
    plain, _, none = F._all_pixel_blocks(o, mu, lmax, chunk, 1e-12, False)
    assert none is None
    for field in ("dd", "ds", "ss", "db", "sb", "bb", "count"):
        for got, want in ((bl_sub, via_table), (bl, plain)):
            x, r = np.asarray(getattr(got.g, field)), np.asarray(getattr(want.g, field))
            assert x.shape == r.shape and x.shape[0] == 9, field  # batched like a round of the mu search
            assert np.max(np.abs(x - r)) <= 1e-12 * max(np.max(np.abs(r)), 1.0), field
    # the rows are those of the pixels after the subset's chunks, in `order`: the other pixels in their order
    _, (d, s) = _numpy_blocks(o, mu, lmax)
    rest = np.setdiff1d(np.arange(5000), idx)
    assert rows[0].shape[1] == rows[1].shape[1] == -(-rest.size // chunk) * chunk
    np.testing.assert_allclose(np.asarray(rows[1])[:, : rest.size], s[:, rest], rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(rows[0])[:, : rest.size], d[:, rest], rtol=0, atol=1e-13)


def test_rows_products_with_and_without_the_fresnel_factor(rng):
    """`_rows_dot`, `_rows_dot_many` and `_coef_rows` against products with the rows formed (`_Joint.rows`), with
    the specular factor `f` (the table's rows) and without it (the all-pixel rows)."""
    o = _observations(rng, 700)
    mu, lmax = jnp.asarray(1.6), 5
    direct = F._joint_jit(o, None, mu, lmax, 256, 1e-12, None)
    tab = F._mirror_table_jit(o, lmax)
    via = F._joint_from_table(o, tab, direct.bl, mu, lmax, F._K0())
    assert direct.f is None and via.f is not None and via.rows_s is tab.ys  # shared with the table, not copied
    np.testing.assert_allclose(np.asarray(via.rows), np.asarray(direct.rows), rtol=1e-12, atol=1e-13)
    x = jnp.asarray(rng.normal(size=(4, 700)))
    coef = jnp.asarray(rng.normal(size=(3, 9 + (lmax + 1) ** 2)))
    for jt in (direct, via):
        rows = np.asarray(jt.rows)
        np.testing.assert_allclose(np.asarray(jax.jit(F._rows_dot_many)(jt, x)), np.asarray(x) @ rows.T, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(jax.jit(F._rows_dot)(jt, x[0])), rows @ np.asarray(x[0]), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(jax.jit(F._coef_rows)(jt, coef)), np.asarray(coef) @ rows, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="specular rows"):
        F._joint_from_table(o, tab, direct.bl, mu, lmax - 1, F._K0())


def test_two_segment_joint_equals_the_rows_of_all_pixels(rng):
    """The refinement's `_Joint` on all pixels: the subset's rows from its `MirrorTable` (with the Fresnel factor
    `f`), then the other pixels' rows from the all-pixel pass. Its rows, in the `joint` order, are `eq25_rows` of
    every pixel (NumPy reference: the rows formed in one shot), its padding weighs nothing, and `_rows_dot`,
    `_rows_dot_many`, `_coef_rows` equal products with the formed rows."""
    o, idx, sub, mu, lmax, chunk = *_subset_of(rng, 3000, 1100), jnp.asarray(1.45), 5, 512
    bl, rows, bl_sub, joint, pos = _pass_with_subset_first(o, idx, mu, lmax, chunk)
    first = F._joint_from_table(sub, F._mirror_table_jit(sub, lmax), bl_sub, mu, lmax, F._K0())
    jt = F._joint_padded(o, bl, rows, None, joint, first)
    assert jt.rows_s is first.rows_s and jt.rows_s2 is rows[1]  # shared, not copied
    _, (d, s) = _numpy_blocks(o, mu, lmax)
    full = np.asarray(jt.rows)
    n_all = full.shape[1]
    assert n_all == 1100 + rows[0].shape[1] and jt.w.shape == (n_all,)
    p = np.asarray(pos)
    np.testing.assert_allclose(full[:, p], np.concatenate([d, s]), rtol=0, atol=1e-12)
    pad = np.setdiff1d(np.arange(n_all), p)
    assert pad.size == n_all - 3000 and np.all(np.asarray(jt.w)[pad] == 0)
    np.testing.assert_array_equal(np.asarray(jt.b)[p], np.asarray(o.values))
    x = jnp.asarray(rng.normal(size=(3, n_all)))
    coef = jnp.asarray(rng.normal(size=(2, 9 + (lmax + 1) ** 2)))
    tols = {"rtol": 1e-12, "atol": 1e-11}
    np.testing.assert_allclose(np.asarray(jax.jit(F._rows_dot_many)(jt, x)), np.asarray(x) @ full.T, **tols)
    np.testing.assert_allclose(np.asarray(jax.jit(F._rows_dot)(jt, x[1])), full @ np.asarray(x[1]), **tols)
    np.testing.assert_allclose(np.asarray(jax.jit(F._coef_rows)(jt, coef)), np.asarray(coef) @ full, **tols)


@pytest.fixture(scope="module")
def sphere():
    cap = solvers.sphere_capture(solvers.TorranceSparrow(jnp.asarray([0.6, 0.5, 0.4]), jnp.asarray([0.3] * 3),
                                                         jnp.asarray(1.6), jnp.asarray(0.15)),
                                 size=40, n_views=3, noise=0.01, seed=3, lighting_lmax=12)
    return cap, solvers.observations(cap.gbuffers, cap.images)


@pytest.mark.parametrize("refine_mu", [False, True])
def test_factorize_on_a_subset_returns_fitted_in_the_pixels_order(sphere, refine_mu):
    """With a search subset the all-pixel rows are in the subset-first order; `fitted` comes back in the samples'
    own order: it equals the renderer's images at the estimate (another program, exact SH sums) and its
    weighted residual is `rms`."""
    cap, obs = sphere
    r = solvers.factorize(obs, 8, search_pixels=1500, refine_mu=refine_mu)
    assert solvers.status_name(r.status) == "converged"
    for img, gb in zip(obs.to_images(r.fitted), cap.gbuffers):
        ref = np.asarray(solvers.predict(r.brdf, r.lighting, gb.normal, gb.view, mask=gb.mask, method="exact"))
        m = np.asarray(gb.mask)
        np.testing.assert_allclose(img[m], ref[m], rtol=1e-9, atol=1e-12 * np.abs(ref[m]).max())
    w, res = np.asarray(obs.weights), np.asarray(r.fitted) - np.asarray(obs.values)
    n_pos = np.count_nonzero(w > 0)
    np.testing.assert_allclose(np.sqrt(np.sum(w[:, None] * res**2) / (n_pos * 3)), float(r.rms), rtol=1e-9)


def test_joint_window_holds_stage_one_mu_in_its_middle_and_shares_its_batch(rng):
    """The joint mu search's first window: the 9 Chebyshev points of an interval of width 2 w around t1, t1 itself
    (bitwise) in the middle unless the window had to be shifted into stage 1's range. Stage 1 then reads its blocks
    from the window's batch (t1 first, `_WINDOW_ORDER`): equal to the batch of 9 copies of its mu it used before."""
    w, (lo, hi) = F._MU_JOINT_HALF_WIDTH, F._MU_T_RANGE
    # (the 2nd, 3rd: the interval's middle is not t1)
    for t1 in (-0.8, -1.9141484640510031, -1.3770710475691386, lo + w + 1e-9):
        ts = F._joint_window(t1)
        ref = t1 - w * np.cos(np.pi * np.arange(9) / 8)
        assert ts[4] == t1 and np.allclose(ts, ref, rtol=0, atol=1e-14)
    for t1 in (lo + 0.1, hi - 0.2):  # shifted: t1 is not in the middle
        ts = F._joint_window(t1)
        assert ts[0] >= lo and ts[-1] <= hi + 1e-12 and ts[4] != t1
    np.testing.assert_array_equal(F._WINDOW_ORDER[F._WINDOW_SLOT], np.arange(9))
    o = _observations(rng, 900)
    tab = F._mirror_table_jit(o, 5)
    t1 = -0.8
    ts = F._joint_window(t1)
    win = F._mu_blocks(tab, jnp.asarray(1.0 + np.exp(ts[F._WINDOW_ORDER])), 5, 1e-12)
    copies = F._mu_blocks(tab, jnp.full((9,), 1.0 + np.exp(t1)), 5, 1e-12)
    for field in ("ds", "ss", "sb"):
        a, b = np.asarray(getattr(win.g, field))[0], np.asarray(getattr(copies.g, field))[0]
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14 * np.max(np.abs(b)))
    np.testing.assert_allclose(np.asarray(F._golden_batch(win)[1]), np.asarray(F._golden_batch(copies)[1]), rtol=1e-12)
