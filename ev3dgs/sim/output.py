"""From simulator results to scene-file parts (used by the CLI, the demo and the dataset maker)."""
from __future__ import annotations

from ..config import to_dict
from ..schema import EventSensor
from .config import DVSConfig, ISPConfig, SimConfig


def event_sensor(cfg: DVSConfig, isp: ISPConfig | None = None) -> EventSensor:
    """The /events attrs the trainer needs to model this simulated sensor: thresholds, knee, the count
    convention of its reference mode, and under a Bayer filter the camera-raw matrix its pixels see (the
    simulator's ColorFilterArray uses ``isp`` or, when None, ISPConfig())."""
    raw = None
    if cfg.color_filter:
        from ..sensor import camera_raw_matrix

        isp = isp or ISPConfig()
        raw = camera_raw_matrix(isp.ccm, isp.white_balance)
    return EventSensor(
        pos_threshold=cfg.pos_threshold,
        neg_threshold=cfg.neg_threshold,
        color_filter=cfg.color_filter.pattern if cfg.color_filter else "none",
        refractory_us=cfg.refractory.period_us if cfg.refractory else 0.0,
        log_knee=cfg.log_knee,
        count_convention="exact_reference" if cfg.reference == "exact" else "random_phase",
        camera_raw_matrix=raw,
        mismatch_sigma=cfg.threshold_mismatch.sigma if cfg.threshold_mismatch else 0.0,
        leak_rate_hz=cfg.leak.rate_hz if cfg.leak else 0.0,
        shot_noise_rate_hz=cfg.shot_noise.rate_hz if cfg.shot_noise else 0.0,
    )


def provenance(cfg: SimConfig, **extra) -> dict:
    """The JSON `config` attr: every setting that made the file, effects included only when on."""
    return {"sim": to_dict(cfg), **extra}
