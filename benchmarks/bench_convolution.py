"""Benchmark jaxsh's reflection-as-convolution routines against plain NumPy (CPU, one process).

Run from the repository root with the project's venv::

    python benchmarks/bench_convolution.py            # full run (~1 min on 2 cores)
    python benchmarks/bench_convolution.py --quick    # reduced sizes (~30 s, mostly compile time)

Options: ``--quick`` (smaller problems), ``--only {irradiance,brdf,convolve,lights}``,
``--seed N``. The script enables float64 in JAX (``jax_enable_x64``); the
library itself never does.

Timings are wall-clock on the host CPU. "first" is the first call (for JAX:
trace + compile + run), "warm" is the minimum of >= 3 runs after a warm-up
call (fast calls are repeated up to 30 times within ~0.3 s); the NumPy peers
are timed the same way. The ratio column is ``jaxsh time / peer time`` for the
same work, so < 1 means jaxsh is faster.

1. Irradiance (Ramamoorthi & Hanrahan 2001, "An efficient representation for
   irradiance environment maps") at 10^6 random unit normals (10^5 with
   --quick) from 9 RGB lighting coefficients, shape (9, 3), float64 and float32:
   * ``jaxsh.irradiance(L, normals)`` (jit inside; called as a user would).
   * NumPy, the paper's closed form (its eq. 13) with the published 6-digit
     constants c1=0.429043, c2=0.511664, c3=0.743125, c4=0.886227,
     c5=0.247708, evaluated term by term with broadcasting.
   * NumPy, the paper's matrix form E = n^T M n (homogeneous n = (x, y, z, 1),
     one 4x4 M per colour channel), as one (N, 4) @ (4, 12) product.
   The 9 coefficients are in jaxsh's flat order l*l+l+m (L00, L1-1, L10, L11,
   L2-2, L2-1, L20, L21, L22); jaxsh's real SH have the paper's signs
   (Y11 ~ x, Y1-1 ~ y, Y2-2 ~ xy, Y2-1 ~ yz, Y21 ~ xz, Y22 ~ x^2-y^2; checked
   at start-up). The accuracy columns compare with the float64 closed form:
   jaxsh uses the exact constants (pi * Y normalisation), so the float64
   difference is the ~1e-6 relative rounding of the published constants.
   float32 rows run with jax_enable_x64 switched off (``jax.enable_x64(False)``),
   as a float32 user would run them.

2. Isotropic BRDF projection rho_lpq (R&H 2001 eq. 8) at lmax 16 of the
   Torrance-Sparrow transfer ``jaxsh.torrance_sparrow(...) * cos(theta_i)``
   (kd=0.3, ks=0.5, mu=1.6, sigma=0.35; built with ``jaxsh.local_directions``
   as in tests/test_convolution.py), for (n_theta, n_phi) = (64, 64) and
   (128, 128) (only (64, 64) with --quick):
   * ``jaxsh.brdf_sh_coefficients(transfer, 16, n_theta, n_phi)`` called
     eagerly (op by op; its model functions are jitted inside), as documented.
   * the same inside ``jax.jit`` with kd, ks, mu, sigma as traced arguments
     (how a fit over BRDF parameters would call it).
   * NumPy peer, the same quadrature written directly: Gauss-Legendre nodes in
     cos(theta) on [0, 1], the Torrance-Sparrow model in NumPy (same formula:
     exact unpolarised Fresnel at theta_o normalised by F(0), Gaussian in the
     half-angle, no G), ``np.fft.rfft`` over delta-phi,
     ``scipy.special.sph_harm_y`` for N_lq P_l^q(cos theta), and
     ``np.einsum(..., optimize=True)``. Everything (nodes, tables, transfer)
     is recomputed on every call on both sides.
   "of which: transfer" rows time evaluating the transfer function on the
   (n_theta, n_theta, n_phi) grid alone (jaxsh model functions, eagerly and
   in jax.jit, vs NumPy; the NumPy version broadcasts over 1-D angle axes and
   evaluates the Fresnel factor on the theta_o axis only, jaxsh's models take
   full (..., 3) direction arrays).
   The agreement column is the max abs difference of the two rho arrays.
   Also ``jaxsh.brdf_incident_coefficients(transfer, theta_o=0.7, 16)`` (its
   defaults n_theta=96, n_phi=128) vs the same quadrature in NumPy.

3. Convolution + synthesis: a lmax-32 RGB lighting filtered by a Phong
   spectrum (``jaxsh.phong_spectrum(20, 32)``) and evaluated on the pixel
   centres of a 256x512 lat-long map (128x256 with --quick):
   * ``jaxsh.synthesize_latlong(jaxsh.convolve(L, A), H, W)`` (jit inside
     synthesize_latlong; called as a user would).
   * the dense NumPy route ``Y @ (A_l L_lm)`` with the (H*W, 1089) matrix Y
     of real SH at the pixel centres precomputed once (built with
     ``jaxsh.real_sh``; building it is timed separately and not included in
     the warm time). Y is 1.1 GB in float64 at 256x512.

4. Lighting from sources, one call per source, as a light stage's images
   are each lit by their own (lmax 16, float64): 100 directional sources
   through ``jaxsh.directional_light_sh`` and 20 disks through
   ``jaxsh.disk_light_sh``, each call with new values of the same shapes;
   "first" is the first source (compilation), "warm" the mean of the others
   per source. Peer: SciPy per source, the real SH at the direction from
   ``scipy.special.sph_harm_y`` (docs/conventions.md's real convention) times
   the energy; for a disk, its zonal closed form with
   ``scipy.special.eval_legendre`` (R&H's Λ_l and [P_{l-1} - P_{l+1}](cos r)).
   Before session 21 each jaxsh call traced and compiled its loop over l
   again: 0.13-0.17 s per source.

Other processes on the machine add noise (the load average at start is
printed): on a quiet machine treat ratios within ~20% as equal; under load
(load average > number of cores) single numbers can move by 2x between runs.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import sys
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402
from scipy.special import sph_harm_y  # noqa: E402

import jaxsh  # noqa: E402

warnings.filterwarnings("ignore", message=".*64-bit precision.*")
warnings.filterwarnings("ignore", category=FutureWarning)


# --------------------------------------------------------------------------
# timing helpers (same protocol as bench_sh.py)
# --------------------------------------------------------------------------


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import (  # noqa: E402,F401
    MAX_REPEATS, MIN_TOTAL, Table, _block, add_hugepages_option, apply_hugepages, fmt_e, fmt_t, malloc_line, ratio,
    time_jax, time_np,
)


def unit_dirs(rng, n, dtype):
    x = rng.normal(size=(n, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x.astype(dtype)


# --------------------------------------------------------------------------
# 1. irradiance: NumPy peers (R&H 2001, irradiance environment maps)
# --------------------------------------------------------------------------

C1, C2, C3, C4, C5 = 0.429043, 0.511664, 0.743125, 0.886227, 0.247708


def irradiance_closed_form(L, n):
    """Eq. 13 of R&H 2001 ("An efficient representation..."), term by term.

    L: (9, C) in flat order l*l+l+m; n: (N, 3) unit normals. Returns (N, C).
    """
    L00, L1m1, L10, L11, L2m2, L2m1, L20, L21, L22 = L
    x, y, z = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    return (C1 * L22 * (x * x - y * y) + C3 * L20 * (z * z) + C4 * L00 - C5 * L20
            + 2 * C1 * (L2m2 * (x * y) + L21 * (x * z) + L2m1 * (y * z))
            + 2 * C2 * (L11 * x + L1m1 * y + L10 * z))


def irradiance_matrix(L):
    """The paper's symmetric 4x4 matrix M per channel: (C, 4, 4)."""
    L00, L1m1, L10, L11, L2m2, L2m1, L20, L21, L22 = L
    return np.stack([
        np.stack([C1 * L22, C1 * L2m2, C1 * L21, C2 * L11], -1),
        np.stack([C1 * L2m2, -C1 * L22, C1 * L2m1, C2 * L1m1], -1),
        np.stack([C1 * L21, C1 * L2m1, C3 * L20, C2 * L10], -1),
        np.stack([C2 * L11, C2 * L1m1, C2 * L10, C4 * L00 - C5 * L20], -1),
    ], -2)


