"""Seeded mutation fuzzing of every reader: AEDAT 4.0 (the shared recording), AEDAT 3.1 and 2.0 (synthetic
files from the test fixture builders) and scene files (ev3dgs.schema.validate on a small valid scene).

Mutations: byte flips, truncation, duplicated / removed / zeroed byte ranges (and, for scenes, rewritten
attributes). Each case runs in a child process with a time limit and an address-space cap, and is classified:
  clean-error     our Ev3dgsError
  warning         data returned with a warning
  caught          the reader dropped a value the file contradicts (the warning says so)
  ok              data returned, no warning, every value within the file's stated bounds
  silent-garbage  a value the file itself contradicts (outside the sensor, time going back, outside the
                  packet table's time range) returned without a warning                    (must be 0)
  uncontradicted  a value differs from the intact file but nothing in the damaged file contradicts it
                  (AEDAT 2.0/3.1 state no time range: a flipped timestamp that stays in order is data)
  traceback       any other exception                                               (must be 0)
  hang            over the time limit (or killed for memory)

    python tools/bench/fuzz.py --seed 0 --cases 300 --json tools/results/fuzz.json
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SHARED = Path("/work/shared/data/aedat/aestream_davis.aedat4")
KINDS = ("flip", "truncate", "duplicate", "remove", "zero")
CLASSES = ("clean-error", "warning", "caught", "ok", "uncontradicted", "silent-garbage", "traceback", "hang")


def build_inputs(d: Path) -> dict[str, Path]:
    sys.path.insert(0, str(ROOT / "tests"))
    from test_aedat_legacy import build_aedat2, build_aedat3

    out = {}
    if SHARED.exists():
        out["aedat4"] = SHARED
    for name, build in (("aedat2", build_aedat2), ("aedat3", build_aedat3)):
        out[name] = d / f"clean.{name}"
        out[name].write_bytes(build()[0])
    out["scene"] = d / "clean.h5"
    _scene(out["scene"])
    return out


def _scene(path: Path) -> None:
    from ev3dgs import schema
    from ev3dgs.events import Events

    rng = np.random.default_rng(0)
    n, W, H = 2000, 32, 24
    ev = Events(np.sort(rng.integers(0, 100_000, n)).astype(np.int64), rng.integers(0, W, n).astype(np.uint16),
                rng.integers(0, H, n).astype(np.uint16), rng.choice(np.array([-1, 1], np.int8), n))
    K = np.array([[30.0, 0, (W - 1) / 2], [0, 30.0, (H - 1) / 2], [0, 0, 1]])
    poses = np.tile(np.eye(4), (2, 3, 1, 1))
    poses[:, :, 2, 3] = 3.0
    scene = schema.Scene(name="fuzz", source="synthetic", camera=schema.Camera(width=W, height=H, K=K,
                                                                                distortion=np.zeros(5)),
                         events=ev, sensor=schema.EventSensor(pos_threshold=0.2, neg_threshold=0.2),
                         train=schema.Train(images=rng.integers(0, 256, (2, H, W, 3), dtype=np.uint8),
                                            exposure=np.array([[0, 40_000], [50_000, 90_000]], np.int64),
                                            poses=poses, pose_t=np.array([[0, 20_000, 40_000],
                                                                          [50_000, 70_000, 90_000]], np.int64)))
    schema.write(scene, path)


def mutate(data: bytes, kind: str, rng: np.random.Generator, lo: int = 0) -> bytes:
    n = len(data)
    a = int(rng.integers(lo, n))
    ln = int(rng.choice([1, 4, 16, 64, 512, 4096]))
    b = min(n, a + ln)
    if kind == "flip":
        buf = bytearray(data)
        for _ in range(int(rng.integers(1, 4))):
            buf[int(rng.integers(lo, n))] ^= int(rng.integers(1, 256))
        return bytes(buf)
    if kind == "truncate":
        return data[:a]
    if kind == "duplicate":
        return data[:b] + data[a:b] + data[b:]
    if kind == "remove":
        return data[:a] + data[b:]
    return data[:a] + bytes(b - a) + data[b:]


# ---------------------------------------------------------------- child: read one file, check its bounds
def _child(fmt: str, path: str, clean: str) -> dict:
    from ev3dgs.errors import Ev3dgsError

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            if fmt == "scene":
                _read_scene(path)
                bad, other = "", ""
            else:
                bad, other = _read_recording(fmt, path, clean)
        except Ev3dgsError as e:
            return {"class": "clean-error", "detail": str(e)[:200]}
        except Exception as e:  # noqa: BLE001 - classified, not swallowed
            return {"class": "traceback", "detail": f"{type(e).__name__}: {e}"[:300]}
    msgs = [str(w.message) for w in caught]
    if bad:
        return {"class": "warning" if msgs else "silent-garbage", "detail": bad[:300]}
    dropped = any("dropped" in m or "skipped" in m or "duplicate" in m for m in msgs)
    if not msgs and other:
        return {"class": "uncontradicted", "detail": other[:300]}
    return {"class": "caught" if dropped else "warning" if msgs else "ok", "detail": (msgs or [""])[0][:200]}


def _bounds(fmt: str, clean: str):
    """(W, H, per-kind time range) that the intact file states."""
    from ev3dgs.io.recording import open_recording

    with open_recording(clean) as r:
        W, H = r.sensor_size()
        ev = np.concatenate([e.t for e in r.events()])
        rng = {"events": (int(ev.min()), int(ev.max()))}
        for k, get in (("imu", r.imu), ("triggers", r.triggers)):
            t = get().t
            rng[k] = (int(t.min()), int(t.max())) if len(t) else (0, -1)
        fr = [f.timestamp for f in r.frames()]
        rng["frames"] = (min(fr), max(fr)) if fr else (0, -1)
    return W, H, rng


def _read_recording(fmt: str, path: str, clean: str) -> tuple[str, str]:
    """Read everything; return (what the damaged file itself contradicts, what only differs from the intact
    file). Time ranges: AEDAT 4.0's packet table states each packet's range (a contradiction); AEDAT 2.0 and
    3.1 state none, so a timestamp outside the intact file's range but in order is only a difference."""
    from ev3dgs.io.recording import open_recording

    W, H, rng = _bounds(fmt, clean)
    problems, differ = [], []
    ranged = problems if fmt == "aedat4" else differ
    with open_recording(path) as r:
        kinds = {s.kind for s in r.streams()}
        last = None
        for e in (r.events() if "events" in kinds or fmt != "aedat4" else ()):
            if len(e) == 0:
                continue
            if e.x.max() >= W or e.y.max() >= H or not np.isin(e.p, (-1, 1)).all():
                problems.append("event x/y/p outside the sensor")
            if e.t.min() < rng["events"][0] or e.t.max() > rng["events"][1]:
                ranged.append(f"event t outside [{rng['events'][0]}, {rng['events'][1]}]")
            if (np.diff(e.t) < 0).any() or (last is not None and e.t[0] < last):
                problems.append("event t decreasing")
            last = int(e.t[-1])
        for k, get in (("imu", r.imu), ("triggers", r.triggers)):
            if k in kinds or fmt != "aedat4":
                t = get().t
                if len(t) and (np.diff(t) < 0).any():
                    problems.append(f"{k} t decreasing")
                if len(t) and (t.min() < rng[k][0] or t.max() > rng[k][1]):
                    ranged.append(f"{k} t outside the intact file's range")
        if "frames" in kinds or fmt != "aedat4":
            for f in r.frames():
                h, w = f.image.shape[:2]
                if f.position[0] + w > W or f.position[1] + h > H:
                    problems.append("frame outside the sensor")
                if not rng["frames"][0] <= f.timestamp <= rng["frames"][1]:
                    ranged.append("frame outside the intact file's time range")
        r.info()
    return "; ".join(dict.fromkeys(problems)), "; ".join(dict.fromkeys(differ))


