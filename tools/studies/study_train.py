"""Study: what the trainer's accuracy costs. On the `make demo` scene: poses per exposure b+1 (2, 3, 5, 9),
event-pair sampling (all vs 3 random), iterations (the PSNR curve along each run), and the naive /
blur-only / blur+event variants; PSNR/SSIM on the sharp test views against training wall time.

    python tools/studies/study_train.py [--quick] [--scene demo_out/lego.h5] --json tools/results/study_train.json
"""
from __future__ import annotations

import sys

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import pareto_plot, save_json  # noqa: E402

from ev3dgs.train.compare import compare_variants  # noqa: E402
from ev3dgs.train.config import TrainConfig  # noqa: E402

RUNS = {
    "naive": dict(naive=True),
    "blur-only b+1=5": dict(event_loss=False),
    "blur+event b+1=2": dict(subposes=2),
    "blur+event b+1=3": dict(subposes=3),
    "blur+event b+1=5": dict(subposes=5),
    "blur+event b+1=9": dict(subposes=9),
    "blur+event b+1=5, 3 random pairs": dict(subposes=5, event_pairs=3),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scene", help="scene .h5 (default: make the demo's quick lego scene)")
    ap.add_argument("--json", default="tools/results/study_train.json")
    ap.add_argument("--plot", default="tools/results/study_train.png")
    args = ap.parse_args(argv)
    iterations = 600 if args.quick else 1500
    with tempfile.TemporaryDirectory() as d:
        scene = args.scene
        if scene is None:
            from ev3dgs.demo import DEMO_RENDER, make_scene

            scene = str(make_scene(Path(d) / "scene", quiet=True, **DEMO_RENDER))
        base = TrainConfig(scene=scene, iterations=iterations, init_points=5000)
        results = compare_variants(scene, Path(d) / "runs", base, eval_every=iterations // 4, variants=RUNS)
    rows = {}
    for name, r in results.items():
        rows[name] = [{"label": c["step"], "seconds": c["seconds"], "test_psnr": c["test_psnr"],
                       "train_sharp_psnr": c["train_sharp_psnr"]} for c in r["curve"]]
        m = r["metrics"]
        print(f"{name:34s} test {m['test']['psnr']:.2f} dB / SSIM {m['test']['ssim']:.3f}, "
              f"deblurred train {m['train_sharp']['psnr']:.2f} dB, {r['train_seconds']:.0f} s")
    save_json(args.json, {"iterations": iterations, "curves": rows,
                          "final": {k: {"test_psnr": v["metrics"]["test"]["psnr"],
                                        "test_ssim": v["metrics"]["test"]["ssim"],
                                        "train_sharp_psnr": v["metrics"]["train_sharp"]["psnr"],
                                        "blurry_input_psnr": v["metrics"]["blurry_input"]["psnr"],
                                        "train_seconds": v["train_seconds"]} for k, v in results.items()}})
    pareto_plot(args.plot, rows, "seconds", "test_psnr", "training seconds (2-core CPU; points = steps)",
                "PSNR on sharp test views (dB)", "Trainer: sub-poses, event pairs, variants", logx=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
