"""Leak events: junction leakage makes each pixel's reference drift down, so a static pixel emits ON
events at its own rate, with jittered intervals and (from the random start reference) a random phase."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..config import Leak

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S32 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(32)
_INV32 = 1.0 / 4294967296.0
_SQRT6 = math.sqrt(6.0)


@njit(cache=True, nogil=True)
def _jittered_drift(mean, jitter, dt_s, key):
    """mean * dt_s + jitter * sqrt(dt_s) * z_i, z_i zero-mean, unit-variance (the sum of two uniforms: a
    triangular draw; over the many intervals of a leak period the sum is Gaussian). The uniforms come from
    splitmix64 of (key, pixel): a counter-based stream, the same for any thread count or chunking, and one
    pass over the pixels (numpy's normal draw for every pixel and interval cost 8x more)."""
    n = mean.shape[0]
    out = np.empty(n)
    s = math.sqrt(dt_s)
    for i in range(n):
        x = key + np.uint64(i + 1) * _GOLDEN
        x = (x ^ (x >> _S30)) * _M1
        x = (x ^ (x >> _S27)) * _M2
        x = x ^ (x >> _S31)
        u1 = np.float64(x >> _S32) * _INV32
        u2 = np.float64(x & np.uint64(0xFFFFFFFF)) * _INV32
        out[i] = mean[i] * dt_s + jitter[i] * s * ((u1 + u2 - 1.0) * _SQRT6)
    return out


class LeakDrift:
    def __init__(self, cfg: Leak, n_pixels: int, rng: np.random.Generator, c_on: np.ndarray):
        # log-normal per-pixel rates, normalised so the mean over pixels is cfg.rate_hz (v2e's draw has
        # median rate_hz and a mean above it)
        sigma_ln = cfg.rate_spread_decades * math.log(10.0)
        z = rng.standard_normal(n_pixels)
        self.rate_hz = cfg.rate_hz * np.exp(sigma_ln * z - 0.5 * sigma_ln**2)
        self.rng = rng
        self._mean = self.rate_hz * c_on                    # reference fall per second
        self._jitter = cfg.jitter_fraction * np.sqrt(self.rate_hz) * c_on if cfg.jitter_fraction else None

    def mean_drift(self, dt_us: float) -> np.ndarray:
        """The drift without jitter: its sign is the direction a static pixel is moving."""
        return self._mean * (dt_us * 1e-6)

    def drift(self, dt_us: float) -> np.ndarray:
        """How far each reference falls over an interval: on average one ON threshold per 1/rate seconds,
        plus Brownian jitter of jitter_fraction * C * sqrt(rate * dt) per interval (so a leak period's
        length has a coefficient of variation of about jitter_fraction). One key per interval from the
        leak's seeded stream."""
        if self._jitter is None:
            return self.mean_drift(dt_us)
        key = np.uint64(self.rng.integers(0, 2**63, dtype=np.int64))
        return _jittered_drift(self._mean, self._jitter, dt_us * 1e-6, key)
