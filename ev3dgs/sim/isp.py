"""A minimal camera ISP: sRGB <-> camera raw (linear, white-balance-free, optionally Bayer mosaiced).

Raw is float64 with 1.0 = sensor saturation. The forward path is the usual one:
clip at saturation (1.0) -> demosaic (OpenCV) -> white balance gains -> highlight clip -> colour matrix ->
clip to [0, 1] -> sRGB encoding -> uint8.
Raw values below 0 (read noise around black) are kept through demosaic, white balance and colour matrix and
clipped only at the output: clipping them at the raw stage kept only the positive half of the noise, which
then went through different channel gains and tinted every shadow (a 0.002 grey at ISO 3200 came out
(19.6, 12.0, 17.3), magenta, instead of ~7). The demosaic carries raw in [-RAW_PEDESTAL, 1].
`inverse_isp` undoes it exactly (up to the final uint8 rounding) for in-gamut colours.
"""
from __future__ import annotations

import colour
import cv2
import numpy as np

from ..errors import InputError
from .config import ISPConfig
from .effects.color import cfa_channels

# OpenCV names its Bayer codes after the 2x2 block starting at (1, 1), not at (0, 0), and its "RGB" output is
# channel-swapped relative to that name. Found empirically with a flat-colour field (and re-checked by
# tests/test_isp.py::test_mosaic_flat_field_round_trip): pattern named row-major from (0, 0) -> code giving RGB.
BAYER_TO_RGB = {
    "RGGB": cv2.COLOR_BayerBG2RGB,
    "BGGR": cv2.COLOR_BayerRG2RGB,
    "GRBG": cv2.COLOR_BayerGB2RGB,
    "GBRG": cv2.COLOR_BayerGR2RGB,
}
RAW_PEDESTAL = 0.25  # demosaic range below black (read noise); values under -RAW_PEDESTAL are clipped
_PAD = 2  # even reflect-101 padding keeps the CFA phase and gives the demosaic a full neighbourhood at borders


def srgb_to_linear(image: np.ndarray) -> np.ndarray:
    """sRGB-encoded uint8 (0..255) or float (0..1) -> linear float64, via colour-science's sRGB EOTF."""
    x = np.asarray(image)
    x = x.astype(np.float64) / 255.0 if x.dtype == np.uint8 else x.astype(np.float64)
    return np.asarray(colour.cctf_decoding(x, function="sRGB"), dtype=np.float64)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Linear float -> sRGB-encoded float64 in [0, 1] (input clipped to [0, 1] first)."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.clip(np.asarray(colour.cctf_encoding(x, function="sRGB"), dtype=np.float64), 0.0, 1.0)


def _matrices(cfg: ISPConfig) -> tuple[np.ndarray, np.ndarray]:
    ccm = np.asarray(cfg.ccm, dtype=np.float64)
    return ccm, np.linalg.inv(ccm)


def check_image(image: np.ndarray, what: str = "image") -> np.ndarray:
    """Validate one (H, W, 3) uint8 sRGB or non-negative finite float linear image; return it as an array."""
    x = np.asarray(image)
    if x.ndim != 3 or x.shape[-1] != 3 or x.shape[0] < 1 or x.shape[1] < 1:
        raise InputError(f"{what} must have shape (H, W, 3), got {x.shape}")
    if x.dtype == np.uint8:
        return x
    if not np.issubdtype(x.dtype, np.floating):
        raise InputError(f"{what} must be uint8 sRGB or float linear, got dtype {x.dtype}")
    if not np.all(np.isfinite(x)):
        raise InputError(f"{what} contains NaN or Inf")
    if np.any(x < 0):
        raise InputError(f"{what} has negative values; linear intensities must be >= 0")
    return x


def _check_mosaic_size(cfg: ISPConfig, height: int, width: int) -> None:
    if cfg.mosaic != "none" and (height < 2 or width < 2):
        raise InputError(f"a {cfg.mosaic} mosaic needs images of at least 2x2 pixels, got {height}x{width}")


def inverse_isp(image: np.ndarray, cfg: ISPConfig | None = None) -> np.ndarray:
    """uint8 sRGB or float linear-sRGB (H, W, 3) -> float64 raw: (H, W) mosaic, or (H, W, 3) if cfg.mosaic == 'none'.

    raw_cam = inv(ccm) @ linear / white_balance; then each pixel keeps its CFA channel when mosaiced.
    """
    cfg = cfg or ISPConfig()
    x = check_image(image)
    h, w = x.shape[:2]
    _check_mosaic_size(cfg, h, w)
    lin = srgb_to_linear(x) if x.dtype == np.uint8 else x.astype(np.float64)
    _, inv_ccm = _matrices(cfg)
    cam = lin.reshape(-1, 3) @ inv_ccm.T
    raw = (cam / np.asarray(cfg.white_balance, dtype=np.float64)).reshape(h, w, 3)
    if cfg.mosaic == "none":
        return raw
    ch = cfa_channels(cfg.mosaic, h, w)
    return np.take_along_axis(raw, ch[..., None], axis=2)[..., 0]


def demosaic(raw: np.ndarray, pattern: str) -> np.ndarray:
    """(H, W) float mosaic in [-RAW_PEDESTAL, 1] (clipped there) -> (H, W, 3) float64 camera RGB, bilinear
    (OpenCV) at 16-bit precision. OpenCV demosaics unsigned integers only, so the raw is shifted up by a
    pedestal first and down after: bilinear interpolation (weights summing to 1) commutes with the shift."""
    span = 1.0 + RAW_PEDESTAL
    u16 = np.round((np.clip(raw, -RAW_PEDESTAL, 1.0) + RAW_PEDESTAL) * (65535.0 / span)).astype(np.uint16)
    padded = np.pad(u16, _PAD, mode="reflect")
    rgb = cv2.cvtColor(padded, BAYER_TO_RGB[pattern])[_PAD:-_PAD, _PAD:-_PAD]
    return rgb.astype(np.float64) * (span / 65535.0) - RAW_PEDESTAL


def forward_isp(raw: np.ndarray, cfg: ISPConfig | None = None) -> np.ndarray:
    """float raw ((H, W) mosaic or (H, W, 3)) -> uint8 sRGB (H, W, 3)."""
    cfg = cfg or ISPConfig()
    r = np.asarray(raw)
    want = 2 if cfg.mosaic != "none" else 3
    if r.ndim != want or (want == 3 and r.shape[-1] != 3):
        shape = "(H, W)" if want == 2 else "(H, W, 3)"
        raise InputError(f"raw for mosaic={cfg.mosaic!r} must have shape {shape}, got {r.shape}")
    if not np.issubdtype(r.dtype, np.floating) or not np.all(np.isfinite(r)):
        raise InputError("raw must be finite floats")
    _check_mosaic_size(cfg, r.shape[0], r.shape[1])
    r = np.minimum(r.astype(np.float64), 1.0)  # sensor saturation; below-black noise is kept (clipped at output)
    cam = demosaic(r, cfg.mosaic) if cfg.mosaic != "none" else r
    h, w = cam.shape[:2]
    ccm, _ = _matrices(cfg)
    gains = np.asarray(cfg.white_balance, dtype=np.float64)
    # Highlight clipping (as dcraw's default): after white balance no channel may exceed the level at which the
    # least-amplified channel saturates, so blown-out highlights go white instead of magenta.
    balanced = np.minimum(cam.reshape(-1, 3) * gains, gains.min())
    lin = (balanced @ ccm.T).reshape(h, w, 3)
    return np.round(linear_to_srgb(lin) * 255.0).astype(np.uint8)
