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

# The physical range of each numeric sensor setting: checked when a simulator config is read (ev3dgs.sim.config,
# before any render or simulation) and when a scene declares it (ev3dgs.schema_validate); docs/simulator.md
# gives the reasons. Outside them a value describes no sensor and only costs memory or time.
RANGES = {
    "threshold": (1e-3, 10.0),       # log units: 0.1 % contrast (40x below measured DVS thresholds) .. e^10
    "sigma": (0.0, 1.0),             # log units: threshold mismatch, measured 0.02-0.05
    "intensity": (1e-6, 1.0),        # fraction of white: log_knee, lowpass dark_intensity (120 dB .. white)
    "period_us": (0.0, 1e6),         # refractory period: measured 0.1-10 ms; a second or more is a dead pixel
    "rate_hz": (0.0, 1e4),           # per-pixel leak / shot noise: a pixel cannot fire faster than ~10 kHz
    "cutoff_hz": (0.0, 1e6),         # photoreceptor bandwidth: measured up to ~10 kHz in bright light
    "gain": (0.0, 100.0),            # ISP white-balance gains and |colour-matrix entries|
    "iso": (1.0, 1e6),
    "electrons": (1.0, 1e7),         # full well; read noise is in [0, this]
    "dn": (-65535.0, 65535.0),       # APS dark level: within a 16-bit frame's range either way
}
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
