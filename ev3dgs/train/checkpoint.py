"""Checkpoints hold everything a resumed run needs to continue exactly as an uninterrupted one: the model,
every optimizer's state, the densification statistics and RNG, the step and the trainer's own RNG."""
from __future__ import annotations

import os
from pathlib import Path

import torch

from ..errors import InputError


def save_checkpoint(path: Path, trainer) -> None:
    strat_gen = trainer.strategy._gen
    payload = {
        "step": trainer.step,
        "model": trainer.model.state_dict(),
        "optimizers": {k: o.state_dict() for k, o in trainer.optimizers.items()},
        "strategy_state": {k: v.clone() for k, v in trainer.strategy_state.items()},
        "strategy_rng": None if strat_gen is None else strat_gen.get_state(),
        "rng": trainer.generator.get_state(),
        "view_queue": list(trainer.view_queue),
        "thresholds": {k: v.detach().clone() for k, v in trainer.thresholds.items()},
        "threshold_opt": None if trainer.threshold_opt is None else trainer.threshold_opt.state_dict(),
    }
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path, trainer) -> None:
    try:
        payload = torch.load(path, map_location=trainer.device, weights_only=False)
    except (OSError, RuntimeError, EOFError) as e:
        raise InputError(f"{path}: not a readable checkpoint ({e})") from None
    trainer.model.load_state_dict(payload["model"])
    trainer.model.to(device=trainer.device)
    trainer.optimizers = trainer.model.make_optimizers(scene_scale=trainer.data.scene_scale)
    for k, o in trainer.optimizers.items():
        o.load_state_dict(payload["optimizers"][k])
    trainer.strategy_state = payload["strategy_state"]
    if payload["strategy_rng"] is not None:
        trainer.strategy._generator()
        trainer.strategy._gen.set_state(payload["strategy_rng"])
    trainer.generator.set_state(payload["rng"])
    trainer.view_queue = list(payload["view_queue"])
    for k, v in payload["thresholds"].items():
        trainer.thresholds[k].data.copy_(v)
    if trainer.threshold_opt is not None and payload["threshold_opt"] is not None:
        trainer.threshold_opt.load_state_dict(payload["threshold_opt"])
    trainer.step = int(payload["step"])
