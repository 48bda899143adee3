"""Seeded fuzzing of every reader and every writing command.

Reader classes (mutated files read in a child process with a time limit and an address-space cap):
  aedat4 / aedat3 / aedat2 / scene   byte flips, truncation, duplicated / removed / zeroed byte ranges of the
                                     shared AEDAT 4.0 recording, of AEDAT 3.1 and 2.0 files from the test fixture
                                     builders, and of a small valid scene (ev3dgs.schema.validate). Outcomes:
    clean-error     our Ev3dgsError
    warning         data returned with a warning
    caught          the reader dropped a value the file contradicts (the warning says so)
    ok              data returned, no warning, every value within the file's stated bounds
    uncontradicted  a value differs from the intact file but nothing in the damaged file contradicts it
                    (AEDAT 2.0/3.1 state no time range: a flipped timestamp that stays in order is data)
    silent-garbage  a value the file itself contradicts returned without a warning       (must be 0)
    traceback       any other exception                                                   (must be 0)
    hang            over the time limit (or killed for memory)                            (must be 0)
  aedat2-shift      1-7 bytes inserted or removed where an AEDAT 2.0 header ends (a third of the cases read
                    with strict=True). Passes: clean-error (strict must give this), realigned (a warning, and
                    every value plausible: each timestamp within the intact file's range of its kind, none over
                    2^33, no frame exposure ending before it starts, x/y on the sensor), ok (plausible, no
                    warning). Fails: garbage-warned, silent-garbage, strict-accepted, traceback, hang.
  aedat2-ts-flip    one bit (20-31) of one AEDAT 2.0 record's timestamp flipped. Passes: dropped (the record,
                    and at most FEW others, dropped with a warning; every value kept is the intact file's),
                    ok, uncontradicted (the flipped timestamp stays between its neighbours: it is data).
                    Fails: reset (read as a timestamp reset), kept-bad / silent-garbage (the bad timestamp or
                    another changed value kept), dropped-too-many, refused, traceback, hang.
  scene-plausible   a valid scene edited with h5py into an impossible one (fx tiny or huge, principal point
                    far outside the image, an exposure of 1e10-1e17 us, an event at t = 2^40..2^62, a damaged
                    compressed chunk in /test/images, /train/sharp or /train/images): `ev3dgs validate FILE` and
                    `ev3dgs train FILE` must both exit 2 with one `error:` line, train before it writes a model
                    and within TRAIN_REFUSE_S. Passes: refused, undetectable (damaged chunk bytes that still
                    decode: nothing to find). Fails: silent-garbage (validate or train accepted it), slow,
                    bad-message, traceback, hang.

  aedat2-midshift   1-7 bytes inserted or removed at a random offset inside an AEDAT 2.0 file's data (dense,
                    fixture and a DAVIS240C file with APS frames; a third read with strict=True). Passes:
                    clean-error (strict must give this), realigned (a warning, every value plausible as for
                    aedat2-shift, and at most FEW events that the intact file does not have). Fails: silent-garbage
                    (changed data without a warning), garbage-warned, strict-accepted, traceback, hang.
  config-hostile    a sensor TOML with one hostile value (1e300, 1e-300, 0, -1, inf, nan, text, ...) in one numeric
                    key, or a binary / deeply nested / bad-comment file, through `ev3dgs-sim events` and
                    `ev3dgs-sim compare` (and once `ev3dgs-sim make-dataset`, its render replaced by a trap) in a
                    child with a time limit and a 6 GiB address-space cap. Passes: refused (exit 2, one `error:`
                    line), completed (exit 0, the output there, a value inside its range). Fails: reached-render
                    (make-dataset got past the config), traceback, bad-message (e.g. a numpy overflow warning),
                    hang (over the limit or out of memory), crash.

Writer class (each command in a child process with a time limit):
  disk-full         every writing command (ev3dgs-sim events / blur, ev3dgs-ingest davis, ev3dgs train, eval,
                    render to .mp4 / .gif / a PNG folder, export .ply, export-dataset in each format, view --out
                    PNG) with its output on a tmpfs mounted for the case (needs root; skipped with the reason
                    when mount fails) whose free space is a seeded fraction (0-105 %) of what the output takes,
                    so the disk fills at different points; half the cases with the commands' up-front free-space
                    estimate switched off (another process filling the disk after the check). Passes:
    checked-first   exit 2, one `error:` line saying there is not enough free space, nothing written
    failed-cleanly  exit 2, one `error:` line (no traceback, no "Exception ignored", no libpng line), nothing
                    undecodable under a final name, no temporary (.NAME.tmp-*, .NAME.old-*) left
    completed       exit 0 and the complete output, every file readable
                    Fails: corrupt-output (a file under a final name that its reader cannot read: h5py and
                    schema.validate for .h5, cv2 frame count for .mp4, PIL for .gif/.png, plyfile for .ply,
                    torch.load, json, the AEDAT 4.0 reader with strict=True; or a folder built under a hidden
                    sibling that is there but incomplete), silent-garbage (exit 0 without the complete output),
                    temp-left, bad-message, crash (killed by a signal, e.g. a segfault, or an exit code
                    other than 0 and 2), traceback (a traceback or "Exception ignored" on stderr), hang. train and eval write into the run folder file by file (each file atomic):
                    there every file present must be readable.

Race class (two processes of one writer on the same output, the second started a seeded 0-1 s after the first):
  races             every disk-full writer plus `ev3dgs-sim calibrate` and `compare`. Passes: one-refused (one
                    exits 0 with the complete output, the other exits 2 with one line saying another ev3dgs
                    process writes it), refused-late (the second came after the first finished and was refused
                    because the output exists). Fails: lost-output (both exit 0: the first result replaced),
                    corrupt-output, no-output, temp-left (a temporary, a claim or a run lock left), bad-message,
                    crash, traceback, hang.

    python tools/bench/fuzz.py --seed 0 --json tools/results/fuzz.json
    python tools/bench/fuzz.py --classes disk-full --cases 2 --writers render-mp4,export-ply
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import resource
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SHARED = Path("/work/shared/data/aedat/aestream_davis.aedat4")
KINDS = ("flip", "truncate", "duplicate", "remove", "zero")
READER_CLASSES = ("aedat2", "aedat3", "aedat4", "scene")
NEW_CLASSES = ("disk-full", "aedat2-shift", "aedat2-ts-flip", "scene-plausible", "aedat2-midshift",
               "config-hostile")
NEW_CLASSES += ("races",)
ALL_CLASSES = READER_CLASSES + NEW_CLASSES
DEFAULT_CASES = {"aedat2": 100, "aedat3": 100, "aedat4": 100, "scene": 100, "disk-full": 112,
                 "aedat2-shift": 84, "aedat2-ts-flip": 84, "scene-plausible": 35, "aedat2-midshift": 84,
                 "config-hostile": 25}
PASS = {"aedat2-shift": ("clean-error", "realigned", "ok"),
        "aedat2-ts-flip": ("dropped", "ok", "uncontradicted"),
        "scene-plausible": ("refused", "undetectable"),
        "disk-full": ("checked-first", "failed-cleanly", "completed"),
        "aedat2-midshift": ("clean-error", "realigned"),
        "config-hostile": ("refused", "completed")}
PASS.update({c: ("clean-error", "warning", "caught", "ok", "uncontradicted") for c in READER_CLASSES})
SUMMARY = ("cases", "passed", "traceback", "crash", "hang", "corrupt-output", "silent-garbage", "warned-garbage",
           "other-failure")
# races (a section of its own): two writers of one output
DEFAULT_CASES["races"] = 34
PASS["races"] = ("one-refused", "refused-late")
SUMMARY = SUMMARY[:-1] + ("lost-output",) + SUMMARY[-1:]
FEW = 4                        # records a single flipped timestamp may cost besides its own
T_MAX = 2 ** 33                # no AEDAT 2.0 timestamp of a plausible read is above this (2.4 h past 2^32)
TRAIN_REFUSE_S = 30.0          # train must refuse an impossible scene within this (2 shared cores, torch import)
FAST = ["--iterations", "5", "--set", "init_points=500", "--threads", "1", "--set", "sh_degree=0",
        "--set", "checkpoint_every=5"]
ENTRY = {"ev3dgs": "ev3dgs.cli.main", "ev3dgs-sim": "ev3dgs.cli.sim", "ev3dgs-ingest": "ev3dgs.cli.ingest"}


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k != "EV3DGS_DEBUG"}
    env.update(PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return env


def _tests_path() -> None:
    if str(ROOT / "tests") not in sys.path:
        sys.path.insert(0, str(ROOT / "tests"))


# ================================================================ reader classes (the original mutations)
def build_inputs(d: Path) -> dict[str, Path]:
    _tests_path()
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


def _run_child(args: list[str], limit_s: float, mem_mb: int) -> dict:
    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (mem_mb << 20, mem_mb << 20))

    try:
        out = subprocess.run([sys.executable, __file__, "--child", *args], capture_output=True, text=True,
                             timeout=limit_s, preexec_fn=cap, cwd=ROOT, env=_env())
    except subprocess.TimeoutExpired:
        return {"class": "hang", "detail": f"over {limit_s} s"}
    if out.returncode != 0 or not out.stdout.strip():
        kind = "hang" if out.returncode < 0 or "MemoryError" in out.stderr else "traceback"
        return {"class": kind, "detail": (out.stderr.strip().splitlines() or ["?"])[-1][:300]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_readers(fmt: str, n: int, rng: np.random.Generator, d: Path, inputs: dict, args) -> list[dict]:
    rows = []
    data = inputs[fmt].read_bytes()
    for c in range(n):
        kind = KINDS[int(rng.integers(len(KINDS)))]
        lo = 3126 if fmt == "aedat4" and rng.random() < 0.8 else 0     # mostly packets, sometimes the header
        p = d / f"case{c}{inputs[fmt].suffix}"
        p.write_bytes(mutate(data, kind, rng, lo))
        res = _run_child([fmt, str(p), str(inputs[fmt])], args.time_limit, args.mem_mb)
        rows.append({"case": c, "mutation": kind, "outcome": res.pop("class"), **res})
        p.unlink()
    return rows


# ================================================================ AEDAT 2.0: header/data shifts, timestamp flips
def build_dense_aedat2(seed: int = 0, n: int = 6000) -> bytes:
    """A DVS-only-like AEDAT 2.0 file at a realistic event rate (0-40 us apart), with an IMU sample every 1000
    records and four triggers: what a single flipped timestamp bit stands out from."""
    _tests_path()
    from test_aedat_legacy import A2_HEADER, a2_dvs, a2_imu

    rng = np.random.default_rng(seed)
    t, recs = 5_000_000, []
    for i in range(n):
        t += int(rng.integers(0, 40))
        recs.append((a2_dvs(int(rng.integers(0, 346)), int(rng.integers(0, 260)), int(rng.integers(0, 2))), t))
        if i % 1000 == 500:
            t += 3
            recs += [(a2_imu(k, int(v)), t) for k, v in enumerate(rng.integers(-30000, 30000, 7))]
        if i % 1500 == 700:
            t += 2
            recs.append(((1 << 10) | 2, t))
    return A2_HEADER + b"".join(struct.pack(">II", a, ts % 2 ** 32) for a, ts in recs)


def _a2_data_start(data: bytes) -> int:
    end = b"#End Of ASCII Header\r\n"
    return data.index(end) + len(end)


def _a2_times(data: bytes) -> np.ndarray:
    """Every record's timestamp, unwrapped over 2^32 (the intact files wrap at most forward)."""
    raw = np.frombuffer(data[_a2_data_start(data):], ">u4")[1::2].astype(np.int64)
    wraps = np.concatenate([[0], np.cumsum(np.diff(raw) < -(2 ** 31))])
    return raw + (wraps << 32)


