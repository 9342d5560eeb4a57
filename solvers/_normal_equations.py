"""The normal-equation engine: Gram blocks over pixel chunks, pseudo-inverses, small eliminations, covariances.

Every linear (or linear-given-the-nonlinear-parameters) least-squares
problem of the solvers goes through here:

- `eq25_rows`, `accumulate_gram`: the design rows of R&H eq. 25 (diffuse
  block $d$, 9 columns; specular block $s$, $(l^*+1)^2$ columns) and the sums
  $\\sum_x w\\,d^Td$, $d^Ts$, $s^Ts$, $d^Tb$, $s^Tb$, $b^Tb$ accumulated over
  pixel chunks by `lax.scan` (memory $O(n^2)$ whatever the pixel count), used
  by `inverse_lighting` and by the final solves of `factorize`.
- `mirror_table`, `grams_at_mus`: the same blocks at many Fresnel indices for
  one pixel set (`factorize`'s search over $\\mu$), the specular block by an
  exact quadrature of the projected point set.
- `channel_system`, `eig_solve`: the per-channel normal equations
  $A_c = K_{d,c}\\,d + K_{s,c}\\,s$ and their eigen-solve with singular values,
  rank, standard errors and the null space flagged (`inverse_lighting`).
- `pinv_psd`: the eigen pseudo-inverse of a PSD block (the $l > 2$ block
  of the factorization's Schur complement).
- `solve_spd_small`, `inverse_spd_small`: Gaussian elimination of
  small SPD systems in plain XLA ops (a rolled pivot loop).
- `solve_sym2`, `solve_sym2_min_norm`, `nonneg_sym2`, `inverse_sym2_diag`, `solve_grouped_shared`,
  `solve_grouped_shared_nonneg`: the $2\\times2$
  $(K_d, K_s)$ eliminations of `fit_brdf` (per channel, per texel, and the
  Schur complement of one shared $K_s$ with a $K_d$ per texel, unconstrained and nonnegative:
  Newton steps on its active set in a `while_loop`).
- `covariance_from_jacobian` (and `covariance_from_gram`, from $J^TJ$): $\\mathrm{cov} = s^2 (J^TJ)^{+}$,
  $s^2 = \\mathrm{RSS}/(n - p)$, with undetermined directions flagged.

**No LAPACK inside loops.** jaxlib runs Cholesky/LU/eigh as LAPACK custom
calls; inside XLA:CPU loops (`lax.scan`, `while_loop`, the simplex) those
stalled or deadlocked on re-execution on the development machine (measured),
and OpenBLAS threads thrashed against XLA's (hence `blas_single_thread`
around every solver). So the functions called inside searches
(`solve_spd_small`, `solve_sym2`, `solve_grouped_shared`, `solve_grouped_shared_nonneg`) are plain
elementwise/matmul arithmetic; the eigendecompositions (`eig_solve`,
`pinv_psd`, `covariance_from_jacobian`) run once per solve, outside the
iterative loops.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

import jaxsh

from ._lapack import map_lapack, unbatched

# --------------------------------------------------------------------------- Gram blocks of eq. 25


class Gram(eqx.Module):
    """Sums over pixels of the two row blocks d (diffuse, 9 columns) and s (specular, n columns) of eq. 25.

    The fields are arrays; a `Gram` of `int | None` can also serve as the `jax.vmap` axis spec of one,
    hence the annotations.
    """

    dd: jax.Array | int | None  # (9, 9)
    ds: jax.Array | int | None  # (9, n)
    ss: jax.Array | int | None  # (n, n)
    db: jax.Array | int | None  # (9, C)
    sb: jax.Array | int | None  # (n, C)
    bb: jax.Array | int | None  # (C,)
    count: jax.Array | int | None  # () pixels with positive weight


def eq25_rows(n, v, transfer, rvis, mu, filt, lmax: int, coeffs_first: bool = False):
    """Diffuse rows `(chunk, 9)` and specular rows `(chunk, n_coeffs)` of R&H eq. 25 (`coeffs_first`: `(9, chunk)`
    and `(n_coeffs, chunk)`, made in that layout).

    Diffuse: $\\Lambda_l\\hat\\rho_l Y_{lm}(n)$, $l \\le 2$ (eq. 21), or the
    transfer vector $T_{lm}$ (sec. 6.4); specular: $F(\\mu,\\theta_o) Y_{lm}(R)$
    times the reflected-ray visibility, times `filt` (the lobe filter, or None).
    Pixels seen from behind ($n\\cdot v \\le 0$) get zero rows.
    """
    dt = n.dtype
    l2 = min(lmax, 2)
    if transfer is not None:
        d = transfer[:, : (l2 + 1) ** 2].T
    else:
        a = jaxsh.lambertian_spectrum(l2, dt)[jaxsh.sh_degrees(l2)]
        d = jaxsh.real_sh(n, l2, coeffs_first=True) * a[:, None]
    d = jnp.pad(d, ((0, 9 - d.shape[0]), (0, 0)))
    cos_o = jnp.sum(n * v, -1)
    vis = cos_o > 0
    cos_o = jnp.where(vis, cos_o, 1.0)
    f = jnp.ones_like(cos_o) if mu is None else jaxsh.fresnel_normalized(cos_o, mu)
    r = jaxsh.reflect(v, n)
    y = jaxsh.real_sh(r, lmax, coeffs_first=True)
    if filt is not None:
        y = y * filt[:, None]
    scale = f if rvis is None else f * rvis
    s = y * jnp.where(vis, scale, 0.0)[None, :]
    d = jnp.where(vis[None, :], d, 0.0)
    return (d, s) if coeffs_first else (d.T, s.T)


def pixel_chunks(n, v, chunk: int, *fields):
    """`n`, `v` `(N, 3)` and each of `fields` (`(N, ...)` or None) cut into `(N / chunk, chunk, ...)` blocks, padded
    to a multiple of `chunk`: the directions with +z (valid unit vectors), the other fields with 0 (weight 0 for
    weights). Returns a tuple in the order of the arguments."""
    pad = (-n.shape[0]) % chunk
    up = jnp.zeros((pad, 3), n.dtype).at[:, 2].set(1.0)

    def cut(a):
        return None if a is None else jnp.pad(a, ((0, pad),) + ((0, 0),) * (a.ndim - 1)).reshape((-1, chunk) + a.shape[1:])

    return (jnp.concatenate([n, up]).reshape(-1, chunk, 3), jnp.concatenate([v, up]).reshape(-1, chunk, 3),
            *(cut(a) for a in fields))


def accumulate_gram(n, v, b, w, transfer, rvis, mu, filt, lmax: int, chunk: int, rows: bool = False,
                    split: int | None = None, rows_from: int = 0, known=None):
    """Accumulate the eq.-25 normal-equation blocks over pixel chunks (`lax.scan`; zero-weight padding).

    With `rows`, also return the design rows of all pixels, diffuse and specular, pixels last:
    `((9, N + pad), (n_coeffs, N + pad))` (`eq25_rows` with `coeffs_first`; the `pad = -N % chunk` last columns are the rows of
    the padding's +z pixels, not 0: their weight 0 keeps them out of every sum, and callers drop them after a
    product; a slice to N would copy the whole array again), from the same pass (`factorize`'s refinement on all pixels
    reads them). With `split` (a number of chunks, static), also the blocks of the first `split · chunk` pixels
    alone, from the same pass (`factorize`: its search subset put first). `rows_from` (static): the rows of the
    chunks from this one on only, `((9, N + pad - rows_from · chunk), ...)` (`factorize` takes its subset's rows
    from the subset's `MirrorTable`: 31 % less to write at 3 × 256²). `known`: `(d (P, 9), y (n_coeffs, P),
    scale (P,))` or None, the rows of the first `rows_from` chunks' pixels as a `MirrorTable` holds them (diffuse
    rows pixels first; the harmonics and their factor, `eq25_rows`' specular rows being `y * scale`), taken instead
    of evaluated, `chunk <= P <= rows_from · chunk` (without `filt`): chunk `j` reads columns `j · chunk` on, the
    last one the last `chunk` columns, so a last partial chunk must hold its pixels at its end (`factorize` puts
    its weight-0 filler first there). Returns `Gram`, then `rows` with `rows`, then the first pixels' `Gram` with
    `split`: a tuple when there is more than the `Gram`."""
    npx = n.shape[0]
    pad = (-npx) % chunk
    n_p, v_p, b_p, w_p, t_p, r_p = pixel_chunks(n, v, chunk, b, w, transfer, rvis)
    nc = (lmax + 1) ** 2
    c = b.shape[1]
    dt = n.dtype
    k = 9 + nc + c

    if split is not None and not 0 < split <= n_p.shape[0]:
        raise ValueError(f"`split` must be in [1, {n_p.shape[0]}] (chunks of {chunk} pixels), got {split}")
    if not 0 <= rows_from < n_p.shape[0]:
        raise ValueError(f"`rows_from` must be in [0, {n_p.shape[0] - 1}] (chunks of {chunk} pixels), got {rows_from}")
    if known is not None and (filt is not None or not chunk <= known[1].shape[1] <= rows_from * chunk):
        raise ValueError(f"`known` rows must span between one chunk ({chunk}) and `rows_from` chunks "
                         f"({rows_from * chunk}) of pixels, without `filt`, got {known[1].shape[1]}")

    def rows_of(i, nn, vv, tt, rr):
        """The chunk's eq.-25 rows: from `known` before `rows_from` (both branches compiled, one run), else
        evaluated (`eq25_rows`). Taken from the table for `factorize`'s 10 subset chunks of 32 at 3 x 256^2:
        26 ms less for the pass."""
        evaluate = lambda: eq25_rows(nn, vv, tt, rr, mu, filt, lmax, coeffs_first=True)  # noqa: E731
        if known is None:
            return evaluate()
        kd, ky, ks = known

        def take():
            at = jnp.minimum(i * chunk, ky.shape[1] - chunk)
            cols = lambda a: jax.lax.dynamic_slice_in_dim(a, at, chunk, a.ndim - 1)  # noqa: E731
            return jax.lax.dynamic_slice_in_dim(kd, at, chunk, 0).T, cols(ky) * cols(ks)[None, :]

        return jax.lax.cond(i < rows_from, take, evaluate)

    def step(carry, xs):
        acc, count, buf, first, i = carry
        nn, vv, bb, ww, tt, rr = xs
        d, s = rows_of(i, nn, vv, tt, rr)  # (9, chunk), (nc, chunk)
        # one product of the stacked [d; s; b^T] with its weighted self gives every block (dd, ds, ss, db, sb, and
        # bb on the diagonal of its last C x C): five products per chunk took 251 ms at 3 x 256^2, lmax 12, this 226
        r = jnp.concatenate([d, s, bb.T], 0)  # (k, chunk)
        acc = acc + jax.lax.dot_general(r * ww[None, :], r, (((1,), (1,)), ((), ())))
        count = count + jnp.sum((ww > 0).astype(dt))
        if rows:  # written in place into the (9, N + pad), (nc, N + pad) carry (stacked scan outputs and a transpose: 2x slower)
            # chunks before `rows_from` write nothing (a `lax.cond`, which XLA runs in place: 23-26 ms less than all
            # rows at 3 x 256^2, 10 of 32 chunks skipped; writing them into the first slot for the next chunk to
            # overwrite saved 11 ms)
            at = (jnp.zeros_like(i), (i - rows_from) * chunk)

            def write(bf):
                return jax.lax.dynamic_update_slice(bf[0], d, at), jax.lax.dynamic_update_slice(bf[1], s, at)

            buf = write(buf) if rows_from == 0 else jax.lax.cond(i >= rows_from, write, lambda bf: bf, buf)
        if split is not None:  # the sums after the first `split` chunks
            first = jax.tree_util.tree_map(lambda a, f: jnp.where(i + 1 == split, a, f), (acc, count), first)
        return (acc, count, buf, first, i + 1), None

    def blocks(acc, count):
        e = 9 + nc
        return Gram(acc[:9, :9], acc[:9, 9:e], acc[9:e, 9:e], acc[:9, e:], acc[9:e, e:], jnp.diagonal(acc[e:, e:]),
                    count)

    zero = (jnp.zeros((k, k), dt), jnp.zeros((), dt))
    width = npx + pad - rows_from * chunk
    buf = (jnp.zeros((9, width), dt), jnp.zeros((nc, width), dt)) if rows else None
    init = (*zero, buf, None if split is None else zero, jnp.zeros((), jnp.int32))
    (acc, count, buf, first, _), _ = jax.lax.scan(step, init, (n_p, v_p, b_p, w_p, t_p, r_p))
    out = (blocks(acc, count),) + ((buf,) if rows else ()) + (() if split is None else (blocks(*first),))
    return out if len(out) > 1 else out[0]


class MirrorTable(eqx.Module):
    """The $\\mu$-independent parts of eq. 25's rows for one pixel set (`mirror_table`), for `grams_at_mus`.

    The table has `N + Q` columns: the `N` pixels, then the `Q` nodes of the Gauss-Legendre grid of
    `grams_at_mus` as extra columns of weight 0 (their harmonics come from the same evaluation as the
    pixels'; they add nothing to any sum). `y2` `(n_2, N + Q)`: $Y_{LM}$ for $L \\le 2l^*$ of the mirror
    directions, then of the nodes (its first $n = (l^*+1)^2$ rows are the specular rows' harmonics); `yq`
    `(Q, n_2)`: the nodes' harmonics (a copy of `y2`'s last columns, transposed) and `wq` `(Q,)` the grid's
    weights (made once per table, not per call); `ys` `(n, N)`: the pixels' $Y_{lm}$, $l \\le l^*$ (a contiguous
    copy of `y2[:n, :N]`: the specular rows of eq. 25 without their Fresnel factor and visibility, which
    `factorize`'s refinement multiplies for every $\\mu$); `d` `(N + Q, 9)`: the diffuse rows; `s_scale` `(N + Q,)`:
    the reflected-ray visibility, 0 where the pixel is seen from behind; `cos_o` `(N + Q,)`:
    $\\cos\\theta_o$ (1 where seen from behind); `b` `(N + Q, C)`, `w` `(N + Q,)` (0 on the nodes).
    """

    y2: jax.Array
    yq: jax.Array
    wq: jax.Array
    ys: jax.Array
    d: jax.Array
    s_scale: jax.Array
    cos_o: jax.Array
    b: jax.Array
    w: jax.Array


def mirror_table(n, v, b, w, transfer, rvis, lmax: int) -> MirrorTable:
    """`MirrorTable` of eq. 25's rows (`eq25_rows` without the Fresnel factor); memory $O(N ((2l^*+1)^2 + (l^*+1)^2))$.

    The harmonics of the mirror directions and of the quadrature nodes are one `jaxsh.real_sh` call (one
    copy of its loop in the compiled program: each copy cost ~0.2 s of XLA compilation)."""
    d, _ = eq25_rows(n, v, transfer, None, None, None, min(lmax, 2), coeffs_first=True)
    cos_o = jnp.sum(n * v, -1)
    vis = cos_o > 0
    scale = jnp.where(vis, 1.0 if rvis is None else rvis, 0.0).astype(n.dtype)
    grid, wq = jaxsh.gauss_legendre_grid(2 * lmax + 1, 4 * lmax + 1, dtype=n.dtype)
    nodes = grid.reshape(-1, 3)
    q = nodes.shape[0]
    y2 = jaxsh.real_sh(jnp.concatenate([jaxsh.reflect(v, n), nodes]), 2 * lmax, coeffs_first=True)
    pad = lambda a, value=0.0: jnp.concatenate([a, jnp.full((q,) + a.shape[1:], value, a.dtype)])  # noqa: E731
    ys = y2[: (lmax + 1) ** 2, : n.shape[0]]
    return MirrorTable(y2, y2[:, -q:].T, wq.reshape(-1), ys, pad(d.T), pad(scale), pad(jnp.where(vis, cos_o, 1.0), 1.0),
                       pad(b), pad(w))


def grams_at_mus(tab: MirrorTable, mus, lmax: int) -> Gram:
    """The eq.-25 `Gram` blocks (unfiltered) at each Fresnel index of `mus` `(K,)`: every field gets a leading K.

    Equal to `accumulate_gram` at each $\\mu$ (to rounding; `tests/test_inverse.py`), at a fraction of the
    cost when several $\\mu$ share one pixel set. The specular block is
    $SS = \\sum_i g_i\\,Y(R_i)\\,Y(R_i)^T$ with $g_i = w_i F(\\mu, \\theta_{o,i})^2 V_i^2$. A product
    $Y_{lm}Y_{l'm'}$ with $l, l' \\le l^*$ is a polynomial of degree $\\le 2l^*$ on the sphere, so
    $\\sum_i g_i Y_{lm}Y_{l'm'}(R_i) = \\int Y_{lm}Y_{l'm'} H\\,d\\omega$ with
    $H = \\sum_{L \\le 2l^*} h_{LM} Y_{LM}$, $h_{LM} = \\sum_i g_i Y_{LM}(R_i)$ (the projection of the weighted
    point set), and the integrand, of degree $\\le 4l^*$, is integrated exactly by the Gauss-Legendre grid of
    $(2l^*+1) \\times (4l^*+1)$ nodes (`jaxsh.gauss_legendre_grid`). Per $\\mu$ that costs
    $O(N(2l^*+1)^2 + Q(l^*+1)^4)$, $Q = (2l^*+1)(4l^*+1)$, instead of $O(N(l^*+1)^4)$: at $l^* = 12$ and
    $N = 40{,}000$, 9 $\\mu$ in 81 ms against 9 × 56 ms for `accumulate_gram` (measured; the table itself,
    made once per pixel set, 136 ms). The other blocks are plain sums; the DS and SB blocks of all $\\mu$ are
    one product with the $l \\le l^*$ harmonics, accumulated over chunks of pixels (`_weighted_products`).
    """
    nc = (lmax + 1) ** 2
    dt = tab.b.dtype
    k, c = mus.shape[0], tab.b.shape[1]
    f = jax.vmap(lambda mu: jaxsh.fresnel_normalized(tab.cos_o, mu))(mus)  # (K, N)
    wf = (tab.w * tab.s_scale)[None, :] * f  # w F V: the s rows' factor times the weight
    g2 = wf * (tab.s_scale[None, :] * f)  # w F^2 V^2
    # the DS and SB blocks of every mu: Y_{<= l*} against [d, b] weighted by each mu's w F V
    lo = _weighted_products(tab.y2, nc, wf, jnp.concatenate([tab.d, tab.b], 1).T)  # (n, K, 9 + C)
    hq = (tab.yq @ (tab.y2 @ g2.T)) * tab.wq[:, None]  # (Q, K): H at the nodes times the weights
    yq = tab.yq[:, :nc]
    ss = jnp.einsum("qa,qk,qb->kab", yq, hq, yq)
    ds = lo[:, :, :9].transpose(1, 2, 0)
    sb = lo[:, :, 9:].transpose(1, 0, 2)
    wd = tab.d * tab.w[:, None]
    dd, db = wd.T @ tab.d, wd.T @ tab.b
    bb = jnp.sum(tab.w[:, None] * tab.b * tab.b, 0)
    count = jnp.sum((tab.w > 0).astype(dt))
    rep = lambda a: jnp.broadcast_to(a, (k,) + a.shape)  # noqa: E731
    return Gram(rep(dd), ds, ss, rep(db), sb, rep(bb), rep(count))


_PRODUCT_CHUNK = 2048  # pixels per step of `_weighted_products`


def _weighted_products(y, n: int, wf, m):
    """$\\sum_i Y_{a}(i)\\,wf_k(i)\\,m_j(i)$ for the first `n` rows $a$ of `y` `(n_2, N)`, every row $k$ of `wf`
    `(K, N)` and $j$ of `m` `(J, N)`: `(n, K, J)`.

    One product of `y[:n]` with the `(N, K·J)` weighted right-hand side, accumulated over chunks of
    `_PRODUCT_CHUNK` pixels (a `fori_loop`), so that neither the slice `y[:n]` (a copy of the table's leading
    rows) nor the whole right-hand side is ever formed: at $N = 40{,}000$, $K = 9$, $l^* = 12$ the blocks of
    one round took 57-75 ms as one product and take 22 ms so (fresh buffers of tens of MB each cost their
    page faults on every call; docs/performance.md)."""
    npx = y.shape[1]
    kj = wf.shape[0] * m.shape[0]
    p = _PRODUCT_CHUNK

    def part(yc, wc, mc):
        rhs = (wc[:, None, :] * mc[None, :, :]).reshape(kj, -1)
        return jax.lax.dot_general(yc, rhs, (((1,), (1,)), ((), ())))

    def body(i, acc):
        cols = lambda a: jax.lax.dynamic_slice_in_dim(a, i * p, p, 1)  # noqa: E731
        return acc + part(jax.lax.dynamic_slice(y, (0, i * p), (n, p)), cols(wf), cols(m))

    nb = npx // p
    acc = jnp.zeros((n, kj), y.dtype)
    if nb:
        acc = jax.lax.fori_loop(0, nb, body, acc)
    t0 = nb * p
    if t0 < npx:
        acc = acc + part(y[:n, t0:], wf[:, t0:], m[:, t0:])
    return acc.reshape(n, wf.shape[0], m.shape[0])


def channel_system(g: Gram, kd, ks):
    """Per-channel normal matrix and right-hand side for $A_c = K_{d,c} d + K_{s,c} s$: `(C, n, n)`, `(C, n)`."""
    nc = g.ss.shape[0]
    k = min(9, nc)
    dd = jnp.zeros((nc, nc), g.ss.dtype).at[:k, :k].set(g.dd[:k, :k])
    ds = jnp.zeros((nc, nc), g.ss.dtype).at[:k, :].set(g.ds[:k, :])
    db = jnp.zeros((nc, g.db.shape[1]), g.ss.dtype).at[:k].set(g.db[:k])
    ata = (kd**2)[:, None, None] * dd[None] + (kd * ks)[:, None, None] * (ds + ds.T)[None] + (ks**2)[:, None, None] * g.ss[None]
    atb = (kd[None, :] * db + ks[None, :] * g.sb).T  # (C, n)
    return ata, atb


# --------------------------------------------------------------------------- eigen solves (outside loops)


def eigh_stack(a):
    """`jnp.linalg.eigh` of each matrix of the stack `a` `(K, n, n)`: on a CPU one matrix at a time, elsewhere one
    batched call (`solvers._lapack`: a batched CPU LAPACK call can deadlock)."""
    return map_lapack(_eigh, a)


def _eigh(a):
    """`jnp.linalg.eigh(a)` of the array alone (`unbatched` traces every argument: no keyword defaults)."""
    return jnp.linalg.eigh(a)


def eig_solve(ata, atb, bb, count, rcond, ridge, rss_of=None):
    """Eigen-solve batched normal equations $A^TA x = A^Tb$ (minimum norm, eigenvalues below `rcond`·max dropped).

    Returns `x` `(C, n)`, standard errors `se` `(C, n)` ($s^2 = \\mathrm{RSS}/(n_{obs} - \\mathrm{rank})$;
    `inf` where a coefficient has weight in the null space, and every one when $n_{obs} \\le$ rank: no degree
    of freedom is left to estimate $s^2$), `determined` `(C, n)`, the singular values of $A$ `(C, n)`
    descending, `rss` `(C,)` and `rank` `(C,)`. The RSS is $b^Tb - 2x^TA^Tb + x^TA^TAx$ (exact for any $x$
    in exact arithmetic), or `rss_of(x, that, bb)` when given: the normal-equation form cancels, its rounding is
    about $\\epsilon\\,b^Tb$, which in float32 made `rms` and every standard error wrong (1.18× at 1 % noise,
    50× at 0.01 %, 1000× on exact data) and in float64 gave an RSS of 0 on exact data; `inverse_lighting`
    passes the residual's own sum over the pixels.
    """
    # ascending; one call per channel on a CPU (`eigh_stack`: batched LAPACK calls deadlock there)
    evals, evecs = eigh_stack(ata)
    top = evals[:, -1:]
    keep = evals > rcond * top
    inv = jnp.where(keep, 1.0 / (jnp.where(keep, evals, 1.0) + ridge), 0.0)
    proj = jnp.einsum("cji,cj->ci", evecs, atb)
    x = jnp.einsum("cij,cj->ci", evecs, inv * proj)
    rss = bb - 2 * jnp.sum(x * atb, -1) + jnp.einsum("ci,cij,cj->c", x, ata, x)
    rss = jnp.maximum(rss, 0.0)
    if rss_of is not None:
        rss = rss_of(x, rss, bb)
    n_free = jnp.sum(keep, -1).astype(rss.dtype)
    dof = count - n_free
    s2 = rss / jnp.maximum(dof, 1.0)
    var = jnp.einsum("cij,cj->ci", evecs**2, inv**2 * jnp.where(keep, evals, 0.0))
    null_weight = jnp.einsum("cij,cj->ci", evecs**2, (~keep).astype(evecs.dtype))
    determined = null_weight < 1e-6
    se = jnp.where(determined & (dof > 0)[:, None], jnp.sqrt(s2[:, None] * var), jnp.inf)
    sv = jnp.sqrt(jnp.clip(evals[:, ::-1], 0.0))
    return x, se, determined, sv, rss, jnp.sum(keep, -1)


def pinv_psd(a, rcond, half: bool = False):
    """Pseudo-inverse of a symmetric PSD matrix by eigendecomposition (eigenvalues < `rcond`·max dropped).

    With `half`, also its square-root factor $H = \\Lambda_+^{-1/2}V^T$ (rows of dropped eigenpairs zero):
    $\\mathrm{pinv} = H^TH$. Returns `pinv` or `(pinv, H)`. A stack `(K, m, m)` goes through `eigh_stack` (one
    matrix at a time on a CPU: a batched CPU `eigh` can deadlock)."""
    evals, evecs = eigh_stack(a) if jnp.ndim(a) == 3 else jnp.linalg.eigh(a)
    keep = evals > rcond * jnp.max(evals, -1, keepdims=True)
    inv = jnp.where(keep, 1.0 / jnp.where(keep, evals, 1.0), 0.0)
    p = (evecs * inv[..., None, :]) @ jnp.swapaxes(evecs, -1, -2)
    if not half:
        return p
    return p, jnp.sqrt(inv)[..., :, None] * jnp.swapaxes(evecs, -1, -2)


def covariance_from_jacobian(J, rss, nobs, n_par):
    """$\\mathrm{cov} = s^2 (J^TJ)^{+}$, $s^2 = \\mathrm{RSS}/\\max(n - p, 1)$, and the standard errors.

    The columns of $J$ are scaled to unit norm first, $J = \\tilde J D$ with
    $D = \\mathrm{diag}(\\lVert J_{:,j}\\rVert)$, and
    $\\mathrm{cov} = s^2 D^{-1}(\\tilde J^T\\tilde J)^{+}D^{-1}$: the same matrix when
    $J$ has full rank, but the rank decision no longer depends on the
    parameters' units (images 1000× brighter scale the $K_d$, $K_s$ columns
    and not the μ, σ ones: the unscaled $J^TJ$'s condition number grew like
    the square of that factor, and in float32 every parameter came out
    undetermined). Eigenvalues of $\\tilde J^T\\tilde J$ below
    $\\epsilon\\,p\\,\\lambda_{max}$ are dropped; a parameter with weight in
    those directions (or with a zero column) is undetermined and gets an
    infinite standard error. Returns `(cov, se)`.
    """
    return covariance_from_gram(J.T @ J, rss, nobs, n_par)


def covariance_from_gram(g, rss, nobs, n_par):
    """`covariance_from_jacobian` from the Gram matrix $G = J^TJ$ `(p, p)` (for callers that sum it without
    forming $J$): the scaling $D = \\mathrm{diag}(G)^{1/2}$, $\\tilde J^T\\tilde J = D^{-1}GD^{-1}$, the same rank
    rule and the same standard errors."""
    dt = g.dtype
    norms = jnp.sqrt(jnp.clip(jnp.diagonal(g), 0.0))
    zero = norms <= jnp.finfo(dt).tiny
    d = jnp.where(zero, 1.0, norms)
    jtj = g / (d[:, None] * d[None, :])
    s2 = rss / jnp.maximum(nobs - n_par, 1.0)
    evals, evecs = unbatched(_eigh)(jtj)  # a `vmap`ped fit (`fit_many`): one at a time on a CPU
    tiny = evals <= jnp.finfo(dt).eps * jnp.max(evals) * jtj.shape[0]
    inv = jnp.where(tiny, 0.0, 1.0 / jnp.where(tiny, 1.0, evals))
    cov = (evecs * inv[None, :]) @ evecs.T * s2 / (d[:, None] * d[None, :])
    # squared weight in the dropped directions, as `eig_solve` (an amplitude threshold of 1e-6 is below float32's
    # eigenvector rounding eps/gap: determined, merely correlated parameters were flagged, 38 of 40 draws at
    # correlation 0.995 beside an exactly dependent pair)
    undetermined = zero | ((evecs**2) @ tiny.astype(dt) > 1e-6)
    se = jnp.where(undetermined, jnp.inf, jnp.sqrt(jnp.clip(jnp.diag(cov), 0.0)))
    return cov, se


# --------------------------------------------------------------------------- small eliminations (loop-safe)


def solve_spd_small(m, r):
    """Solve SPD systems $m x = r$, batched over leading axes, by Gaussian elimination in a `lax.fori_loop`.

    For the 9×9 / 10×10 Schur complements inside the searches: plain XLA ops, no LAPACK
    custom call (module docstring). The system is solved in its Jacobi-scaled form
    $(SmS)(S^{-1}x) = Sr$, $S = \\mathrm{diag}(m_{ii}^{-1/2})$ (1 where $m_{ii} \\le 0$), with a jitter of
    $16\\epsilon$ on that unit diagonal, which keeps exactly singular systems finite. (The jitter was
    $16\\epsilon\\max_j m_{jj}$ on the unscaled diagonal: it moved an entry of $10^{-13}$ of the largest by
    3.5 % and one of $3.5 \\cdot 10^{-15}$ by all of it; a 10×10 system with diagonal entries from $10^{-24}$
    to $10^{24}$ came out wrong in every digit, `tests/test_normal_equations_audit.py`.) The pivot loop is rolled (one body for the k pivots): unrolled in
    Python it was the same arithmetic but ~0.17 s of XLA compilation per copy, and `factorize`'s programs
    hold about a dozen copies (measured: the stage-1 golden search compiled in 1.28 s unrolled, 0.79 s
    rolled, and ran in 7.4 ms against 6.5 ms)."""
    k = m.shape[-1]
    diag = jnp.diagonal(m, axis1=-2, axis2=-1)
    pos = diag > 0
    sc = jnp.where(pos, jax.lax.rsqrt(jnp.where(pos, diag, 1.0)), 1.0)  # (..., k)
    m = m * sc[..., :, None] * sc[..., None, :]
    m = m + (jnp.finfo(m.dtype).eps * 16) * jnp.eye(k, dtype=m.dtype).reshape((1,) * (m.ndim - 2) + (k, k))
    a = jnp.concatenate([m, (r * sc)[..., None]], -1)
    rows = jnp.arange(k)

    def pivot(i, a):
        row = jnp.take(a, i, axis=-2)  # (..., k + 1)
        piv = jnp.take(row, i, axis=-1)
        piv = jnp.where(jnp.abs(piv) > 0, piv, jnp.finfo(m.dtype).tiny)
        row = row / piv[..., None]
        a = a - jnp.take(a, i, axis=-1)[..., :, None] * row[..., None, :]
        return jnp.where((rows == i)[:, None], row[..., None, :], a)

    return jax.lax.fori_loop(0, k, pivot, a)[..., :, -1] * sc


def inverse_spd_small(m):
    """Inverse of one small SPD matrix `(k, k)` by `solve_spd_small` on the columns of the identity."""
    eye = jnp.eye(m.shape[-1], dtype=m.dtype)
    return jax.vmap(lambda e: solve_spd_small(m, e))(eye)


def solve_sym2(a11, a12, a22, r1, r2):
    """Solve $[[a_{11}, a_{12}], [a_{12}, a_{22}]]\\,x = r$ elementwise (Cramer); returns `x1, x2, bad`.

    `bad` flags near-singular systems ($\\det \\le 10^3\\epsilon\\,a_{11}a_{22}$ or a
    non-positive diagonal), whose solution is returned as 0. Solved in the Jacobi-scaled form (unit diagonal,
    $c = a_{12}/\\sqrt{a_{11}a_{22}}$, $\\det = (1-c)(1+c)$), so the result does not depend on the units of the
    weights: the unscaled determinant $a_{11}a_{22} - a_{12}^2$ underflows to 0 at weights of $10^{-200}$ and
    overflows at $10^{200}$ in float64 (at $10^{\\mp 20}$ in float32)."""
    ok = (a11 > 0) & (a22 > 0)
    s1 = jnp.sqrt(jnp.where(ok, a11, 1.0))
    s2 = jnp.sqrt(jnp.where(ok, a22, 1.0))
    c = a12 / s1 / s2
    det = (1.0 - c) * (1.0 + c)
    eps = jnp.finfo(det.dtype).eps
    bad = ~(det > 1e3 * eps) | ~ok
    det_s = jnp.where(bad, 1.0, det)
    y1, y2 = r1 / s1, r2 / s2
    x1 = (y1 - c * y2) / det_s / s1
    x2 = (y2 - c * y1) / det_s / s2
    return jnp.where(bad, 0.0, x1), jnp.where(bad, 0.0, x2), bad


def solve_sym2_min_norm(a11, a12, a22, r1, r2):
    """`solve_sym2`, with the minimum-norm least-squares solution $A^+ r$ where it flags the system singular.

    A singular symmetric PSD $2\\times2$ $A$ has rank $\\le 1$, $A = \\lambda u u^T$, so
    $A^+ = A / (\\mathrm{tr}\\,A)^2$ (0 for $A = 0$; formed as $((A/\\mathrm{tr})\\,r)/\\mathrm{tr}$, which neither
    under- nor overflows where $A$ and $r$ do not). `fit_brdf`'s homogeneous inner solve uses it: under
    lighting that makes the diffuse and specular images proportional (uniform lighting, thesis sec. 3.2.2) the
    data still fix $K_d E + K_s S$, and the profiled residual is that fit's, not the data's. Returns `x1, x2, bad`.
    """
    x1, x2, bad = solve_sym2(a11, a12, a22, r1, r2)
    tr = a11 + a22
    pos = tr > 0
    t = jnp.where(pos, tr, 1.0)
    p1 = jnp.where(pos, (a11 / t * r1 + a12 / t * r2) / t, 0.0)
    p2 = jnp.where(pos, (a12 / t * r1 + a22 / t * r2) / t, 0.0)
    return jnp.where(bad, p1, x1), jnp.where(bad, p2, x2), bad


def nonneg_sym2(x1, x2, a11, a22, r1, r2):
    """The solution of $\\min_{x \\ge 0} x^T A x - 2 r^T x$ for a PSD $2\\times2$ $A$, given the unconstrained
    (or minimum-norm) minimizer `x1, x2`: kept where both are $\\ge 0$; otherwise the minimum lies on an edge,
    $x = (\\max(r_1, 0)/a_{11}, 0)$ or $(0, \\max(r_2, 0)/a_{22})$, whichever lowers the objective more
    ($r_1^2/a_{11}$ against $r_2^2/a_{22}$). Elementwise; returns `x1, x2`."""
    p1, p2 = jnp.maximum(r1, 0.0), jnp.maximum(r2, 0.0)
    o1 = jnp.where(a11 > 0, p1 / jnp.where(a11 > 0, a11, 1.0), 0.0)
    o2 = jnp.where(a22 > 0, p2 / jnp.where(a22 > 0, a22, 1.0), 0.0)
    first = o1 * p1 >= o2 * p2
    neg = (x1 < 0) | (x2 < 0)
    return jnp.where(neg, jnp.where(first, o1, 0.0), x1), jnp.where(neg, jnp.where(first, 0.0, o2), x2)


def inverse_sym2_diag(a11, a12, a22):
    """Diagonal of $[[a_{11}, a_{12}], [a_{12}, a_{22}]]^{-1}$ elementwise: `(v11, v22, ok)`, in the Jacobi-scaled form
    of `solve_sym2`, $c = a_{12}/\\sqrt{a_{11}a_{22}}$, $v_{11} = 1/(a_{11}(1-c)(1+c))$: no under- or overflow of
    $a_{11}a_{22}$ at extreme units (weights scaled by 1e±170 in float64, 1e±20 in float32, made every texel's
    standard error infinite). A zero row and column ($a_{22} = 0$, hence $a_{12} = 0$) leaves the other unknown
    determined: $v_{11} = 1/a_{11}$, $v_{22} = \\infty$ (and vice versa), with `ok` False."""
    p1, p2 = a11 > 0, a22 > 0
    s1 = jnp.sqrt(jnp.where(p1, a11, 1.0))
    s2 = jnp.sqrt(jnp.where(p2, a22, 1.0))
    c = jnp.where(p1 & p2, a12 / s1 / s2, 0.0)
    det = (1.0 - c) * (1.0 + c)
    ok = p1 & p2 & (det > 0)
    det_s = jnp.where(ok, det, 1.0)
    inf = jnp.asarray(jnp.inf, det.dtype)
    v1 = jnp.where(ok, 1.0 / det_s / s1 / s1, jnp.where(p1 & ~p2, 1.0 / s1 / s1, inf))
    v2 = jnp.where(ok, 1.0 / det_s / s2 / s2, jnp.where(p2 & ~p1, 1.0 / s2 / s2, inf))
    return v1, v2, ok


def solve_grouped_shared(dd, ds, ss, db, sb):
    """One unknown per group $t$ ($x_t$) and one shared ($y$), per channel, by the Schur complement.

    Normal equations $dd_t x_t + ds_t y = db_t$, $\\sum_t ds_t x_t + (\\sum_t ss_t) y = \\sum_t sb_t$
    with inputs `(T, C)`: $y = (\\sum sb - \\sum ds\\,db/dd)/(\\sum ss - \\sum ds^2/dd)$, then
    $x_t = (db_t - ds_t y)/dd_t$ (0 for a group with $dd_t = 0$). Returns `x (T, C)`, `y (C,)`, `bad (C,)`
    (a vanishing Schur complement)."""
    dd_s = jnp.where(dd > 0, dd, 1.0)
    num = jnp.sum(sb, 0) - jnp.sum(jnp.where(dd > 0, ds * db / dd_s, 0.0), 0)
    den = jnp.sum(ss, 0) - jnp.sum(jnp.where(dd > 0, ds * ds / dd_s, 0.0), 0)
    bad = ~(den > 1e3 * jnp.finfo(den.dtype).eps * jnp.sum(ss, 0))
    y = jnp.where(bad, 0.0, num / jnp.where(bad, 1.0, den))
    x = jnp.where(dd > 0, (db - y[None, :] * ds) / dd_s, 0.0)
    return x, y, bad


def solve_grouped_shared_nonneg(dd, ds, ss, db, sb, max_iter: int = 64):
    """`solve_grouped_shared` with $x_t \\ge 0$, $y \\ge 0$: the nonnegative least-squares solution.

    For a fixed $y$ the best $x_t$ is $\\max(db_t - ds_t y, 0)/dd_t$ (0 for $dd_t = 0$); the objective minimized
    over the $x_t$ is convex in $y$, with the half-derivative
    $G(y) = y\\,(\\sum ss - \\sum_{A(y)} c_t) - (\\sum sb - \\sum_{A(y)} a_t)$, $a_t = ds_t\\,db_t/dd_t$,
    $c_t = ds_t^2/dd_t$, over the active groups $A(y) = \\{t: db_t - ds_t y > 0\\}$. With $ds_t \\ge 0$
    (nonnegative unit images and weights) groups only leave $A$ as $y$ grows, so $G$ is piecewise linear,
    increasing and convex, and $G \\ge$ its all-active line, whose root is the unconstrained $y_0$. Newton's
    method from $y_0$ (each step the root of the current piece) then descends monotonically to the root of $G$
    and stops, exactly, when the active set repeats (a `while_loop` of elementwise sums, at most `max_iter`
    steps; usually none or a few); a root below 0 gives $y = 0$. Returns `x (T, C)`, `y (C,)`, `bad (C,)`
    (a vanishing Schur complement)."""
    dt = dd.dtype
    pos = dd > 0
    dd_s = jnp.where(pos, dd, 1.0)
    a = jnp.where(pos, ds * db / dd_s, 0.0)
    c = jnp.where(pos, ds * ds / dd_s, 0.0)
    s_ss, s_sb = jnp.sum(ss, 0), jnp.sum(sb, 0)
    tol = 1e3 * jnp.finfo(dt).eps * s_ss

    def piece(act):  # the root of G's line over the active groups `act`
        den = s_ss - jnp.sum(jnp.where(act, c, 0.0), 0)
        num = s_sb - jnp.sum(jnp.where(act, a, 0.0), 0)
        bad = ~(den > tol)
        return jnp.where(bad, 0.0, num / jnp.where(bad, 1.0, den)), bad

    def active(y):
        return pos & (db - ds * y[None, :] > 0)

    def cond(state):
        _, act, prev, _, it = state
        return jnp.any(act != prev) & (it < max_iter)

    def body(state):
        y, act, _, bad, it = state
        y1, bad1 = piece(act)
        y1 = jnp.where(bad1, y, y1)
        return y1, active(y1), act, bad | bad1, it + 1

    y0, bad0 = piece(pos)
    y, _, _, bad, _ = jax.lax.while_loop(cond, body, (y0, active(y0), pos, bad0, jnp.zeros((), jnp.int32)))
    y = jnp.maximum(y, 0.0)
    x = jnp.where(pos, jnp.maximum(db - y[None, :] * ds, 0.0) / dd_s, 0.0)
    return x, y, bad
