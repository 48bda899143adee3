"""A scene file as the trainer needs it: float images, cameras, the b+1 sub-poses of every exposure, and the
raw events binned ONCE into signed counts between consecutive sub-pose times."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .. import schema
from ..errors import InputError
from ..geometry import interpolate_pose
from ..logmap import DEFAULT_LOG_KNEE
from .events import bin_polarity_events, sub_pose_times
from .subposes import exposure_motion, motion_points, subpose_counts


@dataclass
class TrainData:
    name: str
    width: int
    height: int
    K: torch.Tensor                    # (3,3)
    background: torch.Tensor           # (3,) in image (sRGB) units
    images: torch.Tensor               # (N,H,W,3) blurry frames in [0,1]
    sub_times: np.ndarray              # (N,B) int64
    viewmats: torch.Tensor             # (N,B,4,4) world->camera at the sub-pose times
    mid_viewmats: torch.Tensor         # (N,4,4) world->camera at the exposure midpoint
    bins: torch.Tensor | None          # (N,B-1,2,H,W) ON/OFF event counts between sub-poses, None without events
    pos_threshold: float
    neg_threshold: float
    color_filter: str
    log_knee: float
    camera_centres: np.ndarray         # (N,3)
    points: tuple[np.ndarray, np.ndarray] | None
    bounds: np.ndarray | None
    transfer: str = "srgb"             # the scene's /train transfer (schema.TRANSFERS)
    count_convention: str = "random_phase"  # /events count_convention (schema.COUNT_CONVENTIONS)
    raw_matrix: np.ndarray | None = None    # /events camera_raw_matrix (Bayer pixels; None = identity)
    blur_space: str = "linear"         # resolved: how the trainer averages renders (blur_loss space)
    event_transfer: str = "srgb"       # resolved: what log_intensity decodes ("srgb", "linear", "display")
    sub_c2w: np.ndarray | None = None  # (N,B,4,4) float64 camera-to-world of the sub-poses (pose refinement)
    mismatch_sigma: float | None = None   # absolute per-pixel threshold spread (log units) of the sensor model
    noise_rate_hz: float | None = None    # background-activity events per pixel and second (leak + shot noise)
    sensor_source: dict | None = None     # where each came from: "scene" (/events attrs), "provenance (legacy)"
    n_sub: np.ndarray | None = None       # (N,) sub-poses of each view (--subpose-px); None: all B of them.
    # A view with k < B uses [:k] of viewmats, sub_times and sub_c2w and [:k-1] of bins (the rest is padding)
    motion_px: np.ndarray | None = None   # (N,) the image motion --subpose-px measured per exposure

    @property
    def n_views(self) -> int:
        return self.images.shape[0]

    def sub_count(self, v: int) -> int:
        """How many of view v's sub-poses it uses (all B unless --subpose-px chose fewer)."""
        return int(self.viewmats.shape[1] if self.n_sub is None else self.n_sub[v])

    @property
    def scene_scale(self) -> float:
        """3DGS's camera extent: 1.1 x the largest distance of a camera from the cameras' centre."""
        c = self.camera_centres
        return 1.1 * float(np.linalg.norm(c - c.mean(axis=0), axis=1).max() or 1.0)


def _w2c(c2w: np.ndarray) -> np.ndarray:
    return np.linalg.inv(c2w)


def resolve_domains(transfer: str, blur_space: str = "auto", event_domain: str = "auto") -> tuple[str, str]:
    """(blur space, event transfer) for a scene's /train transfer, "auto" taken from it, flags on top.
    Blur: "srgb" images are sRGB-encoded linear-light blur -> average in "linear"; "display" and "linear"
    images were blurred in the stored values -> plain mean ("srgb", i.e. no decode). Events: "display" ->
    log of display values (no decode, luma); otherwise log of linear light (decoded if the images are sRGB);
    --event-domain linear / display overrides."""
    blur = blur_space if blur_space != "auto" else ("linear" if transfer == "srgb" else "srgb")
    if event_domain == "auto":
        ev = transfer
    elif event_domain == "display":
        ev = "display"
    else:
        ev = "linear" if transfer == "linear" else "srgb"
    return blur, ev


