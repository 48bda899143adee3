"""First run against later runs: the same short training in fresh processes, once with an empty numba cache
(the kernels compile and are written to disk) and once with the cache that run filled (they load).

    python tools/bench/bench_first_run.py [--repeats 3] [--iterations 30] \\
        --json tools/results/bench_first_run.json --plot tools/results/bench_first_run.png

Each repeat gets its own empty cache folder (NUMBA_CACHE_DIR), so cold and warm alternate within one run of the
script (the machine's load affects both alike). One torch / numba thread. The scene is a small hand-made one
(tests/view_scene.py: 8 views at 64x48), so the step cost is small next to the compile.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def _train(scene: Path, out: Path, iterations: int, cache: Path) -> tuple[float, str]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1")
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "ev3dgs.cli.main", "train", str(scene), "--out", str(out),
                        "--iterations", str(iterations), "--set", "init_points=2000", "--threads", "1", "--quiet"],
                       env=env, capture_output=True, text=True, check=True)
    return time.perf_counter() - t, r.stderr


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--json", default="tools/results/bench_first_run.json")
    ap.add_argument("--plot", default="tools/results/bench_first_run.png")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT / "tests"))
    from view_scene import make_scene

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = Path(make_scene(tmp / "scene.h5", with_imu=False))
        for i in range(a.repeats):
            cache = tmp / f"cache{i}"
            cold, err = _train(scene, tmp / f"cold{i}", a.iterations, cache)
            warm, err2 = _train(scene, tmp / f"warm{i}", a.iterations, cache)
            rows.append({"cold_s": cold, "warm_s": warm, "notice_cold": "compiling" in err,
                         "notice_warm": "compiling" in err2})
            print(f"repeat {i}: cold {cold:.1f} s, warm {warm:.1f} s", flush=True)
    cold = [r["cold_s"] for r in rows]
    warm = [r["warm_s"] for r in rows]
    summary = {"cold_median_s": statistics.median(cold), "warm_median_s": statistics.median(warm),
               "cold_range_s": [min(cold), max(cold)], "warm_range_s": [min(warm), max(warm)],
               "ratio_median": statistics.median(c / w for c, w in zip(cold, warm))}
    save_json(a.json, {"iterations": a.iterations, "threads": 1, "scene": "tests/view_scene.py (8 views, 64x48)",
                       "rows": rows, "summary": summary})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2))
    ax.bar(["first run (compile)", "later runs (cached)"], [summary["cold_median_s"], summary["warm_median_s"]],
           color=["tab:red", "tab:green"])
    for x, vals in enumerate((cold, warm)):
        ax.plot([x] * len(vals), vals, "k.", ms=6)
    ax.set_ylabel(f"wall time of {a.iterations} training steps, s")
    ax.set_title("numba kernel cache: first run vs later runs", fontsize=10)
    fig.tight_layout()
    Path(a.plot).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.plot, dpi=110)
    print(f"cold {summary['cold_median_s']:.1f} s (range {min(cold):.1f}-{max(cold):.1f}), warm "
          f"{summary['warm_median_s']:.1f} s (range {min(warm):.1f}-{max(warm):.1f}) -> {a.json}, {a.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
