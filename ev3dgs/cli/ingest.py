"""ev3dgs-ingest: bring recordings and other datasets into the scene schema."""
from __future__ import annotations

import sys

from .common import dispatch, parser, subparsers


def _info(args) -> int:
    from ..io.recording import MAGIC

    with open(args.file, "rb") as f:
        head = f.read(16)
    if any(head.startswith(m) for m in MAGIC):
        from ..io.recording import open_recording

        with open_recording(args.file) as reader:
            info = reader.info()
        print(f"{args.file}: {reader.format}")
        for key, value in (info.items() if isinstance(info, dict) else vars(info).items()):
            print(f"  {key}: {value}")
        for w in reader.warnings:
            print(f"  warning: {w}")
    else:
        from .info import describe

        print(describe(args.file))
    return 0


def _davis(args) -> int:
    from ..io.davis import DavisOptions, ingest_davis

    opts = DavisOptions(every=args.every, max_views=args.max_views, min_exposure_us=args.min_exposure_us,
                        events=args.events, event_margin_ms=args.event_margin_ms, subposes=args.subposes,
                        poses=not args.no_poses, calibration=args.calibration, frames_stream=args.frames_stream,
                        events_stream=args.events_stream, pos_threshold=args.pos_threshold,
                        neg_threshold=args.neg_threshold, color_filter=args.color_filter)
    stats = ingest_davis(args.recording, args.out, opts)
    for w in stats.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if not args.quiet:
        reg = ("" if stats.registered is None else
               f", {stats.registered} of {stats.latent_frames} latent frames registered by pycolmap")
        print(f"{stats.views} views (of {stats.frames_in_file} frames), {stats.events} events{reg} -> {args.out}")
    return 0


def _e2nerf(args) -> int:
    from ..io.e2nerf import import_e2nerf

    path = import_e2nerf(args.directory, args.out, pos_threshold=args.pos_threshold,
                         neg_threshold=args.neg_threshold)
    if not args.quiet:
        print(f"imported {args.directory} -> {path}")
    return 0


def build_parser():
    p = parser("ev3dgs-ingest", "Bring event-camera recordings and datasets into the ev3dgs scene schema.")
    sub = subparsers(p)
    i = sub.add_parser("info", help="summarise a recording (.aedat4/.aedat/.aedat3) or a scene file (.h5)")
    i.add_argument("file")
    i.set_defaults(func=_info)
    d = sub.add_parser("davis", help="a DAVIS346 recording -> scene.h5 (EDI + pycolmap poses)")
    d.add_argument("recording")
    d.add_argument("--out", required=True)
    d.add_argument("--calibration", help="DV/OpenCV camera-calibration XML, or TOML/JSON (fx fy cx cy ...)")
    d.add_argument("--every", type=int, default=1, help="use every K-th APS frame")
    d.add_argument("--max-views", type=int)
    d.add_argument("--min-exposure-us", type=int, default=0)
    d.add_argument("--events", choices=("all", "margin"), default="margin")
    d.add_argument("--event-margin-ms", type=float, default=10.0)
    d.add_argument("--subposes", type=int, default=5, help="EDI latent frames / poses per view")
    d.add_argument("--no-poses", action="store_true")
    d.add_argument("--frames-stream")
    d.add_argument("--events-stream")
    d.add_argument("--pos-threshold", type=float, default=0.2)
    d.add_argument("--neg-threshold", type=float, default=0.2)
    d.add_argument("--color-filter", default="none", help="Bayer pattern of a colour DAVIS346's DVS (e.g. RGGB)")
    d.add_argument("--quiet", action="store_true")
    d.set_defaults(func=_davis)
    e = sub.add_parser("e2nerf", help="an E2NeRF dataset folder (synthetic or real) -> scene.h5")
    e.add_argument("directory")
    e.add_argument("--out", required=True)
    e.add_argument("--pos-threshold", type=float, default=0.2)
    e.add_argument("--neg-threshold", type=float, default=0.2)
    e.add_argument("--quiet", action="store_true")
    e.set_defaults(func=_e2nerf)
    return p


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser, argv)


if __name__ == "__main__":
    sys.exit(main())
