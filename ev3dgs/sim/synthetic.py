"""Generated input sequences: the built-in default for `make demo`, the benchmark and tests."""
from __future__ import annotations

import cv2
import numpy as np


def texture(height: int, width: int, seed: int = 0, blur_px: float = 2.0) -> np.ndarray:
    """A non-repeating Gaussian-blurred noise texture, linear intensity in [5/255, 250/255]."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), blur_px)
    tex = (tex - tex.min()) / max(float(tex.max() - tex.min()), 1e-12)
    return (5.0 + 245.0 * tex) / 255.0


def moving_texture(height: int = 260, width: int = 346, frames: int = 17, px_per_frame: float = 1.0,
                   dt_us: int = 1000, seed: int = 0, color: bool = False):
    """A texture sliding right by `px_per_frame` per frame (sub-pixel shifts by linear resampling).

    Returns (frames float32 (T,H,W) or (T,H,W,3), t_us int64 (T,)).
    """
    span = int(np.ceil(px_per_frame * (frames - 1))) + 2
    base = texture(height, width + span, seed)
    if color:
        tint = np.stack([base, np.roll(base, 7, axis=0), np.roll(base, 13, axis=1)], axis=-1)
        base = tint
    out = []
    for k in range(frames):
        shift = px_per_frame * k
        m = np.float32([[1, 0, shift], [0, 1, 0]])
        out.append(cv2.warpAffine(base, m, (width, height), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT))
    return np.stack(out).astype(np.float32), np.arange(frames, dtype=np.int64) * dt_us
