"""Training losses: blur (rendered sub-poses averaged against the blurry frame) and event (log-intensity
change between sub-poses against the observed signed event count).

Fixes relative to the published E2NeRF / Ev3DGS code (reference notes section 4):

* The event loss is a non-negative quantity the trainer ADDS to the blur loss (Ev3DGS subtracted it).
* The log is ``ev3dgs.logmap.safe_log_torch``, the same lin-log the simulator uses: finite value and finite,
  bounded gradient at exactly 0 (E2NeRF's ``torch.where(x <= 20, x * f, log(x))`` gives NaN gradients at
  black pixels even when they are masked out).
* The sRGB transfer functions clamp inside their pow branches so gradients are finite for all inputs.
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F

from ..logmap import DEFAULT_LOG_KNEE, safe_log_torch
from ..sensor import LUMINANCE_WEIGHTS, cfa_channels

_BAYER = {"RGGB", "BGGR", "GRBG", "GBRG"}
_SRGB_KNEE = 0.04045
_LINEAR_KNEE = 0.0031308


def srgb_to_linear_torch(x: torch.Tensor) -> torch.Tensor:
    """sRGB EOTF (display [0,1] -> linear). Negative inputs are clamped to 0 (zero gradient there); the pow
    branch only ever sees values >= the knee, so gradients are finite everywhere, including at 0."""
    x = torch.clamp(x, min=0.0)
    low = x / 12.92
    high = ((torch.clamp(x, min=_SRGB_KNEE) + 0.055) / 1.055) ** 2.4
    return torch.where(x <= _SRGB_KNEE, low, high)


def linear_to_srgb_torch(x: torch.Tensor) -> torch.Tensor:
    """Inverse sRGB EOTF (linear -> display [0,1]). Clamped at 0 below; the x^(1/2.4) branch only sees values
    >= its knee, so the infinite slope of the power at 0 never reaches the gradient."""
    x = torch.clamp(x, min=0.0)
    low = x * 12.92
    high = 1.055 * torch.clamp(x, min=_LINEAR_KNEE) ** (1.0 / 2.4) - 0.055
    return torch.where(x <= _LINEAR_KNEE, low, high)


def _gaussian_window(size: int, sigma: float, channels: int, dtype, device) -> torch.Tensor:
    g = torch.tensor([math.exp(-((i - size // 2) ** 2) / float(2 * sigma ** 2)) for i in range(size)],
                     dtype=torch.float64)
    g = g / g.sum()
    w2 = torch.outer(g, g).to(dtype=dtype, device=device)
    return w2.expand(channels, 1, size, size).contiguous()


def ssim(a: torch.Tensor, b: torch.Tensor, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images, as graphdeco 3DGS ``utils/loss_utils.py``: Gaussian window 11,
    sigma 1.5, per-channel conv2d with zero 'same' padding (padding=5, groups=C), C1=0.01^2, C2=0.03^2."""
    if a.shape != b.shape:
        raise ValueError(f"ssim needs equal shapes, got {tuple(a.shape)} and {tuple(b.shape)}")
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    if a.ndim != 3:
        raise ValueError(f"ssim expects (H, W, C) images, got {tuple(a.shape)}")
    c = a.shape[-1]
    img1 = a.permute(2, 0, 1).unsqueeze(0)
    img2 = b.permute(2, 0, 1).unsqueeze(0).to(img1.dtype)
    win = _gaussian_window(window_size, sigma, c, img1.dtype, img1.device)
    pad = window_size // 2

    def conv(z):
        return F.conv2d(z, win, padding=pad, groups=c)

    mu1, mu2 = conv(img1), conv(img2)
    mu1_sq, mu2_sq, mu1_mu2 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    sigma1_sq = conv(img1 * img1) - mu1_sq
    sigma2_sq = conv(img2 * img2) - mu2_sq
    sigma12 = conv(img1 * img2) - mu1_mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim_map = ((2 * mu1_mu2 + c1) * (2 * sigma12 + c2)) / ((mu1_sq + mu2_sq + c1) * (sigma1_sq + sigma2_sq + c2))
    return ssim_map.mean()


