"""Simulator configuration. An effect runs only when its table is present in the config.

```toml
[dvs]
pos_threshold = 0.2          # log-intensity ON threshold
neg_threshold = 0.2          # log-intensity OFF threshold
log_knee = 1e-3              # lin-log knee, fraction of white (ev3dgs.logmap explains the default)
reference = "random"         # or "exact": the reference at (re)start (see DVSConfig)
[dvs.threshold_mismatch]     # frozen per-pixel thresholds ~ N(nominal, sigma)
sigma = 0.03
[dvs.refractory]
period_us = 500
[dvs.leak]                   # ON events from reference drift
rate_hz = 0.1
jitter_fraction = 0.1
[dvs.shot_noise]             # random ON/OFF events, most frequent in the dark
rate_hz = 1.0
[dvs.lowpass]                # photoreceptor bandwidth, proportional to intensity
cutoff_hz = 300
[dvs.color_filter]           # DAVIS346 colour: each pixel sees its CFA channel
pattern = "RGGB"
[isp]                        # raw <-> sRGB (blur); see ev3dgs.sim.isp
[sensor_noise]               # shot + read noise of the blurry frame
iso = 800
[aps]                        # the real APS frames' dark level (calibrate writes it, compare reads it)
dark_dn = 0.0
```
Every numeric key must lie in its physical range (RANGES below; docs/simulator.md lists them with reasons).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..config import check, from_dict, load_toml
from ..logmap import DEFAULT_LOG_KNEE

from ..sensor import BAYER_PATTERNS, RANGES


def within(key: str, value: float, lo: float, hi: float, low_open: bool = False) -> None:
    """Range check of one numeric key: lo <= value <= hi (lo < value with low_open); RANGES holds the ranges."""
    ok = (lo < value if low_open else lo <= value) and value <= hi
    check(ok, f"{key} = {value:g} is outside its physical range {'(' if low_open else '['}{lo:g}, {hi:g}]")


@dataclass(frozen=True)
class ThresholdMismatch:
    """Per-pixel ON and OFF thresholds drawn once (fixed-pattern noise) from N(nominal, sigma)."""

    sigma: float = 0.03
    min_threshold: float = 0.01  # draws are clipped here so no pixel gets a zero or negative threshold

    def __post_init__(self):
        within("dvs.threshold_mismatch.sigma", self.sigma, *RANGES["sigma"])
        within("dvs.threshold_mismatch.min_threshold", self.min_threshold, *RANGES["threshold"])


@dataclass(frozen=True)
class Refractory:
    """After an event the pixel is held in reset for `period_us`; see ev3dgs.sim.kernel for semantics."""

    period_us: float = 500.0

    def __post_init__(self):
        within("dvs.refractory.period_us", self.period_us, *RANGES["period_us"], low_open=True)


@dataclass(frozen=True)
class Leak:
    """The reference drifts down, giving ON events at `rate_hz` per pixel on a static scene.

    Per-pixel rates are log-normal with `rate_spread_decades` standard deviation (in decades), normalised so
    that their mean over pixels is `rate_hz`. `jitter_fraction` (v2e's leak_jitter_fraction) makes the drift
    a Brownian motion with that drift: its standard deviation over one leak period is `jitter_fraction` of a
    threshold, so a pixel's leak intervals have a coefficient of variation of about `jitter_fraction`,
    whatever the frame rate (v2e's per-frame multiplicative jitter shrinks as sqrt(rate * dt)).
    """

    rate_hz: float = 0.1
    rate_spread_decades: float = 0.1
    jitter_fraction: float = 0.1

    def __post_init__(self):
        within("dvs.leak.rate_hz", self.rate_hz, *RANGES["rate_hz"], low_open=True)
        check(0 <= self.rate_spread_decades <= 3, "dvs.leak.rate_spread_decades must be in [0, 3]")
        check(0 <= self.jitter_fraction <= 1, "dvs.leak.jitter_fraction must be in [0, 1]")


@dataclass(frozen=True)
class ShotNoise:
    """Poisson noise events: `rate_hz` per pixel (ON+OFF together) at intensity 0, falling linearly to
    `white_fraction * rate_hz` at intensity 1 (and staying there for HDR values). Each event resets the
    pixel, as a real noise-triggered reset does. With threshold mismatch, a pixel's ON (OFF) rate is scaled
    by nominal / its own ON (OFF) threshold, as in v2e: a low-threshold pixel is noisier."""

    rate_hz: float = 1.0
    white_fraction: float = 0.25

    def __post_init__(self):
        within("dvs.shot_noise.rate_hz", self.rate_hz, *RANGES["rate_hz"], low_open=True)
        check(0 <= self.white_fraction <= 1, "dvs.shot_noise.white_fraction must be in [0, 1]")


@dataclass(frozen=True)
class LowPass:
    """First-order photoreceptor filter; cutoff = cutoff_hz * (I + dark) / (1 + dark) at intensity I.
    The dark default is v2e's (20 DN of 255), independent of the log knee."""

    cutoff_hz: float = 300.0
    dark_intensity: float = 20.0 / 255.0

    def __post_init__(self):
        within("dvs.lowpass.cutoff_hz", self.cutoff_hz, *RANGES["cutoff_hz"], low_open=True)
        within("dvs.lowpass.dark_intensity", self.dark_intensity, *RANGES["intensity"])


@dataclass(frozen=True)
class ColorFilter:
    """A Bayer colour filter array: pattern of the top-left 2x2 block, row-major."""

    pattern: str = "RGGB"

    def __post_init__(self):
        check(self.pattern in BAYER_PATTERNS, f"dvs.color_filter.pattern must be one of {BAYER_PATTERNS}")


REFERENCE_MODES = ("random", "exact")


@dataclass(frozen=True)
class DVSConfig:
    """The change detector and its effects.

    reference: where each pixel's reference starts, at the first frame and after restart().
      "random" (default): a real sensor has been running, so its reference sits at a uniformly random phase
      within one threshold: a pixel whose first change is upward starts u * C_on below its signal, one whose
      first change is downward (1 - u) * C_off above it, u ~ U[0, 1) per pixel (seeded). The first event in
      either direction then comes at the next point of a threshold lattice with a random offset, so the
      expected count over a monotonic change D is exactly D / C (with "exact" it is floor(D / C): 0.5 short
      on average). A pixel's direction is fixed by its first non-zero change (or first noise event).
      "exact": reference = the first frame's log intensity (ESIM and v2e do this); deterministic counts.
    """

    pos_threshold: float = 0.2
    neg_threshold: float = 0.2
    log_knee: float = DEFAULT_LOG_KNEE
    reference: str = "random"
    threshold_mismatch: ThresholdMismatch | None = None
    refractory: Refractory | None = None
    leak: Leak | None = None
    shot_noise: ShotNoise | None = None
    lowpass: LowPass | None = None
    color_filter: ColorFilter | None = None

    def __post_init__(self):
        within("dvs.pos_threshold", self.pos_threshold, *RANGES["threshold"])
        within("dvs.neg_threshold", self.neg_threshold, *RANGES["threshold"])
        within("dvs.log_knee", self.log_knee, *RANGES["intensity"])
        check(self.reference in REFERENCE_MODES, f"dvs.reference must be one of {REFERENCE_MODES}")

    @property
    def effects(self) -> tuple[str, ...]:
        """Names of the effects this config turns on, in pipeline order."""
        names = ("color_filter", "lowpass", "threshold_mismatch", "leak", "shot_noise", "refractory")
        return tuple(n for n in names if getattr(self, n) is not None)


@dataclass(frozen=True)
class ISPConfig:
    """Camera ISP. Defaults: a typical daylight white balance and a camera->sRGB colour matrix whose rows
    sum to 1 (white stays white) with a non-negative inverse (any in-gamut colour has a non-negative raw)."""

    white_balance: tuple[float, float, float] = (2.0, 1.0, 1.6)
    ccm: tuple[tuple[float, float, float], ...] = (
        (1.60, -0.45, -0.15),
        (-0.25, 1.50, -0.25),
        (-0.05, -0.55, 1.60),
    )
    mosaic: str = "none"  # or a Bayer pattern: the raw is one channel per pixel, demosaiced by OpenCV

    def __post_init__(self):
        check(len(self.ccm) == 3, "isp.ccm must be 3x3")
        for g in self.white_balance:
            within("isp.white_balance gains", g, *RANGES["gain"], low_open=True)
        for row in self.ccm:
            for v in row:
                within("isp.ccm entries", abs(v), 0.0, RANGES["gain"][1])
        check(self.mosaic == "none" or self.mosaic in BAYER_PATTERNS,
              f"isp.mosaic must be 'none' or one of {BAYER_PATTERNS}")
        import numpy as np

        m = np.array(self.ccm, dtype=float)
        check(abs(np.linalg.det(m)) > 1e-6, "isp.ccm must be invertible")


@dataclass(frozen=True)
class SensorNoise:
    """Shot and read noise of the APS frame. `full_well_electrons` is at ISO 100; higher ISO divides it."""

    iso: float = 100.0
    full_well_electrons: float = 10000.0
    read_noise_electrons: float = 3.0

    def __post_init__(self):
        within("sensor_noise.iso", self.iso, *RANGES["iso"])
        within("sensor_noise.full_well_electrons", self.full_well_electrons, *RANGES["electrons"])
        within("sensor_noise.read_noise_electrons", self.read_noise_electrons, 0.0, RANGES["electrons"][1])


@dataclass(frozen=True)
class APSConfig:
    """The APS frames' dark level in DN: `ev3dgs-sim calibrate` fits it and `ev3dgs-sim compare` subtracts it
    before mapping a real frame to intensity. The simulator itself does not read it."""

    dark_dn: float = 0.0

    def __post_init__(self):
        within("aps.dark_dn", self.dark_dn, *RANGES["dn"])


@dataclass(frozen=True)
class SimConfig:
    dvs: DVSConfig = field(default_factory=DVSConfig)
    isp: ISPConfig = field(default_factory=ISPConfig)
    sensor_noise: SensorNoise | None = None
    aps: APSConfig | None = None


def load_sim_config(path: str | Path | None) -> SimConfig:
    """Read a simulator TOML config; None gives the defaults (no effects)."""
    if path is None:
        return SimConfig()
    return from_dict(SimConfig, load_toml(path))
