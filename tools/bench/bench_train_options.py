"""What the trainer's fidelity options cost per step: the blur + event step on one scene file with the defaults,
``--hdr``, the SH degree at 3 (``--sh-interval 1``: degree 3 from the fourth step), both, and the EDI prior
(``--edi-prior``, kept on through the timed steps), 17 sub-poses per exposure instead of 5, and each view's
count from its motion (``--subpose-px 2``, up to 17), and a learned camera response (``--learn-response``), one
thread.
The variants' steps are interleaved round by round, so a busy machine slows them alike; the result is each
variant's median ms per step and its ratio to the default's, and the mean (with ``--subpose-px`` a step's cost
depends on its view: the mean over many visits of every view is what a run pays; every variant visits the
views in the same order). Densification is off so every variant renders
the same number of Gaussians. JSON + PNG.

    python tools/bench/bench_train_options.py --scene tools/results/event_term_cache/t0.05_m0.1/scene.h5 \\
        [--rounds 40] [--init-points 5000] [--json tools/results/bench_train_options.json]
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

VARIANTS = {"default": {}, "--hdr": {"hdr": True}, "SH degree 3": {"sh_interval": 1},
            "--hdr, SH degree 3": {"hdr": True, "sh_interval": 1},
            "--edi-prior": {"edi_prior": 8 / 625, "edi_anneal": 1.0},
            "17 sub-poses": {"subposes": 17}, "--subpose-px 2": {"subposes": 17, "subpose_px": 2.0},
            "--learn-response": {"learn_response": True}}
WARMUP = 5   # steps before timing: the SH degree reaches 3 at the fourth step with --sh-interval 1


def measure(scene: str, rounds: int, init_points: int, variants: dict | None = None, check=None,
            **settings) -> dict:
    """Median (and mean) ms per step of each of ``variants`` (default VARIANTS; one named "default" is the
    ratios' base), steps interleaved round by round; ``settings``: TrainConfig values every variant shares
    (default: densification off); ``check(trainers)``: called before the first step, may refuse."""
    import torch

    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.trainer import Trainer

    variants = VARIANTS if variants is None else variants
    settings = {"densify": False, **settings}
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        trainers = {name: Trainer(TrainConfig(scene=scene, init_points=init_points, threads=1, seed=0,
                                              **settings, **over), Path(tmp) / str(i), quiet=True)
                    for i, (name, over) in enumerate(variants.items())}
        if check is not None:
            check(trainers)
        for tr in trainers.values():
            for _ in range(WARMUP):
                tr.train_step()
        times: dict[str, list[float]] = {name: [] for name in variants}
        for _ in range(rounds):
            for name, tr in trainers.items():
                t = time.perf_counter()
                tr.train_step()
                times[name].append(time.perf_counter() - t)
        degrees = {name: tr.model.active_sh_degree for name, tr in trainers.items()}
        size = next(iter(trainers.values())).data
        shape = [size.width, size.height]
    med = {name: float(np.median(t)) * 1e3 for name, t in times.items()}
    mean = {name: float(np.mean(t)) * 1e3 for name, t in times.items()}
    return {"scene": scene, "size": shape, "gaussians": init_points, "rounds": rounds, "threads": 1,
            "sh_degree": degrees, "ms_per_step": med,
            "ratio_to_default": {name: med[name] / med["default"] for name in med},
            "ms_mean": mean, "mean_ratio_to_default": {name: mean[name] / mean["default"] for name in mean},
            "ms_quartiles": {name: [float(np.percentile(t, q)) * 1e3 for q in (25, 75)] for name, t in times.items()}}


def plot(res: dict, png: Path, title: str = "blur + event step") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(res["ms_per_step"])
    med = [res["ms_per_step"][n] for n in names]
    q = np.array([res["ms_quartiles"][n] for n in names])
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.bar(names, med, yerr=[np.subtract(med, q[:, 0]), q[:, 1] - med], capsize=3)
    ax.set_ylabel("ms per step (median, IQR)")
    w, h = res["size"]
    ax.set_title(f"{title}, {w}x{h}, {res['gaussians']} Gaussians, 1 thread", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="a scene file with events (e.g. a make study-event-term cell)")
    ap.add_argument("--rounds", type=int, default=48, help="timed steps per variant (default %(default)s)")
    ap.add_argument("--init-points", type=int, default=5000, help="Gaussians (default %(default)s)")
    ap.add_argument("--json", type=Path, default=ROOT / "tools/results/bench_train_options.json")
    ap.add_argument("--plot", type=Path, default=ROOT / "tools/results/bench_train_options.png")
    a = ap.parse_args(argv)
    if a.rounds < 1 or a.init_points < 1:
        ap.error("--rounds and --init-points must be >= 1")
    res = measure(a.scene, a.rounds, a.init_points)
    save_json(a.json, res)
    plot(res, a.plot)
    for name, ms in res["ms_per_step"].items():
        print(f"{name:20s} {ms:7.1f} ms/step  x{res['ratio_to_default'][name]:.3f}  "
              f"(mean {res['ms_mean'][name]:.1f}, x{res['mean_ratio_to_default'][name]:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
