"""[threshold_map]: per-pixel ON/OFF thresholds (the sensor's fixed-pattern mismatch) estimated from the events
as the model fits (train/threshold_map.py), with the event noise model's mismatch as prior. The event term
renders its residuals with the map's thresholds and, with weights = "posterior", weighs them by each pixel's
remaining spread. No loss of its own; needs the noise norm."""
from __future__ import annotations

from ...errors import InputError
from . import Term, register


@register
class ThresholdMapTerm(Term):
    table = "threshold_map"
    builtin = True

    @classmethod
    def build(cls, trainer):
        cfg = trainer.cfg
        if not (cfg.threshold_map and cfg.uses_events and trainer.data.bins is not None):
            return None
        from .events import sensor_model

        rel = sensor_model(cfg, trainer.data)[0]
        return cls(trainer, rel) if rel > 0 else None   # no mismatch: nothing to map

    def __init__(self, trainer, rel_mismatch: float):
        super().__init__(trainer)
        from ..threshold_map import ThresholdMap

        d = trainer.data
        self.map = ThresholdMap(rel_mismatch, d.n_views, d.height, d.width, trainer.device)

    def posterior_spread(self):
        """The map's per-pixel spread where threshold_map.weights is "posterior", else None (the prior's)."""
        return self.map.spread if self.trainer.cfg.map_weights == "posterior" else None

    def save(self, payload):
        payload["threshold_map"] = self.map.state_dict()

    def load(self, payload, path):
        if payload.get("threshold_map") is None:
            raise InputError(f"{path}: the checkpoint has no threshold map to continue [threshold_map] from")
        self.map.load_state_dict(payload["threshold_map"])

    def model_extras(self):
        return {"threshold_map": self.map.multiplier.clone()}   # (2, H, W) multipliers of the thresholds
