"""Evaluation metrics: PSNR, SSIM (the same SSIM as the training loss, in float64) and the LPIPS status
(the network itself is in lpips.py)."""
from __future__ import annotations

import math
import os

import numpy as np
import torch

from .losses import ssim


def _as_float64(img) -> np.ndarray:
    if torch.is_tensor(img):
        img = img.detach().cpu().numpy()
    arr = np.asarray(img)
    if arr.dtype == np.uint8:
        return arr.astype(np.float64) / 255.0
    return arr.astype(np.float64)


def psnr(a, b) -> float:
    """10*log10(1/MSE) for [0,1] float images (torch or numpy) or uint8 images (divided by 255). The MSE is
    clamped at 1e-12, so identical images give a large finite value (120 dB)."""
    x, y = _as_float64(a), _as_float64(b)
    if x.shape != y.shape:
        raise ValueError(f"psnr needs equal shapes, got {x.shape} and {y.shape}")
    mse = max(float(np.mean((x - y) ** 2)), 1e-12)
    return 10.0 * math.log10(1.0 / mse)


def psnr_later(a: torch.Tensor, b: torch.Tensor):
    """:func:`psnr` of two [0,1] float tensors without reading anything back: the float64 MSE stays on their
    device and the PSNR is computed from it when read back (readback.Later). The same formula; the MSE's sum
    may round differently from NumPy's in the last bits."""
    from .readback import Later

    if a.shape != b.shape:
        raise ValueError(f"psnr needs equal shapes, got {tuple(a.shape)} and {tuple(b.shape)}")
    mse = torch.mean((a.detach().to(torch.float64) - b.detach().to(torch.float64)) ** 2)
    return Later(mse, _psnr_from_mse)


def _psnr_from_mse(mse: float) -> float:
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def ssim_metric(a, b) -> float:
    """Mean SSIM of two (H, W, C) or (H, W) images as a float, computed in float64 with ``losses.ssim``."""
    x = torch.from_numpy(np.ascontiguousarray(_as_float64(a)))
    y = torch.from_numpy(np.ascontiguousarray(_as_float64(b)))
    with torch.no_grad():
        return float(ssim(x, y))


def lpips_unavailable_reason(weights_path) -> str | None:
    """None if ``weights_path`` names an LPIPS network ("alex", "vgg": its weights are fetched into torch's hub
    cache on first use) or is a readable file, else why LPIPS is reported as null."""
    if weights_path in ("alex", "vgg"):
        return None
    if weights_path and os.path.isfile(weights_path) and os.access(weights_path, os.R_OK):
        return None
    where = f" ({weights_path!s} is not a readable file)" if weights_path else ""
    return ("LPIPS not computed: pass --lpips alex (or vgg) to use the reference weights (downloaded once into "
            "torch's hub cache), or --lpips-weights with a local weights file (see \"LPIPS\" in the ev3dgs eval "
            "docs, docs/commands/ev3dgs-eval.md)"
            f"{where}")
