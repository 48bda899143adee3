"""Motion blur as a real sensor makes it: average the sharp sub-frames in the raw (linear light) domain,
add shot and read noise, then develop with the ISP."""
from __future__ import annotations

import numpy as np

from ..errors import InputError
from .config import ISPConfig, SensorNoise
from .isp import check_image, forward_isp, inverse_isp

_MAX_SIGNAL = 2.0  # raw above this is far beyond full well; capped so huge HDR values keep Poisson finite


def _check_frames(frames) -> np.ndarray:
    x = np.asarray(frames)
    if x.ndim != 4 or x.shape[-1] != 3 or min(x.shape) < 1:
        raise InputError(f"frames must have shape (S, H, W, 3) with S, H, W >= 1, got {x.shape}")
    check_image(x.reshape(-1, *x.shape[2:]), what="frames")
    return x


def add_sensor_noise(raw: np.ndarray, noise: SensorNoise, rng: np.random.Generator) -> np.ndarray:
    """Shot + read noise on raw (1.0 = full well). Electrons = raw * full_well * 100 / iso; the well clips
    at full capacity; Poisson(electrons) + Normal(0, read_noise) electrons, back to raw units.

    Variance in raw units (below saturation): (raw * fw + read_noise**2) / fw**2, fw = full_well * 100 / iso.
    """
    fw = noise.full_well_electrons * 100.0 / noise.iso
    lam = np.clip(raw, 0.0, _MAX_SIGNAL) * fw
    electrons = np.minimum(rng.poisson(lam).astype(np.float64), fw)
    electrons += rng.normal(0.0, noise.read_noise_electrons, size=np.shape(raw))
    return electrons / fw


def blur_frames(frames, cfg: ISPConfig | None = None, noise: SensorNoise | None = None,
                seed: int = 0) -> np.ndarray:
    """(S, H, W, 3) uint8 sRGB or float linear sub-frames -> one uint8 sRGB (H, W, 3) blurry frame."""
    cfg = cfg or ISPConfig()
    x = _check_frames(frames)
    raw = inverse_isp(x[0], cfg)
    for frame in x[1:]:
        raw += inverse_isp(frame, cfg)
    raw /= x.shape[0]
    if noise is not None:
        raw = add_sensor_noise(raw, noise, np.random.default_rng(seed))
    return forward_isp(raw, cfg)
