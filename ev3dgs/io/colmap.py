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
import json
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
                   verbose: bool = False, progress=None, what: str = "views", hint=None) -> PoseResult:
    """Structure from motion on `images` (list of uint8 (H, W) gray or (H, W, 3) RGB, all one size).

    K (3x3, OpenCV convention) -> one PINHOLE camera with these intrinsics held fixed; None -> one
    SIMPLE_RADIAL camera whose focal length and distortion COLMAP estimates (principal point at the centre).
    `workdir` receives images/, database.db and sparse/ (previous runs' files there are replaced).
    `matcher`: "exhaustive", "sequential" (images in capture order) or "auto" (exhaustive up to 50 images).
    `progress(stage, registered)`, if given, is called as the work goes: stage "features", "matching" or
    "mapping", registered the images the mapper has registered so far. `what` names the images in messages;
    `hint(registered)`, if given, says what to try instead of the generic advice when too few register.
    Raises PoseEstimationError when fewer than `min_registered` (a fraction) of the images register.

    pycolmap runs in a child process (`_child`): importing pycolmap installs glog's failure-signal handler,
    which answers SIGTERM with a native stack dump, and a long C++ call would not see Ctrl-C until it returns.
    The child dies with its parent; KeyboardInterrupt (Ctrl-C, or SIGTERM turned into it by the caller) stops
    it at once."""
    if not 0 <= min_registered <= 1:
        raise InputError(f"min_registered must be a fraction in [0, 1], got {min_registered}")
    if matcher not in ("auto", "exhaustive", "sequential"):
        raise InputError(f"matcher must be 'auto', 'exhaustive' or 'sequential', got {matcher!r}")
    workdir = Path(workdir)
    image_dir, db_path, sparse = workdir / "images", workdir / "database.db", workdir / "sparse"
    workdir.mkdir(parents=True, exist_ok=True)
    for old in (db_path, Path(str(db_path) + "-wal"), Path(str(db_path) + "-shm"), workdir / _RESULT):
        old.unlink(missing_ok=True)
    shutil.rmtree(sparse, ignore_errors=True)
    if image_dir.is_dir():
        for old in image_dir.glob("view_*.png"):
            old.unlink()
    n = len(images)
    names, (h, w) = _write_images(images, image_dir)
    need = max(2, math.ceil(min_registered * n))
    if n < 2:
        raise PoseEstimationError(f"only 0 of {n} {what} registered (need {need}): structure from motion needs "
                                  "at least 2 overlapping images")
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"K must be a finite 3x3 intrinsics matrix, got {K}")
    job = {"names": names, "K": None if K is None else K.tolist(), "num_threads": num_threads,
           "matcher": matcher, "seed": seed, "verbose": verbose, "need": need}
    (workdir / _JOB).write_text(json.dumps(job), encoding="utf-8")
    _run_child(workdir, verbose, progress)

    with np.load(workdir / _RESULT, allow_pickle=False) as z:
        r = {k: z[k] for k in z.files}
    count = int(r["registered"].sum())
    poses: list[np.ndarray | None] = [r["poses"][i] if r["registered"][i] else None for i in range(n)]
    if count < need:
        why = ("no reconstruction (too few features or matches)" if not bool(r["reconstructed"]) else
               "the rest did not match")
        raise PoseEstimationError(
            f"only {count} of {n} {what} registered (need {need}, min_registered={min_registered:g}): {why}; "
            + (hint(count) if hint is not None else "try more texture or more overlap between views"))
    return PoseResult(poses=poses, num_registered=count, points_xyz=r["points_xyz"].astype(np.float32),
                      points_rgb=r["points_rgb"].astype(np.uint8), K=r["K"], camera_model=str(r["camera_model"]),
                      radial=float(r["radial"]), image_names=names,
                      mean_reprojection_error=float(r["reprojection_error"]))


_JOB, _RESULT, _LOG = "job.json", "result.npz", "colmap.log"


