"""ev3dgs: train / eval / render / export, and scene-file info / validate."""
from __future__ import annotations

import sys

from .common import dispatch, parser, subparsers


def _train(args) -> int:
    from ..train.config import TrainConfig
    from ..train.trainer import Trainer

    cfg = TrainConfig(
        scene=args.scene, iterations=args.iterations, subposes=args.subposes, event_weight=args.event_weight,
        event_pairs=args.event_pairs, naive=args.naive, event_loss=not args.no_event_loss,
        blur_space=args.blur_space, learn_thresholds=args.learn_thresholds, sh_degree=args.sh_degree,
        init_points=args.init_points, checkpoint_every=args.checkpoint_every, seed=args.seed,
        device=args.device, threads=args.threads, backend=args.backend)
    if args.resume:
        from pathlib import Path

        saved = Path(args.out) / "config.json"
        if saved.exists():
            cfg = TrainConfig.load(saved)
            if args.iterations != cfg.iterations:  # allow extending a finished run
                from dataclasses import replace

                cfg = replace(cfg, iterations=args.iterations)
    trainer = Trainer(cfg, args.out, quiet=args.quiet)
    rec = trainer.fit(resume=args.resume)
    if not args.quiet:
        print(f"trained {rec.get('step', trainer.step)} steps: loss {rec.get('loss', float('nan')):.5f}, "
              f"{len(trainer.model)} Gaussians -> {args.out} (model.pt, ckpt.pt, log.jsonl, training.png)")
    return 0


def _eval(args) -> int:
    from ..train.evaluate import evaluate

    m = evaluate(args.run, lpips_weights=args.lpips_weights, device=args.device)
    for key, label in (("test", "novel views"), ("train_sharp", "deblurred training views"),
                       ("blurry_input", "blurry input (baseline)")):
        if key in m:
            print(f"{label:26s} PSNR {m[key]['psnr']:6.2f} dB  SSIM {m[key]['ssim']:.4f}  ({m[key]['n']} views)")
    print(f"LPIPS: {m['lpips_reason']}" if m["lpips"] is None else f"LPIPS {m['lpips']:.4f}")
    print(f"-> {args.run}/metrics.json, {args.run}/eval/*.png")
    return 0


def _render(args) -> int:
    import numpy as np
    import torch

    from .. import schema
    from ..train.evaluate import load_run
    from ..train.paths import orbit_path, render_frames, write_frames

    cfg, model = load_run(args.run)
    sc = schema.read(cfg.scene)
    poses = orbit_path(np.asarray(sc.train.sharp_poses if sc.train.sharp_poses is not None
                                  else sc.train.poses[:, sc.train.poses.shape[1] // 2]), args.frames)
    K = torch.as_tensor(sc.camera.K, dtype=model.dtype)
    bg = torch.as_tensor(sc.camera.background or (0, 0, 0), dtype=model.dtype)
    write_frames(render_frames(model, poses, K, sc.camera.width, sc.camera.height, bg, backend=cfg.backend),
                 args.out, fps=args.fps)
    print(f"rendered {args.frames} frames -> {args.out}")
    return 0


def _export(args) -> int:
    from ..train.evaluate import load_run
    from ..train.export import save_ply

    _, model = load_run(args.run)
    save_ply(model, args.ply)
    print(f"{len(model)} Gaussians -> {args.ply}")
    return 0


def _info(args) -> int:
    from .info import describe

    print(describe(args.file))
    return 0


def _validate(args) -> int:
    from .. import schema

    schema.validate(args.file, require_complete=not args.partial)
    print(f"{args.file}: valid")
    return 0


def build_parser():
    p = parser("ev3dgs", "Event-enhanced 3D Gaussian Splatting: train, evaluate, render, export.")
    sub = subparsers(p)
    t = sub.add_parser("train", help="train a 3DGS model on a scene file (blur + event rendering losses)")
    t.add_argument("scene", help="scene .h5 with /train/poses")
    t.add_argument("--out", required=True, help="run folder")
    t.add_argument("--iterations", type=int, default=3000)
    t.add_argument("--subposes", type=int, default=5, help="renders across each exposure (b+1, default 5)")
    t.add_argument("--event-weight", type=float, default=1 / 625, help="omega (default 1/625)")
    t.add_argument("--event-pairs", type=int, default=0, help="random pairs per step (0 = all pairs)")
    t.add_argument("--naive", action="store_true", help="ablation: plain 3DGS on the blurry frame at the mid pose")
    t.add_argument("--no-event-loss", action="store_true", help="ablation: blur loss only")
    t.add_argument("--blur-space", choices=("srgb", "linear"), default="srgb")
    t.add_argument("--learn-thresholds", action="store_true")
    t.add_argument("--sh-degree", type=int, default=3)
    t.add_argument("--init-points", type=int, default=20000)
    t.add_argument("--checkpoint-every", type=int, default=500)
    t.add_argument("--resume", action="store_true", help="continue from RUN/ckpt.pt")
    t.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    t.add_argument("--backend", choices=("auto", "reference", "cpu", "cuda"), default="auto")
    t.add_argument("--threads", type=int)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--quiet", action="store_true")
    t.set_defaults(func=_train)
    e = sub.add_parser("eval", help="PSNR/SSIM on sharp novel and deblurred training views -> metrics.json")
    e.add_argument("run")
    e.add_argument("--lpips-weights", help="LPIPS backbone weights (no downloads are possible here)")
    e.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    e.set_defaults(func=_eval)
    r = sub.add_parser("render", help="render a smooth camera path to a folder of PNGs or an .mp4")
    r.add_argument("run")
    r.add_argument("--out", required=True)
    r.add_argument("--frames", type=int, default=120)
    r.add_argument("--fps", type=int, default=30)
    r.set_defaults(func=_render)
    x = sub.add_parser("export", help="write the standard 3DGS .ply")
    x.add_argument("run")
    x.add_argument("--ply", required=True)
    x.set_defaults(func=_export)
    i = sub.add_parser("info", help="summarise a scene file (.h5)")
    i.add_argument("file")
    i.set_defaults(func=_info)
    v = sub.add_parser("validate", help="check a scene file against the schema")
    v.add_argument("file")
    v.add_argument("--partial", action="store_true", help="accept an events-only file (no /train, no K)")
    v.set_defaults(func=_validate)
    return p


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser, argv)


if __name__ == "__main__":
    sys.exit(main())
