"""The `ev3dgs export-dataset` sub-command (registered by ev3dgs.cli.main)."""
from __future__ import annotations

import sys


def _run(args) -> int:
    from ..exporters import export_dataset

    opts = {"e2nerf": {"layout": args.layout, "bins": args.bins}, "transforms": {"images": args.images},
            "aedat4": {"compression": args.compression}}.get(args.format, {})
    from ..claims import claim_output
    claim_output(args.out, force=args.force, folder=True)  # before any work
    export_dataset(args.scene, args.format, args.out, force=args.force, quiet=args.quiet, **opts)
    if not args.quiet:
        print(f"exported {args.scene} as {args.format} -> {args.out} (see {args.out}/README.txt for what was "
              "converted and what the layout cannot hold)", file=sys.stdout)
    return 0


def add_parser(sub) -> None:
    from ..exporters import FORMATS
    from .common import add_output_options
    from ..exporters.aedat4 import COMPRESSION

    x = sub.add_parser("export-dataset", help="write a scene file in the layouts other methods and tools read "
                                              "(E2NeRF, DSEC-style events HDF5, AEDAT 4, NeRF transforms.json)")
    x.add_argument("scene", help="scene file (.h5)")
    x.add_argument("--format", required=True, choices=FORMATS,
                   help="e2nerf: E2NeRF/E2GS folder with events.pt; events-h5: DSEC-style events.h5 + frames; "
                        "aedat4: DV recording; transforms: nerfstudio / NeRF transforms.json (no default)")
    x.add_argument("--out", required=True, help="output folder, built under a temporary sibling name and renamed "
                                                "when complete (no default)")
    add_output_options(x, force_help="replace a non-empty --out folder (default: off, a non-empty folder is "
                                     "refused)")
    x.add_argument("--layout", choices=("auto", "synthetic", "llff"), default="auto",
                   help="e2nerf only: synthetic (Blender json + train/test PNGs) or llff (real-world: images/ + "
                        "poses_bounds.npy); auto = llff for DAVIS recordings, else synthetic (default %(default)s)")
    x.add_argument("--bins", type=int, default=4,
                   help="e2nerf only: event bins per exposure, b; b+1 poses at the bin edges (default %(default)s, "
                        "what E2NeRF's code expects)")
    x.add_argument("--images", choices=("blurry", "sharp", "both"), default="blurry",
                   help="transforms only: training frames, blurry at the mid-exposure pose, sharp (synthetic "
                        "scenes) or both (default %(default)s)")
    x.add_argument("--compression", choices=sorted(COMPRESSION), default="lz4",
                   help="aedat4 only: packet compression (default %(default)s)")
    x.set_defaults(func=_run)
