"""ev3dgs: train / eval / render / export / view, and scene-file info / validate."""
from __future__ import annotations

import argparse
import sys

from .common import add_output_options, dispatch, finite_float, parser, subparsers


def _need_backend(backend: str) -> None:
    """--backend cuda needs the optional gsplat: say so now, not after loading the data."""
    if backend == "cuda":
        import importlib.util

        if importlib.util.find_spec("gsplat") is None:
            from ..errors import Ev3dgsError

            raise Ev3dgsError("--backend cuda needs gsplat, which is not installed: pip install ev3dgs[cuda]")


def _check_train(args, cfg) -> None:
    """Before loading anything: the run folder can take model.pt and checkpoints, holds no earlier run (unless
    --resume or --force), and the backend exists."""
    from ..outputs import OutputError, check_output_dir, remove_stale_temps
    from ..train.trainer import holds_run

    _need_backend(cfg.backend)
    from ..claims import claim_run
    claim_run(args.out)  # one process at a time writes a run folder (ev3dgs.claims)
    if not args.resume and not args.force and holds_run(args.out):
        import errno

        raise OutputError(f"--out {args.out} holds a training run already; pass --resume to continue it or "
                          "--force to start a new one (its model, checkpoint, log and metrics are removed)",
                          errno.EEXIST)
    per_gaussian = 4 * (3 + 4 + 3 + 1 + 3 * (cfg.sh_degree + 1) ** 2)  # float32 parameters
    # ckpt.pt (parameters + 2 Adam moments), its temporary while it replaces the old one, model.pt
    check_output_dir(args.out, 7 * per_gaussian * max(1, cfg.init_points))
    for name in ("ckpt.pt", "model.pt", "config.json", "config.toml"):
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
        opts = [a for a in sub._actions if a.option_strings and a.default is not argparse.SUPPRESS
                and not isinstance(a, argparse._AppendAction)]   # --set: its own list, None when not given
        from ..train.layout import former_flag_message

        for a in args or ():   # a flag that became a config key: say which, in one line
            hint = former_flag_message(a) if isinstance(a, str) and a.startswith("--") else None
            if hint is not None:
                from ..errors import ConfigError

                raise ConfigError(hint)
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


# the command-line options of `ev3dgs train` that set a train.toml key: dest -> (key, value from args)
_TRAIN_FLAGS = {"iterations": ("iterations", lambda a: a.iterations), "seed": ("seed", lambda a: a.seed),
                "threads": ("threads", lambda a: a.threads), "backend": ("backend", lambda a: a.backend),
                "naive": ("naive", lambda a: a.naive), "oracle": ("oracle", lambda a: a.oracle)}


def train_settings(args) -> tuple[dict, set]:
    """(train.toml dict, TrainConfig fields the command line gave): --config (or the defaults), the options,
    then every --set."""
    import os

    from ..config import load_toml
    from ..train.config import TrainConfig
    from ..train.layout import FIELD_KEY, LAYOUT, SWITCHES, apply_set, parse_set

    given = set(getattr(args, "given_options", set()))
    data = load_toml(args.config) if args.config else TrainConfig.default_toml()
    fields = {"scene"}
    if args.config:   # every setting the file holds, and the switches of the terms it leaves out
        fields |= {f for t, keys in LAYOUT.items() for k, f in keys.items()
                   if (k in data if not t else k in data.get(t, {}))}
        fields |= set(SWITCHES.values()) | {"edi_prior"}
    data["scene"] = os.path.abspath(args.scene)
    for dest, (key, value) in _TRAIN_FLAGS.items():
        if dest in given:
            data[key] = value(args)
            fields.add(key)
    if "backend" in given and args.backend in ("cpu", "cuda"):   # --backend cpu/cuda: the device too
        data["device"] = args.backend
        fields.add("device")
    if args.no_event_loss:
        data.pop("events", None)
        fields.add("event_loss")
    if args.refine_poses:
        data.setdefault("poses", {})
        fields.add("refine_poses")
    data = apply_set(data, args.set or [])
    field_of = {key: f for f, key in FIELD_KEY.items()}
    for item in args.set or []:
        path, _ = parse_set(item)
        fields.add(field_of.get(".".join(path), field_of.get(path[0], path[0])))
    return data, fields


