"""What `ev3dgs view` shows, as plain numpy arrays: no viser, no matplotlib (both front ends read from here).

* exposure trajectories: each training view's pose samples (/train/poses at /train/pose_t) as a polyline of
  camera centres in time order, with its start and end;
* camera frusta: the pinhole's vertical field of view, aspect, orientation (wxyz) and centre, in viser's
  convention (OpenCV axes: +z forward, +x right, +y down), and the world corners of the image plane at a depth;
* event images: the events of one view's window [start, t) counted per pixel and polarity, ON and OFF drawn
  in the colours of ev3dgs/palette.py on a white background; the window is the exposure, or, when the exposure
  holds too few events to show anything (a short exposure on a real sensor), the interval to the next frame
  (``event_window`` says which);
* Gaussian splats: centres, 3x3 covariances R diag(s^2) R^T, base colours (the degree-0 SH term, no view
  dependence) and opacities from the same raw parameters `ev3dgs export` writes;
* IMU-integrated rotation: the gyro (camera frame, deg/s) integrated from the first pose sample, beside the
  estimated orientations of an ingested recording;
* the frames of an ingested recording that failed to register (pose estimation dropped them).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import schema
from ..event_file import EventFile
from ..errors import InputError
from ..geometry import matrix_to_quat, relative_rotation_angle, rotvec_to_matrix

from .. import palette  # the polarity colours of every figure (ON red, OFF blue, white background)


# ------------------------------------------------------------------------------------ geometry

def trajectory_polylines(poses: np.ndarray, pose_t: np.ndarray) -> np.ndarray:
    """Camera centres (N, S, 3) of every view's pose samples, each view's samples in time order (a polyline
    from the exposure's start, [:, 0], to its end, [:, -1])."""
    poses, pose_t = np.asarray(poses, np.float64), np.asarray(pose_t)
    if poses.ndim != 4 or poses.shape[-2:] != (4, 4) or pose_t.shape != poses.shape[:2]:
        raise InputError(f"poses {poses.shape} and pose times {pose_t.shape}: expected (N, S, 4, 4) and (N, S)")
    order = np.argsort(pose_t, axis=1, kind="stable")
    centres = poses[..., :3, 3]
    return np.take_along_axis(centres, order[..., None], axis=1)


@dataclass
class Frustum:
    fov_y: float            # vertical field of view, radians
    aspect: float           # width / height
    wxyz: np.ndarray        # camera-to-world rotation as a unit quaternion (w >= 0)
    position: np.ndarray    # camera centre (3,)


def frustum(c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> Frustum:
    """The frustum viser draws for a pinhole camera (principal point taken as the image centre)."""
    c2w, K = np.asarray(c2w, np.float64), np.asarray(K, np.float64)
    return Frustum(2 * np.arctan(0.5 * height / K[1, 1]), width / height, matrix_to_quat(c2w[:3, :3]),
                   c2w[:3, 3].copy())


def image_corners(c2w: np.ndarray, K: np.ndarray, width: int, height: int, depth: float) -> np.ndarray:
    """World points (4, 3) of the image's corners (0,0), (W,0), (W,H), (0,H) on the plane z = depth of the
    camera (pixel corners, not centres)."""
    uv1 = np.array([[0, 0, 1], [width, 0, 1], [width, height, 1], [0, height, 1]], np.float64)
    cam = depth * (np.linalg.solve(np.asarray(K, np.float64), uv1.T)).T
    c2w = np.asarray(c2w, np.float64)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def world_up(rotations: np.ndarray) -> np.ndarray:
    """The mean of the cameras' up vectors (-y in OpenCV axes), normalised: the 'up' of a top view."""
    up = -np.asarray(rotations, np.float64).reshape(-1, 3, 3)[:, :, 1].mean(axis=0)
    n = np.linalg.norm(up)
    return up / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])


