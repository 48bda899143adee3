"""What every CLI shares: one-line errors with exit code 2, atomic output files."""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from ..errors import Ev3dgsError


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # argparse's usage dump -> our one line, exit 2
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def parser(prog: str, description: str) -> argparse.ArgumentParser:
    return _Parser(prog=prog, description=description)


def subparsers(p: argparse.ArgumentParser):
    return p.add_subparsers(dest="command", required=True, parser_class=_Parser)


def dispatch(build_parser: Callable[[], argparse.ArgumentParser], argv: list[str] | None = None) -> int:
    """Parse argv with the CLI's parser and call the chosen sub-command (its `func`), with one-line errors."""
    def _main(argv):
        args = build_parser().parse_args(argv)
        return args.func(args)

    return run(_main, argv)


def run(main: Callable[[list[str] | None], int], argv: list[str] | None = None) -> int:
    """Call main; turn our errors into `error: ...` on stderr and exit code 2."""
    try:
        return main(argv) or 0
    except Ev3dgsError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130


def write_atomic(path: str | Path, data: bytes) -> None:
    """Write bytes to a temporary file beside `path`, then rename: readers never see half a file."""
    path = Path(path)
    if not path.parent.exists():
        raise Ev3dgsError(f"output folder does not exist: {path.parent}")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