def irradiance_matrix_form(L, n):
    """E = n^T M n with homogeneous n, all channels in one (N, 4) @ (4, 4C) product."""
    M = irradiance_matrix(L)  # (C, 4, 4)
    C = M.shape[0]
    nh = np.concatenate([n, np.ones((n.shape[0], 1), n.dtype)], axis=1)  # (N, 4)
    t = (nh @ np.transpose(M, (1, 2, 0)).reshape(4, 4 * C)).reshape(-1, 4, C)  # (n^T M)_j per channel
    return (t * nh[:, :, None]).sum(axis=1)


def check_sign_convention():
    """jaxsh's real Y_lm (l <= 2) equal the paper's polynomials (same signs), to the 6 printed digits."""
    rng = np.random.default_rng(7)
    d = unit_dirs(rng, 64, np.float64)
    x, y, z = d.T
    paper = np.stack([0.282095 + 0 * x, 0.488603 * y, 0.488603 * z, 0.488603 * x, 1.092548 * x * y,
                      1.092548 * y * z, 0.315392 * (3 * z * z - 1), 1.092548 * x * z, 0.546274 * (x * x - y * y)],
                     -1)
    ours = np.asarray(jaxsh.real_sh(jnp.asarray(d), 2))
    err = np.abs(ours - paper).max()
    assert err < 5e-6, f"real SH convention differs from R&H's (max diff {err})"
    return err


