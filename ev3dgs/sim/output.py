"""From simulator results to scene-file parts (used by the CLI, the demo and the dataset maker)."""
from __future__ import annotations

from ..config import to_dict
from ..schema import EventSensor
from .config import DVSConfig, SimConfig


def event_sensor(cfg: DVSConfig) -> EventSensor:
    """The /events attrs the trainer needs to model this simulated sensor."""
    return EventSensor(
        pos_threshold=cfg.pos_threshold,
        neg_threshold=cfg.neg_threshold,
        color_filter=cfg.color_filter.pattern if cfg.color_filter else "none",
        refractory_us=cfg.refractory.period_us if cfg.refractory else 0.0,
        log_knee=cfg.log_knee,
    )


def provenance(cfg: SimConfig, **extra) -> dict:
    """The JSON `config` attr: every setting that made the file, effects included only when on."""
    return {"sim": to_dict(cfg), **extra}
