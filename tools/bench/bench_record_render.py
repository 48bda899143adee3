"""Where `ev3dgs-sim record`'s rendering time goes, per frame: the lego scene at 173x130, 8 samples, OIDN with the
accurate prefilter (the calibrate study's recordings), through the render worker's own code path
(ev3dgs_blender.render.init_scene / render, what every worker process runs).

One Blender process renders consecutive poses of record's trajectory, cycling through the variants in blocks of
--block frames (so load changes hit every variant alike; the first frame of a block, which follows another
variant, is left out of the summary: persistent data only persists from the second frame on):
  accurate       the recording's settings (OIDN, accurate guide prefilter) with a fresh Cycles session every
                 frame (use_persistent_data off: the renderer as it was)
  persistent     the same with use_persistent_data on (Cycles keeps its session, scene and BVH between frames:
                 the renderer as it is now)
  fast, off      OIDN with the fast prefilter, and no denoiser (fresh sessions): the difference to `accurate` is
                 what the denoiser's passes cost
Per frame: wall seconds, CPU seconds of the process (all threads: what a frame costs whatever else runs), and
from Cycles' own progress reports the scene sync (until "Sample 0/N"), the rest of Cycles' render and our
readback after it. Then OIDN's three filters at the same size, called directly through the OIDN library Blender
ships (commit and execute apart, --oidn-repeats times on one device: the first commit is what a fresh device
pays, as Cycles makes one every frame; later ones reuse the device's cache): the share of the denoiser that is
set-up. Then (--record) one short `record`
run end to end: worker start, scene build, chunk transfer and cache writes on top of the frames
(the worker's CPU seconds from the operating system once the pool has reaped it).
`persistent` frames are compared bitwise with `accurate` frames of the same pose (--bitwise poses rendered both
ways). JSON to tools/results/.

    python tools/bench/bench_record_render.py --frames 60 --bitwise 3 --record 0.2 \\
        --json tools/results/bench_record_render.json
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import ctypes  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/: pareto.py
from pareto import save_json  # noqa: E402

VARIANTS = ("accurate", "persistent", "fast", "off")


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def setup(args):
    """Build the recording's scene in this process, as a record worker does; returns (poses, init seconds)."""
    from ev3dgs.geometry import intrinsics
    from ev3dgs.sim.record import Trajectory
    from ev3dgs.sim.scenes import load_scene, resolve_render

    t0 = time.perf_counter()
    from ev3dgs_blender import render as R
    t_import = time.perf_counter() - t0
    spec = load_scene(args.scene)
    r = resolve_render(spec, width=args.width, height=args.height, samples=args.samples)
    K = intrinsics(r.width, r.height, r.fov_deg)
    traj = Trajectory(r.radius, float(np.mean(r.elevation_deg)), args.seconds, 75.0, spec.shake, args.seed)
    n = args.frames + args.bitwise
    poses = traj.pose(np.arange(n) / args.rate)
    t0 = time.perf_counter()
    R.init_scene(spec.builder, spec.params, None, r.width, r.height, K.tolist(), samples=r.samples,
                 denoise=r.denoise, background=list(r.background), seed=args.seed,
                 denoise_prefilter=r.denoise_prefilter)
    return poses, {"import_bpy_s": t_import, "init_scene_s": time.perf_counter() - t0,
                   "render": {"width": r.width, "height": r.height, "samples": r.samples,
                              "denoise": r.denoise, "prefilter": r.denoise_prefilter}}


def set_variant(name: str) -> None:
    import bpy

    scene = bpy.context.scene
    cy = scene.cycles
    scene.render.use_persistent_data = name == "persistent"
    cy.use_denoising = name != "off"
    if name != "off":
        cy.denoising_prefilter = "FAST" if name == "fast" else "ACCURATE"