def bench_irradiance(args, rng):
    N = 10**5 if args.quick else 10**6
    tab = Table(
        f"1. IRRADIANCE from 9 RGB coefficients at N={N:.0e} random unit normals; "
        "ratio = jaxsh / peer (<1: jaxsh faster)",
        ["dtype", "tool", "first call", "warm", "ns/normal", "jaxsh/peer", "max|E - closed f64|",
         "rel. (/max|E|)", "max|E - jaxsh f64|"],
    )
    L64 = rng.normal(size=(9, 3))
    L64[0] += 3.0  # a positive ambient term, as real lighting has
    n64 = unit_dirs(rng, N, np.float64)
    ref = irradiance_closed_form(L64, n64)  # float64 closed form: the accuracy reference
    scale = np.abs(ref).max()
    e_ours64 = None
    for dtype in (np.float64, np.float32):
        dname = np.dtype(dtype).name
        Ld, nd = L64.astype(dtype), n64.astype(dtype)
        with jax.enable_x64(dtype is np.float64):
            Lj, nj = jnp.asarray(Ld), jnp.asarray(nd)
            first, t_ours = time_jax(lambda: jaxsh.irradiance(Lj, nj))
            e = np.asarray(jaxsh.irradiance(Lj, nj))
        assert e.dtype == dtype and e.shape == (N, 3), (e.dtype, e.shape)
        if dtype is np.float64:
            e_ours64 = e
        d_ref = np.abs(e.astype(np.float64) - ref).max()
        d_ours = np.abs(e.astype(np.float64) - e_ours64).max()
        tab.add(dname, "jaxsh.irradiance", fmt_t(first), fmt_t(t_ours), f"{t_ours / N * 1e9:.2f}", "1.00",
                fmt_e(d_ref), fmt_e(d_ref / scale), "-" if dtype is np.float64 else fmt_e(d_ours))
        for label, fn in (("numpy closed form (eq. 13)", irradiance_closed_form),
                          ("numpy matrix form n^T M n", irradiance_matrix_form)):
            first, tp = time_np(lambda fn=fn: fn(Ld, nd))
            out = fn(Ld, nd)
            assert out.dtype == dtype, (label, out.dtype)
            d_ref = np.abs(out.astype(np.float64) - ref).max()
            d_ours = np.abs(out.astype(np.float64) - e_ours64).max()
            tab.add(dname, label, fmt_t(first), fmt_t(tp), f"{tp / N * 1e9:.2f}", ratio(t_ours, tp),
                    fmt_e(d_ref), fmt_e(d_ref / scale), fmt_e(d_ours))
        tab.sep()
        gc.collect()
    tab.show()
    print(f"  note: max|E| = {scale:.2f}; the float64 jaxsh - closed form difference comes from the 6-digit "
          "constants c1..c5 (e.g. c4 = 0.886227 vs pi*Y00 = 0.88622693); float32 rows are compared "
          "with the float64 closed form and with jaxsh float64.")
    print(flush=True)


# --------------------------------------------------------------------------
# 2. BRDF projection: NumPy peer of the same quadrature
# --------------------------------------------------------------------------

TS_PARAMS = dict(kd=0.3, ks=0.5, mu=1.6, sigma=0.35)


