"""How many sub-poses each exposure needs (``ev3dgs train --subpose-px``).

The trainer models a blurry frame as the mean of renders at b + 1 sub-poses spread evenly over the exposure.
Between two neighbouring sub-poses the scene moves in the image; where it moves by more than a pixel or two,
the mean of the renders is a row of sharp copies rather than a streak, and the events between the two poses
are matched against the difference of two images that no longer overlap. The motion of an exposure is
measured here as the longest image path of any scene point in view: the point is projected along the
exposure's camera trajectory (the scene's own pose samples, interpolated as the trainer interpolates them),
and its path length is summed in pixels. A view then gets the fewest sub-poses whose spacing along that path
is at most ``px`` pixels, between 2 and a cap.
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..geometry import interpolate_pose

GRID = 9          # points per axis of the grid spread over /bounds when the scene has no /points
SAMPLES = 64      # uniform steps across each exposure (the pose samples inside it are added)


def motion_points(xyz, bounds) -> np.ndarray:
    """(P, 3) world points whose image motion stands for the scene's: the scene's /points (``xyz``) when it
    has any, else a GRID^3 lattice filling its /bounds box (corners included)."""
    if xyz is not None and len(xyz):
        return np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if bounds is None:
        raise InputError("--subpose-px needs the scene's /points or /bounds to measure how far it moves in the "
                         "image; this scene has neither")
    lo, hi = np.asarray(bounds, dtype=np.float64)
    g = np.linspace(0.0, 1.0, GRID)
    unit = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    return lo + unit * (hi - lo)


def _pixels(K: np.ndarray, c2w: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (P, 2) and depths (P,) of world points X in a rigid camera-to-world pose: what
    ``geometry.project`` gives (to rounding), with the rigid inverse R^T (X - c) in place of its 4x4 LAPACK
    inverse, which this loop calls about 65 times per view (with two training runs on the same two cores
    the inverses took 5 s of a 5.3 s measurement for 12 views, 0.4 s without them), and points at or behind
    the camera divided by 1 instead of their depth (the caller drops them)."""
    R, c = c2w[:3, :3], c2w[:3, 3]
    pc = (X - c) @ R  # R^T (X - c), the camera-frame points
    h = pc @ K.T
    z = pc[:, 2]
    return h[:, :2] / np.where(z > 0, h[:, 2], 1.0)[:, None], z


def exposure_motion(poses, pose_t, exposure, K, width: int, height: int, points: np.ndarray) -> np.ndarray:
    """(N,) the largest image path length (pixels) of any of ``points`` over each view's exposure. A point
    counts for a view when it lies in front of the camera during the whole exposure and inside the image
    at its midpoint. Views that see none of the points get 0. ``poses`` (N, S, 4, 4) camera-to-world at
    ``pose_t`` (N, S) (OpenCV axes), ``exposure`` (N, 2), ``K`` (3, 3)."""
    K = np.asarray(K, dtype=np.float64)
    X = np.asarray(points, dtype=np.float64)
    out = np.zeros(len(exposure))
    for v, (t0, t1) in enumerate(np.asarray(exposure, dtype=np.float64)):
        knots = np.asarray(pose_t[v], dtype=np.float64)
        ts = np.unique(np.concatenate([np.linspace(t0, t1, SAMPLES + 1), knots[(knots > t0) & (knots < t1)]]))
        uv, z = zip(*(_pixels(K, interpolate_pose(poses[v], pose_t[v], t), X) for t in ts))
        uv, z = np.stack(uv), np.stack(z)                      # (T, P, 2), (T, P)
        mid = _pixels(K, interpolate_pose(poses[v], pose_t[v], 0.5 * (t0 + t1)), X)[0]
        seen = ((z > 0).all(axis=0) & (mid[:, 0] >= -0.5) & (mid[:, 0] <= width - 0.5)
                & (mid[:, 1] >= -0.5) & (mid[:, 1] <= height - 0.5))
        if seen.any():
            out[v] = np.linalg.norm(np.diff(uv[:, seen], axis=0), axis=-1).sum(axis=0).max()
    return out


def subpose_counts(motion: np.ndarray, px: float, cap: int) -> np.ndarray:
    """(N,) int: per view the fewest sub-poses k with motion / (k - 1) <= px, clamped to [2, cap]."""
    if not (np.isfinite(px) and px > 0):
        raise ValueError(f"px must be a positive number, got {px}")
    need = np.ceil(np.asarray(motion, dtype=np.float64) / float(px)).astype(np.int64) + 1
    return np.clip(need, 2, max(2, int(cap)))
