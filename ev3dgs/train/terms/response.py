"""[response]: a learned monotone camera response before the sRGB decode (train/response.py), trained with
the model; the blur term renders through it. Writes RUN/response.json."""
from __future__ import annotations

import json

import torch

from ...errors import ConfigError, InputError
from . import Term, register


@register
class Response(Term):
    table = "response"
    builtin = True

    @classmethod
    def build(cls, trainer):
        if not trainer.cfg.learn_response:
            return None
        d = trainer.data
        if d.blur_space != "linear" or (trainer.cfg.uses_events and d.event_transfer != "srgb"):
            raise ConfigError("[response] needs a scene whose frames are decoded with sRGB: the linear-light "
                              f"blur model and sRGB events (this run: {d.blur_space} blur model, "
                              f"{d.event_transfer} events)")
        return cls(trainer)

    def __init__(self, trainer):
        super().__init__(trainer)
        from ..response import RESPONSE_LR, ResponseCurve

        self.curve = ResponseCurve(device=trainer.device)
        self.opt = torch.optim.Adam([self.curve.logits], lr=RESPONSE_LR)

    def parameters(self):
        return [self.curve.logits]

    def after_backward(self, step):
        self.opt.step()
        self.opt.zero_grad(set_to_none=True)
        return {}

    def save(self, payload):
        payload["response"] = {"curve": self.curve.state_dict(), "opt": self.opt.state_dict()}

    def load(self, payload, path):
        if payload.get("response") is None:
            raise InputError(f"{path}: the checkpoint has no camera response to continue [response] from")
        self.curve.load_state_dict(payload["response"]["curve"])
        self.opt.load_state_dict(payload["response"]["opt"])

    def write(self, run_dir):
        from ...outputs import atomic_path

        with atomic_path(run_dir / "response.json") as tmp:   # the curve, for the user to read
            tmp.write_text(json.dumps(self.curve.table(), indent=1) + "\n")
