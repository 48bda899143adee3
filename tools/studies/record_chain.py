"""A DAVIS346 recording we can check, end to end: `ev3dgs-sim record` -> `ev3dgs-ingest davis` (EDI +
pycolmap poses) -> pose error against the ground-truth trajectory after a similarity alignment ->
`ev3dgs train`. JSON out.

    python tools/studies/record_chain.py [--scene lego] [--size 173x130] [--seconds 2] --json tools/results/record_chain.json
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ev3dgs import schema
from ev3dgs.geometry import interpolate_pose, pose_errors
from ev3dgs.io.davis import DavisOptions, ingest_davis
from ev3dgs.sim.record import record


def poses_vs_truth(scene_path: Path, trajectory: Path) -> dict:
    sc = schema.read(scene_path)
    gt = np.load(trajectory)
    est = sc.train.poses.reshape(-1, 4, 4)
    t = sc.train.pose_t.reshape(-1)
    truth = np.stack([interpolate_pose(gt["c2w"], gt["t_us"], int(x)) for x in t])
    return pose_errors(est, truth)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="lego")
    ap.add_argument("--size", default="173x130")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--render-rate", type=float, default=100.0)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--workdir", help="keep the files here (default: a temporary folder)")
    ap.add_argument("--json", default="tools/results/record_chain.json")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    out = {"scene": args.scene, "size": args.size, "seconds": args.seconds}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(args.workdir or tmp)
        d.mkdir(parents=True, exist_ok=True)
        rec = d / f"{args.scene}.aedat4"
        t0 = time.perf_counter()
        info = record(args.scene, rec, seconds=args.seconds, render_rate_hz=args.render_rate, width=w, height=h)
        out["record"] = {k: info[k] for k in ("frames", "events", "imu", "rendered")}
        out["record_seconds"] = time.perf_counter() - t0
        for label, cal in (("estimated_K", None), ("calibrated_K", str(d / f"{args.scene}.calibration.toml"))):
            scene = d / f"{args.scene}_{label}.h5"
            t0 = time.perf_counter()
            stats = ingest_davis(rec, scene, DavisOptions(calibration=cal))
            out[label] = {"views": stats.views, "registered_latent_frames": stats.registered,
                          "latent_frames": stats.latent_frames, "ingest_seconds": time.perf_counter() - t0,
                          **poses_vs_truth(scene, rec.with_suffix(".trajectory.npz"))}
            sc = schema.read(scene)
            out[label]["fx_estimate"] = float(sc.camera.K[0, 0])
        out["fx_true"] = float(np.load(rec.with_suffix(".trajectory.npz"))["K"][0, 0])
        from ev3dgs.train.config import TrainConfig
        from ev3dgs.train.trainer import Trainer

        t0 = time.perf_counter()
        rec_train = Trainer(TrainConfig(scene=str(d / f"{args.scene}_calibrated_K.h5"), iterations=args.iterations),
                            d / "run", quiet=True).fit()
        out["train"] = {"iterations": args.iterations, "seconds": time.perf_counter() - t0,
                        "final_loss": rec_train["loss"], "psnr_vs_blurry_input": rec_train["psnr_blurry"],
                        "gaussians": rec_train["gaussians"]}
    print(json.dumps(out, indent=2))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
