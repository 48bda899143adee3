"""ev3dgs-ingest: bring recordings and other datasets into the scene schema."""
from __future__ import annotations

import sys

from .common import add_output_options, dispatch, finite_float, parser, subparsers


def _input_file(path: str) -> None:
    from pathlib import Path

    from ..errors import InputError

    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not a file")


def _output_file(out: str, estimated_bytes: int, force: bool) -> None:
    from pathlib import Path

    from ..outputs import check_output_file, remove_stale_temps

    check_output_file(out, estimated_bytes, make_parents=True, force=force)
    from ..claims import claim_output
    claim_output(out, force=force)  # one writer (ev3dgs.claims)
    if Path(out).parent.is_dir():
        remove_stale_temps(Path(out).parent, Path(out).name)


def _sensor_size(text: str) -> tuple[int, int]:
    """argparse type: WxH in pixels."""
    import argparse

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH in pixels (e.g. 240x180), got {text!r}") from None
    if not (0 < w <= 1023 and 0 < h <= 511):
        raise argparse.ArgumentTypeError(f"sensor size {w}x{h} outside 1..1023 x 1..511 (the AEDAT address range)")
    return w, h


def _info(args) -> int:
    import json
    import warnings
    from pathlib import Path

    from ..io.recording import MAGIC
    from .info import jsonable, recording_text, scene_summary

    _input_file(args.file)
    with open(args.file, "rb") as f:
        head = f.read(16)
    if any(head.startswith(m) for m in MAGIC) or not head or Path(args.file).suffix.lower().startswith(".aedat"):
        from ..io.recording import open_recording

        with warnings.catch_warnings():     # the reader lists its warnings; print each once, below
            warnings.simplefilter("ignore")
            with open_recording(args.file, strict=args.strict, sensor_size=args.sensor_size) as reader:
                # AEDAT 4 info reads only the header and the packet table unless asked to decode and check
                info = reader.info(scan=args.scan or args.strict) if reader.format == "aedat4" else reader.info()
        info = jsonable(dict(info) if isinstance(info, dict) else vars(info))
        found = list(dict.fromkeys(reader.warnings))
        if args.json:
            info.update(path=str(args.file), format=reader.format, warnings=found)
            print(json.dumps(info, indent=2))
            for w in found:
                print(f"warning: {w}", file=sys.stderr)
        else:
            print(recording_text(args.file, reader.format, info, found))
    elif args.json:
        info = scene_summary(args.file)
        print(json.dumps(info, indent=2))
        for w in info["warnings"]:
            print(f"warning: {w}", file=sys.stderr)
    else:
        from .info import describe

        print(describe(args.file))
    return 0


def kept_events_line(stats, opts) -> str:
    """'kept N of M events (why)': what --events kept of the recording's events stream."""
    if opts.events == "all":
        why = "--events all keeps every event"
    else:
        n = stats.exposures
        why = (f"--events margin: {opts.event_margin_ms:g} ms either side of the {n:,} selected exposure"
               f"{'' if n == 1 else 's'}; --events all keeps every event")
    line = f"kept {stats.events:,} of {stats.events_in_file:,} events ({why})"
    if stats.events_read > stats.events:
        line += f"; {stats.events_read - stats.events:,} fell outside the sensor once undistorted"
    return line


