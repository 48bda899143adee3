"""E2NeRF dataset importer (iCVTEAM/E2NeRF, ICCV'23): synthetic (Blender) and real-world (DAVIS346, LLFF) scenes.

Layouts (detected from the files present):
- synthetic: transform_train.json, transform_test.json, train/r_{0,2,..}.png (blurry), test/r_{0..}.png (sharp),
  events.pt (views, b, H*W) signed counts. Each json frame's `transform_matrix` is a LIST of sub-frame 4x4
  Blender/OpenGL camera-to-world matrices. Training view i is json frame 2i (E2NeRF: frames[0:200:2], image
  r_{2i}.png). We keep the sub-frames E2NeRF trains with: indices 1, 5, 9, ..., 1 + 4b (b = 4: [1,5,9,13,17]),
  because its event bin edges (0.05, 0.09, 0.13, 0.17 s at 10 ms per sub-frame) fall exactly on them.
  Test views: sub-frame index 1 ("first pose", E2NeRF README); all kept, odd indices are novel views, even
  ones share a training viewpoint (config "test_novel_views").
- real-world: images/*.jpg (sorted, E2NeRF names them {i*5:03d}.jpg), poses_bounds.npy with b+1 = 5 LLFF
  poses per view (view i uses rows 5i..5i+4, as E2NeRF's run_nerf_exp.py), events.pt (views, b, H*W).
  Poses are used as stored (no LLFF recentring/rescaling/spherify); near/far bounds go to the config.

Time line (int64 microseconds; E2NeRF stores no timestamps, so this one is ours):
- synthetic: view i starts at i * 250 ms and sub-frame j is at start + 10 ms * j, so the poses are at
  +10, 50, 90, 130, 170 ms and the exposure is [start + 10 ms, start + 170 ms] (first to last kept pose).
- real-world: view i starts at i * 250 ms, poses every 25 ms (E2NeRF bins events in 25 ms steps), exposure
  [start, start + 100 ms] (the paper's DAVIS346 exposure).
With the exposure spanning first to last pose, the trainer's b+1 evenly spread sub-pose times coincide with
the stored poses and with the event bin edges. E2NeRF's first synthetic bin also absorbed events from
0-10 ms; they end up inside (10 ms, 50 ms) here.

Events: E2NeRF keeps only binned counts. For a count c in bin k of a pixel we synthesise |c| events of
polarity sign(c) at t_k + floor((j + 0.5) * (t_{k+1} - t_k) / |c|), j = 0..|c|-1, clipped to stay strictly
inside (t_k, t_{k+1}); pixel index = y * W + x (E2NeRF flattens (H, W) row-major). events.pt is memory-mapped
where torch allows and handled one view at a time; events and images are staged in a temporary HDF5 file
beside the output, so memory stays bounded by one view.

Thresholds are not stored by E2NeRF (its loss hard-codes 0.2/0.3, swapped against the paper; its v2e
"noisy" preset used 0.25): they are arguments, default 0.2/0.2. Images: RGBA is composited onto black
(E2NeRF runs with white_bkgd False; for the alpha-255 blurry images this equals dropping alpha).
"""
from __future__ import annotations

import json
import math
import numbers
import os
from pathlib import Path

import cv2
import h5py
import numpy as np

from .. import schema
from ..errors import InputError
from ..geometry import blender_to_opencv, intrinsics

SYN_PERIOD_US = 250_000
SYN_SUBFRAME_US = 10_000
SYN_STRIDE = 4                  # sub-frames per event bin; kept indices 1, 5, 9, ...
REAL_PERIOD_US = 250_000
REAL_BIN_US = 25_000
EVENTS_NOTE = "synthesised from E2NeRF binned counts: |count| events per pixel and bin, evenly spaced inside the bin"
THRESHOLDS_NOTE = "not stored by E2NeRF; given on the command line"
_IMAGE_EXT = (".jpg", ".jpeg", ".png")
V2E_LOG_KNEE = 20 / 255         # v2e's lin_log knee: 20 DN of 8-bit display values


