"""Frames -> per-pixel linear intensity: luminance, or the pixel's own camera-raw channel under a Bayer filter."""
from __future__ import annotations

import numpy as np

from ...errors import InputError
from ...sensor import LUMINANCE_WEIGHTS, camera_raw_matrix, cfa_channels
from ..config import ISPConfig

__all__ = ["LUMINANCE_WEIGHTS", "cfa_channels", "luminance", "raw_matrix", "ColorFilterArray"]


def luminance(frame: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, 3) -> flat (H*W,) linear intensity, in the frame's float precision."""
    if frame.ndim == 2:
        return np.ascontiguousarray(frame).ravel()
    return frame.reshape(-1, 3) @ LUMINANCE_WEIGHTS.astype(frame.dtype)


def raw_matrix(isp: ISPConfig) -> np.ndarray:
    """3x3 M with camera raw = M @ linear sRGB: inverse colour matrix, then divided by the white-balance
    gains (the inverse of ev3dgs.sim.isp's forward path, the same raw that inverse_isp makes)."""
    return camera_raw_matrix(isp.ccm, isp.white_balance)


class ColorFilterArray:
    """Each pixel sees only its CFA channel, as the DAVIS346 colour sensor's DVS pixels do, in camera raw:
    the same channel (inverse CCM, divided by white balance) that the ISP gives the frame's raw pixel, so
    events and frames see the same light. White is (1/wb_R, 1, 1/wb_B) in raw."""

    def __init__(self, pattern: str, height: int, width: int, isp: ISPConfig | None = None):
        self.pattern = pattern
        self.matrix = raw_matrix(isp or ISPConfig())
        self.flat_index = (np.arange(height * width) * 3 + cfa_channels(pattern, height, width).ravel())

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        if frame.ndim != 3 or frame.shape[-1] != 3:
            raise InputError("a Bayer colour filter needs colour frames of shape (T, H, W, 3)")
        raw = frame.reshape(-1, 3) @ self.matrix.T.astype(frame.dtype)
        return raw.reshape(-1).take(self.flat_index)
