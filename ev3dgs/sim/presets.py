"""Named simulator settings to compare against: our defaults and v2e's `--dvs_params` presets.

v2e (emulator.py, set_dvs_params) has two presets, matched here effect for effect:

* ``v2e-clean``: thresholds 0.2 / 0.2, threshold mismatch sigma 0.02; no photoreceptor low-pass, leak, shot
  noise or refractory period.
* ``v2e-noisy``: thresholds 0.2 / 0.2, mismatch sigma 0.05, low-pass cutoff 30 Hz, leak 0.1 Hz (spread and
  jitter as our Leak defaults), shot noise 5 Hz; no refractory period.

``default`` is the simulator's own DAVIS346-like default (thresholds 0.2 / 0.2, no effects), what
``ev3dgs-sim events`` uses without --config.
"""
from __future__ import annotations

from .config import DVSConfig, Leak, LowPass, ShotNoise, SimConfig, ThresholdMismatch

V2E_CLEAN = SimConfig(dvs=DVSConfig(pos_threshold=0.2, neg_threshold=0.2,
                                    threshold_mismatch=ThresholdMismatch(sigma=0.02)))
V2E_NOISY = SimConfig(dvs=DVSConfig(
    pos_threshold=0.2, neg_threshold=0.2,
    threshold_mismatch=ThresholdMismatch(sigma=0.05),
    leak=Leak(rate_hz=0.1, rate_spread_decades=0.1, jitter_fraction=0.1),
    shot_noise=ShotNoise(rate_hz=5.0),
    lowpass=LowPass(cutoff_hz=30.0),
))
DEFAULT = SimConfig()

PRESETS: dict[str, SimConfig] = {"default": DEFAULT, "v2e-clean": V2E_CLEAN, "v2e-noisy": V2E_NOISY}


def preset(name: str) -> SimConfig:
    from ..errors import ConfigError

    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown preset {name!r} (known: {', '.join(PRESETS)})") from None
