"""What accuracy costs in time for the trainer: PSNR on the sharp test views against training wall time for
naive, blur-only and blur+event on the --quick lego scene of `make demo`. JSON + PNG.

    python tools/bench/bench_train.py [--scene demo_out/lego.h5] [--iterations 1500] [--eval-every 250]
    python tools/bench/bench_train.py --scaling [--threads 1] [--quick]
    python tools/bench/bench_train.py --speed --against DIR --scene S.h5 [--iterations 500] [--threads 1 2]

--scaling: how the cost of one blur+event step grows with the data (synthetic, no scene file needed): ms per
step (5 sub-poses, all 10 event pairs, SH degree 3, forward + backward + Adam, the trainer's step on the
cpu backend) against the pixel count at 6k Gaussians and against the Gaussian count at 96x72, log-log,
written to tools/results/bench_train_scaling.{json,png}.

--speed: ms/step and PSNR of the blur+event variant side by side with another checkout (DIR, e.g. an old
commit unpacked with `git archive`), both checkouts' runs at the same time, one subprocess each
(bench_train_speed.py); JSON only.
"""
from __future__ import annotations

import sys

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

from ev3dgs.train.compare import compare_variants, summary_table  # noqa: E402
from ev3dgs.train.config import TrainConfig  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="scene .h5 (default: make the demo's quick lego scene)")
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--threads", type=int, nargs="+", default=None,
                    help="torch/numba threads (default: torch's; --speed: 1); --speed takes several")
    ap.add_argument("--json", default="tools/results/bench_train.json")
    ap.add_argument("--plot", default="tools/results/bench_train.png")
    ap.add_argument("--scaling", action="store_true", help="ms/step against pixels and Gaussians (synthetic)")
    ap.add_argument("--quick", action="store_true", help="with --scaling: fewer, smaller points")
    ap.add_argument("--speed", action="store_true", help="side by side with --against (default: off)")
    ap.add_argument("--against", help="--speed: the other checkout's root folder (its ev3dgs/ is imported)")
    ap.add_argument("--repeats", type=int, default=1, help="--speed: run pairs per thread count (default 1)")
    ap.add_argument("--seed", type=int, default=0, help="--speed: training seed (default 0)")
    ap.add_argument("--no-densify", action="store_true",
                    help="--speed: train without densification, so both checkouts keep the init's Gaussian count "
                         "(the same work per step; default: off, densify as the trainer does)")
    ap.add_argument("--one-at-a-time", action="store_true",
                    help="--speed: run the two checkouts one after the other, not at the same time (default: off)")
    args = ap.parse_args(argv)
    if args.scaling:
        from bench_train_scaling import run_scaling

        return run_scaling(args.threads[0] if args.threads else 1, args.quick,
                           "tools/results/bench_train_scaling.json", "tools/results/bench_train_scaling.png")
    if args.speed:
        from bench_train_speed import run_speed

        if not args.against or not args.scene:
            ap.error("--speed needs --against DIR and --scene S.h5")
        out = run_speed(args.scene, args.against, args.iterations, args.threads or [1], args.seed, args.repeats,
                        concurrent=not args.one_at_a_time, densify=not args.no_densify)
        save_json(args.json if args.json != ap.get_default("json") else "tools/results/bench_train_speed.json", out)
        return 0
    with tempfile.TemporaryDirectory() as d:
        scene = args.scene
        if scene is None:
            from ev3dgs.demo import DEMO_RENDER, make_scene

            scene = str(make_scene(Path(d) / "scene", quiet=True, **DEMO_RENDER))
        base = TrainConfig(scene=scene, iterations=args.iterations, init_points=5000,
                           threads=args.threads[0] if args.threads else None)
        results = compare_variants(scene, Path(d) / "runs", base, eval_every=args.eval_every)
    print(summary_table(results))
    out = {"iterations": args.iterations,
           "variants": {k: {"test_psnr": v["metrics"]["test"]["psnr"], "test_ssim": v["metrics"]["test"]["ssim"],
                            "train_sharp_psnr": v["metrics"]["train_sharp"]["psnr"],
                            "blurry_input_psnr": v["metrics"]["blurry_input"]["psnr"],
                            "train_seconds": v["train_seconds"], "gaussians": v["gaussians"], "curve": v["curve"]}
                        for k, v in results.items()}}
    save_json(args.json, out)
    plot(out, args.plot)
    return 0


def plot(out, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, v in out["variants"].items():
        ax.plot([c["seconds"] for c in v["curve"]], [c["test_psnr"] for c in v["curve"]], "o-", ms=3, label=name)
    blurry = next(iter(out["variants"].values()))["blurry_input_psnr"]
    ax.axhline(blurry, color="grey", ls="--", lw=1, label="blurry input vs sharp (train views)")
    ax.set_xlabel("training seconds (2-core CPU)")
    ax.set_ylabel("PSNR on sharp test views (dB)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
