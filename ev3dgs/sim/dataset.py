"""`ev3dgs-sim make-dataset`: render shaky sub-frames in Blender workers, then events + blur -> scene.h5.

Rendering is resumable: every rendered view is saved atomically in a cache folder beside the output
(`.NAME.cache-KEY/`, KEY a hash of everything that affects the pixels), so re-running the same command
after an interruption (even kill -9) renders only the missing views. The cache is removed after the scene
file is written, unless keep_cache. The scene file itself is written to a temporary name and renamed.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .. import schema
from ..errors import Ev3dgsError, InputError
from ..events import Events
from ..geometry import intrinsics
from ..outputs import OutputError, atomic_path, check_output_file, os_error_message, remove_stale_temps
from .blur import blur_frames
from .budget import check_noise_memory
from .dvs import DVSSimulator
from .isp import forward_isp, inverse_isp
from .output import event_sensor, provenance
from .scenes import Render, SceneSpec
from .views import novel_view_poses, plan_views


@dataclass
class DatasetStats:
    path: Path
    views_rendered: int = 0
    views_cached: int = 0
    events: int = 0
    seconds: dict = field(default_factory=dict)  # render, simulate, isp, write
    render_device: str | None = None  # where Cycles rendered ("cpu", "cuda", "optix"); None: every view cached


def _cache_key(spec: SceneSpec, render: Render, blend: Path | None, seed: int) -> str:
    h = hashlib.sha256()
    # the device is left out: a run resumed on another device keeps the views already rendered
    render_key = {k: v for k, v in asdict(render).items() if k != "device"}
    h.update(json.dumps({"builder": spec.builder, "params": spec.params, "render": render_key,
                         "shake": asdict(spec.shake), "seed": seed}, sort_keys=True, default=str).encode())
    if blend is not None:
        with open(blend, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:12]


def _save_npz(path: Path, **arrays) -> None:
    # zipped in memory first (one view's frames): a full disk then fails in one plain write, instead of inside
    # zipfile, whose half-closed archive would raise again from ZipFile.__del__ after the error was reported
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with atomic_path(path) as tmp:  # on failure: temporary removed, OutputError naming the reason
        with open(tmp, "wb") as f:
            f.write(buf.getbuffer())


_BLEND_MAGIC = (b"BLENDER", b"\x1f\x8b", b"\x28\xb5\x2f\xfd")  # plain, gzip- or zstd-compressed .blend


def _check_blend(blend: Path) -> None:
    """A .blend that Blender cannot open fails in the worker with a traceback: refuse it here."""
    try:
        with open(blend, "rb") as f:
            head = f.read(8)
    except OSError as e:
        raise InputError(f"cannot read --blend {os_error_message(e, blend)}") from None
    if not head.startswith(_BLEND_MAGIC):
        raise InputError(f"{blend}: not a .blend file (it does not start with BLENDER)")


def _estimate_bytes(render: Render, cache: Path) -> int:
    """Disk space make_dataset still needs: the render cache (float32 frames) and the scene file."""
    px = render.width * render.height * 3
    frames = render.views * (render.subframes + 1) + render.test_views
    have = 0
    with contextlib.suppress(OSError):
        have = sum(e.stat().st_size for e in os.scandir(cache) if e.is_file())
    out = (2 * render.views + render.test_views) * px // 2    # u1 images, gzip; events come on top
    return max(0, frames * px * 4 - have) + out


def _load_npz(path: Path) -> dict | None:
    try:
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    except Exception:  # a damaged cache entry is simply rendered again
        path.unlink(missing_ok=True)
        return None


def _progress(total: int, quiet: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="view", desc="render", disable=quiet or not sys.stderr.isatty(),
                dynamic_ncols=True)


def render_all(jobs: dict[str, np.ndarray], init_kwargs: dict, cache: Path, workers: int,
               quiet: bool, executor: str = "local", address: str | None = None) -> tuple[dict[str, dict], dict, int]:
    """Render every job (key -> poses) not yet in the cache. Returns (results by key, scene info, count).

    executor: "local" (a pool of `workers` spawned Blender processes) or "ray" (`workers` Ray actors on a local
    Ray instance, or on the cluster at `address`); see ev3dgs.sim.executors. Either way this process writes
    the cache."""
    from .executors import RenderFailed, WorkerCrashed, make_executor

    ex = make_executor(executor, workers=workers, address=address, quiet=quiet)
    results, todo = {}, {}
    for key, poses in jobs.items():
        got = _load_npz(cache / f"{key}.npz")
        if got is not None and got["frames"].shape[0] == len(poses):
            results[key] = got
        else:
            todo[key] = poses
    info_path = cache / "info.json"
    info = json.loads(info_path.read_text()) if info_path.exists() else {}
    if not todo:
        return results, info, 0
    bar = _progress(len(jobs), quiet)
    bar.update(len(results))
    try:
        with contextlib.closing(ex.render(init_kwargs, todo)) as done:  # closing stops the workers
            for key, frames, readback, info in done:
                _save_npz(cache / f"{key}.npz", frames=frames, poses=readback)
                results[key] = {"frames": frames, "poses": readback}
                with atomic_path(info_path) as tmp:
                    tmp.write_text(json.dumps(info))
                bar.update(1)
    except WorkerCrashed:
        raise Ev3dgsError(f"a Blender worker crashed; {len(results)} of {len(jobs)} views are cached in "
                          f"{cache}, re-run the same command to resume") from None
    except (RenderFailed, ValueError, RuntimeError, OSError) as e:  # raised inside a worker (bad params, bad .blend)
        raise Ev3dgsError(f"rendering failed: {e}") from None
    finally:
        bar.close()
    return results, info, len(todo)


def _to_srgb(linear: np.ndarray, spec: SceneSpec) -> np.ndarray:
    """A sharp frame developed by the same ISP as the blurry ones, without sensor noise."""
    return forward_isp(inverse_isp(linear, spec.sensor.isp), spec.sensor.isp)


def make_dataset(spec: SceneSpec, render: Render, out: str | Path, blend: str | Path | None = None,
                 workers: int = 1, seed: int = 0, quiet: bool = False, keep_cache: bool = False,
                 executor: str = "local", address: str | None = None, force: bool = True) -> DatasetStats:
    """Render `spec` with `render`'s settings and write the scene file `out` (see the module doc).
    force=False: an existing `out` is refused (OutputError) before any rendering."""
    out = Path(out)
    if out.suffix not in (".h5", ".hdf5"):
        raise InputError(f"--out must end in .h5, got {out}")
    blend = Path(blend) if blend is not None else None
    if blend is not None and not blend.is_file():
        raise InputError(f".blend file not found: {blend}")
    if blend is not None:
        _check_blend(blend)
    if blend is None and spec.builder is None:
        raise InputError(f"scene {spec.name!r} names no builder; give --blend FILE")
    if workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")
    from .executors import make_executor

    make_executor(executor, workers=workers, address=address)  # a bad --executor or a missing ray fails here
    stats = DatasetStats(out)
    W, H = render.width, render.height
    K = intrinsics(W, H, render.fov_deg)
    plans = plan_views(render, spec.shake, seed)
    S = render.subframes
    jobs = {f"view_{p.index:04d}": p.poses if S % 2 else np.concatenate([p.poses, p.mid_pose[None]])
            for p in plans}
    jobs.update({f"test_{j:04d}": pose[None] for j, pose in enumerate(novel_view_poses(render, seed))})
    cache = out.parent / f".{out.stem}.cache-{_cache_key(spec, render, blend, seed)}"
    # before any rendering: the output can be written, with room for the cache and the file, and the noise
    # effects' events over every exposure fit in memory (the simulator checks again per view)
    check_output_file(out, _estimate_bytes(render, cache), force=force, make_parents=True)
    check_noise_memory(spec.sensor.dvs, W * H, sum(int(p.t_us[-1] - p.t_us[0]) for p in plans) * 1e-6)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)   # a missing output folder is made, as every command does
    except OSError as e:
        raise OutputError(f"cannot create the output folder {os_error_message(e, out.parent)}", e.errno) from None
    remove_stale_temps(out.parent, out.name)   # left by a killed run: the scene file's temporary
    try:
        cache.mkdir(exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create the render cache {os_error_message(e, cache)}", e.errno) from None
    remove_stale_temps(cache)                  # and the cached views' temporaries
    init_kwargs = dict(builder=None if blend else spec.builder, params=spec.params,
                       blend_path=str(blend) if blend else None, width=W, height=H, K=K.tolist(),
                       samples=render.samples, denoise=render.denoise,
                       denoise_prefilter=render.denoise_prefilter, background=list(render.background),
                       seed=seed, render_device=render.device)
    t0 = time.perf_counter()
    results, info, stats.views_rendered = render_all(jobs, init_kwargs, cache, workers, quiet,
                                                     executor=executor, address=address)
    stats.views_cached = len(jobs) - stats.views_rendered
    stats.render_device = info.get("render_device") if stats.views_rendered else None
    stats.seconds["render"] = time.perf_counter() - t0

    sim = DVSSimulator(H, W, spec.sensor.dvs, seed=seed, isp=spec.sensor.isp)
    sim_s = isp_s = 0.0
    images, sharp, sharp_poses, poses, pose_t, exposure, parts = [], [], [], [], [], [], []
    for p in plans:
        r = results[f"view_{p.index:04d}"]
        frames, readback = r["frames"][:S], r["poses"]
        t = time.perf_counter()
        sim.restart()  # the camera jumped from the previous view: no events across the gap
        parts.append(sim.feed(frames, p.t_us))
        t1 = time.perf_counter()
        images.append(blur_frames(frames, spec.sensor.isp, spec.sensor.sensor_noise, seed=seed * 100003 + p.index))
        mid = S // 2 if S % 2 else S
        sharp.append(_to_srgb(r["frames"][mid], spec))
        isp_s += time.perf_counter() - t1
        sim_s += t1 - t
        sharp_poses.append(readback[mid])
        poses.append(readback[:S])
        pose_t.append(p.t_us)
        exposure.append(p.exposure)
    t = time.perf_counter()
    tests = [results[f"test_{j:04d}"] for j in range(render.test_views)]
    test_part = None
    if tests:
        test_part = schema.Test(images=np.stack([_to_srgb(r["frames"][0], spec) for r in tests]),
                                poses=np.stack([r["poses"][0] for r in tests]))
    bg = _to_srgb(np.broadcast_to(np.asarray(render.background, np.float32), (2, 2, 3)).copy(), spec)[0, 0]
    isp_s += time.perf_counter() - t
    events = Events.concatenate(parts)
    stats.events = len(events)
    scene = schema.Scene(
        name=spec.name, source="blender",
        camera=schema.Camera(width=W, height=H, K=K, background=tuple(float(c) / 255 for c in bg)),
        events=events, sensor=event_sensor(spec.sensor.dvs, spec.sensor.isp),
        train=schema.Train(images=np.stack(images), exposure=np.array(exposure, np.int64),
                           poses=np.stack(poses), pose_t=np.stack(pose_t), sharp=np.stack(sharp),
                           sharp_poses=np.stack(sharp_poses), transfer="srgb"),  # ISP of linear-light blur
        test=test_part,
        bounds=np.asarray(info["bounds"], np.float64) if info.get("bounds") is not None else None,
        config=provenance(spec.sensor, scene=spec.name, builder=spec.builder, params=spec.params,
                          render=asdict(render), render_device=info.get("render_device"), shake=asdict(spec.shake),
                          seed=seed,
                          blend=str(blend) if blend else None, simulator=asdict(sim.report)),
    )
    t = time.perf_counter()
    schema.write(scene, out)
    stats.seconds.update(simulate=sim_s, isp=isp_s, write=time.perf_counter() - t)
    if not keep_cache:
        shutil.rmtree(cache, ignore_errors=True)
    return stats
