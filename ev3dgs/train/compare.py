"""naive vs blur-only vs blur+event on one scene: the comparison `make demo` prints and
tools/bench/bench_train.py records (PSNR on the sharp test views against training wall time)."""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from .config import TrainConfig
from .evaluate import evaluate
from .jobs import run_parallel
from .trainer import Trainer

VARIANTS = {
    "naive": dict(naive=True),
    "blur-only": dict(event_loss=False),
    "blur+event": dict(),
}


def compare_variants(scene: str | Path, out_dir: str | Path, base: TrainConfig | None = None,
                     eval_every: int = 0, quiet: bool = True, variants=tuple(VARIANTS), jobs: int = 1) -> dict:
    """Train each variant into out_dir/<variant>; returns {variant: {"metrics", "curve", "train_seconds"}}.
    `variants` names entries of VARIANTS, or is a dict {name: TrainConfig overrides}. With eval_every > 0 the
    test views are scored along the way; evaluation time is not counted in the curve's training seconds.
    jobs > 1: that many variants train at once, each in its own process with one thread (the same results,
    bitwise; train_seconds are then those of a one-thread run sharing the machine)."""
    base = base or TrainConfig(scene=str(scene))
    table = variants if isinstance(variants, dict) else {name: VARIANTS[name] for name in variants}
    items = [(name, replace(base, scene=str(scene), **overrides, **({"threads": 1} if jobs > 1 else {})),
              Path(out_dir) / name.replace(" ", "_").replace("/", "_"), eval_every, quiet)
             for name, overrides in table.items()]
    # the most expensive first (naive renders one pose per step, the others b+1), so the last job is short
    order = sorted(range(len(items)), key=lambda i: bool(items[i][1].naive)) if jobs > 1 else range(len(items))
    done = run_parallel(_train_variant, [items[i] for i in order], jobs)
    by_name = {r["name"]: r for r in done}
    return {name: {k: v for k, v in by_name[name].items() if k != "name"} for name in table}


def _train_variant(item) -> dict:
    name, cfg, run, eval_every, quiet = item
    trainer = Trainer(cfg, run, quiet=quiet)
    curve, clock = [], {"train": 0.0, "last": time.perf_counter()}

    def on_step(tr, rec):
        now = time.perf_counter()
        clock["train"] += now - clock["last"]
        if eval_every and (tr.step % eval_every == 0 or tr.step == tr.cfg.iterations):
            tr.save_model()
            m = evaluate(run, write_images=False)
            curve.append({"step": tr.step, "seconds": clock["train"], "gaussians": len(tr.model),
                          "test_psnr": m.get("test", {}).get("psnr"),
                          "train_sharp_psnr": m.get("train_sharp", {}).get("psnr")})
        clock["last"] = time.perf_counter()

    trainer.fit(on_step=on_step)
    return {"name": name, "metrics": evaluate(run), "curve": curve, "train_seconds": clock["train"],
            "iterations": cfg.iterations, "gaussians": len(trainer.model)}


def summary_table(results: dict) -> str:
    rows = [f"{'variant':12s} {'test PSNR':>10s} {'test SSIM':>10s} {'deblurred train PSNR':>21s} {'train s':>8s}"]
    for name, r in results.items():
        m = r["metrics"]
        rows.append(f"{name:12s} {m['test']['psnr']:10.2f} {m['test']['ssim']:10.4f} "
                    f"{m['train_sharp']['psnr']:21.2f} {r['train_seconds']:8.1f}")
    first = next(iter(results.values()))["metrics"]
    rows.append(f"{'blurry input':12s} {'':>10s} {'':>10s} {first['blurry_input']['psnr']:21.2f}")
    return "\n".join(rows)
