"""Training speed side by side with another checkout of ev3dgs (`bench_train.py --speed --against DIR`).

Each (code, threads) run is a fresh subprocess with PYTHONPATH set to that checkout, training the blur+event
variant on the same scene with the same seed and settings (init_points 5000, ``--iterations`` steps), then
scoring the sharp test views and the deblurred training views with that checkout's own evaluate(). The two
checkouts' runs of one thread count run at the same time (--concurrent, the default), so the load of a
shared machine, which changes from minute to minute, hits both alike; what counts is the ratio. Each run
reports wall ms/step (from the end of step 1 to the end of the last step, over the steps in between:
logging and checkpoints included; kernel loading, model setup, the final save and evaluation not) and CPU
ms/step (process CPU time over the same steps, all threads: less sensitive to other processes' load).

    git -C /path/to/repo archive 11158b9 | tar -x -C /tmp/base
    python tools/bench/bench_train.py --speed --against /tmp/base --scene demo_out/lego.h5 --iterations 500 \\
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

REPO = Path(__file__).resolve().parents[2]


def worker(scene: str, iterations: int, threads: int, seed: int, densify: bool = True) -> dict:
    """Runs inside the subprocess: train blur+event with whatever ev3dgs PYTHONPATH provides."""
    import ev3dgs
    from ev3dgs.train.config import TrainConfig
    from ev3dgs.train.evaluate import evaluate
    from ev3dgs.train.trainer import Trainer

    with tempfile.TemporaryDirectory() as d:
        cfg = TrainConfig(scene=scene, iterations=iterations, init_points=5000, seed=seed, threads=threads,
                          densify=densify)
        counts = []
        trainer = Trainer(cfg, Path(d) / "run", quiet=True)
        marks = {}

        def on_step(tr, rec):  # the clock starts after step 1 (kernel loading / JIT cache)
            marks.setdefault("first", (time.perf_counter(), time.process_time()))
            marks["last"] = (time.perf_counter(), time.process_time())
            counts.append(len(tr.model))

        t0 = time.perf_counter()
        trainer.fit(on_step=on_step)
        seconds = time.perf_counter() - t0
        steady = (marks["last"][0] - marks["first"][0]) / max(1, iterations - 1)
        cpu = (marks["last"][1] - marks["first"][1]) / max(1, iterations - 1)
        m = evaluate(Path(d) / "run", write_images=False)
    # the Gaussian count changes with densification: CPU ms per step per 1000 Gaussians (mean count over the
    # timed steps) compares runs whose models grew differently
    mean_gaussians = sum(counts[1:]) / max(1, len(counts) - 1)
    return {"code": str(Path(ev3dgs.__file__).parent.parent), "threads": threads, "seed": seed,
            "iterations": iterations, "fit_seconds": seconds, "ms_per_step": 1e3 * steady,
            "cpu_ms_per_step": 1e3 * cpu, "densify": densify, "mean_gaussians": mean_gaussians,
            "cpu_ms_per_step_per_1k": 1e6 * cpu / max(1.0, mean_gaussians),
            "test_psnr": m["test"]["psnr"], "train_sharp_psnr": m["train_sharp"]["psnr"],
            "gaussians": len(trainer.model)}


def run_speed(scene: str, against: str, iterations: int, threads: list[int], seed: int, repeats: int,
              concurrent: bool = True, densify: bool = True) -> dict:
    runs = []
    trees = (("new", str(REPO)), ("old", str(Path(against).resolve())))
    for th in threads:
        for _ in range(repeats):
            procs = []
            for tag, tree in trees:
                env = dict(os.environ, PYTHONPATH=tree, OMP_WAIT_POLICY="PASSIVE")
                cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", scene, str(iterations), str(th),
                       str(seed), str(int(densify))]
                proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                        cwd=tree)
                procs.append((tag, tree, proc))
                if not concurrent:
                    proc.wait()
            for tag, tree, proc in procs:
                out, err = proc.communicate()
                if proc.returncode != 0:
                    raise SystemExit(f"error: the {tag} run ({tree}, threads {th}) failed:\n{err[-2000:]}")
                rec = json.loads(out.strip().splitlines()[-1])
                rec["tag"] = tag
                rec["concurrent"] = concurrent
                runs.append(rec)
                print(f"{tag:3s} threads {th}: {rec['ms_per_step']:7.1f} ms/step wall, {rec['cpu_ms_per_step']:7.1f} "
                      f"CPU ({rec['cpu_ms_per_step_per_1k']:.2f} per 1000 Gaussians), test PSNR {rec['test_psnr']:.2f}, deblurred train PSNR {rec['train_sharp_psnr']:.2f}, "
                      f"{rec['gaussians']} Gaussians", flush=True)
    summary = {}
    for th in threads:
        pick = lambda tag, key: sorted(r[key] for r in runs if r["tag"] == tag and r["threads"] == th)  # noqa
        med = lambda v: v[len(v) // 2]  # noqa: E731
        summary[f"threads_{th}"] = {
            "speedup_wall": med(pick("old", "ms_per_step")) / med(pick("new", "ms_per_step")),
            "speedup_cpu": med(pick("old", "cpu_ms_per_step")) / med(pick("new", "cpu_ms_per_step")),
            "speedup_cpu_per_1k": (med(pick("old", "cpu_ms_per_step_per_1k"))
                                   / med(pick("new", "cpu_ms_per_step_per_1k"))),
            "test_psnr_new_minus_old": med(pick("new", "test_psnr")) - med(pick("old", "test_psnr"))}
        print(f"threads {th}: old/new {summary[f'threads_{th}']['speedup_wall']:.2f}x wall, "
              f"{summary[f'threads_{th}']['speedup_cpu']:.2f}x CPU time, "
              f"{summary[f'threads_{th}']['speedup_cpu_per_1k']:.2f}x CPU time per 1000 Gaussians", flush=True)
    return {"scene": scene, "against": str(against), "densify": densify,
            "variant": "blur+event, init_points 5000" + ("" if densify else ", no densification"),
            "iterations": iterations, "seed": seed, "runs": runs, "summary": summary}


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "--worker":
    _, _, scene_, it_, th_, seed_, dens_ = sys.argv
    print(json.dumps(worker(scene_, int(it_), int(th_), int(seed_), dens_ == "1")))
