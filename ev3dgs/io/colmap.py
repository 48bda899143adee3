"""Camera poses from images with pycolmap (SIFT on CPU, exhaustive/sequential matching, incremental SfM).

Typical input: EDI latent frames (`ev3dgs.io.edi.edi_to_uint8`) of a real recording, several per blurry view.

Conventions. Returned poses are 4x4 camera-to-world float64 with OpenCV axes (x right, y down, z forward),
which is also COLMAP's camera frame, so cam_from_world only needs inverting. K uses OpenCV's pixel
convention (top-left pixel centre at (0, 0)); COLMAP puts pixel centres at +0.5, so cx, cy gain 0.5 on the
way in and lose it on the way out. The world frame and scale are COLMAP's (arbitrary similarity).

Calls (pycolmap 4.2.1): extract_features(database, image_dir, image_names, CameraMode.SINGLE,
ImageReaderOptions(camera_model, camera_params), FeatureExtractionOptions(num_threads), Device.cpu) ->
match_exhaustive / match_sequential(database, FeatureMatchingOptions(num_threads), ..., Device.cpu) ->
incremental_mapping(database, image_dir, output, IncrementalPipelineOptions) -> {idx: Reconstruction};
the largest reconstruction's images give image.cam_from_world().matrix() (3x4 world -> camera) and its
points3D give xyz / color.
"""
from __future__ import annotations

import contextlib
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import Ev3dgsError, InputError


class PoseEstimationError(Ev3dgsError):
    """Structure from motion failed or registered too few of the views."""


@dataclass
class PoseResult:
    poses: list[np.ndarray | None]          # per input image: 4x4 c2w (OpenCV axes) or None (unregistered)
    num_registered: int
    points_xyz: np.ndarray                  # (P, 3) float32 sparse points, same world frame as the poses
    points_rgb: np.ndarray                  # (P, 3) uint8
    K: np.ndarray                           # (3, 3) float64 intrinsics used / estimated, OpenCV convention
    camera_model: str = "PINHOLE"           # "PINHOLE" (given K, fixed) or "SIMPLE_RADIAL" (estimated)
    radial: float = 0.0                     # SIMPLE_RADIAL's k (0 for PINHOLE)
    image_names: list[str] = field(default_factory=list)
    mean_reprojection_error: float = float("nan")   # pixels

    @property
    def registered(self) -> np.ndarray:
        return np.array([p is not None for p in self.poses], dtype=bool)


def _image_name(i: int) -> str:
    return f"view_{i:05d}.png"


@contextlib.contextmanager
def _quiet_logging(verbose: bool):
    import pycolmap

    lg = pycolmap.logging
    saved = (lg.minloglevel, lg.verbose_level)
    if not verbose:
        lg.minloglevel, lg.verbose_level = 3, 0      # fatal only: failures are reported by our exception
    try:
        yield
    finally:
        lg.minloglevel, lg.verbose_level = saved


def _write_images(images, image_dir: Path) -> tuple[list[str], tuple[int, int]]:
    import cv2

    if len(images) == 0:
        raise PoseEstimationError("only 0 of 0 views registered: no images given")
    shape = None
    names = []
    image_dir.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(images):
        a = np.asarray(img)
        if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (1, 3)):
            raise InputError(f"image {i} must be uint8 (H, W) or (H, W, 3), got {a.dtype} {a.shape}")
        if shape is None:
            shape = a.shape[:2]
        elif a.shape[:2] != shape:
            raise InputError(f"all images must have the same size: image {i} is {a.shape[:2]}, not {shape}")
        if a.ndim == 3 and a.shape[2] == 3:
            a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
        name = _image_name(i)
        if not cv2.imwrite(str(image_dir / name), a):
            raise PoseEstimationError(f"could not write {image_dir / name}")
        names.append(name)
    return names, (shape[0], shape[1])


def _c2w_from_cam_from_world(m34: np.ndarray) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3, :4] = m34
    c2w = np.eye(4)
    R = w2c[:3, :3]
    c2w[:3, :3] = R.T
    c2w[:3, 3] = -R.T @ w2c[:3, 3]
    return c2w


