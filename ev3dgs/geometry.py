"""Pose conventions and SE(3) helpers.

Poses are 4x4 float64 camera-to-world matrices with OpenCV camera axes (x right, y down, z forward). World
coordinates of synthetic scenes are Blender's (z up). Blender cameras look along their -z with y up, so
    c2w_opencv = c2w_blender @ diag(1, -1, -1, 1)       (and the same matrix converts back).
Intrinsics K follow OpenCV's pixel convention: the centre of the top-left pixel is (0, 0), so a centred
principal point is ((W - 1) / 2, (H - 1) / 2).
"""
from __future__ import annotations

import numpy as np

BLENDER_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def blender_to_opencv(c2w: np.ndarray) -> np.ndarray:
    return np.asarray(c2w, dtype=np.float64) @ BLENDER_TO_OPENCV


def opencv_to_blender(c2w: np.ndarray) -> np.ndarray:
    return np.asarray(c2w, dtype=np.float64) @ BLENDER_TO_OPENCV


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera-to-world at `eye` looking at `target`, image up roughly along `up`."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def intrinsics(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    fx = 0.5 * width / np.tan(np.deg2rad(fov_x_deg) / 2)
    return np.array([[fx, 0.0, (width - 1) / 2], [0.0, fx, (height - 1) / 2], [0.0, 0.0, 1.0]])


def project(K: np.ndarray, c2w: np.ndarray, points: np.ndarray) -> np.ndarray:
    """World points (N, 3) -> pixel coordinates (N, 2) (OpenCV convention) and depth (N,)."""
    w2c = np.linalg.inv(c2w)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    uv = pc @ np.asarray(K).T
    return uv[:, :2] / uv[:, 2:3], pc[:, 2]


def _vee_skew(R: np.ndarray) -> np.ndarray:
    """vee(R - R^T): (..., 3). For a rotation by angle theta about unit axis k this is 2 sin(theta) k."""
    return np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle in [0, pi] (radians) of rotation matrices (..., 3, 3).

    atan2(|vee(R - R^T)| / 2, (trace - 1) / 2) = atan2(sin, cos): both arguments carry an absolute error of a few
    ulp of the entries, and atan2 turns that into an absolute angle error of a few ulp over the whole range.
    (arccos((trace - 1) / 2) loses half the digits near 0 and near pi: an error of 1 ulp in the trace becomes
    ~1e-8 rad there, and the result then depends on the BLAS and CPU that formed R.)"""
    R = np.asarray(R, dtype=np.float64)
    sin = 0.5 * np.linalg.norm(_vee_skew(R), axis=-1)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin, cos)


def relative_rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle (radians) of Ra^T Rb for stacks of rotation matrices (..., 3, 3)."""
    Ra, Rb = np.asarray(Ra, dtype=np.float64), np.asarray(Rb, dtype=np.float64)
    return rotation_angle(np.swapaxes(Ra, -1, -2) @ Rb)


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vectors (..., 3) -> matrices (..., 3, 3).

    R = I + sin(t)/t K + (1 - cos t)/t^2 K^2 with K = [v]x, written with sinc so that no branch and no
    cancellation occurs: sin(t)/t = sinc(t/pi), (1 - cos t)/t^2 = 2 sin^2(t/2)/t^2 = sinc(t/(2 pi))^2 / 2."""
    v = np.asarray(v, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    k = np.zeros(v.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k = k - np.swapaxes(k, -1, -2)
    s = np.sinc(theta / np.pi)
    c = 0.5 * np.sinc(theta / (2 * np.pi)) ** 2
    return np.eye(3) + s * k + c * (k @ k)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> rotation vectors (..., 3) with angle in [0, pi].

    Away from pi the axis comes from vee(R - R^T) = 2 sin(t) k, so rotvec = vee * t / (2 sin t), with
    t / sin t = 1 / sinc(t/pi) bounded by pi/2 for t <= pi/2 (no division by a small number near 0). Near pi,
    sin t -> 0 and vee carries no direction: there the axis comes from the symmetric part,
    (R + R^T)/2 - cos(t) I = (1 - cos t) k k^T, whose largest-diagonal column is well conditioned, with the
    sign taken from vee (the two signs describe the same rotation at exactly pi)."""
    R = np.asarray(R, dtype=np.float64)
    batch = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    w = _vee_skew(R)
    theta = rotation_angle(R)
    out = np.empty((len(R), 3))
    near_pi = theta > np.pi / 2
    far = ~near_pi
    out[far] = w[far] * (0.5 / np.sinc(theta[far] / np.pi))[..., None]
    if np.any(near_pi):
        Rn, th, wn = R[near_pi], theta[near_pi], w[near_pi]
        cos = np.cos(th)
        B = 0.5 * (Rn + np.swapaxes(Rn, -1, -2)) - cos[:, None, None] * np.eye(3)
        i = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        col = B[np.arange(len(B)), :, i]
        k = col / np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.einsum("ni,ni->n", k, wn) < 0, -1.0, 1.0)
        out[near_pi] = k * (sign * th)[:, None]
    return out.reshape(batch + (3,))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (w, x, y, z), w >= 0. Shepperd's method: the largest of
    |w|, |x|, |y|, |z| is taken from a square root of a sum >= 1, so no step divides by a small number."""
    m = np.asarray(R, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2 * np.sqrt(t + 1)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(max(1 + m[i, i] - m[j, j] - m[k, k], 1.0))  # >= 1 in exact arithmetic for a rotation
        q = np.empty(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q, dtype=np.float64)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def _unit_quat(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"not a rotation: quaternion {q.tolist()} has norm {n}")
    return q / n


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = _unit_quat(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions along the shorter arc (a in [0, 1]).

    The half-angle between them comes from atan2(|q0 - q1|, |q0 + q1|) (accurate to a few ulp for any
    angle, unlike arccos of the dot product), and the weights sin(a th)/sin(th) are written as
    a sinc(a th/pi)/sinc(th/pi): exact down to th = 0 with no switch to linear interpolation."""
    q0, q1 = _unit_quat(q0), _unit_quat(q1)
    if float(np.dot(q0, q1)) < 0:
        q1 = -q1
    th = 2.0 * np.arctan2(np.linalg.norm(q0 - q1), np.linalg.norm(q0 + q1))  # angle between them, <= pi/2
    d = np.sinc(th / np.pi)
    q = ((1 - a) * np.sinc((1 - a) * th / np.pi) * q0 + a * np.sinc(a * th / np.pi) * q1) / d
    return q / np.linalg.norm(q)