def _read_a2(path: str, strict: bool) -> dict:
    """Everything a read returns: events (t, x, y, p), frames' times, imu and trigger t; sensor size."""
    from ev3dgs.io.recording import open_recording

    with open_recording(path, strict=strict) as r:
        W, H = r.sensor_size()
        evs = [e for e in r.events() if len(e)]
        ev = (np.stack([np.concatenate([getattr(e, k).astype(np.int64) for e in evs]) for k in "txyp"], 1)
              if evs else np.zeros((0, 4), np.int64))
        frames = [(f.timestamp, f.exposure_start, f.exposure_end, f.frame_start, f.frame_end) for f in r.frames()]
        out = {"W": W, "H": H, "ev": ev, "frames": np.array(frames, np.int64).reshape(-1, 5),
               "imu": np.asarray(r.imu().t, np.int64), "triggers": np.asarray(r.triggers().t, np.int64)}
        r.info()
    return out


def _plausible(got: dict, ref: dict) -> str:
    """What in `got` no intact read could give: '' when every value is plausible."""
    bad = []
    ev, W, H = got["ev"], ref["W"], ref["H"]
    rng = {k: (int(v.min()), int(v.max())) if v.size else None
           for k, v in (("ev", ref["ev"][:, 0]), ("frames", ref["frames"]), ("imu", ref["imu"]),
                        ("triggers", ref["triggers"]))}
    if len(ev):
        if ev[:, 0].max() > T_MAX:
            bad.append(f"event t = {ev[:, 0].max()} > 2^33")
        lo, hi = rng["ev"]
        if ev[:, 0].min() < lo or ev[:, 0].max() > hi:
            bad.append(f"event t {ev[:, 0].min()}..{ev[:, 0].max()} outside the intact {lo}..{hi}")
        if (ev[:, 1] >= W).any() or (ev[:, 2] >= H).any() or (ev[:, 1] < 0).any() or (ev[:, 2] < 0).any():
            bad.append("event x/y outside the sensor")
        if (np.diff(ev[:, 0]) < 0).any():
            bad.append("event t decreasing")
    for k in ("frames", "imu", "triggers"):
        v = got[k]
        if not v.size:
            continue
        if v.max() > T_MAX:
            bad.append(f"{k} t = {v.max()} > 2^33")
        lo, hi = rng[k] if rng[k] else (rng["ev"][0] if rng["ev"] else 0, rng["ev"][1] if rng["ev"] else -1)
        if v.min() < lo or v.max() > hi:
            bad.append(f"{k} t {v.min()}..{v.max()} outside the intact {lo}..{hi}")
    fr = got["frames"]
    if len(fr) and ((fr[:, 2] < fr[:, 1]) | (fr[:, 4] < fr[:, 3])).any():
        bad.append("a frame whose exposure or readout ends before it starts")
    return "; ".join(bad)