def _read_scene(path: str) -> None:
    from ev3dgs import schema

    schema.validate(path)


def _run_case(fmt: str, path: Path, clean: Path, limit_s: float, mem_mb: int) -> dict:
    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (mem_mb << 20, mem_mb << 20))

    try:
        out = subprocess.run([sys.executable, __file__, "--child", fmt, str(path), str(clean)], capture_output=True,
                             text=True, timeout=limit_s, preexec_fn=cap, cwd=ROOT,
                             env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"})
    except subprocess.TimeoutExpired:
        return {"class": "hang", "detail": f"over {limit_s} s"}
    if out.returncode != 0 or not out.stdout.strip():
        kind = "hang" if out.returncode < 0 or "MemoryError" in out.stderr else "traceback"
        return {"class": kind, "detail": (out.stderr.strip().splitlines() or ["?"])[-1][:300]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ap.add_argument("--cases", type=int, default=300, help="mutated files in all, spread over the formats (default 300)")
    ap.add_argument("--json", help="write every case and the table here (default: no file)")
    ap.add_argument("--time-limit", type=float, default=60.0, help="seconds per case (default 60)")
    ap.add_argument("--mem-mb", type=int, default=3072, help="address-space cap per case in MiB (default 3072)")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(_child(*args.child)))
        return 0
    rng = np.random.default_rng(args.seed)
    rows = []
    with tempfile.TemporaryDirectory(prefix="ev3dgs_fuzz_") as d:
        inputs = build_inputs(Path(d))
        fmts = sorted(inputs)
        for c in range(args.cases):
            fmt, kind = fmts[c % len(fmts)], KINDS[int(rng.integers(len(KINDS)))]
            data = inputs[fmt].read_bytes()
            lo = 3126 if fmt == "aedat4" and rng.random() < 0.8 else 0     # mostly packets, sometimes the header
            p = Path(d) / f"case{c}{inputs[fmt].suffix}"
            p.write_bytes(mutate(data, kind, rng, lo))
            res = _run_case(fmt, p, inputs[fmt], args.time_limit, args.mem_mb)
            rows.append({"case": c, "format": fmt, "mutation": kind, **res})
            p.unlink()
            if res["class"] in ("silent-garbage", "traceback", "hang"):
                print(f"case {c} {fmt} {kind}: {res['class']}: {res['detail']}", file=sys.stderr)
    table = {f: Counter(r["class"] for r in rows if r["format"] == f) for f in sorted({r["format"] for r in rows})}
    print(f"{'format':8s} {'cases':>6s} " + " ".join(f"{c:>14s}" for c in CLASSES))
    for f, cnt in [*table.items(), ("all", Counter(r["class"] for r in rows))]:
        print(f"{f:8s} {sum(cnt.values()):6d} " + " ".join(f"{cnt.get(c, 0):14d}" for c in CLASSES))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"seed": args.seed, "cases": args.cases,
                                               "table": {f: dict(c) for f, c in table.items()}, "rows": rows},
                                              indent=1))
    bad = sum(1 for r in rows if r["class"] in ("silent-garbage", "traceback"))
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