def make_transfer(kd, ks, mu, sigma):
    """rho_hat = torrance_sparrow * cos(theta_i) as transfer(theta_i, theta_o, dphi), jaxsh models."""

    def transfer(ti, to, dphi):
        wi, wo = jaxsh.local_directions(*jnp.broadcast_arrays(ti, to, dphi))
        n = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], wi.dtype), wi.shape)
        return jaxsh.torrance_sparrow(wi, wo, n, kd, ks, mu, sigma) * jnp.cos(ti)

    return transfer


def np_transfer(ti, to, dphi, kd, ks, mu, sigma):
    """The same transfer in NumPy (angles strictly inside the upper hemisphere, as on GL nodes)."""
    si, ci = np.sin(ti), np.cos(ti)
    so, co = np.sin(to), np.cos(to)
    # unnormalised half vector wi + wo (atan2 does not need |h| = 1)
    hx = si + so * np.cos(dphi)
    hy = so * np.sin(dphi)
    hz = ci + co
    theta_h = np.arctan2(np.sqrt(hx * hx + hy * hy), hz)
    s = np.exp(-((theta_h / sigma) ** 2)) / (np.pi * sigma * sigma)
    # exact unpolarised Fresnel at theta_o, normalised by its value at normal incidence
    g = np.sqrt(mu * mu - 1.0 + co * co)
    rs = (co - g) / (co + g)
    rp = (mu * mu * co - g) / (mu * mu * co + g)
    f = 0.5 * (rs * rs + rp * rp) / ((mu - 1.0) / (mu + 1.0)) ** 2
    return (kd + ks * f * s / (4.0 * ci * co)) * ci


def np_nodes(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return np.arccos(0.5 * (x + 1.0)), 0.5 * w


def np_zonal(theta, lmax):
    """N_lq P_l^q(cos theta) = Y_lq(theta, 0) (q >= 0), (n, l, q), zero for q > l."""
    l = np.arange(lmax + 1)[:, None]
    q = np.arange(lmax + 1)[None, :]
    y = sph_harm_y(l, q, theta[:, None, None], 0.0).real
    return np.where(q <= l, y, 0.0)


def np_azimuth(vals, lmax, n_phi):
    return np.fft.rfft(vals, axis=-1).real[..., : lmax + 1] * (2 * np.pi / n_phi)


def np_brdf_sh_coefficients(lmax, n_theta, n_phi, p=TS_PARAMS):
    th, w = np_nodes(n_theta)
    dphi = 2 * np.pi * np.arange(n_phi) / n_phi
    vals = np_transfer(th[:, None, None], th[None, :, None], dphi[None, None, :], **p)
    g = np_azimuth(vals, lmax, n_phi)  # (i, o, q)
    z = np_zonal(th, lmax) * w[:, None, None]
    return 2 * np.pi * np.einsum("ilq,opq,ioq->lpq", z, z, g, optimize=True)


def np_brdf_incident_coefficients(theta_o, lmax, n_theta, n_phi, p=TS_PARAMS):
    th, w = np_nodes(n_theta)
    dphi = 2 * np.pi * np.arange(n_phi) / n_phi
    vals = np_transfer(th[:, None], theta_o, dphi[None, :], **p)
    g = np_azimuth(vals, lmax, n_phi)  # (i, q)
    z = np_zonal(th, lmax) * w[:, None, None]
    lq = np.einsum("ilq,iq->lq", z, g)
    ls = np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1)
    ms = np.concatenate([np.arange(-l, l + 1) for l in range(lmax + 1)])
    sign = np.where(ms < 0, (-1.0) ** np.abs(ms), 1.0)
    return lq[ls, np.abs(ms)] * sign