def _child_a2(mode: str, path: str, clean: str, spec: str) -> dict:
    from ev3dgs.errors import Ev3dgsError

    spec = json.loads(spec)
    ref = _read_a2(clean, False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            got = _read_a2(path, spec.get("strict", False))
        except Ev3dgsError as e:
            if mode == "aedat2-ts-flip":
                return {"class": "refused", "detail": str(e)[:300]}
            return {"class": "clean-error", "detail": str(e)[:300]}
        except Exception as e:  # noqa: BLE001 - classified, not swallowed
            return {"class": "traceback", "detail": f"{type(e).__name__}: {e}"[:300]}
    msgs = [str(w.message) for w in caught]
    first = (msgs or [""])[0][:300]
    if mode in ("aedat2-shift", "aedat2-midshift"):
        bad = _plausible(got, ref)
        if spec.get("strict"):
            return {"class": "strict-accepted", "detail": (bad or first or "data returned")[:300]}
        if not bad and mode == "aedat2-midshift":
            extra = Counter(map(tuple, got["ev"].tolist()))
            extra.subtract(Counter(map(tuple, ref["ev"].tolist())))
            n_extra = sum(v for v in extra.values() if v > 0)
            if n_extra > FEW:
                bad = f"{n_extra} events that the intact file does not have"
            elif not msgs:
                bad = "the data changed without a warning"
        if bad:
            return {"class": "garbage-warned" if msgs else "silent-garbage", "detail": bad[:300]}
        return {"class": "realigned" if msgs else "ok", "detail": first}
    # one flipped timestamp: the read may drop it (and a few more) but keep nothing that was not in the file
    if any("timestamp reset" in m for m in msgs):
        return {"class": "reset", "detail": next(m for m in msgs if "timestamp reset" in m)[:300]}
    have = Counter(map(tuple, ref["ev"].tolist()))
    extra = Counter(map(tuple, got["ev"].tolist()))
    extra.subtract(have)
    extra = [k for k, v in extra.items() if v > 0]
    missing = len(ref["ev"]) - (len(got["ev"]) - len(extra))
    new_t = spec["new_t"]
    if extra and not (spec["in_order"] and len(extra) == 1 and extra[0][0] == new_t):
        return {"class": "kept-bad" if msgs else "silent-garbage",
                "detail": f"{len(extra)} events not in the intact file, e.g. t = {extra[0][0]}"[:300]}
    others = _plausible({**got, "ev": np.zeros((0, 4), np.int64)}, ref)
    if others:
        return {"class": "kept-bad" if msgs else "silent-garbage", "detail": others[:300]}
    n_frames, n_imu = len(ref["frames"]) - len(got["frames"]), len(ref["imu"]) - len(got["imu"])
    if missing > 1 + FEW or n_frames > 1 or n_imu > 1 or len(ref["triggers"]) - len(got["triggers"]) > 1:
        return {"class": "dropped-too-many",
                "detail": f"{missing} events, {n_frames} frames, {n_imu} IMU samples dropped; {first}"[:300]}
    if extra:
        return {"class": "uncontradicted", "detail": f"t = {new_t} kept between its neighbours"}
    if missing or n_frames or n_imu or msgs:
        return {"class": "dropped" if msgs else "silent-garbage",
                "detail": (first or f"{missing} events dropped without a warning")[:300]}
    return {"class": "ok", "detail": ""}


def a2_files(d: Path) -> dict[str, Path]:
    _tests_path()
    from test_aedat_legacy import build_aedat2

    files = {"dense": d / "dense.aedat", "fixture": d / "fixture.aedat"}
    files["dense"].write_bytes(build_dense_aedat2())
    files["fixture"].write_bytes(build_aedat2()[0])
    return files


def _a2_shift_rows(mode: str, n: int, rng: np.random.Generator, d: Path, files: dict, args, pick_at,
                   fill) -> list[dict]:
    """The cases of an AEDAT 2.0 shift class: per case one file (round robin), ``pick_at(data)`` the byte
    where 1-7 bytes are inserted (``fill(k)``) or removed, strict one time in three; checked by child ``mode``."""
    rows = []
    names = sorted(files)
    for c in range(n):
        which = names[c % len(names)]
        data = files[which].read_bytes()
        at = pick_at(data)
        k = int(rng.integers(1, 8))
        op = "insert" if rng.random() < 0.5 else "remove"
        strict = bool(rng.random() < 1 / 3)
        mutated = data[:at] + fill(k) + data[at:] if op == "insert" else data[:at] + data[at + k:]
        p = d / f"{mode.removeprefix('aedat2-')}{c}.aedat"
        p.write_bytes(mutated)
        res = _run_child([mode, str(p), str(files[which]), json.dumps({"strict": strict})],
                         args.time_limit, args.mem_mb)
        rows.append({"case": c, "file": which, "mutation": f"{op} {k} bytes at byte {at}", "strict": strict,
                     "outcome": res.pop("class"), **res})
        p.unlink()
    return rows


def run_a2_shift(n: int, rng: np.random.Generator, d: Path, files: dict, args) -> list[dict]:
    """Bytes inserted (random, or zeros three times in ten) or removed where the header ends."""
    def fill(k: int) -> bytes:
        return rng.integers(0, 256, k, dtype=np.uint8).tobytes() if rng.random() < 0.7 else bytes(k)

    return _a2_shift_rows("aedat2-shift", n, rng, d, files, args, _a2_data_start, fill)


def run_a2_flip(n: int, rng: np.random.Generator, d: Path, files: dict, args) -> list[dict]:
    rows = []
    for c in range(n):
        which = "fixture" if c % 3 == 2 else "dense"
        data = files[which].read_bytes()
        at = _a2_data_start(data)
        times = _a2_times(data)
        i = int(rng.integers(len(times)))
        bit = int(rng.integers(20, 32))
        off = at + 8 * i + 4
        raw = int.from_bytes(data[off:off + 4], "big")
        new_raw = raw ^ (1 << bit)
        new_t = int(times[i] + new_raw - raw)
        prev_t = int(times[i - 1]) if i > 0 else None
        next_t = int(times[i + 1]) if i + 1 < len(times) else None
        in_order = (prev_t is None or prev_t <= new_t) and (next_t is None or new_t <= next_t)
        mutated = data[:off] + new_raw.to_bytes(4, "big") + data[off + 4:]
        p = d / f"flip{c}.aedat"
        p.write_bytes(mutated)
        res = _run_child(["aedat2-ts-flip", str(p), str(files[which]),
                          json.dumps({"new_t": new_t, "in_order": in_order})], args.time_limit, args.mem_mb)
        rows.append({"case": c, "file": which, "mutation": f"record {i} (byte {off}) timestamp bit {bit}: "
                     f"{int(times[i])} -> {new_t} us", "in_order": in_order, "outcome": res.pop("class"), **res})
        p.unlink()
    return rows


# ================================================================ commands: helpers shared by the last two classes
def _cli(mode: str, entry: str, argv: list[str]) -> int:
    """Run one console script in this process (the child of a case); mode 'no-estimate' switches off the
    commands' up-front free-space check, as when another process fills the disk after it; mode 'no-render'
    lets make-dataset past its Blender check and makes its render entry exit 99 (reached)."""
    if mode == "no-render":
        from ev3dgs.cli import sim as sim_cli
        from ev3dgs.sim import dataset

        sim_cli.require_blender = lambda command: None

        def trap(*a, **k):
            os._exit(99)

        dataset.make_dataset = trap
    if mode == "no-estimate":
        from ev3dgs import outputs

        outputs._check_space = lambda *a, **k: None
    sys.argv = [entry, *argv]
    return importlib.import_module(ENTRY[entry]).main()


def _command(mode: str, entry: str, argv: list, limit_s: float) -> dict:
    """Run a console script in a child process: rc (None = over the limit), stderr, seconds."""
    t0 = time.perf_counter()
    try:
        out = subprocess.run([sys.executable, __file__, "--cli", mode, entry, *map(str, argv)], capture_output=True,
                             text=True, timeout=limit_s, cwd=ROOT, env=_env(), stdin=subprocess.DEVNULL)
        rc, err = out.returncode, out.stderr
    except subprocess.TimeoutExpired as e:
        rc, err = None, (e.stderr.decode(errors="replace") if isinstance(e.stderr, bytes) else e.stderr or "")
    return {"rc": rc, "stderr": err, "seconds": round(time.perf_counter() - t0, 2)}


def _stderr_problem(err: str, failed: bool) -> tuple[str, str]:
    """(outcome, detail) for a stderr that breaks the one-line rule, else ('', '')."""
    if "Traceback" in err or "Exception ignored" in err:
        return "traceback", err.strip().splitlines()[-1][:300] if err.strip() else ""
    lines = err.strip("\n").splitlines()
    errors = [ln for ln in lines if ln.startswith("error: ")]
    others = [ln for ln in lines if not ln.startswith(("error: ", "warning: "))]
    if others or (failed and len(errors) != 1) or (not failed and errors) or "libpng" in err:
        return "bad-message", " | ".join(lines)[:300]
    return "", ""


# ================================================================ disk-full: every writer on a small tmpfs
PAGE = 4096


def _mount(where: Path, size: int) -> str:
    where.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={max(PAGE, size) // 1024}k", "tmpfs", str(where)],
                       capture_output=True, text=True)
    return "" if r.returncode == 0 else (r.stderr or r.stdout).strip() or f"mount exit {r.returncode}"


def _remount(where: Path, size: int) -> None:
    subprocess.run(["mount", "-o", f"remount,size={max(PAGE, size) // 1024}k", str(where)], check=True,
                   capture_output=True)


def _umount(where: Path) -> None:
    if subprocess.run(["umount", str(where)], capture_output=True).returncode != 0:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)
    shutil.rmtree(where, ignore_errors=True)