def estimate_poses(images, K: np.ndarray | None, workdir, min_registered: float = 0.5, *,
                   num_threads: int = 2, matcher: str = "auto", seed: int = 0,
                   verbose: bool = False) -> PoseResult:
    """Structure from motion on `images` (list of uint8 (H, W) gray or (H, W, 3) RGB, all one size).

    K (3x3, OpenCV convention) -> one PINHOLE camera with these intrinsics held fixed; None -> one
    SIMPLE_RADIAL camera whose focal length and distortion COLMAP estimates (principal point at the centre).
    `workdir` receives images/, database.db and sparse/ (previous runs' files there are replaced).
    `matcher`: "exhaustive", "sequential" (images in capture order) or "auto" (exhaustive up to 50 images).
    Raises PoseEstimationError when fewer than `min_registered` (a fraction) of the images register."""
    import pycolmap

    if not 0 <= min_registered <= 1:
        raise InputError(f"min_registered must be a fraction in [0, 1], got {min_registered}")
    if matcher not in ("auto", "exhaustive", "sequential"):
        raise InputError(f"matcher must be 'auto', 'exhaustive' or 'sequential', got {matcher!r}")
    workdir = Path(workdir)
    image_dir, db_path, sparse = workdir / "images", workdir / "database.db", workdir / "sparse"
    workdir.mkdir(parents=True, exist_ok=True)
    for old in (db_path, Path(str(db_path) + "-wal"), Path(str(db_path) + "-shm")):
        old.unlink(missing_ok=True)
    shutil.rmtree(sparse, ignore_errors=True)
    if image_dir.is_dir():
        for old in image_dir.glob("view_*.png"):
            old.unlink()
    n = len(images)
    names, (h, w) = _write_images(images, image_dir)
    need = max(2, math.ceil(min_registered * n))
    if n < 2:
        raise PoseEstimationError(f"only 0 of {n} views registered (need {need}): structure from motion needs "
                                  "at least 2 overlapping images")

    reader = pycolmap.ImageReaderOptions()
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"K must be a finite 3x3 intrinsics matrix, got {K}")
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(f"{v:.10g}" for v in (K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5))
    else:
        reader.camera_model = "SIMPLE_RADIAL"

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.use_gpu = False
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = num_threads
    mapping.random_seed = seed
    mapping.mapper.random_seed = seed
    mapping.triangulation.random_seed = seed
    mapping.min_model_size = min(10, max(2, need))
    if K is not None:                                  # intrinsics fixed everywhere
        mapping.ba_refine_focal_length = False
        mapping.ba_refine_principal_point = False
        mapping.ba_refine_extra_params = False
        mapping.mapper.abs_pose_refine_focal_length = False
        mapping.mapper.abs_pose_refine_extra_params = False

    with _quiet_logging(verbose):
        pycolmap.set_random_seed(seed)
        pycolmap.extract_features(db_path, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        if matcher == "sequential" or (matcher == "auto" and n > 50):
            pairing = pycolmap.SequentialPairingOptions()
            pairing.num_threads = num_threads
            pycolmap.match_sequential(db_path, matching_options=matching, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.ExhaustivePairingOptions()
            pycolmap.match_exhaustive(db_path, matching_options=matching, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        sparse.mkdir(parents=True, exist_ok=True)
        recs = pycolmap.incremental_mapping(db_path, image_dir, sparse, options=mapping)

    rec = max(recs.values(), key=lambda r: r.num_reg_images(), default=None)
    poses: list[np.ndarray | None] = [None] * n
    index = {name: i for i, name in enumerate(names)}
    if rec is not None:
        for image in rec.images.values():
            if image.has_pose and image.name in index:
                poses[index[image.name]] = _c2w_from_cam_from_world(image.cam_from_world().matrix())
    count = sum(p is not None for p in poses)
    if count < need:
        why = "no reconstruction (too few features or matches)" if rec is None else "the rest did not match"
        raise PoseEstimationError(
            f"only {count} of {n} views registered (need {need}, min_registered={min_registered:g}): {why}; "
            "try more texture, more overlap between views or EDI-deblurred frames")

    cam = next(iter(rec.cameras.values()))
    params = np.asarray(cam.params, dtype=np.float64)
    if cam.model_name == "PINHOLE":
        fx, fy, cx, cy, radial = params[0], params[1], params[2], params[3], 0.0
    else:                                               # SIMPLE_RADIAL: f, cx, cy, k
        fx = fy = params[0]
        cx, cy, radial = params[1], params[2], float(params[3])
    K_used = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])

    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], dtype=np.float32).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3)
    return PoseResult(poses=poses, num_registered=count, points_xyz=xyz, points_rgb=rgb, K=K_used,
                      camera_model=cam.model_name, radial=radial, image_names=names,
                      mean_reprojection_error=float(rec.compute_mean_reprojection_error()))
