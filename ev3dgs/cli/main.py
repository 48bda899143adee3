"""ev3dgs: train / eval / render / export / view, and scene-file info / validate."""
from __future__ import annotations

import argparse
import sys

from ..train.config import DENSIFY_FROM, EVENT_WEIGHTS, FLOOR_STATS, MAP_WEIGHTS
from .common import add_output_options, dispatch, finite_float, parser, subparsers


def _need_backend(backend: str) -> None:
    """--backend cuda needs the optional gsplat: say so now, not after loading the data."""
    if backend == "cuda":
        import importlib.util

        if importlib.util.find_spec("gsplat") is None:
            from ..errors import Ev3dgsError

            raise Ev3dgsError("--backend cuda needs gsplat, which is not installed: pip install ev3dgs[cuda]")


def _check_train(args) -> None:
    """Before loading anything: the run folder can take model.pt and checkpoints, holds no earlier run (unless
    --resume or --force), and the backend exists."""
    from ..outputs import OutputError, check_output_dir, remove_stale_temps
    from ..train.trainer import holds_run

    if args.resume and args.force:
        raise OutputError("--resume continues the run in --out, --force replaces it: give one")
    if args.map_weights != "prior" and not args.threshold_map and not args.resume:
        from ..errors import ConfigError

        raise ConfigError(f"--map-weights {args.map_weights} weighs the events by a threshold map: give "
                          "--threshold-map too")
    _need_backend(args.backend)
    if not args.resume and not args.force and holds_run(args.out):
        import errno

        raise OutputError(f"--out {args.out} holds a training run already; pass --resume to continue it or "
                          "--force to start a new one (its model, checkpoint, log and metrics are removed)",
                          errno.EEXIST)
    per_gaussian = 4 * (3 + 4 + 3 + 1 + 3 * (args.sh_degree + 1) ** 2)  # float32 parameters
    # ckpt.pt (parameters + 2 Adam moments), its temporary while it replaces the old one, model.pt
    check_output_dir(args.out, 7 * per_gaussian * max(1, args.init_points))
    for name in ("ckpt.pt", "model.pt", "config.json"):
        remove_stale_temps(args.out, name)
    import warnings

    from .. import schema

    # every byte of the scene read once now: a damaged chunk in /test or /train/sharp (read only by eval and
    # export-dataset) fails before the training, not after it; the trainer repeats the warnings itself
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        schema.validate(args.scene, read_data=True, warn=False)


_UNSET = object()


def _record_given(sub) -> None:
    """Make sub-parser `sub` note which options the command line gave (``args.given_options``, a set of
    dests): a resumed run must tell "not given" from "given, equal to the default"."""
    import argparse

    parse = sub.parse_known_args

    def parse_known_args(args=None, namespace=None):
        opts = [a for a in sub._actions if a.option_strings and a.default is not argparse.SUPPRESS]
        namespace = argparse.Namespace() if namespace is None else namespace
        for a in opts:
            if not hasattr(namespace, a.dest):
                setattr(namespace, a.dest, _UNSET)
        ns, rest = parse(args, namespace)
        ns.given_options = {a.dest for a in opts if getattr(ns, a.dest) is not _UNSET}
        for a in opts:
            if getattr(ns, a.dest) is _UNSET:
                setattr(ns, a.dest, sub._get_value(a, a.default) if isinstance(a.default, str) and a.type
                        else a.default)
        return ns, rest

    sub.parse_known_args = parse_known_args


def _auto_or(parse, expected: str):
    """An argparse type for an option whose value is "auto" (None: the trainer chooses) or ``parse(text)``."""
    def convert(text: str):
        if text == "auto":
            return None
        try:
            return parse(text)
        except (ValueError, argparse.ArgumentTypeError):
            raise argparse.ArgumentTypeError(f"expected auto or {expected}, got {text!r}") from None
    return convert


_frame_noise = _auto_or(finite_float, "a number")   # --frame-noise: auto = estimated from the frames
_sh_interval = _auto_or(int, "an integer")          # --sh-interval: auto = scaled to --iterations


