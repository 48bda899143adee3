"""Study: exposure-trajectory refinement (``ev3dgs train --refine-poses``) on known trajectories.

A small simulated scene (the quick lego, 64x48 by default); every training view's whole exposure trajectory is
moved by one rigid error (a 1 degree rotation about a random axis through the camera centre and a translation
of 2% of the camera's distance to the scene centre, random direction; fixed seed), written to a copy of the
scene. Three trainings, same seed and settings (blur + event losses):

* "true poses": the scene as simulated (the upper bound);
* "perturbed": the perturbed copy, poses kept fixed;
* "perturbed + refine": the perturbed copy with --refine-poses (and, unless --quick, a second learning rate;
  with ``--pose-frame world camera`` each learning rate in both frames of the corrections).

Reported: mid-exposure rotation / centre errors of the training cameras against the truth before and after
refinement (``geometry.pose_errors``: similarity-aligned centres, orientation-aligned rotations, so the
common gauge motion is not counted), the blur-view PSNR (sharp mid-exposure frames; refined runs at their
refined trajectory, the others at the given sharp poses and, for "perturbed", also at its own training
poses), novel-view PSNR (refined runs: aligned and unaligned test cameras), and seconds per step.

    python tools/investigations/study_refine.py [--quick] [--scene S.h5] [--json tools/results/study_refine.json]
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import h5py  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

from ev3dgs import schema  # noqa: E402
from ev3dgs.geometry import interpolate_pose, pose_errors, relative_rotation_angle, rotvec_to_matrix  # noqa: E402
from ev3dgs.train.config import TrainConfig  # noqa: E402


def mid_poses(poses, pose_t, exposure) -> np.ndarray:
    mid = np.asarray(exposure, np.float64).mean(axis=1)
    return np.stack([interpolate_pose(p, t, m) for p, t, m in zip(poses, pose_t, mid)])


def perturb_scene(src: str, dst: Path, rot_deg: float, trans_frac: float, seed: int) -> dict:
    """Copy ``src`` to ``dst`` with every training view's trajectory moved by one rigid error (rotation about
    the camera's mid-exposure centre, then a translation); returns the true and perturbed mid poses."""
    shutil.copyfile(src, dst)
    sc = schema.read(src)
    poses, pose_t = np.asarray(sc.train.poses, np.float64), np.asarray(sc.train.pose_t)
    true_mid = mid_poses(poses, pose_t, sc.train.exposure)
    rng = np.random.default_rng(seed)
    centre = (np.asarray(sc.bounds).mean(0) if sc.bounds is not None else np.zeros(3))
    new = poses.copy()
    for v in range(len(poses)):
        axis = rng.normal(size=3)
        R = rotvec_to_matrix(np.radians(rot_deg) * axis / np.linalg.norm(axis))
        d = rng.normal(size=3)
        dist = np.linalg.norm(true_mid[v, :3, 3] - centre)
        shift = trans_frac * dist * d / np.linalg.norm(d)
        c0 = true_mid[v, :3, 3]
        new[v, :, :3, :3] = R @ poses[v, :, :3, :3]
        new[v, :, :3, 3] = (R @ (poses[v, :, :3, 3] - c0).T).T + c0 + shift
    with h5py.File(dst, "r+") as f:
        f["/train/poses"][...] = new
    pert_mid = mid_poses(new, pose_t, sc.train.exposure)
    return {"true_mid": true_mid, "perturbed_mid": pert_mid}