def profile(args, poses) -> tuple[dict, list[dict]]:
    import bpy
    from bpy.app.handlers import persistent

    from ev3dgs_blender import render as R

    stats: list[tuple[float, str]] = []
    handler = persistent(lambda s, *a: stats.append((time.perf_counter(), str(s))))
    bpy.app.handlers.render_stats.append(handler)
    rows = []
    try:
        for i in range(args.frames):
            name = VARIANTS[(i // args.block) % len(VARIANTS)]
            set_variant(name)
            stats.clear()
            t0, c0 = time.perf_counter(), cpu_s()
            R.render(poses[i:i + 1])
            t1, c1 = time.perf_counter(), cpu_s()
            sync = next((t for t, s in stats if "Sample 0/" in s), t0)
            done = next((t for t, s in stats if "Finished" in s), t1)
            rows.append({"variant": name, "frame": i, "first_in_block": i % args.block == 0, "wall_s": t1 - t0,
                         "cpu_s": c1 - c0, "sync_s": sync - t0, "cycles_s": done - sync, "readback_s": t1 - done,
                         "cycles_reported": next((s for _, s in reversed(stats) if s.startswith("Time:")), None)})
            print(f"{name:10s} wall {t1 - t0:.3f} s  cpu {c1 - c0:.3f} s  sync {sync - t0:.3f}  "
                  f"cycles {done - sync:.3f}  readback {t1 - done:.3f}", flush=True)
        bitwise = []
        for j in range(args.frames, args.frames + args.bitwise):   # the same pose both ways
            out = {}
            for name in ("accurate", "persistent", "persistent", "accurate"):   # persistent: its second frame
                set_variant(name)
                out.setdefault(name, []).append(R.render(poses[j:j + 1])[0])
            a0, a1, p = out["accurate"][0], out["accurate"][1], out["persistent"][1]
            bitwise.append({"pose": j, "accurate_repeat_identical": bool(np.array_equal(a0, a1)),
                            "persistent_identical": bool(np.array_equal(a0, p)),
                            "max_abs_diff": float(np.abs(a0 - p).max())})
            print("bitwise", bitwise[-1], flush=True)
    finally:
        bpy.app.handlers.render_stats.remove(handler)
        set_variant("accurate")
    summary = {}
    for name in VARIANTS:
        sel = [r for r in rows if r["variant"] == name and not (r["first_in_block"] and args.block > 1)]
        if sel:
            summary[name] = {k: quantiles([r[k] for r in sel]) for k in ("wall_s", "cpu_s", "sync_s", "cycles_s",
                                                                       "readback_s")}
    # new over old, per cycle of blocks (the two blocks of a cycle ran a few seconds apart): the ratio's spread
    cycles: dict[int, dict[str, list[dict]]] = {}
    for r in rows:
        if not (r["first_in_block"] and args.block > 1):
            cycles.setdefault(r["frame"] // (args.block * len(VARIANTS)), {}).setdefault(r["variant"], []).append(r)
    ratio = {}
    for key in ("cpu_s", "wall_s"):
        v = [statistics.median(x[key] for x in c["persistent"]) / statistics.median(x[key] for x in c["accurate"])
             for c in cycles.values() if "persistent" in c and "accurate" in c]
        if v:
            ratio[key] = quantiles(v)
    return {"variants": summary, "persistent_over_accurate": ratio, "bitwise": bitwise}, rows


def quantiles(v: list[float]) -> dict:
    return {"min": min(v), "median": statistics.median(v), "max": max(v), "n": len(v)}


def oidn_filters(width: int, height: int, repeats: int) -> dict:
    """OIDN's three filters of the accurate prefilter (albedo, normal, beauty), at the recording's size, through
    the OIDN library Blender ships: commit (set-up: weights, graph, scratch) and execute, wall and CPU."""
    import bpy

    # bpy.__file__ is bpy/<version>/scripts/modules/bpy/__init__.py; the shared libraries sit in bpy/lib
    cands = [c for p in Path(bpy.__file__).parents for c in sorted((p / "lib").glob("libOpenImageDenoise.so*"))]
    if not cands:
        return {"skipped": f"no libOpenImageDenoise.so* in a lib folder above {bpy.__file__}"}
    oidn = ctypes.CDLL(str(cands[0]))
    vp, cp = ctypes.c_void_p, ctypes.c_char_p
    oidn.oidnNewDevice.restype = vp
    oidn.oidnNewDevice.argtypes = [ctypes.c_int]
    oidn.oidnSetDeviceBool.argtypes = [vp, cp, ctypes.c_bool]
    oidn.oidnCommitDevice.argtypes = [vp]
    oidn.oidnNewFilter.restype = vp
    oidn.oidnNewFilter.argtypes = [vp, cp]
    oidn.oidnSetSharedFilterImage.argtypes = [vp, cp, vp, ctypes.c_int] + [ctypes.c_size_t] * 5
    oidn.oidnSetFilterBool.argtypes = [vp, cp, ctypes.c_bool]
    for f in ("oidnCommitFilter", "oidnExecuteFilter", "oidnReleaseFilter", "oidnReleaseDevice"):
        getattr(oidn, f).argtypes = [vp]
    oidn.oidnGetDeviceError.argtypes = [vp, ctypes.POINTER(cp)]
    rng = np.random.default_rng(0)
    col = rng.random((height, width, 3), np.float32)
    alb = rng.random((height, width, 3), np.float32)
    nrm = rng.random((height, width, 3), np.float32) * 2 - 1
    outs = {k: np.empty((height, width, 3), np.float32) for k in ("albedo", "normal", "color")}
    dev = oidn.oidnNewDevice(1)   # OIDN_DEVICE_TYPE_CPU
    oidn.oidnSetDeviceBool(dev, b"setAffinity", False)   # as Cycles sets it
    oidn.oidnCommitDevice(dev)

    def image(f, name, a):
        oidn.oidnSetSharedFilterImage(f, name, a.ctypes.data, 3, width, height, 0, 0, 0)   # 3: FLOAT3

    res = {k: {"commit_wall_s": [], "commit_cpu_s": [], "execute_wall_s": [], "execute_cpu_s": []}
           for k in outs}
    for _ in range(repeats):
        for kind in ("albedo", "normal", "color"):
            t0, c0 = time.perf_counter(), cpu_s()
            f = oidn.oidnNewFilter(dev, b"RT")
            if kind == "albedo":
                image(f, b"albedo", alb)
            elif kind == "normal":
                image(f, b"normal", nrm)
            else:
                image(f, b"color", col)
                image(f, b"albedo", alb)
                image(f, b"normal", nrm)
                oidn.oidnSetFilterBool(f, b"hdr", True)
                oidn.oidnSetFilterBool(f, b"cleanAux", True)
            image(f, b"output", outs[kind])
            oidn.oidnCommitFilter(f)
            t1, c1 = time.perf_counter(), cpu_s()
            oidn.oidnExecuteFilter(f)
            t2, c2 = time.perf_counter(), cpu_s()
            oidn.oidnReleaseFilter(f)
            r = res[kind]
            r["commit_wall_s"].append(t1 - t0)
            r["commit_cpu_s"].append(c1 - c0)
            r["execute_wall_s"].append(t2 - t1)
            r["execute_cpu_s"].append(c2 - c1)
    msg = cp()
    err = oidn.oidnGetDeviceError(dev, ctypes.byref(msg))
    oidn.oidnReleaseDevice(dev)
    if err:
        return {"error": (msg.value or b"").decode()}
    return {"library": cands[0].name, "filters": {k: {m: quantiles(v) for m, v in r.items()} for k, r in res.items()}}


def record_run(seconds: float, args) -> dict:
    """One `record` run end to end (its own worker process): render seconds against its frame count."""
    from ev3dgs.sim.record import record

    def children_cpu_s() -> float:   # the render worker, once the pool has reaped it
        r = resource.getrusage(resource.RUSAGE_CHILDREN)
        return r.ru_utime + r.ru_stime

    with tempfile.TemporaryDirectory(prefix="bench-record-") as d:
        t0, c0, w0 = time.perf_counter(), cpu_s(), children_cpu_s()
        info = record(args.scene, Path(d) / "rec.aedat4", seconds=seconds, fps=25, exposure_ms=10,
                      render_rate_hz=args.rate, width=args.width, height=args.height, samples=args.samples,
                      seed=args.seed, quiet=True)
        wall = time.perf_counter() - t0
    return {"seconds": seconds, "rendered": info["rendered"], "wall_s": wall, "stages_s": info["seconds"],
            "render_s_per_frame": info["seconds"]["render"] / info["rendered"],
            "driver_cpu_s": cpu_s() - c0, "worker_cpu_s": children_cpu_s() - w0,
            "worker_cpu_s_per_frame": (children_cpu_s() - w0) / info["rendered"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="lego")
    ap.add_argument("--width", type=int, default=173)
    ap.add_argument("--height", type=int, default=130)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rate", type=float, default=250.0, help="render rate (Hz): poses 1/rate apart")
    ap.add_argument("--seconds", type=float, default=2.0, help="length of the trajectory the poses come from")
    ap.add_argument("--frames", type=int, default=48, help="frames profiled (cycling through the variants)")
    ap.add_argument("--block", type=int, default=3, help="consecutive frames per variant")
    ap.add_argument("--bitwise", type=int, default=2, help="poses rendered accurate, persistent, accurate")
    ap.add_argument("--oidn-repeats", type=int, default=4)
    ap.add_argument("--record", type=float, default=0.0, help="also time one record run of this many seconds")
    ap.add_argument("--json", default="tools/results/bench_record_render.json")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()
    poses, init = setup(args)
    summary, rows = profile(args, poses)
    oidn = oidn_filters(args.width, args.height, args.oidn_repeats)
    rec = record_run(args.record, args) if args.record > 0 else None
    payload = {"settings": vars(args), "init": init, "summary": summary, "oidn": oidn, "record": rec,
               "frames": rows, "loadavg_start": load0, "loadavg_end": os.getloadavg(), "cpus": os.cpu_count()}
    save_json(args.json, payload)
    for name, s in summary["variants"].items():
        print(f"{name:10s} " + "  ".join(f"{k} {v['median']:.3f} [{v['min']:.3f}, {v['max']:.3f}]"
                                         for k, v in s.items()))
    for key, q in summary["persistent_over_accurate"].items():
        print(f"persistent / accurate {key}: median {q['median']:.3f} [{q['min']:.3f}, {q['max']:.3f}], "
              f"{q['n']} cycles")
    if rec:
        print(f"record {rec['seconds']} s: {rec['rendered']} frames, render {rec['render_s_per_frame']:.3f} s a frame, "
              f"worker {rec['worker_cpu_s_per_frame']:.3f} CPU s a frame")
    print(f"load average {load0[0]:.1f} -> {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
