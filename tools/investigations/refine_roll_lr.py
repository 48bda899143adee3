"""Study (issue 16): is the roll left after `--refine-poses` a matter of step size?  A larger learning rate for
the roll coordinate alone.

In camera-frame corrections (``--pose-frame camera``) omega_z is the roll about the view's optical axis, the
component the images constrain least (docs/trainer.md, pose refinement). Adam's moments do not
depend on the learning rate, so scaling one coordinate's update by K after each Adam step is Adam with that
coordinate's learning rate times K. This study patches ``PoseRefiner.step`` to do exactly that (then projects
the gauge and clamps again, as every step does) and runs ``study_refine.py`` once per K on one scene, the same
perturbations and seeds, then ``refine_compensation.py`` for the roll and pan/tilt split. A study-only knob:
it is not a trainer option, because it does not help (see docs/trainer.md).

    python tools/investigations/refine_roll_lr.py --scene lego96.h5 --roll-scale 1 3 10 --seeds 0 1 2 \
        --json tools/results/refine_roll_lr.json
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import refine_compensation  # noqa: E402
import study_refine  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

from ev3dgs.train import pose_refine  # noqa: E402

ROLL = 5  # index of omega_z in a (rho, omega) correction
_SCALE = {"roll": 1.0}
_step = pose_refine.PoseRefiner.step


def _scaled_step(self, step: int) -> dict:
    before = [p.detach().clone() for p in self.params]
    out = _step(self, step)
    if _SCALE["roll"] != 1.0 and out["pose_lr"] > 0:
        with torch.no_grad():
            for p, b in zip(self.params, before):
                p[:, ROLL] = b[:, ROLL] + _SCALE["roll"] * (p[:, ROLL] - b[:, ROLL])
        self._project()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="scene .h5 with /train/sharp (e.g. the quick lego at 96x72)")
    ap.add_argument("--roll-scale", type=float, nargs="+", default=[1.0, 3.0, 10.0],
                    help="roll learning-rate multipliers, one study each (default 1 3 10)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="study seeds (default 0 1 2)")
    ap.add_argument("--pose-lr", type=float, default=3e-3, help="pose learning rate (default 3e-3)")
    ap.add_argument("--iterations", type=int, default=500, help="training steps (default 500)")
    ap.add_argument("--json", default="tools/results/refine_roll_lr.json")
    ap.add_argument("--keep", help="folder to keep the runs in (default: a temporary one)")
    args = ap.parse_args(argv)
    pose_refine.PoseRefiner.step = _scaled_step
    tmp = None if args.keep else tempfile.TemporaryDirectory()
    root = Path(args.keep or tmp.name)
    rows = []
    for k in args.roll_scale:
        _SCALE["roll"] = k
        keep = root / f"roll{k:g}"
        study_json, comp_json = keep / "study.json", keep / "compensation.json"
        study_refine.main(["--scene", args.scene, "--seeds", *map(str, args.seeds), "--skip-true",
                           "--iterations", str(args.iterations), "--pose-lr", str(args.pose_lr),
                           "--pose-frame", "camera", "--keep", str(keep), "--json", str(study_json),
                           "--plot", str(keep / "study.png")])
        refine_compensation.main([*[str(keep)] * len(args.seeds), "--scene", args.scene,
                                  "--seed", *map(str, args.seeds), "--pose-lr", str(args.pose_lr),
                                  "--pose-frame", "camera", "--json", str(comp_json)])
        study, comp = json.loads(study_json.read_text()), json.loads(comp_json.read_text())
        name = study_refine.refine_name(args.pose_lr, "camera")
        seeds = study["per_seed"] if "per_seed" in study else [study]
        per_seed = []
        for s, c in zip(seeds, comp["rows"]):
            run = s["runs"][name]
            before, after = s["pose_errors_before"], run["pose_errors_after"]
            per_seed.append({
                "seed": c["seed"],
                "rotation_ratio": after["rotation_deg_median"] / before["rotation_deg_median"],
                "roll_ratio": c["after"]["roll_deg"] / c["before"]["roll_deg"],
                "pan_tilt_ratio": c["after"]["pan_tilt_deg"] / c["before"]["pan_tilt_deg"],
                "reprojection_px": [before["reprojection_px_median"], after["reprojection_px_median"]],
                "blur_view_gain_db": run["blur_view_psnr"] - s["runs"]["perturbed"]["blur_view_psnr_training_poses"]})
        summary = {key: [statistics.mean(r[key] for r in per_seed), statistics.pstdev(r[key] for r in per_seed)]
                   for key in ("rotation_ratio", "roll_ratio", "pan_tilt_ratio", "blur_view_gain_db")}
        rows.append({"roll_scale": k, "per_seed": per_seed, "mean_std": summary})
        print(f"roll lr x{k:g}: " + ", ".join(f"{key} {m:.2f} +- {sd:.2f}" for key, (m, sd) in summary.items()),
              flush=True)
    save_json(args.json, {"scene": args.scene, "pose_lr": args.pose_lr, "iterations": args.iterations,
                          "pose_frame": "camera", "rows": rows,
                          "command": "python tools/investigations/refine_roll_lr.py " + " ".join(sys.argv[1:] if argv is None else argv)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