def import_e2nerf(directory, out: Path, pos_threshold: float = 0.2, neg_threshold: float = 0.2,
                  name: str | None = None) -> Path:
    """Convert an E2NeRF scene directory (synthetic or real-world layout) into the scene file `out`."""
    d = Path(directory)
    out = Path(out)
    if not d.is_dir():
        raise InputError(f"{d}: not a directory")
    for label, v in (("pos_threshold", pos_threshold), ("neg_threshold", neg_threshold)):
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not (math.isfinite(v) and v > 0):
            raise InputError(f"{label} must be a finite number > 0, found {v!r}")
    synthetic = (d / "transform_train.json").is_file()
    if not synthetic and not (d / "poses_bounds.npy").is_file():
        raise InputError(f"{d}: not an E2NeRF scene (neither transform_train.json nor poses_bounds.npy)")
    tmp = out.parent / f".{out.name}.e2nerf-{os.getpid()}.h5"
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        with h5py.File(tmp, "w") as stage:
            scene = (_synthetic if synthetic else _real)(d, stage)
        lazy = {n: schema.LazyArray(tmp, n, s, dt) for n, (s, dt) in scene.pop("_staged").items()}
        events = schema.LazyEvents(lazy["t"], lazy["x"], lazy["y"], lazy["p"])
        H, W = scene["hw"]
        config = {"events": EVENTS_NOTE, "thresholds": THRESHOLDS_NOTE, "directory": str(d.resolve()),
                  **scene["config"]}
        sc = schema.Scene(
            name=name or d.resolve().name, source="e2nerf",
            camera=schema.Camera(W, H, scene["K"], background=(0.0, 0.0, 0.0)), events=events,
            # v2e: lin_log of display grey (8-bit), knee 20 DN; reference set at each view's first frame;
            # blur by E2NeRF's ISP and events both from display-referred frames
            sensor=schema.EventSensor(float(pos_threshold), float(neg_threshold), log_knee=V2E_LOG_KNEE,
                                      count_convention="exact_reference"),
            train=schema.Train(images=lazy["train_images"], exposure=scene["exposure"], poses=scene["poses"],
                               pose_t=scene["pose_t"], transfer="display"),
            test=None if "test_images" not in lazy else schema.Test(lazy["test_images"], scene["test_poses"]),
            config=config)
        return schema.write(sc, out)
    finally:
        tmp.unlink(missing_ok=True)


# ------------------------------------------------------------------------------------------ layouts

