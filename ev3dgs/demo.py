"""`make demo`: the simulator on the built-in default sequence.

A DAVIS346-sized (346x260) colour texture seen by a shaking camera: 3 views, each a 100 ms exposure
rendered as 17 sub-frames. Events come from the DVS model with DAVIS-like noise effects, each view's blurry
frame from raw-domain averaging of its sub-frames plus sensor noise. Writes demo_out/scene.h5 (valid against
the schema), a blurry / sharp / event-image PNG per view, and prints what ran and how long it took.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from . import schema
from .cli.common import write_atomic
from .sim import DVSConfig, SimConfig, simulate_events
from .sim.blur import blur_frames
from .sim.config import ISPConfig, Leak, Refractory, SensorNoise, ShotNoise, ThresholdMismatch
from .sim.isp import linear_to_srgb
from .sim.output import event_sensor, provenance
from .sim.synthetic import texture

DEMO_CONFIG = SimConfig(
    dvs=DVSConfig(threshold_mismatch=ThresholdMismatch(sigma=0.03), refractory=Refractory(period_us=100),
                  leak=Leak(rate_hz=0.1), shot_noise=ShotNoise(rate_hz=0.5)),
    isp=ISPConfig(),
    sensor_noise=SensorNoise(iso=400),
)


def shaky_sequence(views=3, subframes=17, exposure_us=100_000, height=260, width=346, seed=0):
    """Linear RGB frames of a texture under a smooth random camera shake (translation in pixels)."""
    rng = np.random.default_rng(seed)
    n = views * (subframes - 1) + 1
    t_us = np.round(np.linspace(0, views * exposure_us, n)).astype(np.int64)
    # smooth shake: a few random sinusoids per axis, amplitude ~6 px over an exposure
    phase = rng.uniform(0, 2 * np.pi, (2, 3))
    freq = rng.uniform(3, 12, (2, 3))
    sec = t_us * 1e-6
    shift = 2.5 * np.sin(2 * np.pi * freq[..., None] * sec + phase[..., None]).sum(axis=1)
    pad = 24
    gray = texture(height + 2 * pad, width + 2 * pad, seed)
    base = np.stack([gray, np.roll(gray, 9, 0), np.roll(gray, 17, 1)], axis=-1).astype(np.float32)
    frames = np.stack([
        cv2.warpAffine(base, np.float32([[1, 0, -pad + dx], [0, 1, -pad + dy]]), (width, height),
                       flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        for dx, dy in shift.T])
    return frames, t_us


def event_image(ev, height, width) -> np.ndarray:
    """ON events red, OFF blue, on white (what DV shows)."""
    img = np.full((height, width, 3), 255, np.uint8)
    on = np.zeros((height, width), np.int32)
    off = np.zeros((height, width), np.int32)
    np.add.at(on, (ev.y[ev.p > 0], ev.x[ev.p > 0]), 1)
    np.add.at(off, (ev.y[ev.p < 0], ev.x[ev.p < 0]), 1)
    img[on > off] = (220, 40, 40)
    img[off > on] = (40, 60, 220)
    return img


def _png(path: Path, rgb: np.ndarray) -> None:
    write_atomic(path, cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].tobytes())


def _psnr(a, b) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def run(out: Path, views=3, subframes=17, seed=0) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    cfg = DEMO_CONFIG
    t0 = time.perf_counter()
    frames, t_us = shaky_sequence(views, subframes, seed=seed)
    H, W = frames.shape[1:3]
    ev = simulate_events(frames, t_us, cfg.dvs, seed=seed)
    images, sharp, exposure, rows = [], [], [], []
    for v in range(views):
        sub = slice(v * (subframes - 1), (v + 1) * (subframes - 1) + 1)
        blurry = blur_frames(frames[sub], cfg.isp, cfg.sensor_noise, seed=seed + v)
        mid = (linear_to_srgb(frames[sub][subframes // 2]) * 255 + 0.5).astype(np.uint8)
        start, end = int(t_us[sub][0]), int(t_us[sub][-1])
        images.append(blurry)
        sharp.append(mid)
        exposure.append((start, end))
        win = ev.window(start, end)
        _png(out / f"view{v}_blurry.png", blurry)
        _png(out / f"view{v}_sharp.png", mid)
        _png(out / f"view{v}_events.png", event_image(win, H, W))
        rows.append((v, len(win), win.on_count, win.off_count, _psnr(blurry, mid)))
    f = 0.5 * W / np.tan(np.deg2rad(35))  # a 70 degree horizontal field of view
    scene = schema.Scene(
        name="demo-shaky-texture", source="ev3dgs-sim demo",
        camera=schema.Camera(width=W, height=H, K=np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])),
        events=ev, sensor=event_sensor(cfg.dvs),
        train=schema.Train(images=np.stack(images), exposure=np.array(exposure, np.int64)),
        config=provenance(cfg, seed=seed, views=views, subframes=subframes),
    )
    schema.write(scene, out / "scene.h5")
    schema.validate(out / "scene.h5", require_complete=True)
    total = time.perf_counter() - t0
    rep = ev.report
    print(f"ev3dgs demo: {views} views x {subframes} sub-frames of {W}x{H} over 100 ms exposures "
          f"({total:.1f} s in all)")
    print(f"  {'view':>4} {'events':>8} {'ON':>7} {'OFF':>7} {'blurry vs sharp PSNR':>21}")
    for v, n, on, off, p in rows:
        print(f"  {v:>4} {n:>8} {on:>7} {off:>7} {p:>18.2f} dB")
    print(f"  simulator: {rep.events} events from {rep.frames} frames; effects: {', '.join(rep.effects)}")
    print("  time per stage: " + ", ".join(f"{k} {1e3 * s:.1f} ms" for k, s in rep.seconds.items()))
    print(f"  wrote {out / 'scene.h5'} (valid) and view*_{{blurry,sharp,events}}.png")
    return {"events": rep.events, "views": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Run the simulator on the built-in default sequence.")
    ap.add_argument("--out", default="demo_out")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    run(Path(args.out), seed=args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
