"""Flat spherical-harmonic indexing, `Λ_l`, and real↔complex change of basis."""

from __future__ import annotations

import math

import numpy as np

from ._checks import check_lmax


def num_coeffs(lmax: int) -> int:
    """Number of SH coefficients up to and including band `lmax`: $(l_{max}+1)^2$."""
    lmax = check_lmax(lmax)
    return (lmax + 1) ** 2


def sh_index(l: int, m: int) -> int:
    """Flat index of $(l, m)$: $i = l^2 + l + m$, for $-l \\le m \\le l$."""
    l = check_lmax(l, "l")
    m = int(m)
    if abs(m) > l:
        raise ValueError(f"`m` must satisfy -l <= m <= l, got l={l}, m={m}")
    return l * l + l + m


def sh_degree_order(index: int) -> tuple[int, int]:
    """Inverse of `sh_index`: the $(l, m)$ of a flat index."""
    i = check_lmax(index, "index")
    l = math.isqrt(i)
    return l, i - l * l - l


def sh_degrees(lmax: int) -> np.ndarray:
    """The degree $l$ of every flat index up to `lmax`, shape `((lmax+1)**2,)`."""
    lmax = check_lmax(lmax)
    return np.repeat(np.arange(lmax + 1), 2 * np.arange(lmax + 1) + 1)


def sh_orders(lmax: int) -> np.ndarray:
    """The order $m$ of every flat index up to `lmax`, shape `((lmax+1)**2,)`."""
    lmax = check_lmax(lmax)
    return np.concatenate([np.arange(-l, l + 1) for l in range(lmax + 1)])


def sh_lambda(lmax: int) -> np.ndarray:
    """$\\Lambda_l = \\sqrt{4\\pi/(2l+1)}$ for $l = 0..l_{max}$ (R&H 2001, eq. 5).

    Returned as a NumPy float64 array (a constant of the band limit); cast it to
    your dtype where you use it.
    """
    lmax = check_lmax(lmax)
    l = np.arange(lmax + 1)
    return np.sqrt(4.0 * np.pi / (2 * l + 1))


def real_to_complex_matrix(lmax: int) -> np.ndarray:
    """Unitary $U$ with $Y^{\\mathbb C} = U\\, Y^{\\mathbb R}$ (basis functions).

    With the conventions of this library (complex $Y_l^m$ with the
    Condon-Shortley phase; real $Y_{l,\\pm m}$ with no sign flips):

    * $Y_l^{m} = (-1)^m (Y_{l,m} + i Y_{l,-m})/\\sqrt2$ for $m > 0$,
    * $Y_l^{-m} = (Y_{l,m} - i Y_{l,-m})/\\sqrt2$ for $m > 0$,
    * $Y_l^0 = Y_{l,0}$.

    Coefficients convert the other way: for $f = \\sum c_i Y^{\\mathbb R}_i =
    \\sum a_i Y^{\\mathbb C}_i$, $a = \\bar U c$ and $c = U^{T} a$ (see
    `real_to_complex_coeffs`). Block-diagonal in $l$; shape
    `((lmax+1)**2, (lmax+1)**2)`, complex128.
    """
    lmax = check_lmax(lmax)
    n = (lmax + 1) ** 2
    u = np.zeros((n, n), dtype=np.complex128)
    s = 1.0 / np.sqrt(2.0)
    for l in range(lmax + 1):
        base = l * l + l
        u[base, base] = 1.0
        for m in range(1, l + 1):
            sign = (-1.0) ** m
            u[base + m, base + m] = sign * s
            u[base + m, base - m] = 1j * sign * s
            u[base - m, base + m] = s
            u[base - m, base - m] = -1j * s
    return u
