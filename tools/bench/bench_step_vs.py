"""The blur+event training step of bench_train_scaling.make_step, this tree against another ev3dgs tree (e.g. the
main branch), alternating in one run: `--baseline DIR` names the other tree's root (a `git worktree add` or a
`git archive | tar -x` of it).

For every (size, Gaussian count) two worker processes start, one per tree (PYTHONPATH set to it), each builds
the step from its own tools/bench/bench_train_scaling.py (same seeds: the same model, poses and targets),
runs one warm-up step, then steps on command: the driver asks baseline and new in turn, `--repeats` times, so
that the machine's load hits both alike. Each step is timed in the worker in CPU time (process_time: torch
and numba on one thread each, so it is the step's own work, less sensitive to other jobs' load than wall
time) and wall time. Reported per case: median ms of each, and the ratio baseline / new per round with
min / median / max. After the timed steps each worker hashes its model's parameters: equal hashes mean
the two trees trained bitwise the same model (the change did not alter any result).

    python tools/bench/bench_step_vs.py --baseline ../main-snapshot \\
        --json tools/results/bench_step_vs.json --plot tools/results/bench_step_vs.png
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parents[1]
ROOT = TOOLS.parent
sys.path.insert(0, str(TOOLS))  # pareto.py

SIZES = [(96, 72), (173, 130), (346, 260)]
COUNTS = [10_000, 50_000, 100_000]

# runs inside a worker, with the tree's root as cwd and on PYTHONPATH: a workload's set-up (defining work()
# and digest()) between the common head and the common loop
WORKER_HEAD = r"""
import hashlib, sys, time
sys.path.insert(0, "tools/bench")
n, w, h = (int(v) for v in sys.argv[1:4])
"""
WORKER_LOOP = r"""
work()
print("ready", flush=True)
for line in sys.stdin:
    if line.strip() == "step":
        t0, c0 = time.perf_counter(), time.process_time()
        work()
        print(f"{1e3 * (time.process_time() - c0)} {1e3 * (time.perf_counter() - t0)}", flush=True)
    else:
        print(digest(), flush=True)
        break
"""
# the blur+event training step; the hash is the model's parameters
STEP = r"""
from bench_train_scaling import make_step
step = make_step(n, w, h)
model = next(c.cell_contents for c in step.__closure__ if hasattr(c.cell_contents, "params"))
def work():
    step(1)
def digest():
    hsh = hashlib.sha256()
    for name in sorted(model.params):
        hsh.update(model.params[name].detach().numpy().tobytes())
    return hsh.hexdigest()
"""
# --raster: the rasterizer's forward + backward of tools/bench/bench_raster.py (projection, binning, kernels,
# gradients) on its random cloud, instead of the training step; the hash is the last call's image
RASTER = r"""
from bench_raster import cloud, run
params, viewmat, K = cloud(n, w)
last = []
def work():
    last[:] = [run("cpu", params, viewmat, K, w, 1, h)]
def digest():
    return hashlib.sha256(last[0].numpy().tobytes()).hexdigest()
