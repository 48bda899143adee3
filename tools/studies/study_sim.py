"""Study: what the simulator's accuracy costs. Rendered sub-frames per exposure (5..65) against a dense
oracle (257 sub-frames of the same analytic motion): per-pixel event-count error, timestamp error,
blurry-image PSNR against the oracle blur, and seconds; per-pixel timestamp interpolation on/off; the cost
of each effect on its own.

    python tools/studies/study_sim.py [--quick] --json tools/results/study_sim.json --plot tools/results/study_sim.png
"""
from __future__ import annotations

import sys
from pathlib import Path

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import pareto_plot, save_json  # noqa: E402

from ev3dgs.sim import DVSConfig, simulate_events  # noqa: E402
from ev3dgs.sim.blur import blur_frames  # noqa: E402
from ev3dgs.sim.config import Leak, LowPass, Refractory, ShotNoise, ThresholdMismatch  # noqa: E402
from ev3dgs.sim.synthetic import texture  # noqa: E402

EXPOSURE_US = 100_000


def frames_at(n: int, base: np.ndarray, H: int, W: int, travel_px: float) -> tuple[np.ndarray, np.ndarray]:
    """n frames of a texture moving smoothly (an eased diagonal path of `travel_px`) over the exposure."""
    s = np.linspace(0, 1, n)
    path = travel_px * (0.5 - 0.5 * np.cos(np.pi * s))  # eased: velocity varies within the exposure
    out = [cv2.warpAffine(base, np.float32([[1, 0, -20 + p], [0, 1, -20 + 0.6 * p]]), (W, H),
                          flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT) for p in path]
    return np.clip(np.stack(out), 0, None).astype(np.float32), np.round(s * EXPOSURE_US).astype(np.int64)


def per_pixel_counts(ev, H, W):
    return np.bincount(ev.y.astype(np.int64) * W + ev.x, weights=ev.p.astype(np.float64), minlength=H * W), \
        np.bincount(ev.y.astype(np.int64) * W + ev.x, minlength=H * W)


def timestamp_error(ev, oracle, H, W) -> float:
    """Median |t - t_oracle| between the k-th event of each pixel, over pixels with equal event counts."""
    def by_pixel(e):
        key = e.y.astype(np.int64) * W + e.x
        order = np.lexsort((e.t, key))
        return key[order], e.t[order]

    ka, ta = by_pixel(ev)
    kb, tb = by_pixel(oracle)
    ca, cb = np.bincount(ka, minlength=H * W), np.bincount(kb, minlength=H * W)
    same = (ca == cb) & (ca > 0)
    ma, mb = same[ka], same[kb]
    if not ma.any():
        return float("nan")
    return float(np.median(np.abs(ta[ma] - tb[mb])))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default="tools/results/study_sim.json")
    ap.add_argument("--plot", default="tools/results/study_sim.png")
    args = ap.parse_args(argv)
    H, W = (130, 173) if args.quick else (260, 346)
    travel = 12.0
    base = (texture(H + 80, W + 80, seed=1) * 1.2).astype(np.float32)
    oracle_frames, oracle_t = frames_at(257, base, H, W, travel)
    oracle = simulate_events(oracle_frames, oracle_t)
    o_signed, o_count = per_pixel_counts(oracle, H, W)
    oracle_blur = blur_frames(np.repeat(oracle_frames[..., None], 3, -1))
    rows = []
    for n in (5, 9, 17, 33, 65):
        f, t = frames_at(n, base, H, W, travel)
        t0 = time.perf_counter()
        ev = simulate_events(f, t)
        sim_s = time.perf_counter() - t0
        signed, count = per_pixel_counts(ev, H, W)
        blur = blur_frames(np.repeat(f[..., None], 3, -1))
        mse = np.mean((blur.astype(np.float64) - oracle_blur) ** 2)
        # timestamp interpolation off: every event stamped at the end of its interval (a per-frame grid)
        grid = t[np.searchsorted(t, ev.t, side="left")]
        off = type(ev)(grid, ev.x, ev.y, ev.p)
        rows.append({"label": n, "subframes": n, "events": len(ev), "oracle_events": len(oracle),
                     "count_error_per_pixel": float(np.mean(np.abs(count - o_count))),
                     "signed_count_error_per_pixel": float(np.mean(np.abs(signed - o_signed))),
                     "timestamp_error_us": timestamp_error(ev, oracle, H, W),
                     "timestamp_error_us_no_interpolation": timestamp_error(off, oracle, H, W),
                     "blur_psnr_vs_oracle": float(10 * np.log10(255**2 / max(mse, 1e-12))),
                     "simulate_seconds": sim_s})
        r = rows[-1]
        print(f"{n:3d} sub-frames: |count err| {r['count_error_per_pixel']:.3f}/px, t err "
              f"{r['timestamp_error_us']:.0f} us (no interp. {r['timestamp_error_us_no_interpolation']:.0f} us), "
              f"blur {r['blur_psnr_vs_oracle']:.1f} dB, {1e3 * sim_s:.1f} ms")
    # each effect on its own, 17 sub-frames
    f, t = frames_at(17, base, H, W, travel)
    effects = {"clean": DVSConfig(), "threshold_mismatch": DVSConfig(threshold_mismatch=ThresholdMismatch()),
               "refractory": DVSConfig(refractory=Refractory()), "leak": DVSConfig(leak=Leak()),
               "shot_noise": DVSConfig(shot_noise=ShotNoise()), "lowpass": DVSConfig(lowpass=LowPass()),
               "all": DVSConfig(threshold_mismatch=ThresholdMismatch(), refractory=Refractory(), leak=Leak(),
                                shot_noise=ShotNoise(), lowpass=LowPass())}
    simulate_events(f, t, effects["all"])  # warm-up
    cost = {}
    for name, cfg in effects.items():
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            ev = simulate_events(f, t, cfg)
            times.append(time.perf_counter() - t0)
        cost[name] = {"seconds": float(np.median(times)), "events": len(ev)}
    for name in cost:
        cost[name]["vs_clean"] = cost[name]["seconds"] / cost["clean"]["seconds"]
        print(f"effect {name:18s} {1e3 * cost[name]['seconds']:7.1f} ms  x{cost[name]['vs_clean']:.2f}")
    save_json(args.json, {"size": [W, H], "travel_px": travel, "subframes": rows, "effects_17_subframes": cost})
    pareto_plot(args.plot, {"per-pixel timestamps": rows}, "simulate_seconds", "count_error_per_pixel",
                "simulation seconds (17..65 frames, 1 thread)", "mean |event count error| per pixel vs oracle",
                f"Simulator: sub-frames per exposure vs a 257-frame oracle ({W}x{H})", higher_is_better=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
