"""A small recording with known sensor settings, made without Blender: APS frames of a numpy scene, events
from ev3dgs.sim at a high internal rate, written with write_aedat4. For recovery tests and the study.

The scene (W x H, default 64 x 48):
  * the left STATIC_COLS columns: a static vertical intensity ramp (0.05 to 0.9) with a fine static texture:
    only noise fires there (background activity, its intensity dependence);
  * the rest: a smooth log-intensity texture translating at `speed_px_s` (monotonic stretches of several
    frame intervals per pixel: the threshold fit);
  * a FLASH patch at the bottom of the moving part: steps between 0.01 and 0.9 within one internal step
    (1 ms) every 100 ms, whose events come in refractory-limited bursts (the refractory period).
With moving=True (a moving camera: no pixel sees a static scene) the texture covers the static columns too,
except a flat FLAT patch at the top left (a white wall, the sky: flat regions stay unchanged however the camera
moves); the flash patch stays.
APS frames: the linear intensity averaged over each exposure, DN = dark + (255 - dark) I + Gaussian read noise
and photon noise, rounded to uint8 (GRAY). Hot pixels: Poisson events at `hot_hz` added at `hot` pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..events import Events
from ..io.types import FrameData
from ..sim.config import DVSConfig, Leak, Refractory, ShotNoise, ThresholdMismatch

STATIC_COLS = 20
FLAT = (0, 12, 0, 16)   # moving=True: rows y0:y1, columns x0:x1 of the flat patch
FLAT_LEVEL = 0.5
EPOCH = 1_700_000_000_000_000


@dataclass(frozen=True)
class Truth:
    pos_threshold: float = 0.2
    neg_threshold: float = 0.3
    sigma: float = 0.03
    leak_hz: float = 0.5
    shot_hz: float = 3.0
    white_fraction: float = 0.25
    refractory_us: float = 500.0
    dark_dn: float = 6.0
    hot: tuple[tuple[int, int], ...] = ((3, 5), (10, 30), (17, 44))
    hot_hz: float = 40.0

    def dvs(self) -> DVSConfig:
        return DVSConfig(pos_threshold=self.pos_threshold, neg_threshold=self.neg_threshold,
                         threshold_mismatch=ThresholdMismatch(sigma=self.sigma),
                         refractory=Refractory(period_us=self.refractory_us),
                         leak=Leak(rate_hz=self.leak_hz) if self.leak_hz > 0 else None,
                         shot_noise=(ShotNoise(rate_hz=self.shot_hz, white_fraction=self.white_fraction)
                                     if self.shot_hz > 0 else None))


def scene(t_s: np.ndarray, width: int, height: int, seed: int, speed_px_s: float = 40.0, shake_px: float = 0.0,
          shake_hz: float = 7.0, moving: bool = False) -> np.ndarray:
    """(T, H, W) float32 linear intensity at times t_s. shake_px: the texture also shakes by this amplitude
    (pixels) along x at shake_hz and 1.7 shake_hz (a hand-held camera's shake: reversals inside frame
    intervals, which the frames do not resolve)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    out = np.empty((len(t_s), height, width), np.float32)
    ramp = 0.05 + 0.85 * y / (height - 1)
    static = ramp * (1 + 0.05 * rng.standard_normal((height, width)))
    comps = [(rng.uniform(14, 28), rng.uniform(-0.6, 0.6), rng.uniform(0, 2 * np.pi), a)
             for a in (0.8, 0.5, 0.3)]
    fy0, fy1 = height - 8, height
    fx0, fx1 = STATIC_COLS, STATIC_COLS + 12
    for i, t in enumerate(t_s):
        u = x - speed_px_s * t - shake_px * (np.sin(2 * np.pi * shake_hz * t)
                                             + 0.5 * np.sin(2 * np.pi * 1.7 * shake_hz * t + 1.0))
        f = np.zeros_like(x)
        for lam, ang, ph, a in comps:
            f += a * np.sin(2 * np.pi * (u * np.cos(ang) + y * np.sin(ang)) / lam + ph)
        img = np.exp(np.log(0.25) + f)
        if moving:
            y0, y1, x0, x1 = FLAT
            img[y0:y1, x0:x1] = FLAT_LEVEL
        else:
            img[:, :STATIC_COLS] = static[:, :STATIC_COLS]
        phase = (t * 1e3) % 100.0
        img[fy0:fy1, fx0:fx1] = 0.9 if 20.0 <= phase < 70.0 else 0.01
        out[i] = np.clip(img, 0.0, 1.0)
    return out


