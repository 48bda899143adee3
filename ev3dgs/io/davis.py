"""A DAVIS346 recording (AEDAT 4.0 / 3.1 / 2.0) -> scene.h5.

Views are APS frames (every K-th, at most N, exposures of at least U us); each view's exposure window is the
frame's [start of exposure, end of exposure). Events are kept whole or within a margin of the used exposures,
the IMU is kept. Intrinsics come from a calibration file, or from pycolmap when there is none.

Undistortion policy: with a calibration whose distortion is non-zero, the APS frames are undistorted with
cv2.undistort keeping the same K, and every event's coordinates are undistorted to the nearest pixel
(events that land outside the sensor are dropped), so the scene file is a pure pinhole camera and
/camera/distortion is stored as zeros; the calibration's coefficients go to the file's config.

Poses (unless poses=False): for every view, the event double integral (ev3dgs.io.edi) turns the blurry frame
and the exposure's events into b+1 sharp latent frames at evenly spread times; pycolmap (SIFT, matching,
incremental mapping) on all latent frames gives a pose per latent frame -> /train/poses, /train/pose_t, and
its sparse points -> /points. A view is kept only if all its latent frames register.
"""
from __future__ import annotations

import contextlib
import dataclasses
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .. import schema
from ..errors import InputError
from ..events import Events
from ..logmap import DEFAULT_LOG_KNEE
from .calibration import load_calibration
from .recording import open_recording
from .edi import linear_to_srgb
from .motion import MotionCheck, camera_motion
from .types import FrameData

BAYER = ("RGGB", "BGGR", "GRBG", "GBRG")


@dataclass(frozen=True)
class DavisOptions:
    every: int = 1
    max_views: int | None = None
    min_exposure_us: int = 0
    events: str = "margin"            # "all" | "margin"
    event_margin_ms: float = 10.0
    subposes: int = 5                 # latent frames (and poses) per view
    poses: bool = True
    calibration: str | None = None
    frames_stream: str | None = None
    events_stream: str | None = None
    pos_threshold: float = 0.2        # the recording does not store the bias-derived thresholds
    neg_threshold: float = 0.2
    color_filter: str = "none"        # the DVS colour filter of a colour DAVIS346: pass it, it is not in the file
    min_registered: float = 0.5       # fraction of the latent frames pycolmap must register
    check_motion: bool = True         # refuse pose estimation on a camera that did not move (ev3dgs.io.motion)
    motion: MotionCheck = MotionCheck()
    aps_linear: bool = True           # DAVIS APS frames are linear in light: sRGB-encode them for the scene
    strict: bool = False              # reader: raise on a corrupt packet / contradicted value instead of dropping it
    sensor_size: tuple[int, int] | None = None   # AEDAT 2.0/3.1 without a camera name in the header: (W, H)
    sensor: str | None = None         # sensor TOML (ev3dgs.calib.sensor): thresholds, mismatch, noise, refractory

    def __post_init__(self):
        if self.every < 1:
            raise InputError("--every must be >= 1")
        if self.max_views is not None and self.max_views < 1:
            raise InputError("--max-views must be >= 1")
        if self.events not in ("all", "margin"):
            raise InputError("--events must be all or margin")
        if self.subposes < 2 and self.poses:
            raise InputError("--subposes must be >= 2 for pose estimation")
        if self.color_filter not in ("none", *BAYER):
            raise InputError(f"--color-filter must be none or one of {', '.join(BAYER)}")
        if not (self.pos_threshold > 0 and self.neg_threshold > 0):
            raise InputError("thresholds must be > 0")
        if not (0 <= self.min_registered <= 1):
            raise InputError(f"--min-registered must be a fraction in [0, 1], got {self.min_registered}")
        if not (np.isfinite(self.event_margin_ms) and self.event_margin_ms >= 0):  # < 0 keeps no event at all
            raise InputError(f"--event-margin-ms must be a finite number >= 0, got {self.event_margin_ms}")


@dataclass
class IngestStats:
    path: Path
    frames_in_file: int = 0
    views: int = 0
    registered: int | None = None
    latent_frames: int = 0
    events: int = 0                   # events in the scene file
    events_in_file: int = 0           # events in the recording's events stream (its FileDataTable, or as read)
    events_read: int = 0              # events --events selected, before undistortion drops those off the sensor
    exposures: int = 0                # exposures the --events margin windows surround (views before pose estimation)
    warnings: list = field(default_factory=list)


