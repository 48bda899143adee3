"""Export a scene in E2NeRF's layouts (iCVTEAM/E2NeRF, read by its loaders, E2GS and Ev3DGS-style code).

synthetic (Blender) layout:
  train/r_{2i}.png        blurry view i (RGBA, alpha 255, like E2NeRF's data; lossless for our uint8 images)
  test/r_{2k}.png         "blur view" k: the sharp frame of training view k (/train/sharp) at its pose
  test/r_{2k+1}.png       "novel view" k: /test/images[k]
  transform_train.json    camera_angle_x + 2N frames; frame 2i = view i, transform_matrix = a LIST of 4b+2
                          Blender/OpenGL camera-to-world matrices: entry 1 + j (j = 0..4b) at the exposure time
                          start + j * (end - start) / 4b, entry 0 a copy of entry 1. The loaders read entries
                          1, 5, ..., 1 + 4b (b = 4: [1, 5, 9, 13, 17]), the b + 1 bin edges. Frame 2i+1 is
                          not read by any loader; it repeats the test json's frame 2i+1 (novel view i) when
                          there is one, else frame 2i.
  transform_test.json     2K frames (K pairs), each transform_matrix [pose, pose] (loaders read entry 1)
  events.pt               float64 tensor (N, b, H*W): signed event counts (ON +1, OFF -1) of view i in bin k,
                          t in [edge_k, edge_k+1) (the last bin closed), pixel index y * W + x
real-world (LLFF) layout:
  images/{5i:03d}.png     blurry view i (PNG, lossless; E2NeRF's own are .jpg, its LLFF loader reads both)
  poses_bounds.npy        float64 (N*(b+1), 17): row i*(b+1)+j = view i at bin edge j, LLFF [down, right,
                          back | t | H, W, f] flattened row-major, then near, far
  events.pt               as above

Bin edges are the trainer's sub-pose times (ev3dgs.train.events.sub_pose_times of the exposure), the poses at
them are interpolated from /train/poses (slerp + lerp, exact at stored sample times).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import interpolate_pose, opencv_to_blender, project
from ..event_file import EventFile
from .common import image_width, progress, write_png
from .notes import intrinsics_lines, sensor_lines, transfer_lines
from .torch_file import save_streamed

SUBFRAMES_PER_BIN = 4            # E2NeRF: sub-frame indices 1, 5, 9, ... are the bin edges
DEFAULT_BINS = 4


def opencv_to_llff(c2w: np.ndarray) -> np.ndarray:
    """(..., 4, 4) OpenCV [right, down, forward | t] camera-to-world -> (..., 3, 4) LLFF [down, right, back | t]."""
    m = np.asarray(c2w, dtype=np.float64)
    out = np.empty(m.shape[:-2] + (3, 4))
    out[..., 0], out[..., 1], out[..., 2] = m[..., :3, 1], m[..., :3, 0], -m[..., :3, 2]
    out[..., 3] = m[..., :3, 3]
    return out


def _need_poses(sc) -> None:
    if sc.train is None or sc.train.poses is None or sc.train.pose_t is None:
        raise InputError("the scene has no /train/poses: the e2nerf layout needs a pose per bin edge "
                         "(ingest the recording with pose estimation)")


def _poses_at(sc, times: np.ndarray) -> np.ndarray:
    tr = sc.train
    return np.stack([[interpolate_pose(tr.poses[v], tr.pose_t[v], t) for t in row] for v, row in enumerate(times)])


def _write_events(stage: Path, ev_path: str, sc, edges: np.ndarray, quiet: bool) -> dict:
    """events.pt (N, b, H*W) float64, one view at a time from the streamed events."""
    from ..train.events import bin_signed_events

    N, b = edges.shape[0], edges.shape[1] - 1
    H, W = sc.camera.height, sc.camera.width
    with EventFile(ev_path) as es:
        lo = es.searchsorted(edges[:, 0], "left")
        hi = es.searchsorted(edges[:, -1], "right")
        kept = int(np.sum(hi - lo))
        bar = progress(kept, "e2nerf events", quiet)

        def views():
            for v in range(N):
                counts = np.zeros((b, H * W), np.float64)
                for ev in es.blocks(int(lo[v]), int(hi[v])):
                    counts += bin_signed_events(ev.t, ev.x, ev.y, ev.p, edges[v:v + 1], H, W).reshape(b, H * W)
                    bar.update(len(ev))
                yield counts[None]

        nbytes = save_streamed(stage / "events.pt", (N, b, H * W), np.float64, views())
        bar.close()
        total = len(es)
    return {"events_total": total, "events_in_exposures": kept, "events_pt_bytes": nbytes}


def _near_far(sc, c2w: np.ndarray) -> tuple[list[float], str]:
    """Near/far bounds for poses_bounds.npy from /points, else the /bounds box, else the scene's config."""
    pts, what = None, ""
    if sc.points is not None and len(sc.points.xyz):
        pts, what = np.asarray(sc.points.xyz, np.float64), "depths of /points"
    elif sc.bounds is not None:
        lo, hi = np.asarray(sc.bounds, np.float64)
        pts = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        what = "depths of the /bounds box corners"
    if pts is not None:
        d = np.concatenate([project(sc.camera.K, m, pts)[1] for m in c2w.reshape(-1, 4, 4)])
        d = d[d > 0]
        if len(d):
            return [float(d.min() * 0.9), float(d.max() * 1.1)], what + " x 0.9 / 1.1"
    nf = sc.config.get("near_far") if isinstance(sc.config, dict) else None
    arr = np.asarray(nf, dtype=np.float64).reshape(-1) if nf is not None else np.zeros(0)
    if arr.size >= 2 and np.all(np.isfinite(arr)) and 0 < arr.min():
        return [float(arr.min()), float(arr.max())], "the scene config's near_far"
    return [0.1, 100.0], "no points, bounds or near_far in the scene: a generic 0.1 / 100"


