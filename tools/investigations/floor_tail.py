"""How the noise norm's model floor is made up: the excess of each pixel-pair's squared event residual over its
count noise, (r^2 - v) / g (losses.noise_event_loss), in trained runs.

The floor f is the mean of that excess over pairs and pixels. For each run folder given, a copy of the run
is resumed for ``--steps`` more steps (one per view, in the trainer's order) and every step's excess is
summarised: its mean (the step's floor estimate), its median, and the share of the positive excess held by
the top 1 % and 5 % of pixel-pairs. Printed per run as the median over the steps; ``--json`` writes them.
The runs themselves are not touched.

    python tools/investigations/floor_tail.py tools/results/event_term_cache/runs/t0.05_m0.1_blur+event-sh_s0 \
        tools/results/event_term_cache/runs/t0.4_m0.1_blur+event-sh_s0 \
        tools/results/event_term_cache/runs/t0.05_m0.4_blur+event-sh_s0 --json tools/results/floor_tail.json
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def tail_summary(excess) -> dict:
    """Mean, median and the top 1 % / 5 % share of the positive part of a 1-d tensor of excess values."""
    x = excess.flatten().double()
    pos = x.clamp(min=0).sort(descending=True).values
    total = float(pos.sum())
    share = (lambda k: float(pos[:k].sum()) / total if total > 0 else 0.0)
    return {"mean": float(x.mean()), "median": float(x.median()),
            "top1": share(len(pos) // 100), "top5": share(len(pos) // 20)}


def measure(run: Path, steps: int) -> dict:
    """The median over ``steps`` resumed steps of each summary value, for a copy of ``run``."""
    import torch

    import ev3dgs.train.losses as losses
    import ev3dgs.train.terms.events as events_term
    import ev3dgs.train.trainer as trainer_module
    from ev3dgs.train.config import TrainConfig

    seen = []
    real = events_term.noise_event_loss   # the event term's call (train/terms/events.py)

    def spy(log_l, counts, pairs, theta_pos, theta_neg, convention, rel, noise, floor, knee, spread=None, *rest):
        with torch.no_grad():   # rest: the floor statistic and penalty, passed on as the trainer gave them
            tp, tn = losses._thetas(theta_pos, theta_neg, log_l)
            r, v, g = losses.noise_terms(log_l.detach(), counts, pairs, tp, tn, convention, rel, noise, knee, spread)
            seen.append(tail_summary((r * r - v) / g))
        return real(log_l, counts, pairs, theta_pos, theta_neg, convention, rel, noise, floor, knee, spread, *rest)

    events_term.noise_event_loss = spy
    try:
        with tempfile.TemporaryDirectory() as tmp:
            copy = Path(tmp) / run.name
            shutil.copytree(run, copy)
            cfg = TrainConfig.load(copy / "config.json")
            done = json.loads((copy / "log.jsonl").read_text().splitlines()[-1])["step"]
            trainer_module.Trainer(replace(cfg, iterations=done + steps, schedule_length=cfg.schedule_iterations),
                                   copy, quiet=True).fit(resume=True)   # more steps on the run's schedules
    finally:
        events_term.noise_event_loss = real
    return {k: sorted(s[k] for s in seen)[len(seen) // 2] for k in seen[0]} | {"steps": len(seen)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="training run folders with the noise norm")
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    out = {}
    for run in a.runs:
        out[run.name] = m = measure(run, a.steps)
        print(run.name, json.dumps({k: round(v, 6) for k, v in m.items()}), flush=True)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
