"""The one safe log of intensity, shared by the simulator and the trainer's event loss.

    safe_log(I) = log(I)                         for I >= knee
                = log(knee) + (I - knee) / knee  for I <  knee

A lin-log curve: pure log above the knee (so threshold crossings there are exact log-intensity steps), a
straight line below it that meets the log with the same value *and* slope at the knee (C1-smooth, unlike
v2e's lin_log whose slope jumps 3x at its 20 DN knee). It is finite at 0 (log(knee) - 1) and for negative
noise excursions, with bounded slope 1/knee, so gradients through it never blow up.

Why the default knee is 1e-3 of white: a DAVIS pixel's photoreceptor (photodiode into a subthreshold
transistor with feedback) responds logarithmically over 5-6 decades of photocurrent (DAVIS346: 120 dB) and
turns linear only where the photocurrent approaches the junction's dark current, several decades below a
well-lit scene's white. So every level that a normally exposed frame shows belongs in the log region:
1e-3 of white is sRGB DN ~3, the bottom of an 8-bit frame. Doubling the light then gives log 2 = 0.69
(3 events at theta 0.2) at I = 0.02 as at 0.5. The previous default, v2e's 20/255 (sRGB DN ~79: v2e applies
its 20 DN knee to display-referred 8-bit input), put the bottom third of the frame's range on the linear
segment, where doubling 0.02 gave 0.26 (1 event). It is not lower because below ~1e-3 what rendered or
8-bit inputs carry is quantisation and Monte-Carlo noise rather than signal: on the linear segment (slope
1/knee) such noise moves the log by about noise/knee, whereas a pure log down to 1e-5 turns it into floods
of events. A scene sets its own in [sensor.dvs] log_knee; it is stored in the scene file (/events attr
log_knee) and the trainer reads it from there, so simulator and trainer use the same curve.
"""
from __future__ import annotations

import math

import numpy as np

DEFAULT_LOG_KNEE = 1e-3


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