def mount_reason(d: Path) -> str:
    """'' when a tmpfs can be mounted here, else why not."""
    m = d / "probe-mount"
    why = _mount(m, 64 << 10)
    if not why:
        _umount(m)
    else:
        shutil.rmtree(m, ignore_errors=True)
    return why


def _make_recording(path: Path) -> None:
    """A 64x48 AEDAT 4.0 file: 30,000 events and 6 APS frames (ingest davis input)."""
    from ev3dgs.events import Events
    from ev3dgs.io.aedat4.writer import write_aedat4
    from ev3dgs.io.types import FrameData

    rng = np.random.default_rng(0)
    n = 30_000
    t = 1_000_000 + 20 * np.arange(n, dtype=np.int64)
    ev = Events(t, rng.integers(0, 64, n).astype(np.uint16), rng.integers(0, 48, n).astype(np.uint16),
                rng.choice(np.array([-1, 1], np.int8), n))
    frames = [FrameData(timestamp=s, exposure_start=s, exposure_end=s + 10_000, frame_start=s - 500,
                        frame_end=s + 10_500, image=rng.integers(0, 256, (48, 64), dtype=np.uint8))
              for s in range(1_040_000, 1_560_000, 90_000)]
    write_aedat4(path, 64, 48, ev, frames, None)


def tiny_scene(d: Path, cache: dict) -> str:
    """tests/test_cli_uniform.make_scene, made once per fuzz run: 4 shaky views (sub-frame poses), 2 test views,
    32x24, events simulated, sharp ground truth; trains in seconds with FAST."""
    if "scene" not in cache:
        _tests_path()
        from test_cli_uniform import make_scene

        (d / "inputs").mkdir(exist_ok=True)
        cache["scene"] = make_scene(d / "inputs" / "tiny.h5")
    return cache["scene"]


def prepare_commands(d: Path, limit_s: float, cache: dict, need_run: bool) -> dict:
    """Inputs of every writer, made once: the tiny scene, a run trained on it for 5 iterations (when a writer
    reads a run), frames for the simulator, a small AEDAT 4.0 recording."""
    scene = tiny_scene(d, cache)
    inp = d / "inputs"
    rng = np.random.default_rng(1)
    np.savez(inp / "frames.npz", frames=rng.uniform(0.1, 1.0, (6, 48, 64)).astype(np.float32),
             t_us=np.arange(6, dtype=np.int64) * 1000)
    np.savez(inp / "sub.npz", frames=rng.uniform(0, 1, (3, 120, 160, 3)))
    _make_recording(inp / "rec.aedat4")
    run = inp / "run"
    if need_run:
        r = _command("estimate", "ev3dgs", ["train", scene, "--out", run, *FAST, "--quiet"], limit_s)
        if r["rc"] != 0:
            raise RuntimeError(f"training the fuzz run failed: {r['stderr'][-2000:]}")
    return {"scene": scene, "inp": inp, "run": run}


def writers(p: dict) -> dict:
    """name -> (entry, argv builder(out folder) , output name, layout). Layout: 'file'; 'folder' (built under a
    hidden sibling: there complete or not at all); 'run' (written file by file in place: every file readable)."""
    inp, scene, run = p["inp"], p["scene"], p["run"]
    w = {
        "sim-events": ("ev3dgs-sim", lambda o: ["events", inp / "frames.npz", "--out", o / "ev.h5"], "ev.h5", "file"),
        "sim-blur": ("ev3dgs-sim", lambda o: ["blur", inp / "sub.npz", "--out", o / "blur.png"], "blur.png", "file"),
        "ingest-davis": ("ev3dgs-ingest", lambda o: ["davis", inp / "rec.aedat4", "--no-poses", "--out", o / "davis.h5"],
                         "davis.h5", "file"),
        "train": ("ev3dgs", lambda o: ["train", scene, "--out", o / "run", *FAST], "run", "run"),
        "eval": ("ev3dgs", lambda o: ["eval", o / "run", "--scene", scene], "run", "run"),
        "render-mp4": ("ev3dgs", lambda o: ["render", run, "--out", o / "o.mp4", "--frames", "24", "--size", "128x96"],
                       "o.mp4", "file"),
        "render-gif": ("ev3dgs", lambda o: ["render", run, "--out", o / "o.gif", "--frames", "24", "--size", "128x96"],
                       "o.gif", "file"),
        "render-png": ("ev3dgs", lambda o: ["render", run, "--out", o / "frames", "--frames", "24", "--size", "128x96"],
                       "frames", "folder"),
        "export-ply": ("ev3dgs", lambda o: ["export", run, "--out", o / "m.ply"], "m.ply", "file"),
        "view-png": ("ev3dgs", lambda o: ["view", run, "--out", o / "fig.png"], "fig.png", "file"),
    }
    for fmt in ("e2nerf", "events-h5", "aedat4", "transforms"):
        w[f"export-dataset-{fmt}"] = ("ev3dgs", lambda o, fmt=fmt: ["export-dataset", scene, "--format", fmt,
                                                                     "--out", o / "ds"], "ds", "folder")
    return w


WRITERS = tuple(writers({"inp": Path(), "scene": "", "run": Path()}))


def _setup(name: str, mnt: Path, p: dict) -> None:
    if name == "eval":                  # eval writes into the run folder: the run lives on the small disk
        shutil.copytree(p["run"], mnt / "run")


