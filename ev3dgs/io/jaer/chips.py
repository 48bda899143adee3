"""What an AEDAT 2.0 (jAER) file's header says about its camera: the chip and its address layout, the IMU full
scale and the IMU axes. Facts from jAER's public sources (github.com/SensorsINI/jaer):

* Chips (`# AEChip: <java class>`): DAVIS cameras (eu.seebetter.ini.chips.davis.DAVIS240A/B/C, Davis346*,
  Davis640) share the DAVIS address layout (DavisChip.java: y bits 30-22, x 21-12, polarity 11, bit 31 APS/IMU);
  the DVS128 (ch.unizh.ini.jaer.chip.retina.DVS128) uses x = 127 - bits 7-1, y = bits 14-8, raw bit 0 = 0 for ON,
  and addresses with bit 15 or 31 set are sync/special events (DVS128.java Extractor). Other chips are refused.
* APS frame boundaries: jAER starts a frame at the reset read of the chip's first pixel address and ends it at the
  signal read of its last one (DavisBaseCamera.firstFrameAddress/lastFrameAddress, overridden per chip:
  DAVIS240C and Davis346B read from (0, H-1) to (W-1, 0), Davis346cBSI from (W-1, 0) to (0, H-1), the others from
  (W-1, H-1) to (0, 0); raw jAER coordinates, y up).
* IMU scale: the prefs in the header name the full scale (`ImuAccelScale` = ImuAccelScaleG2/4/8/16 -> 16384/8192/
  4096/2048 LSB/g; `ImuGyroScale` = GyroFullScaleDegPerSec250/500/1000/2000 -> 131/65.5/32.8/16.4 LSB/(deg/s)) and
  the MPU-6150 config bytes `imu3_GYRO_CONFIG` / `imu4_ACCEL_CONFIG` (bits 4-3 = FS_SEL / AFS_SEL). jAER's
  defaults when the prefs are absent are G8 and 1000 deg/s (DavisConfig.loadPreference).
* IMU axes (IMU_AXES): the scene's camera frame is OpenCV's (x right, y down, z forward). jAER's IMUSample says raw
  accel x positive is camera left (it negates it for "right"), its gyro signs are tilt-up = -gx, pan-right = +gy,
  roll-clockwise = -gz, and an upright camera at rest reads raw ay = -1 g (so raw y points down). The MPU's axes
  are right-handed, so raw z points backward: camera = diag(-1, +1, -1) x raw, for the accelerometer and the gyro
  alike (a proper rotation, so integrating the gyro predicts what the accelerometer reads).
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..types import AedatError

IMU_AXES = np.array([-1.0, 1.0, -1.0])        # raw MPU axes (left, down, backward) -> camera (right, down, forward)
ACCEL_LSB = {2: 16384.0, 4: 8192.0, 8: 4096.0, 16: 2048.0}
GYRO_LSB = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
DEFAULT_ACCEL_G, DEFAULT_GYRO_DPS = 8, 1000   # jAER's defaults


@dataclass(frozen=True)
class Chip:
    name: str                                  # e.g. DAVIS240C
    layout: str                                # "davis" | "dvs128"
    size: tuple[int, int]
    first: tuple[int, int] | None = None       # raw (x, y) of the first / last APS pixel read out
    last: tuple[int, int] | None = None


def _davis(name: str, w: int, h: int, order: str = "default") -> Chip:
    first, last = {"default": ((w - 1, h - 1), (0, 0)), "x0": ((0, h - 1), (w - 1, 0)),
                   "bsi": ((w - 1, 0), (0, h - 1))}[order]
    return Chip(name, "davis", (w, h), first, last)


# (pattern on the class's simple name, case-insensitive) -> chip; first match wins
CHIPS = [
    (r"DVS128$", lambda n: Chip(n, "dvs128", (128, 128))),
    (r"DAVIS240C$", lambda n: _davis(n, 240, 180, "x0")),
    (r"DAVIS240", lambda n: _davis(n, 240, 180)),
    (r"Davis346B$", lambda n: _davis(n, 346, 260, "x0")),
    (r"Davis346cBSI$", lambda n: _davis(n, 346, 260, "bsi")),
    (r"Davis346", lambda n: _davis(n, 346, 260)),
    (r"Davis640$", lambda n: _davis(n, 640, 480)),
]
SUPPORTED = "DVS128, DAVIS240A/B/C, DAVIS346 (red/blue/B/cBSI/...), DAVIS640"


def chip_from_header(header: str, path: str) -> tuple[str, Chip | None]:
    """-> (the AEChip class name or "", its Chip; None when the header has no AEChip line). An AEChip that is
    not supported raises AedatError (its layout is unknown: decoding it would give garbage)."""
    m = re.search(r"^#\s*AEChip:\s*(\S+)", header, re.M)
    if not m:
        return "", None
    full = m.group(1)
    simple = full.rsplit(".", 1)[-1]
    for pat, make in CHIPS:
        if re.search(pat, simple, re.I):
            return full, make(simple)
    raise AedatError(f"{path}: unsupported AEChip {full!r} (its address layout is unknown; supported: {SUPPORTED})")


def chip_for_size(size: tuple[int, int]) -> Chip:
    """The chip a --sensor-size WxH names (DAVIS layout unless 128x128)."""
    w, h = size
    if (w, h) == (128, 128):
        return Chip("DVS128", "dvs128", (128, 128))
    return _davis(f"DAVIS {w}x{h}", w, h)


def infer_chip(addr: np.ndarray, path: str) -> tuple[Chip, str]:
    """No AEChip line: guess the chip from the address ranges of (a sample of) the records; -> (chip, why)."""
    a = addr.astype(np.uint32)
    dvs = a[(a >> 31) == 0]
    if len(dvs) and (dvs < (1 << 15)).all() and (dvs >= (1 << 8)).any():
        return Chip("DVS128", "dvs128", (128, 128)), "all addresses below 2^15 (the DVS128 layout)"
    ev = a[((a >> 31) == 0) & (((a >> 10) & 1) == 0)]
    aps = a[((a >> 31) == 1) & (((a >> 10) & 3) < 2)]
    xy = np.concatenate([ev, aps])
    if not len(xy):
        raise AedatError(f"{path}: no AEChip line in the header and no DVS/APS addresses to infer the sensor "
                         "from: pass --sensor-size WxH")
    mx, my = int(((xy >> 12) & 0x3FF).max()), int(((xy >> 22) & 0x1FF).max())
    for w, h in ((240, 180), (346, 260), (640, 480)):
        if mx < w and my < h:
            return _davis(f"DAVIS {w}x{h} (inferred)", w, h), f"max x {mx}, max y {my}"
    raise AedatError(f"{path}: no AEChip line and addresses up to x {mx}, y {my} fit no known DAVIS: pass "
                     "--sensor-size WxH")


def imu_scales(header: str) -> tuple[float, float, str | None]:
    """-> (accel LSB/g, gyro LSB/(deg/s), None or a warning when the header names no full scale)."""
    acc = gyr = None
    m = re.search(r"imu4_ACCEL_CONFIG\"?\s*(?:value=)?\"?(\d+)", header)
    if m:
        acc = ACCEL_LSB[2 << ((int(m.group(1)) >> 3) & 3)]
    else:
        m = re.search(r"ImuAccelScaleG(2|4|8|16)\b", header)
        acc = ACCEL_LSB[int(m.group(1))] if m else None
    m = re.search(r"imu3_GYRO_CONFIG\"?\s*(?:value=)?\"?(\d+)", header)
    if m:
        gyr = GYRO_LSB[250 << ((int(m.group(1)) >> 3) & 3)]
    else:
        m = re.search(r"GyroFullScaleDegPerSec(250|500|1000|2000)\b", header)
        gyr = GYRO_LSB[int(m.group(1))] if m else None
    note = None
    if acc is None or gyr is None:
        note = (f"the header does not state the IMU full scale ({'accelerometer' if acc is None else ''}"
                f"{' and ' if acc is None and gyr is None else ''}{'gyro' if gyr is None else ''}): assuming "
                f"jAER's defaults, +-{DEFAULT_ACCEL_G} g ({ACCEL_LSB[DEFAULT_ACCEL_G]:g} LSB/g) and "
                f"+-{DEFAULT_GYRO_DPS} deg/s ({GYRO_LSB[DEFAULT_GYRO_DPS]:g} LSB/(deg/s))")
    return (acc or ACCEL_LSB[DEFAULT_ACCEL_G], gyr or GYRO_LSB[DEFAULT_GYRO_DPS], note)


def imu_to_camera(raw: np.ndarray, accel_lsb: float, gyro_lsb: float):
    """(n, 7) int16 IMU words (ax ay az temp gx gy gz) -> accel (g), gyro (deg/s) in the camera frame, temp (C)."""
    r = raw.astype(np.float64)
    accel = r[:, 0:3] / accel_lsb * IMU_AXES
    gyro = r[:, 4:7] / gyro_lsb * IMU_AXES
    return accel.astype(np.float32), gyro.astype(np.float32), (r[:, 3] / 340.0 + 35.0).astype(np.float32)


def decode_dvs128(addr: np.ndarray):
    """uint32 DVS128 addresses -> (event mask, special mask, x, row (top-left origin), polarity +1/-1)."""
    special = (addr & ((1 << 15) | (1 << 31))) != 0
    x = (127 - ((addr >> 1) & 0x7F)).astype(np.int64)
    row = (127 - ((addr >> 8) & 0x7F)).astype(np.int64)
    p = np.where(addr & 1, -1, 1).astype(np.int8)
    return ~special, special, x, row, p
