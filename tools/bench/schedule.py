"""Load balance of the `cpu` rasterizer's tile schedule for 1-16 threads, from measured per-tile times.

    python tools/bench/schedule.py [--repeats 5] [--json tools/results/schedule.json] [--plot ...]

The C kernels (ev3dgs/splat/cpu_simd.py) record every tile's thread CPU time (forward and backward, one
thread, median over --repeats runs per tile); the schedule the kernels use (tiles sorted by their (tile,
Gaussian) list length, most first, dealt round robin: thread t runs tiles t, t + n, ...) is then simulated
on those times for n threads: efficiency = total / (n * the most loaded thread's time), i.e. the best
T1 / (n Tn) the schedule allows when threads do not slow each other down (memory bandwidth, shared caches
and SMT are not modelled). Two schedules over the same list: the numba kernels' round-robin deal and the C
kernels' shared work queue (a free thread takes the next tile: each tile goes to the least loaded thread);
for comparison the round robin ordered by the measured times, and the greedy longest-first schedule on
the measured times (the best a list schedule can do knowing them).
Workloads: the 10k @ 200x200 cloud of bench_raster.py and one camera of the 346x260 blur+event step's scene
with 50k Gaussians.
"""
from __future__ import annotations

import argparse
import heapq
import os
import statistics
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_raster import cloud, run, step_scene  # noqa: E402
from pareto import save_json  # noqa: E402

THREADS = (1, 2, 3, 4, 6, 8, 12, 16)


def round_robin(cost, order, n):
    loads = np.zeros(n)
    for i, t in enumerate(order):
        loads[i % n] += cost[t]
    return float(cost.sum() / (n * loads.max())) if loads.max() > 0 else 1.0


def greedy(cost, n, order=None):
    """Each tile, in ``order`` (default: by cost, most first), to the least loaded thread: what threads taking
    the next tile of a shared work list when they are free do (the C kernels' schedule, ordered by list
    length)."""
    heap = [(0.0, i) for i in range(n)]
    for c in (sorted(cost, reverse=True) if order is None else cost[order]):
        load, i = heapq.heappop(heap)
        heapq.heappush(heap, (load + c, i))
    top = max(load for load, _ in heap)
    return float(cost.sum() / (n * top)) if top > 0 else 1.0


def tile_times(params, vm, K, w, h, repeats):
    """Per tile: (list length, median forward + backward thread CPU time in s) of the C kernels, one thread."""
    import ev3dgs.splat.cpu as cpu
    import ev3dgs.splat.cpu_simd as cs

    lengths = {}
    real = cpu._work_order

    def spy(offsets):
        lengths["n"] = np.diff(offsets)
        return real(offsets)

    cpu._work_order = spy
    cs.TILE_TIMES = []
    try:
        run("cpu", params, vm, K, w, 1, h)
        cs.TILE_TIMES.clear()
        for _ in range(repeats):
            run("cpu", params, vm, K, w, 1, h)
        per_run = {}
        for kind, ns in cs.TILE_TIMES:
            per_run.setdefault(kind, []).append(ns)
    finally:
        cpu._work_order = real
        cs.TILE_TIMES = None
    fwd = np.median(np.stack(per_run["forward"]), axis=0)
    bwd = np.median(np.stack(per_run["backward"]), axis=0)
    return lengths["n"], 1e-9 * (fwd + bwd)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="runs per workload, median per tile (default: 5)")
    ap.add_argument("--json", default="tools/results/schedule.json", help="result file (default: %(default)s)")
    ap.add_argument("--plot", default="tools/results/schedule.png", help="plot, '' for none (default: %(default)s)")
    args = ap.parse_args(argv)
    import ev3dgs.splat.cpu_simd as cs

    if not cs.available():
        print("error: the C rasterizer extension is not built (python setup.py build_ext --inplace)",
              file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    rows = []
    for name, n, w, h in (("cloud", 10_000, 200, 200), ("step scene", 50_000, 346, 260)):
        params, vm, K = cloud(n, w) if name == "cloud" else step_scene(n, w, h)
        length, cost = tile_times(params, vm, K, w, h, args.repeats)
        by_length = np.argsort(-length, kind="stable")
        by_cost = np.argsort(-cost, kind="stable")
        row = {"scene": name, "gaussians": n, "width": w, "height": h, "tiles": int(len(cost)),
               "total_ms": 1e3 * float(cost.sum()), "largest_tile_share": float(cost.max() / cost.sum()),
               "efficiency": {str(t): {"round_robin_by_list_length": round_robin(cost, by_length, t),
                                       "work_queue_by_list_length": greedy(cost, t, by_length),
                                       "round_robin_by_time": round_robin(cost, by_cost, t),
                                       "greedy_by_time": greedy(cost, t)} for t in THREADS},
               "rank_correlation_length_time": float(np.corrcoef(np.argsort(np.argsort(length)),
                                                                 np.argsort(np.argsort(cost)))[0, 1])}
        rows.append(row)
        e = row["efficiency"]
        print(f"{name} {n} @ {w}x{h}: {len(cost)} tiles, {row['total_ms']:.1f} ms, largest tile "
              f"{100 * row['largest_tile_share']:.1f} %; round robin by list length: "
              + ", ".join(f"{t}: {e[str(t)]['round_robin_by_list_length']:.2f}" for t in THREADS)
              + "; work queue: " + ", ".join(f"{t}: {e[str(t)]['work_queue_by_list_length']:.2f}" for t in THREADS)
              + f"; greedy by time at 8/16: {e['8']['greedy_by_time']:.2f}/{e['16']['greedy_by_time']:.2f}")
    save_json(args.json, {"rows": rows, "median_of": args.repeats}, ", per-tile C kernel times, one thread")
    if args.plot:
        plot(rows, args.plot)
    return 0


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.2))
    for r in rows:
        lab = f"{r['scene']} {r['gaussians'] // 1000}k @ {r['width']}x{r['height']}"
        for key, style in (("round_robin_by_list_length", "o-"), ("work_queue_by_list_length", "s-"),
                           ("greedy_by_time", "x--")):
            ax.plot(THREADS, [r["efficiency"][str(t)][key] for t in THREADS], style,
                    label=f"{lab}: {key.replace('_', ' ')}")
    ax.set_xlabel("threads")
    ax.set_ylabel("T1 / (n Tn), simulated")
    ax.set_ylim(0, 1.05)
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