# ---------------------------------------------------------------- reading back what a writer left
def _decode(path: Path) -> str:
    """'' when the file reads back whole with the reader its type calls for, else why not."""
    suf = path.suffix.lower()
    try:
        if suf in (".h5", ".hdf5"):
            import h5py

            with h5py.File(path, "r") as f:
                scene = "camera" in f or "events" in f and "sensor" in f
                f.visititems(lambda n, o: o[()] if isinstance(o, h5py.Dataset) else None)
            if scene:
                from ev3dgs import schema

                schema.validate(str(path), require_complete=False, warn=False, read_data=True)
        elif suf in (".png", ".gif", ".jpg", ".jpeg"):
            from PIL import Image, ImageSequence

            n = 0
            with Image.open(path) as im:
                for fr in ImageSequence.Iterator(im):
                    fr.load()
                    n += 1
            if n < 1:
                return "no image"
        elif suf == ".mp4":
            n = _mp4_frames(path)
            if n < 1:
                return "0 decodable frames"
        elif suf == ".ply":
            from plyfile import PlyData

            ply = PlyData.read(str(path))
            if not len(ply["vertex"].data):
                return "no vertices"
        elif suf in (".pt", ".pth"):
            import torch

            torch.load(path, map_location="cpu", weights_only=False)
        elif suf == ".json":
            json.loads(path.read_text())
        elif suf == ".jsonl":
            for ln in path.read_text().splitlines():
                json.loads(ln)
        elif suf in (".npy", ".npz"):
            z = np.load(path, allow_pickle=False)
            if suf == ".npz":
                for k in z.files:
                    z[k]
        elif suf == ".aedat4":
            from ev3dgs.io.recording import open_recording

            with warnings.catch_warnings():
                warnings.simplefilter("error")
                with open_recording(path, strict=True) as r:
                    for _ in r.events():
                        pass
                    list(r.frames())
        elif suf in (".txt", ".md", ".csv", ""):
            path.read_text()
    except Exception as e:  # noqa: BLE001 - any failure to read back is the finding
        return f"{type(e).__name__}: {e}"[:200]
    return ""


def _mp4_frames(path: Path) -> int:
    import cv2

    cap = cv2.VideoCapture(str(path))
    n = 0
    try:
        while cap.isOpened():
            ok, _ = cap.read()
            if not ok:
                break
            n += 1
    finally:
        cap.release()
    return n


def _frames_of(path: Path) -> int | None:
    suf = path.suffix.lower()
    if suf == ".mp4":
        return _mp4_frames(path)
    if suf == ".gif":
        from PIL import Image

        with Image.open(path) as im:
            return getattr(im, "n_frames", 1)
    return None


def _listing(root: Path) -> dict[str, int]:
    """relative path -> size of every file under root (root itself when it is a file)."""
    if root.is_file():
        return {".": root.stat().st_size}
    return {str(q.relative_to(root)): q.stat().st_size for q in sorted(root.rglob("*")) if q.is_file()}


def _hidden(mnt: Path, before: set[str]) -> list[str]:
    return sorted(str(q.relative_to(mnt)) for q in mnt.rglob(".*") if str(q.relative_to(mnt)) not in before)


def _check_output(out: Path, layout: str, ref: dict | None) -> tuple[str, str]:
    """('', '') or ('corrupt-output', why) for what lies under the final name; ref = the complete output."""
    if not out.exists():
        return "", ""
    files = [out] if out.is_file() else [q for q in sorted(out.rglob("*")) if q.is_file()]
    for q in files:
        why = _decode(q)
        if why:
            return "corrupt-output", f"{q.name}: {why}"
    if ref is not None and layout in ("file", "folder"):
        got = set(_listing(out))
        if got != set(ref["files"]):
            return "corrupt-output", f"incomplete: {len(got)} of {len(ref['files'])} files under the final name"
        if layout == "file" and ref.get("frames") is not None and _frames_of(out) != ref["frames"]:
            return "corrupt-output", f"{_frames_of(out)} of {ref['frames']} frames"
    return "", ""


def _disk_case(name: str, spec: tuple, p: dict, mnt: Path, size: int | None, mode: str, ref: dict | None,
               limit_s: float) -> dict:
    """Run writer `name` with its output on a fresh tmpfs with `size` bytes free (None: plenty)."""
    entry, argv, out_name, layout = spec
    why = _mount(mnt, 256 << 20)
    if why:
        return {"outcome": "hang", "detail": f"mount failed: {why}"}
    try:
        _setup(name, mnt, p)
        used0 = shutil.disk_usage(mnt).used
        before = {str(q.relative_to(mnt)) for q in mnt.rglob(".*")}
        if size is not None:
            _remount(mnt, used0 + size)
        r = _command(mode, entry, argv(mnt), limit_s)
        out = mnt / out_name
        res = {"rc": r["rc"], "seconds": r["seconds"], "stderr": r["stderr"].strip()[-1500:],
               "used": shutil.disk_usage(mnt).used - used0}
        if r["rc"] is None:
            return {**res, "outcome": "hang", "detail": f"over {limit_s} s"}
        if r["rc"] < 0 and ref is not None:
            return {**res, "outcome": "crash", "detail": f"killed by signal {-r['rc']}: "
                    f"{' | '.join(r['stderr'].strip().splitlines()[-3:])}"[:400]}
        kind, why = _stderr_problem(r["stderr"], r["rc"] != 0)
        if kind == "traceback":
            return {**res, "outcome": kind, "detail": why}
        bad, detail = _check_output(out, layout, ref)
        if ref is None:                                          # the reference run: the complete output
            res.update(files=_listing(out) if out.exists() else {},
                       frames=_frames_of(out) if out.is_file() else None)
            if r["rc"] != 0 or bad or kind:
                return {**res, "outcome": "reference-failed", "detail": detail or why or r["stderr"][-300:]}
            return {**res, "outcome": "completed", "detail": ""}
        if bad:
            return {**res, "outcome": bad, "detail": detail}
        if r["rc"] not in (0, 2):
            return {**res, "outcome": "crash", "detail": f"exit {r['rc']}: {r['stderr'].strip()[-200:]}"}
        if kind:
            return {**res, "outcome": kind, "detail": why}
        left = _hidden(mnt, before)
        if left:
            return {**res, "outcome": "temp-left", "detail": ", ".join(left)[:300]}
        if r["rc"] == 0:
            if not out.exists() or (layout != "run" and set(_listing(out)) != set(ref["files"])):
                return {**res, "outcome": "silent-garbage", "detail": "exit 0 without the complete output"}
            return {**res, "outcome": "completed", "detail": ""}
        err = r["stderr"].strip().splitlines()[-1]
        if "not enough free space" in err:
            if out.exists() and layout != "run":
                return {**res, "outcome": "bad-message", "detail": "refused up front but wrote an output"}
            return {**res, "outcome": "checked-first", "detail": err[:300]}
        return {**res, "outcome": "failed-cleanly", "detail": err[:300]}
    finally:
        _umount(mnt)


