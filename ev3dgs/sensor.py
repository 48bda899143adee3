"""Sensor facts shared by the simulator and the trainer's event loss (the trainer never imports the
simulator): how colour becomes the intensity a DVS pixel sees."""
from __future__ import annotations

import numpy as np

# Y row of the sRGB (Rec. 709 primaries, D65) RGB->XYZ matrix, as IEC 61966-2-1 and colour-science give it
# (tests/test_sensor_constants.py checks it against colour.RGB_COLOURSPACES["sRGB"]). Written out rather than
# read from colour at import: importing colour pulls in matplotlib (~0.8 s), and every trainer process
# imports this module.
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)

BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
_CHANNEL = {"R": 0, "G": 1, "B": 2}


def cfa_channels(pattern: str, height: int, width: int) -> np.ndarray:
    """(H, W) array of channel indices (0=R, 1=G, 2=B) for a Bayer pattern named row-major from (0, 0)."""
    block = np.array([[_CHANNEL[pattern[0]], _CHANNEL[pattern[1]]],
                      [_CHANNEL[pattern[2]], _CHANNEL[pattern[3]]]])
    return np.tile(block, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


def camera_raw_matrix(ccm, white_balance) -> np.ndarray:
    """3x3 M with camera raw = M @ linear sRGB, for an ISP whose forward path is white balance (gains)
    then colour matrix `ccm` (camera -> linear sRGB): M = inv(ccm) divided row-wise by the gains. Under a
    Bayer filter a DVS pixel sees its channel of this raw, as the frame's raw pixel does (ev3dgs.sim.isp)."""
    m = np.linalg.inv(np.asarray(ccm, dtype=np.float64))
    return m / np.asarray(white_balance, dtype=np.float64)[:, None]
