"""Simulate a DAVIS346 recording (.aedat4) of a built-in scene along a smooth hand-held trajectory.

The camera sweeps an arc of `arc_deg` around the scene's origin at the scene's render radius and mean
elevation (a slow sinusoidal elevation wobble adds vertical parallax), looking at the origin, with the
scene's smooth shake (ev3dgs_blender.shake, zero-mean over the whole recording) on top. Linear frames are
rendered in Blender at `render_rate_hz` over the whole recording (jobs of CHUNK poses, cached beside the
output so an interrupted run resumes), then
  * events: one continuous DVSSimulator stream over every rendered frame (the scene's sensor effects);
  * APS frames at `fps`: frame i exposes [t_i, t_i + exposure) with t_i = READOUT_US + i / fps; the rendered
    frames inside that window are averaged in linear light through the ISP (blur_frames, with the scene's
    sensor noise) and converted to GRAY 8-bit LINEAR luminance, as a DAVIS346 APS reads out (no tone
    curve; the DAVIS346 is monochrome). startOfFrame / endOfFrame = exposure start - READOUT_US / end + READOUT_US;
    the frame's own timestamp is the start of exposure (as dv-processing 2.x writes it);
  * IMU at IMU_RATE_HZ from the analytic trajectory. IMU axes = the camera's OpenCV axes (x right, y down,
    z forward): gyro = angular velocity of the camera in its own frame (deg/s); accel = specific force
    (acceleration minus gravity, world z up, g = 9.80665 m/s^2 per scene unit) in the camera frame, in g,
    so a camera at rest reads +1 g along world up (about -y for a level camera). Temperature 30 C.
All times are Unix-epoch-like microseconds from EPOCH_US. Beside OUT.aedat4 goes OUT.trajectory.npz: t_us
(M,), c2w (M,4,4) OpenCV camera-to-world at every rendered frame (as requested; Blender's readback agrees
to float32), K (3,3) OpenCV pixel convention, width, height, frame_timestamp (F,), exposure (F,2) [start,
end) us, imu_t (N,), gyro (N,3), accel (N,3).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import zlib
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import intrinsics, look_at, matrix_to_rotvec
from ..io.aedat4.writer import write_aedat4
from ..io.types import FrameData, ImuData
from ..sensor import LUMINANCE_WEIGHTS
from .blur import blur_frames
from .dataset import render_all
from .dvs import DVSSimulator
from .scenes import load_scene, resolve_render

EPOCH_US = 1_700_000_000_000_000
READOUT_US = 1000
IMU_RATE_HZ = 1000
GRAVITY = 9.80665
CHUNK = 25


class Trajectory:
    """The camera path: an arc around the origin plus smooth shake; `pose(t_s)` for any times in [0, T]."""

    def __init__(self, radius: float, elevation_deg: float, duration_s: float, arc_deg: float, shake, seed: int):
        from ev3dgs_blender.shake import Shake

        rng = np.random.default_rng(zlib.crc32(f"{seed}/record".encode()))
        self.radius, self.T = float(radius), float(duration_s)
        self.el0 = np.deg2rad(elevation_deg)
        self.az0 = rng.uniform(0, 2 * np.pi)
        self.arc = np.deg2rad(arc_deg)
        self.el_amp = np.deg2rad(min(5.0, 0.1 * arc_deg))
        self.shake = Shake(shake.rotation_deg, shake.translation, shake.min_hz, shake.max_hz, shake.components)
        self.shake_seed = zlib.crc32(f"{seed}/record/shake".encode())

    def pose(self, t_s) -> np.ndarray:
        from ev3dgs_blender.shake import apply_offsets, shake_offsets

        t = np.atleast_1d(np.asarray(t_s, float))
        u = t / self.T
        az = self.az0 + self.arc * u
        el = self.el0 + self.el_amp * np.sin(np.pi * u)
        eye = self.radius * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
        offsets = shake_offsets(self.shake, t, self.T, self.shake_seed)
        out = np.empty((len(t), 4, 4))
        for i in range(len(t)):
            out[i] = apply_offsets(look_at(eye[i], (0.0, 0.0, 0.0)), offsets[i:i + 1])[0]
        return out


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3) (angles <= pi)."""
    return matrix_to_rotvec(R)


