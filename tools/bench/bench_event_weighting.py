"""What the event term's weighting costs per step: the blur + event step on one scene file with the default
mean floor (``--event-floor mean --event-huber 0 --densify-from all``), the chi-square floor with the Huber
penalty (``--event-floor chi2 --event-huber 3``) and both with the densification statistics from the blur
term too (``--densify-from blur``: one more backward pass through it while the strategy densifies), one
thread.

The steps are those of a 30 000-step run's first few hundred: densification statistics are gathered every
step (the extra backward pass runs), no Gaussian is split or pruned yet, so every variant renders the same
number of Gaussians. The variants' steps are interleaved round by round, so a busy machine slows them alike;
the result is each variant's median ms per step and its ratio to the mean floor's. JSON + PNG.

    python tools/bench/bench_event_weighting.py --scene tools/results/event_term_cache/t0.05_m0.1/scene.h5 \\
        [--rounds 48] [--init-points 5000] [--json tools/results/bench_event_weighting.json]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from pareto import save_json  # noqa: E402

VARIANTS = {"mean floor": dict(event_floor="mean", event_huber=0.0, densify_from="all"),
            "chi2 floor, Huber 3": dict(event_floor="chi2", event_huber=3.0, densify_from="all"),
            "+ densify from blur": dict(event_floor="chi2", event_huber=3.0, densify_from="blur")}
BASE = "mean floor"
ITERATIONS = 30_000   # the schedule of a full-length run: densification from step 500, statistics from step 0
WARMUP = 5


def measure(scene: str, rounds: int, init_points: int) -> dict:
    import torch

    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.trainer import Trainer

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        trainers = {name: Trainer(TrainConfig(scene=scene, iterations=ITERATIONS, init_points=init_points,
                                              threads=1, seed=0, **over), Path(tmp) / str(i), quiet=True)
                    for i, (name, over) in enumerate(VARIANTS.items())}
        refine_start = next(iter(trainers.values())).strategy.refine_start
        if WARMUP + rounds >= refine_start:
            raise SystemExit(f"--rounds must stay below {refine_start - WARMUP}: no Gaussian may be split yet")
        for tr in trainers.values():
            for _ in range(WARMUP):
                tr.train_step()
        times: dict[str, list[float]] = {name: [] for name in VARIANTS}
        for _ in range(rounds):
            for name, tr in trainers.items():
                t = time.perf_counter()
                tr.train_step()
                times[name].append(time.perf_counter() - t)
        counts = {name: len(tr.model) for name, tr in trainers.items()}
        data = next(iter(trainers.values())).data
        shape = [data.width, data.height]
    med = {name: float(np.median(t)) * 1e3 for name, t in times.items()}
    return {"scene": scene, "size": shape, "gaussians": counts, "rounds": rounds, "threads": 1,
            "variants": VARIANTS, "ms_per_step": med, "ratio_to_mean_floor": {n: med[n] / med[BASE] for n in med},
            "ms_quartiles": {name: [float(np.percentile(t, q)) * 1e3 for q in (25, 75)] for name, t in times.items()}}


def plot(res: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(res["ms_per_step"])
    med = [res["ms_per_step"][n] for n in names]
    q = np.array([res["ms_quartiles"][n] for n in names])
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.bar(names, med, yerr=[np.subtract(med, q[:, 0]), q[:, 1] - med], capsize=3)
    ax.set_ylabel("ms per step (median, IQR)")
    ax.tick_params(axis="x", labelsize=8)
    w, h = res["size"]
    ax.set_title(f"blur + event step while densifying, {w}x{h}, {res['gaussians'][BASE]} Gaussians, 1 thread",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="a scene file with events (e.g. a make study-event-term cell)")
    ap.add_argument("--rounds", type=int, default=48, help="timed steps per variant (default %(default)s)")
    ap.add_argument("--init-points", type=int, default=5000, help="Gaussians (default %(default)s)")
    ap.add_argument("--json", type=Path, default=ROOT / "tools/results/bench_event_weighting.json")
    ap.add_argument("--plot", type=Path, default=ROOT / "tools/results/bench_event_weighting.png")
    a = ap.parse_args(argv)
    if a.rounds < 1 or a.init_points < 1:
        ap.error("--rounds and --init-points must be >= 1")
    res = measure(a.scene, a.rounds, a.init_points)
    save_json(a.json, res)
    plot(res, a.plot)
    for name, ms in res["ms_per_step"].items():
        print(f"{name:30s} {ms:7.1f} ms/step  x{res['ratio_to_mean_floor'][name]:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
