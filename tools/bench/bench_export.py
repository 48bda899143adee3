"""`ev3dgs export-dataset` memory against scene size: peak memory of each format's export on synthetic scenes
of growing size (up to 100 views at 800x800), next to what loading all events at once costs.

Scenes are built quickly with our own schema writer (no Blender): smooth gradient images, uniform random events
inside each view's exposure, written through a staging HDF5 file so the builder never holds them all either.
Each export runs in its own process; we report the growth of the resident-set high-water mark over the
process's state after its imports (/proc/self/clear_refs resets VmHWM), the tracemalloc peak (numpy buffers
included) and the wall time (2 shared cores: indicative only).

    python tools/bench/bench_export.py --json tools/results/bench_export.json --plot tools/results/bench_export.png
    python tools/bench/bench_export.py --sizes 4x64x64x5000 --formats e2nerf      # quick check
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

FORMATS = ("e2nerf", "events-h5", "aedat4", "transforms")
DEFAULT_SIZES = ("10x200x200x50000", "30x400x400x200000", "100x800x800x400000")  # views x H x W x events/view
EXPOSURE_US, PERIOD_US = 100_000, 150_000


def build_scene(path: Path, views: int, h: int, w: int, per_view: int, seed: int = 0) -> dict:
    import h5py

    from ev3dgs import schema
    from ev3dgs.geometry import intrinsics, look_at

    rng = np.random.default_rng(seed)
    stage = path.with_name(path.name + ".stage.h5")
    with h5py.File(stage, "w") as f:
        ds = {n: f.create_dataset(n, shape=(views * per_view,), dtype=dt, chunks=(min(1 << 18, views * per_view),))
              for n, dt in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8))}
        img = f.create_dataset("images", shape=(views, h, w, 3), dtype=np.uint8, chunks=(1, h, w, 3))
        yy, xx = np.mgrid[0:h, 0:w]
        for v in range(views):
            t0 = v * PERIOD_US
            sl = slice(v * per_view, (v + 1) * per_view)
            ds["t"][sl] = np.sort(rng.integers(t0, t0 + EXPOSURE_US + 1, per_view))
            ds["x"][sl] = rng.integers(0, w, per_view)
            ds["y"][sl] = rng.integers(0, h, per_view)
            ds["p"][sl] = rng.choice(np.array([-1, 1], np.int8), per_view)
            img[v] = np.stack([(xx * 255 // max(1, w - 1) + v) % 256, yy * 255 // max(1, h - 1),
                               np.full_like(xx, 40 * v % 256)], axis=-1).astype(np.uint8)
    lazy = {n: schema.LazyArray(stage, n, (views * per_view,), dt)
            for n, dt in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8))}
    images = schema.LazyArray(stage, "images", (views, h, w, 3), np.uint8)
    ang = np.linspace(0, 2 * np.pi, views, endpoint=False)
    S = 17
    exposure = np.array([[v * PERIOD_US, v * PERIOD_US + EXPOSURE_US] for v in range(views)], np.int64)
    pose_t = exposure[:, :1] + np.arange(S)[None] * (EXPOSURE_US // (S - 1))
    poses = np.stack([[look_at([4 * np.cos(a + 0.002 * s), 4 * np.sin(a + 0.002 * s), 1.5], [0, 0, 0])
                       for s in range(S)] for a in ang])
    sc = schema.Scene(name=path.stem, source="blender", camera=schema.Camera(w, h, intrinsics(w, h, 40.0)),
                      events=schema.LazyEvents(lazy["t"], lazy["x"], lazy["y"], lazy["p"]),
                      sensor=schema.EventSensor(0.2, 0.2),
                      train=schema.Train(images=images, exposure=exposure, poses=poses, pose_t=pose_t),
                      bounds=np.array([[-1.0, -1, -1], [1, 1, 1]]))
    try:
        schema.write(sc, path)
    finally:
        stage.unlink(missing_ok=True)
    return {"views": views, "height": h, "width": w, "events": views * per_view,
            "events_mb": views * per_view * 13 / 2**20, "file_mb": path.stat().st_size / 2**20}


def _status_kb(key: str) -> int:
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1])
    return 0


def child(fmt: str, scene: str, out: str) -> dict:
    """In its own process: imports first, then the measured export (or the all-events load reference)."""
    import tracemalloc

    import torch  # noqa: F401 - the e2nerf writer imports it; keep imports out of the measurement

    from ev3dgs import schema
    from ev3dgs.exporters import export_dataset
    from ev3dgs.exporters import aedat4, e2nerf, events_h5, transforms  # noqa: F401

    base = _status_kb("VmRSS:")
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    tracemalloc.start()
    t0 = time.perf_counter()
    if fmt == "load-all":
        ev = schema.read(scene).events.load()
        n = len(ev)
    else:
        export_dataset(scene, fmt, out, force=True, quiet=True)
        n = 0
    sec = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    out_mb = sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file()) / 2**20 if n == 0 else 0
    return {"seconds": sec, "peak_rss_growth_mb": (_status_kb("VmHWM:") - base) / 1024,
            "tracemalloc_peak_mb": peak / 2**20, "output_mb": out_mb}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=list(DEFAULT_SIZES),
                    help="scenes as VIEWSxHxWxEVENTS_PER_VIEW (default: %(default)s)")
    ap.add_argument("--formats", nargs="+", default=list(FORMATS), choices=FORMATS,
                    help="formats to export (default: all)")
    ap.add_argument("--dir", help="work folder (default: a temporary folder, removed afterwards)")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument("--json", default="tools/results/bench_export.json", help="results (default %(default)s)")
    ap.add_argument("--plot", default="tools/results/bench_export.png", help="plot (default %(default)s)")
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(*args.child)))
        return 0
    work = Path(args.dir or tempfile.mkdtemp(prefix="bench_export_"))
    work.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE",
           "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    rows = []
    try:
        for size in args.sizes:
            v, h, w, e = (int(s) for s in size.split("x"))
            scene = work / f"scene_{size}.h5"
            t0 = time.perf_counter()
            meta = build_scene(scene, v, h, w, e)
            meta["build_seconds"] = time.perf_counter() - t0
            print(f"scene {size}: {meta['events']} events ({meta['events_mb']:.0f} MB as t,x,y,p), "
                  f"file {meta['file_mb']:.0f} MB, built in {meta['build_seconds']:.0f} s", flush=True)
            for fmt in ("load-all", *args.formats):
                out = work / f"out_{fmt}"
                r = subprocess.run([sys.executable, __file__, "--child", fmt, str(scene), str(out)],
                                   capture_output=True, text=True, env=env)
                if r.returncode != 0:
                    print(f"  {fmt}: failed: {r.stderr.strip()[-400:]}")
                    continue
                res = json.loads(r.stdout.strip().splitlines()[-1])
                rows.append({"scene": size, **meta, "format": fmt, **res})
                print(f"  {fmt:10s} {res['seconds']:7.1f} s  peak RSS +{res['peak_rss_growth_mb']:7.1f} MB  "
                      f"tracemalloc {res['tracemalloc_peak_mb']:7.1f} MB  output {res['output_mb']:.0f} MB",
                      flush=True)
                shutil.rmtree(out, ignore_errors=True)
            scene.unlink()
    finally:
        if not args.dir:
            shutil.rmtree(work, ignore_errors=True)
    save_json(args.json, {"sizes": args.sizes, "rows": rows,
                          "note": "peak_rss_growth_mb: VmHWM growth after imports; load-all: schema.read(...)"
                                  ".events.load(), the cost of holding every event"})
    plot(rows, args.plot)
    return 0


def plot(rows, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    for fmt in dict.fromkeys(r["format"] for r in rows):
        rr = [r for r in rows if r["format"] == fmt]
        style = dict(color="k", marker="s") if fmt == "load-all" else dict(marker="o")
        label = "all events in memory (reference)" if fmt == "load-all" else fmt
        ax[0].plot([r["events"] / 1e6 for r in rr], [r["peak_rss_growth_mb"] for r in rr], label=label, **style)
        ax[1].plot([r["events"] / 1e6 for r in rr], [r["tracemalloc_peak_mb"] for r in rr], label=label,
                   **style)
    for a, t in zip(ax, ("peak RSS growth (MB)", "tracemalloc peak (MB)")):
        a.set_xlabel("events in the scene (millions)")
        a.set_ylabel(t)
        a.set_xscale("log")
        a.set_yscale("log")
        a.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.suptitle("export-dataset: memory vs scene size (scenes: 10x200^2, 30x400^2, 100x800^2 views)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
