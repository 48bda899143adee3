import sys
from pathlib import Path
"""Which decompressors release the GIL (so that AEDAT 4 decoding threads can overlap)? A probe that works on a
loaded machine: while a worker thread makes one long decompression call, the main
thread runs a Python loop noting time stamps. If the call holds the GIL, the main thread makes no progress for
the whole call (largest gap ~ call duration); if it releases the GIL, the main thread keeps running (largest gap
~ an OS time slice or the 5 ms switch interval). 2 M events (32 MB) of event-like data, 3 calls each.

    python tools/investigations/probe_gil.py --json tools/results/probe_gil.json
"""
import argparse
import threading
import time

import cramjam
import lz4.frame
import numpy as np
import zstandard

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--json", default="tools/results/probe_gil.json", help="output JSON (default %(default)s)")
args = ap.parse_args()
rng = np.random.default_rng(0)
n = 2_000_000
ev = np.zeros(n, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1"), ("pad", "V3")])
ev["t"] = np.cumsum(rng.integers(0, 3, n))
ev["x"], ev["y"], ev["p"] = rng.integers(0, 346, n), rng.integers(0, 260, n), rng.integers(0, 2, n)
data = ev.tobytes()
c_lz4, c_zst = lz4.frame.compress(data), zstandard.ZstdCompressor(level=3).compress(data)
out = np.empty(len(data) + 1024, np.uint8)
calls = {
    "lz4.frame.decompress": lambda: lz4.frame.decompress(c_lz4),
    "cramjam.lz4.decompress_into": lambda: cramjam.lz4.decompress_into(c_lz4, out),
    "cramjam.zstd.decompress_into": lambda: cramjam.zstd.decompress_into(c_zst, out),
    "zstandard.decompress": lambda: zstandard.ZstdDecompressor().decompress(c_zst),
    "numpy strided copy": lambda: np.frombuffer(data, np.int64)[0::2].copy(),
    "python loop (control, holds the GIL)": lambda: sum(range(3_000_000)),
}
rows = []
for name, f in calls.items():
    res = []
    for rep in range(3):
        done, span = threading.Event(), []

        def work():
            a = time.perf_counter()
            f()
            span.append(time.perf_counter() - a)
            done.set()

        th = threading.Thread(target=work)
        stamps = [time.perf_counter()]
        th.start()
        while not done.is_set():
            stamps.append(time.perf_counter())
        th.join()
        res.append({"call_ms": span[0] * 1e3, "largest_gap_ms": float(np.max(np.diff(stamps))) * 1e3,
                    "main_thread_steps": len(stamps)})
    med = lambda k: float(np.median([r[k] for r in res]))   # noqa: E731
    releases = med("largest_gap_ms") < 0.5 * med("call_ms")
    rows.append({"call": name, "runs": res, "releases_gil": releases})
    print(f"{name:38s} call {med('call_ms'):6.1f} ms, main thread's largest gap {med('largest_gap_ms'):6.1f} ms: "
          f"{'releases' if releases else 'HOLDS'} the GIL")
save_json(args.json, {"rows": rows})
