"""What every exporter shares: the staged output folder, progress, images.

Output folder: everything is written into a temporary sibling `.DIR.tmp-PID` and renamed to DIR at the end,
so an interrupted export leaves nothing half-written under DIR (a later export removes the sibling once its
process is gone). An existing non-empty DIR is refused unless `force`; with `force` the old folder is moved
aside, the new one renamed into place, then the old one deleted.

Events are never loaded whole: ev3dgs.event_file.EventFile reads `/events/*` in blocks of `chunk` rows
(default 2^20 events, 13 MiB as t, x, y, p), with the file opened once.
"""
from __future__ import annotations

import contextlib
import errno as _errno
import os
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..claims import may_replace
from ..errors import InputError
from ..outputs import OutputError, _pid_alive, check_output_dir, os_error_message, publish, write_image

_STAGE = ".{name}.tmp-{pid}"


# ------------------------------------------------------------------------------------------ output folder

def _is_empty_dir(p: Path) -> bool:
    with os.scandir(p) as it:
        return next(it, None) is None


def check_out_dir(out: str | os.PathLike, force: bool, estimated_bytes: int = 0) -> Path:
    """Fail now (one line) if DIR is a file, not writable, short of space, or non-empty without force."""
    out = Path(out)
    check_output_dir(out, estimated_bytes, force=force)   # a non-empty folder: one line naming --force
    return out


def _remove_stale_stages(out: Path) -> None:
    """Delete `.DIR.tmp-PID` / `.DIR.old-PID` folders left by exports whose process is gone."""
    parent = out.parent if out.parent.exists() else None
    if parent is None:
        return
    for kind in ("tmp", "old"):
        prefix = f".{out.name}.{kind}-"
        for entry in parent.iterdir():
            tag = entry.name[len(prefix):] if entry.name.startswith(prefix) else ""
            if tag.isdigit() and entry.is_dir() and not entry.is_symlink() and not _pid_alive(int(tag)):
                shutil.rmtree(entry, ignore_errors=True)


@contextlib.contextmanager
def staged_dir(out: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """Yield an empty temporary folder beside `out`; on success it becomes `out` (see module doc)."""
    out = Path(out)
    check_out_dir(out, force)
    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_stages(out)
    stage = out.with_name(_STAGE.format(name=out.name, pid=os.getpid()))
    shutil.rmtree(stage, ignore_errors=True)
    old = None
    try:
        stage.mkdir()
        yield stage
        if out.exists():
            if not may_replace(out) or (not force and not _is_empty_dir(out)):  # made or filled while we worked
                raise OutputError(f"--out {out} is a folder that is not empty (filled while exporting); pass --force "
                                      "to replace its contents", _errno.ENOTEMPTY)
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
        publish(stage, out)   # never over a folder that appeared meanwhile (ev3dgs.claims)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException as e:
        shutil.rmtree(stage, ignore_errors=True)
        if old is not None and old.exists() and not os.path.lexists(out):
            with contextlib.suppress(OSError):
                os.rename(old, out)   # the earlier output back where it was
        if isinstance(e, OSError):
            raise OutputError(f"cannot write {os_error_message(e, out)}", e.errno) from None
        raise


# ------------------------------------------------------------------------------------------ events

def progress(total: int, desc: str, quiet: bool, unit: str = "ev"):
    """A tqdm bar on a terminal; silent when stderr is not a TTY or with quiet."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, unit_scale=True, leave=False,
                disable=quiet or not sys.stderr.isatty(), file=sys.stderr)


# ------------------------------------------------------------------------------------------ images

def write_png(path: Path, rgb: np.ndarray, alpha: bool = False) -> None:
    """uint8 (H, W, 3) RGB -> PNG (lossless), RGBA with alpha 255 when `alpha`."""
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"{path.name}: expected uint8 (H, W, 3) image, found {img.dtype} {img.shape}")
    bgr = img[..., ::-1]
    if alpha:
        bgr = np.concatenate([bgr, np.full(img.shape[:2] + (1,), 255, np.uint8)], axis=2)
    write_image(path, np.ascontiguousarray(bgr), "PNG")


def image_width(n: int, step: int = 1) -> int:
    """Digits for zero-padded indices 0..(n-1)*step so that names sort in index order."""
    return max(3, len(str(max(0, n - 1) * step)))


def scene_events_path(scene) -> str:
    """The HDF5 file that holds the scene's events (schema.read gives LazyEvents)."""
    path = getattr(scene.events.t, "path", None)
    if path is None:
        raise InputError("the scene's events are not file-backed (give a scene file read with schema.read)")
    return path
