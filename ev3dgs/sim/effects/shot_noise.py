"""Shot-noise events: a Poisson process per pixel whose rate falls with intensity."""
from __future__ import annotations

import numpy as np
from numba import njit

from ..config import ShotNoise


@njit(cache=True, nogil=True)
def _cumulative_expected(i0, i1, rate_dark, white_fraction, dt_s, weight):
    """Running sum over pixels of the expected noise count in an interval, at the mean intensity, times
    the per-pixel weight (empty: 1)."""
    out = np.empty(i0.shape[0])
    acc = 0.0
    slope = 1.0 - white_fraction
    has_w = weight.shape[0] > 0
    for i in range(i0.shape[0]):
        v = min(max(0.5 * (i0[i] + i1[i]), 0.0), 1.0)
        r = rate_dark * (1.0 - slope * v) * dt_s
        acc += r * weight[i] if has_w else r
        out[i] = acc
    return out


class ShotNoiseSampler:
    """With per-pixel thresholds (c_on, c_off differing from the nominal ones), each pixel's ON rate is
    scaled by nominal_on / c_on and its OFF rate by nominal_off / c_off, as in v2e: a pixel with a low
    threshold needs a smaller noise excursion to fire. Its total rate is then rate * (w_on + w_off) / 2 and
    an event is ON with probability w_on / (w_on + w_off)."""

    def __init__(self, cfg: ShotNoise, rng: np.random.Generator, c_on=None, c_off=None,
                 nominal_on: float = 0.2, nominal_off: float = 0.2):
        self.cfg = cfg
        self.rng = rng
        self.weight = np.zeros(0)
        self.p_on = None
        if c_on is not None and not (np.all(c_on == nominal_on) and np.all(c_off == nominal_off)):
            w_on, w_off = nominal_on / c_on, nominal_off / c_off
            self.weight = 0.5 * (w_on + w_off)
            self.p_on = w_on / (w_on + w_off)

    def rate_hz(self, intensity: np.ndarray) -> np.ndarray:
        """Events per second per pixel (ON and OFF together) at linear intensity I, nominal thresholds."""
        c = self.cfg
        return c.rate_hz * (1.0 - (1.0 - c.white_fraction) * np.clip(intensity, 0.0, 1.0))

    def sample(self, intensity_start: np.ndarray, intensity_end: np.ndarray, dt_us: float):
        """One interval's noise events (rate at the mean of the interval's end intensities): pixel indices
        (ascending), times as fractions of the interval (ascending within a pixel) and polarities (+1/-1,
        equal odds at nominal thresholds).

        Independent Poisson processes per pixel are drawn as one Poisson total over all pixels, each event
        assigned to pixel p with probability rate_p / sum(rate): the same distribution, but the cost is
        one pass over the pixels plus the (few) events, instead of one Poisson draw per pixel.
        """
        cumulative = _cumulative_expected(intensity_start, intensity_end, self.cfg.rate_hz,
                                          self.cfg.white_fraction, dt_us * 1e-6, self.weight)
        total = float(cumulative[-1]) if len(cumulative) else 0.0
        m = int(self.rng.poisson(total))
        pix = np.searchsorted(cumulative, self.rng.random(m) * total, side="right")
        pix = np.minimum(pix, len(cumulative) - 1)
        key = np.sort(pix + self.rng.random(m))  # by pixel, then by time within the pixel
        pix = key.astype(np.int64)
        frac = key - pix
        p_on = 0.5 if self.p_on is None else self.p_on[pix]
        pol = np.where(self.rng.random(m) < p_on, 1, -1).astype(np.int8)
        return pix, frac, pol