def run_disk_full(n: int, rng: np.random.Generator, d: Path, args, only: list[str] | None,
                  cache: dict) -> tuple[list, dict]:
    why = mount_reason(d)
    if why:
        return [], {"skipped": f"cannot mount a tmpfs ({why}); run as root on a kernel that allows tmpfs mounts"}
    names = [k for k in WRITERS if only is None or k in only]
    if not names:
        raise SystemExit(f"--writers: none of {only} is a writer ({', '.join(WRITERS)})")
    need_run = any(k.startswith(("eval", "render", "export-ply", "view")) for k in names)
    p = prepare_commands(d, args.cmd_time_limit, cache, need_run)
    ws = writers(p)
    refs, meta = {}, {}
    for k, name in enumerate(names):
        ref = _disk_case(name, ws[name], p, d / f"ref{k}", None, "estimate", None, args.cmd_time_limit)
        if ref["outcome"] != "completed":
            raise RuntimeError(f"{name}: the run with room to spare failed: {ref['detail']}")
        refs[name] = ref
        meta[name] = {"output_bytes_on_tmpfs": ref["used"], "files": len(ref["files"]), "seconds": ref["seconds"]}
    rows = []
    per = {name: [c for c in range(n) if names[c % len(names)] == name] for name in names}
    fracs = {}
    for name, cases in per.items():         # stratified: each writer's disk fills at spread-out points
        m = max(1, (len(cases) + 1) // 2)
        f = [(j + rng.random()) / m * 1.05 for j in range(m)]
        fracs[name] = [f[j // 2] for j in range(len(cases))]
    for c in range(n):
        name = names[c % len(names)]
        j = per[name].index(c)
        mode = "estimate" if j % 2 == 0 else "no-estimate"
        size = max(PAGE, int(np.ceil(fracs[name][j] * refs[name]["used"] / PAGE)) * PAGE)
        res = _disk_case(name, ws[name], p, d / f"mnt{c}", size, mode, refs[name], args.cmd_time_limit)
        res.pop("files", None), res.pop("frames", None)
        rows.append({"case": c, "writer": name, "mode": mode, "free_bytes": size,
                     "fraction_of_output": round(size / max(1, refs[name]["used"]), 3), **res})
    return rows, {"writers": meta}


# ================================================================ scene plausibility
SCENE_EDITS = ("fx-tiny", "fx-huge", "principal-point", "exposure", "event-t", "chunk-test-images",
               "chunk-train-sharp")


def _edit_scene(path: Path, kind: str, rng: np.random.Generator) -> str:
    """Make the scene at `path` impossible; returns what was done."""
    import h5py

    if kind.startswith("chunk-"):
        ds = {"chunk-test-images": "/test/images", "chunk-train-sharp": "/train/sharp"}[kind]
        if rng.random() < 0.25:
            ds = "/train/images"
        with h5py.File(path, "r") as f:
            d = f[ds]
            i = int(rng.integers(d.id.get_num_chunks()))
            info = d.id.get_chunk_info(i)
        n = int(rng.choice([4, 16, 64]))
        at = info.byte_offset + int(rng.integers(0, max(1, info.size - n)))
        with open(path, "r+b") as fh:
            fh.seek(at)
            fh.write(rng.integers(0, 256, n, dtype=np.uint8).tobytes())
        return f"{ds} chunk {i}: {n} random bytes at byte {at}"
    with h5py.File(path, "r+") as f:
        W, H = int(f["camera"].attrs["width"]), int(f["camera"].attrs["height"])
        K = f["/camera/K"][()]
        if kind in ("fx-tiny", "fx-huge"):
            v = 10 ** (rng.uniform(-12, -3) if kind == "fx-tiny" else rng.uniform(7, 15))
            which = [(0, 0)], [(1, 1)], [(0, 0), (1, 1)]
            ij = which[int(rng.integers(3))]
            for a, b in ij:
                K[a, b] = v
            f["/camera/K"][...] = K
            return f"{'/'.join('fx' if a == 0 else 'fy' for a, _ in ij)} = {v:.3g} px"
        if kind == "principal-point":
            axis = int(rng.integers(2))
            size = W if axis == 0 else H
            off = size * 10 ** rng.uniform(0.5, 7)
            v = -off if rng.random() < 0.5 else size + off
            K[axis, 2] = v
            f["/camera/K"][...] = K
            return f"{'cx' if axis == 0 else 'cy'} = {v:.3g} px in a {W}x{H} image"
        if kind == "exposure":
            e = f["/train/exposure"][()]
            v = int(rng.integers(len(e)))
            length = int(10 ** rng.uniform(10, 17))
            e[v, 1] = e[v, 0] + length
            f["/train/exposure"][...] = e
            pt = f["/train/pose_t"][()]                  # pose samples stay inside their exposure
            pt[v] = np.linspace(e[v, 0], e[v, 1], pt.shape[1]).astype(np.int64)
            f["/train/pose_t"][...] = pt
            return f"view {v} exposed for {length:.3g} us"
        t = f["/events/t"][()]
        v = int(2 ** rng.uniform(40, 62))
        t[-1] = v
        f["/events/t"][...] = t
        return f"last event at t = {v}"


def _chunk_readable(path: Path, what: str) -> bool:
    import h5py

    ds = what.split(" ", 1)[0]
    try:
        with h5py.File(path, "r") as f:
            f[ds][()]
        return True
    except Exception:  # noqa: BLE001
        return False


def run_scene_plausible(n: int, rng: np.random.Generator, d: Path, args, cache: dict) -> list[dict]:
    scene = tiny_scene(d, cache)
    rows = []
    for c in range(n):
        kind = SCENE_EDITS[c % len(SCENE_EDITS)]
        p = d / f"implausible{c}.h5"
        shutil.copyfile(scene, p)
        what = _edit_scene(p, kind, rng)
        row = {"case": c, "mutation": kind, "edit": what}
        if kind.startswith("chunk-") and _chunk_readable(p, what):
            rows.append({**row, "outcome": "undetectable", "detail": "the damaged chunk still decodes"})
            p.unlink()
            continue
        v = _command("estimate", "ev3dgs", ["validate", p], args.cmd_time_limit)
        run = d / f"implausible_run{c}"
        t = _command("estimate", "ev3dgs", ["train", p, "--out", run, *FAST, "--quiet"], args.cmd_time_limit)
        row.update(validate_rc=v["rc"], validate_stderr=v["stderr"].strip()[-300:], train_rc=t["rc"],
                   train_stderr=t["stderr"].strip()[-300:], train_seconds=t["seconds"])
        trained = run.exists() and any((run / f).exists() for f in ("model.pt", "ckpt.pt"))
        outcome, detail = "refused", v["stderr"].strip()[:300]
        for r, who in ((v, "validate"), (t, "train")):
            kindp, why = _stderr_problem(r["stderr"], r["rc"] != 0)
            if r["rc"] is None:
                outcome, detail = "hang", f"{who}: over {args.cmd_time_limit} s"
            elif kindp == "traceback":
                outcome, detail = "traceback", f"{who}: {why}"
            elif r["rc"] == 0:
                outcome, detail = "silent-garbage", f"{who} exit 0 on an impossible scene"
            elif r["rc"] != 2 or kindp or len(r["stderr"].strip().splitlines()) != 1:
                outcome, detail = "bad-message", f"{who} exit {r['rc']}: {r['stderr'].strip()[-300:]}"
            if outcome != "refused":
                break
        if outcome == "refused" and (trained or t["seconds"] > TRAIN_REFUSE_S):
            outcome, detail = "slow", f"train refused after {t['seconds']} s (model written: {trained})"
        rows.append({**row, "outcome": outcome, "detail": detail})
        p.unlink()
        shutil.rmtree(run, ignore_errors=True)
    return rows


# ================================================================ races: two writers of one output
RACE_DELAY_S = 1.0             # the second writer starts 0..this many seconds after the first


def race_writers(p: dict, d: Path) -> dict:
    """The disk-full writers plus calibrate and compare (on a recording calibrate can fit), as in writers()."""
    rec = p["inp"] / "calib.aedat4"
    if not rec.exists():
        from ev3dgs.calib.synth import Truth, make_recording

        make_recording(rec, Truth(), seed=1, seconds=0.4)
    w = writers(p)
    w["calibrate"] = ("ev3dgs-sim", lambda o: ["calibrate", rec, "--out", o / "sensor.toml", "--bootstrap", "4"],
                      "sensor.toml", "file")
    w["compare"] = ("ev3dgs-sim", lambda o: ["compare", rec, "--out", o / "report"], "report", "folder")
    return w


def _race_case(name: str, spec: tuple, p: dict, where: Path, delay: float, limit_s: float) -> dict:
    """Two processes of writer `name` on one output, the second started `delay` s after the first. Passes:
    one-refused (one exit 0 with the complete output, the other exit 2 with one line saying another process
    writes it), refused-late (the second came after the first had finished: exit 2, the output exists).
    Fails: lost-output (both exit 0: one result replaced the other), corrupt-output, no-output, bad-message,
    temp-left (a temporary or a claim left behind), crash, traceback, hang."""
    entry, argv, out_name, layout = spec
    where.mkdir(parents=True)
    if name == "eval":
        shutil.copytree(p["run"], where / "run")
    cmd = [sys.executable, __file__, "--cli", "estimate", entry, *map(str, argv(where))]
    procs = []
    t0 = time.perf_counter()
    for k in range(2):
        if k:
            time.sleep(delay)
        procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                                      env=_env(), stdin=subprocess.DEVNULL))
    res = []
    for q in procs:
        try:
            _, err = q.communicate(timeout=max(1.0, limit_s - (time.perf_counter() - t0)))
            res.append((q.returncode, err))
        except subprocess.TimeoutExpired:
            q.kill()
            res.append((None, q.communicate()[1]))
    row = {"rc": [r for r, _ in res], "stderr": [e.strip()[-600:] for _, e in res],
           "seconds": round(time.perf_counter() - t0, 2)}
    if None in row["rc"]:
        return {**row, "outcome": "hang", "detail": f"over {limit_s} s"}
    for rc, err in res:
        kind, why = _stderr_problem(err, rc != 0)
        if kind == "traceback":
            return {**row, "outcome": kind, "detail": why}
        if rc not in (0, 2):
            return {**row, "outcome": "crash", "detail": f"exit {rc}: {err.strip()[-200:]}"}
        if kind:
            return {**row, "outcome": kind, "detail": why}
    out = where / out_name
    bad, detail = _check_output(out, layout, None)
    if bad:
        return {**row, "outcome": bad, "detail": detail}
    left = [str(q.relative_to(where)) for q in where.rglob("*")
            if ".tmp-" in q.name or q.name.endswith(".claim") or q.name == ".ev3dgs.lock"]
    if left:
        return {**row, "outcome": "temp-left", "detail": ", ".join(left)[:300]}
    rcs = sorted(row["rc"])
    if rcs == [0, 0]:
        return {**row, "outcome": "lost-output", "detail": "both writers exited 0: the first result was replaced"}
    if rcs != [0, 2]:
        return {**row, "outcome": "no-output", "detail": " | ".join(row["stderr"])[:300]}
    if not out.exists():
        return {**row, "outcome": "no-output", "detail": "exit 0 without the output"}
    refusal = res[row["rc"].index(2)][1].strip().splitlines()[-1]
    if "is being written by another ev3dgs process" in refusal:
        return {**row, "outcome": "one-refused", "detail": refusal[:300]}
    return {**row, "outcome": "refused-late", "detail": refusal[:300]}


def run_races(n: int, rng: np.random.Generator, d: Path, args, cache: dict) -> list[dict]:
    """Each writer in turn (case c: writer c mod count), the second process started a seeded 0..RACE_DELAY_S
    after the first."""
    names = [*WRITERS, "calibrate", "compare"]
    used = {names[c % len(names)] for c in range(n)}
    p = prepare_commands(d, args.cmd_time_limit, cache,
                         need_run=any(k.startswith(("eval", "render", "export-ply", "view")) for k in used))
    ws = race_writers(p, d)
    assert list(ws) == names
    rows = []
    for c in range(n):
        name = names[c % len(names)]
        delay = round(float(rng.uniform(0, RACE_DELAY_S)), 3)
        res = _race_case(name, ws[name], p, d / f"race{c}", delay, args.cmd_time_limit)
        rows.append({"case": c, "writer": name, "delay_s": delay, **res})
        shutil.rmtree(d / f"race{c}", ignore_errors=True)
    return rows


# ================================================================ table and main
def _summary(cls: str, rows: list[dict]) -> dict:
    s = dict.fromkeys(SUMMARY, 0)
    s["cases"] = len(rows)
    for r in rows:
        o = r["outcome"]
        if o in PASS[cls]:
            s["passed"] += 1
        elif o in ("traceback", "crash", "hang", "corrupt-output", "silent-garbage", "lost-output"):
            s[o] += 1
        elif o in ("garbage-warned", "kept-bad"):         # garbage returned, with a warning
            s["warned-garbage"] += 1
        else:
            s["other-failure"] += 1
    return s


def _parse_cases(items: list[str] | None) -> tuple[int | None, dict[str, int]]:
    default, per = None, {}
    for it in items or []:
        for part in it.split(","):
            if "=" in part:
                k, v = part.split("=", 1)
                if k not in ALL_CLASSES:
                    raise SystemExit(f"--cases: unknown class {k!r} (one of {', '.join(ALL_CLASSES)})")
                per[k] = int(v)
            else:
                default = int(part)
    return default, per


# ================================================================ issue 53: mid-file AEDAT 2.0 shifts, hostile configs
def run_a2_midshift(n: int, rng: np.random.Generator, d: Path, files: dict, args) -> list[dict]:
    _tests_path()
    from aedat2_build import build as build_davis240

    files = dict(files)
    if "davis240" not in files:
        files["davis240"] = d / "davis240.aedat"
        files["davis240"].write_bytes(build_davis240()[0])
    def pick_at(data: bytes) -> int:   # 64 events clear of the data's ends
        return int(rng.integers(_a2_data_start(data) + 8 * 64, len(data) - 8 * 64))

    def fill(k: int) -> bytes:
        return rng.integers(0, 256, k, dtype=np.uint8).tobytes()

    return _a2_shift_rows("aedat2-midshift", n, rng, d, files, args, pick_at, fill)


HOSTILE_KEYS = (("dvs", "pos_threshold"), ("dvs", "neg_threshold"), ("dvs", "log_knee"),
                ("dvs.threshold_mismatch", "sigma"), ("dvs.threshold_mismatch", "min_threshold"),
                ("dvs.refractory", "period_us"), ("dvs.leak", "rate_hz"), ("dvs.leak", "jitter_fraction"),
                ("dvs.shot_noise", "rate_hz"), ("dvs.shot_noise", "white_fraction"), ("dvs.lowpass", "cutoff_hz"),
                ("dvs.lowpass", "dark_intensity"), ("sensor_noise", "iso"), ("aps", "dark_dn"))
HOSTILE_VALUES = ("1e300", "-1e300", "1e-300", "0", "-1", "1e6", "1e-6", "1e5", "inf", "nan", '"text"', "true",
                  "[1, 2]")
HOSTILE_FILES = ("binary", "nested", "comment")
CONFIG_MEM_MB = 6144          # address space of a config case: numba's compiler and the simulator fit easily


def _hostile_config(path: Path, rng: np.random.Generator, out_of_range: bool) -> str:
    """Write one hostile sensor TOML; returns what it holds."""
    if not out_of_range and rng.random() < 0.2:
        kind = HOSTILE_FILES[int(rng.integers(len(HOSTILE_FILES)))]
        if kind == "binary":
            path.write_bytes(b"[dvs]\n" + rng.integers(0, 256, 256, dtype=np.uint8).tobytes())
        elif kind == "nested":
            path.write_text("x = " + "[" * 10000 + "]" * 10000 + "\n")
        else:
            path.write_text(f"# aps_dark_dn = {('-', 'e', '1.2.3', '1e999')[int(rng.integers(4))]}\n[dvs]\n")
        return kind
    table, key = HOSTILE_KEYS[int(rng.integers(len(HOSTILE_KEYS)))]
    values = ("1e300", "-1e300") if out_of_range else HOSTILE_VALUES     # every key is bounded in magnitude
    value = values[int(rng.integers(len(values)))]
    path.write_text(f"[{table}]\n{key} = {value}\n")
    return f"{table}.{key} = {value}"


def _config_inputs(d: Path) -> dict:
    from ev3dgs.calib.synth import Truth, make_recording

    frames = np.linspace(0.1, 0.9, 11, dtype=np.float32)[:, None, None] * np.ones((1, 24, 32), np.float32)
    np.savez(d / "frames.npz", frames=frames, t_us=np.arange(11, dtype=np.int64) * 100_000)
    make_recording(d / "small.aedat4", Truth(hot=((3, 5),)), seed=3, seconds=0.6, width=32, height=24, warmup_s=0.2)
    return {"npz": d / "frames.npz", "rec": d / "small.aedat4"}


def run_config_hostile(n: int, rng: np.random.Generator, d: Path, args) -> list[dict]:
    inputs = _config_inputs(d)
    rows = []
    for c in range(n):
        target = "make-dataset" if c == 0 else ("events" if c % 2 else "compare")
        cfg = d / f"hostile{c}.toml"
        what = _hostile_config(cfg, rng, out_of_range=target == "make-dataset")
        out = d / f"out{c}" / ("s.h5" if target != "compare" else "rep")
        if target == "events":
            argv = ["events", inputs["npz"], "--config", cfg, "--out", out, "--quiet"]
        elif target == "compare":
            argv = ["compare", inputs["rec"], "--config", cfg, "--out", out, "--quiet"]
        else:
            argv = ["make-dataset", "--scene", "lego", "--config", cfg, "--out", out, "--quiet"]
        t0 = time.perf_counter()
        try:
            run = subprocess.run([sys.executable, __file__, "--cli", "no-render" if target == "make-dataset"
                                  else "plain", "ev3dgs-sim", *map(str, argv)], capture_output=True, text=True,
                                 timeout=args.cmd_time_limit, cwd=ROOT, env=_env(), stdin=subprocess.DEVNULL,
                                 preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (CONFIG_MEM_MB << 20,) * 2))
            rc, err = run.returncode, run.stderr
        except subprocess.TimeoutExpired:
            rc, err = None, ""
        problem, detail = _stderr_problem(err, rc != 0)
        if rc is None or "MemoryError" in err:
            outcome, detail = "hang", f"over {args.cmd_time_limit} s" if rc is None else "out of memory"
        elif rc == 99:
            outcome, detail = "reached-render", "make-dataset reached its render with this config"
        elif rc not in (0, 2):
            outcome, detail = "crash", f"exit {rc}: {err.strip()[-200:]}"
        elif problem:
            outcome = problem
        elif rc == 2:
            outcome, detail = "refused", err.strip()[:300]
        else:
            outcome = "completed" if out.exists() else "silent-garbage"
            detail = "" if out.exists() else "exit 0 without the output"
        rows.append({"case": c, "command": target, "mutation": what, "outcome": outcome, "detail": detail,
                     "seconds": round(time.perf_counter() - t0, 2)})
    return rows


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--cli"]:
        return _cli(argv[1], argv[2], argv[3:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ap.add_argument("--cases", action="append", metavar="N|CLASS=N",
                    help="cases per class: N for every class, CLASS=N for one (repeatable, comma-separated; "
                         "default " + ", ".join(f"{k}={v}" for k, v in DEFAULT_CASES.items()) + ")")
    ap.add_argument("--classes", default=",".join(ALL_CLASSES),
                    help=f"comma-separated classes to run (default all: {','.join(ALL_CLASSES)})")
    ap.add_argument("--writers", help="disk-full: only these writers, comma-separated (default all)")
    ap.add_argument("--json", help="write every case and the tables here (default: no file)")
    ap.add_argument("--time-limit", type=float, default=60.0, help="seconds per reader case (default 60)")
    ap.add_argument("--cmd-time-limit", type=float, default=180.0, help="seconds per command (default 180)")
    ap.add_argument("--mem-mb", type=int, default=3072, help="address-space cap per reader case in MiB (default 3072)")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        if args.child[0] in ("aedat2-shift", "aedat2-ts-flip", "aedat2-midshift"):
            print(json.dumps(_child_a2(*args.child)))
        else:
            print(json.dumps(_child(*args.child)))
        return 0
    classes = [c for c in args.classes.split(",") if c]
    unknown = [c for c in classes if c not in ALL_CLASSES]
    if unknown:
        ap.error(f"--classes: unknown {', '.join(unknown)} (one of {', '.join(ALL_CLASSES)})")
    default, per = _parse_cases(args.cases)
    counts = {c: per.get(c, default if default is not None else DEFAULT_CASES[c]) for c in classes}
    only = args.writers.split(",") if args.writers else None
    if only and set(only) - set(WRITERS):
        ap.error(f"--writers: unknown {', '.join(sorted(set(only) - set(WRITERS)))} (one of {', '.join(WRITERS)})")
    t_start = time.perf_counter()
    results, notes = {}, {}
    with tempfile.TemporaryDirectory(prefix="ev3dgs_fuzz_") as tmp:
        d = Path(tmp)
        inputs = a2 = None
        cache: dict = {}
        for cls in classes:
            rng = np.random.default_rng([args.seed, ALL_CLASSES.index(cls)])
            t0 = time.perf_counter()
            n = counts[cls]
            if cls in READER_CLASSES:
                inputs = inputs or build_inputs(d)
                if cls not in inputs:
                    notes[cls] = {"skipped": f"{SHARED} is not here"}
                    rows = []
                else:
                    rows = run_readers(cls, n, rng, d, inputs, args)
            elif cls in ("aedat2-shift", "aedat2-ts-flip"):
                a2 = a2 or a2_files(d)
                rows = (run_a2_shift if cls == "aedat2-shift" else run_a2_flip)(n, rng, d, a2, args)
            elif cls == "aedat2-midshift":
                a2 = a2 or a2_files(d)
                rows = run_a2_midshift(n, rng, d, a2, args)
            elif cls == "config-hostile":
                rows = run_config_hostile(n, rng, d, args)
            elif cls == "disk-full":
                rows, meta = run_disk_full(n, rng, d, args, only, cache)
                notes[cls] = meta
            elif cls == "races":
                rows = run_races(n, rng, d, args, cache)
            else:
                rows = run_scene_plausible(n, rng, d, args, cache)
            results[cls] = rows
            notes.setdefault(cls, {})["seconds"] = round(time.perf_counter() - t0, 1)
            for r in rows:
                if r["outcome"] not in PASS[cls]:
                    what = r.get("writer") or r.get("mutation")
                    print(f"{cls} case {r['case']} {what}: {r['outcome']}: {r.get('detail', '')}", file=sys.stderr)
    summary = {c: _summary(c, rows) for c, rows in results.items()}
    outcomes = {c: dict(Counter(r["outcome"] for r in rows)) for c, rows in results.items()}
    w = max(len(c) for c in [*summary, "class"])
    print(f"{'class':{w}s} " + " ".join(f"{k:>14s}" for k in SUMMARY))
    for c, s in summary.items():
        skipped = notes.get(c, {}).get("skipped")
        print(f"{c:{w}s} " + (f"skipped: {skipped}" if skipped else " ".join(f"{s[k]:14d}" for k in SUMMARY)))
    for c, o in outcomes.items():
        print(f"{c}: " + ", ".join(f"{k} {v}" for k, v in sorted(o.items())))
    failed = sum(s["cases"] - s["passed"] for s in summary.values())
    print(f"{failed} failures in {sum(s['cases'] for s in summary.values())} cases, "
          f"{time.perf_counter() - t_start:.0f} s")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({
            "command": "python tools/bench/fuzz.py " + " ".join(argv),
            "seed": args.seed, "cases": counts,
            "machine": {"cpus": os.cpu_count(), "arch": platform.machine(), "python": platform.python_version()},
            "seconds": round(time.perf_counter() - t_start, 1), "failures": failed,
            "summary": summary, "outcomes": outcomes, "notes": notes, "rows": results}, indent=1))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
