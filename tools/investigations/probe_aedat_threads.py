"""Where the time of a threaded AEDAT 4 read through the numpy path (ev3dgs.io.aedat4.packets; the C fast path
switched off) goes: per read, wall time, the process's CPU time, the consuming
thread's own CPU time and the time it spends waiting for the read-ahead workers, and context switches
(voluntary ones are mostly GIL and future hand-overs between threads), for 1 and 2 threads, optionally also
for an older ev3dgs tree (--previous DIR, e.g. `git archive <commit> ev3dgs | tar -x -C DIR`).

Each configuration runs in its own child process (import first, one warm-up read, then --reads timed reads;
the median is reported), configurations interleaved round by round. A consumer that mostly waits while the
process burns about the 1-thread CPU time means the workers do the work and the stages overlap; a consumer that
keeps busy while the process burns much more CPU than with 1 thread means the threads fight over the GIL.

    python tools/investigations/probe_aedat_threads.py FILE.aedat4 [--previous /tmp/prev] [--rounds 3] [--reads 5]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
from pathlib import Path
import time

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json


def child(path: str, threads: int, reads: int) -> dict:
    import concurrent.futures._base as fb

    from ev3dgs.io.aedat4 import Aedat4Reader
    try:                                          # the numpy path's read-ahead is what this probes (the C fast
        from ev3dgs.io.aedat4 import fast as aedat4_fast         # path's threads never touch Python: bench_aedat.py times them)
        aedat4_fast.FAST = False
    except ImportError:                           # an older tree (--previous) has no fast path
        pass

    waited = [0.0]
    result = fb.Future.result

    def timed_result(self, timeout=None):        # the consumer blocks here while a worker is still fetching
        t = time.perf_counter()
        try:
            return result(self, timeout)
        finally:
            waited[0] += time.perf_counter() - t

    fb.Future.result = timed_result

    def read():
        n = 0
        with Aedat4Reader(path, threads=threads) as r:
            for ev in r.events():
                n += len(ev)
        return n

    read()
    rows = []
    for _ in range(reads):
        waited[0] = 0.0
        ru0 = resource.getrusage(resource.RUSAGE_SELF)
        w0, c0, m0 = time.perf_counter(), time.process_time(), time.thread_time()
        n = read()
        wall, cpu, main = time.perf_counter() - w0, time.process_time() - c0, time.thread_time() - m0
        ru1 = resource.getrusage(resource.RUSAGE_SELF)
        rows.append({"events": n, "wall_s": wall, "cpu_s": cpu, "consumer_cpu_s": main, "consumer_wait_s": waited[0],
                     "voluntary_switches": ru1.ru_nvcsw - ru0.ru_nvcsw,
                     "involuntary_switches": ru1.ru_nivcsw - ru0.ru_nivcsw})
    return {k: statistics.median(r[k] for r in rows) for k in rows[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file", nargs="?", help="AEDAT 4 file to read (required unless --child)")
    ap.add_argument("--previous", metavar="DIR", help="also probe the reader of an older ev3dgs tree in DIR "
                    "(default: none)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds (default 3)")
    ap.add_argument("--reads", type=int, default=5, help="timed reads per child process (default 5)")
    ap.add_argument("--json", default="tools/results/probe_aedat_threads.json",
                    help="output JSON (default %(default)s)")
    ap.add_argument("--child", nargs=3, metavar=("FILE", "THREADS", "READS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child[0], int(args.child[1]), int(args.child[2]))))
        return 0
    if not args.file:
        ap.error("FILE is required")
    trees = {"current": os.environ.get("PYTHONPATH", "")}
    if args.previous:
        trees["previous"] = os.path.abspath(args.previous)
    configs = [(tree, th) for tree in trees for th in (1, 2)]
    runs: dict = {c: [] for c in configs}
    for _ in range(args.rounds):
        for tree, th in configs:
            env = {**os.environ, "PYTHONPATH": trees[tree], "OMP_NUM_THREADS": "1"}
            out = subprocess.run([sys.executable, __file__, "--child", args.file, str(th), str(args.reads)],
                                 capture_output=True, text=True, env=env, check=True)
            runs[(tree, th)].append(json.loads(out.stdout))
    rows = []
    for (tree, th), rs in runs.items():
        row = {"reader": tree, "threads": th, **{k: statistics.median(r[k] for r in rs) for k in rs[0]},
               "wall_range_s": [min(r["wall_s"] for r in rs), max(r["wall_s"] for r in rs)]}
        rows.append(row)
        print(f"{tree:9s} threads={th}: wall {row['wall_s'] * 1e3:7.1f} ms  cpu {row['cpu_s'] * 1e3:7.1f} ms  "
              f"consumer cpu {row['consumer_cpu_s'] * 1e3:6.1f} ms, waiting {row['consumer_wait_s'] * 1e3:6.1f} ms  "
              f"switches {row['voluntary_switches']:.0f} vol / {row['involuntary_switches']:.0f} invol", flush=True)
    load = os.getloadavg()
    save_json(args.json, {"file": os.path.basename(args.file), "rounds": args.rounds, "reads": args.reads,
                          "cores": os.cpu_count(), "rows": rows}, f", load average {load[0]:.1f} at end")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