def top_view_basis(rotations: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal axes of the plane perpendicular to `world_up`: world points @ basis.T -> 2-D."""
    up = world_up(rotations)
    helper = np.eye(3)[int(np.argmin(np.abs(up)))]
    a = np.cross(up, helper)
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(up, a)])


# -------------------------------------------------------------------------------------- events

def polarity_counts(x: np.ndarray, y: np.ndarray, p: np.ndarray, width: int, height: int):
    """(on, off): per-pixel event counts (H, W) of each polarity."""
    idx = np.asarray(y, np.int64) * width + np.asarray(x, np.int64)
    pos = np.asarray(p) > 0
    on = np.bincount(idx[pos], minlength=width * height).reshape(height, width)
    off = np.bincount(idx[~pos], minlength=width * height).reshape(height, width)
    return on, off


def event_image(on: np.ndarray, off: np.ndarray, saturation: float | None = None) -> np.ndarray:
    """An RGB uint8 picture of ON/OFF counts: white where no event fired, palette.ON_RGB / OFF_RGB at
    `saturation` counts or more, linear in between; a pixel with both mixes them (their weights add). The
    default saturation is the 99th percentile of the non-zero per-pixel counts (at least 1), so one hot pixel
    does not wash out the rest."""
    on, off = np.asarray(on, np.float64), np.asarray(off, np.float64)
    if saturation is None:
        nz = np.concatenate([on[on > 0], off[off > 0]])
        saturation = max(1.0, float(np.percentile(nz, 99))) if nz.size else 1.0
    a_on = np.minimum(on / saturation, 1.0)[..., None]
    a_off = np.minimum(off / saturation, 1.0)[..., None]
    bg = np.asarray(palette.BACKGROUND_RGB, np.float64)
    img = bg + a_on * (np.asarray(palette.ON_RGB) - bg) + a_off * (np.asarray(palette.OFF_RGB) - bg)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


MIN_WINDOW_EVENTS = 0.01   # an exposure with fewer events than this fraction of the pixels shows the interval


def event_window(exposure: np.ndarray, i: int, count, width: int, height: int) -> tuple[int, int, str]:
    """(start, end, what) of the events shown for view i: its exposure when that holds at least
    MIN_WINDOW_EVENTS x the pixel count of events, else the interval from its exposure's start to the next
    view's (the last view: as long as the previous interval), when that is longer. `count(start, end)` counts
    the events in [start, end). `what` names the window for a caption, e.g. "exposure, 100.0 ms" or "to the
    next frame, 33.3 ms (the 0.50 ms exposure holds 12 events)"."""
    exposure = np.asarray(exposure, np.int64)
    start, end = (int(v) for v in exposure[i])
    n = int(count(start, end))
    if n >= MIN_WINDOW_EVENTS * width * height or len(exposure) < 2:
        return start, end, f"exposure, {_ms(end - start)}"
    if i + 1 < len(exposure):
        nxt = int(exposure[i + 1, 0])
    else:
        nxt = start + int(exposure[i, 0] - exposure[i - 1, 0])
    if nxt <= end:
        return start, end, f"exposure, {_ms(end - start)}"
    return start, nxt, f"to the next frame, {_ms(nxt - start)} (the {_ms(end - start)} exposure holds {n} events)"


def _ms(us: int) -> str:
    return f"{us / 1000:.1f} ms" if us >= 10_000 else f"{us / 1000:.2f} ms"


def accumulation_time(exposure: np.ndarray, fraction: float) -> int:
    """The time (us) a slider position in [0, 1] stands for inside [start, end)."""
    start, end = (int(v) for v in exposure)
    return start + int(round(min(max(float(fraction), 0.0), 1.0) * (end - start)))


# ------------------------------------------------------------------------------------------ IMU

def integrate_gyro(t_us: np.ndarray, gyro_dps: np.ndarray, times_us: np.ndarray) -> np.ndarray:
    """Rotations (K, 3, 3) of the camera from times_us[0] to each of times_us, from gyro samples in the camera
    frame (deg/s): dR/dt = R [w]x, with w linear between samples and each step between consecutive sample or
    query times taken as exp(w(midpoint) dt) (exact for a constant rate, and for a rate linear in time about a
    fixed axis). Query times outside the IMU's time span are NaN."""
    t = np.asarray(t_us, np.int64)
    w = np.deg2rad(np.asarray(gyro_dps, np.float64))
    q = np.asarray(times_us, np.int64)
    out = np.full((len(q), 3, 3), np.nan)
    if len(t) < 2 or len(q) == 0:
        return out
    t0 = q[0]
    ok = (q >= t[0]) & (q <= t[-1])
    if not (t[0] <= t0 <= t[-1]):
        return out
    lo, hi = min(q[ok].min(), t0), max(q[ok].max(), t0)
    grid = np.unique(np.concatenate([t[(t > lo) & (t < hi)], q[ok], [t0]]))
    mid = 0.5 * (grid[1:] + grid[:-1])
    rate = np.stack([np.interp(mid, t, w[:, k]) for k in range(3)], axis=1)
    steps = rotvec_to_matrix(rate * (np.diff(grid) * 1e-6)[:, None])
    cum = np.empty((len(grid), 3, 3))
    cum[0] = np.eye(3)
    for i, s in enumerate(steps):
        cum[i + 1] = cum[i] @ s
    # rotation from t0: R(t0)^T R(t) (both from grid[0])
    base = cum[np.searchsorted(grid, t0)]
    sel = np.searchsorted(grid, q[ok])
    out[ok] = np.einsum("ji,njk->nik", base, cum[sel])
    return out


@dataclass
class ImuComparison:
    rotations: np.ndarray        # (N, S, 3, 3) camera-to-world rotations predicted by the gyro (NaN: no IMU data)
    angle_deg: np.ndarray        # (N,) angle between the gyro's and the estimated rotation at each view's mid sample


def imu_rotations(imu: schema.Imu, poses: np.ndarray, pose_t: np.ndarray) -> ImuComparison:
    """The gyro integrated from the first pose sample (in time) and started at its estimated orientation:
    R_imu(t) = R_est(t_first) dR_gyro(t_first -> t), for every pose sample. The angle per view compares it with
    the estimated rotation at the view's middle sample (gyro bias and pose error both show up there)."""
    poses, pose_t = np.asarray(poses, np.float64), np.asarray(pose_t, np.int64)
    n, s = pose_t.shape
    flat_t = pose_t.reshape(-1)
    first = int(np.argmin(flat_t))
    order = np.concatenate([[first], np.delete(np.arange(n * s), first)])
    rel = np.empty((n * s, 3, 3))
    rel[order] = integrate_gyro(imu.t, imu.gyro, flat_t[order])
    r0 = poses.reshape(-1, 4, 4)[first, :3, :3]
    rot = (r0 @ rel).reshape(n, s, 3, 3)
    mid = s // 2
    ang = np.full(n, np.nan)
    good = np.isfinite(rot[:, mid]).all(axis=(1, 2))
    if good.any():
        ang[good] = np.rad2deg(relative_rotation_angle(rot[good, mid], poses[good, mid, :3, :3]))
    return ImuComparison(rot, ang)


# ---------------------------------------------------------------------------------- registration

def failed_registrations(scene: schema.Scene) -> list[str]:
    """The frames of an ingested recording that pose estimation dropped, one line each (from the config that
    `ingest davis` writes: "unregistered_views", or for older files the counts only)."""
    cfg = scene.config or {}
    rows = cfg.get("unregistered_views")
    if isinstance(rows, list):
        return [f"frame {r.get('frame')} (exposure {r.get('exposure', ['?', '?'])[0]}-"
                f"{r.get('exposure', ['?', '?'])[1]} us)" for r in rows if isinstance(r, dict)]
    reg, opts = cfg.get("registered_latent_frames"), cfg.get("options")
    if isinstance(reg, int) and isinstance(opts, dict) and isinstance(opts.get("subposes"), int) and \
            scene.train is not None and scene.train.poses is not None:
        kept = len(scene.train) * opts["subposes"]
        if reg > kept:  # registered latent frames of views that were dropped (not all of theirs registered)
            return [f"{reg - kept} registered latent frames belong to views that were dropped "
                    "(this file predates the per-frame list)"]
    return []


# ------------------------------------------------------------------------------------- splats

def splat_arrays(model) -> dict[str, np.ndarray]:
    """The arrays viser's add_gaussian_splats takes, from a GaussianModel: centers (N,3), covariances
    (N,3,3) = R diag(s^2) R^T, rgbs (N,3) in [0,1] (degree-0 SH colour) and opacities (N,1), float32."""
    import torch

    with torch.no_grad():
        q = model.quats_normalised.double()
        w, x, y, z = q.unbind(-1)
        R = torch.stack([
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)
        s2 = model.scales.double() ** 2
        cov = (R * s2[:, None, :]) @ R.transpose(1, 2)
        from ..splat.sh import sh_to_rgb

        rgb = sh_to_rgb(model.params["sh0"][:, 0].double()).clamp(0, 1)
        out = {"centers": model.means, "covariances": cov, "rgbs": rgb, "opacities": model.opacities[:, None]}
        return {k: v.detach().to("cpu", torch.float32).numpy() for k, v in out.items()}


# -------------------------------------------------------------------------------------- content

@dataclass
class SceneContent:
    """Everything a viewer of one scene file shows, read once."""
    path: Path
    scene: schema.Scene
    train_poses: np.ndarray | None      # (N, S, 4, 4)
    pose_t: np.ndarray | None           # (N, S)
    exposure: np.ndarray | None         # (N, 2)
    test_poses: np.ndarray | None       # (M, 4, 4)
    imu: ImuComparison | None
    failed: list[str]
    extent: float                       # a length of the scene's size (for frusta and markers)

    @property
    def n_views(self) -> int:
        return 0 if self.scene.train is None else len(self.scene.train)

    @property
    def size(self) -> tuple[int, int]:
        return self.scene.camera.width, self.scene.camera.height

    def frame(self, i: int) -> np.ndarray:
        return self.scene.train.images[i]

    def sharp(self, i: int) -> np.ndarray | None:
        return None if self.scene.train.sharp is None else self.scene.train.sharp[i]

    def polylines(self) -> np.ndarray | None:
        return None if self.train_poses is None else trajectory_polylines(self.train_poses, self.pose_t)

    def mid_poses(self) -> np.ndarray | None:
        return None if self.train_poses is None else self.train_poses[:, self.train_poses.shape[1] // 2]

    def event_window(self, reader: EventFile, i: int) -> tuple[int, int, str]:
        """(start, end, what) of view i's events: the exposure, or the interval to the next frame when the
        exposure holds too few events (see the module function `event_window`)."""
        def count(a, b):  # two binary searches over the time stamps
            return reader._index(b) - reader._index(a)

        return event_window(self.exposure, i, count, *self.size)

    def event_counts(self, reader: EventFile, i: int, fraction: float = 1.0):
        """(on, off) counts of view i's event window (`event_window`) from its start up to `fraction` of it."""
        start, end, _ = self.event_window(reader, i)
        _, x, y, p = reader.window(start, accumulation_time((start, end), fraction))
        return polarity_counts(x, y, p, *self.size)


def _extent(centres: np.ndarray | None, bounds: np.ndarray | None) -> float:
    sizes = []
    if centres is not None and len(centres) > 1:
        sizes.append(float(np.linalg.norm(np.ptp(centres, axis=0))))
    if bounds is not None:
        sizes.append(float(np.linalg.norm(np.asarray(bounds)[1] - np.asarray(bounds)[0])))
    return max([s for s in sizes if np.isfinite(s)] + [1e-3])


def load_scene(path: str | os.PathLike) -> SceneContent:
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such scene file or run folder")
    sc = schema.read(p)
    tr = sc.train
    poses = None if tr is None or tr.poses is None else np.asarray(tr.poses, np.float64)
    pose_t = None if poses is None else np.asarray(tr.pose_t, np.int64)
    imu = None
    if sc.imu is not None and poses is not None and len(sc.imu.t) >= 2:
        imu = imu_rotations(sc.imu, poses, pose_t)
    test = None if sc.test is None else np.asarray(sc.test.poses, np.float64)
    centres = None if poses is None else poses[:, :, :3, 3].reshape(-1, 3)
    return SceneContent(p, sc, poses, pose_t, None if tr is None else np.asarray(tr.exposure, np.int64), test,
                        imu, failed_registrations(sc), _extent(centres, sc.bounds))


@dataclass
class RunContent:
    """A training run: its scene's content, its Gaussians and, where it refined poses, the refined ones."""
    path: Path
    scene: SceneContent
    model: object                       # GaussianModel
    source: str                         # "model.pt" or "ckpt.pt (step N)"
    refined_poses: np.ndarray | None = None   # (N, S, 4, 4) from RUN/trajectory.npz
    refined_t: np.ndarray | None = None
    config: dict = field(default_factory=dict)


def _refined(run: Path, sc: SceneContent):
    f = run / "trajectory.npz"
    if not f.is_file():
        return None, None
    try:
        with np.load(f) as z:
            poses, pose_t = np.asarray(z["poses"], np.float64), np.asarray(z["pose_t"], np.int64)
    except (OSError, ValueError, KeyError) as e:
        raise InputError(f"{f}: not a readable trajectory (poses and pose_t expected: {e})") from None
    n = sc.n_views
    if poses.ndim != 4 or poses.shape[0] != n or poses.shape[2:] != (4, 4) or pose_t.shape != poses.shape[:2]:
        raise InputError(f"{f}: poses {poses.shape} / pose_t {pose_t.shape} do not match the scene's {n} views")
    return poses, pose_t


def _scene_of_run(run: Path, config: dict, override: str | os.PathLike | None = None,
                  other_scene: bool = False) -> Path:
    """The run's scene file (train/run_scene.py): the --scene override, else the path config.json records
    relative to the run folder, its absolute path, an old run's path as given (from the current folder, the
    run folder or its parents), the file name beside the run folder or in its parents."""
    from ..train.run_scene import resolve_scene

    return resolve_scene(run, config, override, other_scene)


def load_run_content(run_dir: str | os.PathLike, device="cpu", scene: str | os.PathLike | None = None,
                     other_scene: bool = False) -> RunContent:
    """A run folder's model (model.pt, or the latest ckpt.pt of a run still training) and its scene (`scene`:
    the --scene override; one that is not the run's scene only with `other_scene`)."""
    from ..splat.model import GaussianModel
    from ..train.checkpoint import read_checkpoint

    run = Path(run_dir)
    if not run.is_dir():
        raise InputError(f"{run}: no such scene file or run folder")
    if not (run / "config.json").is_file():
        raise InputError(f"{run}: not a training run (no config.json; `ev3dgs view` takes a scene .h5 or a run "
                         "folder written by `ev3dgs train`)")
    try:
        config = json.loads((run / "config.json").read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{run / 'config.json'}: not readable ({e})") from None
    if not isinstance(config, dict) or not isinstance(config.get("scene"), str):
        raise InputError(f"{run / 'config.json'}: names no scene file")
    scene_path = _scene_of_run(run, config, scene, other_scene)
    if (run / "model.pt").is_file():
        from ..train.evaluate import load_run

        _, model = load_run(run, device, scene=scene_path, other_scene=True)  # checked just above
        source = "model.pt"
    elif (run / "ckpt.pt").is_file():
        payload = read_checkpoint(run / "ckpt.pt", device)
        model = GaussianModel.from_state_dict(payload["model"], device=device)
        source = f"ckpt.pt (step {payload['step']})"
    else:
        raise InputError(f"{run}: the run has no checkpoint yet (no model.pt or ckpt.pt)")
    sc = load_scene(scene_path)
    poses, pose_t = _refined(run, sc)
    return RunContent(run, sc, model, source, poses, pose_t, config)


def load(path: str | os.PathLike) -> SceneContent | RunContent:
    """A scene file or a run folder, whichever `path` is."""
    p = Path(path)
    if p.is_dir():
        return load_run_content(p)
    return load_scene(p)
