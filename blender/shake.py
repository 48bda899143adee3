"""Camera shake: smooth, bounded, seeded, zero-mean random motion over an exposure (pure numpy; our own
generator, since Camera Shakify is GPL).

Each of the 6 axes (3 rotation, 3 translation, in the camera frame) is a sum of sinusoids with random
frequencies in [min_hz, max_hz] and random phases, minus its exact mean over the exposure, scaled so
that its largest excursion within the exposure equals the configured amplitude: smooth (band-limited),
bounded by construction, zero-mean over the exposure (so the blurry frame is centred on the nominal pose).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Shake:
    rotation_deg: float = 1.0     # largest rotation about each camera axis within an exposure
    translation: float = 0.01     # largest translation along each camera axis (scene units)
    min_hz: float = 2.0
    max_hz: float = 8.0
    components: int = 3           # sinusoids per axis


def shake_offsets(shake: Shake, t_s: np.ndarray, exposure_s: float, seed: int) -> np.ndarray:
    """(len(t_s), 6) offsets: rotation vector (radians, camera frame) then translation, at times t_s
    measured from the exposure start."""
    rng = np.random.default_rng(seed)
    k = shake.components
    freq = rng.uniform(shake.min_hz, shake.max_hz, (6, k))
    phase = rng.uniform(0, 2 * np.pi, (6, k))
    weight = rng.uniform(0.5, 1.0, (6, k))
    grid = np.linspace(0.0, exposure_s, 1025)

    def raw(t):
        w = 2 * np.pi * freq[..., None]
        return (weight[..., None] * np.sin(w * t + phase[..., None])).sum(axis=1)  # (6, len(t))

    # exact mean of sin(w t + p) over [0, T]: (cos(p) - cos(w T + p)) / (w T)
    wT = 2 * np.pi * freq * max(exposure_s, 1e-12)
    mean = (weight * (np.cos(phase) - np.cos(wT + phase)) / wT).sum(axis=1)
    peak = np.abs(raw(grid) - mean[:, None]).max(axis=1)
    amp = np.array([np.deg2rad(shake.rotation_deg)] * 3 + [shake.translation] * 3)
    scale = np.where(peak > 0, amp / np.maximum(peak, 1e-300), 0.0)
    return ((raw(np.asarray(t_s, float)) - mean[:, None]) * scale[:, None]).T


def apply_offsets(c2w: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Nominal camera-to-world (4, 4) moved by camera-frame offsets (n, 6) -> (n, 4, 4)."""
    from ev3dgs.geometry import rotvec_to_matrix

    delta = np.tile(np.eye(4), (len(offsets), 1, 1))
    delta[:, :3, :3] = rotvec_to_matrix(offsets[:, :3])
    delta[:, :3, 3] = offsets[:, 3:]
    return c2w @ delta