def export(sc, ev_path: str, stage: Path, quiet: bool = False, layout: str = "auto",
           bins: int = DEFAULT_BINS) -> dict:
    _need_poses(sc)
    if isinstance(bins, bool) or not isinstance(bins, int) or bins < 1:
        raise InputError(f"--bins must be an integer >= 1, found {bins!r}")
    if layout == "auto":
        layout = "llff" if sc.source == "davis" else "synthetic"
    if layout not in ("synthetic", "llff"):
        raise InputError(f"unknown e2nerf layout {layout!r} (synthetic, llff)")
    from ..train.events import sub_pose_times

    exposure = np.asarray(sc.train.exposure, np.int64)
    edges = sub_pose_times(exposure, bins + 1)
    info = (_synthetic if layout == "synthetic" else _llff)(sc, stage, exposure, edges, bins, quiet)
    info.update(_write_events(stage, ev_path, sc, edges, quiet))
    info["layout"], info["bins"] = layout, bins
    (stage / "README.txt").write_text(_readme(sc, info), encoding="utf-8")
    return info


def _synthetic(sc, stage: Path, exposure, edges, bins: int, quiet: bool) -> dict:
    from ..train.events import sub_pose_times

    tr, N = sc.train, len(sc.train)
    sub = SUBFRAMES_PER_BIN * bins
    times = sub_pose_times(exposure, sub + 1)
    assert np.array_equal(times[:, ::SUBFRAMES_PER_BIN], edges)
    mats = opencv_to_blender(_poses_at(sc, times))                 # (N, 4b+1, 4, 4)
    mats = np.concatenate([mats[:, :1], mats], axis=1)              # entry 0 = entry 1
    K = np.asarray(sc.camera.K, np.float64)
    W = sc.camera.width
    angle_x = 2.0 * math.atan(W / (2.0 * K[0, 0]))
    has_sharp = tr.sharp is not None and tr.sharp_poses is not None
    M = len(sc.test.images) if sc.test is not None else 0
    pairs = min(N, M) if has_sharp else 0
    (stage / "train").mkdir()
    (stage / "test").mkdir()
    bar = progress(N + 2 * pairs, "e2nerf images", quiet, unit="img")
    for i in range(N):
        write_png(stage / "train" / f"r_{2 * i}.png", tr.images[i], alpha=True)
        bar.update()
    test_frames = []
    for k in range(pairs):
        for j, (img, pose) in enumerate(((tr.sharp[k], tr.sharp_poses[k]), (sc.test.images[k], sc.test.poses[k]))):
            write_png(stage / "test" / f"r_{2 * k + j}.png", img, alpha=True)
            m = opencv_to_blender(np.asarray(pose)).tolist()
            test_frames.append({"file_path": f"./test/r_{2 * k + j}", "transform_matrix": [m, m]})
            bar.update()
    bar.close()
    train_frames = []
    for i in range(N):
        train_frames.append({"file_path": f"./train/r_{2 * i}", "transform_matrix": mats[i].tolist()})
        train_frames.append(test_frames[2 * i + 1] if i < pairs else
                            {"file_path": f"./train/r_{2 * i}", "transform_matrix": mats[i].tolist()})
    for name, frames in (("transform_train.json", train_frames), ("transform_test.json", test_frames)):
        (stage / name).write_text(json.dumps({"camera_angle_x": angle_x, "frames": frames}), encoding="utf-8")
    return {"views": N, "test_pairs": pairs, "novel_views": M, "has_sharp": has_sharp,
            "subframes": sub + 2, "pose_samples": int(tr.poses.shape[1])}


