"""[poses] (--refine-poses): learnable per-view SE(3) corrections of each exposure's trajectory (start and end,
interpolated over the sub-poses; train/pose_refine.py). It corrects the view's cameras before the core renders
them; its own Adam steps after the backward pass. Writes RUN/trajectory.npz (read by eval)."""
from __future__ import annotations

from ...errors import ConfigError
from . import Term, register


@register
class Poses(Term):
    table = "poses"
    builtin = True

    @classmethod
    def build(cls, trainer):
        if not trainer.cfg.refine_poses:
            return None
        if trainer.cfg.oracle:
            raise ConfigError("--refine-poses with --oracle: the oracle's poses are exact")
        return cls(trainer)

    def __init__(self, trainer):
        super().__init__(trainer)
        from ..pose_refine import PoseRefiner

        self.refiner = PoseRefiner.for_training(trainer.data, trainer.cfg, trainer.device)

    def adjust_cameras(self, step, poses):
        # the view's corrected sub-poses, differentiable in its corrections
        return self.refiner.viewmats(step.view, poses.dtype)[:step.k]

    def after_backward(self, step):
        return self.refiner.step(self.trainer.step)

    def save(self, payload):
        payload["pose_refiner"] = self.refiner.state_dict()

    def load(self, payload, path):
        if payload.get("pose_refiner") is not None:
            self.refiner.load_state_dict(payload["pose_refiner"])

    def write(self, run_dir):
        self.refiner.save(run_dir / "trajectory.npz")
