"""How much should the events weigh? The noise norm (losses.noise_event_loss) with its model floor, its penalty
and the densification statistics changed, one at a time or together (the trainer's options):

* ``--floor median`` (--event-floor): the floor f from each step's median excess residual instead of the
  mean (the mean is set by the few pixel-pairs the model cannot render: floor_tail.py); ``--floor chi2``:
  the f at which the penalised chi-square averages what the noise model expects (losses.chi2_floor);
* ``--huber C`` (--event-huber): each pixel-pair's normalised residual x = r^2 / (v + f g) penalised as x
  within C standard deviations and 2 C sqrt(x) - C^2 beyond, so that a pixel-pair the model cannot fit
  pulls as |r|, not r^2; 0 = off;
* ``--densify blur`` (--densify-from): the densification statistics from the blur term's gradient alone
  (one more backward pass through the blur loss per step), so that the event term's weight does not decide
  how many Gaussians are split;
* ``--event-mismatch S`` (the trainer's option of that name): the noise model's relative threshold spread
  instead of the scene file's, e.g. a change-proportional term where the scene has no mismatch.

Cells are heldout_shake's (study_event_term's cache, ``t0.05_m0.1``: threshold 0.05, 10 % mismatch) or
built-in scenes (bench_fidelity's cache, 24 + 8 views at 96x72); each run is scored on its file's blur and
novel views, the defaults of both tools otherwise (the heldout cells at ``--sh-interval 33``, the default
schedule at 1000 steps).

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

from ev3dgs.train.config import DENSIFY_FROM, FLOOR_STATS  # noqa: E402
from ev3dgs.train.jobs import run_parallel  # noqa: E402


def _run(job: dict) -> dict:
    import torch

    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.evaluate import evaluate
    from ev3dgs.train.trainer import Trainer

    torch.set_num_threads(1)
    out = Path(job["out"])
    cfg = TrainConfig(scene=job["path"], iterations=job["iterations"], init_points=5000, seed=job["seed"],
                      checkpoint_every=job["iterations"], threads=1, event_floor=job["floor"],
                      event_huber=job["huber"], densify_from=job["densify"], **job["overrides"])
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
    ap.add_argument("--floor", choices=FLOOR_STATS, default="mean")
    ap.add_argument("--huber", type=float, default=0.0, help="C in standard deviations; 0 = off (default)")
    ap.add_argument("--densify", choices=DENSIFY_FROM, default="all")
    ap.add_argument("--event-mismatch", type=float, default=None,
                    help="the noise norm's relative threshold spread (default: each scene file's own)")
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--event-term-cache", type=Path, default=ROOT / "tools/results/event_term_cache")
    ap.add_argument("--fidelity-cache", type=Path, default=ROOT / "tools/results/fidelity_cache")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", type=Path, required=True)
    a = ap.parse_args(argv)
    if not (a.huber >= 0 and math.isfinite(a.huber)):
        ap.error("--huber must be >= 0")
    if a.event_mismatch is not None and not 0 <= a.event_mismatch <= 1:
        ap.error("--event-mismatch must be in [0, 1]")
    tag = f"ew_{a.floor}_h{a.huber:g}_{a.densify}" + ("" if a.event_mismatch is None else f"_em{a.event_mismatch:g}")
    mismatch = {} if a.event_mismatch is None else {"event_mismatch": a.event_mismatch}
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
            jobs.append({"cell": cell, "seed": seed, "path": str(path), "overrides": {**overrides, **mismatch},
                         "out": str(out),
                         "iterations": a.iterations, "floor": a.floor, "huber": a.huber, "densify": a.densify})
    runs = run_parallel(_run, jobs, a.jobs, lambda r: print(json.dumps(r), flush=True) or r)
    a.json.parent.mkdir(parents=True, exist_ok=True)
    settings = {"cells": a.cells, "seeds": a.seeds, "floor": a.floor, "huber": a.huber, "densify": a.densify,
                "event_mismatch": a.event_mismatch, "iterations": a.iterations}
    a.json.write_text(json.dumps({"settings": settings, "runs": runs}, indent=2))
    print(f"-> {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