def bench_brdf(args, rng):
    lmax = 16
    sizes = [(64, 64)] if args.quick else [(64, 64), (128, 128)]
    tab = Table(
        f"2. BRDF PROJECTION rho_lpq, Torrance-Sparrow, lmax={lmax} (float64); "
        "ratio = jaxsh / numpy (<1: jaxsh faster)",
        ["case", "tool", "first call", "warm", "jaxsh/numpy", "max|diff| vs numpy", "max|rho|"],
    )
    transfer = make_transfer(**TS_PARAMS)
    pj = {k: jnp.asarray(v) for k, v in TS_PARAMS.items()}
    for nt, npf in sizes:
        case = f"n_theta={nt}, n_phi={npf}"
        first_np, t_np = time_np(lambda: np_brdf_sh_coefficients(lmax, nt, npf))
        ref = np_brdf_sh_coefficients(lmax, nt, npf)
        mx = f"{np.abs(ref).max():.3f}"

        first, t_e = time_jax(lambda: jaxsh.brdf_sh_coefficients(transfer, lmax, n_theta=nt, n_phi=npf))
        got = np.asarray(jaxsh.brdf_sh_coefficients(transfer, lmax, n_theta=nt, n_phi=npf))
        assert got.shape == ref.shape == (lmax + 1,) * 3
        tab.add(case, "jaxsh.brdf_sh_coefficients (eager)", fmt_t(first), fmt_t(t_e), ratio(t_e, t_np),
                fmt_e(np.abs(got - ref).max()), mx)

        f_jit = jax.jit(lambda kd, ks, mu, sigma, nt=nt, npf=npf: jaxsh.brdf_sh_coefficients(
            make_transfer(kd, ks, mu, sigma), lmax, n_theta=nt, n_phi=npf))
        first, t_j = time_jax(lambda: f_jit(**pj))
        got = np.asarray(f_jit(**pj))
        tab.add(case, "  same in jax.jit (params traced)", fmt_t(first), fmt_t(t_j), ratio(t_j, t_np),
                fmt_e(np.abs(got - ref).max()), mx)
        tab.add(case, "numpy + scipy sph_harm_y (same rule)", fmt_t(first_np), fmt_t(t_np), "-", "-", mx)

        # the transfer evaluation on the (nt, nt, npf) grid alone
        th, _ = np_nodes(nt)
        dphi = 2 * np.pi * np.arange(npf) / npf
        thj, dphij = jnp.asarray(th), jnp.asarray(dphi)
        first, t_te = time_jax(lambda: transfer(thj[:, None, None], thj[None, :, None], dphij[None, None, :]))
        first_n, t_tn = time_np(lambda: np_transfer(th[:, None, None], th[None, :, None], dphi[None, None, :],
                                                    **TS_PARAMS))
        v_j = np.asarray(transfer(thj[:, None, None], thj[None, :, None], dphij[None, None, :]))
        v_n = np_transfer(th[:, None, None], th[None, :, None], dphi[None, None, :], **TS_PARAMS)
        tab.add(case, f"  of which: transfer, jaxsh models ({nt}x{nt}x{npf})", fmt_t(first), fmt_t(t_te),
                ratio(t_te, t_tn), fmt_e(np.abs(v_j - v_n).max()), f"{np.abs(v_n).max():.3f} (max|vals|)")
        tr_jit = jax.jit(lambda a, b: transfer(a[:, None, None], a[None, :, None], b[None, None, :]))
        first, t_tj = time_jax(lambda: tr_jit(thj, dphij))
        tab.add(case, "  of which: transfer, jaxsh models in jax.jit", fmt_t(first), fmt_t(t_tj), ratio(t_tj, t_tn),
                "", "")
        tab.add(case, "  of which: transfer, numpy", fmt_t(first_n), fmt_t(t_tn), "-", "-", "")
        tab.sep()
        gc.collect()

    # incident coefficients at one view
    theta_o = 0.7
    nt, npf = 96, 128  # jaxsh's defaults
    case = f"incident, theta_o={theta_o}, n_theta={nt}, n_phi={npf}"
    first_np, t_np = time_np(lambda: np_brdf_incident_coefficients(theta_o, lmax, nt, npf))
    ref = np_brdf_incident_coefficients(theta_o, lmax, nt, npf)
    to_j = jnp.asarray(theta_o)
    first, t_e = time_jax(lambda: jaxsh.brdf_incident_coefficients(transfer, to_j, lmax))
    got = np.asarray(jaxsh.brdf_incident_coefficients(transfer, to_j, lmax))
    mx = f"{np.abs(ref).max():.3f}"
    tab.add(case, "jaxsh.brdf_incident_coefficients (eager)", fmt_t(first), fmt_t(t_e), ratio(t_e, t_np),
            fmt_e(np.abs(got - ref).max()), mx)
    f_jit = jax.jit(lambda to, kd, ks, mu, sigma: jaxsh.brdf_incident_coefficients(
        make_transfer(kd, ks, mu, sigma), to, lmax))
    first, t_j = time_jax(lambda: f_jit(to_j, **pj))
    got = np.asarray(f_jit(to_j, **pj))
    tab.add(case, "  same in jax.jit (theta_o, params traced)", fmt_t(first), fmt_t(t_j), ratio(t_j, t_np),
            fmt_e(np.abs(got - ref).max()), mx)
    tab.add(case, "numpy + scipy sph_harm_y (same rule)", fmt_t(first_np), fmt_t(t_np), "-", "-", mx)
    tab.show()
    print("  note: the NumPy transfer evaluates trig functions on the 1-D angle axes and the Fresnel factor "
          "on the theta_o axis only (broadcasting), as hand-written code would; jaxsh's model functions "
          "take full (..., 3) direction arrays and evaluate everything per grid point.")
    print("  note: eager first calls include compiling every op-by-op primitive and the jitted model "
          "functions for the new shapes; sizes run in the order shown, so later first calls reuse "
          "shape-independent compilations of earlier ones.")
    print(flush=True)