def imu_samples(traj: Trajectory, t_s: np.ndarray, h: float = 5e-4) -> tuple[np.ndarray, np.ndarray]:
    """(gyro deg/s, accel g), both (N, 3) in the camera (OpenCV) frame, by central differences of the
    analytic trajectory with step h (clamped inside [0, T])."""
    t = np.clip(np.asarray(t_s, float), h, traj.T - h)
    p0, p, p1 = traj.pose(t - h), traj.pose(t), traj.pose(t + h)
    # body angular velocity: R(t+h) = R(t-h) exp([w] 2h)
    w_mid = rotation_log(np.swapaxes(p0[:, :3, :3], 1, 2) @ p1[:, :3, :3]) / (2 * h)
    gyro = np.rad2deg(w_mid)
    acc_world = (p1[:, :3, 3] - 2 * p[:, :3, 3] + p0[:, :3, 3]) / h**2
    specific = acc_world + np.array([0.0, 0.0, GRAVITY])
    accel = np.einsum("nji,nj->ni", p[:, :3, :3], specific) / GRAVITY
    return gyro, accel


def _gray(srgb: np.ndarray) -> np.ndarray:
    """A DAVIS346 APS frame is LINEAR in light (no tone curve): decode the developed sRGB frame (which carries
    the ISP's noise and clipping) back to linear light and take its luminance, 8-bit."""
    from .isp import srgb_to_linear

    lin = srgb_to_linear(srgb) @ LUMINANCE_WEIGHTS
    return np.clip(np.round(255.0 * lin), 0, 255).astype(np.uint8)


def outputs(out) -> dict[str, Path]:
    """The files `record` writes for OUT.aedat4: the recording, its ground-truth trajectory, camera
    calibration and sensor (the simulated DVS, as the TOML `ev3dgs-ingest davis --sensor` reads)."""
    out = Path(out)
    return {"--out": out, "ground truth": out.with_suffix(".trajectory.npz"),
            "calibration": out.parent / f"{out.stem}.calibration.toml",
            "sensor": out.parent / f"{out.stem}.sensor.toml"}


def sensor_toml(sensor) -> str:
    """The simulated sensor (a SimConfig: [dvs] with its effect tables, [isp], [sensor_noise]) as a TOML that
    load_sim_config, `--config` and `ev3dgs-ingest davis --sensor` read back to the same settings. AEDAT 4
    has no field for it, so it goes beside the recording: the ground truth a calibration is held against."""
    from ..config import dumps_toml, to_dict

    return ("# the sensor ev3dgs-sim record simulated (ground truth; AEDAT 4 stores no sensor model)\n"
            + dumps_toml(to_dict(sensor)) + "\n")


def check_outputs(out, force: bool = True) -> None:
    """Fail now (OutputError) if OUT.aedat4 cannot be written, or (unless force) if any of the four files
    exists: a new recording never silently replaces an earlier one or its ground truth."""
    from ..outputs import check_output_file

    for option, path in outputs(out).items():
        check_output_file(path, option=option, force=force, make_parents=True)


def timeline(seconds: float, fps: float, exposure_ms: float, render_rate_hz: float) -> tuple:
    """(soe, eoe, duration_us, t_rel) of a recording, relative to its start: the frames' exposure starts and
    ends (us), the recording's length, and the times of the rendered frames (every 1 / render_rate_hz and the
    last microsecond). Unchecked: record validates its arguments first."""
    soe = READOUT_US + np.round(np.arange(int(round(seconds * fps))) * (1e6 / fps)).astype(np.int64)
    eoe = soe + int(round(exposure_ms * 1000))
    duration_us = max(int(round(seconds * 1e6)), int(eoe[-1]) + READOUT_US)
    t_rel = np.unique(np.append(np.round(np.arange(0, duration_us, 1e6 / render_rate_hz)).astype(np.int64),
                                duration_us))
    return soe, eoe, duration_us, t_rel


