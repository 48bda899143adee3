"""`ev3dgs train --view`: the viewer beside a running training, through Trainer.fit's on_step callback.

The callback returns at once except every `every` steps (and at the last step), when it copies the current
Gaussians into splat arrays (one pass over N Gaussians, no rendering: the browser renders) and hands them to
viser, whose own thread sends them. The training loop itself is untouched.
"""
from __future__ import annotations

from contextlib import contextmanager

from ..errors import InputError


class LiveUpdate:
    def __init__(self, viewer, every: int, iterations: int):
        self.viewer, self.every, self.iterations = viewer, every, iterations
        self.updates = 0

    def __call__(self, trainer, rec: dict) -> None:
        step = trainer.step
        if step % self.every and step != self.iterations:
            return
        from .data import splat_arrays

        self.viewer.show_splats(splat_arrays(trainer.model))
        self.viewer.set_status(f"training: step {step}/{self.iterations}, loss {rec.get('loss', float('nan')):.5f}, "
                               f"PSNR vs blurry {rec.get('psnr_blurry', float('nan')):.2f} dB, "
                               f"{len(trainer.model)} Gaussians")
        self.updates += 1


@contextmanager
def live_view(args, cfg):
    """Yields the on_step callback for Trainer.fit (None without --view); stops the viewer afterwards."""
    if not getattr(args, "view", False):
        yield None
        return
    if args.view_every < 1:
        raise InputError(f"--view-every must be >= 1, got {args.view_every}")
    from .data import load_scene
    from .server import Viewer, require_viser

    require_viser()
    content = load_scene(cfg.scene)
    viewer = Viewer(args.view_host, args.view_port, label=f"ev3dgs train: {content.scene.name}")
    try:
        viewer.show_scene(content)
        viewer.set_status(f"training: starting ({cfg.iterations} steps)")
        viewer.announce()
        yield LiveUpdate(viewer, args.view_every, cfg.iterations)
    finally:
        viewer.stop()
