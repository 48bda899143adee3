"""Export a NeRF-style transforms.json (nerfstudio's "nerfstudio-data" layout) plus the original NeRF Blender
split files, so a plain 3DGS / NeRF baseline trains on the scene in the framework a user already has.

transforms.json (nerfstudio; splatfacto, nerfacto, gsplat's nerfstudio-style loaders):
  camera_model "OPENCV", fl_x, fl_y, cx, cy, w, h, k1, k2, k3, p1, p2 (nerfstudio reads all five): one camera
  for every frame. cx, cy follow nerfstudio's (COLMAP's) pixel convention, where the top-left pixel's centre is
  (0.5, 0.5): cx = K[0, 2] + 0.5 with our OpenCV-centre K.
  frames[]: file_path (relative, with extension), transform_matrix = 4x4 camera-to-world in the OpenGL /
  Blender camera convention (x right, y up, z back): c2w_gl = c2w_cv @ diag(1, -1, -1, 1).
  train_filenames / val_filenames / test_filenames: the split (val = test = our /test views).
  ply_file_path "points3d.ply" when the scene has /points (splatfacto's initialisation).
transforms_train.json / transforms_val.json / transforms_test.json (original NeRF Blender loaders, graphdeco
  3DGS's readCamerasFromTransforms, gsplat's examples/datasets/blender.py): camera_angle_x and frames[] with
  file_path "./DIR/NNN" WITHOUT extension (those loaders append ".png"), same transform_matrix; they assume
  cx = W/2, cy = H/2 and fx = fy.

--images picks the training frames: blurry (the recorded frames at the mid-exposure pose, the pose ev3dgs'
naive baseline trains them at), sharp (/train/sharp at /train/sharp_poses, synthetic scenes) or both.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .. import schema
from ..errors import InputError
from ..geometry import interpolate_pose, opencv_to_blender
from .common import image_width, progress, write_png
from .notes import intrinsics_lines

IMAGE_SETS = ("blurry", "sharp", "both")


def mid_exposure_poses(sc) -> np.ndarray:
    """(N, 4, 4) OpenCV camera-to-world of each view at its exposure midpoint (the naive baseline's pose)."""
    tr = sc.train
    mid = np.asarray(tr.exposure, np.float64).mean(axis=1)
    return np.stack([interpolate_pose(tr.poses[v], tr.pose_t[v], mid[v]) for v in range(len(tr))])


def _write_points(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    from plyfile import PlyData, PlyElement

    v = np.zeros(len(xyz), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                  ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    v["x"], v["y"], v["z"] = np.asarray(xyz, np.float32).T
    v["red"], v["green"], v["blue"] = np.asarray(rgb, np.uint8).T
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))


def export(sc, ev_path: str, stage: Path, quiet: bool = False, images: str = "blurry") -> dict:
    tr = sc.train
    if images not in IMAGE_SETS:
        raise InputError(f"--images must be one of {IMAGE_SETS}, found {images!r}")
    if tr is None or sc.camera.K is None:
        raise InputError("the scene has no /train views or intrinsics: nothing to put in transforms.json")
    sets = []   # (split, folder, images, (n,4,4) OpenCV poses)
    if images in ("blurry", "both"):
        if tr.poses is None:
            raise InputError("the scene has no /train/poses (ingested without pose estimation)")
        sets.append(("train", "blurry", tr.images, mid_exposure_poses(sc)))
    if images in ("sharp", "both"):
        if tr.sharp is None or tr.sharp_poses is None:
            raise InputError("--images sharp/both needs /train/sharp and /train/sharp_poses (synthetic scenes)")
        sets.append(("train", "sharp", tr.sharp, np.asarray(tr.sharp_poses)))
    if sc.test is not None:
        sets.append(("test", "test", sc.test.images, np.asarray(sc.test.poses)))
    K = np.asarray(sc.camera.K, np.float64)
    W, H = sc.camera.width, sc.camera.height
    d = np.asarray(sc.camera.distortion, np.float64)
    frames, split_names = [], {"train": [], "test": []}
    total = sum(len(s[2]) for s in sets)
    bar = progress(total, "transforms images", quiet, unit="img")
    for split, folder, imgs, poses in sets:
        (stage / folder).mkdir()
        digits = image_width(len(imgs))
        for i in range(len(imgs)):
            rel = f"{folder}/{i:0{digits}d}"
            write_png(stage / f"{rel}.png", imgs[i])
            frames.append((split, rel, opencv_to_blender(poses[i]).tolist()))
            split_names[split].append(f"{rel}.png")
            bar.update()
    bar.close()
    head = {"camera_model": "OPENCV", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5,
            "cy": K[1, 2] + 0.5, "w": W, "h": H, "k1": d[0], "k2": d[1], "p1": d[2], "p2": d[3], "k3": d[4]}
    ns = dict(head, frames=[{"file_path": f"{rel}.png", "transform_matrix": m} for _, rel, m in frames],
              train_filenames=split_names["train"], val_filenames=split_names["test"],
              test_filenames=split_names["test"])
    if sc.points is not None and len(sc.points.xyz):
        _write_points(stage / "points3d.ply", sc.points.xyz, sc.points.rgb)
        ns["ply_file_path"] = "points3d.ply"
    (stage / "transforms.json").write_text(json.dumps(ns, indent=1), encoding="utf-8")
    angle_x = 2.0 * math.atan(W / (2.0 * K[0, 0]))
    for name, split in (("transforms_train.json", "train"), ("transforms_val.json", "test"),
                        ("transforms_test.json", "test")):
        blender = {"camera_angle_x": angle_x,
                   "frames": [{"file_path": f"./{rel}", "transform_matrix": m} for s, rel, m in frames if s == split]}
        (stage / name).write_text(json.dumps(blender, indent=1), encoding="utf-8")
    info = {"images": images, "train_frames": len(split_names["train"]), "test_frames": len(split_names["test"]),
            "points": "ply_file_path" in ns}
    (stage / "README.txt").write_text(_readme(sc, info), encoding="utf-8")
    return info


def _readme(sc, info: dict) -> str:
    which = {"blurry": "the blurry frames at the mid-exposure pose", "sharp": "the sharp frames at their poses",
             "both": "the blurry frames (mid-exposure pose) and the sharp frames (their poses)"}[info["images"]]
    L = [f"NeRF-style transforms export of ev3dgs scene '{sc.name}' (source {sc.source}) by `ev3dgs "
         f"export-dataset --format transforms --images {info['images']}`: {info['train_frames']} training "
         f"frames ({which}), {info['test_frames']} test frames.", "",
         "transforms.json is nerfstudio's layout (fl_x, fl_y, cx, cy, distortion, per-frame OpenGL camera-to-world "
         "transform_matrix, train/val/test file lists); transforms_{train,val,test}.json are the NeRF Blender "
         "layout (camera_angle_x, file paths without extension). Matrices are float64 JSON, exact.", "",
         "Lost:",
         "- events, exposure windows and the motion within each exposure: a blurry frame gets one pose (the "
         "mid-exposure one), the naive baseline.",
         "- world orientation/scale normalisation is left to the reader (nerfstudio auto-orients and scales)."]
    L += intrinsics_lines(sc, "fl_x, fl_y, cx, cy and OpenCV k1 k2 k3 p1 p2 in transforms.json, "
                              "camera_angle_x only in the Blender files")
    tr = sc.train.transfer or schema.default_transfer(sc.source)
    L.append(f"- images: 8-bit, transfer '{tr}' (srgb: ordinary sRGB-encoded images, what NeRF/3DGS trainers "
             "expect; the blur in a blurry frame was averaged in linear light, which a plain trainer ignores).")
    if sc.camera.background is not None:
        L.append(f"- background colour {list(sc.camera.background)}: not stored (set the trainer's background, "
                 "e.g. nerfstudio --pipeline.model.background-color).")
    return "\n".join(L) + "\n"
