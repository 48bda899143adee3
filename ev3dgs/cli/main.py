"""ev3dgs: train / eval / render / export / view, and scene-file info / validate."""
from __future__ import annotations

import sys

from .common import dispatch, finite_float, parser, subparsers


def _need_backend(backend: str) -> None:
    """--backend cuda needs the optional gsplat: say so now, not after loading the data."""
    if backend == "cuda":
        import importlib.util

        if importlib.util.find_spec("gsplat") is None:
            from ..errors import Ev3dgsError

            raise Ev3dgsError("--backend cuda needs gsplat, which is not installed: pip install ev3dgs[cuda]")


def _check_train(args) -> None:
    """Before loading anything: the run folder can take model.pt and checkpoints, and the backend exists."""
    from ..outputs import check_output_dir, remove_stale_temps

    _need_backend(args.backend)
    per_gaussian = 4 * (3 + 4 + 3 + 1 + 3 * (args.sh_degree + 1) ** 2)  # float32 parameters
    # ckpt.pt (parameters + 2 Adam moments), its temporary while it replaces the old one, model.pt
    check_output_dir(args.out, 7 * per_gaussian * max(1, args.init_points))
    for name in ("ckpt.pt", "model.pt", "config.json"):
        remove_stale_temps(args.out, name)


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


