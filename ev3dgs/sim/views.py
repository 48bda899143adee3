"""Where the cameras go and when: nominal view poses on a hemisphere band, one time line with each
exposure in its own window, and shaky sub-frame poses inside each exposure."""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from ..geometry import look_at
from .scenes import Render, ShakeSpec

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


@dataclass
class ViewPlan:
    index: int
    exposure: tuple[int, int]      # [start, end) us
    t_us: np.ndarray               # (S,) sub-frame times, both exposure ends included
    poses: np.ndarray              # (S, 4, 4) requested camera-to-world (OpenCV axes)
    mid_pose: np.ndarray           # (4, 4) pose at the exposure midpoint (the sharp frame's)


def orbit_poses(n: int, radius: float, elevation_deg: tuple[float, float], azimuth0: float = 0.0,
                target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """n cameras looking at `target`, azimuths on the golden angle, elevations evenly over the band."""
    lo, hi = np.deg2rad(elevation_deg)
    out = np.empty((n, 4, 4))
    for i in range(n):
        az = azimuth0 + i * GOLDEN_ANGLE
        el = lo + (hi - lo) * (i + 0.5) / n
        eye = radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        out[i] = look_at(eye, target)
    return out


def plan_views(render: Render, shake: ShakeSpec, seed: int) -> list[ViewPlan]:
    from ev3dgs_blender.shake import Shake, apply_offsets, shake_offsets

    nominal = orbit_poses(render.views, render.radius, render.elevation_deg)
    exposure_us = int(round(render.exposure_ms * 1000))
    period = exposure_us + int(round(render.gap_ms * 1000))
    S = render.subframes
    sh = Shake(shake.rotation_deg, shake.translation, shake.min_hz, shake.max_hz, shake.components)
    plans = []
    for i in range(render.views):
        start = i * period
        rel = np.round(np.linspace(0, exposure_us, S)).astype(np.int64)
        view_seed = zlib.crc32(f"{seed}/shake/{i}".encode())
        times_s = np.append(rel, exposure_us / 2) * 1e-6
        offsets = shake_offsets(sh, times_s, exposure_us * 1e-6, view_seed)
        poses = apply_offsets(nominal[i], offsets)
        plans.append(ViewPlan(i, (start, start + exposure_us), start + rel, poses[:S], poses[S]))
    return plans


def novel_view_poses(render: Render, seed: int) -> np.ndarray:
    """Novel views: a different azimuth phase, at elevations between the training bands' samples."""
    rng = np.random.default_rng(zlib.crc32(f"{seed}/test".encode()))
    return orbit_poses(render.test_views, render.radius, render.elevation_deg,
                       azimuth0=GOLDEN_ANGLE / 2 + rng.uniform(0, 0.3))