def _run_child(workdir: Path, verbose: bool, progress) -> None:
    """Run `_child(workdir)` in a new interpreter; relay its progress lines; kill it on any exception."""
    import subprocess
    import sys

    root = str(Path(__file__).resolve().parents[2])    # the folder holding the ev3dgs package
    code = f"import sys; sys.path.insert(0, {root!r}); from ev3dgs.io.colmap import _child; _child({str(workdir)!r})"

    log = open(workdir / _LOG, "wb")
    try:
        child = subprocess.Popen([sys.executable, "-P", "-c", code], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                 stderr=None if verbose else log, text=True, bufsize=1)
        try:
            for line in child.stdout:
                stage, _, reg = line.strip().partition(" ")
                if progress is not None and stage in ("features", "matching", "mapping"):
                    progress(stage, int(reg) if reg else 0)
            rc = child.wait()
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
            child.stdout.close()
    finally:
        log.close()
    if rc != 0 or not (workdir / _RESULT).is_file():
        tail = [ln for ln in (workdir / _LOG).read_text(errors="replace").splitlines() if ln.strip()]
        raise PoseEstimationError(f"pycolmap stopped (exit code {rc})" + (f": {tail[-1].strip()}" if tail else ""))


def _child(workdir: str) -> None:
    """The child process: read job.json, run pycolmap, write result.npz; progress lines on stdout."""
    import os
    import signal
    import sys

    signal.signal(signal.SIGINT, signal.SIG_IGN)      # Ctrl-C reaches the parent, which stops the child
    parent = os.getppid()
    try:                                              # Linux: SIGKILL when the parent dies, however it dies
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:                        # the parent died before that
        os._exit(1)
    import pycolmap

    signal.signal(signal.SIGTERM, signal.SIG_DFL)     # no glog stack dump when the parent stops the child
    workdir = Path(workdir)
    job = json.loads((workdir / _JOB).read_text(encoding="utf-8"))
    names, K, num_threads, seed = job["names"], job["K"], job["num_threads"], job["seed"]
    n, need, matcher = len(names), job["need"], job["matcher"]
    image_dir, db_path, sparse = workdir / "images", workdir / "database.db", workdir / "sparse"

    def say(stage: str, reg: int = 0) -> None:
        print(f"{stage} {reg}", flush=True)
        sys.stdout.flush()

    reader = pycolmap.ImageReaderOptions()
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
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

    registered = [0]

    def initial_pair():
        registered[0] += 2
        say("mapping", registered[0])

    def next_image():
        registered[0] += 1
        say("mapping", registered[0])

    with _quiet_logging(job["verbose"]):
        pycolmap.set_random_seed(seed)
        say("features")
        pycolmap.extract_features(db_path, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        say("matching")
        if matcher == "sequential" or (matcher == "auto" and n > 50):
            pairing = pycolmap.SequentialPairingOptions()
            pairing.num_threads = num_threads
            pycolmap.match_sequential(db_path, matching_options=matching, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.ExhaustivePairingOptions()
            pycolmap.match_exhaustive(db_path, matching_options=matching, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
        say("mapping")
        sparse.mkdir(parents=True, exist_ok=True)
        recs = pycolmap.incremental_mapping(db_path, image_dir, sparse, options=mapping,
                                            initial_image_pair_callback=initial_pair,
                                            next_image_callback=next_image)

    rec = max(recs.values(), key=lambda r: r.num_reg_images(), default=None)
    poses = np.zeros((n, 4, 4))
    ok = np.zeros(n, bool)
    index = {name: i for i, name in enumerate(names)}
    out = {"reconstructed": rec is not None, "K": np.eye(3), "camera_model": "", "radial": 0.0,
           "points_xyz": np.zeros((0, 3), np.float32), "points_rgb": np.zeros((0, 3), np.uint8),
           "reprojection_error": float("nan")}
    if rec is not None:
        for image in rec.images.values():
            if image.has_pose and image.name in index:
                poses[index[image.name]] = _c2w_from_cam_from_world(image.cam_from_world().matrix())
                ok[index[image.name]] = True
        cam = next(iter(rec.cameras.values()))
        params = np.asarray(cam.params, dtype=np.float64)
        if cam.model_name == "PINHOLE":
            fx, fy, cx, cy, radial = params[0], params[1], params[2], params[3], 0.0
        else:                                           # SIMPLE_RADIAL: f, cx, cy, k
            fx = fy = params[0]
            cx, cy, radial = params[1], params[2], float(params[3])
        pts = list(rec.points3D.values())
        out.update(K=np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]]),
                   camera_model=cam.model_name, radial=radial,
                   points_xyz=np.array([p.xyz for p in pts], dtype=np.float32).reshape(-1, 3),
                   points_rgb=np.array([p.color for p in pts], dtype=np.uint8).reshape(-1, 3),
                   reprojection_error=float(rec.compute_mean_reprojection_error()))
    tmp = workdir / ("partial-" + _RESULT)
    np.savez(tmp, poses=poses, registered=ok, **out)
    tmp.replace(workdir / _RESULT)
