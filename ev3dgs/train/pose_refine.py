"""Exposure-trajectory refinement (``ev3dgs train --refine-poses``): learnable SE(3) corrections of every
training view's camera path inside its exposure, optimised with the Gaussians by the blur and event losses.

Parametrisation
---------------
Per view v two 6-vectors, at the start (a = 0) and the end (a = 1) of the exposure, each
(rho, omega): rho (3) a translation of the camera centre in world units divided by the scene scale, omega (3)
a rotation vector in radians. Sub-pose k of the exposure (time t_k, a_k = (t_k - t_start) / (t_end - t_start);
a = 1/2 for a single mid-exposure pose) gets the linear interpolation xi_k = (1 - a_k) xi_start + a_k xi_end,
applied to the stored camera-to-world pose (OpenCV axes) as a LEFT perturbation about the camera's own centre:

    R'_k = Exp(Q omega_k) R_k          (a rotation about the centre: the image rotates, the camera stays put)
    c'_k = c_k + scene_scale * Q rho_k  (the centre moves)

i.e. a correction of (SO(3) x R^3), decoupled so that an orientation error (what a photometric loss sees most)
is corrected without moving the centre. ``frame`` picks the axes the 12 numbers are written in:

* ``"world"``: Q = I, world axes.
* ``"camera"``: Q = R_ref, the stored rotation of the view's reference sub-pose (the one nearest the middle
  of the exposure: the mid-exposure pose for an odd number of sub-poses, e.g. the default 5), so omega and
  rho are in that camera's own OpenCV axes (x right, y down, z the optical axis: omega_z is the roll). At the
  reference sub-pose R'_k = R_k Exp(omega_k) (a right perturbation); at the others the axes stay those of
  the reference camera (one fixed set of axes per view, whatever the motion inside the exposure).

The two frames are one linear change of coordinates per view (an orthogonal one): the same set of corrected
trajectories, the same gauge subspace and the same clamps; what differs is Adam, whose per-coordinate
normalisation scales each coordinate on its own, so in "camera" the weakly observed roll (omega_z) gets steps
of its own size instead of being mixed with pan/tilt.

The corrected world->camera matrices feed the
rasterizer, whose backward (every backend; ``cpu``: project_cpu.py's hand-written camera gradient) gives
d(loss)/d(viewmat), and autograd carries it to the 12 numbers of the view. The interpolation is linear in the
correction, which is exact for a constant offset of the whole exposure and first order otherwise.

Gauge
-----
The losses only compare renders of the model with images: moving every camera AND the scene by one similarity
transform (rotation, translation, scale: 7 degrees of freedom) leaves them unchanged. Left free, the corrections
drift along that null space (the Gaussians follow slowly), the refined frame wanders away from the frame the
test cameras are given in, and the pose error is ill-defined. After every update the corrections' component
in that subspace is removed: to first order a similarity (w, tau, s) about the mean camera centre o changes
(omega, rho) of every endpoint by (w, (w x (c - o) + tau + s (c - o)) / scene_scale); its least-squares
fit to all corrections (the pseudo-inverse: rank-deficient sets, e.g. one view, still get a minimiser) is
subtracted. In ``"camera"`` the basis rows of each endpoint are rotated into the view's axes (block
diagonal Q^T, Q^T), an orthogonal map: the projection removes exactly the same subspace as in "world".
``gauge="none"`` keeps the corrections as they are (for a fixed, known scene).

Guard
-----
A step whose pose gradient is not finite is skipped (counted in ``skipped``); after each update every
endpoint's rotation is clamped to ``max_rotation_deg`` and its translation to ``max_translation`` x the scene
scale (rescaled, direction kept): a correction larger than that is not a refinement but a lost camera.

Schedule
--------
Adam (its own; one parameter per view, so a view's moments only move when it is rendered), learning rate
0 before ``start``, rising linearly over ``warmup`` steps to ``lr``, then decaying exponentially to
``lr * lr_final`` at the last iteration (like the 3DGS position learning rate).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError

GAUGES = ("similarity", "none")
FRAMES = ("world", "camera")


def _hat(w: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(w[..., 0])
    return torch.stack([z, -w[..., 2], w[..., 1], w[..., 2], z, -w[..., 0], -w[..., 1], w[..., 0], z],
                       -1).reshape(w.shape[:-1] + (3, 3))


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues, (..., 3) -> (..., 3, 3), with finite values and gradients at w = 0: the coefficients
    sin(t)/t and (1 - cos t)/t^2 come from their Taylor series below t^2 = 1e-6 (truncation error
    t^6/5040 < 1e-21) and from the closed form (with a t that is never 0) above."""
    t2 = (w * w).sum(-1)[..., None, None]
    small = t2 < 1e-6
    ts = torch.where(small, torch.ones_like(t2), t2).sqrt()
    a = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(ts) / ts)
    b = torch.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, (1 - torch.cos(ts)) / (ts * ts))
    K = _hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(K.shape)
    return eye + a * K + b * (K @ K)


