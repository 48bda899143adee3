"""[edi_prior]: the event double integral prior (train/edi_prior.py). Each sub-pose render is pulled towards
the sharp frame the blurry frame and the exposure's events give, weighted by that target's expected error;
its weight falls linearly to 0 at edi_prior.anneal of the run's schedule length (over at least
trainer.MIN_EDI_ANNEAL_STEPS steps). Reads the event term's
renders, floor and thresholds of the same step; needs the noise norm."""
from __future__ import annotations

import torch

from ...errors import ConfigError
from ..edi_prior import anneal_factor, edi_prior_loss
from ..losses import log_intensity
from . import Term, register


@register
class EDIPrior(Term):
    table = "edi_prior"
    builtin = True

    @classmethod
    def build(cls, trainer):
        if not (trainer.cfg.edi_prior > 0 and trainer.term("events") is not None):
            return None
        return cls(trainer)

    def __init__(self, trainer):
        super().__init__(trainer)
        self.inputs = self._inputs()

    def _inputs(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Each view's (N, H, W) log intensity of the blurry frame and where the EDI target holds
        (edi_prior.valid_mask). Refused where the event intensity is not linear in what the blur model averages."""
        from ..edi_prior import COMPATIBLE, valid_mask

        d = self.trainer.data
        if (d.blur_space, d.event_transfer) not in COMPATIBLE:
            raise ConfigError(f"[edi_prior]: the blurry frame's event intensity is not the mean of the sub-poses' "
                              f"with the {d.blur_space} blur model and {d.event_transfer} events (give "
                              f"blur.space = \"linear\" for sRGB scenes)")
        with torch.no_grad():
            log_b = log_intensity(d.images, d.color_filter, d.log_knee, d.event_transfer, d.raw_matrix)
        return log_b, valid_mask(d.images, log_b, d.log_knee)

    def loss(self, step):
        cfg, d, sh = self.trainer.cfg, self.trainer.data, step.shared
        from ..trainer import MIN_EDI_ANNEAL_STEPS

        length = max(cfg.schedule_iterations, MIN_EDI_ANNEAL_STEPS / cfg.edi_anneal)   # fades over >= that
        fade = anneal_factor(self.trainer.step, length, cfg.edi_anneal)
        if fade <= 0 or "log_l" not in sh:
            return None, {"edi": 0.0}
        events = self.trainer.term("events")
        tpm, tnm = sh["thresholds"]
        l_edi = edi_prior_loss(sh["log_l"], sh["counts"], self.inputs[0][step.view], self.inputs[1][step.view], tpm,
                               tnm, sh["event_floor"], d.count_convention, events.rel_mismatch, events.noise_rate_hz,
                               sh["times_s"], d.log_knee, sh["spread"])
        return cfg.edi_prior * fade * l_edi, {"edi": l_edi.detach()}
