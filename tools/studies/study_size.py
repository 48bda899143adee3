"""Study: what a CPU training step costs at DAVIS346 size. Step time, peak memory and Gaussian count against
image size (96x72, 173x130, 346x260) and Gaussian count (10k, 50k, 100k), numba rasterizer on 1 and 2
threads (torch pinned to 1 thread, as the trainer's `reproducible()` does), and a profile of one 346x260 step
against one 96x72 step.

The step is the trainer's blur+event step on the cpu backend on synthetic data (tools/bench/bench_train_scaling.py:
a random cloud in a unit cube, SH degree 3, 5 sub-poses, blur loss + event loss, backward, Adam). Each (size,
count) runs in its own subprocess so that its peak resident memory (ru_maxrss) is its own; inside it the
1-thread and 2-thread steps alternate (repeats interleaved), so the machine's load hits both alike and the
thread ratio is taken inside one run. Reported: median, min and max ms over the repeats.

    python tools/studies/study_size.py [--quick] --json tools/results/study_size.json --plot tools/results/study_size.png
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import json  # noqa: E402
import pstats  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

TOOLS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TOOLS))  # pareto.py
sys.path.insert(0, str(TOOLS / "bench"))  # bench_train_scaling.py
from bench_train_scaling import SUBPOSES, make_step  # noqa: E402
from pareto import machine, save_json  # noqa: E402

SIZES = [(96, 72), (173, 130), (346, 260)]
COUNTS = [10_000, 50_000, 100_000]
THREADS = [1, 2]
# profile groups: a function's cumulative time is charged to the first group whose pattern its name contains
GROUPS = [("projection + SH (numba fwd+bwd)", ("_project_forward", "_project_backward")),
          ("binning / packing (tiles, sort)", ("_bin", "_pack", "_pixel_boxes", "_stable_argsort", "_sort_keys")),
          ("rasterize forward (numba)", ("_forward",)),
          ("rasterize backward (numba)", ("_backward", "_reduce")),
          ("losses (torch)", ("blur_loss", "pose_event_loss", "log_intensity")),
          ("Adam (torch)", ("step",))]


def rss_mib() -> float:
    """Current resident memory (Linux /proc), MiB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def worker(n: int, width: int, height: int, repeats: int) -> dict:
    """One (size, count): warm-up, then `repeats` rounds of one step per thread count (interleaved)."""
    step = make_step(n, width, height)
    before = rss_mib()  # model, optimiser state, targets allocated; no step run yet
    for th in THREADS:  # warm-up: kernel loading, first-touch allocations
        step(th)
    times = {th: [] for th in THREADS}
    for _ in range(repeats):
        for th in THREADS:
            t0 = time.perf_counter()
            step(th)
            times[th].append(1e3 * (time.perf_counter() - t0))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    out = {"width": width, "height": height, "pixels": width * height, "gaussians": n, "repeats": repeats,
           "rss_before_step_mib": before, "peak_rss_mib": peak}
    for th in THREADS:
        out[f"ms_{th}t"] = {"median": statistics.median(times[th]), "min": min(times[th]), "max": max(times[th]),
                            "all": times[th]}
    # per-round ratios (the two steps of a round ran back to back under the same load), then their median
    out["speedup_2t"] = statistics.median(a / b for a, b in zip(times[1], times[2]))
    return out


def profile(n: int, width: int, height: int, threads: int = 1) -> dict:
    """cProfile one step (after a warm-up) and charge cumulative time to GROUPS."""
    step = make_step(n, width, height)
    step(threads)
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    step(threads)
    prof.disable()
    total = 1e3 * (time.perf_counter() - t0)
    stats = pstats.Stats(prof).stats
    groups = {}
    for label, names in GROUPS:
        ms = 0.0
        for (file, _line, func), (_cc, _nc, _tt, ct, _callers) in stats.items():
            if func in names and ("ev3dgs" in file or "torch/optim" in file or label.startswith("Adam")):
                if label.startswith("Adam") and "optim" not in file:
                    continue
                ms += 1e3 * ct
        groups[label] = ms
    groups["other"] = max(0.0, total - sum(groups.values()))
    return {"width": width, "height": height, "gaussians": n, "threads": threads, "total_ms": total,
            "groups_ms": groups, "groups_share": {k: v / total for k, v in groups.items()}}


