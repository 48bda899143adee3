"""mkdocs hook: the option reference of every command page, generated from the real argparse parsers.

A page asks for a command's reference with a marker line of its own::

    <!-- cli-reference: ev3dgs train -->

and `on_page_markdown` replaces it with the usage line and a table of the arguments, built from
`ev3dgs.cli.sim.build_parser`, `ev3dgs.cli.ingest.build_parser` and `ev3dgs.cli.main.build_parser` at build time,
so the lists follow the code. A marker naming a command that does not exist, and a command without a page
(docs/commands/<program>-<command>.md), are logged as warnings: `mkdocs build --strict` fails on both.

The hook also copies the benchmark plots (tools/results/*.png) into the site under results/, so the pages can
show them without keeping a second copy in docs/.
"""
from __future__ import annotations

import argparse
import html
import importlib
import logging
import os
import re
from pathlib import Path

log = logging.getLogger("mkdocs.hooks.cli_reference")

PARSERS = {
    "ev3dgs-sim": "ev3dgs.cli.sim",
    "ev3dgs-ingest": "ev3dgs.cli.ingest",
    "ev3dgs": "ev3dgs.cli.main",
}
MARKER = re.compile(r"^<!--\s*cli-reference:\s*(\S+)\s+(\S+)\s*-->\s*$", re.MULTILINE)
REPO = Path(__file__).resolve().parents[2]


def build_parser(program: str) -> argparse.ArgumentParser:
    return importlib.import_module(PARSERS[program]).build_parser()


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """name -> sub-parser, in the order the CLI defines them."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def all_commands() -> list[tuple[str, str]]:
    """(program, command) for every sub-command of the three CLIs."""
    return [(prog, name) for prog in PARSERS for name in subcommands(build_parser(prog))]


def page_path(program: str, command: str) -> str:
    """The page of a command, relative to docs/."""
    return f"commands/{program}-{command}.md"


def _text(s: str) -> str:
    """Help text as a table cell: HTML-escaped, no markdown emphasis or table breaks, `code` kept."""
    s = html.escape(" ".join(str(s).split()), quote=False)
    for ch in "*_[]|":
        s = s.replace(ch, "\\" + ch)
    return s


def _code(s: str) -> str:
    s = str(s).replace("|", "\\|")
    return f"<code>{html.escape(s, quote=False)}</code>"


def _help(formatter: argparse.HelpFormatter, action: argparse.Action) -> str:
    if not action.help or action.help == argparse.SUPPRESS:
        return ""
    try:
        return formatter._expand_help(action)
    except (KeyError, TypeError, ValueError):
        return action.help


def _value(action: argparse.Action) -> str:
    """What the option takes: its choices, its metavar, or nothing for a flag."""
    if action.nargs == 0 or (not action.option_strings and action.choices is None and not action.metavar):
        return ""  # a flag, or a positional whose name is already in the first column
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        return " \\| ".join(_code(c) for c in action.choices)
    metavar = action.metavar or (action.dest.upper() if action.option_strings else action.dest)
    if isinstance(metavar, tuple):
        metavar = " ".join(metavar)
    if action.type is not None and getattr(action.type, "__name__", "") in ("int", "float", "finite_float"):
        kind = {"int": "integer", "float": "number", "finite_float": "number"}[action.type.__name__]
        return f"{_code(metavar)} ({kind})"
    return _code(metavar)


def _default(action: argparse.Action) -> str:
    if action.nargs == 0 or action.default in (None, argparse.SUPPRESS) or action.required:
        return ""
    return _code(action.default)


def reference(program: str, command: str) -> str:
    """The generated markdown for `program command`."""
    parser = subcommands(build_parser(program)).get(command)
    if parser is None:
        raise KeyError(f"{program} has no command {command!r}")
    formatter = parser._get_formatter()
    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps the usage to the terminal; the page gets a fixed width
    try:
        usage = parser.format_usage().strip()
    finally:
        if saved is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = saved
    usage = usage[len("usage: "):] if usage.startswith("usage: ") else usage
    out = ["## Options", "",
           f"Generated from the command's argparse parser when the site is built (`{program} {command} --help` "
           "prints the same).", "",
           "```text", usage, "```", ""]
    if parser.description:
        out += [_text(parser.description), ""]
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
            continue  # -h is mentioned below; hidden (deprecated) aliases are not documented
        name = ", ".join(_code(o) for o in action.option_strings) if action.option_strings else _code(action.dest)
        if not action.option_strings or action.required:
            name += " (required)"
        rows.append(f"| {name} | {_value(action)} | {_default(action)} | {_text(_help(formatter, action))} |")
    out += ["| argument | value | default | what it does |", "|---|---|---|---|", *rows, "",
            f"Every command also takes `-h` / `--help`; `{program} --version` prints the version.", ""]
    return "\n".join(out)


def on_page_markdown(markdown: str, page, config, files, **kwargs) -> str:
    def replace(m: re.Match) -> str:
        program, command = m.group(1), m.group(2)
        if program not in PARSERS:
            log.warning("%s: cli-reference names an unknown program %r", page.file.src_uri, program)
            return m.group(0)
        try:
            return reference(program, command)
        except KeyError as e:
            log.warning("%s: %s", page.file.src_uri, e.args[0])
            return m.group(0)

    return MARKER.sub(replace, markdown)


def on_files(files, config, **kwargs):
    from mkdocs.structure.files import File

    for program, command in all_commands():
        if files.get_file_from_path(page_path(program, command)) is None:
            log.warning("no page for `%s %s`: add docs/%s", program, command, page_path(program, command))
    results = REPO / "tools" / "results"
    for png in sorted(results.glob("*.png")):
        uri = f"results/{png.name}"
        if files.get_file_from_path(uri) is None:
            files.append(File.generated(config, uri, abs_src_path=str(png)))
    return files
