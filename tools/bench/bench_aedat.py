"""AEDAT 4 event reading: events/s and peak memory of our reader against dv-processing on the same files, in one
run, as ratios taken round by round. "ours-1thread" / "ours-2threads" is the reader as installed (events through
the C fast path, ev3dgs.io.aedat4.fast, with 1 or 2 C threads decoding packets); "ours-general" the same reader
with the fast path switched off (the numpy path that every packet the fast path does not find intact takes, one
thread). dv-processing reads with one thread. With 2 threads the wall time only shows the gain where a core is
idle; the CPU-time ratio shows the cost.

Files: the shared DAVIS346 recording (117 667 events; read --inner times per process), a file written by
dv-processing with uniformly random events (LZ4, the worst case for decompression), and files written by our
writer (ev3dgs.io.aedat4.writer) from the shared recording's events tiled in time (realistic compression: real
event statistics, 20 000-event packets) with LZ4 (DV's default) and ZSTD. Every read runs in its own child
process (import first and time it apart as `import_s`, then time the read; peak memory = growth of the resident-set high-water mark during the
read). The readers run interleaved, one round after another, so that load from other processes hits them
alike; the ratio to dv-processing is taken within each round and reported as median [min, max] over rounds,
for wall time (speed) and for CPU time (work: on a machine whose cores are busy with other work, wall time
mostly measures waiting, and a decoding thread cannot overlap anything).
A warm-up child reads each file once first (page cache).

    git archive b894e45 ev3dgs | tar -x -C /tmp/prev      # optional: the reader before this work
    python tools/bench/bench_aedat.py --events 20000000 --rounds 5 --previous /tmp/prev
    python tools/bench/bench_aedat.py --resync --events 400000 --rounds 7 --previous /tmp/prev   # AEDAT 2.0
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json

SHARED = Path("/work/shared/data/aedat/aestream_davis.aedat4")
READERS = ["ours-1thread", "ours-2threads", "ours-general", "dv-processing"]
PREVIOUS: str | None = None     # --previous: an older ev3dgs tree whose reader runs as "previous" (threads: its own)


def make_dv_file(path: Path, n_events: int) -> None:
    """dv-processing's writer, uniformly random events over 346x260 (poorly compressible)."""
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


def make_tiled_file(path: Path, n_events: int, compression: str) -> None:
    """Our writer, the shared recording's events repeated back to back in time until n_events."""
    from ev3dgs.events import Events
    from ev3dgs.io.aedat4 import Aedat4Reader
    from ev3dgs.io.aedat4.writer import write_aedat4

    with Aedat4Reader(SHARED) as r:
        ev = Events.concatenate(list(r.events()))
    span = int(ev.t[-1] - ev.t[0]) + 1

    def tiles():
        for k in range(-(-n_events // len(ev))):
            m = min(len(ev), n_events - k * len(ev))
            yield Events(ev.t[:m] + k * span, ev.x[:m], ev.y[:m], ev.p[:m])

    write_aedat4(path, 346, 260, tiles(), compression=compression)


def read_once(reader: str, path: str, inner: int) -> dict:
    """Runs in a child process: import, then time `inner` reads and measure the peak RSS growth."""
    t_import = time.perf_counter()
    if reader.startswith("ours") or reader == "previous":
        from ev3dgs.io.aedat4 import Aedat4Reader

        kw = {} if reader == "previous" else {"threads": 2 if reader == "ours-2threads" else 1}
        if reader == "ours-general":
            from ev3dgs.io.aedat4 import fast as aedat4_fast
            aedat4_fast.FAST = False

        def run():
            n = 0
            with Aedat4Reader(path, **kw) as r:
                for ev in r.events():
                    n += len(ev)
            return n
    else:
        import dv_processing as dv

        def run():
            n = 0
            rec = dv.io.MonoCameraRecording(path)
            while (b := rec.getNextEventBatch()) is not None:
                n += len(b.numpy())
            return n
    import_s = time.perf_counter() - t_import
    base = _status_kb("VmRSS:")
    with open("/proc/self/clear_refs", "w") as f:  # reset the high-water mark left by the imports
        f.write("5")
    t0 = time.perf_counter()
    c0 = time.process_time()
    n = sum(run() for _ in range(inner))
    sec, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"events": n // inner, "seconds": sec / inner, "cpu_seconds": cpu / inner, "import_s": import_s,
            "peak_growth_mb": (_status_kb("VmHWM:") - base) / 1024}


def _status_kb(key: str) -> int:
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1])
    return 0


def _child(reader: str, path: Path, inner: int) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    if reader == "previous":
        env["PYTHONPATH"] = PREVIOUS
    out = subprocess.run([sys.executable, __file__, "--child", reader, str(path), str(inner)], capture_output=True,
                         text=True, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"{reader} on {path.name}: {out.stderr.strip().splitlines()[-1] if out.stderr else '?'}")
    return json.loads(out.stdout)


