"""A small scene file whose content is known in closed form, for the viewer's tests (no Blender, no renderer).

Cameras orbit the origin at distance D while panning about their own y axis at a constant OMEGA_DPS: the
camera-to-world rotation is R(t) = R_BASE exp([0, omega t, 0]x) and the centre -D * (its z axis), so a gyro
that reads (0, OMEGA_DPS, 0) integrates to exactly the poses. Events: per view, a fixed set at known pixels
and times inside its exposure, and a few between exposures (which no view's window may count).
"""
import numpy as np

from ev3dgs import schema
from ev3dgs.events import Events
from ev3dgs.geometry import intrinsics, look_at, rotvec_to_matrix

W, H = 48, 32
N, S = 4, 5
D = 3.0
OMEGA_DPS = 60.0
EXPOSURE_US, PERIOD_US = 100_000, 200_000
R_BASE = look_at([0.0, -D, 0.0], [0, 0, 0])[:3, :3]


def pose_at(t_us: float) -> np.ndarray:
    R = R_BASE @ rotvec_to_matrix(np.array([0.0, np.deg2rad(OMEGA_DPS) * t_us * 1e-6, 0.0]))
    c2w = np.eye(4)
    c2w[:3, :3] = R
    c2w[:3, 3] = -D * R[:, 2]
    return c2w


def view_events(rng: np.random.Generator):
    """Per view: (x, y, p, t) of its exposure's events; plus the events between exposures."""
    per_view, between = [], []
    for v in range(N):
        start = v * PERIOD_US
        n = 200 + 50 * v
        t = np.sort(rng.integers(start, start + EXPOSURE_US, n))
        per_view.append((rng.integers(0, W, n), rng.integers(0, H, n), rng.choice([-1, 1], n), t))
        tb = rng.integers(start + EXPOSURE_US, start + PERIOD_US, 30)
        between.append((rng.integers(0, W, 30), rng.integers(0, H, 30), rng.choice([-1, 1], 30), tb))
    return per_view, between


def frame(v: int, sharp: bool = False) -> np.ndarray:
    """A distinct picture per view: a gradient whose colour and stripe count depend on v."""
    yy, xx = np.mgrid[0:H, 0:W]
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = (xx * 255 // (W - 1)).astype(np.uint8)
    img[..., 1] = ((yy * 255 // (H - 1)) ^ (40 * v)).astype(np.uint8)
    img[..., 2] = np.where((xx // (4 + v)) % 2 == 0, 60 + 40 * v, 230 - 30 * v).astype(np.uint8)
    return img if not sharp else np.ascontiguousarray(img[:, ::-1])


def make_scene(path, with_imu: bool = True, registration: list | None = None) -> str:
    rng = np.random.default_rng(7)
    per_view, between = view_events(rng)
    parts = [np.stack(a, axis=1) for a in per_view + between]
    allev = np.concatenate(parts)
    allev = allev[np.argsort(allev[:, 3], kind="stable")]
    ev = Events(allev[:, 3], allev[:, 0], allev[:, 1], allev[:, 2])
    pose_t = np.stack([v * PERIOD_US + np.linspace(0, EXPOSURE_US, S).astype(np.int64) for v in range(N)])
    poses = np.stack([[pose_at(t) for t in row] for row in pose_t])
    imu = None
    if with_imu:
        ti = np.arange(-10_000, N * PERIOD_US + 10_000, 1000, dtype=np.int64)
        gyro = np.tile(np.array([0.0, OMEGA_DPS, 0.0], np.float32), (len(ti), 1))
        accel = np.tile(np.array([0.0, -1.0, 0.0], np.float32), (len(ti), 1))
        imu = schema.Imu(t=ti, accel=accel, gyro=gyro, temperature=np.full(len(ti), 30.0, np.float32))
    test_poses = np.stack([look_at([D * np.cos(a), D * np.sin(a), 0.5], [0, 0, 0]) for a in (0.3, 2.0)])
    pts = rng.uniform(-0.5, 0.5, (60, 3)).astype(np.float32)
    config = {"test": "view"}
    if registration is not None:
        config["unregistered_views"] = registration
    sc = schema.Scene(
        name="viewtest", source="test", camera=schema.Camera(W, H, K=intrinsics(W, H, 60), background=(1, 1, 1)),
        events=ev, sensor=schema.EventSensor(), bounds=np.array([[-0.6] * 3, [0.6] * 3]), imu=imu,
        train=schema.Train(images=np.stack([frame(v) for v in range(N)]),
                           exposure=np.stack([pose_t[:, 0], pose_t[:, 0] + EXPOSURE_US], axis=1),
                           poses=poses, pose_t=pose_t, sharp=np.stack([frame(v, True) for v in range(N)]),
                           sharp_poses=poses[:, S // 2]),
        test=schema.Test(images=np.stack([frame(9), frame(8)]), poses=test_poses),
        points=schema.Points(pts, rng.integers(0, 255, (60, 3)).astype(np.uint8)),
        config=config)
    schema.write(sc, path)
    return str(path)
