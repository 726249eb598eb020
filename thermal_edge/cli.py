"""The ``thermal-edge`` command: one module per sub-command in :mod:`thermal_edge.commands`,
imported only when chosen.

Bad input (a broken model, cycle, run or config file, a bad option) raises a
:class:`~thermal_edge.errors.ThermalEdgeError`: it exits with status 2 and one line naming the
file, key or option and the cause. Anything else is a bug and shows its traceback (exit 1);
``--debug`` shows the traceback of a user error too. ``--model`` and ``--cycle`` take a file or
the name of a model or drive cycle shipped with the package, on every command.
"""
from __future__ import annotations

import os

# The matrices here are small (tens of nodes): BLAS threads only contend with each other and with
# the service's own threads. Set before numpy is imported; an explicit setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import typing  # noqa: E402

from . import __version__  # noqa: E402
from .commands import COMMANDS, add_commands, resolve_named_files, stream_is_journal, warnings_to_stderr  # noqa: E402
from .errors import ThermalEdgeError  # noqa: E402


def chosen_command(argv: list[str]) -> str | None:
    """The sub-command named on the command line (the first argument that is not an option: the
    top level has no option that takes a value), or None."""
    names = {c.name for c in COMMANDS}
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in names else None


class OneLineParser(argparse.ArgumentParser):
    """argparse's parser with its errors in one line, as every other user error: ``thermal-edge
    replay: error: argument --threshold: ...`` and exit status 2 (``--help`` shows the usage).
    Sub-command parsers are made of the same class."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, error_line(f"{self.prog}: error: {message}") + "\n")


def error_line(text: str) -> str:
    """``text``, the one line of a user error, with the journal's priority prefix ``<3>`` (err)
    when stderr is the journal (under systemd): the line that says why the unit stopped must
    show in ``journalctl -p warning`` as the service's own ERROR lines do."""
    return f"<3>{text}" if stream_is_journal(sys.stderr) else text


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser for ``argv`` (default ``sys.argv[1:]``): every command listed, the chosen one
    complete."""
    parser = OneLineParser(
        prog="thermal-edge",
        description="Online-adapted LPTN thermal protection for PM machines: CAN in, derating out.",
    )
    parser.add_argument("--version", action="version", version=f"thermal-edge {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an error caused by the input too")
    add_commands(parser, chosen_command(sys.argv[1:] if argv is None else argv))
    return parser


def innermost_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The parser of the (sub-)sub-command ``args`` chose, e.g. ``thermal-edge flux calibrate``'s."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and action.dest and action.choices:
            chosen = getattr(args, action.dest, None)
            if chosen in action.choices:
                return innermost_parser(action.choices[chosen], args)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(argv)
    args, unknown = parser.parse_known_args(argv)
    if "--debug" in unknown:  # given after the command (``thermal-edge replay ... --debug``): the same option
        unknown = [u for u in unknown if u != "--debug"]
        args.debug = True
    if unknown:  # named by the command that does not know them, as its other option errors are
        innermost_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown)}")
    warnings_to_stderr()
    try:
        resolve_named_files(args)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into head & co.
        sys.stderr.close()
        return 0
    except ThermalEdgeError as exc:
        if args.debug:
            raise
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        # named by the (sub-)sub-command, as its option errors are: `thermal-edge flux calibrate: error:`
        print(error_line(f"{innermost_parser(parser, args).prog}: error: {msg}"), file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