def train_and_eval(cfg: TrainConfig, run: Path, reuse: bool = False) -> dict:
    """Train (or, with ``reuse``, take the finished run already in ``run`` made with the same settings) and
    evaluate. Training time: the log's last "seconds" (the trainer's own clock)."""
    from ev3dgs.train.evaluate import evaluate, load_run
    from ev3dgs.train.trainer import Trainer

    done = reuse and (run / "model.pt").is_file() and (run / "config.json").is_file() and \
        not TrainConfig.load(run / "config.json").differences(cfg, ignore=("threads",))
    if not done:
        torch.manual_seed(cfg.seed)
        Trainer(cfg, run, quiet=True).fit()
    last = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    m = evaluate(run, device="cpu", write_images=False)
    return {"train_seconds": last["seconds"], "seconds_per_step": last["seconds"] / cfg.iterations,
            "metrics": m, "model": load_run(run)[1], "pose_skipped": last.get("pose_skipped"),
            "reused": bool(done)}


def reprojection_px(est_mid, true_mid, K, bounds, n=2000, seed=0) -> np.ndarray:
    """Per view, the median image displacement (pixels) of points spread uniformly in the scene bounds between
    the true camera and the estimated one mapped into the true frame (``align_similarity``): the pose error
    as the images see it, blind to the rotation/translation trade-off a narrow field of view allows."""
    from ev3dgs.geometry import project
    from ev3dgs.train.pose_refine import align_similarity, apply_similarity

    pts = np.random.default_rng(seed).uniform(bounds[0], bounds[1], (n, 3))
    est = apply_similarity(est_mid, *align_similarity(est_mid, true_mid))
    out = []
    for e, t in zip(est, true_mid):
        (a, za), (b, zb) = project(K, e, pts), project(K, t, pts)
        ok = (za > 0) & (zb > 0)
        out.append(float(np.median(np.linalg.norm(a[ok] - b[ok], axis=1))))
    return np.array(out)


