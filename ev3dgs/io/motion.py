"""Did the camera move? A check that runs in about a second, before EDI and pose estimation.

Structure from motion needs parallax: a point is triangulated only when the rays of two views meet at an angle
of at least COLMAP's `filter_min_tri_angle` (1.5 degrees). A camera that did not move gives none, and pycolmap
would spend minutes before failing. Two witnesses, both from data the ingest has already read:

* the IMU, where the recording has one. A sensor at rest reads its bias plus noise; its noise floor comes from
  the data itself: the high-frequency residual (first differences, robust spread / sqrt 2) estimates the
  per-sample noise sigma. Noise that the IMU's digital low-pass filter (bandwidth B, sampled at fs) correlates
  has std / sigma_diff = 1 / sqrt(1 - exp(-2 pi B / fs)) (first-order filter), so every axis of gyroscope and
  accelerometer whose std over the recording stays below that ratio for B = `imu_min_bandwidth_hz` is
  consistent with a sensor at rest. A camera carried by hand varies many times its noise (the DAVIS346
  recording in the aestream repository: 18 x on the gyroscope).
* the APS frames: dense optical flow (Farneback) from the first used frame to up to `max_frames` others spread
  over the recording; the median displacement over the textured half of the pixels (moving objects, which
  occupy a minority of the frame, do not move the median). The camera moved too little when that median stays
  below the displacement a ray needs for `min_parallax_deg`, f * tan(angle) pixels.

The IMU cannot tell a constant velocity (a camera on a slider or a vehicle) from rest, so a static IMU is only
believed when the frames agree: a recording is refused only when every witness it has says static.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MotionCheck:
    """[motion] of an ingest: when a recording counts as made with a camera that did not move."""
    imu_min_bandwidth_hz: float = 10.0   # lowest IMU low-pass bandwidth whose correlated noise counts as rest
    min_parallax_deg: float = 1.5        # COLMAP's filter_min_tri_angle: below it no point triangulates
    max_frames: int = 12                 # frames compared with the first (the flow costs ~10 ms per pair)
    min_imu_samples: int = 20            # fewer: the IMU is not used


@dataclass
class MotionReport:
    static: bool
    imu: dict | None = None       # {"samples", "gyro_ratio", "accel_ratio", "limit", "static"}
    frames: dict | None = None    # {"frames", "median_px", "limit_px", "static"}

    def evidence(self) -> str:
        """What the witnesses measured, in words."""
        parts = []
        if self.imu is not None:
            i = self.imu
            parts.append(f"its gyroscope and accelerometer vary at most {max(i['gyro_ratio'], i['accel_ratio']):.1f} "
                         f"times their own noise over {i['samples']:,} IMU samples (a moving camera: more than "
                         f"{i['limit']:.1f})")
        if self.frames is not None:
            f = self.frames
            parts.append(f"the median image motion between its APS frames is {f['median_px']:.2f} px over "
                         f"{f['frames']} frames (pose estimation needs more than {f['limit_px']:.1f} px, "
                         f"{f['parallax_deg']:g} degrees of parallax)")
        return "; ".join(parts)


def imu_ratio_limit(fs_hz: float, bandwidth_hz: float) -> float:
    """std / sigma_diff of first-order low-passed white noise (bandwidth B) sampled at fs."""
    rho = math.exp(-2 * math.pi * bandwidth_hz / fs_hz)
    return 1.0 / math.sqrt(max(1.0 - rho, 1e-12))


def _axis_ratio(x: np.ndarray) -> np.ndarray:
    """Per column: std over the recording / the per-sample noise sigma from the first differences (MAD)."""
    x = np.asarray(x, np.float64)
    d = np.diff(x, axis=0)
    sigma = 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / math.sqrt(2)
    # a quantised sensor at rest can hold one value for most samples (MAD 0): its noise is then at least the
    # quantisation step seen in the data (the smallest non-zero difference) / sqrt(12)
    nz = np.abs(d)[np.abs(d) > 0]
    q = (nz.min() / math.sqrt(12)) if len(nz) else 0.0
    sigma = np.maximum(sigma, q)
    std = x.std(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(std == 0, 0.0, np.where(sigma > 0, std / sigma, np.inf))


def imu_motion(t_us: np.ndarray, accel: np.ndarray, gyro: np.ndarray, cfg: MotionCheck = MotionCheck()) -> dict | None:
    """The IMU witness, or None when the recording has too few IMU samples."""
    t = np.asarray(t_us, np.int64)
    if len(t) < cfg.min_imu_samples:
        return None
    dt = np.diff(t)
    dt = dt[dt > 0]
    if not len(dt):
        return None
    fs = 1e6 / float(np.median(dt))
    limit = imu_ratio_limit(fs, cfg.imu_min_bandwidth_hz)
    g, a = float(_axis_ratio(gyro).max()), float(_axis_ratio(accel).max())
    return {"samples": int(len(t)), "rate_hz": fs, "gyro_ratio": g, "accel_ratio": a, "limit": limit,
            "static": bool(g <= limit and a <= limit)}


def frame_motion(gray: list[np.ndarray], focal_px: float, cfg: MotionCheck = MotionCheck()) -> dict | None:
    """The frames witness: the largest median Farneback displacement from the first frame to up to
    `max_frames` others (uint8 (H, W) frames). None with fewer than 2 frames."""
    import cv2

    if len(gray) < 2:
        return None
    idx = np.unique(np.round(np.linspace(0, len(gray) - 1, min(len(gray), cfg.max_frames + 1))).astype(int))
    g0 = np.ascontiguousarray(gray[idx[0]])
    f0 = g0.astype(np.float32)
    grad = np.hypot(cv2.Sobel(f0, cv2.CV_32F, 1, 0), cv2.Sobel(f0, cv2.CV_32F, 0, 1))
    textured = grad >= np.median(grad)
    worst = 0.0
    for k in idx[1:]:
        flow = cv2.calcOpticalFlowFarneback(g0, np.ascontiguousarray(gray[k]), None, 0.5, 4, 15, 3, 5, 1.2, 0)
        worst = max(worst, float(np.median(np.hypot(flow[..., 0], flow[..., 1])[textured])))
    limit = float(focal_px * math.tan(math.radians(cfg.min_parallax_deg)))
    return {"frames": int(len(idx)), "median_px": worst, "limit_px": limit, "parallax_deg": cfg.min_parallax_deg,
            "static": bool(worst < limit)}


def camera_motion(gray: list[np.ndarray], focal_px: float, imu=None, cfg: MotionCheck = MotionCheck()) -> MotionReport:
    """Both witnesses; static only when every witness present says so (the frames are skipped when the IMU
    already shows motion)."""
    im = None if imu is None or not len(imu) else imu_motion(imu.t, imu.accel, imu.gyro, cfg)
    if im is not None and not im["static"]:
        return MotionReport(static=False, imu=im)
    fr = frame_motion(gray, focal_px, cfg)
    witnesses = [w for w in (im, fr) if w is not None]
    return MotionReport(static=bool(witnesses) and all(w["static"] for w in witnesses), imu=im, frames=fr)