def bench_file(label: str, path: Path, rounds: int, inner: int) -> dict:
    _child("ours-1thread", path, 1)                       # warm-up: page cache
    runs = {r: [] for r in READERS}
    for _ in range(rounds):
        for reader in READERS:
            runs[reader].append(_child(reader, path, inner))
    ref = runs["dv-processing"]
    rows = []
    for reader in READERS:
        rs = runs[reader]
        ratios = [d["seconds"] / o["seconds"] for o, d in zip(rs, ref)]   # > 1: ours is faster
        cpu_ratios = [d["cpu_seconds"] / o["cpu_seconds"] for o, d in zip(rs, ref)]   # > 1: ours needs less CPU
        sec = statistics.median(r["seconds"] for r in rs)
        rows.append({"reader": reader, "events": rs[0]["events"], "seconds": sec,
                     "cpu_seconds": statistics.median(r["cpu_seconds"] for r in rs),
                     "events_per_s": rs[0]["events"] / sec,
                     "vs_dv_processing": statistics.median(ratios),
                     "vs_dv_processing_range": [min(ratios), max(ratios)],
                     "cpu_vs_dv_processing": statistics.median(cpu_ratios),
                     "cpu_vs_dv_processing_range": [min(cpu_ratios), max(cpu_ratios)],
                     "import_s": statistics.median(r["import_s"] for r in rs),
                     "peak_growth_mb": statistics.median(r["peak_growth_mb"] for r in rs)})
        print(f"{label:22s} {reader:14s} {rows[-1]['events']:>10d} ev  {rows[-1]['events_per_s'] / 1e6:6.1f} M ev/s  "
              f"cpu {rows[-1]['cpu_seconds']:.3f} s  peak +{rows[-1]['peak_growth_mb']:5.1f} MB  "
              f"x{rows[-1]['vs_dv_processing']:.2f} [{min(ratios):.2f}, {max(ratios):.2f}] vs dv-processing "
              f"(CPU x{rows[-1]['cpu_vs_dv_processing']:.2f})  import {rows[-1]['import_s']:.2f} s",
              flush=True)
    return {"file": label, "file_mb": path.stat().st_size / 2**20, "rows": rows}


# ---------------------------------------------------------------- AEDAT 2.0 mid-file realignment
def _a2_child(tree: str, path: str) -> dict:
    """One full AEDAT 2.0 read (events, frames, IMU, triggers: info() decodes everything) in this process."""
    import warnings

    sys.path.insert(0, tree)
    from ev3dgs.io.jaer.aedat2 import Aedat2Reader

    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with Aedat2Reader(path) as r:
            info = r.info()
    return {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0, "events": info["events"]}