# --------------------------------------------------------------------------
# 3. convolution + synthesis on a lat-long map
# --------------------------------------------------------------------------


def bench_convolve(args, rng):
    lmax = 32
    H, W = (128, 256) if args.quick else (256, 512)
    n = (lmax + 1) ** 2
    tab = Table(
        f"3. CONVOLVE + SYNTHESIZE: lmax={lmax} RGB lighting, Phong s=20 spectrum, {H}x{W} map (float64); "
        "ratio = jaxsh / peer",
        ["tool", "first call", "warm", "ns/pixel", "jaxsh/peer", "max|diff| vs jaxsh", "max|image|"],
    )
    ls = np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1)
    c = rng.normal(size=(n, 3)) / (1.0 + ls[:, None]) ** 1.5
    c[0] += 2.0
    A = np.asarray(jaxsh.phong_spectrum(jnp.asarray(20.0), lmax))
    cj, Aj = jnp.asarray(c), jnp.asarray(A)

    first, t_ours = time_jax(lambda: jaxsh.synthesize_latlong(jaxsh.convolve(cj, Aj), H, W))
    ours = np.asarray(jaxsh.synthesize_latlong(jaxsh.convolve(cj, Aj), H, W))
    mx = f"{np.abs(ours).max():.3f}"
    tab.add("jaxsh synthesize_latlong(convolve(L, A))", fmt_t(first), fmt_t(t_ours),
            f"{t_ours / (H * W) * 1e9:.1f}", "1.00", "-", mx)

    theta = np.pi * (np.arange(H) + 0.5) / H
    phi = 2 * np.pi * (np.arange(W) + 0.5) / W
    st = np.sin(theta)[:, None]
    dirs = np.stack(np.broadcast_arrays(st * np.cos(phi)[None, :], st * np.sin(phi)[None, :],
                                        np.cos(theta)[:, None]), -1).reshape(-1, 3)
    build = jax.jit(lambda d: jaxsh.real_sh(d, lmax))
    dj = jnp.asarray(dirs)
    jax.block_until_ready(build(dj))  # compiled first: the 'incl. Y' ratio charges the build, not its compilation
    t0 = time.perf_counter()
    Y = np.asarray(build(dj))  # (H*W, n)
    t_build = time.perf_counter() - t0

    def dense():
        return (Y @ (A[ls][:, None] * c)).reshape(H, W, 3)

    first_p, tp = time_np(dense)
    diff = np.abs(dense() - ours).max()
    tab.add(f"numpy dense Y @ (A_l L_lm), Y {H * W}x{n} prebuilt", fmt_t(first_p), fmt_t(tp),
            f"{tp / (H * W) * 1e9:.1f}", ratio(t_ours, tp), fmt_e(diff), mx)
    tab.add("  (building Y with jaxsh.real_sh, once)", fmt_t(t_build), "-", "-",
            ratio(t_ours, tp + t_build) + " (incl. Y)", "-", "")
    del Y
    gc.collect()
    tab.show()
    print(f"  note: Y is {H * W * n * 8 / 2**30:.2f} GiB (float64); the dense route's warm time excludes "
          "building it, the 'incl. Y' ratio charges one build to one evaluation.")
    print(flush=True)


def _scipy_real_sh(d, lmax):
    """Real SH of one unit direction from scipy's complex ones (docs/conventions.md)."""
    theta, phi = np.arctan2(np.hypot(d[0], d[1]), d[2]), np.arctan2(d[1], d[0])
    out = np.empty((lmax + 1) ** 2)
    for l in range(lmax + 1):
        out[l * l + l] = sph_harm_y(l, 0, theta, phi).real
        for m in range(1, l + 1):
            y = sph_harm_y(l, m, theta, phi)
            out[l * l + l + m] = np.sqrt(2.0) * (-1) ** m * y.real
            out[l * l + l - m] = np.sqrt(2.0) * (-1) ** m * y.imag
    return out