def _llff(sc, stage: Path, exposure, edges, bins: int, quiet: bool) -> dict:
    tr, N = sc.train, len(sc.train)
    c2w = _poses_at(sc, edges)                                       # (N, b+1, 4, 4)
    near_far, nf_how = _near_far(sc, c2w)
    H, W = sc.camera.height, sc.camera.width
    hwf = np.array([H, W, float(np.asarray(sc.camera.K)[0, 0])], np.float64)
    m = opencv_to_llff(c2w).reshape(-1, 3, 4)
    rows = np.concatenate([np.concatenate([m, np.broadcast_to(hwf[:, None], (len(m), 3, 1))], axis=2)
                           .reshape(len(m), 15), np.tile(near_far, (len(m), 1))], axis=1)
    np.save(stage / "poses_bounds.npy", rows)
    (stage / "images").mkdir()
    digits = image_width(N, 5)
    bar = progress(N, "e2nerf images", quiet, unit="img")
    for i in range(N):
        write_png(stage / "images" / f"{5 * i:0{digits}d}.png", tr.images[i])
        bar.update()
    bar.close()
    M = len(sc.test.images) if sc.test is not None else 0
    return {"views": N, "novel_views": M, "has_sharp": tr.sharp is not None, "near_far": near_far,
            "near_far_from": nf_how, "pose_samples": int(tr.poses.shape[1])}


def _readme(sc, info: dict) -> str:
    b, N = info["bins"], info["views"]
    L = [f"E2NeRF-layout export of ev3dgs scene '{sc.name}' (source {sc.source}) by `ev3dgs export-dataset "
         f"--format e2nerf`, {info['layout']} layout, {N} training views, {b} event bins per view.", "",
         "Converted:",
         f"- poses: {info['pose_samples']} stored pose samples per view -> "
         + (f"{info['subframes']} matrices per frame in transform_train.json (OpenGL/Blender axes, "
            f"c2w_gl = c2w_cv @ diag(1,-1,-1,1)), entry 1+j at start + j/{SUBFRAMES_PER_BIN * b} of the "
            "exposure, entry 0 = entry 1; the loaders read entries "
            f"{[1 + SUBFRAMES_PER_BIN * k for k in range(b + 1)]}."
            if info["layout"] == "synthetic" else
            f"{b + 1} LLFF rows per view in poses_bounds.npy (view i: rows i*{b + 1}..i*{b + 1}+{b}), at the "
            "bin edges.")
         + " Poses between stored samples are interpolated (slerp + lerp); JSON/npy keep float64 exactly "
           "(E2NeRF's loaders cast to float32).",
         f"- events: {info['events_in_exposures']} of {info['events_total']} events fall inside the exposures "
         f"and are counted in events.pt ({N}, {b}, H*W) float64, signed (ON +1, OFF -1), bin k = "
         "[edge_k, edge_k+1), last bin closed, edges evenly spread over each exposure.",
         "", "Lost:",
         f"- {info['events_total'] - info['events_in_exposures']} events outside the exposures (E2NeRF keeps "
         "only in-exposure bins).",
         "- event timestamps within a bin, and ON/OFF events that cancel within a bin (net counts only).",
         "- absolute times: E2NeRF stores none (`ev3dgs-ingest e2nerf` assigns its own time line)."]
    L += sensor_lines(sc, "E2NeRF (its loss hard-codes 0.2 / 0.3)")
    L += transfer_lines(sc)
    if info["layout"] == "synthetic":
        L += intrinsics_lines(sc, "camera_angle_x only (one focal length, centred principal point)")
        L.append(f"- test views: {info['test_pairs']} blur-view / novel-view pairs (even / odd test/r_*.png). "
                 f"Of {N} sharp training frames and {info['novel_views']} novel views, "
                 f"{max(0, N - info['test_pairs']) if info['has_sharp'] else N} sharp frames and "
                 f"{info['novel_views'] - info['test_pairs']} novel views could not be paired and are left out"
                 + ("" if info["has_sharp"] else " (the scene has no /train/sharp)") + ".")
        if sc.camera.background is not None:
            L.append(f"- background colour {list(sc.camera.background)}: not stored (E2NeRF runs with a black "
                     "background, white_bkgd False; the images keep the rendered background).")
        L.append("- the blur-view ground truth is the sharp frame at its own pose (/train/sharp_poses), which "
                 "transform_test.json gives as entry 1; E2NeRF's was rendered at the first sub-frame.")
    else:
        L += intrinsics_lines(sc, "H, W and one focal length (LLFF hwf, centred principal point)")
        L.append(f"- near/far bounds ({info['near_far'][0]:.4g}, {info['near_far'][1]:.4g}) from "
                 f"{info['near_far_from']}.")
        L.append(f"- test views ({info['novel_views']}) and sharp frames: the LLFF layout has none "
                 "(use --format transforms for them).")
        if b != 4:
            L.append(f"- E2NeRF's real-world code hard-codes 5 poses (4 bins) per view; this export has {b} bins.")
    if sc.imu is not None:
        L.append("- IMU samples: not stored.")
    return "\n".join(L) + "\n"
