"""`ev3dgs eval RUN`: novel views (/test) and deblurred training views (/train/sharp poses) against their
sharp ground truth, with the blurry inputs as the baseline; metrics.json and side-by-side PNGs.

Evaluation protocol (E2NeRF / EvaGaussians), metrics.json keys:
* "blur_view": every training view's sharp frame at mid-exposure (/train/sharp), rendered at the matching pose
  (/train/sharp_poses): deblurring quality. For an E2NeRF import (no /train/sharp) the /test views that share
  a training viewpoint (those not in the config's test_novel_views) are the blur views.
* "novel_view": /test views at poses not trained on (all of /test for our simulated scenes; the odd-indexed
  ones, config test_novel_views, for E2NeRF imports).
* "blurry_input": the blurry training frames against the blur-view ground truth (the baseline).
Each is {"psnr", "ssim", "n", "psnr_per_view"}, plus "lpips" (mean) and "lpips_per_view" when LPIPS is asked for
(a network name, "alex" or "vgg", whose standard weights are fetched into torch's hub cache, or a weights file:
ev3dgs/train/lpips.py); the top-level "lpips" then names the network ({"net", "version", "weights",
"sha256", "min_size"}), else it is null and "lpips_reason" says why. LPIPS that was asked for but could not be
computed (weights missing or unreadable, no network for the first fetch, images too small) leaves the PSNR/SSIM
scores written, "lpips_failed": true and the reason.
"variant" is naive / blur-only / blur+event / oracle (TrainConfig.variant). The old keys "test" and
"train_sharp" are kept as aliases of all /test views and of the /train/sharp blur views.

Runs trained with --refine-poses (RUN/trajectory.npz, pose_refine.py) live in the refined camera frame:
* blur views are rendered at the refined trajectory's mid-exposure pose ("blur_view"); "blur_view_given_poses"
  keeps the score at /train/sharp_poses as given.
* novel views: the test cameras are given in the frame of the initial poses. As pose-free NeRF evaluations
  do (BARF, NoPe-NeRF), they are mapped into the refined frame by the similarity that best takes the
  training views' initial mid-exposure cameras onto their refined ones (``align_similarity``: rotation from
  the orientations, then scale and translation from the centres); "novel_view" is scored at the aligned
  cameras, "novel_view_unaligned" at the given ones, and "test_alignment" gives the transform. No per-view
  test-time pose optimisation is done. (E2NeRF imports, whose blur views are /test views, use the aligned
  /test cameras for both.)"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch

from .. import schema
from ..errors import InputError
from ..splat.model import GaussianModel
from .config import TrainConfig
from .lpips import load_lpips
from .metrics import lpips_unavailable_reason, psnr, ssim_metric
from .trainer import resolve_device


def load_run(run_dir: str | Path, device="cpu", scene: str | Path | None = None, find_scene: bool = True,
             other_scene: bool = False):
    """(TrainConfig, GaussianModel) of a finished run. The config's ``scene`` is the scene file found by
    run_scene.resolve_scene (``scene``: the --scene override, refused when it is not the run's scene unless
    ``other_scene``), an absolute path: any working folder works,
    and so does a run moved together with its scene. ``find_scene=False`` (the model alone is needed, e.g.
    export): the recorded path is kept as it is and a missing scene is no error."""
    import dataclasses

    from .run_scene import resolve_run_scene

    run = Path(run_dir)
    if not (run / "config.json").is_file() or not (run / "model.pt").is_file():
        raise InputError(f"{run}: not a finished training run (config.json and model.pt expected)")
    cfg = TrainConfig.load(run / "config.json")
    if find_scene or scene is not None:
        cfg = dataclasses.replace(cfg, scene=str(resolve_run_scene(run, scene, other_scene)))
    try:
        payload = torch.load(run / "model.pt", map_location=device, weights_only=False)
    except (OSError, RuntimeError, EOFError) as e:
        raise InputError(f"{run / 'model.pt'}: not a readable model ({e})") from None
    return cfg, GaussianModel.from_state_dict(payload["model"], device=device)


@torch.no_grad()
def render_views(model: GaussianModel, poses: np.ndarray, K, width, height, background, backend="auto") -> list:
    from ..splat.rasterize import rasterization

    out = []
    for c2w in poses:
        vm = torch.as_tensor(np.linalg.inv(c2w), dtype=model.dtype, device=model.device)
        img, _, _ = rasterization(model.means, model.quats_normalised, model.scales, model.opacities, model.sh,
                                  vm, K, width, height, sh_degree=model.active_sh_degree, background=background,
                                  backend=backend)
        out.append((img.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8))
    return out


def _refined_frame(run: Path, sc):
    """(refined mid-exposure c2w (N,4,4), the test-camera alignment dict, initial mid c2w) of a
    --refine-poses run, from RUN/trajectory.npz."""
    from ..geometry import interpolate_pose, rotation_angle
    from .pose_refine import align_similarity, load_trajectory

    path = run / "trajectory.npz"
    if not path.is_file():
        raise InputError(f"{run}: trained with --refine-poses but {path.name} is missing (re-run the training)")
    tj = load_trajectory(path, len(sc.train))
    mid_t = np.asarray(sc.train.exposure, dtype=np.float64).mean(axis=1)
    refined = np.stack([interpolate_pose(p, t, m) for p, t, m in zip(tj["poses"], tj["pose_t"], mid_t)])
    initial = np.stack([interpolate_pose(p, t, m) for p, t, m in zip(tj["initial_poses"], tj["pose_t"], mid_t)])
    s, R, t = align_similarity(initial, refined)
    align = {"scale": s, "rotation": R.tolist(), "translation": t.tolist(),
             "rotation_deg": float(np.degrees(rotation_angle(R))), "method": "similarity fitted from the "
             "training views' initial to refined mid-exposure cameras (orientations, then centres)"}
    return refined, align, initial


def training_mid_poses(run: Path, cfg: TrainConfig, sc, given: bool = False) -> tuple[np.ndarray, str]:
    """(mid-exposure c2w (N,4,4) of the training views, where they come from), the cameras `ev3dgs render`
    builds its orbit around. A --refine-poses run's model lives in the frame of its refined trajectory
    (RUN/trajectory.npz), so that is used unless ``given``; otherwise /train/sharp_poses, else each view's
    central pose sample."""
    if cfg.refine_poses and not given:
        return _refined_frame(Path(run), sc)[0], "the refined trajectory (trajectory.npz)"
    if sc.train.sharp_poses is not None:
        return np.asarray(sc.train.sharp_poses), "the scene's /train/sharp_poses"
    return np.asarray(sc.train.poses[:, sc.train.poses.shape[1] // 2]), "the scene's /train/poses"


def _scores(pred: list, truth, lp=None) -> dict:
    p = [psnr(a, np.asarray(b)) for a, b in zip(pred, truth)]
    s = [ssim_metric(a, np.asarray(b)) for a, b in zip(pred, truth)]
    out = {"psnr": float(np.mean(p)), "ssim": float(np.mean(s)), "n": len(p), "psnr_per_view": p}
    if lp is not None:
        d = [lp.distance(a, np.asarray(b)) for a, b in zip(pred, truth)]
        out |= {"lpips": float(np.mean(d)), "lpips_per_view": d}
    return out


LABEL_HEIGHT = 14  # px of the caption strip above each panel of the eval images


def _labelled(image: np.ndarray, label: str) -> np.ndarray:
    """`image` (H, W, 3 RGB uint8) with `label` written in a white strip above it (the column is widened, the
    image centred, when the text is wider than the image)."""
    font, scale, thick = cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1
    (tw, th), base = cv2.getTextSize(label, font, scale, thick)
    img = np.asarray(image, np.uint8)
    h, w = img.shape[:2]
    width = max(w, tw + 4)
    strip = np.full((LABEL_HEIGHT, width, 3), 255, np.uint8)  # drawn apart: no stroke touches the image
    cv2.putText(strip, label, ((width - tw) // 2, min(LABEL_HEIGHT - base, (LABEL_HEIGHT + th) // 2)), font, scale,
                (0, 0, 0), thick, cv2.LINE_AA)
    col = np.full((LABEL_HEIGHT + h, width, 3), 255, np.uint8)
    col[:LABEL_HEIGHT] = strip
    x0 = (width - w) // 2
    col[LABEL_HEIGHT:, x0:x0 + w] = img
    return col


def _png(path: Path, images, labels) -> None:
    """One PNG of the panels side by side, each captioned with its label."""
    cols = [_labelled(i, t) for i, t in zip(images, labels)]
    hmax = max(c.shape[0] for c in cols)
    cols = [np.pad(c, ((0, hmax - c.shape[0]), (0, 0), (0, 0)), constant_values=255) for c in cols]
    row = np.hstack([np.pad(c, ((1, 1), (1, 1), (0, 0)), constant_values=255) for c in cols])
    ok, data = cv2.imencode(".png", cv2.cvtColor(row, cv2.COLOR_RGB2BGR))
    from ..outputs import OutputError, atomic_path

    if not ok:
        raise OutputError(f"cannot encode {path}")
    with atomic_path(path) as tmp:  # removes the temporary and names the reason on failure
        tmp.write_bytes(data.tobytes())


def evaluate(run_dir: str | Path, lpips_weights: str | None = None, device: str = "auto",
             write_images: bool = True, scene: str | Path | None = None, force: bool = True,
             other_scene: bool = False) -> dict:
    """Score the run in `run_dir` (see the module doc) -> RUN/metrics.json and RUN/eval/*.png. `scene`: the
    scene file instead of the one the run records (one that is not the run's scene, by name, size or
    fingerprint, only with `other_scene`); without `force` an existing metrics.json is refused (OutputError).
    The earlier evaluation's images are removed."""
    run = Path(run_dir)
    dev = resolve_device(device)
    cfg, model = load_run(run, dev, scene=scene, other_scene=other_scene)
    import errno

    from ..outputs import OutputError, check_output_dir, remove_stale_temps
    from .trainer import clear_eval_images

    if not force and (run / "metrics.json").exists():
        raise OutputError(f"{run / 'metrics.json'} exists (the run was evaluated before); pass --force to "
                          "evaluate again and replace it and the eval images", errno.EEXIST)
    check_output_dir(run, option="run folder")  # writable? before rendering every view
    for folder in (run, run / "eval"):
        remove_stale_temps(folder)
    sc = schema.read(cfg.scene)
    W, H = sc.camera.width, sc.camera.height
    K = torch.as_tensor(sc.camera.K, dtype=model.dtype, device=dev)
    bg = torch.as_tensor(sc.camera.background if sc.camera.background is not None else (0, 0, 0),
                         dtype=model.dtype, device=dev)
    lp, lpips_failed = None, None
    if lpips_weights is not None:
        # a missing or bad weights file, no network for the fetch, too small images: found before any rendering,
        # and PSNR/SSIM are still scored; "lpips_reason" says what is missing (the CLI then exits 2)
        try:
            lp = load_lpips(lpips_weights, dev)
            lp.check_size(W, H)
        except InputError as e:
            lp, lpips_failed = None, f"LPIPS not computed: {e}"
    metrics = {"run": str(run), "scene": cfg.scene,  # the resolved, absolute path
               "variant": cfg.variant, "seed": cfg.seed, "iterations": cfg.iterations,
               "lpips": lp.info if lp else None,
               "lpips_reason": None if lp else lpips_failed or lpips_unavailable_reason(None)}
    if lpips_failed:
        metrics["lpips_failed"] = True
    out_dir = run / "eval"
    clear_eval_images(run)  # the images of an earlier evaluation (other views, other model)
    if write_images:
        out_dir.mkdir(exist_ok=True)
    refined_mid = align = None
    if cfg.refine_poses:
        refined_mid, align, initial_mid = _refined_frame(run, sc)
        metrics["test_alignment"] = align
    if sc.test is not None and len(sc.test.images):
        test_poses = np.asarray(sc.test.poses)
        if align is not None:
            from .pose_refine import apply_similarity

            unaligned = render_views(model, test_poses, K, W, H, bg, cfg.backend)
            metrics["novel_view_unaligned"] = _scores(unaligned, np.asarray(sc.test.images), lp)
            test_poses = apply_similarity(test_poses, align["scale"], np.asarray(align["rotation"]),
                                          np.asarray(align["translation"]))
        pred = render_views(model, test_poses, K, W, H, bg, cfg.backend)
        truth = np.asarray(sc.test.images)
        metrics["test"] = _scores(pred, truth, lp)
        novel = sc.config.get("test_novel_views") if sc.train.sharp is None else None
        if isinstance(novel, list) and all(isinstance(i, int) and 0 <= i < len(pred) for i in novel):
            blur_ids = [i for i in range(len(pred)) if i not in set(novel)]
            metrics["novel_view"] = _scores([pred[i] for i in novel], truth[novel], lp)
            if blur_ids:
                metrics["blur_view"] = _scores([pred[i] for i in blur_ids], truth[blur_ids], lp)
        else:
            metrics["novel_view"] = metrics["test"]
        for i, (p, t) in enumerate(zip(pred, truth)) if write_images else ():
            _png(out_dir / f"test_{i:03d}.png", (t, p), ("ground truth", "rendered"))
    tr = sc.train
    if tr.sharp is not None and tr.sharp_poses is not None:
        pred = render_views(model, np.asarray(tr.sharp_poses), K, W, H, bg, cfg.backend)
        sharp, blurry = np.asarray(tr.sharp), np.asarray(tr.images)
        if refined_mid is not None:
            metrics["blur_view_given_poses"] = _scores(pred, sharp, lp)
            pred = render_views(model, refined_mid, K, W, H, bg, cfg.backend)
        metrics["train_sharp"] = metrics["blur_view"] = _scores(pred, sharp, lp)
        metrics["blurry_input"] = _scores(list(blurry), sharp, lp)
        for i, (b, p, s) in enumerate(zip(blurry, pred, sharp)) if write_images else ():
            _png(out_dir / f"train_{i:03d}.png", (b, p, s), ("blurry input", "rendered", "ground truth"))
    if "test" not in metrics and "train_sharp" not in metrics:
        raise InputError(f"{cfg.scene}: no sharp ground truth (/test or /train/sharp) to evaluate against")
    from ..outputs import atomic_path

    with atomic_path(run / "metrics.json") as tmp:
        tmp.write_text(json.dumps(metrics, indent=2))
    return metrics
