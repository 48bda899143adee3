"""Per-pixel threshold mismatch: fixed-pattern noise drawn once per simulator."""
from __future__ import annotations

import numpy as np

from ..config import ThresholdMismatch


def draw_thresholds(cfg: ThresholdMismatch, nominal_on: float, nominal_off: float, n_pixels: int,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """ON and OFF thresholds ~ N(nominal, sigma), independent, clipped below at cfg.min_threshold."""
    c_on = rng.normal(nominal_on, cfg.sigma, n_pixels)
    c_off = rng.normal(nominal_off, cfg.sigma, n_pixels)
    return np.maximum(c_on, cfg.min_threshold), np.maximum(c_off, cfg.min_threshold)
