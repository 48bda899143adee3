"""What runs in a render worker process: build the scene once, then render poses on request.

Each worker is a separate (spawned) process because bpy state is global and a crash in Blender must not
take the parent down; ev3dgs.sim.dataset drives a pool of them."""
from __future__ import annotations

import os
import sys

_INFO: dict | None = None


def init(kwargs: dict) -> None:
    global _INFO
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    # A parent that imported bpy added bpy's own script folders to sys.path, which spawn copies here;
    # with them first, `import bpy` finds bpy/5.0/scripts/modules/bpy instead of the module. Drop them.
    sys.path[:] = [p for p in sys.path if f"{os.sep}bpy{os.sep}" not in p]
    # Blender logs every saved frame on stdout: keep the parent's terminal for the progress bar. Errors
    # still reach the parent as exceptions, and stderr stays open for crash messages.
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)
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
