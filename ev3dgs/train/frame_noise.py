"""How noisy the training frames are, and how much that should weigh the blur term down against the events.

A blurry frame's squared error against the model's blur of its sub-poses has two parts: what the model gets
wrong, and the frame's own noise, which no model should fit. Where the frames are clean the first is all
there is; where they carry sensor noise (a dark scene at high ISO) the second can be most of it, and a model
that lowers the blur loss there renders the noise as detail (deblurring amplifies it). The event term is
measured against its own noise (losses.noise_event_loss); this module puts the blur term on the same footing:
its weight is the share of its error that the model can still fix,

    w = clamp(1 - s2 / mse, W_MIN, 1),

with s2 the frames' noise variance (display values, 1 = white) and mse the blur term's squared error as the
run goes. The trainer applies it as the event weight omega / w, so frames without noise (s2 = 0) train as
without it, bit for bit, and the blur term's gradients, which drive densification, keep their size.

The noise is estimated from the frames themselves (``estimate_noise``), as a user's frames come without a
noise figure, with the 3x3 mask of J. Immerkaer ("Fast noise variance estimation", CVIU 64(2), 1996),
[[1, -2, 1], [-2, 4, -2], [1, -2, 1]] (the difference of two Laplacians): it is zero on any constant or
linear ramp, so a smooth image - and motion blur makes frames smooth - leaves only the noise, and for white
Gaussian noise of sigma its response is Gaussian with standard deviation 6 sigma (the mask's L2 norm).
Immerkaer averages the absolute response; the median is taken here instead (as in Donoho's MAD estimate:
sigma = median |response| / (6 * 0.6745)), because edges and texture add large responses at a few pixels,
which move the mean (0.7-1.6 levels on noise-free built-in scenes) but not the median (0-0.16 levels). Under
one 8-bit level the estimate is 0: rounding alone can read as up to 0.99 levels (``estimate_noise``).
"""
from __future__ import annotations

import math

import numpy as np
import torch

W_MIN = 1.0 / 16.0   # the blur term keeps at least this share: the event weight grows at most 16-fold
MSE_MOMENTUM = 0.9   # exponential average of the blur term's squared error over steps (as losses.update_floor)
_MAD_NORMAL = 0.6744897501960817   # the median of |N(0, 1)|, the normal's 3/4 quantile
_MASK = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def estimate_noise(frames: np.ndarray, step: float | None = None) -> float:
    """The noise variance of ``frames`` ((N, H, W, C) uint8 or (N, H, W[, C]) floats in [0, 1]): the median
    form of Immerkaer's estimate (module doc) per frame and channel, as a variance in display values (1 =
    white), averaged. Below one level of the stored values (``step``; None: 1/255 for uint8 frames, 0 for
    floats) it is 0: rounding a smooth image makes the response an integer number of levels, at most 4 on a
    linear ramp (the second difference of a rounded ramp is -1, 0 or 1 along each axis), which reads as up
    to 4 / (6 * 0.6745) = 0.99 levels of noise where there is none. Frames smaller than 3x3 have none to
    give: 0."""
    x = np.asarray(frames)
    scale = 255.0 if x.dtype == np.uint8 else 1.0
    if step is None:
        step = 1.0 / 255.0 if x.dtype == np.uint8 else 0.0
    if x.ndim == 3:
        x = x[..., None]
    if x.ndim != 4:
        raise ValueError(f"frames must be (N, H, W) or (N, H, W, C), got shape {x.shape}")
    n, h, w, c = x.shape
    if h < 3 or w < 3 or n == 0:
        return 0.0

    def median_response(frame: np.ndarray) -> np.ndarray:
        """(C,) median |response| of one frame: the mask at every interior pixel from shifted views (a 3x3
        correlation, no SciPy needed), one frame at a time so that a long recording's float copy stays small."""
        f = frame.astype(np.float64) / scale
        resp = sum(_MASK[i, j] * f[i:h - 2 + i, j:w - 2 + j, :] for i in range(3) for j in range(3))
        return np.median(np.abs(resp), axis=(0, 1))

    sigma = np.stack([median_response(frame) for frame in x]) / (6.0 * _MAD_NORMAL)   # (N, C)
    var = float(np.mean(sigma ** 2))
    return var if var >= step * step else 0.0


def blur_weight(noise_var: float, mse: float | None) -> float:
    """The blur term's weight w (module doc) for frames of noise variance ``noise_var`` at a tracked squared
    error ``mse`` (None, before the first step: 1)."""
    if noise_var <= 0 or mse is None:
        return 1.0
    if torch.is_tensor(mse):   # the trainer's tracked error on the device (0-dim float64): nothing read back
        w = (1.0 - torch.div(torch.full_like(mse, noise_var), mse)).clamp(W_MIN, 1.0)   # (not noise_var / mse:
        return torch.where(torch.isfinite(mse) & (mse > 0), w, 1.0)                     # mse^-1 * noise_var)
    if not math.isfinite(mse) or mse <= 0:
        return 1.0
    return min(1.0, max(W_MIN, 1.0 - noise_var / mse))


def update_mse(tracked: float | None, mse: float) -> float | None:
    """``mse`` (one step's) as an exponential average over steps; a non-finite step leaves it as it was."""
    if torch.is_tensor(mse):   # on the device (0-dim float64): the same IEEE operations, nothing read back;
        # NaN stands for "nothing tracked yet" (None on the float path; blur_weight reads both as weight 1)
        if tracked is None:
            return torch.where(torch.isfinite(mse), mse, math.nan)
        avg = MSE_MOMENTUM * tracked + (1.0 - MSE_MOMENTUM) * mse
        return torch.where(torch.isfinite(mse), torch.where(torch.isfinite(tracked), avg, mse), tracked)
    if not math.isfinite(mse):
        return tracked
    return mse if tracked is None else MSE_MOMENTUM * tracked + (1.0 - MSE_MOMENTUM) * mse