def record(scene_name_or_toml, out, seconds: float = 2.0, fps: float = 10, exposure_ms: float = 50,
           render_rate_hz: float = 250, width: int = 346, height: int = 260, samples: int = 8, seed: int = 0,
           workers: int = 1, quiet: bool = True, arc_deg: float = 75.0, compression: str = "lz4",
           keep_cache: bool = False, denoise_prefilter: str | None = None, force: bool = True) -> dict:
    """Render, simulate and write OUT.aedat4 + OUT.trajectory.npz + OUT.calibration.toml + OUT.sensor.toml;
    returns a summary
    (counts, seconds). denoise_prefilter: OIDN's guide prefilter ("accurate", "fast", "none"; None: the
    scene's). force=False: refuse (OutputError) if any of the four files exists, before any rendering."""
    out = Path(out)
    if out.suffix != ".aedat4":
        raise InputError(f"the recording must end in .aedat4, got {out}")
    if not (seconds > 0 and fps > 0 and exposure_ms > 0 and render_rate_hz > 0 and workers >= 1):
        raise InputError("seconds, fps, exposure_ms, render_rate_hz must be > 0 and workers >= 1")
    check_outputs(out, force)
    out.parent.mkdir(parents=True, exist_ok=True)   # a missing output folder is made, as every command does
    spec = load_scene(str(scene_name_or_toml))
    if spec.builder is None:
        raise InputError(f"scene {spec.name!r} names no builder")
    render = resolve_render(spec, width=width, height=height, samples=samples, denoise_prefilter=denoise_prefilter)
    W, H = render.width, render.height
    K = intrinsics(W, H, render.fov_deg)
    period_us = 1e6 / fps
    exposure_us = int(round(exposure_ms * 1000))
    if exposure_us + 2 * READOUT_US > period_us:
        raise InputError(f"exposure {exposure_ms} ms + readout does not fit in a frame period at {fps} fps")
    n_frames = int(round(seconds * fps))
    if n_frames < 1:
        raise InputError("the recording needs at least one frame (seconds * fps >= 1)")
    soe, eoe, duration_us, t_rel = timeline(seconds, fps, exposure_ms, render_rate_hz)
    if len(t_rel) < 2:
        raise InputError("render_rate_hz is too low for the duration")
    traj = Trajectory(render.radius, float(np.mean(render.elevation_deg)), duration_us * 1e-6, arc_deg,
                      spec.shake, seed)
    poses = traj.pose(t_rel * 1e-6)
    timing: dict[str, float] = {}

    # render (cached in chunks beside the output)
    t0 = time.perf_counter()
    h = hashlib.sha256(json.dumps({"builder": spec.builder, "params": spec.params, "render": asdict(render),
                                   "seed": seed}, sort_keys=True, default=str).encode())
    h.update(poses.tobytes())
    cache = out.parent / f".{out.stem}.cache-{h.hexdigest()[:12]}"
    cache.mkdir(exist_ok=True)
    jobs = {f"traj_{i // CHUNK:05d}": poses[i:i + CHUNK] for i in range(0, len(poses), CHUNK)}
    init_kwargs = dict(builder=spec.builder, params=spec.params, blend_path=None, width=W, height=H,
                       K=K.tolist(), samples=render.samples, denoise=render.denoise,
                       denoise_prefilter=render.denoise_prefilter,
                       background=list(render.background), seed=seed)
    results, _info, rendered = render_all(jobs, init_kwargs, cache, workers, quiet)
    keys = sorted(jobs)
    readback = np.concatenate([results[k]["poses"] for k in keys])
    timing["render"] = time.perf_counter() - t0

    # events: one continuous stream over every rendered frame
    t0 = time.perf_counter()
    t_abs = EPOCH_US + t_rel
    sim = DVSSimulator(H, W, spec.sensor.dvs, seed=seed, isp=spec.sensor.isp)
    parts, i = [], 0
    for k in keys:
        frames = results[k]["frames"]
        parts.append(sim.feed(frames, t_abs[i:i + len(frames)]))
        i += len(frames)
    timing["events"] = time.perf_counter() - t0

    # APS frames: mean of the rendered frames inside each exposure window, through the ISP
    t0 = time.perf_counter()
    def linear(a: int, b: int) -> np.ndarray:   # rendered frames a..b-1 without copying the whole video
        return np.concatenate([results[keys[g // CHUNK]]["frames"][g % CHUNK][None] for g in range(a, b)])

    aps = []
    for j in range(n_frames):
        a, b = np.searchsorted(t_rel, [soe[j], eoe[j]], side="left")
        if b <= a:  # no rendered frame inside a very short exposure: the nearest one
            a = int(np.argmin(np.abs(t_rel - (soe[j] + eoe[j]) / 2)))
            b = a + 1
        srgb = blur_frames(linear(a, b), spec.sensor.isp, spec.sensor.sensor_noise, seed=seed * 100003 + j)
        s, e = int(EPOCH_US + soe[j]), int(EPOCH_US + eoe[j])
        aps.append(FrameData(timestamp=s, exposure_start=s, exposure_end=e, frame_start=s - READOUT_US,
                             frame_end=e + READOUT_US, image=_gray(srgb), source="DAVIS346_SIM"))
    timing["frames"] = time.perf_counter() - t0

    # IMU from the analytic trajectory
    t0 = time.perf_counter()
    imu_rel = np.arange(0, duration_us + 1, 1_000_000 // IMU_RATE_HZ, dtype=np.int64)
    gyro, accel = imu_samples(traj, imu_rel * 1e-6)
    imu = ImuData(EPOCH_US + imu_rel, accel.astype(np.float32), gyro.astype(np.float32),
                  np.full(len(imu_rel), 30.0, np.float32))
    timing["imu"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    n_events = sum(len(p) for p in parts)
    write_aedat4(out, W, H, (p for p in parts if len(p)), aps, imu, compression=compression,
                 camera_name="DAVIS346_SIM", ts_offset=EPOCH_US)
    traj_path = outputs(out)["ground truth"]
    tmp = traj_path.with_name(f".{traj_path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        np.savez(f, t_us=t_abs, c2w=poses, K=K, width=W, height=H,
                 frame_timestamp=np.array([fr.timestamp for fr in aps], np.int64),
                 exposure=np.stack([EPOCH_US + soe, EPOCH_US + eoe], 1), imu_t=imu.t, gyro=gyro, accel=accel,
                 imu_axes="camera OpenCV axes: x right, y down, z forward; gyro deg/s, accel g (specific force)")
    from ..outputs import atomic_path, publish

    publish(tmp, traj_path)
    timing["write"] = time.perf_counter() - t0
    if not keep_cache:
        shutil.rmtree(cache, ignore_errors=True)
    # the ground-truth intrinsics as a calibration file `ev3dgs-ingest davis --calibration` reads
    K_true = np.asarray(K, float)
    with atomic_path(outputs(out)["calibration"]) as tmp:
        tmp.write_text(f"width = {W}\nheight = {H}\nfx = {K_true[0, 0]!r}\nfy = {K_true[1, 1]!r}\n"
                       f"cx = {K_true[0, 2]!r}\ncy = {K_true[1, 2]!r}\n")
    with atomic_path(outputs(out)["sensor"]) as tmp:
        tmp.write_text(sensor_toml(spec.sensor), encoding="utf-8")
    return {"path": str(out), "trajectory": str(traj_path), "scene": spec.name, "width": W, "height": H,
            "frames": n_frames, "events": int(n_events), "imu": len(imu), "rendered": len(poses),
            "rendered_now": rendered, "duration_us": duration_us, "start_us": EPOCH_US,
            "readback_error": float(np.abs(readback - poses).max()), "seconds": timing}


__all__ = ["record", "timeline", "outputs", "check_outputs", "Trajectory", "imu_samples", "EPOCH_US", "READOUT_US",
           "IMU_RATE_HZ"]