def _train(args) -> int:
    _check_train(args)
    from ..train.config import TrainConfig, resume_config
    from ..train.trainer import Trainer

    opts = dict(
        scene=args.scene, iterations=args.iterations, subposes=args.subposes, event_weight=args.event_weight,
        event_pairs=args.event_pairs, naive=args.naive, event_loss=not args.no_event_loss,
        blur_space=args.blur_space, event_domain=args.event_domain, oracle=args.oracle,
        learn_thresholds=args.learn_thresholds, sh_degree=args.sh_degree,
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


def _eval(args) -> int:
    from ..train.evaluate import evaluate

    m = evaluate(args.run, lpips_weights=args.lpips_weights, device=args.device)
    for key, label in (("test", "novel views"), ("novel_view_unaligned", "novel views, unaligned"),
                       ("train_sharp", "deblurred training views"),
                       ("blur_view_given_poses", "deblurred, at given poses"),
                       ("blurry_input", "blurry input (baseline)")):
        if key in m:
            lp = f"  LPIPS {m[key]['lpips']:.4f}" if "lpips" in m[key] else ""
            print(f"{label:26s} PSNR {m[key]['psnr']:6.2f} dB  SSIM {m[key]['ssim']:.4f}{lp}  ({m[key]['n']} views)")
    lp = m["lpips"]
    print(f"LPIPS: {m['lpips_reason']}" if lp is None else f"LPIPS v{lp['version']} ({lp['net']}, {lp['weights']})")
    print(f"-> {args.run}/metrics.json, {args.run}/eval/*.png")
    return 0


def _render(args) -> int:
    import numpy as np
    import torch

    from .. import schema
    from ..train.evaluate import load_run, training_mid_poses
    from ..train.paths import orbit_path, render_frames, write_frames

    cfg, model = load_run(args.run)
    sc = schema.read(cfg.scene)
    from ..outputs import check_output_dir, check_output_file

    _need_backend(cfg.backend)
    size = args.frames * sc.camera.width * sc.camera.height  # about 1 byte a pixel as PNG, less as mp4
    if str(args.out).lower().endswith(".mp4"):
        check_output_file(args.out, size // 10, make_parents=True)
    else:
        check_output_dir(args.out, size)
    mid, source = training_mid_poses(args.run, cfg, sc, given=args.given_poses)
    poses = orbit_path(mid, args.frames)
    K = torch.as_tensor(sc.camera.K, dtype=model.dtype)
    bg = torch.as_tensor(sc.camera.background or (0, 0, 0), dtype=model.dtype)
    write_frames(render_frames(model, poses, K, sc.camera.width, sc.camera.height, bg, backend=cfg.backend),
                 args.out, fps=args.fps)
    print(f"rendered {args.frames} frames on an orbit around {source} -> {args.out}")
    return 0


def _export(args) -> int:
    from ..train.evaluate import load_run
    from ..train.export import save_ply

    from ..outputs import check_output_file

    _, model = load_run(args.run)
    check_output_file(args.ply, 4 * 62 * len(model), make_parents=True, option="--ply")
    save_ply(model, args.ply)
    print(f"{len(model)} Gaussians -> {args.ply}")
    return 0


def _info(args) -> int:
    from .info import describe

    print(describe(args.file))
    return 0


def _validate(args) -> int:
    from .. import schema

    for note in schema.validate(args.file, require_complete=not args.partial, warn=False):
        print(f"warning: {note}", file=sys.stderr)
    print(f"{args.file}: valid")
    return 0


def build_parser():
    p = parser("ev3dgs", "Event-enhanced 3D Gaussian Splatting: train, evaluate, render, export.")
    sub = subparsers(p)
    t = sub.add_parser("train", help="train a 3DGS model on a scene file (blur + event rendering losses)")
    t.add_argument("scene", help="scene file (.h5) with /train/poses")
    t.add_argument("--out", required=True, help="run folder (created if missing; model.pt, ckpt.pt, log.jsonl, "
                                                "config.json, training.png go there)")
    t.add_argument("--iterations", type=int, default=3000, help="optimisation steps (default %(default)s)")
    t.add_argument("--subposes", type=int, default=5, help="renders across each exposure, b+1 (default %(default)s)")
    t.add_argument("--event-weight", type=finite_float, default=1 / 625,
                   help="omega, the weight of the event loss (default 1/625 = %(default)s)")
    t.add_argument("--event-pairs", type=int, default=0,
                   help="random pairs of sub-pose renders per step for the event loss, 0 = all pairs "
                        "(default %(default)s)")
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
    t.add_argument("--init-points", type=int, default=20000,
                   help="random initial Gaussians inside the scene bounds when the file has no /points "
                        "(default %(default)s)")
    t.add_argument("--checkpoint-every", type=int, default=500,
                   help="write RUN/ckpt.pt every this many steps (default %(default)s)")
    t.add_argument("--resume", action="store_true", help="continue from RUN/ckpt.pt")
    t.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="torch device; auto = cuda when available (default %(default)s)")
    t.add_argument("--backend", choices=("auto", "reference", "cpu", "cuda"), default="auto",
                   help="rasterizer: reference (plain torch), cpu (numba), cuda (gsplat, needs ev3dgs[cuda]); "
                        "auto = cuda for CUDA tensors when gsplat is installed, else cpu (default %(default)s)")
    t.add_argument("--threads", type=int, help="CPU threads for torch (default: torch's choice, all cores)")
    t.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    t.add_argument("--quiet", action="store_true", help="no progress bar or summary (default: off)")
    from ..view.command import add_train_options

    add_train_options(t)  # --view, --view-every, --view-host, --view-port
    t.set_defaults(func=_train)
    _record_given(t)
    e = sub.add_parser("eval", help="PSNR/SSIM (LPIPS with --lpips-weights) on sharp novel and deblurred training "
                                    "views -> metrics.json")
    e.add_argument("run", help="run folder written by `ev3dgs train`")
    e.add_argument("--lpips-weights", metavar="FILE",
                   help="LPIPS v0.1 weights: one torch file with lpips.LPIPS(net='alex' or 'vgg').state_dict() "
                        "(recipe: ev3dgs/train/lpips.py); images must be >= 31 px (alex) or 16 px (vgg) per side "
                        "(default: none, LPIPS is skipped; nothing is downloaded)")
    e.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="torch device; auto = cuda when available (default %(default)s)")
    e.set_defaults(func=_eval)
    r = sub.add_parser("render", help="render a smooth camera path to a folder of PNGs or an .mp4")
    r.add_argument("run", help="run folder written by `ev3dgs train`")
    r.add_argument("--out", required=True, help="a folder for frame_NNNN.png, or a file ending in .mp4")
    r.add_argument("--frames", type=int, default=120, help="frames along the orbit (default %(default)s)")
    r.add_argument("--fps", type=int, default=30, help="frames per second of an .mp4 (default %(default)s)")
    r.add_argument("--given-poses", action="store_true",
                   help="for a --refine-poses run, build the orbit around the scene's given poses instead of the "
                        "refined trajectory (trajectory.npz) the model was trained in (default: off)")
    r.set_defaults(func=_render)
    x = sub.add_parser("export", help="write the standard 3DGS .ply")
    x.add_argument("run", help="run folder written by `ev3dgs train`")
    x.add_argument("--ply", required=True, help="output .ply (graphdeco 3DGS layout, written atomically)")
    x.set_defaults(func=_export)
    i = sub.add_parser("info", help="summarise a scene file (.h5)")
    i.add_argument("file", help="scene file (.h5)")
    i.set_defaults(func=_info)
    v = sub.add_parser("validate", help="check a scene file against the schema")
    v.add_argument("file", help="scene file (.h5)")
    v.add_argument("--partial", action="store_true",
                   help="accept an events-only file, no /train and no K (default: off, a complete file is required)")
    v.set_defaults(func=_validate)
    from .export_dataset import add_parser as add_export_dataset  # issue 19: ev3dgs export-dataset

    add_export_dataset(sub)
    from ..view.command import add_parser as add_view_parser

    add_view_parser(sub)  # `ev3dgs view` (browser viewer, optional extra ev3dgs[view]; --png without it)
    return p


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser, argv)


if __name__ == "__main__":
    sys.exit(main())