def to_rgb8(image: np.ndarray) -> np.ndarray:
    """A frame in the file's OpenCV order (GRAY, BGR, BGRA; 8 or 16 bit) -> RGB uint8 (values unchanged)."""
    img = image
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InputError(f"unsupported frame dtype {img.dtype}")
    if img.ndim == 2 or img.shape[-1] == 1:
        return np.repeat(img.reshape(img.shape[0], img.shape[1], 1), 3, axis=2)
    if img.shape[-1] == 3:
        return img[..., ::-1].copy()
    if img.shape[-1] == 4:
        return img[..., 2::-1].copy()
    raise InputError(f"unsupported frame with {img.shape[-1]} channels")


def min_exposure(opts: DavisOptions) -> int:
    """The exposure threshold applied (a frame with no exposure at all is never a view)."""
    return max(1, opts.min_exposure_us)


def select_frames(frames, opts: DavisOptions, width: int, height: int) -> tuple[list[FrameData], int]:
    kept, total, eligible = [], 0, 0
    for f in frames:
        total += 1
        if f.exposure_end - f.exposure_start < min_exposure(opts):
            continue
        if f.image.shape[:2] != (height, width) or tuple(f.position) != (0, 0):
            continue  # an ROI frame: not a full view of the scene
        if eligible % opts.every == 0 and (opts.max_views is None or len(kept) < opts.max_views):
            kept.append(f)
        eligible += 1
    return kept, total


def _merge_windows(windows: list[tuple[int, int]]) -> list[tuple[int, int]]:
    out = []
    for s, e in sorted(windows):
        if out and s <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], e))
        else:
            out.append((s, e))
    return out


def events_in_file(reader, stream=None) -> int | None:
    """Events in the recording's events stream as far as the reader already knows them, without decoding again:
    an AEDAT 4.0 file from its FileDataTable, an AEDAT 2.0/3.1 file from the pass that decoded it (kept in memory
    for files up to ~128 MiB). None when unknown (no FileDataTable, a large file kept only as a time index)."""
    if reader.format == "aedat4":
        sid = reader._select(stream, "events").id
        table = reader.packet_table()
        n = table["elements"][table["stream"] == sid]
        return int(n.sum()) if (n >= 0).all() else None
    info = getattr(reader, "_info", None)
    if isinstance(info, dict) and "events" in info and stream is None:
        return int(info["events"])
    if reader.format == "aedat2":
        cache = getattr(reader, "_cache", None)
        if cache is not None and cache.get("events") is not None:
            return sum(len(e) for e in cache["events"])
    elif reader.format == "aedat3.1":
        parts = getattr(reader, "_ev_cache", {}).get(reader._select(stream, "events"))
        if parts is not None:
            return sum(len(e) for e in parts)
    return None


def read_events_counted(reader, opts: DavisOptions, views: list[FrameData]) -> tuple[Events, int]:
    """(the events --events keeps, the events in the recording's stream). The total comes from what the reader
    knows (events_in_file); when it does not know it, the events are read in one pass that counts them and keeps
    those inside the windows (the same events, in the same order, as reading the windows)."""
    total = events_in_file(reader, opts.events_stream)
    if opts.events == "all" or not views:
        parts = list(reader.events(opts.events_stream))
        if total is None:
            total = sum(len(p) for p in parts)
    else:
        m = int(opts.event_margin_ms * 1000)
        windows = _merge_windows([(_window(v)[0] - m, _window(v)[1] + m) for v in views])
        parts = []
        if total is not None:   # the reader skips the packets outside the windows (FileDataTable, time index)
            for s, e in windows:
                parts.extend(reader.events(opts.events_stream, s, e))
        else:
            starts = np.array([w[0] for w in windows], np.int64)
            ends = np.array([w[1] for w in windows], np.int64)
            total = 0
            for ev in reader.events(opts.events_stream):
                total += len(ev)
                i = np.searchsorted(starts, ev.t, side="right") - 1
                keep = (i >= 0) & (ev.t < ends[np.maximum(i, 0)])
                if keep.any():
                    parts.append(ev if keep.all() else Events(ev.t[keep], ev.x[keep], ev.y[keep], ev.p[keep]))
    ev = Events.concatenate(parts)
    if len(ev) and (np.diff(ev.t) < 0).any():  # packets of one stream out of order: restore time order
        order = np.argsort(ev.t, kind="stable")
        ev = Events(ev.t[order], ev.x[order], ev.y[order], ev.p[order])
    return ev, int(total)


