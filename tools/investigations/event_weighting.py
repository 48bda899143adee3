"""How much should the events weigh? The noise norm (losses.noise_event_loss) with its model floor, its penalty
and the densification statistics changed, one at a time or together, without touching the trainer.

* ``--floor median``: the floor f from each step's median excess residual instead of the mean (the mean is
  set by the few pixel-pairs the model cannot render: floor_tail.py);
* ``--huber C``: each pixel-pair's normalised residual x = r^2 / (v + f g) penalised as x within C standard
  deviations and 2 C sqrt(x) - C^2 beyond (continuous, with a continuous slope), so that a pixel-pair the
  model cannot fit pulls as |r|, not r^2; 0 = off;
* ``--densify blur``: the densification statistics from the blur term's gradient alone (one more backward
  pass through the blur loss per step), so that the event term's weight does not decide how many Gaussians
  are split.

Cells are heldout_shake's (study_event_term's cache, ``t0.05_m0.1``: threshold 0.05, 10 % mismatch) or
built-in scenes (bench_fidelity's cache, 24 + 8 views at 96x72); each run is scored on its file's blur and
novel views, the defaults of both tools otherwise (the heldout cells at ``--sh-interval 33``, the default
schedule at 1000 steps). With the defaults (mean, no Huber, all) it is the default trainer, bit for bit.

    python tools/investigations/event_weighting.py --cells t0.05_m0.1 t0.1_m0 lego lowlight --seeds 0 \
        --floor median --huber 3 --densify blur --json tools/results/event_weighting_all.json
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from ev3dgs.train.jobs import run_parallel  # noqa: E402


def huber(x, c: float):
    """x (a normalised squared residual, >= 0) within c^2, 2 c sqrt(x) - c^2 beyond; c <= 0: x."""
    import torch

    if c <= 0:
        return x
    c2 = c * c
    return torch.where(x <= c2, x, 2 * c * torch.sqrt(x.clamp(min=c2)) - c2)


_ORIGINAL: dict = {}


def _patch(floor_stat: str, c: float, blur_densify: bool) -> None:
    """Replace the trainer's event loss and wrap its blur loss and the densification strategy (in this
    process: a pool worker)."""
    import torch

    import ev3dgs.splat.strategy as strategy
    import ev3dgs.train.losses as losses
    import ev3dgs.train.trainer as trainer

    hold = {"infos": [], "grads": None}

    def event_loss(log_l, counts, pairs, theta_pos, theta_neg, convention="random_phase", rel_mismatch=0.1,
                   noise_events=None, floor=None, knee=losses.DEFAULT_LOG_KNEE, spread=None):
        tp, tn = losses._thetas(theta_pos, theta_neg, log_l)
        residual, v, g = losses.noise_terms(log_l, counts, pairs, tp, tn, convention, rel_mismatch, noise_events,
                                            knee, spread)
        with torch.no_grad():
            excess = (residual * residual - v) / g
            estimate = float(excess.median() if floor_stat == "median" else excess.mean())
        if floor is None:
            floor = max(estimate, losses.FLOOR_MIN) if math.isfinite(estimate) else losses.FLOOR_MIN
        return torch.mean(huber(residual * residual / (v + floor * g), c)), estimate

    if not _ORIGINAL:   # a pool worker's later job wraps the originals again, not its earlier wrappers
        _ORIGINAL.update(blur=trainer.average_loss, pre=strategy.DefaultStrategy.step_pre_backward,
                         post=strategy.DefaultStrategy.step_post_backward)
    blur_loss, pre, post = _ORIGINAL["blur"], _ORIGINAL["pre"], _ORIGINAL["post"]

    def step_pre_backward(self, info):
        hold["infos"].append(info)
        return pre(self, info)

    def average_loss(*args, **kwargs):   # the blur term; with --densify blur its gradient at the renders' means
        out = blur_loss(*args, **kwargs)
        if blur_densify:
            hold["grads"] = torch.autograd.grad(out, [i["means2d"] for i in hold["infos"]], retain_graph=True,
                                                allow_unused=True)
        return out

    def step_post_backward(self, model, optimizers, state, step, infos):
        if hold["grads"] is not None:
            for info, grad in zip(hold["infos"], hold["grads"]):
                info["means2d"].grad = grad
        hold["infos"], hold["grads"] = [], None
        return post(self, model, optimizers, state, step, infos)

    trainer.noise_event_loss, trainer.average_loss = event_loss, average_loss
    strategy.DefaultStrategy.step_pre_backward = step_pre_backward
    strategy.DefaultStrategy.step_post_backward = step_post_backward


def _run(job: dict) -> dict:
    import torch

    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.evaluate import evaluate
    from ev3dgs.train.trainer import Trainer

    torch.set_num_threads(1)
    _patch(job["floor"], job["huber"], job["densify"] == "blur")
    out = Path(job["out"])
    cfg = TrainConfig(scene=job["path"], iterations=job["iterations"], init_points=5000, seed=job["seed"],
                      checkpoint_every=job["iterations"], threads=1, **job["overrides"])
    t = time.perf_counter()
    Trainer(cfg, out, quiet=True).fit()
    m = evaluate(out, write_images=False)
    last = json.loads((out / "log.jsonl").read_text().splitlines()[-1])
    return {"cell": job["cell"], "seed": job["seed"], "train_seconds": time.perf_counter() - t,
            "gaussians": last["gaussians"], **{v: m[v]["psnr"] for v in ("blur_view", "novel_view")}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", nargs="+", required=True,
                    help="heldout_shake cells (t<threshold>_m<relative mismatch>) or built-in scene names")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--floor", choices=("mean", "median"), default="mean")
    ap.add_argument("--huber", type=float, default=0.0, help="C in standard deviations; 0 = off (default)")
    ap.add_argument("--densify", choices=("all", "blur"), default="all")
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--event-term-cache", type=Path, default=ROOT / "tools/results/event_term_cache")
    ap.add_argument("--fidelity-cache", type=Path, default=ROOT / "tools/results/fidelity_cache")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", type=Path, required=True)
    a = ap.parse_args(argv)
    if not (a.huber >= 0 and math.isfinite(a.huber)):
        ap.error("--huber must be >= 0")
    tag = f"ew_{a.floor}_h{a.huber:g}_{a.densify}"
    jobs = []
    for seed in a.seeds:
        for cell in a.cells:
            if cell.startswith("t") and "_m" in cell:
                path, overrides = a.event_term_cache / cell / "scene.h5", {"sh_interval": 33}
                out = a.event_term_cache / "runs" / f"{cell}_{tag}_s{seed}"
            else:
                path, overrides = a.fidelity_cache / f"{cell}_96x72_v24t8s17p16.h5", {}
                out = a.fidelity_cache / "runs" / path.stem / f"{tag}_s{seed}"
            if not path.exists():
                ap.error(f"{path} is missing: make it with study_event_term.py or bench_fidelity.py")
            jobs.append({"cell": cell, "seed": seed, "path": str(path), "overrides": overrides, "out": str(out),
                         "iterations": a.iterations, "floor": a.floor, "huber": a.huber, "densify": a.densify})
    runs = run_parallel(_run, jobs, a.jobs, lambda r: print(json.dumps(r), flush=True) or r)
    a.json.parent.mkdir(parents=True, exist_ok=True)
    settings = {"cells": a.cells, "seeds": a.seeds, "floor": a.floor, "huber": a.huber, "densify": a.densify,
                "iterations": a.iterations}
    a.json.write_text(json.dumps({"settings": settings, "runs": runs}, indent=2))
    print(f"-> {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