def bench_resync(rounds: int, events: int, previous: str | None) -> dict:
    """A DAVIS240C AEDAT 2.0 file (tests/aedat2_build.py) read intact, with 3 bytes removed and 5 inserted
    mid-file, and with 1 MiB of random bytes inserted; every read in its own child, the cases interleaved round
    by round. Ratios to the intact read of the same round (CPU time): what realigning costs. With --previous,
    the older reader's intact read too (the cost of the realignment pass on intact files)."""
    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
    from aedat2_build import HEADER, build

    data = build(n_events=events, frames=4)[0]
    mid = len(HEADER) + (len(data) - len(HEADER)) // 16 * 8 + 3
    garbage = np.random.default_rng(0).integers(0, 256, 1 << 20, dtype=np.uint8).tobytes()
    cases = {"intact": data, "remove 3": data[:mid] + data[mid + 3:],
             "insert 5": data[:mid] + b"\x01" * 5 + data[mid:], "insert 1 MiB": data[:mid] + garbage + data[mid:]}
    trees = {"current": str(Path(__file__).resolve().parents[2])}
    if previous:
        trees["previous"] = str(Path(previous).resolve())
    rows = {f"{t} {c}": [] for t in trees for c in cases if t == "current" or c == "intact"}
    with tempfile.TemporaryDirectory() as d:
        paths = {}
        for c, b in cases.items():
            paths[c] = Path(d) / f"{c.replace(' ', '_')}.aedat"
            paths[c].write_bytes(b)
        for r in range(rounds + 1):                          # round 0 warms the page cache
            for key in rows:
                t, c = key.split(" ", 1)
                out = subprocess.run([sys.executable, __file__, "--child-a2", trees[t], str(paths[c])],
                                     capture_output=True, text=True, check=True)
                if r:
                    rows[key].append(json.loads(out.stdout.strip().splitlines()[-1]))
    ratio = {}
    for key, runs in rows.items():
        base = rows["current intact"]
        q = [a["cpu_s"] / b["cpu_s"] for a, b in zip(runs, base)]
        ratio[key] = {"cpu_s_median": statistics.median(a["cpu_s"] for a in runs), "events": runs[0]["events"],
                      "ratio_to_current_intact": {"min": min(q), "median": statistics.median(q), "max": max(q)}}
    return {"file_mb": len(data) / 2**20, "records": (len(data) - len(HEADER)) // 8, "rounds": rounds,
            "cases": ratio}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--events", type=int, default=20_000_000, help="events per synthetic file (default 20000000)")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds per file (default 5)")
    ap.add_argument("--inner", type=int, default=20,
                    help="reads per child process of the small shared recording (default 20)")
    ap.add_argument("--previous", metavar="DIR",
                    help="also time the AEDAT 4 reader of an older ev3dgs tree in DIR (e.g. `git archive <commit> "
                         "ev3dgs | tar -x -C DIR`) as 'previous' (default: none)")
    ap.add_argument("--child", nargs=3, metavar=("READER", "FILE", "INNER"), help=argparse.SUPPRESS)
    ap.add_argument("--child-a2", nargs=2, metavar=("TREE", "FILE"), help=argparse.SUPPRESS)
    ap.add_argument("--resync", action="store_true",
                    help="instead: the AEDAT 2.0 reader on an intact file and on copies with bytes inserted or "
                         "removed mid-file (--events DVS events; JSON to tools/results/bench_aedat_resync.json)")
    ap.add_argument("--json", default="tools/results/bench_aedat.json", help="output JSON (default %(default)s)")
    ap.add_argument("--plot", default="tools/results/bench_aedat.png", help="output plot (default %(default)s)")
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(read_once(args.child[0], args.child[1], int(args.child[2]))))
        return 0
    if args.child_a2:
        print(json.dumps(_a2_child(*args.child_a2)))
        return 0
    if args.resync:
        load0 = os.getloadavg()
        res = bench_resync(args.rounds, min(args.events, 2_000_000), args.previous)
        save_json("tools/results/bench_aedat_resync.json" if args.json == "tools/results/bench_aedat.json"
                  else args.json, res, f", load average {load0[0]:.1f} at start, {os.getloadavg()[0]:.1f} at end")
        for k, v in res["cases"].items():
            q = v["ratio_to_current_intact"]
            print(f"{k:>24}: {v['cpu_s_median']:.3f} s CPU, {v['events']} events, x{q['median']:.2f} "
                  f"[{q['min']:.2f}, {q['max']:.2f}] of the intact read")
        return 0
    global PREVIOUS
    if args.previous:
        PREVIOUS = str(Path(args.previous).resolve())
        READERS.insert(0, "previous")
    load0 = os.getloadavg()
    results = []
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        if SHARED.exists():
            results.append(bench_file("shared DAVIS346", SHARED, args.rounds, args.inner))
        for label, make in (("dv uniform LZ4", lambda p: make_dv_file(p, args.events)),
                            ("tiled LZ4 (our writer)", lambda p: make_tiled_file(p, args.events, "lz4")),
                            ("tiled ZSTD (our writer)", lambda p: make_tiled_file(p, args.events, "zstd"))):
            if label.startswith("tiled") and not SHARED.exists():
                continue
            p = d / "bench.aedat4"
            make(p)
            results.append(bench_file(label, p, args.rounds, 1))
            p.unlink()
    note = f", load average {load0[0]:.1f} at start, {os.getloadavg()[0]:.1f} at end"
    save_json(args.json, {"rounds": args.rounds, "events": args.events, "previous": args.previous,
                          "files": results}, note)
    plot(results, args.plot)
    return 0


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(1, 2, figsize=(11, 3.6))
    xs = np.arange(len(results))
    ours = [r for r in READERS if r != "dv-processing"]
    wid = 0.8 / len(ours)
    for k, reader in enumerate(ours):
        rows = [next(x for x in f["rows"] if x["reader"] == reader) for f in results]
        med = np.array([r["vs_dv_processing"] for r in rows])
        lo = med - np.array([r["vs_dv_processing_range"][0] for r in rows])
        hi = np.array([r["vs_dv_processing_range"][1] for r in rows]) - med
        ax[0].bar(xs + (k - (len(ours) - 1) / 2) * wid, med, wid, yerr=[lo, hi], capsize=3, label=reader)
    ax[0].axhline(1.0, color="k", lw=0.8, ls="--")
    ax[0].set_ylabel("speed / dv-processing (>1: faster)")
    wid = 0.8 / len(READERS)
    for k, reader in enumerate(READERS):
        rows = [next(x for x in f["rows"] if x["reader"] == reader) for f in results]
        ax[1].bar(xs + (k - (len(READERS) - 1) / 2) * wid, [r["peak_growth_mb"] for r in rows], wid, label=reader)
    ax[1].set_ylabel("peak RSS growth during the read (MB)")
    for a in ax:
        a.set_xticks(xs, [f["file"] for f in results], fontsize=7)
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