def _train(args) -> int:
    _check_train(args)
    from ..train.config import TrainConfig, resume_config
    from ..train.trainer import Trainer

    import os

    opts = dict(
        scene=os.path.abspath(args.scene), iterations=args.iterations, subposes=args.subposes,
        subpose_px=args.subpose_px, event_weight=args.event_weight,
        event_norm=args.event_norm, event_mismatch=args.event_mismatch,
        event_pairs=args.event_pairs, event_floor=args.event_floor, event_huber=args.event_huber,
        densify_from=args.densify_from, frame_noise=args.frame_noise, naive=args.naive,
        event_loss=not args.no_event_loss,
        blur_space=args.blur_space, event_domain=args.event_domain, oracle=args.oracle,
        learn_thresholds=args.learn_thresholds, threshold_map=args.threshold_map, map_weights=args.map_weights,
        hdr=args.hdr,
        learn_response=args.learn_response,
        edi_prior=args.edi_prior, edi_anneal=args.edi_anneal, sh_degree=args.sh_degree, sh_interval=args.sh_interval,
        init_points=args.init_points, checkpoint_every=args.checkpoint_every, seed=args.seed,
        device=args.device, threads=args.threads, backend=args.backend,
        refine_poses=args.refine_poses, pose_lr=args.pose_lr, pose_lr_final=args.pose_lr_final,
        pose_start=args.pose_start, pose_warmup=args.pose_warmup, pose_max_rotation=args.pose_max_rotation,
        pose_max_translation=args.pose_max_translation, pose_gauge=args.pose_gauge, pose_frame=args.pose_frame)
    if args.resume:  # the run's saved settings, with only what the command line gave on top (checked there)
        given = {"scene"} | {{"no_event_loss": "event_loss"}.get(d, d) for d in getattr(args, "given_options", opts)}
        cfg = resume_config(args.out, opts, given)
    else:
        cfg = TrainConfig(**opts)
    from ..view.live import live_view

    with live_view(args, cfg) as on_step:  # None without --view
        trainer = Trainer(cfg, args.out, quiet=args.quiet)
        rec = trainer.fit(resume=args.resume, on_step=on_step)
    if not args.quiet:
        print(f"trained {rec.get('step', trainer.step)} steps: loss {rec.get('loss', float('nan')):.5f}, "
              f"{len(trainer.model)} Gaussians -> {args.out} (model.pt, ckpt.pt, log.jsonl, training.png)")
    return 0


def _say(args, text: str) -> None:
    """A summary line on stdout, unless --quiet."""
    if not getattr(args, "quiet", False):
        print(text)


def _eval(args) -> int:
    from ..train.evaluate import evaluate

    if args.lpips and args.lpips_weights:
        from ..errors import InputError

        raise InputError("give either --lpips NET (standard weights, fetched once) or --lpips-weights FILE")
    m = evaluate(args.run, lpips_weights=args.lpips or args.lpips_weights, device=args.device, scene=args.scene,
                 force=args.force, other_scene=args.other_scene)
    for key, label in (("test", "novel views"), ("novel_view_unaligned", "novel views, unaligned"),
                       ("train_sharp", "deblurred training views"),
                       ("blur_view_given_poses", "deblurred, at given poses"),
                       ("blurry_input", "blurry input (baseline)")):
        if key in m:
            lp = f"  LPIPS {m[key]['lpips']:.4f}" if "lpips" in m[key] else ""
            _say(args, f"{label:26s} PSNR {m[key]['psnr']:6.2f} dB  SSIM {m[key]['ssim']:.4f}{lp}  "
                       f"({m[key]['n']} views)")
    lp = m["lpips"]
    if not m.get("lpips_failed"):
        _say(args, f"LPIPS: {m['lpips_reason']}" if lp is None else f"LPIPS v{lp['version']} ({lp['net']}, "
                                                                     f"{lp['weights']})")
    _say(args, f"-> {args.run}/metrics.json, {args.run}/eval/*.png")
    if m.get("lpips_failed"):  # asked for and not computed: the scores above are written, the exit code says
        from ..errors import Ev3dgsError

        raise Ev3dgsError(f"{m['lpips_reason']}; PSNR and SSIM are written to {args.run}/metrics.json")
    return 0


