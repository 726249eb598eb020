"""The command-line reference, from the parser itself (:func:`thermal_edge.cli.build_parser`):
every command and sub-command with its ``--help`` text."""
from __future__ import annotations

import argparse
import os


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:  # argparse keeps its sub-commands only here
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _sections(prog: list[str], parser: argparse.ArgumentParser, level: int) -> list[str]:
    out = [f"{'#' * level} `{' '.join(prog)}`", "", "```text", parser.format_help().rstrip("\n"), "```", ""]
    for name, sub in _subparsers(parser).items():
        out += _sections([*prog, name], sub, level + 1)
    return out


def render_cli() -> str:
    """Every command's ``--help``, the sub-commands' under their command, at 100 columns."""
    from thermal_edge.cli import build_parser
    from thermal_edge.commands import COMMANDS

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps at $COLUMNS: the same page on every terminal
    try:
        top = build_parser([])
        out = ["```text", top.format_help().rstrip("\n"), "```", ""]
        for command in COMMANDS:
            parser = _subparsers(build_parser([command.name]))[command.name]
            out += _sections(["thermal-edge", command.name], parser, 2)
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old
    return "\n".join(out).rstrip("\n") + "\n"