def _view_times(exposure: np.ndarray, n_sub: np.ndarray) -> np.ndarray:
    """(N, max n_sub) int64: view v's n_sub[v] sub-pose times spread over its exposure, then its end time
    repeated (padding: a step slices each view to its own count)."""
    exposure = np.asarray(exposure, dtype=np.int64)
    times = np.repeat(exposure[:, 1:], int(n_sub.max()), axis=1)
    for k in np.unique(n_sub):
        rows = n_sub == k
        times[rows, :k] = sub_pose_times(exposure[rows], int(k))
    return times


def _view_bins(ev, times: np.ndarray, n_sub: np.ndarray, height: int, width: int) -> np.ndarray:
    """ON/OFF counts between each view's own sub-poses, (N, max n_sub - 1, 2, H, W), zero in the padding."""
    out = np.zeros((len(times), times.shape[1] - 1, 2, height, width), dtype=np.float32)
    for k in np.unique(n_sub):
        rows = np.flatnonzero(n_sub == k)
        out[rows, :k - 1] = bin_polarity_events(ev.t, ev.x, ev.y, ev.p, times[rows, :k], height, width)
    return out


def load_train_data(path: str | Path, subposes: int, device="cpu", dtype=torch.float32, blur_space: str = "auto",
                    event_domain: str = "auto", oracle: bool = False, subpose_px: float = 0.0) -> TrainData:
    """``oracle``: the sharp frames (/train/sharp) at their sharp poses as the training images, one pose per
    view and no events (the sharp-oracle upper bound of the evaluation protocol). ``subpose_px`` > 0: each
    view gets the fewest sub-poses (2 to ``subposes``) spaced at most that many pixels along its exposure's
    largest image motion (subposes.py); 0: every view gets ``subposes``."""
    sc = schema.read(path, require_complete=True)
    tr = sc.train
    if oracle and (tr.sharp is None or tr.sharp_poses is None):
        raise InputError(f"{path}: --oracle needs /train/sharp and /train/sharp_poses (a simulated scene)")
    if tr.poses is None:
        raise InputError(f"{path}: /train/poses is missing (a recording ingested with --no-poses): training needs "
                         "camera poses, which `ev3dgs-ingest davis` estimates only from a recording made with a "
                         "moving camera; a static camera's file is for `ev3dgs info`, `ev3dgs view --out` and "
                         "`ev3dgs export-dataset --format events-h5 or aedat4`, and `ev3dgs-sim calibrate` / "
                         "`compare` read its recording")
    if subposes < 1:
        raise InputError(f"--subposes must be >= 1, got {subposes}")
    if np.any(np.asarray(sc.camera.distortion) != 0):   # the renderer is a pinhole: refuse, never ignore
        raise InputError(f"{path}: /camera/distortion is {np.asarray(sc.camera.distortion).tolist()}: the trainer "
                         "renders a pinhole camera and cannot model lens distortion; undistort the frames and "
                         "events first (ev3dgs-ingest davis does, given the calibration)")
    N, H, W = len(tr), sc.camera.height, sc.camera.width
    n_sub = motion = None
    if subpose_px > 0 and subposes > 1 and not oracle:
        xyz = None if sc.points is None else np.asarray(sc.points.xyz)
        motion = exposure_motion(tr.poses, tr.pose_t, tr.exposure, sc.camera.K, W, H,
                                 motion_points(xyz, sc.bounds))
        n_sub = subpose_counts(motion, subpose_px, subposes)
        times = _view_times(tr.exposure, n_sub)
    else:
        times = sub_pose_times(np.asarray(tr.exposure), subposes)
    sub = np.stack([[interpolate_pose(tr.poses[v], tr.pose_t[v], t) for t in times[v]] for v in range(N)])
    mid_t = np.asarray(tr.exposure).mean(axis=1)
    mid = np.stack([interpolate_pose(tr.poses[v], tr.pose_t[v], mid_t[v]) for v in range(N)])
    bins = None
    if len(sc.events) and subposes > 1 and not oracle:
        ev = sc.events.load()
        binned = (bin_polarity_events(ev.t, ev.x, ev.y, ev.p, times, H, W) if n_sub is None
                  else _view_bins(ev, times, n_sub, H, W))
        bins = torch.from_numpy(binned).to(device)
    if oracle:  # one pose per view, the one the sharp frame was taken at
        sub = np.asarray(tr.sharp_poses)[:, None]
        mid = np.asarray(tr.sharp_poses)
    transfer = tr.transfer or schema.default_transfer(sc.source)
    blur, ev_transfer = resolve_domains(transfer, blur_space, event_domain)
    bg = sc.camera.background if sc.camera.background is not None else (0.0, 0.0, 0.0)
    to = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype, device=device)  # noqa: E731
    images = torch.from_numpy(np.asarray(tr.sharp if oracle else tr.images)).to(device=device, dtype=dtype) / 255.0
    points = None
    if sc.points is not None:
        points = (np.asarray(sc.points.xyz), np.asarray(sc.points.rgb))
    return TrainData(
        name=sc.name, width=W, height=H, K=to(sc.camera.K), background=to(bg), images=images,
        sub_times=times, viewmats=to(np.linalg.inv(sub)), mid_viewmats=to(np.linalg.inv(mid)), bins=bins,
        pos_threshold=float(sc.sensor.pos_threshold), neg_threshold=float(sc.sensor.neg_threshold),
        color_filter=sc.sensor.color_filter,
        log_knee=float(sc.sensor.log_knee) if sc.sensor.log_knee is not None else DEFAULT_LOG_KNEE,
        camera_centres=mid[:, :3, 3], points=points,
        bounds=None if sc.bounds is None else np.asarray(sc.bounds),
        transfer=transfer,
        count_convention=sc.sensor.count_convention or schema.default_count_convention(sc.source, sc.config),
        raw_matrix=sc.sensor.camera_raw_matrix, blur_space=blur, event_transfer=ev_transfer, sub_c2w=sub,
        n_sub=n_sub, motion_px=motion, **sensor_model(sc.sensor, sc.config),
    )


