"""Every option of every command and sub-command has a help text that states its default (issue 10)."""
import argparse
import importlib
import pkgutil

import pytest

import ev3dgs.cli


def _cli_modules():
    mods = []
    for info in pkgutil.iter_modules(ev3dgs.cli.__path__):
        mod = importlib.import_module(f"ev3dgs.cli.{info.name}")
        if callable(getattr(mod, "build_parser", None)):
            mods.append(mod)
    return mods


def _walk(parser: argparse.ArgumentParser, seen=None):
    """(parser, action) for every action of the parser and of every sub-parser, depth first."""
    seen = set() if seen is None else seen
    if id(parser) in seen:
        return
    seen.add(id(parser))
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _walk(sub, seen)
        else:
            yield parser, action


def _expanded_help(parser, action) -> str:
    return parser._get_formatter()._expand_help(action) if action.help else ""


def test_the_three_clis_are_walked():
    progs = {mod.build_parser().prog for mod in _cli_modules()}
    assert {"ev3dgs", "ev3dgs-sim", "ev3dgs-ingest"} <= progs


def _all_options():
    out = []
    for mod in _cli_modules():
        for parser, action in _walk(mod.build_parser()):
            if isinstance(action, argparse._HelpAction):
                continue
            name = "/".join(action.option_strings) or action.dest
            out.append((f"{parser.prog} {name}", parser, action))
    return out


OPTIONS = _all_options()


def test_there_are_many_options():
    assert len(OPTIONS) > 60


@pytest.mark.parametrize("label,parser,action", OPTIONS, ids=[o[0] for o in OPTIONS])
def test_option_has_help_with_default(label, parser, action):
    if action.help is argparse.SUPPRESS and any(a is not action and a.dest == action.dest and
                                                a.help is not argparse.SUPPRESS for a in parser._actions):
        return  # a hidden alias (an option's earlier name) of a documented option
    text = _expanded_help(parser, action)
    assert action.help is not argparse.SUPPRESS and text.strip(), f"{label}: no help text"
    default = action.default
    if default is None or default is False or default is argparse.SUPPRESS:
        return
    assert "default" in text.lower() and str(default) in text, \
        f"{label}: the help does not state the default {default!r}: {text!r}"


def test_events_option_explains_margin():
    from ev3dgs.cli.ingest import build_parser

    davis = build_parser()._subparsers._group_actions[0].choices["davis"]
    (action,) = [a for a in davis._actions if "--events" in a.option_strings]
    text = _expanded_help(davis, action)
    assert "margin" in text and "--event-margin-ms" in text and "default" in text


def test_help_renders_for_every_subcommand(capsys):
    for mod in _cli_modules():
        p = mod.build_parser()
        for parser in {id(pp): pp for pp, _ in _walk(p)}.values():
            with pytest.raises(SystemExit) as e:
                parser.parse_args(["--help"])
            assert e.value.code == 0
    assert "%(default)" not in capsys.readouterr().out
