"""Study: `ev3dgs train --refine-poses` on a recording we can check end to end (issue 16, item 3b).

`ev3dgs-sim record` (a simulated DAVIS346 recording of a built-in scene with its ground-truth trajectory,
rendered frames kept) -> `ev3dgs-ingest davis` with the true intrinsics (EDI latent frames + pycolmap
poses) -> `ev3dgs train` on the ingested scene without and with --refine-poses, same seed and settings.

Reported per run:
* mid-exposure pose error of every training view against the ground truth (``geometry.pose_errors``: the
  estimated cameras are first mapped onto the true ones by the best similarity, since COLMAP's frame is
  arbitrary): rotation median / max (degrees) and centre error (scene units). Without refinement the
  poses are the ingested ones; with it, the run's trajectory.npz.
* blur-view PSNR against the recording's sharp ground truth: the recorder renders linear frames at
  --render-rate over the whole recording; for each view the rendered frame nearest to mid-exposure is
  developed like an APS frame (ISP, linear gray luminance, without sensor noise) and sRGB-encoded as
  `ingest davis` stores APS frames. The model is rendered at the run's camera trajectory interpolated to
  that frame's time (ingested poses, or the refined trajectory) — the deblurred view at the pose the
  pipeline believes, so pose error shows up as PSNR loss.
* the trainer's PSNR against the blurry inputs through its blur model (``psnr_blurry``, last log line).

    python tools/investigations/chain_refine.py [--workdir DIR] [--iterations 1500] [--pose-lr 1e-3]
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

from ev3dgs import schema  # noqa: E402
from ev3dgs.geometry import interpolate_pose, pose_errors  # noqa: E402
from ev3dgs.train.config import TrainConfig  # noqa: E402


def sharp_ground_truth(rec: Path, scene_name: str, exposure: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sharp sRGB frames (N,H,W,3) uint8, their times (N,) us) for the views with these exposure windows,
    from the recorder's kept render cache (``record(..., keep_cache=True)``)."""
    from ev3dgs.sim.blur import blur_frames
    from ev3dgs.io.edi import linear_to_srgb
    from ev3dgs.sim.record import CHUNK, _gray
    from ev3dgs.sim.scenes import load_scene

    caches = sorted(rec.parent.glob(f".{rec.stem}.cache-*"))
    if len(caches) != 1:
        raise SystemExit(f"need exactly one render cache .{rec.stem}.cache-* beside {rec} (record with "
                         f"keep_cache=True), found {len(caches)}")
    gt = np.load(rec.with_suffix(".trajectory.npz"))
    t_us = np.asarray(gt["t_us"], np.int64)
    isp = load_scene(scene_name).sensor.isp
    lut = np.round(255 * linear_to_srgb(np.arange(256) / 255.0)).astype(np.uint8)  # as ingest davis stores APS
    frames, times = [], []
    for start, end in exposure:
        g = int(np.argmin(np.abs(t_us - 0.5 * (start + end))))
        with np.load(caches[0] / f"traj_{g // CHUNK:05d}.npz") as z:
            lin = z["frames"][g % CHUNK]
        gray = lut[_gray(blur_frames(lin[None], isp, None))]  # developed like an APS frame, no sensor noise
        frames.append(np.repeat(gray[..., None], 3, axis=2))
        times.append(t_us[g])
    return np.stack(frames), np.array(times)


def border_background(scene: Path) -> np.ndarray:
    """Give the ingested scene the background colour its frames show at their borders (median, sRGB units).
    A DAVIS scene has none, and the trainer's default black background would have to be painted over with
    Gaussians in front of this scene's white backdrop, which takes most of a short run; a user sees the
    colour just as well."""
    import h5py

    im = np.asarray(schema.read(scene).train.images)
    border = np.concatenate([im[:, [0, -1]].reshape(-1, 3), im[:, :, [0, -1]].reshape(-1, 3)])
    bg = np.median(border, axis=0) / 255.0
    with h5py.File(scene, "r+") as f:
        f["/camera"].attrs["background"] = bg
    return bg