"""
WORKER = WORKER_HEAD + STEP + WORKER_LOOP
WORKER_RASTER = WORKER_HEAD + RASTER + WORKER_LOOP


def _start(tree: Path, n: int, w: int, h: int, worker: str = WORKER) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1")
    p = subprocess.Popen([sys.executable, "-c", worker, str(n), str(w), str(h)], cwd=tree, env=env,
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    line = p.stdout.readline()
    if line.strip() != "ready":
        p.kill()
        raise RuntimeError(f"worker in {tree} did not start (exit {p.wait()})")
    return p


def _ask(p: subprocess.Popen, cmd: str) -> str:
    p.stdin.write(cmd + "\n")
    p.stdin.flush()
    return p.stdout.readline().strip()


def case(baseline: Path, n: int, w: int, h: int, repeats: int, worker: str = WORKER) -> dict:
    procs = {"baseline": _start(baseline, n, w, h, worker), "new": _start(ROOT, n, w, h, worker)}
    times = {"baseline": [], "new": []}
    try:
        for r in range(repeats):
            for name in (("baseline", "new") if r % 2 == 0 else ("new", "baseline")):
                cpu_ms, wall_ms = (float(v) for v in _ask(procs[name], "step").split())
                times[name].append((cpu_ms, wall_ms))
        hashes = {name: _ask(p, "hash") for name, p in procs.items()}
    finally:
        for p in procs.values():
            p.stdin.close()
            p.wait()
    out = {"width": w, "height": h, "gaussians": n, "repeats": repeats,
           "same_model_after_steps": hashes["baseline"] == hashes["new"]}
    for i, kind in enumerate(("cpu", "wall")):
        base = [t[i] for t in times["baseline"]]
        new = [t[i] for t in times["new"]]
        ratios = [b / m for b, m in zip(base, new)]
        out[kind] = {"baseline_ms": statistics.median(base), "new_ms": statistics.median(new),
                     "ratio": {"min": min(ratios), "median": statistics.median(ratios), "max": max(ratios)},
                     "baseline_all_ms": base, "new_all_ms": new}
    return out


def plot(out: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = out["cases"]
    fig, ax = plt.subplots(figsize=(7, 3.4))
    x = range(len(rows))
    med = [r["cpu"]["ratio"]["median"] for r in rows]
    lo = [m - r["cpu"]["ratio"]["min"] for m, r in zip(med, rows)]
    hi = [r["cpu"]["ratio"]["max"] - m for m, r in zip(med, rows)]
    ax.errorbar(x, med, yerr=[lo, hi], fmt="o", capsize=3)
    ax.axhline(1.0, color="gray", lw=0.8)
    ax.set_xticks(list(x))
    ax.set_xticklabels([f"{r['width']}x{r['height']}\n{r['gaussians'] // 1000}k" for r in rows], fontsize=7)
    ax.set_ylabel("baseline / new CPU time per step")
    ax.set_title("blur+event step, one thread: speed-up over the baseline tree (min / median / max)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    from pareto import save_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", required=True, help="root of the other ev3dgs tree")
    ap.add_argument("--label", default=None, help="what the baseline is, for the JSON (default: its folder's name)")
    ap.add_argument("--repeats", type=int, default=6)
    ap.add_argument("--quick", action="store_true", help="96x72 and 173x130 with 10k Gaussians only")
    ap.add_argument("--raster", action="store_true",
                    help="the rasterizer's forward + backward on bench_raster's 10k cloud at 200x200 instead of the step")
    ap.add_argument("--case", default=None, metavar="WxH:N",
                    help="one step case only, e.g. 346x260:50000 (default: every size and Gaussian count)")
    ap.add_argument("--json", default="tools/results/bench_step_vs.json")
    ap.add_argument("--plot", default="tools/results/bench_step_vs.png")
    args = ap.parse_args(argv)
    baseline = Path(args.baseline).resolve()
    if not all((baseline / f).is_file() for f in ("ev3dgs/__init__.py", "tools/bench/bench_train_scaling.py")):
        print(f"error: {args.baseline} is not an ev3dgs tree (no ev3dgs/ or tools/bench/bench_train_scaling.py)",
              file=sys.stderr)
        return 2
    if args.repeats < 1:
        print("error: --repeats must be at least 1", file=sys.stderr)
        return 2
    sizes, counts = (SIZES[:2], COUNTS[:1]) if args.quick else (SIZES, COUNTS)
    cases = [(n, w, h) for (w, h) in sizes for n in counts]
    if args.case:
        try:
            size, n = args.case.split(":")
            w, h = (int(v) for v in size.lower().split("x"))
            cases = [(int(n), w, h)]
        except ValueError:
            print(f"error: --case must look like 346x260:50000, got {args.case!r}", file=sys.stderr)
            return 2
        if min(cases[0]) < 1:
            print(f"error: --case needs a positive size and Gaussian count, got {args.case!r}", file=sys.stderr)
            return 2
    if args.raster:
        cases = [(10_000, 200, 200)]
    rows = []
    for n, w, h in cases:
        r = case(baseline, n, w, h, args.repeats, WORKER_RASTER if args.raster else WORKER)
        rows.append(r)
        c = r["cpu"]
        print(f"{w}x{h} {n // 1000}k: baseline {c['baseline_ms']:.0f} ms, new {c['new_ms']:.0f} ms CPU; ratio "
              f"{c['ratio']['median']:.2f} ({c['ratio']['min']:.2f}-{c['ratio']['max']:.2f}); "
              f"same model: {r['same_model_after_steps']}", flush=True)
    out = {"baseline": args.label or baseline.name, "threads": 1, "cases": rows,
           "workload": "rasterizer forward + backward" if args.raster else "blur+event training step"}
    save_json(args.json, out, ", torch and numba on 1 thread")
    plot(out, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
