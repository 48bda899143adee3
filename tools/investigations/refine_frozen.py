"""Study (issue 16): is the rotation left after `--refine-poses` a limit of what the images say, or of the
joint optimisation?  Pose-only refinement against a FROZEN scene.

The joint problem (`study_refine.py`) lets the Gaussians move while the cameras do: a scene fitted to wrong
poses can absorb part of each view's error, and the gradients the cameras get come from a scene that is itself
wrong. Here the scene is trained first and then frozen (every Gaussian learning rate 0, no densification; the
tool stops if any Gaussian parameter changes), and only the pose corrections are optimised, with the same
losses, on the perturbed scene (1 deg + 2 % per view, the study's perturbation). ``--scene-from`` picks the
scene:

* ``true``: trained on the true poses (the study's "true poses" run, the upper bound), one for all seeds.
  If the rotation then falls well below half, the images do pin the cameras;
* ``perturbed``: trained on the perturbed poses without refinement (what a scene fitted to wrong poses
  leaves for the cameras to find);
* ``joint``: trained on the perturbed poses with ``--refine-poses``; the pose-only phase starts from its
  corrections (does a final pose-only phase help a joint run?).

The scene fixes the gauge (``pose_gauge="none"``); the errors are measured as in the study
(similarity-aligned centres and orientations), split into roll and pan/tilt in each true camera's axes
(``refine_compensation.split_errors``), and without any alignment.

    python tools/investigations/refine_frozen.py --scene lego96.h5 --seeds 0 1 2 --scene-steps 1500 --pose-steps 1200 \
        --scene-from true --json tools/results/refine_frozen_true_1200.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import refine_compensation  # noqa: E402
import study_refine  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

from ev3dgs import schema  # noqa: E402
from ev3dgs.train.config import TrainConfig  # noqa: E402


def fit_scene(scene: str, steps: int, seed: int, run: Path, refine: bool = False, lr: float = 3e-3,
              frame: str = "camera") -> dict:
    """A scene to freeze: the trainer's defaults on ``scene`` (with ``refine``, jointly with --refine-poses
    at its default schedule). Returns the model's state_dict, the pose corrections (refine) and the
    refined mid-exposure cameras (refine), and the blur-view PSNR of the run."""
    from ev3dgs.train.evaluate import evaluate
    from ev3dgs.train.trainer import Trainer

    cfg = TrainConfig(scene=scene, iterations=steps, init_points=5000, seed=seed, device="cpu", backend="cpu",
                      checkpoint_every=10 ** 6, refine_poses=refine, pose_lr=lr, pose_frame=frame)
    tr = Trainer(cfg, run, quiet=True)
    tr.fit()
    out = {"state": tr.model.state_dict(), "corrections": None, "refined_mid": None,
           "blur_view_psnr": evaluate(run, device="cpu", write_images=False)["blur_view"]["psnr"]}
    if refine:
        refiner = tr.term("poses").refiner
        out["corrections"] = torch.stack([p.detach() for p in refiner.params]).clone()
        ex = schema.read(scene).train.exposure
        out["refined_mid"] = study_refine.mid_poses(refiner.all_c2w(), np.asarray(refiner.times), ex)
    return out


def frozen_refine(pert_scene: str, known: dict, steps: int, lr: float, frame: str, seed: int, run: Path):
    """Only the poses move: the trainer on the perturbed scene with the known model loaded, every Gaussian
    learning rate 0, no densification, poses from step 0 (starting from ``known["corrections"]`` when the
    known scene was trained jointly with refinement). Returns the refined mid-exposure camera-to-world and
    the blur-view PSNR at the refined poses."""
    from ev3dgs.train.evaluate import evaluate
    from ev3dgs.train.trainer import Trainer

    cfg = TrainConfig(scene=pert_scene, iterations=steps, init_points=5000, seed=seed, device="cpu", backend="cpu",
                      checkpoint_every=10 ** 6, densify=False, refine_poses=True, pose_lr=lr, pose_frame=frame,
                      pose_start=0, pose_warmup=0, pose_gauge="none", sh_interval=10 ** 9)
    tr = Trainer(cfg, run, quiet=True)
    tr.model.load_state_dict(known["state"])
    if known["corrections"] is not None:
        with torch.no_grad():
            for v, p in enumerate(tr.term("poses").refiner.params):
                p.copy_(known["corrections"][v])
    tr.optimizers = tr.model.make_optimizers(scene_scale=tr.data.scene_scale)  # for the loaded tensors
    for opt in tr.optimizers.values():
        for g in opt.param_groups:
            g["lr"] = 0.0
    tr.strategy_state = tr.strategy.initialize_state(len(tr.model), device=tr.device)
    tr.means_lr0 = 0.0  # _set_lr rescales the means' rate from this every step
    before = {k: v.detach().clone() for k, v in tr.model.params.items()}
    for _ in range(steps):
        tr.train_step()
    moved = max(float((tr.model.params[k].detach() - before[k]).abs().max()) for k in before)
    if moved != 0.0:
        raise SystemExit(f"error: the frozen Gaussians moved (max change {moved})")
    tr.save_model()  # model.pt (the frozen scene) and trajectory.npz (the refined poses), for evaluate
    psnr = evaluate(run, device="cpu", write_images=False)["blur_view"]["psnr"]
    ex = schema.read(pert_scene).train.exposure
    refiner = tr.term("poses").refiner
    return study_refine.mid_poses(refiner.all_c2w(), np.asarray(refiner.times), ex), psnr


def scene_geometry(path: str):
    """(schema scene, K, bounds) of a scene file: what the error measures need."""
    sc = schema.read(path)
    bounds = np.asarray(sc.bounds) if sc.bounds is not None else np.array([[-1.0] * 3, [1.0] * 3])
    return sc, np.asarray(sc.camera.K), bounds


def measure(est_mid, true_mid, K, bounds) -> dict:
    e = study_refine.errors(est_mid, true_mid, K, bounds)
    split = refine_compensation.split_errors(est_mid, true_mid, K, bounds)
    return {"rotation_deg_median": e["rotation_deg_median"],
            "rotation_deg_median_unaligned": float(np.median(e["rotation_deg_per_view"])),
            "roll_deg_median": float(np.median(split["roll_deg"])),
            "pan_tilt_deg_median": float(np.median(split["pan_tilt_deg"])),
            "reprojection_px_median": e["reprojection_px_median"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="scene .h5 with /train/sharp (e.g. the quick lego at 96x72)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="perturbation seeds (default 0 1 2)")
    ap.add_argument("--scene-steps", type=int, default=1500, help="steps of the known scene (default 1500)")
    ap.add_argument("--pose-steps", type=int, default=1200, help="pose-only steps (default 1200)")
    ap.add_argument("--pose-lr", type=float, default=3e-3, help="pose learning rate (default 3e-3)")
    ap.add_argument("--pose-frame", default="camera", choices=("world", "camera"))
    ap.add_argument("--scene-from", default="true", choices=("true", "perturbed", "joint"),
                    help="the frozen scene: trained on the true poses (one for all seeds), on the perturbed "
                         "poses, or on the perturbed poses jointly with --refine-poses, whose corrections the "
                         "pose-only phase then starts from (default: true)")
    ap.add_argument("--rot-deg", type=float, default=1.0)
    ap.add_argument("--trans-frac", type=float, default=0.02)
    ap.add_argument("--json", default="tools/results/refine_frozen.json")
    ap.add_argument("--keep", help="folder to keep the runs in (default: a temporary one)")
    args = ap.parse_args(argv)
    sc, K, bounds = scene_geometry(args.scene)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(args.keep or tmp)
        d.mkdir(parents=True, exist_ok=True)
        if args.scene_from == "true":  # one known scene for every perturbation
            known = fit_scene(args.scene, args.scene_steps, 0, d / "known")
        rows = []
        for seed in args.seeds:
            pert = d / f"perturbed_s{seed}.h5"
            truth = study_refine.perturb_scene(args.scene, pert, args.rot_deg, args.trans_frac, seed)
            if args.scene_from != "true":  # the scene a user would have: trained on the perturbed poses
                known = fit_scene(str(pert), args.scene_steps, seed, d / f"{args.scene_from}_s{seed}",
                                  refine=args.scene_from == "joint", lr=args.pose_lr, frame=args.pose_frame)
            before = measure(truth["perturbed_mid"], truth["true_mid"], K, bounds)
            est, psnr = frozen_refine(str(pert), known, args.pose_steps, args.pose_lr, args.pose_frame, seed,
                                      d / f"frozen_s{seed}")
            after = measure(est, truth["true_mid"], K, bounds)
            ratio = {k: after[k] / before[k] for k in before if before[k] > 0}
            row = {"seed": seed, "before": before, "after": after, "ratio": ratio,
                   "blur_view_psnr_scene": known["blur_view_psnr"], "blur_view_psnr_after": psnr}
            if known["refined_mid"] is not None:  # the joint run's own poses, before the pose-only phase
                joint = measure(known["refined_mid"], truth["true_mid"], K, bounds)
                row["joint"] = joint
                row["ratio_joint"] = {k: joint[k] / before[k] for k in before if before[k] > 0}
            rows.append(row)
            print(f"seed {seed}: rotation {before['rotation_deg_median']:.3f} -> {after['rotation_deg_median']:.3f} "
                  f"deg (x{ratio['rotation_deg_median']:.2f}; unaligned x{ratio['rotation_deg_median_unaligned']:.2f}),"
                  f" roll x{ratio['roll_deg_median']:.2f}, pan/tilt x{ratio['pan_tilt_deg_median']:.2f}, "
                  f"reprojection {before['reprojection_px_median']:.2f} -> {after['reprojection_px_median']:.2f} px;"
                  f" blur view {known['blur_view_psnr']:.2f} -> {psnr:.2f} dB"
                  + (f"; joint alone x{row['ratio_joint']['rotation_deg_median']:.2f}" if "joint" in row else ""),
                  flush=True)
    summary = {}
    for name, get in (("ratio", lambda r: r["ratio"]), ("ratio_joint", lambda r: r.get("ratio_joint")),
                      ("blur_view_psnr", lambda r: {"scene": r["blur_view_psnr_scene"],
                                                    "after": r["blur_view_psnr_after"]})):
        if get(rows[0]) is None:
            continue
        summary[name] = {}
        for k in get(rows[0]):
            xs = [get(r)[k] for r in rows]
            summary[name][k] = {"mean": statistics.mean(xs), "std": statistics.stdev(xs) if len(xs) > 1 else 0.0,
                                "values": xs}
    out = {"study": "pose-only refinement against a frozen scene", "scene_from": args.scene_from,
           "scene": Path(args.scene).name, "size": f"{sc.camera.width}x{sc.camera.height}",
           "scene_steps": args.scene_steps, "pose_steps": args.pose_steps, "pose_lr": args.pose_lr,
           "pose_frame": args.pose_frame, "rot_deg": args.rot_deg, "trans_frac": args.trans_frac,
           "per_seed": rows, "summary": summary,
           "command": "python tools/investigations/refine_frozen.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    save_json(args.json, out)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