def read_events(reader, opts: DavisOptions, views: list[FrameData]) -> Events:
    return read_events_counted(reader, opts, views)[0]


def _window(v: FrameData) -> tuple[int, int]:
    """[start, end] covering the exposure of every row (a rolling-shutter frame exposes each row at its own time)."""
    r = v.row_exposure
    if r is None or not len(r):
        return v.exposure_start, v.exposure_end
    return min(v.exposure_start, int(r[:, 0].min())), max(v.exposure_end, int(r[:, 1].max()))


def undistort(images: list[np.ndarray], ev: Events, K: np.ndarray, dist: np.ndarray, width: int, height: int):
    images = [cv2.undistort(img, K, dist, None, K) for img in images]
    if len(ev):
        pts = np.stack([ev.x, ev.y], axis=1).astype(np.float64).reshape(-1, 1, 2)
        und = cv2.undistortPoints(pts, K, dist, P=K).reshape(-1, 2)
        x, y = np.rint(und[:, 0]), np.rint(und[:, 1])
        ok = (x >= 0) & (x < width) & (y >= 0) & (y < height)
        ev = Events(ev.t[ok], x[ok].astype(np.uint16), y[ok].astype(np.uint16), ev.p[ok])
    return images, ev


class StaticCameraError(InputError):
    """The recording's camera did not move: no pose can be estimated from it."""


class _Progress:
    """One line on a terminal, rewritten in place (nothing when stderr is not a terminal or quiet)."""

    def __init__(self, quiet: bool):
        self.on = not quiet and sys.stderr.isatty()
        self.t0 = time.monotonic()
        self.width = 0

    def __call__(self, text: str) -> None:
        if self.on:
            line = f"{text} [{time.monotonic() - self.t0:.0f} s]"
            sys.stderr.write("\r" + line.ljust(self.width))
            sys.stderr.flush()
            self.width = len(line)

    def close(self) -> None:
        if self.on and self.width:
            sys.stderr.write("\r" + " " * self.width + "\r")
            sys.stderr.flush()
            self.width = 0