def _scipy_disk_sh(d, r, rad, lmax):
    from scipy.special import eval_legendre

    u = np.cos(r)
    zon = np.empty(lmax + 1)
    zon[0] = 2 * np.pi * (1 - u) / np.sqrt(4 * np.pi)
    for l in range(1, lmax + 1):
        zon[l] = np.sqrt(np.pi / (2 * l + 1)) * (eval_legendre(l - 1, u) - eval_legendre(l + 1, u))
    lam = np.sqrt(4 * np.pi / (2 * np.arange(lmax + 1) + 1))
    ls = np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1)
    return ((lam * zon)[ls] * _scipy_real_sh(d, lmax))[:, None] * rad[None, :]


def bench_lights(args, rng):
    lmax = 16
    tab = Table(f"4. LIGHTING FROM SOURCES, one call per source, lmax={lmax} RGB (float64); ratio = jaxsh / peer",
                ["tool", "sources", "first (1st source)", "warm per source", "jaxsh/peer", "max|diff|"])
    for kind, n_src in (("directional", 100), ("disk", 20)):
        d = unit_dirs(rng, n_src, np.float64)
        e = rng.uniform(0.5, 2.0, (n_src, 3))
        r = rng.uniform(0.05, 0.3, n_src)
        if kind == "directional":
            ours_f = lambda k: jaxsh.directional_light_sh(d[k:k + 1], e[k:k + 1], lmax)  # noqa: E731
            peer_f = lambda k: _scipy_real_sh(d[k], lmax)[:, None] * e[k][None, :]  # noqa: E731
        else:
            ours_f = lambda k: jaxsh.disk_light_sh(d[k], r[k], e[k], lmax)  # noqa: E731
            peer_f = lambda k: _scipy_disk_sh(d[k], r[k], e[k], lmax)  # noqa: E731
        t0 = time.perf_counter()
        ours = [np.asarray(ours_f(0))]
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        ours += [np.asarray(ours_f(k)) for k in range(1, n_src)]
        warm = (time.perf_counter() - t0) / (n_src - 1)
        t0 = time.perf_counter()
        peer = [peer_f(k) for k in range(n_src)]
        tp = (time.perf_counter() - t0) / n_src
        diff = max(float(np.abs(a - b).max()) for a, b in zip(ours, peer))
        tab.add(f"jaxsh {kind}_light_sh", str(n_src), fmt_t(first), fmt_t(warm), ratio(warm, tp), fmt_e(diff))
        tab.add(f"scipy sph_harm_y{' + eval_legendre' if kind == 'disk' else ''}", str(n_src), "-", fmt_t(tp), "", "")
    tab.show()
    print(flush=True)


# --------------------------------------------------------------------------


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="reduced sizes (~30 s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--only", choices=["irradiance", "brdf", "convolve", "lights"], default=None)
    add_hugepages_option(p)
    args = p.parse_args(argv)
    apply_hugepages(args)
    rng = np.random.default_rng(args.seed)
    sign_err = check_sign_convention()

    print("jaxsh convolution benchmark" + (" (--quick)" if args.quick else ""))
    print(f"  python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} CPUs, "
          f"jax {jax.__version__} ({jax.default_backend()}), x64 enabled by this script, "
          f"jaxsh compile options {jaxsh.compile_options()}")
    print(f"  jaxsh {jaxsh.__version__}, numpy {np.__version__}, scipy {scipy.__version__}")
    print(f"  load average at start: {', '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print(f"  {malloc_line()}")
    print(f"  real SH l<=2 vs R&H's printed polynomials (sign convention check): max diff {sign_err:.1e}")
    print("  threads: XLA CPU uses all cores; NumPy matmul/einsum through its BLAS "
          f"(OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}); NumPy ufuncs and FFT 1 thread.")
    print(flush=True)
    t0 = time.perf_counter()
    if args.only in (None, "irradiance"):
        bench_irradiance(args, rng)
    if args.only in (None, "brdf"):
        bench_brdf(args, rng)
    if args.only in (None, "convolve"):
        bench_convolve(args, rng)
    if args.only in (None, "lights"):
        bench_lights(args, rng)
    print(f"total wall time {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
