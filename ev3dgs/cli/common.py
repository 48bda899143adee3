"""What every CLI shares: one-line errors with exit code 2, atomic output files."""
from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

from ..errors import Ev3dgsError, raised_in_h5py


class _Parser(argparse.ArgumentParser):
    def error(self, message: str, prog: str | None = None):  # argparse's usage dump -> our one line, exit 2
        print(f"error: {message} (see {prog or self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)

    def parse_args(self, args=None, namespace=None):
        """argparse's, but an unknown option points to the help of the sub-command it was given to
        (`ev3dgs train --help`), where the options are listed, not to the program's."""
        ns, rest = self.parse_known_args(args, namespace)
        if rest:
            self.error(f"unrecognized arguments: {' '.join(rest)}", _subcommand_prog(self, ns))
        return ns


def _subcommand_prog(p: argparse.ArgumentParser, ns: argparse.Namespace) -> str | None:
    """The prog ("ev3dgs train") of the sub-command `ns` was parsed for, or None."""
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            sub = action.choices.get(getattr(ns, action.dest or "", None) or "")
            if sub is not None:
                return _subcommand_prog(sub, ns) or sub.prog
    return None


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGINT) with what the user can do next: `run` prints `error: interrupted; <message>`."""


def finite_float(text: str) -> float:
    """argparse type: a finite number (nan and inf are refused with one line, exit 2)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def int_in(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer in [lo, hi] (hi None: no upper bound)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < lo or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"{v} is outside [{lo}, {hi if hi is not None else 'inf'}]")
        return v
    parse.__name__ = "integer"
    return parse


def parser(prog: str, description: str) -> argparse.ArgumentParser:
    """A top-level parser with one-line errors and --version."""
    from .. import __version__

    p = _Parser(prog=prog, description=description)
    p.add_argument("--version", action="version", version=f"{prog} {__version__}")
    return p


def add_output_options(p: argparse.ArgumentParser, *, force_help: str = "replace an existing output "
                       "(default: off, an existing output is refused)") -> None:
    """--force and --quiet, the same words on every sub-command that writes."""
    p.add_argument("--force", action="store_true", help=force_help)
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary (default: off)")


def subparsers(p: argparse.ArgumentParser):
    return p.add_subparsers(dest="command", required=True, parser_class=_Parser)


def dispatch(build_parser: Callable[[], argparse.ArgumentParser], argv: list[str] | None = None,
             on_interrupt: Callable[[argparse.Namespace, list[str]], str | None] | None = None) -> int:
    """Parse argv with the CLI's parser and call the chosen sub-command (its `func`), with one-line errors.
    `on_interrupt(args, argv)`: what to tell the user after Ctrl-C (e.g. the command that resumes), or None."""
    def _main(argv):
        args = build_parser().parse_args(argv)
        try:
            return args.func(args)
        except KeyboardInterrupt:
            hint = on_interrupt(args, list(sys.argv[1:] if argv is None else argv)) if on_interrupt else None
            if hint:
                raise Interrupted(hint) from None
            raise

    return run(_main, argv)


_EXTRAS = {"gsplat": "pip install ev3dgs[cuda] (gsplat, for --backend cuda)",
           "ray": "pip install ev3dgs[ray] (for --executor ray)"}


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def warning_text(message, category: type[Warning], filename: str = "") -> str:
    """One line for a warning: ours (Ev3dgsWarning) as it is; any other library's (numpy, torch...) named as
    such, since it was not meant for the user and says nothing about what to do."""
    from ..errors import Ev3dgsWarning

    text = _one_line(message)
    parts = Path(str(filename)).parts
    lib = next((parts[i + 1] for i, d in enumerate(parts[:-1]) if d in ("site-packages", "dist-packages")), None)
    lib = (lib or "").removesuffix(".py")
    ours = lib == "ev3dgs" or (not lib and "ev3dgs" in parts)
    if issubclass(category, Ev3dgsWarning) or (category is UserWarning and ours):   # a plain warn() of ours
        return text
    who = f"the library {lib}" if lib and lib != "ev3dgs" else "a library ev3dgs uses"
    return (f"{who} warned: {text!r} ({category.__name__}; unexpected: the results may be affected, please "
            "report it with the command line)")


def error_message(e: BaseException) -> str | None:
    """The one-line message for an error a user can act on, or None for a bug (which keeps its traceback)."""
    from ..outputs import _is_write_failure, os_error_message

    if isinstance(e, Ev3dgsError):
        return str(e)
    if isinstance(e, ModuleNotFoundError) and e.name and not e.name.startswith("ev3dgs"):
        root = e.name.split(".")[0]
        hint = _EXTRAS.get(root, f"pip install {root}")
        return f"this needs the optional package {root!r}, which is not installed: {hint}"
    if raised_in_h5py(e):
        return f"HDF5: {e}"
    if isinstance(e, OSError):
        return os_error_message(e)
    if isinstance(e, RuntimeError) and _is_write_failure(e):
        return f"a file could not be written ({_one_line(e).split(' Exception raised from')[0]})"
    if isinstance(e, MemoryError):
        return "out of memory"
    return None


def run(main: Callable[[list[str] | None], int], argv: list[str] | None = None) -> int:
    """Call main; turn our errors, OS errors (disk full, read-only, missing files), h5py errors and missing
    optional packages into one line `error: ...` on stderr and exit code 2. EV3DGS_DEBUG=1 re-raises them
    with their traceback instead."""
    import warnings

    def _one_line_warning(message, category, filename, lineno, file=None, line=None):
        # our warnings (damaged packets, odd scenes) are for users: one line each, no source location
        print(f"warning: {warning_text(message, category, filename)}", file=file or sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning
            return main(argv) or 0
    except KeyboardInterrupt as e:
        print(f"error: interrupted{'; ' + _one_line(e) if isinstance(e, Interrupted) else ''}", file=sys.stderr)
        return 130
    except Exception as e:
        message = error_message(e)
        if message is None or os.environ.get("EV3DGS_DEBUG", "") not in ("", "0"):
            raise
        print(f"error: {_one_line(message)}", file=sys.stderr)
        return 2
    finally:
        from ..claims import release_all

        release_all()  # the outputs this command claimed (ev3dgs.claims)


def write_atomic(path: str | Path, data: bytes) -> None:
    """Write bytes to a temporary file beside `path`, then rename: readers never see half a file."""
    from ..outputs import atomic_path, remove_stale_temps

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)   # OSError (read-only, no space) -> one line from run()
    remove_stale_temps(path.parent, path.name)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