def _davis(args) -> int:
    import os

    from ..errors import InputError
    from ..io.davis import DavisOptions, ingest_davis

    if args.sensor is not None and (args.pos_threshold is not None or args.neg_threshold is not None
                                    or args.color_filter is not None):
        raise InputError("--sensor gives the thresholds and colour filter: drop --pos-threshold, "
                         "--neg-threshold and --color-filter, or drop --sensor")
    _input_file(args.recording)
    # a rough lower bound: the events kept (a fraction of the recording with --events margin) and the frames
    _output_file(args.out, os.path.getsize(args.recording) // (4 if args.events == "all" else 20), args.force)
    opts = DavisOptions(every=args.every, max_views=args.max_views, min_exposure_us=args.min_exposure_us,
                        events=args.events, event_margin_ms=args.event_margin_ms, subposes=args.subposes,
                        poses=not args.no_poses, calibration=args.calibration, frames_stream=args.frames_stream,
                        events_stream=args.events_stream,
                        pos_threshold=0.2 if args.pos_threshold is None else args.pos_threshold,
                        neg_threshold=0.2 if args.neg_threshold is None else args.neg_threshold,
                        color_filter=args.color_filter or "none", strict=args.strict,
                        sensor_size=args.sensor_size, sensor=args.sensor, min_registered=args.min_registered,
                        check_motion=not args.no_motion_check)
    stats = ingest_davis(args.recording, args.out, opts, quiet=args.quiet)
    for w in dict.fromkeys(stats.warnings):
        print(f"warning: {w}", file=sys.stderr)
    if not args.quiet:
        reg = ("" if stats.registered is None else
               f", {stats.registered} of {stats.latent_frames} latent frames registered by pycolmap")
        print(kept_events_line(stats, opts))
        print(f"{stats.views} views (of {stats.frames_in_file} frames), {stats.events:,} events{reg} -> {args.out}")
    return 0


def _e2nerf(args) -> int:
    from ..io.e2nerf import import_e2nerf

    _output_file(args.out, 0, args.force)
    path = import_e2nerf(args.directory, args.out, pos_threshold=args.pos_threshold,
                         neg_threshold=args.neg_threshold)
    if not args.quiet:
        print(f"imported {args.directory} -> {path}")
    return 0


def build_parser():
    p = parser("ev3dgs-ingest", "Bring event-camera recordings and datasets into the ev3dgs scene schema.")
    sub = subparsers(p)
    i = sub.add_parser("info", help="summarise a recording (.aedat4/.aedat/.aedat3) or a scene file (.h5)")
    i.add_argument("file", help="recording (.aedat4/.aedat/.aedat3) or scene file (.h5)")
    i.add_argument("--scan", action="store_true",
                   help="AEDAT 4.0: also decode and check every packet, as reading does (default: off: only the header "
                        "and the packet table are read, counts and time ranges come from the FileDataTable; AEDAT "
                        "2.0/3.1 recordings are always scanned)")
    i.add_argument("--strict", action="store_true",
                   help="fail (exit 2) on the first corrupt packet or value the recording contradicts; implies "
                        "--scan (default: off: drop it with a warning)")
    i.add_argument("--sensor-size", type=_sensor_size, metavar="WxH",
                   help="sensor size of an AEDAT 2.0/3.1 recording whose header names no camera, e.g. 240x180 "
                        "(default: from the header; without one, inferred from the addresses with a warning)")
    i.add_argument("--json", action="store_true",
                   help="print the same information as JSON, for scripts (default: off, aligned text); warnings "
                        "are in its \"warnings\" list and on stderr")
    i.set_defaults(func=_info)
    d = sub.add_parser("davis", help="a DAVIS recording (DAVIS346/240, jAER or DV) -> scene.h5 (EDI + pycolmap poses)")
    d.add_argument("recording", help="DAVIS recording (.aedat4, .aedat3 or .aedat 2.0)")
    d.add_argument("--out", required=True, help="output scene file (.h5, written atomically)")
    d.add_argument("--calibration", help="DV/OpenCV camera-calibration XML, or TOML/JSON (fx fy cx cy ...) "
                                         "(default: none, pycolmap estimates the intrinsics)")
    d.add_argument("--every", type=int, default=1, help="use every K-th APS frame (default %(default)s = every frame)")
    d.add_argument("--max-views", type=int, help="keep at most this many views (default: no limit)")
    d.add_argument("--min-exposure-us", type=int, default=0,
                   help="skip APS frames exposed for less than this, in microseconds (default %(default)s us)")
    d.add_argument("--events", choices=("all", "margin"), default="margin",
                   help="which events to keep: margin keeps only the events within --event-margin-ms before or "
                        "after the exposure of a used view (the default, %(default)s); all keeps the whole "
                        "recording")
    d.add_argument("--event-margin-ms", type=finite_float, default=10.0,
                   help="with --events margin: milliseconds kept either side of each used exposure "
                        "(default %(default)s ms)")
    d.add_argument("--subposes", type=int, default=5, help="EDI latent frames / poses per view (default %(default)s)")
    d.add_argument("--no-poses", action="store_true",
                   help="skip EDI + pycolmap pose estimation: a scene file without poses, for `ev3dgs info`, "
                        "`ev3dgs view --out` and `ev3dgs export-dataset --format events-h5 or aedat4`, not for "
                        "training (default: off, poses are estimated)")
    d.add_argument("--min-registered", type=finite_float, default=0.5,
                   help="fraction of the EDI sub-frames pycolmap must register, else ingest fails "
                        "(default %(default)s)")
    d.add_argument("--no-motion-check", action="store_true",
                   help="estimate poses even when the IMU and the frames show a camera that did not move "
                        "(default: off, such a recording is refused in seconds: pose estimation needs a moving "
                        "camera)")
    d.add_argument("--sensor-size", type=_sensor_size, metavar="WxH",
                   help="sensor size of an AEDAT 2.0/3.1 recording whose header names no camera, e.g. 240x180 "
                        "(default: from the header; without one, inferred from the addresses with a warning)")
    d.add_argument("--frames-stream", help="AEDAT4 stream name of the APS frames (default: the first frame stream)")
    d.add_argument("--events-stream", help="AEDAT4 stream name of the events (default: the first event stream)")
    d.add_argument("--pos-threshold", type=finite_float,
                   help="ON contrast threshold in log intensity; not stored in recordings (default 0.2)")
    d.add_argument("--neg-threshold", type=finite_float,
                   help="OFF contrast threshold in log intensity (default 0.2)")
    d.add_argument("--color-filter",
                   help="Bayer pattern of a colour DAVIS346's DVS, e.g. RGGB (default none)")
    d.add_argument("--sensor", help="sensor TOML from `ev3dgs-sim calibrate` (or the NAME.sensor.toml "
                                    "`ev3dgs-sim record` writes): thresholds, mismatch, refractory period, leak "
                                    "and shot noise go into the scene file for the trainer's event noise model "
                                    "(default: none, thresholds from the options above and no noise model)")
    add_output_options(d)
    d.add_argument("--strict", action="store_true",
                   help="fail (exit 2) on the first corrupt packet or value the recording contradicts (default: off: "
                        "drop it with a warning)")
    d.set_defaults(func=_davis)
    e = sub.add_parser("e2nerf", help="an E2NeRF dataset folder (synthetic or real) -> scene.h5")
    e.add_argument("directory", help="E2NeRF scene folder (synthetic or real-world layout)")
    e.add_argument("--out", required=True, help="output scene file (.h5, written atomically)")
    e.add_argument("--pos-threshold", type=finite_float, default=0.2,
                   help="ON contrast threshold in log intensity (default %(default)s)")
    e.add_argument("--neg-threshold", type=finite_float, default=0.2,
                   help="OFF contrast threshold in log intensity (default %(default)s)")
    add_output_options(e)
    e.set_defaults(func=_e2nerf)
    return p


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser, argv)


if __name__ == "__main__":
    sys.exit(main())
