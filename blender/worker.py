"""What runs in a render worker process: build the scene once, then render poses on request.

Each worker is a separate (spawned) process because bpy state is global and a crash in Blender must not
take the parent down; ev3dgs.sim.dataset drives a pool of them."""
from __future__ import annotations

import os

_INFO: dict | None = None


def init(kwargs: dict) -> None:
    global _INFO
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from . import render

    _INFO = render.init_scene(**kwargs)


def info() -> dict:
    """JSON-safe scene info (bounds as nested lists)."""
    import numpy as np

    return {k: np.asarray(v).tolist() if hasattr(v, "__len__") and not isinstance(v, str) else v
            for k, v in (_INFO or {}).items()}


def render_poses(key: str, poses):
    from . import render

    frames, readback = render.render(poses)
    return key, frames, readback, info()
