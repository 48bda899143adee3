"""`ev3dgs export-dataset`: a scene file in the layouts other methods and tools read.

One module per format (e2nerf, events_h5, aedat4, transforms), each `export(scene, events_path, stage, quiet,
**options) -> dict` writing into a staged folder (common.staged_dir) that becomes --out only when complete.
Events are streamed from the scene file in blocks (ev3dgs.event_file.EventFile), never loaded whole.
"""
from __future__ import annotations

import os
from pathlib import Path

from .. import schema
from ..errors import InputError

FORMATS = ("e2nerf", "events-h5", "aedat4", "transforms")
_EVENTS_ONLY_OK = ("events-h5", "aedat4")


def _module(fmt: str):
    if fmt == "e2nerf":
        from . import e2nerf as m
    elif fmt == "events-h5":
        from . import events_h5 as m
    elif fmt == "aedat4":
        from . import aedat4 as m
    elif fmt == "transforms":
        from . import transforms as m
    else:
        raise InputError(f"unknown export format {fmt!r} (one of {', '.join(FORMATS)})")
    return m


def estimated_bytes(sc, fmt: str, bins: int = 4) -> int:
    """A rough upper bound of the export's size, for the free-space check before any work."""
    H, W = sc.camera.height, sc.camera.width
    n_img = (len(sc.train) if sc.train is not None else 0) * (2 if fmt == "transforms" else 1)
    n_img += len(sc.test.images) if sc.test is not None else 0
    size = n_img * H * W * 3                                  # PNG of smooth renders: below raw size
    if fmt == "e2nerf":
        size += (len(sc.train) if sc.train is not None else 0) * bins * H * W * 8
    elif fmt in _EVENTS_ONLY_OK:
        size += len(sc.events) * 13
    return int(size)


def export_dataset(scene: str | os.PathLike, fmt: str, out: str | os.PathLike, force: bool = False,
                   quiet: bool = False, **options) -> dict:
    """Export scene file `scene` as `fmt` into folder `out` (atomically; see common.staged_dir)."""
    from .common import check_out_dir, scene_events_path, staged_dir

    m = _module(fmt)
    out = Path(out)
    if Path(scene).resolve().is_relative_to(out.resolve()):
        raise InputError(f"--out {out} contains the scene file {scene}: choose another folder")
    check_out_dir(out, force)                                 # before reading anything: a fast, clear failure
    sc = schema.read(scene, require_complete=fmt not in _EVENTS_ONLY_OK)
    check_out_dir(out, force, estimated_bytes(sc, fmt, options.get("bins", 4)))
    ev_path = scene_events_path(sc)
    with staged_dir(out, force) as stage:
        info = m.export(sc, ev_path, stage, quiet=quiet, **options)
    return {"format": fmt, "out": str(out), **info}