def blur_loss(renders: torch.Tensor, target: torch.Tensor, lam: float = 0.2, space: str = "srgb") -> torch.Tensor:
    """(K, H, W, 3) sub-pose renders and the (H, W, 3) blurry sRGB frame -> (1-lam)*MSE + lam*(1-SSIM) of
    their average. ``space="srgb"`` averages display values; ``space="linear"`` averages in linear light
    (each render through the sRGB EOTF, mean, back to sRGB), which is how a real exposure integrates."""
    if renders.ndim != 4:
        raise ValueError(f"renders must be (K, H, W, 3), got {tuple(renders.shape)}")
    if space == "srgb":
        avg = renders.mean(dim=0)
    elif space == "linear":
        avg = linear_to_srgb_torch(srgb_to_linear_torch(renders).mean(dim=0))
    else:
        raise ValueError(f"space must be 'srgb' or 'linear', got {space!r}")
    target = target.to(avg.dtype)
    mse = torch.mean((avg - target) ** 2)
    return (1.0 - lam) * mse + lam * (1.0 - ssim(avg, target))


def log_intensity(renders: torch.Tensor, color_filter: str = "none", knee: float = DEFAULT_LOG_KNEE) -> torch.Tensor:
    """(K, H, W, 3) sRGB renders -> (K, H, W) safe log of the linear intensity each event pixel sees: the
    sRGB luminance (``LUMINANCE_WEIGHTS``) for ``color_filter="none"``, or the pixel's own CFA channel for a
    Bayer pattern ("RGGB", "BGGR", "GRBG", "GBRG"). Same ``safe_log_torch`` and knee as the simulator."""
    if renders.ndim != 4 or renders.shape[-1] != 3:
        raise ValueError(f"renders must be (K, H, W, 3), got {tuple(renders.shape)}")
    lin = srgb_to_linear_torch(renders)
    cf = (color_filter or "none")
    if cf.lower() == "none":
        w = torch.as_tensor(LUMINANCE_WEIGHTS, dtype=lin.dtype, device=lin.device)
        inten = (lin * w).sum(dim=-1)
    elif cf.upper() in _BAYER:
        k, h, wd, _ = lin.shape
        idx = torch.as_tensor(cfa_channels(cf.upper(), h, wd), dtype=torch.long, device=lin.device)
        inten = torch.gather(lin, -1, idx[None, :, :, None].expand(k, h, wd, 1)).squeeze(-1)
    else:
        raise ValueError(f"color_filter must be 'none' or a Bayer pattern {sorted(_BAYER)}, got {color_filter!r}")
    return safe_log_torch(inten, knee)


def event_loss(log_l: torch.Tensor, targets: torch.Tensor, pairs: Sequence[tuple[int, int]],
               theta_pos, theta_neg) -> torch.Tensor:
    """Mean squared error between predicted and observed signed event counts over all pairs and pixels.

    For pair (k1, k2): predicted = (log_l[k2] - log_l[k1]) / theta, with theta = theta_pos where the change
    is positive and theta_neg elsewhere (``torch.where``, so 0-d tensors requiring grad work as learnable
    thresholds; python floats work too).

    The target is the RAW signed count, with no +-0.5 offset. E2NeRF adds +-0.5 because it assumes the
    pixel's reference was reset exactly at the first pose, so n observed events mean a change in
    [n, n+1) thresholds. Our simulator's per-pixel reference carries its residual across pose boundaries
    (it is not reset at sub-pose times), so the residual at k1 is ~uniform in one threshold and
    E[count] = delta/theta exactly: the unbiased target is the count itself.

    Returns a non-negative scalar that the trainer must ADD to the blur loss (the published Ev3DGS
    ``loss = image_loss - event_loss`` subtracted it, rewarding wrong event predictions).
    """
    if log_l.ndim != 3 or targets.ndim != 3:
        raise ValueError("log_l must be (K, H, W) and targets (P, H, W)")
    if len(pairs) != targets.shape[0]:
        raise ValueError(f"{len(pairs)} pairs but {targets.shape[0]} target maps")
    for th in (theta_pos, theta_neg):
        if not torch.is_tensor(th) and not float(th) > 0:
            raise ValueError(f"thresholds must be positive, got {th!r}")
    if len(pairs) == 0:
        return log_l.sum() * 0.0
    idx = torch.as_tensor([tuple(pr) for pr in pairs], dtype=torch.long, device=log_l.device)
    # index_select, not log_l[idx]: the backward of advanced indexing with repeated indices (every pose is in
    # several pairs) is index_put_(accumulate=True), whose multi-threaded CPU kernel adds in a racy order;
    # index_select's backward (index_add_) adds slice by slice in index order: bitwise reproducible
    delta = log_l.index_select(0, idx[:, 1]) - log_l.index_select(0, idx[:, 0])
    tp = torch.as_tensor(theta_pos, dtype=delta.dtype, device=delta.device)
    tn = torch.as_tensor(theta_neg, dtype=delta.dtype, device=delta.device)
    theta = torch.where(delta > 0, tp, tn)
    pred = delta / theta
    return torch.mean((pred - targets.to(pred.dtype)) ** 2)