def sensor_model(sensor, config: dict) -> dict:
    """{mismatch_sigma, noise_rate_hz, sensor_source} of the event noise model: the scene's declared sensor
    model (/events attrs mismatch_sigma, leak_rate_hz, shot_noise_rate_hz: schema.SENSOR_MODEL_ATTRS), each
    value where the file declares it. A file that declares none of them (made before they were declared) falls
    back to its simulator provenance where it has one (legacy_sensor_noise); otherwise None: the trainer's
    defaults (terms/events.py)."""
    sigma = getattr(sensor, "mismatch_sigma", None)
    rates = [getattr(sensor, k, None) for k in ("leak_rate_hz", "shot_noise_rate_hz")]
    if sigma is not None or any(r is not None for r in rates):
        rate = None if all(r is None for r in rates) else float(sum(r or 0.0 for r in rates))
        return {"mismatch_sigma": None if sigma is None else float(sigma), "noise_rate_hz": rate,
                "sensor_source": {"mismatch_sigma": "scene" if sigma is not None else "default",
                                  "noise_rate_hz": "scene" if rate is not None else "default"}}
    legacy = legacy_sensor_noise(config)
    src = {k: ("provenance (legacy)" if legacy[k] is not None else "default") for k in legacy}
    return {**legacy, "sensor_source": src}


def legacy_sensor_noise(config: dict) -> dict:
    """LEGACY, for scene files simulated before /events declared the sensor model: {mismatch_sigma,
    noise_rate_hz} from the simulator's provenance (/config sim.dvs); None where the file does not say."""
    sim = config.get("sim") if isinstance(config, dict) else None
    dvs = sim.get("dvs") if isinstance(sim, dict) else None
    if not isinstance(dvs, dict):
        return {"mismatch_sigma": None, "noise_rate_hz": None}

    def num(table, key):
        v = table.get(key) if isinstance(table, dict) else None
        return float(v) if isinstance(v, (int, float)) and np.isfinite(v) and v >= 0 else None

    sigma = num(dvs.get("threshold_mismatch"), "sigma")
    rate = sum(num(dvs.get(k), "rate_hz") or 0.0 for k in ("leak", "shot_noise"))
    return {"mismatch_sigma": 0.0 if sigma is None else sigma, "noise_rate_hz": rate}