@contextlib.contextmanager
def _sigterm_interrupts():
    """SIGTERM raises KeyboardInterrupt, as Ctrl-C does: temporary files are removed and the CLI ends with
    one line. Only in the main thread (signal handlers can be set only there)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _pose_hint(opts: DavisOptions, registered: int) -> str:
    """What the user can still try after pycolmap registered too few latent frames."""
    tips = []
    if registered >= 2 and opts.min_registered > 0:
        tips.append(f"a lower --min-registered (now {opts.min_registered:g}) keeps the frames that did register")
    if not opts.calibration:
        tips.append("--calibration with the lens calibration (pycolmap had to estimate the focal length too)")
    if opts.every > 1 or opts.max_views is not None:
        tips.append("more frames (--every 1, no --max-views): more overlap between neighbouring frames")
    if opts.subposes > 2:
        tips.append(f"fewer --subposes (now {opts.subposes}): a frame is kept only if all its sub-frames register")
    tips.append("--no-poses writes the frames, events and IMU without poses (for `ev3dgs info`, `ev3dgs view "
                "--out` and `ev3dgs export-dataset --format events-h5 or aedat4`)")
    return "try " + "; ".join(tips)


def estimate_view_poses(images: list[np.ndarray], ev: Events, views: list[FrameData], K, opts: DavisOptions,
                        progress=None):
    """EDI latent frames per view -> pycolmap. Returns (kept view indices, poses (n,S,4,4), pose_t (n,S),
    K used, points or None, registered count)."""
    from .colmap import PoseEstimationError, estimate_poses
    from .edi import edi_latent_frames, edi_to_uint8

    say = progress or (lambda text: None)
    S = opts.subposes
    N = len(views) * S
    latent_imgs, times = [], []
    for img, v in zip(images, views):
        say(f"EDI: {len(latent_imgs):,} of {N:,} sub-frames ({len(views)} frames x {S})")
        t = np.round(np.linspace(v.exposure_start, v.exposure_end, S)).astype(np.int64)
        w = ev.window(v.exposure_start, v.exposure_end + 1)
        gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float64) / 255.0  # APS values are linear
        lat = edi_latent_frames(gray, w.t, w.x, w.y, w.p, (v.exposure_start, v.exposure_end), t,
                                opts.pos_threshold, opts.neg_threshold)
        latent_imgs.extend(edi_to_uint8(frame) for frame in lat)
        times.append(t)
    stages = {"features": "SIFT features", "matching": "matching", "mapping": "mapping"}

    def colmap_progress(stage: str, registered: int) -> None:
        reg = f", {registered:,} registered so far" if stage == "mapping" else ""
        say(f"pose estimation: {stages[stage]} on {N:,} sub-frames ({len(views)} frames x {S}){reg}")

    with tempfile.TemporaryDirectory(prefix="ev3dgs_colmap_") as work:
        res = estimate_poses(latent_imgs, K, Path(work), min_registered=opts.min_registered,
                             progress=colmap_progress, what=f"sub-frames ({len(views)} frames x {S})",
                             hint=lambda registered: _pose_hint(opts, registered))
    kept, poses = [], []
    for i in range(len(views)):
        ps = res.poses[i * S:(i + 1) * S]
        if all(p is not None for p in ps):
            kept.append(i)
            poses.append(np.stack(ps))
    if not kept:
        raise PoseEstimationError(f"pycolmap registered {res.num_registered} of {N} sub-frames ({len(views)} frames "
                                  f"x {S}), but no frame had all its {S} sub-frames registered; "
                                  + _pose_hint(opts, res.num_registered))
    return kept, np.stack(poses), np.stack([times[i] for i in kept]), res.K, res, res.num_registered


def check_camera_moved(path, images: list[np.ndarray], imu, K, W: int, H: int, opts: DavisOptions):
    """Raise StaticCameraError when the IMU and the frames show a camera that did not move (ev3dgs.io.motion).
    Returns the MotionReport."""
    f = float(K[0, 0]) if K is not None else 0.5 * W / np.tan(np.deg2rad(35))
    gray = [cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) for img in images]
    report = camera_motion(gray, f, imu, opts.motion)
    if report.static:
        raise StaticCameraError(
            f"{path}: the camera did not move: {report.evidence()}. Training a 3D scene needs a recording made "
            "with a moving camera (views from different places), so no poses can be estimated from this one. "
            "With --no-poses ingest writes the frames, events and IMU without poses, for `ev3dgs info`, `ev3dgs "
            "view --out` and `ev3dgs export-dataset --format events-h5 or aedat4`; `ev3dgs-sim calibrate` and "
            "`ev3dgs-sim compare` read the recording itself (--no-motion-check estimates poses regardless)")
    return report


def ingest_davis(path: str | Path, out: str | Path, opts: DavisOptions = DavisOptions(),
                 quiet: bool = True) -> IngestStats:
    """`quiet`: no progress line on a terminal during EDI and pose estimation. SIGTERM ends it as Ctrl-C does
    (KeyboardInterrupt), with no temporary file left."""
    with _sigterm_interrupts():
        return _ingest_davis(path, out, opts, quiet)


def _ingest_davis(path, out, opts: DavisOptions, quiet: bool) -> IngestStats:
    out = Path(out)
    stats = IngestStats(out)
    sensor = None
    if opts.sensor is not None:   # before reading: a bad sensor file fails at once
        from dataclasses import replace

        from ..calib.sensor import load_sensor_toml

        sensor = load_sensor_toml(opts.sensor)
        opts = replace(opts, pos_threshold=sensor.pos_threshold, neg_threshold=sensor.neg_threshold,
                       color_filter=sensor.color_filter)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reader keeps its own list (opening included); we report it once
        with open_recording(path, strict=opts.strict, sensor_size=opts.sensor_size) as reader:
            W, H = reader.sensor_size()
            views, stats.frames_in_file = select_frames(reader.frames(opts.frames_stream), opts, W, H)
            if not views:
                n = stats.frames_in_file
                why = ("the recording has no APS frames (0 frames)" if n == 0 else
                       f"none of its {n} APS frames is usable (a view needs a full-size {W}x{H} frame at position "
                       f"(0, 0) exposed for >= {min_exposure(opts)} us)")
                raise InputError(f"{path}: {why}")
            ev, stats.events_in_file = read_events_counted(reader, opts, views)
            stats.events_read, stats.exposures = len(ev), len(views)
            imu = reader.imu()
            stats.warnings = list(reader.warnings)
            fmt = reader.format
    if any(v.rolling_shutter for v in views):
        stats.warnings.append("rolling-shutter APS frames: each row is exposed at its own time; the scene stores "
                              "the first row's exposure window per view (events are kept for every row's window)")
    images = [to_rgb8(v.image) for v in views]
    if opts.color_filter == "none" and any(v.image.ndim == 3 and v.image.shape[-1] >= 3 for v in views):
        stats.warnings.append("colour APS frames: a colour DAVIS346's DVS pixels sit under a Bayer filter that "
                              "the file does not name; pass --color-filter so the trainer models it")
    K, dist_in = None, np.zeros(5)
    if opts.calibration:
        cal = load_calibration(opts.calibration)
        if (cal.width, cal.height) != (W, H):
            raise InputError(f"{opts.calibration}: calibration is for {cal.width}x{cal.height}, the sensor is {W}x{H}")
        K, dist_in = cal.K, cal.distortion
        if np.any(dist_in != 0):
            images, ev = undistort(images, ev, K, dist_in, W, H)
    exposure = np.array([(v.exposure_start, v.exposure_end) for v in views], np.int64)
    train_kw, points = {}, None
    if opts.poses:
        if opts.check_motion:
            check_camera_moved(path, images, imu, K, W, H, opts)
        stats.latent_frames = len(views) * opts.subposes
        progress = _Progress(quiet)
        try:
            kept, poses, pose_t, K, res, stats.registered = estimate_view_poses(images, ev, views, K, opts,
                                                                                progress)
        finally:
            progress.close()
        # the views pose estimation dropped, for `ev3dgs view` (index among the usable frames, exposure, us)
        unregistered = [{"frame": i, "exposure": [int(v.exposure_start), int(v.exposure_end)]}
                        for i, v in enumerate(views) if i not in set(kept)]
        images = [images[i] for i in kept]
        exposure = exposure[kept]
        train_kw = dict(poses=poses, pose_t=pose_t)
        if res.points_xyz is not None and len(res.points_xyz):
            points = schema.Points(xyz=res.points_xyz.astype(np.float32), rgb=res.points_rgb.astype(np.uint8))
    if K is None:  # no calibration and no pose estimation: a nominal DAVIS346 lens, flagged in the config
        f = 0.5 * W / np.tan(np.deg2rad(35))
        K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    stats.views, stats.events = len(images), len(ev)
    if opts.aps_linear:  # the schema's images are sRGB; a DAVIS APS frame is linear in light
        lut = np.round(255 * linear_to_srgb(np.arange(256) / 255.0)).astype(np.uint8)
        images = [lut[img] for img in images]
    scene = schema.Scene(
        name=Path(path).stem, source="davis",
        camera=schema.Camera(width=W, height=H, K=np.asarray(K, float), distortion=np.zeros(5)),
        events=ev,
        sensor=sensor or schema.EventSensor(pos_threshold=opts.pos_threshold, neg_threshold=opts.neg_threshold,
                                            color_filter=opts.color_filter, refractory_us=0.0,
                                            log_knee=DEFAULT_LOG_KNEE,
                                            count_convention="random_phase"),  # a running sensor's reference
        train=schema.Train(images=np.stack(images), exposure=exposure, transfer="srgb", **train_kw),
        points=points,
        imu=schema.Imu(t=imu.t, accel=imu.accel, gyro=imu.gyro, temperature=imu.temperature) if len(imu) else None,
        config={"recording": str(path), "format": fmt, "options": dataclasses.asdict(opts),
                "intrinsics": "calibration file" if opts.calibration else
                ("pycolmap estimate" if opts.poses else "nominal 70-degree guess (no calibration, no poses)"),
                "input_distortion": dist_in.tolist(), "undistorted": bool(np.any(dist_in != 0)),
                "frames_in_file": stats.frames_in_file, "events_in_file": stats.events_in_file,
                "registered_latent_frames": stats.registered,
                **({"unregistered_views": unregistered} if opts.poses else {}),
                "reader_warnings": stats.warnings},
    )
    schema.write(scene, out)
    return stats
