"""The ``thermal-edge`` command: one module per sub-command in :mod:`thermal_edge.commands`.

Bad input (a broken model, cycle, run or config file) exits with status 2 and one line naming
the file and key; it never prints a traceback.
"""
from __future__ import annotations

import argparse
import sys

from . import __version__
from .commands import COMMANDS, USER_ERRORS


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="thermal-edge",
        description="Online-adapted LPTN thermal protection for PM machines: CAN in, derating out.",
    )
    parser.add_argument("--version", action="version", version=f"thermal-edge {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMANDS:
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except USER_ERRORS as exc:
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"thermal-edge {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
