"""What the event term's weighting costs per step: the blur + event step on one scene file with the defaults
(the chi-square floor with the Huber penalty, densification statistics from the blur term: ``--event-floor chi2
--event-huber 3 --densify-from blur``, one more backward pass through the blur term while the strategy
densifies), the same from the whole loss (``--densify-from all``) and the mean floor without a penalty
(``--event-floor mean --event-huber 0 --densify-from all``), one thread.

The steps are those of a 30 000-step run's first few hundred: densification statistics are gathered every
step (the extra backward pass runs), no Gaussian is split or pruned yet, so every variant renders the same
number of Gaussians. The variants' steps are interleaved round by round, so a busy machine slows them alike;
the result is each variant's median ms per step and its ratio to the default's (measured as
tools/bench/bench_train_options.py does). JSON + PNG.

    python tools/bench/bench_event_weighting.py --scene tools/results/event_term_cache/t0.05_m0.1/scene.h5 \\
        [--rounds 48] [--init-points 5000] [--json tools/results/bench_event_weighting.json]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT / "tools" / "bench"))

from bench_train_options import WARMUP, measure, plot  # noqa: E402
from pareto import save_json  # noqa: E402

VARIANTS = {"default": {}, "densify from all": dict(densify_from="all"),
            "mean floor, no Huber": dict(event_floor="mean", event_huber=0.0, densify_from="all")}
ITERATIONS = 30_000   # the schedule of a full-length run: densification from step 500, statistics from step 0


def _no_split(rounds: int):
    def check(trainers):
        start = next(iter(trainers.values())).strategy.refine_start
        if WARMUP + rounds >= start:
            raise SystemExit(f"--rounds must stay below {start - WARMUP}: no Gaussian may be split yet")
    return check


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
    res = measure(a.scene, a.rounds, a.init_points, VARIANTS, _no_split(a.rounds), densify=True,
                  iterations=ITERATIONS)
    res["variants"] = VARIANTS
    save_json(a.json, res)
    plot(res, a.plot, "blur + event step while densifying")
    for name, ms in res["ms_per_step"].items():
        print(f"{name:22s} {ms:7.1f} ms/step  x{res['ratio_to_default'][name]:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
