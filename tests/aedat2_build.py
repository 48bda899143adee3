"""A realistic jAER DAVIS240C AEDAT 2.0 recording built record by record from the documented layout (jAER's
DavisChip.java: DVS y 30-22, x 21-12, polarity 11; APS bit 31, reset/signal read in bits 11-10, ADC 9-0; IMU
bit 31 + bits 11-10 = 3, 7 words per sample; external input bit 10): events at a realistic rate, rolling-shutter
APS frames, IMU samples and triggers, with every record's expected decoding kept."""
from __future__ import annotations

import numpy as np

W, H = 240, 180
HEADER = (b"#!AER-DAT2.0\r\n# This is a raw AE data file created by AEOutputStream\r\n"
          b"# AEChip: eu.seebetter.ini.chips.davis.DAVIS240C\r\n"
          b"#      <entry key=\"ImuAccelScale\" value=\"ImuAccelScaleG8\"/>\r\n"
          b"#      <entry key=\"ImuGyroScale\" value=\"GyroFullScaleDegPerSec1000\"/>\r\n"
          b"#End Of ASCII Header\r\n")


def dvs(x, y, p):
    return (y << 22) | (x << 12) | (p << 11)


def aps(x, y, readout, adc):
    return (1 << 31) | (y << 22) | (x << 12) | (readout << 10) | adc


def imu_word(kind, value):
    return (1 << 31) | (kind << 28) | ((int(value) & 0xFFFF) << 12) | (3 << 10)


def build(seed: int = 0, n_events: int = 20000, frames: int = 2, roi: int = 40, t0: int = 1_000_000):
    """-> (bytes, records (n, 2) int64 [address, t], kinds (n,) str 'e' event / 'a' APS / 'i' IMU / 't' trigger).
    Events 0-40 us apart; after every n_events // (frames + 1) events an APS frame of roi x roi pixels
    (jAER's DAVIS240C readout order from (0, H-1), reset reads then signal reads 1 ms later, interleaved with
    events); an IMU sample every 1500 events; a trigger every 2500."""
    rng = np.random.default_rng(seed)
    recs, kinds = [], []
    t = t0
    every = n_events // (frames + 1)
    for i in range(n_events):
        t += int(rng.integers(0, 40))
        recs.append((dvs(int(rng.integers(0, W)), int(rng.integers(0, H)), int(rng.integers(0, 2))), t))
        kinds.append("e")
        if i % 1500 == 700:
            recs += [(imu_word(k, int(v)), t) for k, v in enumerate(rng.integers(-30000, 30000, 7))]
            kinds += ["i"] * 7
        if i % 2500 == 1200:
            recs.append(((1 << 10) | 3, t))
            kinds.append("t")
        if i % every == every - 1 and i // every < frames:
            for readout, dt in ((0, 0), (1, 1000)):
                for y in range(H - 1, H - 1 - roi, -1):
                    for x in range(roi):
                        recs.append((aps(x, y, readout, int(rng.integers(0, 1024))), t + dt))
                        kinds.append("a")
                t += dt
    rec = np.array(recs, np.int64)
    out = np.empty((len(rec), 2), ">u4")
    out[:, 0], out[:, 1] = rec[:, 0] & 0xFFFFFFFF, rec[:, 1] & 0xFFFFFFFF
    return HEADER + out.tobytes(), rec, np.array(kinds)
