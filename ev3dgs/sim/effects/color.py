"""Frames -> per-pixel linear intensity: luminance, or the pixel's own channel under a Bayer filter."""
from __future__ import annotations

import colour
import numpy as np

from ...errors import InputError

# Y row of the sRGB (Rec. 709 primaries, D65) RGB->XYZ matrix: 0.2126, 0.7152, 0.0722.
LUMINANCE_WEIGHTS = np.ascontiguousarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ[1], dtype=np.float64)

_CHANNEL = {"R": 0, "G": 1, "B": 2}


def cfa_channels(pattern: str, height: int, width: int) -> np.ndarray:
    """(H, W) array of channel indices (0=R, 1=G, 2=B) for a Bayer pattern named row-major from (0, 0)."""
    block = np.array([[_CHANNEL[pattern[0]], _CHANNEL[pattern[1]]],
                      [_CHANNEL[pattern[2]], _CHANNEL[pattern[3]]]])
    return np.tile(block, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


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