def plot(out: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    rows = out["runs"]
    for n, marker in zip(COUNTS, "osd"):
        sel = [r for r in rows if r["gaussians"] == n]
        if not sel:
            continue
        px = [r["pixels"] for r in sel]
        for th, ls in ((1, "-"), (2, "--")):
            med = [r[f"ms_{th}t"]["median"] for r in sel]
            lo = [m - r[f"ms_{th}t"]["min"] for m, r in zip(med, sel)]
            hi = [r[f"ms_{th}t"]["max"] - m for m, r in zip(med, sel)]
            ax[0].errorbar(px, med, yerr=[lo, hi], marker=marker, ls=ls, capsize=2,
                           label=f"{n // 1000}k Gaussians, {th} thread{'s' if th > 1 else ''}")
        ax[1].plot(px, [r["peak_rss_mib"] for r in sel], marker=marker, label=f"{n // 1000}k Gaussians")
    for a in ax:
        a.set_xscale("log")
        a.set_yscale("log")
        a.set_xticks([w * h for w, h in SIZES], [f"{w}x{h}" for w, h in SIZES])
        a.minorticks_off()
        a.grid(True, which="both", lw=0.3)
    ax[0].set_ylabel("ms per blur+event step (median, min-max)")
    ax[1].set_ylabel("peak resident memory (MiB)")
    ax[0].legend(fontsize=6)
    ax[1].legend(fontsize=6)
    fig.suptitle(f"CPU training step against image size, {SUBPOSES} sub-poses, SH degree 3 ({machine()})",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one count (10k), 2 repeats, no profile (a smoke run)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", default="tools/results/study_size.json")
    ap.add_argument("--plot", default="tools/results/study_size.png")
    ap.add_argument("--worker", nargs=4, type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(*args.worker)))
        return 0
    counts = COUNTS[:1] if args.quick else COUNTS
    repeats = 2 if args.quick else args.repeats
    t_start = time.perf_counter()
    runs = []
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE", NUMBA_NUM_THREADS=str(max(THREADS)))
    for w, h in SIZES:
        for n in counts:
            cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(n), str(w), str(h), str(repeats)]
            res = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            r = json.loads(res.stdout.strip().splitlines()[-1])
            runs.append(r)
            print(f"{w}x{h} {n // 1000:4d}k: 1 thread {r['ms_1t']['median']:8.0f} ms "
                  f"[{r['ms_1t']['min']:.0f}-{r['ms_1t']['max']:.0f}], 2 threads {r['ms_2t']['median']:8.0f} ms "
                  f"(x{r['speedup_2t']:.2f}), peak {r['peak_rss_mib']:.0f} MiB", flush=True)
    out = {"subposes": SUBPOSES, "sh_degree": 3, "torch_threads": 1, "repeats": repeats, "runs": runs}
    base = {(r["width"], r["gaussians"]): r for r in runs}
    out["ratio_to_96x72"] = {f"{w}x{h} {n // 1000}k": base[(w, n)]["ms_1t"]["median"] / base[(96, n)]["ms_1t"]["median"]
                             for w, h in SIZES for n in counts}
    if not args.quick:
        import numba

        numba.set_num_threads(1)
        out["profile"] = [profile(50_000, 96, 72), profile(50_000, 346, 260)]
        for p in out["profile"]:
            print(f"profile {p['width']}x{p['height']} 50k, 1 thread: {p['total_ms']:.0f} ms: " + ", ".join(
                f"{k} {100 * v:.0f}%" for k, v in p["groups_share"].items()))
    out["study_seconds"] = time.perf_counter() - t_start
    save_json(args.json, out, ", torch 1 thread, numba 1 and 2 threads")
    plot(out, args.plot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
