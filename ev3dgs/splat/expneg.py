"""exp(-s) for s >= 0 as straight-line float64 arithmetic, so the cpu rasterizer's per-pixel loops can be
vectorised by LLVM (numba has no vector exp here: without SVML ``np.exp`` is one scalar libm call per
pixel and keeps the whole loop scalar).

Method (per lane, no table, no bit tricks): r = s * 2^-m (exact: a power of two), exp(-r) by its Taylor
polynomial of degree 12 in Horner form, then squared m times: exp(-s) = exp(-r)^(2^m). The caller picks m
per Gaussian from the largest s it will pass (``squarings``) so that r <= 0.35:

* truncation: the first omitted term is r^13 / 13! <= 0.35^13 / 13! = 1.9e-16 relative (Taylor remainder of
  an alternating series with decreasing terms is below the first omitted term);
* rounding: Horner with |x| <= 0.35 and coefficients that decrease keeps the relative rounding error within
  about 2 ulp (u = 2^-53 = 1.1e-16);
* squaring m times multiplies a relative error eps by 2^m and adds one rounding per square: the result is
  within (2^m * (2.2 u + 1.9e-16) + m u) relative, i.e. about 5e-15 at m = 4 (s <= 5.6, every opacity
  <= 1: ln(255) = 5.54) and 2^m grows only like s.

For the float32 rasterizer the float64 result is rounded once to float32, so it agrees with a correctly
rounded expf except when exp(-s) lies within ~1e-14 relative of a float32 rounding boundary.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

R_MAX = 0.35  # largest reduced argument (see the error bound above)
MIN_SQUARINGS = 4
MAX_SQUARINGS = 12  # s up to 0.35 * 4096 = 1433: exp(-s) underflows float64 (below 1e-308) long before that

_C = tuple(1.0 / math.factorial(i) for i in range(13))


@njit(cache=True, nogil=True, inline="always")
def squarings(s_max):
    """Number of squarings m (MIN_SQUARINGS..MAX_SQUARINGS) with s_max * 2^-m <= R_MAX; NaN or s_max <= 5.6
    (no pixel or the usual case) give MIN_SQUARINGS."""
    s = np.float64(s_max)
    m = MIN_SQUARINGS
    while m < MAX_SQUARINGS and s > R_MAX * (2.0 ** m):
        m += 1
    return m


@njit(cache=True, nogil=True, inline="always")
def exp_neg_reduced(s, scale):
    """exp(-s * scale) in float64, for 0 <= s * scale <= R_MAX (scale = 2^-m): square the result m times to
    get exp(-s). Straight-line code (vectorisable)."""
    x = -(np.float64(s) * scale)
    p = _C[12]
    p = p * x + _C[11]
    p = p * x + _C[10]
    p = p * x + _C[9]
    p = p * x + _C[8]
    p = p * x + _C[7]
    p = p * x + _C[6]
    p = p * x + _C[5]
    p = p * x + _C[4]
    p = p * x + _C[3]
    p = p * x + _C[2]
    p = p * x + _C[1]
    return p * x + _C[0]


@njit(cache=True, nogil=True)
def exp_neg(s):
    """exp(-s) for an array of s >= 0 (float64 out): the scalar form of what the rasterizer does per lane."""
    out = np.empty(s.shape[0], np.float64)
    for i in range(s.shape[0]):
        m = squarings(s[i])
        scale = 0.5 ** m
        e = exp_neg_reduced(s[i], scale)
        for _ in range(m):
            e = e * e
        out[i] = e
    return out
