"""Study (issue 16): does the rotation left after `--refine-poses` hide behind a translation?  For a finished
tools/investigations/study_refine.py run (kept with --keep), the refined mid-exposure cameras (mapped onto the true frame by
``align_similarity``) are split into their two errors, and each is measured as the images see it (median
reprojection of points in the scene bounds, pixels):

* full: refined rotation and refined centre (what the loss was minimising);
* rotation only: refined rotation at the TRUE centre;
* centre only: the true rotation at the refined centre.

If the full error is well below both partial ones, the rotation and centre errors cancel in the image: the
loss sees (almost) no difference between the refined and the true camera, and the residual rotation sits on
a weakly observable rotation/translation trade-off rather than on a failure to optimise.

    python tools/investigations/refine_compensation.py KEEP_DIR [KEEP_DIR ...] [--json tools/results/refine_compensation.json]

KEEP_DIR is a study_refine.py --keep folder (holding scene/lego.h5, else name the scene with --scene), or
one refined run folder (holding trajectory.npz).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402


def split_errors(refined_mid: np.ndarray, true_mid: np.ndarray, K: np.ndarray, bounds: np.ndarray,
                 n: int = 2000, seed: int = 0) -> dict:
    """Per view, median reprojection (px) of n points uniform in ``bounds`` for the full, rotation-only and
    centre-only error of ``refined_mid`` against ``true_mid`` (both (M, 4, 4) camera-to-world), after the
    similarity alignment of the refined cameras onto the true ones."""
    from ev3dgs.geometry import matrix_to_rotvec, project
    from ev3dgs.train.pose_refine import align_similarity, apply_similarity

    pts = np.random.default_rng(seed).uniform(bounds[0], bounds[1], (n, 3))
    est = apply_similarity(refined_mid, *align_similarity(refined_mid, true_mid))
    rot_only, cen_only = true_mid.copy(), true_mid.copy()
    rot_only[:, :3, :3] = est[:, :3, :3]
    cen_only[:, :3, 3] = est[:, :3, 3]
    out = {}
    for name, cams in (("full", est), ("rotation_only", rot_only), ("centre_only", cen_only)):
        px = []
        for e, t in zip(cams, true_mid):
            (a, za), (b, zb) = project(K, e, pts), project(K, t, pts)
            ok = (za > 0) & (zb > 0)
            px.append(float(np.median(np.linalg.norm(a[ok] - b[ok], axis=1))))
        out[name] = px
    # the residual rotation in each TRUE camera's own axes (OpenCV: z = optical axis): roll (about z) turns the
    # image about the principal point, so for a centred object it moves pixels far less than pan/tilt (x, y)
    rv = np.stack([matrix_to_rotvec(t[:3, :3].T @ e[:3, :3]) for e, t in
                   zip(est, true_mid)])
    out["roll_deg"] = np.degrees(np.abs(rv[:, 2])).tolist()
    out["pan_tilt_deg"] = np.degrees(np.linalg.norm(rv[:, :2], axis=1)).tolist()
    return out


def analyse(keep: Path, scene: Path, seed: int, rot_deg: float, trans_frac: float, lr: float,
            frame: str = "world") -> dict:
    import study_refine
    from ev3dgs import schema
    from ev3dgs.train.pose_refine import load_trajectory

    sc = schema.read(str(scene))
    K = np.asarray(sc.camera.K)
    bounds = np.asarray(sc.bounds) if sc.bounds is not None else np.array([[-1.0] * 3, [1.0] * 3])
    with tempfile.TemporaryDirectory() as d:  # the perturbation is seeded: re-derive the truth it started from
        truth = study_refine.perturb_scene(str(scene), Path(d) / "p.h5", rot_deg, trans_frac, seed)
    run = keep if (keep / "trajectory.npz").is_file() else \
        keep / "runs" / f"s{seed}" / study_refine.run_folder(study_refine.refine_name(lr, frame))
    if not (run / "trajectory.npz").is_file():
        raise SystemExit(f"error: no refined run at {run}")
    tj = load_trajectory(run / "trajectory.npz", len(truth["true_mid"]))
    refined = study_refine.mid_poses(tj["poses"], tj["pose_t"], sc.train.exposure)
    before = split_errors(truth["perturbed_mid"], truth["true_mid"], K, bounds)
    after = split_errors(refined, truth["true_mid"], K, bounds)
    med = lambda v: float(np.median(v))  # noqa: E731
    return {"keep": str(keep), "scene": scene.name, "pose_lr": lr, "pose_frame": frame, "run": run.name,
            "size": f"{sc.camera.width}x{sc.camera.height}",
            "iterations": json.loads((run / "config.json").read_text()).get("iterations"), "seed": seed,
            "before": {k: med(v) for k, v in before.items()}, "after": {k: med(v) for k, v in after.items()},
            "after_per_view": after}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("keep", nargs="+", help="study_refine.py --keep folders (no default)")
    p.add_argument("--scene", nargs="+", default=None,
                   help="the studies' scene .h5 files, one for all or one per KEEP_DIR (default: KEEP_DIR/scene/"
                        "lego.h5, what study_refine simulates)")
    p.add_argument("--seed", type=int, nargs="+", default=[0],
                   help="the study seeds, one for all or one per KEEP_DIR (default 0)")
    p.add_argument("--pose-lr", type=float, nargs="+", default=[3e-3],
                   help="the refined runs' learning rates, one for all or one per KEEP_DIR (default 3e-3)")
    p.add_argument("--pose-frame", nargs="+", choices=("world", "camera"), default=["world"],
                   help="the refined runs' frames (study_refine --pose-frame), one for all or one per KEEP_DIR "
                        "(default world)")
    p.add_argument("--rot-deg", type=float, default=1.0, help="the study's rotation error, degrees (default 1)")
    p.add_argument("--trans-frac", type=float, default=0.02,
                   help="the study's translation error, fraction of the camera distance (default 0.02)")
    p.add_argument("--json", default="tools/results/refine_compensation.json",
                   help="results (default tools/results/refine_compensation.json)")
    a = p.parse_args(argv)
    n = len(a.keep)
    for name, v in (("--scene", a.scene), ("--seed", a.seed), ("--pose-lr", a.pose_lr),
                    ("--pose-frame", a.pose_frame)):
        if v is not None and len(v) not in (1, n):
            raise SystemExit(f"error: {name} takes one value or one per KEEP_DIR ({n}), not {len(v)}")
    pick = lambda v, i: v[0] if len(v) == 1 else v[i]  # noqa: E731
    rows = []
    for i, k in enumerate(a.keep):
        scene = Path(pick(a.scene, i)) if a.scene else Path(k) / "scene" / "lego.h5"
        r = analyse(Path(k), scene, pick(a.seed, i), a.rot_deg, a.trans_frac, pick(a.pose_lr, i),
                    pick(a.pose_frame, i))
        rows.append(r)
        b, f = r["before"], r["after"]
        print(f"{r['size']:>6} {r['iterations']} steps seed {r['seed']} {r['scene']} {r['pose_frame']}: px before "
              f"full "
              f"{b['full']:.2f} (rotation only "
              f"{b['rotation_only']:.2f}, centre only {b['centre_only']:.2f}); after full {f['full']:.2f} "
              f"(rotation only {f['rotation_only']:.2f}, centre only {f['centre_only']:.2f}); rotation deg "
              f"(median) roll {b['roll_deg']:.2f} -> {f['roll_deg']:.2f}, pan/tilt {b['pan_tilt_deg']:.2f} -> "
              f"{f['pan_tilt_deg']:.2f}")
    save_json(a.json, {"rows": rows, "command": "python tools/investigations/refine_compensation.py "
                       + " ".join(sys.argv[1:] if argv is None else argv)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
