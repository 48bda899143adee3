"""Checkpoints hold everything a resumed run needs to continue exactly as an uninterrupted one: the model,
every optimizer's state, the densification statistics and RNG, the step and the trainer's own RNG; plus the
settings and the scene that made them, so a resume with other settings is refused instead of silently mixing
two runs. Written atomically (temporary file, then rename); read with ``weights_only=True`` (no pickled code).
"""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch

from ..config import from_dict
from ..errors import ConfigError, InputError
from .config import RESUMABLE_CHANGES, TrainConfig, mismatch_error, with_legacy_values

REQUIRED_KEYS = ("step", "model", "optimizers", "strategy_state", "strategy_rng", "rng", "view_queue")


def scene_fingerprint(data) -> dict:
    """What identifies the training data a checkpoint was made on (a different file at the same path too)."""
    return {"name": data.name, "width": int(data.width), "height": int(data.height), "views": int(data.n_views)}


def save_checkpoint(path: Path, trainer) -> None:
    """The core's state, then every term's (terms.Term.save: each under the keys it has always used, so
    checkpoints of runs made before the terms existed still load)."""
    strat_gen = trainer.strategy._gen
    payload = {
        "step": trainer.step,
        "model": trainer.model.state_dict(),
        "optimizers": {k: o.state_dict() for k, o in trainer.optimizers.items()},
        "strategy_state": {k: v.clone() for k, v in trainer.strategy_state.items()},
        "strategy_rng": None if strat_gen is None else strat_gen.get_state(),
        "rng": {"views": trainer.generator.get_state()},
        "view_queue": list(trainer.view_queue),
        "config": asdict(trainer.cfg),
        "scene": scene_fingerprint(trainer.data),
        "terms": [t.table for t in trainer.terms],
    }
    for term in trainer.terms:
        term.save(payload)
    from ..outputs import atomic_path

    with atomic_path(path) as tmp:  # a kill mid-write never leaves half a checkpoint under the final name
        torch.save(payload, tmp)


def _one_line(e: BaseException, limit: int = 160) -> str:
    text = (str(e).strip().splitlines() or [type(e).__name__])[0]
    return text if len(text) <= limit else text[:limit - 3] + "..."


def read_checkpoint(path: Path, device="cpu") -> dict:
    """The checkpoint's payload; a file that is not one (text, truncated, another program's) is a one-line
    InputError naming it, never a torch traceback."""
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # torch raises RuntimeError, UnpicklingError, EOFError, ValueError... by damage
        raise InputError(f"{path}: not a readable checkpoint (truncated, or not written by ev3dgs train): "
                         f"{_one_line(e)}") from None
    missing = [k for k in REQUIRED_KEYS if not isinstance(payload, dict) or k not in payload]
    if missing:
        raise InputError(f"{path}: not an ev3dgs training checkpoint (no {missing[0]!r})")
    return payload


def check_compatible(path: Path, payload: dict, cfg: TrainConfig, data) -> None:
    """Refuse to resume a checkpoint made with other settings or on other data: one ConfigError listing every
    difference as ``key: saved X vs given Y``. Only TrainConfig.RESUMABLE_CHANGES may differ."""
    diffs = []
    if payload.get("config") is not None:
        try:
            saved = from_dict(TrainConfig, with_legacy_values(payload["config"]))
        except (ConfigError, TypeError) as e:
            raise InputError(f"{path}: the checkpoint's settings are unreadable ({_one_line(e)})") from None
        # a run moved with its scene: the saved path is gone, the scene's fingerprint below identifies it
        moved = payload.get("scene") is not None and not Path(saved.scene).exists()
        ignore = RESUMABLE_CHANGES + (("scene",) if moved else ())
        diffs += saved.differences(cfg, ignore=ignore)
    if payload.get("scene") is not None:
        now = scene_fingerprint(data)
        diffs += [(f"scene {k}", v, now.get(k)) for k, v in payload["scene"].items() if now.get(k) != v]
    if diffs:
        raise mismatch_error(path, diffs)


def load_checkpoint(path: Path, trainer, payload: dict | None = None) -> None:
    """Restore the trainer's state from the checkpoint at ``path`` (after check_compatible)."""
    if payload is None:
        payload = read_checkpoint(path, trainer.device)
    check_compatible(path, payload, trainer.cfg, trainer.data)
    rng = payload["rng"]
    if not (isinstance(rng, dict) and "views" in rng):
        raise InputError(f"{path}: the checkpoint has one shared random stream (made before the view order and "
                         "event-pair draws were separated): it cannot be continued exactly; start the run again")
    try:
        trainer.model.load_state_dict(payload["model"])
        trainer.model.to(device=trainer.device)
        trainer.optimizers = trainer.model.make_optimizers(scene_scale=trainer.data.scene_scale)
        for k, o in trainer.optimizers.items():
            o.load_state_dict(payload["optimizers"][k])
    except (KeyError, ValueError, TypeError, RuntimeError) as e:
        raise InputError(f"{path}: the checkpoint's model or optimizer state is damaged ({_one_line(e)})") from None
    trainer.strategy_state = payload["strategy_state"]
    if payload["strategy_rng"] is not None:
        trainer.strategy._generator()
        trainer.strategy._gen.set_state(payload["strategy_rng"])
    trainer.generator.set_state(rng["views"])
    trainer.view_queue = list(payload["view_queue"])
    for term in trainer.terms:
        term.load(payload, path)
    trainer.step = int(payload["step"])