def interpolate_pose(poses: np.ndarray, pose_t: np.ndarray, t: float) -> np.ndarray:
    """Camera-to-world at time t from samples (S, 4, 4) at sorted times (S,): slerp + lerp between the two
    neighbouring samples, clamped at the ends; exact at the sample times."""
    poses, pose_t = np.asarray(poses, float), np.asarray(pose_t)
    if len(poses) == 1 or t <= pose_t[0]:
        return poses[0].copy()
    if t >= pose_t[-1]:
        return poses[-1].copy()
    j = int(np.searchsorted(pose_t, t, side="right")) - 1
    a = (t - pose_t[j]) / (pose_t[j + 1] - pose_t[j])
    if a == 0:
        return poses[j].copy()
    out = np.eye(4)
    out[:3, :3] = quat_to_matrix(slerp(matrix_to_quat(poses[j][:3, :3]), matrix_to_quat(poses[j + 1][:3, :3]), a))
    out[:3, 3] = (1 - a) * poses[j][:3, 3] + a * poses[j + 1][:3, 3]
    return out


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising ||dst - (s R src + t)|| over point sets (N, 3) (Umeyama 1991).

    Degenerate sets still get a minimiser, never NaN: coincident source points (zero variance) give s = 1 and
    the rotation that the SVD of the (zero or rank-deficient) covariance returns; collinear or coplanar sets
    leave a rotation about the line (plane normal) free, and any of the minimisers is returned."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) == 0:
        raise ValueError(f"umeyama needs two (N, 3) point sets of the same N >= 1, got {src.shape} and {dst.shape}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise ValueError("umeyama: point sets must be finite")
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, R, md - s * R @ ms


def pose_errors(est_c2w: np.ndarray, gt_c2w: np.ndarray) -> dict:
    """Camera poses against ground truth in an arbitrary similarity frame. Centres: Umeyama alignment of the
    camera centres, then the centre error (ground-truth units, and relative to the trajectory extent).
    Orientations: the one rotation that best maps the estimated orientations onto the true ones (chordal
    mean), then each camera's angle error: a short, nearly planar path constrains the centre-based rotation
    poorly, which would otherwise show up as a spurious common rotation error. Angles come from
    `relative_rotation_angle` (atan2 form: a few ulp accurate, also for errors near 0)."""
    est, gt = np.asarray(est_c2w, float), np.asarray(gt_c2w, float)
    s, R, t = umeyama(est[:, :3, 3], gt[:, :3, 3])
    centres = (s * (R @ est[:, :3, 3].T)).T + t
    d_centre = np.linalg.norm(centres - gt[:, :3, 3], axis=1)
    U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", gt[:, :3, :3], est[:, :3, :3]))
    R_rot = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    d_rot = np.degrees(relative_rotation_angle(R_rot @ est[:, :3, :3], gt[:, :3, :3]))
    extent = float(np.linalg.norm(gt[:, :3, 3].max(0) - gt[:, :3, 3].min(0))) or 1.0
    # with the centre-based rotation too, for reference
    d_rot_c = np.degrees(relative_rotation_angle(R @ est[:, :3, :3], gt[:, :3, :3]))
    return {"rotation_deg_median": float(np.median(d_rot)), "rotation_deg_max": float(d_rot.max()),
            "rotation_deg_median_centre_aligned": float(np.median(d_rot_c)),
            "centre_error_median": float(np.median(d_centre)), "centre_error_max": float(d_centre.max()),
            "centre_error_rel_extent": float(np.median(d_centre) / extent), "scale": s, "n": len(est)}
