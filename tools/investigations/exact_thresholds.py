"""What is a threshold map worth at best? ``--threshold-map`` with the thresholds the simulator drew in place
of the fitted ones.

A built-in scene's per-pixel ON and OFF thresholds come from the simulator's mismatch stream (dataset seed
0, the benchmark's). This run trains like bench_fidelity's ``blur+event-mapprior`` (``--threshold-map``,
prior weights) but sets the map's multipliers to the drawn thresholds over the nominal ones after every
solve: the event term then reads each pixel's counts at its true thresholds, with the same weights as
without a map. What it gains over the default is what per-pixel thresholds can give on that scene; what
the fitted map gains less is its estimation error.

    python tools/investigations/exact_thresholds.py --scenes ficus materials lowlight --seeds 0 1 2 \
        --json tools/results/exact_thresholds.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools" / "bench"))

from bench_fidelity import MEAN_FLOOR  # noqa: E402
from ev3dgs.train.jobs import run_parallel  # noqa: E402


def drawn_multipliers(scene: str, height: int, width: int) -> np.ndarray:
    """(2, H, W) ON and OFF thresholds the simulator draws for built-in ``scene`` (dataset seed 0) over the
    nominal ones: the pattern a perfect threshold map would find."""
    from ev3dgs.sim.dvs import DVSSimulator
    from ev3dgs.sim.scenes import load_scene

    dvs = load_scene(scene).sensor.dvs
    sim = DVSSimulator(height, width, dvs, seed=0)
    return np.stack([sim.c_on / dvs.pos_threshold, sim.c_off / dvs.neg_threshold]).reshape(2, height, width)


_ORIGINAL: dict = {}


def _run(job: dict) -> dict:
    """One training in a pool worker (one thread), the map held at the drawn thresholds."""
    import torch

    import ev3dgs.train.threshold_map as tm
    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.evaluate import evaluate
    from ev3dgs.train.trainer import Trainer

    torch.set_num_threads(1)
    solve = _ORIGINAL.setdefault("calibrate", tm.ThresholdMap._calibrate)   # a worker's later job: not a wrapper
    true = torch.from_numpy(drawn_multipliers(job["scene"], job["height"], job["width"]))

    def calibrate(self, m, informed):   # the fit as usual, then the multipliers replaced by the truth
        solve(self, m, informed)
        self.multiplier = true.to(self.stats.dtype)

    tm.ThresholdMap._calibrate = calibrate
    out = Path(job["out"])
    # the mean floor, as the blur+event-mapprior table this is set against (bench_fidelity.MEAN_FLOOR)
    cfg = TrainConfig(scene=job["path"], iterations=job["iterations"], init_points=5000, seed=job["seed"],
                      checkpoint_every=job["iterations"], threads=1, threshold_map=True, **MEAN_FLOOR)
    t = time.perf_counter()
    Trainer(cfg, out, quiet=True).fit()
    m = evaluate(out, write_images=False)
    return {"scene": job["scene"], "seed": job["seed"], "train_seconds": time.perf_counter() - t,
            **{v: m[v]["psnr"] for v in ("blur_view", "novel_view")}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["ficus", "materials", "lowlight"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--cache", type=Path, default=ROOT / "tools/results/fidelity_cache",
                    help="bench_fidelity's cache: its 24 + 8-view 96x72 scene files and a folder for these runs")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", type=Path, default=ROOT / "tools/results/exact_thresholds.json")
    a = ap.parse_args(argv)
    jobs = []
    for seed in a.seeds:
        for scene in a.scenes:
            path = a.cache / f"{scene}_96x72_v24t8s17p16.h5"
            if not path.exists():
                ap.error(f"{path} is missing: make it with tools/bench/bench_fidelity.py --scenes {scene}")
            jobs.append({"scene": scene, "seed": seed, "path": str(path), "height": 72, "width": 96,
                         "iterations": a.iterations,
                         "out": str(a.cache / "runs" / path.stem / f"exact_thresholds_s{seed}")})
    runs = run_parallel(_run, jobs, a.jobs, lambda r: print(json.dumps(r), flush=True) or r)
    a.json.parent.mkdir(parents=True, exist_ok=True)
    settings = {"scenes": a.scenes, "seeds": a.seeds, "iterations": a.iterations, "views": "24 + 8",
                "size": "96x72", "dataset_seed": 0}
    a.json.write_text(json.dumps({"settings": settings, "runs": runs}, indent=2))
    print(f"-> {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