def step_cost(scene: str, steps: int = 40, block: int = 5) -> dict:
    """Seconds per training step with and without --refine-poses, measured in one process with blocks of
    ``block`` steps alternating between two trainers (poses moving from step 0), so machine load hits both
    alike; torch pinned to 1 thread by the trainer's step. Returns the medians and their ratio."""
    from ev3dgs.train.trainer import Trainer

    with tempfile.TemporaryDirectory() as d:
        base = TrainConfig(scene=scene, iterations=10 * steps, init_points=5000, device="cpu", backend="cpu",
                           pose_start=0, pose_warmup=0)
        tr = {k: Trainer(replace(base, refine_poses=k), Path(d) / str(k), quiet=True) for k in (False, True)}
        for t in tr.values():  # compile and warm up
            for _ in range(3):
                t.train_step()
        times = {False: [], True: []}
        for _ in range(steps // block):
            for k, t in tr.items():
                t0 = time.perf_counter()
                for _ in range(block):
                    t.train_step()
                times[k].append((time.perf_counter() - t0) / block)
    off, on = float(np.median(times[False])), float(np.median(times[True]))
    return {"seconds_per_step_off": off, "seconds_per_step_on": on, "ratio": on / off, "blocks": steps // block,
            "block": block, "ratio_per_block": [b / a for a, b in zip(times[False], times[True])]}


def errors(est_mid, true_mid, K, bounds) -> dict:
    e = pose_errors(est_mid, true_mid)
    raw = np.degrees(relative_rotation_angle(est_mid[:, :3, :3], true_mid[:, :3, :3]))
    e["rotation_deg_per_view"] = [float(x) for x in raw]  # unaligned: as the trainer saw them
    e["rotation_deg_mean_unaligned"] = float(raw.mean())
    px = reprojection_px(est_mid, true_mid, K, bounds)
    e["reprojection_px_per_view"] = [float(x) for x in px]
    e["reprojection_px_median"] = float(np.median(px))
    return e


def refine_name(lr: float, frame: str) -> str:
    """The run's name: "perturbed + refine (lr 0.003)" for world-frame corrections (the name the study used
    before --pose-frame existed), "perturbed + refine (lr 0.003, camera)" for camera-frame ones."""
    return f"perturbed + refine (lr {lr:g})" if frame == "world" else f"perturbed + refine (lr {lr:g}, {frame})"


def run_folder(name: str) -> str:
    return name.replace(" ", "_").replace("(", "").replace(")", "").replace(",", "")


def study_one(args, scene: str, d: Path, seed: int, iterations: int, lrs: list[float]) -> dict:
    """One perturbation + training seed: perturb, train the runs, evaluate; the per-seed JSON block."""
    pert = d / f"perturbed_s{seed}.h5"
    truth = perturb_scene(scene, pert, args.rot_deg, args.trans_frac, seed)
    base = TrainConfig(scene=scene, iterations=iterations, init_points=5000, seed=seed, device="cpu",
                       backend="cpu", checkpoint_every=10 ** 6, densify=not args.no_densify)
    sc0 = schema.read(scene)
    K0 = np.asarray(sc0.camera.K)
    bounds = np.asarray(sc0.bounds) if sc0.bounds is not None else np.array([[-1.0] * 3, [1.0] * 3])
    before = errors(truth["perturbed_mid"], truth["true_mid"], K0, bounds)
    runs = {} if args.skip_true else {"true poses": base}
    runs["perturbed"] = replace(base, scene=str(pert))
    for lr in lrs:
        for frame in args.pose_frame:
            runs[refine_name(lr, frame)] = replace(base, scene=str(pert), refine_poses=True, pose_lr=lr,
                                                   pose_frame=frame, pose_start=args.pose_start,
                                                   pose_warmup=args.pose_warmup)
    results = {}
    for name, cfg in runs.items():
        run_dir = d / "runs" / f"s{seed}" / run_folder(name)
        r = train_and_eval(cfg, run_dir, reuse=args.reuse)
        m, model = r.pop("metrics"), r.pop("model")
        row = {**r, "blur_view_psnr": m["blur_view"]["psnr"], "blur_view_ssim": m["blur_view"]["ssim"],
               "novel_view_psnr": m["novel_view"]["psnr"], "blurry_input_psnr": m["blurry_input"]["psnr"]}
        if cfg.refine_poses:
            from ev3dgs.train.pose_refine import load_trajectory

            row["pose_frame"] = cfg.pose_frame
            tj = load_trajectory(run_dir / "trajectory.npz", len(truth["true_mid"]))
            ex = schema.read(cfg.scene).train.exposure
            refined_mid = mid_poses(tj["poses"], tj["pose_t"], ex)
            row["pose_errors_after"] = errors(refined_mid, truth["true_mid"], K0, bounds)
            row["blur_view_psnr_given_poses"] = m["blur_view_given_poses"]["psnr"]
            row["novel_view_psnr_unaligned"] = m["novel_view_unaligned"]["psnr"]
            row["test_alignment"] = {k: m["test_alignment"][k] for k in ("scale", "rotation_deg", "translation")}
            row["pose_steps_skipped"] = r.pop("pose_skipped")
        if name == "perturbed":  # also at the poses it was trained with (what a user without ground truth has)
            from ev3dgs.train.evaluate import _scores, render_views

            sc = schema.read(cfg.scene)
            K = torch.as_tensor(sc.camera.K, dtype=torch.float32)
            bg = torch.as_tensor(sc.camera.background or (0, 0, 0), dtype=torch.float32)
            pred = render_views(model, truth["perturbed_mid"], K, sc.camera.width, sc.camera.height, bg, "cpu")
            row["blur_view_psnr_training_poses"] = _scores(pred, np.asarray(sc.train.sharp))["psnr"]
        results[name] = row
        after = row.get("pose_errors_after")
        extra = (f", rotation error {before['rotation_deg_median']:.3f} -> {after['rotation_deg_median']:.3f} deg "
                 f"(median, aligned), reprojection {before['reprojection_px_median']:.2f} -> "
                 f"{after['reprojection_px_median']:.2f} px" if after else "")
        print(f"{name:30s} blur-view {row['blur_view_psnr']:.2f} dB, novel {row['novel_view_psnr']:.2f} dB, "
              f"{r['seconds_per_step'] * 1e3:.0f} ms/step{extra}", flush=True)
    fov = float(np.degrees(2 * np.arctan(0.5 * sc0.camera.width / K0[0, 0])))
    cost = step_cost(str(pert)) if args.step_cost else None
    if cost:
        print(f"step cost: {cost['seconds_per_step_on'] * 1e3:.0f} ms with refinement vs "
              f"{cost['seconds_per_step_off'] * 1e3:.0f} ms without (x{cost['ratio']:.2f})", flush=True)
    return {"scene": Path(scene).name, "step_cost": cost, "size": f"{sc0.camera.width}x{sc0.camera.height}",
           "fov_deg": fov, "views": len(truth["true_mid"]),
           "iterations": iterations, "seed": seed, "rot_deg": args.rot_deg, "trans_frac": args.trans_frac,
           "pose_errors_before": before, "runs": results}


def summarise(per_seed: list[dict]) -> dict:
    """Mean, standard deviation (ddof 1) and values across seeds of the numbers the claims rest on, per run."""
    def stats(xs):
        xs = [float(x) for x in xs]
        return {"mean": float(np.mean(xs)), "std": float(np.std(xs, ddof=1)) if len(xs) > 1 else 0.0, "values": xs}

    out = {"rotation_deg_median_before": stats(s["pose_errors_before"]["rotation_deg_median"] for s in per_seed),
           "reprojection_px_median_before": stats(s["pose_errors_before"]["reprojection_px_median"]
                                                  for s in per_seed)}
    base = [s["runs"]["perturbed"] for s in per_seed]
    out["perturbed"] = {k: stats(r[k] for r in base) for k in
                        ("blur_view_psnr", "blur_view_psnr_training_poses", "novel_view_psnr")}
    for name in per_seed[0]["runs"]:
        rows = [s["runs"][name] for s in per_seed]
        if "pose_errors_after" not in rows[0]:
            continue
        e = {k: stats(r["pose_errors_after"][k] for r in rows) for k in
             ("rotation_deg_median", "rotation_deg_max", "centre_error_median", "reprojection_px_median")}
        ratio = stats(r["pose_errors_after"]["rotation_deg_median"] / s["pose_errors_before"]["rotation_deg_median"]
                      for r, s in zip(rows, per_seed))
        out[name] = {**e, "rotation_ratio_after_before": ratio,
                     "blur_view_psnr": stats(r["blur_view_psnr"] for r in rows),
                     "gain_db_vs_perturbed_given_poses": stats(r["blur_view_psnr"] - b["blur_view_psnr"]
                                                               for r, b in zip(rows, base)),
                     "gain_db_vs_perturbed_training_poses": stats(r["blur_view_psnr"] - b["blur_view_psnr_training_poses"]
                                                                  for r, b in zip(rows, base)),
                     "novel_view_psnr": stats(r["novel_view_psnr"] for r in rows)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps and one refinement setting (default: off)")
    ap.add_argument("--scene", help="scene .h5 with /train/sharp (default: simulate the quick lego at --size)")
    ap.add_argument("--size", default="64x48", help="image size of the simulated scene (default %(default)s)")
    ap.add_argument("--views", type=int, default=8, help="training views of the simulated scene (default 8)")
    ap.add_argument("--fov", type=float, help="horizontal field of view of the simulated scene, degrees "
                                              "(default: the scene's, 40)")
    ap.add_argument("--radius", type=float, help="camera distance from the origin in the simulated scene "
                                                 "(default: the scene's, 4)")
    ap.add_argument("--iterations", type=int, help="training steps (default 1500, --quick 500)")
    ap.add_argument("--rot-deg", type=float, default=1.0, help="rotation error per view, degrees (default 1)")
    ap.add_argument("--trans-frac", type=float, default=0.02,
                    help="translation error per view, fraction of the camera distance (default 0.02)")
    ap.add_argument("--pose-lr", type=float, nargs="+", default=None,
                    help="refinement learning rates to run (default 1e-3 3e-3; --quick 3e-3)")
    ap.add_argument("--pose-frame", nargs="+", choices=("world", "camera"), default=[TrainConfig.pose_frame],
                    help="axes of the refined runs' corrections (train --pose-frame), one refined run per frame "
                         "and learning rate (default: TrainConfig's, %(default)s)")
    ap.add_argument("--pose-start", type=int, help="the refined runs' train --pose-start (default: TrainConfig's)")
    ap.add_argument("--pose-warmup", type=int, help="the refined runs' train --pose-warmup (default: TrainConfig's)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0],
                    help="perturbation and training seeds, one study each; with several, the JSON also holds "
                         "their mean and standard deviation (default 0)")
    ap.add_argument("--no-densify", action="store_true",
                    help="every run keeps its initial Gaussians (train --no-densify): a scene with less freedom to "
                         "absorb pose error (default: off)")
    ap.add_argument("--skip-true", action="store_true",
                    help="leave out the training on the true poses (the upper bound) to save time (default: off)")
    ap.add_argument("--json", default="tools/results/study_refine.json", help="results (default %(default)s)")
    ap.add_argument("--plot", default="tools/results/study_refine.png", help="figure (default %(default)s)")
    ap.add_argument("--keep", help="folder to keep the scenes and runs in (default: a temporary one)")
    ap.add_argument("--step-cost", action="store_true",
                    help="also time training steps with and without refinement, interleaved in one process "
                         "(default: off)")
    ap.add_argument("--reuse", action="store_true",
                    help="with --keep: evaluate finished runs found there (same settings) instead of training "
                         "them again (default: off)")
    args = ap.parse_args(argv)
    args.pose_start = TrainConfig.pose_start if args.pose_start is None else args.pose_start
    args.pose_warmup = TrainConfig.pose_warmup if args.pose_warmup is None else args.pose_warmup
    iterations = args.iterations or (500 if args.quick else 1500)
    lrs = args.pose_lr or ([3e-3] if args.quick else [1e-3, 3e-3])
    W, H = (int(x) for x in args.size.split("x"))
    torch.set_num_threads(1)
    tmp = None if args.keep else tempfile.TemporaryDirectory()
    d = Path(args.keep or tmp.name)
    d.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    scene = args.scene
    if scene is None:
        from ev3dgs.demo import make_scene

        scene = str(make_scene(d / "scene", quiet=True, width=W, height=H, views=args.views, test_views=3,
                               fov_deg=args.fov, radius=args.radius))
    per_seed = [study_one(args, scene, d, seed, iterations, lrs) for seed in args.seeds]
    if len(per_seed) == 1:
        out = per_seed[0]
    else:
        out = {k: per_seed[0][k] for k in ("scene", "size", "fov_deg", "views", "iterations", "rot_deg",
                                            "trans_frac")}
        out.update(seeds=args.seeds, summary=summarise(per_seed), per_seed=per_seed)
    out["pose_frames"] = args.pose_frame
    out["densify"] = not args.no_densify
    out["pose_start"], out["pose_warmup"] = args.pose_start, args.pose_warmup
    out["seconds_total"] = time.perf_counter() - t_all
    out["command"] = "python tools/investigations/study_refine.py " + " ".join(argv if argv is not None else sys.argv[1:])
    save_json(args.json, out)
    (plot if len(per_seed) == 1 else plot_seeds)(out, args.plot)
    if tmp is not None:
        tmp.cleanup()
    return 0


def plot(out: dict, png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(out["runs"])
    fig, ax = plt.subplots(1, 3, figsize=(15, 3.8))
    x = np.arange(len(names))
    ax[0].bar(x - 0.2, [out["runs"][n]["blur_view_psnr"] for n in names], 0.4, label="blur views")
    ax[0].bar(x + 0.2, [out["runs"][n]["novel_view_psnr"] for n in names], 0.4, label="novel views (aligned)")
    ax[0].set_xticks(x, [n.replace(" + ", "\n+ ") for n in names], fontsize=7)
    ax[0].set_ylabel("PSNR (dB)")
    lo = min(min(out["runs"][n]["blur_view_psnr"], out["runs"][n]["novel_view_psnr"]) for n in names)
    ax[0].set_ylim(lo - 2, None)
    ax[0].legend(fontsize=8)
    for a, key, ylabel in ((ax[1], "rotation_deg_per_view", "mid-exposure rotation error (deg, unaligned)"),
                           (ax[2], "reprojection_px_per_view", "median reprojection error of scene points (px)")):
        a.plot(out["pose_errors_before"][key], "ko-", label="perturbed (before)")
        for n in names:
            if "pose_errors_after" in out["runs"][n]:
                a.plot(out["runs"][n]["pose_errors_after"][key], "o-", label=n)
        a.set_xlabel("training view")
        a.set_ylabel(ylabel)
        a.legend(fontsize=7)
    ax[2].set_ylim(0, None)
    fig.suptitle(f"--refine-poses on {out['scene']} {out['size']} (FOV {out['fov_deg']:.0f} deg), {out['views']} "
                 f"views, {out['iterations']} steps, {out['rot_deg']} deg / {out['trans_frac']:.0%} pose errors",
                 fontsize=9)
    fig.tight_layout()
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)
    plt.close(fig)


def plot_seeds(out: dict, png: str) -> None:
    """Several seeds: per seed, the rotation error before/after and the blur-view PSNR of each run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds, per = out["seeds"], out["per_seed"]
    names = list(per[0]["runs"])
    fig, ax = plt.subplots(1, 3, figsize=(15, 3.8))
    x = np.arange(len(seeds))
    w = 0.8 / (len(names) + 1)
    ax[0].bar(x - 0.4 + w / 2, [p["runs"]["perturbed"]["blur_view_psnr_training_poses"] for p in per], w,
              label="perturbed, at its training poses")
    for j, n in enumerate(names):
        ax[0].bar(x - 0.4 + (j + 1.5) * w, [p["runs"][n]["blur_view_psnr"] for p in per], w, label=n)
    ax[0].set_ylabel("blur-view PSNR (dB)")
    lo = min(min(p["runs"][n]["blur_view_psnr"] for n in names) for p in per)
    ax[0].set_ylim(lo - 2, None)
    for a, key, ylabel in ((ax[1], "rotation_deg_median", "median mid-exposure rotation error (deg, aligned)"),
                           (ax[2], "reprojection_px_median", "median reprojection error (px)")):
        a.bar(x - 0.2, [p["pose_errors_before"][key] for p in per], 0.4, color="k", label="perturbed (before)")
        refined = [n for n in names if "pose_errors_after" in per[0]["runs"][n]]
        for j, n in enumerate(refined):
            a.bar(x + 0.2 + j * 0.4 / len(refined), [p["runs"][n]["pose_errors_after"][key] for p in per],
                  0.4 / len(refined), label=n)
        a.set_ylabel(ylabel)
    ax[1].axhline(0.5 * out["summary"]["rotation_deg_median_before"]["mean"], ls="--", c="grey",
                  label="half the error before")
    for a in ax:
        a.set_xticks(x, [f"seed {s}" for s in seeds])
        a.legend(fontsize=7)
    fig.suptitle(f"--refine-poses on {out['scene']} {out['size']} (FOV {out['fov_deg']:.0f} deg), {out['views']} "
                 f"views, {out['iterations']} steps, {out['rot_deg']} deg / {out['trans_frac']:.0%} pose errors, "
                 f"{len(seeds)} seeds", fontsize=9)
    fig.tight_layout()
    Path(png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
