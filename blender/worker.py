"""What runs in a render worker process: build the scene once, then render poses on request.

Each worker is a separate (spawned) process because bpy state is global and a crash in Blender must not
take the parent down; ev3dgs.sim.dataset drives a pool of them."""
from __future__ import annotations

import os
import sys
import threading
import time

_INFO: dict | None = None
_ERROR: BaseException | None = None   # why the scene could not be built; raised by every render_poses


def _parent_pid() -> int:
    import multiprocessing

    parent = multiprocessing.parent_process()
    return parent.pid if parent is not None and parent.pid else os.getppid()


def die_with_parent(poll_s: float = 0.5) -> None:
    """Exit when the process that started this worker dies (even by kill -9), instead of rendering on for
    minutes with ~330 MB of Blender (and keeping multiprocessing's resource tracker alive with it).

    Linux: the kernel sends SIGKILL at the parent's death (prctl PR_SET_PDEATHSIG). Everywhere: a daemon thread
    exits when the parent PID changes (the orphan was re-parented)."""
    ppid = _parent_pid()
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            import signal

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != ppid:  # the parent died before the line above
        os._exit(1)

    def watch():
        while True:
            time.sleep(poll_s)
            if os.getppid() != ppid:
                os._exit(1)

    threading.Thread(target=watch, name="ev3dgs-parent-watchdog", daemon=True).start()


def init(kwargs: dict, die_with_parent_: bool = True) -> None:
    """Pool initializer: build the scene once. An error is kept and raised by render_poses, so that it reaches
    the parent as that exception (a failing initializer would print a traceback here and break the pool,
    which the parent can only report as a crash)."""
    global _INFO, _ERROR
    if die_with_parent_:
        die_with_parent()
    try:
        _init(kwargs)
    except Exception as e:
        _ERROR = e if isinstance(e, (ValueError, RuntimeError, OSError)) else RuntimeError(f"{type(e).__name__}: {e}")


def _init(kwargs: dict) -> None:
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

    if _ERROR is not None:
        raise _ERROR
    frames, readback = render.render(poses)
    return key, frames, readback, info()
