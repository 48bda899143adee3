"""Reading the simulator CLI's input: an .npz with `frames` (T,H,W[,3]) and `t_us` (T,)."""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from ..errors import InputError


def load_frames_npz(path: str | Path, need_t: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"input file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            if "frames" not in keys:
                raise InputError(f"{path}: missing array 'frames' (has: {', '.join(sorted(keys)) or 'none'})")
            if need_t and "t_us" not in keys:
                raise InputError(f"{path}: missing array 't_us' (has: {', '.join(sorted(keys))})")
            frames = z["frames"]
            t_us = z["t_us"] if "t_us" in keys else None
    except InputError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise InputError(f"{path}: not a readable .npz file ({e})") from None
    if frames.ndim not in (3, 4) or (frames.ndim == 4 and frames.shape[-1] != 3):
        raise InputError(f"{path}: 'frames' must have shape (T, H, W) or (T, H, W, 3), got {frames.shape}")
    if len(frames) == 0:
        raise InputError(f"{path}: 'frames' is empty")
    return frames, t_us