def _synthetic(d: Path, stage: h5py.File) -> dict:
    meta = _json(d / "transform_train.json")
    test_meta = _json(d / "transform_test.json")
    ev, V, B, HW = _load_events(d / "events.pt")
    frames = _frames(meta, "transform_train.json")[::2]
    if len(frames) != V:
        raise InputError(f"{d / 'transform_train.json'}: {len(frames)} training frames (every 2nd of the json) "
                         f"but events.pt has {V} views")
    idx = [1 + SYN_STRIDE * k for k in range(B + 1)]
    poses = np.stack([blender_to_opencv(_matrices(f, "transform_train.json", i, idx[-1] + 1)[idx])
                      for i, f in enumerate(frames)])
    try:
        fov_x = float(meta["camera_angle_x"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{d / 'transform_train.json'}: missing or invalid camera_angle_x") from None
    H, W = _stage_images(stage, "train_images", [d / "train" / f"r_{2 * i}.png" for i in range(V)])
    _check_pixels(d, H, W, HW)
    test_frames = _frames(test_meta, "transform_test.json")
    test_poses = np.stack([blender_to_opencv(_matrices(f, "transform_test.json", i, 2)[1])
                           for i, f in enumerate(test_frames)]) if test_frames else None
    if test_frames:
        _stage_images(stage, "test_images", [d / "test" / f"r_{i}.png" for i in range(len(test_frames))], (H, W))
    start = np.arange(V, dtype=np.int64)[:, None] * SYN_PERIOD_US
    pose_t = start + np.asarray(idx, np.int64)[None, :] * SYN_SUBFRAME_US
    _stage_events(stage, ev, V, pose_t, W, d / "events.pt")
    return dict(hw=(H, W), K=intrinsics(W, H, math.degrees(fov_x)), poses=poses, pose_t=pose_t,
                exposure=pose_t[:, [0, -1]].copy(), test_poses=test_poses, _staged=_staged(stage),
                config={"layout": "synthetic", "train_subframe_indices": idx, "test_subframe_index": 1,
                        "train_json_frames": "every 2nd frame (frame 2i, image train/r_{2i}.png)",
                        "test_novel_views": list(range(1, len(test_frames), 2)),
                        "timeline": f"view i starts at i*{SYN_PERIOD_US} us; sub-frame j at start + "
                                    f"j*{SYN_SUBFRAME_US} us; exposure = first..last kept pose",
                        "near_far": [2.0, 6.0]})


def _real(d: Path, stage: h5py.File) -> dict:
    path = d / "poses_bounds.npy"
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or not np.all(np.isfinite(arr)):
        raise InputError(f"{path}: expected a finite (N, 17) LLFF array, found shape {arr.shape}")
    ev, V, B, HW = _load_events(d / "events.pt")
    S = B + 1
    if len(arr) != V * S:
        raise InputError(f"{path}: {len(arr)} poses but events.pt has {V} views x {S} poses")
    img_dir = d / "images"
    files = sorted(f for f in img_dir.iterdir() if f.suffix.lower() in _IMAGE_EXT) if img_dir.is_dir() else []
    if len(files) != V:
        raise InputError(f"{img_dir}: {len(files)} images but events.pt has {V} views")
    H, W = _stage_images(stage, "train_images", files)
    _check_pixels(d, H, W, HW)
    m = arr[:, :15].reshape(-1, 3, 5)
    hh, ww, f = m[0, :, 4]
    if ww <= 0 or hh <= 0 or f <= 0:
        raise InputError(f"{path}: invalid hwf {m[0, :, 4].tolist()}")
    f = f * W / ww                   # LLFF rescales the focal when the images are resized
    K = np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    poses = llff_to_opencv(m[:, :, :4]).reshape(V, S, 4, 4)
    start = np.arange(V, dtype=np.int64)[:, None] * REAL_PERIOD_US
    pose_t = start + np.arange(S, dtype=np.int64)[None, :] * REAL_BIN_US
    _stage_events(stage, ev, V, pose_t, W, d / "events.pt")
    return dict(hw=(H, W), K=K, poses=poses, pose_t=pose_t, exposure=pose_t[:, [0, -1]].copy(),
                _staged=_staged(stage),
                config={"layout": "real-world (LLFF)", "poses_per_view": S, "pose_rows": "view i: rows i*S..i*S+S-1",
                        "images": [f.name for f in files], "near_far": arr[:, 15:17].tolist(),
                        "timeline": f"view i starts at i*{REAL_PERIOD_US} us; pose j at start + j*{REAL_BIN_US} us; "
                                    "exposure = first..last pose",
                        "world": "LLFF world as stored (no recentring, rescaling or spherify)"})


def llff_to_opencv(m: np.ndarray) -> np.ndarray:
    """LLFF (..., 3, 4) [down, right, back | t] camera-to-world -> (..., 4, 4) OpenCV [right, down, forward | t]."""
    m = np.asarray(m, dtype=np.float64)
    out = np.zeros(m.shape[:-2] + (4, 4))
    out[..., :3, 0], out[..., :3, 1], out[..., :3, 2] = m[..., :, 1], m[..., :, 0], -m[..., :, 2]
    out[..., :3, 3] = m[..., :, 3]
    out[..., 3, 3] = 1.0
    return out


# ------------------------------------------------------------------------------------------ events

def synthesise_events(counts: np.ndarray, edges: np.ndarray, width: int):
    """Signed counts (b, H*W) and bin edges (b+1,) int64 us -> sorted (t, x, y, p) arrays (see module doc)."""
    c = np.asarray(counts).astype(np.int64)
    edges = np.asarray(edges, dtype=np.int64)
    k, pix = np.nonzero(c)
    n = np.abs(c[k, pix])
    total = int(n.sum())
    rk, rpix, rn = np.repeat(k, n), np.repeat(pix, n), np.repeat(n, n)
    j = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(n) - n, n)
    dt = (edges[1:] - edges[:-1])[rk]
    t = edges[rk] + np.clip(((2 * j + 1) * dt) // (2 * rn), 1, dt - 1)
    p = np.repeat(np.sign(c[k, pix]), n).astype(np.int8)
    order = np.argsort(t, kind="stable")
    rpix = rpix[order]
    return t[order], (rpix % width).astype(np.uint16), (rpix // width).astype(np.uint16), p[order]


def _load_events(path: Path):
    if not path.is_file():
        raise InputError(f"{path}: missing")
    import torch
    try:
        try:
            ev = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError:     # legacy (non-zip) torch files cannot be memory-mapped
            ev = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure means a bad file
        first = (str(e).splitlines() or [""])[0]
        raise InputError(f"{path}: cannot read ({type(e).__name__}: {first})") from None
    if isinstance(ev, np.ndarray):
        ev = torch.from_numpy(ev)
    if not isinstance(ev, torch.Tensor) or ev.ndim not in (3, 4) or ev.is_complex():
        raise InputError(f"{path}: expected a real tensor (views, bins, H*W), found "
                         f"{tuple(ev.shape) if isinstance(ev, torch.Tensor) else type(ev).__name__}")
    if ev.ndim == 4:
        ev = ev.reshape(ev.shape[0], ev.shape[1], -1)
    V, B, HW = (int(s) for s in ev.shape)
    if V < 1 or B < 1 or HW < 1:
        raise InputError(f"{path}: empty event tensor {tuple(ev.shape)}")
    return ev, V, B, HW


def _stage_events(stage: h5py.File, ev, V: int, pose_t: np.ndarray, W: int, path: Path) -> None:
    ds = {n: stage.create_dataset(n, shape=(0,), maxshape=(None,), dtype=dt, chunks=(1 << 16,))
          for n, dt in (("t", np.int64), ("x", np.uint16), ("y", np.uint16), ("p", np.int8))}
    for v in range(V):
        c = ev[v].double().numpy()
        if not np.all(np.isfinite(c)) or np.any(c != np.rint(c)):
            raise InputError(f"{path}: view {v} holds non-integer or non-finite counts")
        parts = synthesise_events(c, pose_t[v], W)
        n0 = ds["t"].shape[0]
        for a, arr in zip(ds.values(), parts):
            a.resize((n0 + len(arr),))
            a[n0:] = arr


# ------------------------------------------------------------------------------------------ helpers

def _json(path: Path) -> dict:
    try:
        with open(path, encoding="utf-8") as fh:
            meta = json.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: missing") from None
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: unreadable JSON ({e})") from None
    if not isinstance(meta, dict):
        raise InputError(f"{path}: expected a JSON object")
    return meta


def _frames(meta: dict, fname: str) -> list:
    frames = meta.get("frames")
    if not isinstance(frames, list) or not all(isinstance(f, dict) for f in frames):
        raise InputError(f"{fname}: missing or invalid 'frames' list")
    return frames


def _matrices(frame: dict, fname: str, i: int, need: int) -> np.ndarray:
    """A frame's transform_matrix as (S, 4, 4) with S >= need; a single 4x4 matrix counts as S=1."""
    try:
        m = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise InputError(f"{fname}: frame {i} has a missing or ragged transform_matrix") from None
    m = m[None] if m.shape == (4, 4) else m
    if m.ndim != 3 or m.shape[1:] != (4, 4) or not np.all(np.isfinite(m)):
        raise InputError(f"{fname}: frame {i} transform_matrix has shape {m.shape}, expected (S, 4, 4)")
    if len(m) < need:
        raise InputError(f"{fname}: frame {i} has {len(m)} sub-frame matrices, needs at least {need}")
    return m


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    if img is None:
        raise InputError(f"{path}: missing or unreadable image")
    if img.dtype == np.uint16:
        img = (img.astype(np.float64) / 257.0).round().astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.shape[2] == 4:   # composite onto black: rgb * alpha
        a = img[..., 3:].astype(np.float64) / 255.0
        img = np.round(img[..., :3] * a).astype(np.uint8)
    return np.ascontiguousarray(img[..., 2::-1])


def _stage_images(stage: h5py.File, name: str, files: list, hw: tuple | None = None) -> tuple[int, int]:
    ds = None
    for i, f in enumerate(files):
        img = _read_rgb(Path(f))
        if ds is None:
            hw = hw or img.shape[:2]
            ds = stage.create_dataset(name, shape=(len(files),) + tuple(hw) + (3,), dtype=np.uint8,
                                      chunks=(1,) + tuple(hw) + (3,))
        if img.shape[:2] != tuple(hw):
            raise InputError(f"{f}: image is {img.shape[1]}x{img.shape[0]}, expected {hw[1]}x{hw[0]}")
        ds[i] = img
    if ds is None:
        raise InputError(f"{name.replace('_images', '')}: no images")
    return int(hw[0]), int(hw[1])


def _check_pixels(d: Path, H: int, W: int, HW: int) -> None:
    if H * W != HW:
        raise InputError(f"{d / 'events.pt'}: {HW} pixels per bin but the images are {W}x{H} ({W * H})")


def _staged(stage: h5py.File) -> dict:
    return {n: (stage[n].shape, stage[n].dtype) for n in stage}