def at_times(poses: np.ndarray, pose_t: np.ndarray, times) -> np.ndarray:
    return np.stack([interpolate_pose(p, t, float(m)) for p, t, m in zip(poses, pose_t, times)])


def evaluate_run(run: Path, cfg: TrainConfig, truth_traj: dict, sharp: np.ndarray, sharp_t: np.ndarray) -> dict:
    from ev3dgs.train.evaluate import _scores, load_run, render_views

    sc = schema.read(cfg.scene)
    poses, pose_t = np.asarray(sc.train.poses, np.float64), np.asarray(sc.train.pose_t)
    if cfg.refine_poses:
        from ev3dgs.train.pose_refine import load_trajectory

        tj = load_trajectory(run / "trajectory.npz", len(poses))
        poses, pose_t = tj["poses"], tj["pose_t"]
    mid = np.asarray(sc.train.exposure, np.float64).mean(axis=1)
    true_mid = np.stack([interpolate_pose(truth_traj["c2w"], truth_traj["t_us"], float(m)) for m in mid])
    err = pose_errors(at_times(poses, pose_t, mid), true_mid)
    model = load_run(run)[1]
    K = torch.as_tensor(sc.camera.K, dtype=torch.float32)
    bg = torch.as_tensor(sc.camera.background or (0, 0, 0), dtype=torch.float32)
    pred = render_views(model, at_times(poses, pose_t, sharp_t), K, sc.camera.width, sc.camera.height, bg, "cpu")
    last = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    return {"pose_errors": err, "blur_view": _scores(pred, sharp), "psnr_blurry": last.get("psnr_blurry"),
            "train_seconds": last["seconds"], "seconds_per_step": last["seconds"] / cfg.iterations,
            "gaussians": last.get("gaussians"), "pose_skipped": last.get("pose_skipped")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="lego", help="built-in scene to record (default %(default)s)")
    ap.add_argument("--size", default="173x130", help="sensor size WxH, pixels (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=2.0, help="recording length, seconds (default 2)")
    ap.add_argument("--render-rate", type=float, default=100.0,
                    help="rendered frames per second of the recording, Hz (default 100)")
    ap.add_argument("--iterations", type=int, default=1500, help="training steps per run (default 1500)")
    ap.add_argument("--pose-lr", type=float, nargs="+", default=[1e-3],
                    help="refinement learning rates, one run each (default 1e-3, the trainer's)")
    ap.add_argument("--pose-start", type=int, default=100,
                    help="steps before the corrections move, as `train --pose-start` (default 100)")
    ap.add_argument("--pose-warmup", type=int, default=100,
                    help="steps of linear lr warm-up, as `train --pose-warmup` (default 100)")
    ap.add_argument("--seed", type=int, default=0, help="recording and training seed (default 0)")
    ap.add_argument("--workdir", help="keep the files here; a recording and scene found there are reused "
                                      "(default: a temporary folder)")
    ap.add_argument("--json", default="tools/results/chain_refine.json", help="results (default %(default)s)")
    ap.add_argument("--plot", default="tools/results/chain_refine.png", help="figure (default %(default)s)")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    torch.set_num_threads(1)
    tmp = None if args.workdir else tempfile.TemporaryDirectory()
    d = Path(args.workdir or tmp.name)
    d.mkdir(parents=True, exist_ok=True)
    out = {"recording": {"scene": args.scene, "size": args.size, "seconds": args.seconds,
                         "render_rate_hz": args.render_rate, "seed": args.seed}, "iterations": args.iterations}
    rec = d / f"{args.scene}.aedat4"
    if not rec.is_file():
        from ev3dgs.sim.record import record

        t0 = time.perf_counter()
        record(args.scene, rec, seconds=args.seconds, render_rate_hz=args.render_rate, width=w, height=h,
               seed=args.seed, keep_cache=True)
        out["record_seconds"] = time.perf_counter() - t0
    scene = d / f"{args.scene}_calibrated.h5"
    if not scene.is_file():
        from ev3dgs.io.davis import DavisOptions, ingest_davis

        t0 = time.perf_counter()
        ingest_davis(rec, scene, DavisOptions(calibration=str(d / f"{args.scene}.calibration.toml")))
        out["ingest_seconds"] = time.perf_counter() - t0
    bg = border_background(scene)
    out["background"] = bg.tolist()
    gt = np.load(rec.with_suffix(".trajectory.npz"))
    truth_traj = {"c2w": gt["c2w"], "t_us": gt["t_us"]}
    sc = schema.read(scene)
    sharp, sharp_t = sharp_ground_truth(rec, args.scene, np.asarray(sc.train.exposure))
    mid = np.asarray(sc.train.exposure, np.float64).mean(axis=1)
    out["views"] = len(sharp)
    out["sharp_frame_offset_from_mid_us"] = [float(x) for x in sharp_t - mid]
    from ev3dgs.train.evaluate import _scores

    out["blurry_input_vs_sharp"] = _scores(list(sc.train.images), sharp)
    from ev3dgs.train.trainer import Trainer

    base = TrainConfig(scene=str(scene), iterations=args.iterations, seed=args.seed, device="cpu", backend="cpu",
                       checkpoint_every=10 ** 6)
    runs = {"ingested poses": base}
    for lr in args.pose_lr:
        runs[f"refine (lr {lr:g})"] = TrainConfig(**{**base.__dict__, "refine_poses": True, "pose_lr": lr,
                                                          "pose_start": args.pose_start,
                                                          "pose_warmup": args.pose_warmup})
    out["runs"] = {}
    for name, cfg in runs.items():
        run = d / "runs" / name.replace(" ", "_").replace("(", "").replace(")", "")
        done = (run / "model.pt").is_file() and (run / "config.json").is_file() and \
            not TrainConfig.load(run / "config.json").differences(cfg, ignore=("threads",))
        if not done:
            torch.manual_seed(cfg.seed)
            Trainer(cfg, run, quiet=True).fit()
        r = out["runs"][name] = {**evaluate_run(run, cfg, truth_traj, sharp, sharp_t), "reused": bool(done)}
        e = r["pose_errors"]
        print(f"{name:18s} rotation {e['rotation_deg_median']:.3f} / {e['rotation_deg_max']:.3f} deg "
              f"(median / max), centre {e['centre_error_median']:.4f}, blur view {r['blur_view']['psnr']:.2f} dB, "
              f"blurry fit {r['psnr_blurry']:.2f} dB, {r['seconds_per_step'] * 1e3:.0f} ms/step", flush=True)
    out["command"] = "python tools/investigations/chain_refine.py " + " ".join(argv if argv is not None else sys.argv[1:])
    save_json(args.json, out)
    plot(out, args.plot)
    if tmp is not None:
        tmp.cleanup()
    return 0


def plot(out: dict, png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(out["runs"])
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.8))
    for n in names:
        ax[0].plot(out["runs"][n]["blur_view"]["psnr_per_view"], "o-", label=n)
    ax[0].plot(out["blurry_input_vs_sharp"]["psnr_per_view"], "k.--", label="blurry input")
    ax[0].set_xlabel("training view")
    ax[0].set_ylabel("PSNR vs sharp ground truth (dB)")
    ax[0].legend(fontsize=8)
    x = np.arange(len(names))
    for j, (key, label) in enumerate((("rotation_deg_median", "rotation median (deg)"),
                                      ("rotation_deg_max", "rotation max (deg)"))):
        ax[1].bar(x + (j - 0.5) * 0.4, [out["runs"][n]["pose_errors"][key] for n in names], 0.4, label=label)
    ax[1].set_xticks(x, names, fontsize=8)
    ax[1].set_ylabel("mid-exposure pose error vs ground truth")
    ax[1].legend(fontsize=8)
    r = out["recording"]
    fig.suptitle(f"record -> ingest davis -> train: {r['scene']} {r['size']}, {out['views']} views, "
                 f"{out['iterations']} steps", fontsize=9)
    fig.tight_layout()
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