def gauge_basis(centres: np.ndarray, scene_scale: float, axes: np.ndarray | None = None) -> np.ndarray:
    """(M, 6, 7): the first-order change of the M endpoints' corrections (rho, omega) under the similarity
    generators (w (3), tau (3), s (1)) about the centres' mean; world axes, or, with ``axes`` (M, 3, 3) the
    rotations Q of the endpoints' correction frames, in those axes (rows rotated by Q^T)."""
    d = (centres - centres.mean(0)) / scene_scale
    M = len(centres)
    A = np.zeros((M, 6, 7))
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        A[:, :3, i] = np.cross(e[None], d)  # w x (c - o)
        A[:, 3 + i, i] = 1.0
        A[:, i, 3 + i] = 1.0  # tau, in units of the scene scale like rho
    A[:, :3, 6] = d
    if axes is not None:
        Qt = np.swapaxes(np.asarray(axes, np.float64), -1, -2)
        A = np.concatenate([Qt @ A[:, :3], Qt @ A[:, 3:]], axis=1)
    return A


def reference_rotations(c2w: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """(N, 3, 3): per view the stored rotation of the sub-pose nearest the middle of the exposure (fraction
    0.5; the first of a tie), the axes of the "camera" frame."""
    k = np.argmin(np.abs(np.asarray(fractions, np.float64) - 0.5), axis=1)
    return np.asarray(c2w, np.float64)[np.arange(len(k)), k, :3, :3]


class PoseRefiner:
    """Corrections of N views' exposure trajectories. ``c2w`` (N, B, 4, 4) float64 sub-poses (camera-to-world,
    OpenCV axes) at ``times`` (N, B) us; ``fractions`` (N, B) their place in the exposure (0 start, 1 end)."""

    def __init__(self, c2w: np.ndarray, times: np.ndarray, fractions: np.ndarray, scene_scale: float, *,
                 lr: float = 1e-3, lr_final: float = 0.01, start: int = 0, warmup: int = 0,
                 iterations: int = 1, max_rotation_deg: float = 5.0, max_translation: float = 0.1,
                 gauge: str = "similarity", frame: str = "world", device="cpu"):
        c2w = np.asarray(c2w, np.float64)
        if c2w.ndim != 4 or c2w.shape[2:] != (4, 4) or not np.isfinite(c2w).all():
            raise InputError(f"pose refinement needs finite (N, B, 4, 4) poses, got {c2w.shape}")
        if gauge not in GAUGES:
            raise InputError(f"gauge must be one of {GAUGES}, got {gauge!r}")
        if frame not in FRAMES:
            raise InputError(f"frame must be one of {FRAMES}, got {frame!r}")
        self.N, self.B = c2w.shape[:2]
        self.device = torch.device(device)
        self.c2w0 = c2w
        self.times = np.asarray(times, np.int64)
        self.scene_scale = float(scene_scale)
        self.lr, self.lr_final, self.start, self.warmup = float(lr), float(lr_final), int(start), int(warmup)
        self.iterations = max(1, int(iterations))
        self.max_rot = math.radians(float(max_rotation_deg))
        self.max_trans = float(max_translation)
        self.gauge, self.frame = gauge, frame
        t = lambda a: torch.as_tensor(a, dtype=torch.float64, device=self.device)  # noqa: E731
        self.R0, self.c0 = t(c2w[..., :3, :3]), t(c2w[..., :3, 3])
        self.frac = t(np.asarray(fractions, np.float64))[..., None]  # (N, B, 1)
        # the correction frame's axes per view (None: world axes, no product, bitwise the world-frame maths)
        self.Q = reference_rotations(c2w, fractions) if frame == "camera" else None
        self._Q = None if self.Q is None else t(self.Q)
        self.params = [torch.zeros(2, 6, dtype=torch.float64, device=self.device, requires_grad=True)
                       for _ in range(self.N)]
        self.opt = torch.optim.Adam(self.params, lr=self.lr)
        self.skipped = 0
        ends = np.concatenate([c2w[:, 0, :3, 3], c2w[:, -1, :3, 3]])  # (2N, 3): starts, then ends
        axes = None if self.Q is None else np.concatenate([self.Q, self.Q])
        A = gauge_basis(ends, self.scene_scale, axes).reshape(2 * self.N * 6, 7)
        # least-squares fit of the 7 generators: coef = pinv(A) x (rank-deficient A, e.g. one view: minimum
        # norm); applied with torch in the trainer's pinned-thread context (bitwise reproducible)
        self._gauge_A = A
        self._gauge = (t(A), t(np.linalg.pinv(A, rcond=1e-10)))

    @classmethod
    def for_training(cls, data, cfg, device) -> "PoseRefiner":
        """From the trainer's data (its float64 sub-poses) and config (the [poses] table; the learning rate decays
        over the run's schedule length)."""
        times = np.asarray(data.sub_times)
        span = (times[:, -1:] - times[:, :1]).astype(np.float64)
        frac = np.where(span > 0, (times - times[:, :1]) / np.where(span > 0, span, 1.0), 0.5)
        return cls(data.sub_c2w, times, frac, data.scene_scale, lr=cfg.pose_lr, lr_final=cfg.pose_lr_final,
                   start=cfg.pose_start, warmup=cfg.pose_warmup, iterations=cfg.schedule_iterations,
                   max_rotation_deg=cfg.pose_max_rotation, max_translation=cfg.pose_max_translation,
                   gauge=cfg.pose_gauge, frame=cfg.pose_frame, device=device)

    # ------------------------------------------------------------------ poses
    def corrections(self, v: int) -> torch.Tensor:
        """(B, 6) interpolated (rho, omega) of view v's sub-poses (differentiable)."""
        p = self.params[v]
        return (1 - self.frac[v]) * p[0] + self.frac[v] * p[1]

    def world_corrections(self, v: int) -> torch.Tensor:
        """(B, 6) the interpolated corrections in world axes: (Q rho, Q omega) (differentiable)."""
        xi = self.corrections(v)
        if self._Q is None:
            return xi
        Qt = self._Q[v].transpose(0, 1)
        return torch.cat([xi[:, :3] @ Qt, xi[:, 3:] @ Qt], -1)

    def _rotation_centre(self, v: int) -> tuple[torch.Tensor, torch.Tensor]:
        xi = self.world_corrections(v)
        return so3_exp(xi[:, 3:]) @ self.R0[v], self.c0[v] + self.scene_scale * xi[:, :3]

    @staticmethod
    def _homogeneous(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        bottom = R.new_zeros(len(R), 1, 4)   # (0, 0, 0, 1) made on the device: no host-to-device copy per step
        bottom[..., 3] = 1.0
        return torch.cat([torch.cat([R, t[:, :, None]], -1), bottom], -2)

    def c2w(self, v: int) -> torch.Tensor:
        """(B, 4, 4) corrected camera-to-world sub-poses of view v (float64, differentiable)."""
        return self._homogeneous(*self._rotation_centre(v))

    def viewmats(self, v: int, dtype=torch.float32) -> torch.Tensor:
        """(B, 4, 4) world->camera of view v's corrected sub-poses: [R^T, -R^T c] (a rigid inverse)."""
        R, c = self._rotation_centre(v)
        Rt = R.transpose(-1, -2)
        return self._homogeneous(Rt, -(Rt @ c[:, :, None])[..., 0]).to(dtype)

    @torch.no_grad()
    def all_c2w(self) -> np.ndarray:
        """(N, B, 4, 4) refined trajectory, float64."""
        return np.stack([self.c2w(v).cpu().numpy() for v in range(self.N)])

    @torch.no_grad()
    def table(self, world: bool = False) -> np.ndarray:
        """(N, 2, 6) corrections in world units: translation of the centre (3), rotation vector in rad (3);
        in the frame's axes, or with ``world`` in world axes."""
        p = torch.stack(self.params).cpu().numpy().copy()
        p[..., :3] *= self.scene_scale
        if world and self.Q is not None:
            p = np.concatenate([np.einsum("nij,nkj->nki", self.Q, p[..., :3]),
                                np.einsum("nij,nkj->nki", self.Q, p[..., 3:])], -1)
        return p

    # ------------------------------------------------------------------ optimisation
    def lr_at(self, step: int) -> float:
        """0 before start, linear warm-up over ``warmup`` steps, then exponential decay to lr * lr_final."""
        if step < self.start:
            return 0.0
        ramp = min(1.0, (step - self.start + 1) / self.warmup) if self.warmup > 0 else 1.0
        frac = min(1.0, max(0.0, (step - self.start) / max(1, self.iterations - self.start)))
        return self.lr * ramp * self.lr_final ** frac

    def step(self, step: int) -> dict:
        """After loss.backward(): one Adam update of the views rendered this step (skipped when the learning
        rate is 0 or a gradient is not finite), then the gauge projection and the clamp."""
        lr = self.lr_at(step)
        grads = [p.grad for p in self.params if p.grad is not None]
        finite = all(bool(torch.isfinite(g).all()) for g in grads)
        applied = lr > 0 and finite and bool(grads)
        if grads and not finite:
            self.skipped += 1
        if applied:
            for group in self.opt.param_groups:
                group["lr"] = lr
            self.opt.step()
            self._project()
        self.opt.zero_grad(set_to_none=True)
        return {"pose_lr": lr, "pose_skipped": self.skipped}

    @torch.no_grad()
    def _project(self) -> None:
        P = torch.stack(self.params)  # (N, 2, 6)
        if self.gauge == "similarity":
            A, pinv = self._gauge
            flat = P.transpose(0, 1).reshape(-1)  # starts then ends, like the rows of A
            flat = flat - A @ (pinv @ flat)
            P = flat.reshape(2, self.N, 6).transpose(0, 1)
        rot = P[..., 3:].norm(dim=-1, keepdim=True)
        trn = P[..., :3].norm(dim=-1, keepdim=True)
        P[..., 3:] *= torch.where(rot > self.max_rot, self.max_rot / rot.clamp_min(1e-300), torch.ones_like(rot))
        P[..., :3] *= torch.where(trn > self.max_trans, self.max_trans / trn.clamp_min(1e-300),
                                  torch.ones_like(trn))
        for v, p in enumerate(self.params):
            p.copy_(P[v])

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        return {"params": torch.stack([p.detach() for p in self.params]).clone(), "opt": self.opt.state_dict(),
                "skipped": self.skipped, "frame": self.frame}

    def load_state_dict(self, state: dict) -> None:
        saved = state.get("frame", "world")  # checkpoints from before the option held world-frame corrections
        if saved != self.frame:
            raise InputError(f"the checkpoint's pose corrections are in the {saved!r} frame, not {self.frame!r}")
        with torch.no_grad():
            for v, p in enumerate(self.params):
                p.copy_(state["params"][v])
        self.opt.load_state_dict(state["opt"])
        self.skipped = int(state["skipped"])

    def save(self, path: str | Path) -> None:
        """trajectory.npz: ``poses`` (N, B, 4, 4) refined camera-to-world (OpenCV axes) at ``pose_t`` (N, B) us
        (the b+1 sub-pose times of each exposure), ``initial_poses`` the stored ones at the same times,
        ``corrections`` (N, 2, 6) (centre translation in world units, rotation vector in rad) at the
        exposure's start and end in the axes of ``frame`` ("world" or "camera"), ``corrections_world`` the
        same in world axes, ``frame_rotations`` (N, 3, 3) the axes Q of each view's corrections (identity for
        "world"), and ``perturbation`` ("left, about the camera centre")."""
        from ..outputs import atomic_path

        with atomic_path(Path(path)) as tmp, open(tmp, "wb") as f:
            np.savez(f, poses=self.all_c2w(), pose_t=self.times, initial_poses=self.c2w0,
                     corrections=self.table(), corrections_world=self.table(world=True), frame=np.array(self.frame),
                     frame_rotations=np.tile(np.eye(3), (self.N, 1, 1)) if self.Q is None else self.Q,
                     perturbation=np.array("left, about the camera centre"))


def load_trajectory(path: str | Path, n_views: int) -> dict:
    """A run's trajectory.npz, checked: poses (N, S, 4, 4) finite, pose_t (N, S) sorted per view."""
    try:
        with np.load(path) as z:
            out = {k: z[k] for k in ("poses", "pose_t", "initial_poses")}
    except (OSError, KeyError, ValueError, EOFError) as e:
        raise InputError(f"{path}: not a readable trajectory.npz ({e})") from None
    p, t = out["poses"], out["pose_t"]
    if p.ndim != 4 or p.shape[0] != n_views or p.shape[2:] != (4, 4) or t.shape != p.shape[:2]:
        raise InputError(f"{path}: poses must be ({n_views}, S, 4, 4) with pose_t ({n_views}, S), got "
                         f"{p.shape} and {t.shape}")
    if not np.isfinite(p).all() or (np.diff(t, axis=1) < 0).any():
        raise InputError(f"{path}: poses must be finite and pose_t sorted per view")
    return out


def align_similarity(src_c2w: np.ndarray, dst_c2w: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, R, t) taking cameras ``src_c2w`` (M, 4, 4) onto ``dst_c2w``: R the chordal mean of
    the per-camera rotations R_dst R_src^T (SVD projection, orientation-based: well conditioned even for few,
    nearly coplanar centres), then s and t by least squares on the centres given R. Returns s, R, t such
    that a camera c2w maps to [R R_c, s R c + t]."""
    src, dst = np.asarray(src_c2w, float), np.asarray(dst_c2w, float)
    M = np.einsum("nij,nkj->ik", dst[:, :3, :3], src[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    a, b = src[:, :3, 3], dst[:, :3, 3]
    ac, bc = a - a.mean(0), b - b.mean(0)
    den = float((ac ** 2).sum())
    s = float(np.einsum("ni,ni->", (R @ ac.T).T, bc) / den) if den > 0 else 1.0
    t = b.mean(0) - s * R @ a.mean(0)
    return s, R, t


def apply_similarity(c2w: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = np.array(c2w, dtype=np.float64, copy=True)
    out[:, :3, :3] = R @ out[:, :3, :3]
    out[:, :3, 3] = s * (R @ out[:, :3, 3].T).T + t
    return out


__all__ = ["PoseRefiner", "so3_exp", "gauge_basis", "reference_rotations", "load_trajectory", "align_similarity",
           "apply_similarity", "GAUGES", "FRAMES"]
