"""Leak events: junction leakage makes each pixel's reference drift down, so a static pixel emits ON
events at its own steady rate."""
from __future__ import annotations

import math

import numpy as np

from ..config import Leak


class LeakDrift:
    def __init__(self, cfg: Leak, n_pixels: int, rng: np.random.Generator):
        # log-normal per-pixel rates, normalised so the mean over pixels is cfg.rate_hz (v2e's draw has
        # median rate_hz and a mean above it)
        sigma_ln = cfg.rate_spread_decades * math.log(10.0)
        z = rng.standard_normal(n_pixels)
        self.rate_hz = cfg.rate_hz * np.exp(sigma_ln * z - 0.5 * sigma_ln**2)

    def drift(self, dt_us: float, c_on: np.ndarray) -> np.ndarray:
        """How far each reference falls over an interval: one ON threshold per 1/rate seconds."""
        return self.rate_hz * (dt_us * 1e-6) * c_on