def parse_size(text: str) -> tuple[int, int]:
    """argparse type: WxH (e.g. 640x480) -> (W, H)."""
    import argparse
    import re

    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if m is None or int(m[1]) < 1 or int(m[2]) < 1 or max(int(m[1]), int(m[2])) > 16384:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels (1-16384), e.g. 640x480, got {text!r}")
    return int(m[1]), int(m[2])


def _render(args) -> int:
    import torch

    from .. import schema
    from ..outputs import check_output_dir, check_output_file
    from ..train.evaluate import load_run, training_mid_poses
    from ..train.paths import orbit_path, output_kind, render_frames, scaled_camera, write_frames

    kind = output_kind(args.out)  # an unknown extension is refused before anything is loaded
    if args.frames < 1:
        from ..errors import InputError

        raise InputError(f"--frames must be >= 1, got {args.frames}")
    if not args.fps > 0:
        from ..errors import InputError

        raise InputError(f"--fps must be > 0, got {args.fps}")
    if kind == "png":
        check_output_dir(args.out, force=args.force)
    else:
        check_output_file(args.out, make_parents=True, force=args.force)
    cfg, model = load_run(args.run, scene=args.scene, other_scene=args.other_scene)
    sc = schema.read(cfg.scene)
    _need_backend(cfg.backend)
    W, H = sc.camera.width, sc.camera.height
    K = sc.camera.K
    if args.size is not None:
        K, (W, H) = scaled_camera(K, W, H, *args.size), args.size
    size = args.frames * W * H  # about 1 byte a pixel as PNG, less as mp4 or GIF
    if kind == "png":
        check_output_dir(args.out, size, force=True)
    else:
        check_output_file(args.out, size // 10, make_parents=True, force=True)
    mid, source = training_mid_poses(args.run, cfg, sc, given=args.given_poses)
    poses = orbit_path(mid, args.frames)
    K = torch.as_tensor(K, dtype=model.dtype)
    bg = torch.as_tensor(sc.camera.background or (0, 0, 0), dtype=model.dtype)
    info: dict = {}
    n = write_frames(render_frames(model, poses, K, W, H, bg, backend=cfg.backend), args.out, fps=args.fps,
                     info=info)
    codec = ("H.264" if info.get("fourcc") in ("avc1", "H264") else
             f"MPEG-4 part 2 (fourcc {info.get('fourcc')}; pip install 'ev3dgs[video]' for H.264)")
    what = {"png": "PNG frames", "gif": "GIF", "mp4": f"mp4, {codec}"}[kind]
    _say(args, f"rendered {n} frames ({W}x{H}, {what}) on an orbit around {source} -> {args.out}")
    return 0


def _export(args) -> int:
    from ..errors import InputError
    from ..outputs import check_output_file
    from ..train.evaluate import load_run
    from ..train.export import save_ply

    if args.out is None:
        raise InputError("export: give the output file with --out FILE.ply")
    if not str(args.out).lower().endswith(".ply"):
        raise InputError(f"--out {args.out}: export writes a .ply; give a file name ending in .ply")
    check_output_file(args.out, make_parents=True, force=args.force)
    _, model = load_run(args.run, find_scene=False)  # the model alone: no scene needed
    check_output_file(args.out, 4 * 62 * len(model), make_parents=True, force=True)
    save_ply(model, args.out)
    _say(args, f"{len(model)} Gaussians -> {args.out}")
    return 0


def _info(args) -> int:
    from pathlib import Path

    from .info import describe, describe_run

    print(describe_run(args.file) if Path(args.file).is_dir() else describe(args.file))
    return 0


def _validate(args) -> int:
    from .. import schema

    for note in schema.validate(args.file, require_complete=not args.partial, warn=False,
                                read_data=not args.quick):
        print(f"warning: {note}", file=sys.stderr)
    _say(args, f"{args.file}: valid")
    return 0


def _add_other_scene(p, verb: str) -> None:
    p.add_argument("--other-scene", action="store_true",
                   help=f"with --scene: {verb} on a scene file that is not the one the run was trained on (its name, "
                        "size or creation time differs; default: off, such a file is refused)")


def build_parser():
    p = parser("ev3dgs", "Event-enhanced 3D Gaussian Splatting: train, evaluate, render, export.")
    sub = subparsers(p)
    t = sub.add_parser("train", help="train a 3DGS model on a scene file (blur + event rendering losses)")
    t.add_argument("scene", help="scene file (.h5) with /train/poses")
    t.add_argument("--out", required=True, help="run folder (created if missing; model.pt, ckpt.pt, log.jsonl, "
                                                "config.json, training.png go there); a folder that holds a run "
                                                "already is refused unless --resume or --force")
    t.add_argument("--iterations", type=int, default=3000, help="optimisation steps (default %(default)s)")
    t.add_argument("--subposes", type=int, default=5,
                   help="renders across each exposure, b+1; with --subpose-px the most a view gets "
                        "(default %(default)s)")
    t.add_argument("--subpose-px", type=finite_float, default=0.0, metavar="P",
                   help="give each view the fewest renders (2 to --subposes) that lie at most P pixels apart "
                        "along its exposure's largest image motion (measured from the scene's poses and "
                        "points or bounds), so views that move more get more sub-poses "
                        "(default %(default)s: every view gets --subposes)")
    t.add_argument("--event-weight", type=finite_float, default=None,
                   help="omega, the weight of the event loss (default: the event norm's, "
                        f"{EVENT_WEIGHTS['noise']:g} for noise, 1/625 for count)")
    t.add_argument("--event-norm", choices=tuple(EVENT_WEIGHTS), default="noise",
                   help="noise: each event residual over its expected error (quantisation, threshold mismatch, "
                        "noise events and the model's own error), so finer thresholds never let the event term "
                        "swamp the blur loss; count: the residual in events, as E2NeRF/Ev3DGS "
                        "(default %(default)s)")
    t.add_argument("--event-mismatch", type=finite_float, default=None,
                   help="pixel-to-pixel threshold spread relative to the threshold, for --event-norm noise "
                        "(default: the scene's simulated value, or 0.1 for recordings)")
    t.add_argument("--event-pairs", type=int, default=0,
                   help="random pairs of sub-pose renders per step for the event loss, 0 = all pairs; a view "
                        "with fewer pairs (--subpose-px) uses all of them (default %(default)s)")
    t.add_argument("--event-floor", choices=FLOOR_STATS, default=None,
                   help="--event-norm noise: the model's own error, which caps every pixel-pair's weight: the "
                        "mean or the median of the pixel-pairs' squared residual beyond the counts' noise, or "
                        "chi2, the error at which their (--event-huber penalised) chi-square averages what the "
                        "noise model expects; the mean is set by the few pixels the model cannot render "
                        "(default chi2; the count norm has no floor)")
    t.add_argument("--event-huber", type=finite_float, default=None, metavar="C",
                   help="--event-norm noise: event residuals beyond C standard deviations pull linearly, not "
                        "quadratically (a Huber penalty); 0 = off (default 3; the count norm has none)")
    t.add_argument("--densify-from", choices=DENSIFY_FROM, default=None,
                   help="which loss's gradient decides where Gaussians are split and cloned: all of it, or the "
                        "blur term alone, so the event term's weight does not (one more backward pass through "
                        "the blur term per densifying step) (default blur under --event-norm noise, all under "
                        "count)")
    t.add_argument("--frame-noise", type=_frame_noise, default="auto", metavar="auto|SIGMA",
                   help="the blurry frames' noise, sigma in 8-bit levels: as the blur loss's error comes down to "
                        "that noise, which no model should fit, the event loss weighs up to 16 times more; 0 "
                        "turns it off (default %(default)s: estimated from the frames, 0 for clean ones)")
    t.add_argument("--naive", action="store_true",
                   help="ablation: plain 3DGS on the blurry frame at the mid pose (default: off)")
    t.add_argument("--no-event-loss", action="store_true",
                   help="ablation: blur loss only (default: off, the event loss is used)")
    t.add_argument("--blur-space", choices=("auto", "srgb", "linear"), default="auto",
                   help="where the sub-pose renders are averaged into the blurry image: srgb (stored) values or "
                        "linear intensity; auto: from the scene's /train transfer, linear for sRGB images of "
                        "linear-light blur, srgb for display/linear ones (default %(default)s)")
    t.add_argument("--event-domain", choices=("auto", "linear", "display"), default="auto",
                   help="what the event pixels' log is taken of: linear light or display values (v2e-made "
                        "events, E2NeRF); auto: from the scene's /train transfer (default %(default)s)")
    t.add_argument("--oracle", action="store_true",
                   help="the evaluation's upper bound: plain 3DGS on the sharp frames (/train/sharp) at their "
                        "poses, no blur model, no events (default: off)")
    t.add_argument("--learn-thresholds", action="store_true",
                   help="optimise the ON/OFF contrast thresholds (log intensity) with the model "
                        "(default: off, the scene file's thresholds are kept fixed)")
    t.add_argument("--threshold-map", action="store_true",
                   help="estimate each pixel's ON and OFF thresholds (the sensor's fixed-pattern mismatch) "
                        "from the events as the model fits, with the scene's mismatch or --event-mismatch as "
                        "prior; for sensors with a large pixel-to-pixel spread; noise norm only; no effect "
                        "where the mismatch is 0 (default: off)")
    t.add_argument("--map-weights", choices=MAP_WEIGHTS, default="prior",
                   help="with --threshold-map, how the events are weighed: prior = by the mismatch the map "
                        "started from, as without a map (only the thresholds change); posterior = by each "
                        "pixel's remaining threshold error after the fit, ON and OFF independently "
                        "(default %(default)s)")
    t.add_argument("--hdr", action="store_true",
                   help="let the model hold radiance above the frame's full scale (specular highlights, lamps): "
                        "renders above 1 decode to up to 10^4 x full scale, the blurry frame is modelled as "
                        "the exposure's integral clipped by the sensor, and the sharp renders clip at 1; "
                        "linear-light blur model only (default: off)")
    t.add_argument("--learn-response", action="store_true",
                   help="learn the camera's response (a monotone curve before the sRGB decode, 16 segments, "
                        "starting at plain sRGB) from how the blurry frames and the events agree: for frames "
                        "with a tone curve the scene does not declare; linear-light blur model with sRGB "
                        "frames only; the curve is written to RUN/response.json (default: off)")
    t.add_argument("--edi-prior", type=finite_float, default=0.0, metavar="W",
                   help="add the event double integral prior with weight W (per unit of chi-square, like "
                        "--event-weight under the noise norm): each sub-pose render is pulled towards the sharp "
                        "frame the blurry frame and the exposure's events give (EDI), weighted by that "
                        "target's expected error, saturated pixels left out; noise norm only (default %(default)s: off)")
    t.add_argument("--edi-anneal", type=finite_float, default=0.5, metavar="F",
                   help="the EDI prior's weight falls linearly to 0 at this fraction of --iterations "
                        "(default %(default)s)")
    t.add_argument("--refine-poses", action="store_true",
                   help="learn per-view SE(3) corrections of each exposure's trajectory (start and end, "
                        "interpolated over the sub-poses) with the model; saves RUN/trajectory.npz, which eval "
                        "uses (default: off, the scene's poses are kept)")
    t.add_argument("--pose-lr", type=finite_float, default=1e-3,
                   help="Adam learning rate of the pose corrections, in radians and scene-scale units per "
                        "step (default %(default)s)")
    t.add_argument("--pose-lr-final", type=finite_float, default=0.01,
                   help="the pose learning rate decays exponentially to --pose-lr times this at the last step "
                        "(default %(default)s)")
    t.add_argument("--pose-start", type=int, default=100,
                   help="steps before the poses start moving (default %(default)s)")
    t.add_argument("--pose-warmup", type=int, default=100,
                   help="steps of linear warm-up of the pose learning rate after --pose-start "
                        "(default %(default)s)")
    t.add_argument("--pose-max-rotation", type=finite_float, default=5.0,
                   help="divergence guard: each correction's rotation is clamped to this, in degrees "
                        "(default %(default)s)")
    t.add_argument("--pose-max-translation", type=finite_float, default=0.1,
                   help="divergence guard: each correction's translation is clamped to this fraction of the "
                        "scene scale (1.1 x the largest camera distance from the cameras' centre; default "
                        "%(default)s)")
    t.add_argument("--pose-gauge", choices=("similarity", "none"), default="similarity",
                   help="similarity: remove the corrections' common rotation, translation and scale after every "
                        "update (the losses cannot see them); none: keep them (default %(default)s)")
    t.add_argument("--pose-frame", choices=("world", "camera"), default="world",
                   help="axes of the corrections: world, or camera (each view's own mid-exposure camera axes, "
                        "z the optical axis: the roll gets its own Adam scale) (default %(default)s)")
    t.add_argument("--sh-degree", type=int, default=3, help="spherical-harmonics degree of the colours, 0-3 "
                                                           "(default %(default)s)")
    t.add_argument("--sh-interval", type=_sh_interval, default="auto", metavar="auto|N",
                   help="raise the active spherical-harmonics degree by one every N steps, up to --sh-degree; "
                        "auto: the 3DGS schedule (every 1000 of 30 000 steps) scaled to --iterations, every "
                        "--iterations / 30 steps (default %(default)s)")
    t.add_argument("--init-points", type=int, default=20000,
                   help="random initial Gaussians inside the scene bounds when the file has no /points "
                        "(default %(default)s)")
    t.add_argument("--checkpoint-every", type=int, default=500,
                   help="write RUN/ckpt.pt every this many steps (default %(default)s)")
    t.add_argument("--resume", action="store_true", help="continue from RUN/ckpt.pt (default: off)")
    t.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="torch device; auto = cuda when available (default %(default)s)")
    t.add_argument("--backend", choices=("auto", "reference", "cpu", "cuda"), default="auto",
                   help="rasterizer: reference (plain torch), cpu (numba), cuda (gsplat, needs ev3dgs[cuda]); "
                        "auto = cuda for CUDA tensors when gsplat is installed, else cpu (default %(default)s)")
    t.add_argument("--threads", type=int, help="CPU threads for torch (default: torch's choice, all cores)")
    t.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    add_output_options(t, force_help="start a new run in a --out folder that holds one: the old run's model.pt, "
                                     "ckpt.pt, log.jsonl, metrics.json, eval images, trajectory.npz and "
                                     "training.png are removed, other files kept (default: off, refused)")
    from ..view.command import add_train_options

    add_train_options(t)  # --view, --view-every, --view-host, --view-port
    t.set_defaults(func=_train)
    _record_given(t)
    e = sub.add_parser("eval", help="PSNR/SSIM (and LPIPS with --lpips) on sharp novel and deblurred training "
                                    "views -> metrics.json")
    e.add_argument("run", help="run folder written by `ev3dgs train`")
    e.add_argument("--lpips", choices=("alex", "vgg"),
                   help="also LPIPS v0.1 with this trunk, as the lpips package computes it: the torchvision "
                        "ImageNet weights are fetched once into torch's hub cache ($TORCH_HOME, checksum "
                        "verified) and the v0.1 linear weights from the lpips package (or fetched the same way); "
                        "images must be >= 31 px (alex) or 16 px (vgg) per side (default: none, LPIPS is skipped)")
    e.add_argument("--lpips-weights", metavar="FILE",
                   help="LPIPS v0.1 weights from a file instead: one torch file with "
                        "lpips.LPIPS(net='alex' or 'vgg').state_dict() (default: none)")
    e.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="torch device; auto = cuda when available (default %(default)s)")
    e.add_argument("--scene", metavar="FILE",
                   help="the scene file to evaluate on (default: the one the run records, looked for relative to "
                        "the run folder, at its absolute path, then by name beside the run folder and its parents)")
    _add_other_scene(e, "evaluate")
    add_output_options(e, force_help="evaluate a run that has metrics.json already, replacing it and the eval "
                                     "images (default: off, refused)")
    e.set_defaults(func=_eval)
    r = sub.add_parser("render", help="render a smooth camera path to an .mp4, a .gif or a folder of PNGs")
    r.add_argument("run", help="run folder written by `ev3dgs train`")
    r.add_argument("--out", required=True,
                   help="FILE.mp4 (H.264 where the installed OpenCV can encode it, else MPEG-4), FILE.gif "
                        "(animated GIF), or a folder name without an extension for frame_NNNN.png; any other "
                        "extension is refused")
    r.add_argument("--frames", type=int, default=120, help="frames along the orbit (default %(default)s)")
    r.add_argument("--fps", type=int, default=30, help="frames per second of an .mp4 or .gif (default %(default)s)")
    r.add_argument("--size", type=parse_size, metavar="WxH",
                   help="render at this resolution, e.g. 1280x960 (the camera's intrinsics scaled to it; "
                        "default: the scene's camera size)")
    r.add_argument("--scene", metavar="FILE",
                   help="the scene file whose cameras and background are used (default: the one the run records)")
    _add_other_scene(r, "render")
    r.add_argument("--given-poses", action="store_true",
                   help="for a --refine-poses run, build the orbit around the scene's given poses instead of the "
                        "refined trajectory (trajectory.npz) the model was trained in (default: off)")
    add_output_options(r)
    r.set_defaults(func=_render)
    x = sub.add_parser("export", help="write the standard 3DGS .ply")
    x.add_argument("run", help="run folder written by `ev3dgs train`")
    x.add_argument("--out", metavar="FILE.ply",
                   help="output .ply (graphdeco 3DGS layout, written atomically; required)")
    x.add_argument("--ply", dest="out", help=argparse.SUPPRESS)  # the option's earlier name
    add_output_options(x)
    x.set_defaults(func=_export)
    i = sub.add_parser("info", help="summarise a scene file (.h5) or a training run folder")
    i.add_argument("file", help="scene file (.h5), or a run folder written by `ev3dgs train` (its settings, "
                                "progress, scene and metrics)")
    i.set_defaults(func=_info)
    v = sub.add_parser("validate", help="check a scene file against the schema")
    v.add_argument("file", help="scene file (.h5)")
    v.add_argument("--partial", action="store_true",
                   help="accept an events-only file, no /train and no K (default: off, a complete file is required)")
    v.add_argument("--quick", action="store_true",
                   help="check the layout, values and events but not every byte of the images (default: off, "
                        "every dataset is read so that a damaged compressed chunk is found)")
    v.add_argument("--quiet", action="store_true", help="no summary line; the exit code says (default: off)")
    v.set_defaults(func=_validate)
    from .export_dataset import add_parser as add_export_dataset  # issue 19: ev3dgs export-dataset

    add_export_dataset(sub)
    from ..view.command import add_parser as add_view_parser

    add_view_parser(sub)  # `ev3dgs view` (browser viewer, optional extra ev3dgs[view]; --out FILE.png without it)
    return p


def _interrupt_hint(args, argv: list[str]) -> str | None:
    """After Ctrl-C in `ev3dgs train`: the exact command that continues the run from its last checkpoint."""
    if getattr(args, "command", None) != "train":
        return None
    import shlex
    from pathlib import Path

    ckpt = Path(args.out) / "ckpt.pt"
    if not ckpt.is_file():
        return (f"no checkpoint was written yet (one every --checkpoint-every {args.checkpoint_every} steps), so "
                "there is nothing to resume: run the same command again to start over")
    again = [a for a in argv if a != "--force"] + ([] if "--resume" in argv else ["--resume"])
    return f"the run keeps its last checkpoint, {ckpt}; continue it with: {shlex.join(['ev3dgs', *again])}"


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser, argv, on_interrupt=_interrupt_hint)


if __name__ == "__main__":
    sys.exit(main())
