"""Frames -> per-pixel linear intensity: luminance, or the pixel's own channel under a Bayer filter."""
from __future__ import annotations

import numpy as np

from ...errors import InputError
from ...sensor import LUMINANCE_WEIGHTS, cfa_channels

__all__ = ["LUMINANCE_WEIGHTS", "cfa_channels", "luminance", "ColorFilterArray"]


def luminance(frame: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) -> flat (H*W,) linear intensity, in the frame's float precision."""
    if frame.ndim == 2:
        return np.ascontiguousarray(frame).ravel()
    return frame.reshape(-1, 3) @ LUMINANCE_WEIGHTS.astype(frame.dtype)


class ColorFilterArray:
    """Each pixel sees only its CFA channel, as the DAVIS346 colour sensor's DVS pixels do."""

    def __init__(self, pattern: str, height: int, width: int):
        self.pattern = pattern
        self.flat_index = (np.arange(height * width) * 3 + cfa_channels(pattern, height, width).ravel())

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        if frame.ndim != 3 or frame.shape[-1] != 3:
            raise InputError("a Bayer colour filter needs colour frames of shape (T, H, W, 3)")
        return frame.reshape(-1).take(self.flat_index)
