"""ev3dgs-ingest: bring recordings into the scene schema. (Readers for AEDAT and E2NeRF come next.)"""
from __future__ import annotations

import sys

from .common import parser, run, subparsers


def build_parser():
    p = parser("ev3dgs-ingest", "Bring event-camera recordings into the ev3dgs scene schema.")
    sub = subparsers(p)
    i = sub.add_parser("info", help="summarise a scene file (.h5)")
    i.add_argument("file")
    return p


def _main(argv):
    from .info import describe

    args = build_parser().parse_args(argv)
    print(describe(args.file))
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(_main, argv)


if __name__ == "__main__":
    sys.exit(main())
