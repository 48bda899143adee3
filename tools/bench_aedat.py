"""AEDAT 4 event reading: events/s and peak memory of our reader, dv-processing and the `aedat` package on
the same >= 20 M-event file (written by dv-processing, LZ4), in one run. Each read runs in its own process
so peak memory (growth of the resident-set high-water mark during the read) is measured cleanly.

    python tools/bench_aedat.py [--events 20000000] [--repeats 3] --json tools/results/bench_aedat.json
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from pareto import save_json

READERS = ("ours", "dv-processing", "aedat")


def make_file(path: Path, n_events: int) -> None:
    import datetime

    import dv_processing as dv

    cfg = dv.io.MonoCameraWriter.Config("DAVIS346_bench", dv.CompressionType.LZ4)
    cfg.addEventStream((346, 260))
    w = dv.io.MonoCameraWriter(str(path), cfg)
    batch = 200_000
    for k in range(0, n_events, batch):
        n = min(batch, n_events - k)
        w.writeEvents(dv.data.generate.uniformEventsWithinTimeRange(
            1_000_000 + k * 5, datetime.timedelta(microseconds=5 * n), (346, 260), n, k))
    del w


def read_once(reader: str, path: str) -> dict:
    """Runs in a child process: import, then time the read and measure the peak RSS growth."""
    if reader == "ours":
        from ev3dgs.io.aedat4 import Aedat4Reader

        def run():
            n = 0
            with Aedat4Reader(path) as r:
                for ev in r.events():
                    n += len(ev)
            return n
    elif reader == "dv-processing":
        import dv_processing as dv

        def run():
            n = 0
            rec = dv.io.MonoCameraRecording(path)
            while (b := rec.getNextEventBatch()) is not None:
                n += len(b.numpy())
            return n
    else:
        import aedat

        def run():
            n = 0
            for packet in aedat.Decoder(path):
                if "events" in packet:
                    n += len(packet["events"])
            return n
    base = _rss_kb()
    with open("/proc/self/clear_refs", "w") as f:  # reset the high-water mark left by the imports
        f.write("5")
    t0 = time.perf_counter()
    n = run()
    sec = time.perf_counter() - t0
    return {"events": n, "seconds": sec, "peak_growth_mb": (_hwm_kb() - base) / 1024}


def _status_kb(key: str) -> int:
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1])
    return 0


def _rss_kb() -> int:
    return _status_kb("VmRSS:")


def _hwm_kb() -> int:
    return _status_kb("VmHWM:")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=20_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--file", help="use this AEDAT4 file instead of generating one")
    ap.add_argument("--child", nargs=2, metavar=("READER", "FILE"), help=argparse.SUPPRESS)
    ap.add_argument("--json", default="tools/results/bench_aedat.json")
    ap.add_argument("--plot", default="tools/results/bench_aedat.png")
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(read_once(*args.child)))
        return 0
    with tempfile.TemporaryDirectory() as d:
        path = Path(args.file) if args.file else Path(d) / "bench.aedat4"
        if not args.file:
            make_file(path, args.events)
        rows = []
        for reader in READERS:
            runs = []
            for _ in range(args.repeats):  # interleaving would be fairer on a noisy box; repeats + median
                out = subprocess.run([sys.executable, __file__, "--child", reader, str(path)],
                                     capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
                if out.returncode != 0:
                    runs = None
                    print(f"{reader}: failed: {out.stderr.strip().splitlines()[-1] if out.stderr else '?'}")
                    break
                runs.append(json.loads(out.stdout))
            if not runs:
                continue
            sec = statistics.median(r["seconds"] for r in runs)
            rows.append({"reader": reader, "events": runs[0]["events"], "seconds": sec,
                         "events_per_s": runs[0]["events"] / sec,
                         "peak_growth_mb": statistics.median(r["peak_growth_mb"] for r in runs)})
        size_mb = path.stat().st_size / 2**20
    ref = next((r for r in rows if r["reader"] == "dv-processing"), None)
    for r in rows:
        r["vs_dv_processing"] = r["events_per_s"] / ref["events_per_s"] if ref else None
        print(f"{r['reader']:14s} {r['events']:>10d} events  {r['events_per_s'] / 1e6:6.1f} M ev/s  "
              f"peak +{r['peak_growth_mb']:.0f} MB  (x{r['vs_dv_processing'] or 0:.2f} vs dv-processing)")
    save_json(args.json, {"file_mb": size_mb, "rows": rows})
    plot(rows, args.plot)
    return 0


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(8, 3))
    names = [r["reader"] for r in rows]
    ax[0].bar(names, [r["events_per_s"] / 1e6 for r in rows])
    ax[0].set_ylabel("M events / s")
    ax[1].bar(names, [r["peak_growth_mb"] for r in rows])
    ax[1].set_ylabel("peak memory growth (MB)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
