"""Camera paths and frame output for ``ev3dgs render``.

Poses are 4x4 camera-to-world matrices with OpenCV axes (see ``ev3dgs.geometry``); world up is +z.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import torch

from ..errors import InputError
from ..geometry import look_at

__all__ = ["orbit_path", "scene_target", "render_frames", "write_frames"]

WORLD_UP = np.array([0.0, 0.0, 1.0])
MAX_ELEVATION_DEG = 85.0  # keeps the orbit a real circle and look_at away from its degenerate case


def _as_poses(poses) -> np.ndarray:
    if isinstance(poses, torch.Tensor):
        poses = poses.detach().cpu().numpy()
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim == 2 and p.shape == (4, 4):
        p = p[None]
    if p.ndim != 3 or p.shape[1:] != (4, 4) or len(p) == 0:
        raise InputError(f"poses must be (N, 4, 4) with N >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InputError("poses contain NaN or inf")
    return p


def scene_target(poses) -> np.ndarray:
    """The point closest (least squares) to all the cameras' optical axes.

    Falls back to a point in front of the cameras (the mean centre plus the mean viewing direction times
    the cameras' spread, or 1 unit) when the axes are (nearly) parallel or meet behind the cameras.
    """
    p = _as_poses(poses)
    centres = p[:, :3, 3]
    dirs = p[:, :3, 2] / np.linalg.norm(p[:, :3, 2], axis=1, keepdims=True)
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # (N,3,3) projectors orthogonal to each axis
    a = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, centres)
    eig = np.linalg.eigvalsh(a)
    if eig[0] > 1e-3 * len(p):  # well conditioned: axes are not all parallel
        t = np.linalg.solve(a, b)
        depth = np.einsum("ni,ni->n", t[None] - centres, dirs)
        if np.median(depth) > 0:
            return t
    mean_dir = dirs.mean(0)
    nd = np.linalg.norm(mean_dir)
    mean_dir = mean_dir / nd if nd > 1e-9 else dirs[0]
    spread = float(np.sqrt(((centres - centres.mean(0)) ** 2).sum(1).mean()))
    return centres.mean(0) + mean_dir * (spread if spread > 1e-9 else 1.0)


def orbit_path(mid_poses, n_frames: int, target=None) -> np.ndarray:
    """A closed circular orbit (n_frames, 4, 4) around ``target`` looking at it.

    ``target`` defaults to :func:`scene_target`.  The circle lies at the mean camera distance from the
    target and the mean camera elevation above it (world z up; clamped to +-85 deg), starts at the first
    camera's azimuth and turns counter-clockwise (seen from above) by 2*pi/n_frames per frame, so frame
    n_frames would coincide with frame 0: the path loops seamlessly and consecutive poses differ by the
    same rotation about z.
    """
    p = _as_poses(mid_poses)
    n_frames = int(n_frames)
    if n_frames < 1:
        raise InputError(f"n_frames must be >= 1, got {n_frames}")
    t = scene_target(p) if target is None else np.asarray(
        target.detach().cpu().numpy() if isinstance(target, torch.Tensor) else target, dtype=np.float64
    ).reshape(-1)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise InputError(f"target must be a finite 3-vector, got {t}")
    off = p[:, :3, 3] - t
    dist = np.linalg.norm(off, axis=1)
    radius = float(dist.mean())
    if radius < 1e-9:
        raise InputError("the cameras sit on the orbit target; give another target")
    elev = float(np.mean(np.arctan2(off[:, 2], np.linalg.norm(off[:, :2], axis=1))))  # no division, any distance
    lim = np.deg2rad(MAX_ELEVATION_DEG)
    elev = float(np.clip(elev, -lim, lim))
    # start azimuth: the first camera not straight above/below the target
    horiz = off[:, :2]
    hn = np.linalg.norm(horiz, axis=1)
    i0 = int(np.argmax(hn > 1e-9 * max(radius, 1.0))) if np.any(hn > 1e-9 * max(radius, 1.0)) else -1
    az0 = float(np.arctan2(horiz[i0, 1], horiz[i0, 0])) if i0 >= 0 else 0.0

    r_h, h = radius * np.cos(elev), radius * np.sin(elev)
    out = np.empty((n_frames, 4, 4))
    for i in range(n_frames):
        az = az0 + 2.0 * np.pi * i / n_frames
        eye = t + np.array([r_h * np.cos(az), r_h * np.sin(az), h])
        out[i] = look_at(eye, t, WORLD_UP)
    return out


@torch.no_grad()
def render_frames(model, poses, K, width: int, height: int, background=None, backend: str = "cpu",
                  threads: int | None = None) -> Iterator[np.ndarray]:
    """Render each camera-to-world pose; yields uint8 (height, width, 3) RGB frames.

    Colours come from the model's SH at ``model.active_sh_degree``; ``background`` is an RGB triple in
    [0, 1] (default black).  Lazy: one frame is rendered per ``next``.
    """
    from ..splat.rasterize import rasterization

    p = _as_poses(poses)
    width, height = int(width), int(height)
    dev, dt = model.device, model.dtype
    Kt = torch.as_tensor(np.asarray(K.detach().cpu() if isinstance(K, torch.Tensor) else K, np.float64),
                         dtype=dt, device=dev)
    if Kt.shape != (3, 3):
        raise InputError(f"K must be (3, 3), got {tuple(Kt.shape)}")
    bg = torch.zeros(3, dtype=dt, device=dev) if background is None else torch.as_tensor(
        np.asarray(background.detach().cpu() if isinstance(background, torch.Tensor) else background, np.float64),
        dtype=dt, device=dev).reshape(-1)
    if bg.shape != (3,):
        raise InputError(f"background must be an RGB triple, got shape {tuple(bg.shape)}")
    means, quats, scales, opac = model.means, model.quats_normalised, model.scales, model.opacities
    deg = int(model.active_sh_degree)
    sh = model.sh[:, : (deg + 1) ** 2]
    for c2w in p:
        viewmat = torch.as_tensor(np.linalg.inv(c2w), dtype=dt, device=dev)
        img, _, _ = rasterization(means, quats, scales, opac, sh, viewmat, Kt, width, height,
                                  sh_degree=deg, background=bg, backend=backend, threads=threads)
        yield (img[..., :3].clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).cpu().numpy()


def _check_frame(frame, i: int, size) -> np.ndarray:
    f = np.asarray(frame)
    if f.dtype != np.uint8 or f.ndim != 3 or f.shape[2] != 3:
        raise InputError(f"frame {i}: expected uint8 (H, W, 3), got {f.dtype} {f.shape}")
    if size is not None and f.shape[:2] != size:
        raise InputError(f"frame {i}: size {f.shape[:2]} differs from the first frame's {size}")
    return np.ascontiguousarray(f[..., ::-1])  # RGB -> BGR for OpenCV


def write_frames(frames: Iterable[np.ndarray], out: str | os.PathLike, fps: float = 30) -> int:
    """Write RGB uint8 frames to ``out``; returns the number written.

    ``out`` ending in ``.mp4``: an mp4v video, written to a temporary name beside it and renamed at the end
    (InputError "cannot write mp4 here; give a folder for PNGs" when this OpenCV cannot open the writer).
    Anything else: a folder (created) of ``frame_0000.png``, ``frame_0001.png``, ...
    """
    import cv2

    out = Path(out)
    if out.suffix.lower() == ".mp4":
        if not fps > 0:
            raise InputError(f"fps must be > 0, got {fps}")
        from ..outputs import remove_stale_temps

        out.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(out.parent, out.stem)  # left by a killed render of the same file
        tmp = out.with_name(f".{out.stem}.tmp-{os.getpid()}.mp4")
        writer, size, n = None, None, 0
        try:
            for i, frame in enumerate(frames):
                bgr = _check_frame(frame, i, size)
                if writer is None:
                    size = bgr.shape[:2]
                    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps),
                                             (size[1], size[0]))
                    if not writer.isOpened():
                        raise InputError("cannot write mp4 here; give a folder for PNGs")
                writer.write(bgr)
                n += 1
            if writer is None:
                raise InputError("no frames to write")
            writer.release()
            writer = None
            os.replace(tmp, out)
        finally:
            if writer is not None:
                writer.release()
            try:
                tmp.unlink()
            except OSError:  # missing, or a read-only folder: never hide the real error
                pass
        return n
    out.mkdir(parents=True, exist_ok=True)
    size, n = None, 0
    for i, frame in enumerate(frames):
        bgr = _check_frame(frame, i, size)
        size = bgr.shape[:2]
        dst = out / f"frame_{i:04d}.png"
        if not cv2.imwrite(str(dst), bgr):
            from ..outputs import OutputError, check_output_dir

            check_output_dir(out, bgr.nbytes)  # says why (read-only, no space) when it can
            raise OutputError(f"cannot write {dst}")
        n += 1
    return n
