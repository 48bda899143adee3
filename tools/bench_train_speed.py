"""Training speed side by side with another checkout of ev3dgs (`bench_train.py --speed --against DIR`).

Each (code, threads) run is a fresh subprocess with PYTHONPATH set to that checkout, training the blur+event
variant on the same scene with the same seed and settings (init_points 5000, ``--iterations`` steps), then
scoring the sharp test views and the deblurred training views with that checkout's own evaluate(). Runs
alternate between the checkouts (new, old, new, old, ... per thread count) so that a change in the load of a
shared machine hits both about equally; what counts is the ratio. ms/step is the wall time from the end of
step 1 to the end of the last step over the steps in between (logging and checkpoints included; kernel
loading, model setup, the final save and evaluation not).

    git -C /path/to/repo archive 11158b9 | tar -x -C /tmp/base
    python tools/bench_train.py --speed --against /tmp/base --scene demo_out/lego.h5 --iterations 500 \\
        --threads 1 2 --json tools/results/bench_train_speed.json
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def worker(scene: str, iterations: int, threads: int, seed: int) -> dict:
    """Runs inside the subprocess: train blur+event with whatever ev3dgs PYTHONPATH provides."""
    import ev3dgs
    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.evaluate import evaluate
    from ev3dgs.train.trainer import Trainer

    with tempfile.TemporaryDirectory() as d:
        cfg = TrainConfig(scene=scene, iterations=iterations, init_points=5000, seed=seed, threads=threads)
        trainer = Trainer(cfg, Path(d) / "run", quiet=True)
        marks = {}

        def on_step(tr, rec):  # the clock starts after step 1 (kernel loading / JIT cache)
            marks.setdefault("first", time.perf_counter())
            marks["last"] = time.perf_counter()

        t0 = time.perf_counter()
        trainer.fit(on_step=on_step)
        seconds = time.perf_counter() - t0
        steady = (marks["last"] - marks["first"]) / max(1, iterations - 1)
        m = evaluate(Path(d) / "run", write_images=False)
    return {"code": str(Path(ev3dgs.__file__).parent.parent), "threads": threads, "seed": seed,
            "iterations": iterations, "fit_seconds": seconds, "ms_per_step": 1e3 * steady,
            "test_psnr": m["test"]["psnr"], "train_sharp_psnr": m["train_sharp"]["psnr"],
            "gaussians": len(trainer.model)}


def run_speed(scene: str, against: str, iterations: int, threads: list[int], seed: int, repeats: int) -> dict:
    runs = []
    for th in threads:
        for _ in range(repeats):
            for tag, tree in (("new", str(REPO)), ("old", str(Path(against).resolve()))):
                env = dict(os.environ, PYTHONPATH=tree, OMP_WAIT_POLICY="PASSIVE")
                cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", scene, str(iterations), str(th),
                       str(seed)]
                out = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tree)
                if out.returncode != 0:
                    raise SystemExit(f"error: the {tag} run ({tree}, threads {th}) failed:\n{out.stderr[-2000:]}")
                rec = json.loads(out.stdout.strip().splitlines()[-1])
                rec["tag"] = tag
                runs.append(rec)
                print(f"{tag:3s} threads {th}: {rec['ms_per_step']:7.1f} ms/step, test PSNR {rec['test_psnr']:.2f}, "
                      f"deblurred train PSNR {rec['train_sharp_psnr']:.2f}, {rec['gaussians']} Gaussians", flush=True)
    summary = {}
    for th in threads:
        new = [r["ms_per_step"] for r in runs if r["tag"] == "new" and r["threads"] == th]
        old = [r["ms_per_step"] for r in runs if r["tag"] == "old" and r["threads"] == th]
        summary[f"threads_{th}"] = {"speedup_per_pair": [o / n for o, n in zip(old, new)],
                                    "speedup_median_ms": sorted(old)[len(old) // 2] / sorted(new)[len(new) // 2]}
    return {"scene": scene, "against": str(against), "variant": "blur+event, init_points 5000",
            "iterations": iterations, "seed": seed, "runs": runs, "summary": summary}


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "--worker":
    _, _, scene_, it_, th_, seed_ = sys.argv
    print(json.dumps(worker(scene_, int(it_), int(th_), int(seed_))))
