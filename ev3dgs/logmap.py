"""The one safe log of intensity, shared by the simulator and the trainer's event loss.

    safe_log(I) = log(I)                         for I >= knee
                = log(knee) + (I - knee) / knee  for I <  knee

A lin-log curve: pure log above the knee (so threshold crossings there are exact log-intensity steps), a
straight line below it that meets the log with the same value *and* slope at the knee (C1-smooth, unlike
v2e's lin_log whose slope jumps 3x at its 20 DN knee). It is finite at 0 (log(knee) - 1) and for negative
noise excursions, with bounded slope 1/knee, so gradients through it never blow up. The default knee is
v2e's 20/255 of sensor white, so dark pixels are as insensitive as users of v2e expect.
"""
from __future__ import annotations

import math

import numpy as np

DEFAULT_LOG_KNEE = 20.0 / 255.0


def safe_log(intensity, knee: float = DEFAULT_LOG_KNEE) -> np.ndarray:
    """Numpy version, in the input's float precision (float64 for integer input). Vectorised: SIMD log
    of max(I, knee), then the linear segment written only where some values lie below the knee."""
    x = np.asarray(intensity)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    k = x.dtype.type(knee)
    out = np.log(np.maximum(x, k))
    if out.ndim == 0:
        return out if x >= k else (math.log(knee) - 1.0) + x / k
    if x.size and x.min() < k:
        below = x < k
        np.copyto(out, (x.dtype.type(math.log(knee) - 1.0) + x / k), where=below)
    return out


def safe_log_torch(intensity, knee: float = DEFAULT_LOG_KNEE):
    """Torch version with finite gradients everywhere (the log branch never sees values below the knee)."""
    import torch

    lin = math.log(knee) + (intensity - knee) / knee
    return torch.where(intensity >= knee, torch.log(torch.clamp(intensity, min=knee)), lin)