def make_recording(path, truth: Truth = Truth(), seed: int = 0, seconds: float = 2.0, fps: float = 25.0,
                   exposure_us: int = 5000, width: int = 64, height: int = 48, rate_hz: float = 1000.0,
                   read_noise_dn: float = 1.0, with_frames: bool = True, n_frames: int | None = None,
                   saturate: bool = False, warmup_s: float = 2.0, shake_px: float = 0.0,
                   shake_hz: float = 7.0, hot_hz: tuple[float, ...] | None = None, moving: bool = False) -> dict:
    """Write an AEDAT 4.0 recording of the synthetic scene; returns what went in. The simulator runs
    `warmup_s` before the recording starts (its events are dropped), so that every pixel's state (reference,
    leak phase) is in its steady state, as in a sensor that has been on for a while: started at t = 0, the
    simulator's random reference phases give extra leak events in the first seconds. shake_px: see scene;
    hot_hz: one rate per hot pixel (default truth.hot_hz for each); moving: see scene."""
    from ..io.aedat4.writer import write_aedat4
    from ..sim.dvs import simulate_events

    n0 = int(round(warmup_s * rate_hz))
    n = int(round(seconds * rate_hz)) + 1
    t_us = np.round(np.arange(-n0, n) * 1e6 / rate_hz).astype(np.int64)
    frames = scene(t_us * 1e-6, width, height, seed, shake_px=shake_px, shake_hz=shake_hz, moving=moving)
    ev = simulate_events(frames, t_us, truth.dvs(), seed=seed)
    ev = ev.window(0, int(t_us[-1]) + 1)
    rng = np.random.default_rng(seed + 7)
    parts = [Events(ev.t, ev.x, ev.y, ev.p)]
    rates = [truth.hot_hz] * len(truth.hot) if hot_hz is None else list(hot_hz)
    for (hx, hy), hz in zip(truth.hot, rates):
        k = rng.poisson(hz * seconds)
        parts.append(Events(np.sort(rng.integers(0, t_us[-1], k)), np.full(k, hx), np.full(k, hy),
                            rng.choice(np.array([1, -1], np.int8), k)))
    allev = Events.concatenate(parts)
    o = np.argsort(allev.t, kind="stable")
    allev = Events(allev.t[o] + EPOCH, allev.x[o], allev.y[o], allev.p[o])
    aps = []
    if with_frames:
        starts = np.arange(0, seconds * 1e6 - exposure_us, 1e6 / fps).astype(np.int64) + 2000
        if n_frames is not None:
            starts = starts[:n_frames]
        for s in starts:
            m = (t_us >= s) & (t_us < s + exposure_us)
            lin = frames[m].mean(0)
            dn = truth.dark_dn + (255.0 - truth.dark_dn) * lin
            dn = dn + rng.normal(0, 1, dn.shape) * np.sqrt(read_noise_dn ** 2 + 0.05 * dn)
            if saturate:
                dn[:] = 255
            img = np.clip(np.round(dn), 0, 255).astype(np.uint8)
            aps.append(FrameData(timestamp=int(s) + EPOCH, exposure_start=int(s) + EPOCH,
                                 exposure_end=int(s + exposure_us) + EPOCH, frame_start=int(s) + EPOCH - 500,
                                 frame_end=int(s + exposure_us) + EPOCH + 500, image=img, source="SYNTH"))
    write_aedat4(path, width, height, events=allev, frames=aps)
    return {"events": len(allev), "frames": len(aps), "truth": truth}
