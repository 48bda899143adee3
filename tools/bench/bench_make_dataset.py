"""Seconds per view of `make-dataset`, split into render / simulate / ISP / write, for the --quick and the
default render presets (a few views each: per-view cost is what matters). JSON + PNG.

    python tools/bench/bench_make_dataset.py [--scene lego] [--views 2] --json tools/results/bench_make_dataset.json
"""
from __future__ import annotations

import sys

import os

os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

import argparse  # noqa: E402
import tempfile  # noqa: E402
from dataclasses import asdict  # noqa: E402
from pathlib import Path  # noqa: E402

from ev3dgs.sim.dataset import make_dataset  # noqa: E402
from ev3dgs.sim.scenes import load_scene, resolve_render  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="lego")
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--presets", default="quick,default")
    ap.add_argument("--json", default="tools/results/bench_make_dataset.json")
    ap.add_argument("--plot", default="tools/results/bench_make_dataset.png")
    args = ap.parse_args(argv)
    spec = load_scene(args.scene)
    rows = []
    for preset in args.presets.split(","):
        render = resolve_render(spec, quick=preset == "quick", views=args.views, test_views=0)
        with tempfile.TemporaryDirectory() as d:
            stats = make_dataset(spec, render, Path(d) / "scene.h5", quiet=True)
        per_view = {k: v / render.views for k, v in stats.seconds.items()}
        overhead = (per_view["simulate"] + per_view["isp"] + per_view["write"]) / per_view["render"]
        rows.append({"preset": preset, "scene": args.scene, "render": asdict(render), "events": stats.events,
                     "seconds_per_view": per_view, "post_over_render": overhead})
        print(f"{preset:8s} {render.width}x{render.height} {render.samples} spp x {render.subframes} sub-frames: "
              + ", ".join(f"{k} {v:.3f} s" for k, v in per_view.items())
              + f" per view; simulate+ISP+write = {100 * overhead:.1f}% of render")
    save_json(args.json, {"rows": rows})
    plot(rows, args.plot)
    return 0


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3))
    stages = ["render", "simulate", "isp", "write"]
    left = [0.0] * len(rows)
    for s in stages:
        vals = [r["seconds_per_view"][s] for r in rows]
        ax.barh([r["preset"] for r in rows], vals, left=left, label=s)
        left = [a + b for a, b in zip(left, vals)]
    ax.set_xscale("symlog", linthresh=0.1)
    ax.set_xlabel("seconds per view (17 sub-frames)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
