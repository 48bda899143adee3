"""`ev3dgs view PATH`: argument parsing and the command (registered by ev3dgs/cli/main.py)."""
from __future__ import annotations

import sys
from pathlib import Path

from ..errors import InputError

DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8080


def port_number(text: str) -> int:
    import argparse

    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number, got {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0-65535, got {v}")
    return v


def add_parser(sub) -> None:
    import argparse

    v = sub.add_parser("view", help="look at a scene file or a training run in the browser (viser), or as a PNG")
    v.add_argument("path", help="scene file (.h5) or run folder written by `ev3dgs train`")
    v.add_argument("--out", metavar="FILE.png",
                   help="write the content as a static figure to this PNG (contact sheet of frames, event images "
                        "and a top view of the trajectories) instead of starting the viewer (default: none, start "
                        "the viewer)")
    v.add_argument("--png", dest="out", help=argparse.SUPPRESS)  # the option's earlier name
    v.add_argument("--scene", metavar="FILE",
                   help="for a run folder: the scene file to show it with (default: the one the run records, "
                        "looked for relative to the run folder, at its absolute path, then by name beside it)")
    v.add_argument("--other-scene", action="store_true",
                   help="with --scene: show the run with a scene file that is not the one it was trained on (its "
                        "name, size or creation time differs; default: off, such a file is refused)")
    v.add_argument("--rows", type=int, default=4,
                   help="training views (rows) in the --out contact sheet, spread over all views "
                        "(default %(default)s)")
    v.add_argument("--host", default=DEFAULT_HOST,
                   help="address the viewer binds to; 0.0.0.0 makes it reachable from other machines "
                        "(default %(default)s, local connections only)")
    v.add_argument("--port", type=port_number, default=DEFAULT_PORT,
                   help="TCP port of the viewer; when taken the next free one is used, 0 = any free port "
                        "(default %(default)s)")
    v.add_argument("--select", type=int, default=0,
                   help="training view selected when the page opens (index, default %(default)s)")
    from ..cli.common import add_output_options

    add_output_options(v)
    v.set_defaults(func=run)


def add_train_options(t) -> None:
    """`ev3dgs train --view`: the options on the train parser."""
    t.add_argument("--view", action="store_true",
                   help="show the training in the browser viewer (viser, ev3dgs[view]), updated every "
                        "--view-every steps (default: off)")
    t.add_argument("--view-every", type=int, default=100,
                   help="steps between viewer updates with --view (default %(default)s)")
    t.add_argument("--view-host", default=DEFAULT_HOST,
                   help="address the --view viewer binds to (default %(default)s, local connections only)")
    t.add_argument("--view-port", type=port_number, default=DEFAULT_PORT,
                   help="TCP port of the --view viewer, the next free one when taken (default %(default)s)")


def run(args) -> int:
    from . import data

    if args.rows < 1:
        raise InputError(f"--rows must be >= 1, got {args.rows}")
    if args.out is None:
        from .server import require_viser

        require_viser()  # before reading anything: the one-line install hint comes first
    else:
        from ..outputs import check_output_file

        if not str(args.out).lower().endswith(".png"):
            raise InputError(f"--out {args.out}: view writes a PNG figure; give a file name ending in .png")
        check_output_file(args.out, 2 << 20, make_parents=True, force=args.force)
        from ..claims import claim_output
        claim_output(args.out, force=args.force)  # one writer (ev3dgs.claims)
    if Path(args.path).is_dir():
        content = data.load_run_content(args.path, scene=args.scene, other_scene=args.other_scene)
    elif args.scene is not None or args.other_scene:
        raise InputError(f"{'--scene' if args.scene is not None else '--other-scene'} is for a run folder; a "
                         "scene file is shown as it is")
    else:
        content = data.load(args.path)
    scene = content.scene if isinstance(content, data.RunContent) else content
    if scene.n_views and not 0 <= args.select < scene.n_views:
        raise InputError(f"--select {args.select}: the scene has views 0-{scene.n_views - 1}")
    if args.out is not None:
        from .figure import write_png

        write_png(content, args.out, rows=args.rows)
        if not args.quiet:
            print(f"-> {args.out}")
        return 0
    from .server import Viewer

    viewer = Viewer(args.host, args.port, label=f"ev3dgs: {scene.scene.name or scene.path.name}")
    try:
        viewer.show_scene(scene, args.select)
        if isinstance(content, data.RunContent):
            viewer.show_splats(data.splat_arrays(content.model))
            if content.refined_poses is not None:
                viewer.show_refined(scene, content.refined_poses, content.refined_t)
            viewer.set_status(f"run {content.path}: {len(content.model)} Gaussians from {content.source}")
    except BaseException:
        viewer.stop()
        raise
    viewer.serve()
    print("viewer stopped", file=sys.stderr)
    return 0