def _train(args) -> int:
    from ..train.config import TrainConfig, resume_config
    from ..train.layout import view_settings
    from ..train.trainer import Trainer

    if args.resume and args.force:
        from ..outputs import OutputError

        raise OutputError("--resume continues the run in --out, --force replaces it: give one")
    data, given = train_settings(args)
    cfg = TrainConfig.from_toml(data)
    if args.resume:  # the run's saved settings, with only what the command line gave on top (checked there)
        from dataclasses import asdict

        cfg = resume_config(args.out, asdict(cfg), given)
    _check_train(args, cfg)
    view = {"every": 100, "host": None, "port": None, **view_settings(data)}
    args.view_every = view["every"]
    if view["host"] is not None:
        args.view_host = view["host"]
    if view["port"] is not None:
        args.view_port = view["port"]
    from ..view.live import live_view

    with live_view(args, cfg) as on_step:  # None without --view
        trainer = Trainer(cfg, args.out, quiet=args.quiet)
        rec = trainer.fit(resume=args.resume, on_step=on_step)
    if not args.quiet:
        print(f"trained {rec.get('step', trainer.step)} steps: loss {rec.get('loss', float('nan')):.5f}, "
              f"{len(trainer.model)} Gaussians -> {args.out} (model.pt, ckpt.pt, log.jsonl, config.toml, "
              "training.png)")
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
    from ..claims import claim_run
    claim_run(args.run, option="run folder")  # eval writes into it
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
    from ..claims import claim_output
    claim_output(args.out, force=args.force, folder=kind == "png")  # before any work (ev3dgs.claims)
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
    from ..claims import claim_output
    claim_output(args.out, force=args.force)  # before any work
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


def _VIEW_DEFAULTS():
    from ..view.command import DEFAULT_HOST, DEFAULT_PORT

    return DEFAULT_HOST, DEFAULT_PORT


def build_parser():
    p = parser("ev3dgs", "Event-enhanced 3D Gaussian Splatting: train, evaluate, render, export.")
    sub = subparsers(p)
    t = sub.add_parser("train", help="train a 3DGS model on a scene file (blur + event rendering losses)")
    t.add_argument("scene", help="scene file (.h5) with /train/poses")
    t.add_argument("--out", required=True, help="run folder (created if missing; model.pt, ckpt.pt, log.jsonl, "
                                                "config.json, training.png go there); a folder that holds a run "
                                                "already is refused unless --resume or --force")
    t.add_argument("--config", metavar="TOML",
                   help="settings file (train.toml): core settings at the top, one table per term ([blur], "
                        "[events], [poses], [edi_prior], [threshold_map], [hdr], [response], [densify], [view]); "
                        "a term whose table is absent is off; see docs/trainer.md (default: the built-in "
                        "settings, blur + event losses)")
    t.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one setting of the config, e.g. --set events.huber=3 or --set init_points=5000 "
                        "(a TOML value; a key of an absent term's table turns that term on); repeatable")
    t.add_argument("--iterations", type=int, default=3000, help="optimisation steps (default %(default)s)")
    t.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    t.add_argument("--backend", choices=("auto", "reference", "cpu", "cuda"), default="auto",
                   help="rasterizer and device: reference (plain torch), cpu (numba, on the CPU), cuda (gsplat on "
                        "the GPU, needs ev3dgs[cuda]); auto = cuda when a GPU and gsplat are there, else cpu "
                        "(default %(default)s)")
    t.add_argument("--threads", type=int, help="CPU threads for torch (default: torch's choice, all cores)")
    t.add_argument("--naive", action="store_true",
                   help="ablation: plain 3DGS on the blurry frame at the mid pose (default: off)")
    t.add_argument("--no-event-loss", action="store_true",
                   help="ablation: blur loss only, the [events] table dropped (default: off, the event loss is "
                        "used)")
    t.add_argument("--oracle", action="store_true",
                   help="the evaluation's upper bound: plain 3DGS on the sharp frames (/train/sharp) at their "
                        "poses, no blur model, no events (default: off)")
    t.add_argument("--refine-poses", action="store_true",
                   help="learn per-view SE(3) corrections of each exposure's trajectory with the model ([poses] "
                        "table); saves RUN/trajectory.npz, which eval uses (default: off, the scene's poses "
                        "are kept)")
    t.add_argument("--resume", action="store_true",
                   help="continue from RUN/ckpt.pt with the run's settings (RUN/config.toml); only --iterations "
                        "(the schedules keep the run's original length), checkpoint_every and --threads may "
                        "change (default: off)")
    add_output_options(t, force_help="start a new run in a --out folder that holds one: the old run's model.pt, "
                                     "ckpt.pt, log.jsonl, metrics.json, eval images, trajectory.npz and "
                                     "training.png are removed, other files kept (default: off, refused)")
    t.add_argument("--view", action="store_true",
                   help="show the training in the browser viewer (viser, ev3dgs[view]), updated every view.every "
                        "steps ([view] every, host, port in the config) (default: off)")
    t.set_defaults(func=_train, view_every=100, view_host=_VIEW_DEFAULTS()[0], view_port=_VIEW_DEFAULTS()[1])
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
        return ("no checkpoint was written yet (one every checkpoint_every steps), so there is nothing to "
                "resume: run the same command again to start over")
    again = [a for a in argv if a != "--force"] + ([] if "--resume" in argv else ["--resume"])
    return f"the run keeps its last checkpoint, {ckpt}; continue it with: {shlex.join(['ev3dgs', *again])}"


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser, argv, on_interrupt=_interrupt_hint)


if __name__ == "__main__":
    sys.exit(main())
