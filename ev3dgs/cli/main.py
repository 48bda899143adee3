"""ev3dgs: scene files (validate, info); training arrives with the trainer."""
from __future__ import annotations

import sys

from .common import parser, run, subparsers


def build_parser():
    p = parser("ev3dgs", "Event-enhanced 3D Gaussian Splatting toolkit.")
    sub = subparsers(p)
    i = sub.add_parser("info", help="summarise a scene file (.h5)")
    i.add_argument("file")
    v = sub.add_parser("validate", help="check a scene file against the schema")
    v.add_argument("file")
    v.add_argument("--partial", action="store_true", help="accept an events-only file (no /train, no K)")
    return p


def _main(argv):
    args = build_parser().parse_args(argv)
    if args.command == "info":
        from .info import describe

        print(describe(args.file))
    else:
        from .. import schema

        schema.validate(args.file, require_complete=not args.partial)
        print(f"{args.file}: valid")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
