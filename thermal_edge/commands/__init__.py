"""Sub-commands of ``thermal-edge``: one module per command, each with ``register(subparsers)``.

The commands are listed here by name and one-line help, and a command's module is imported only
when it is the one chosen (as cantools does): ``thermal-edge --help`` and ``thermal-edge run
--help`` load none of the modules that other commands need (discovery, the benchmarks, the
simulator, scipy.optimize).
"""
from __future__ import annotations

import argparse
import importlib
from dataclasses import dataclass
from types import ModuleType

from ..log_rate import stream_is_journal, warnings_to_stderr

__all__ = ["COMMANDS", "Command", "add_commands", "resolve_named_files", "stream_is_journal",
           "warnings_to_stderr"]


@dataclass(frozen=True)
class Command:
    """A sub-command: its name, the one line ``thermal-edge --help`` lists, and its module."""

    name: str
    help: str
    module: str  # in this package

    def load(self) -> ModuleType:
        return importlib.import_module(f"{__name__}.{self.module}")


COMMANDS = (
    Command("run", "run the edge service", "run"),
    Command("demo", "the service against the simulated machine (virtual bus, live metrics)", "demo"),
    Command("monitor", "live view of a running service (metrics or bus)", "monitor"),
    Command("simulate", "simulate the machine over a drive cycle", "simulate"),
    Command("replay", "replay a recorded run through the model", "replay"),
    Command("export", "a CAN log as run CSVs (one sample per tick, as the service saw it)", "export"),
    Command("calibrate", "offline fit of the model to recorded runs", "calibrate"),
    Command("flux", "commission the magnet-temperature estimate from the inverter's voltages", "flux"),
    Command("discover", "find, name and add the physical effect a model lacks", "discover"),
    Command("bench", "run a benchmark", "bench"),
    Command("fleet", "calibrate, evaluate and screen many machines' runs on Dask", "fleet"),
    Command("config", "print the example service configuration (edge.yaml) to start from", "config"),
)


def add_commands(parser: argparse.ArgumentParser, chosen: str | None) -> None:
    """Add every command to ``parser``: the ``chosen`` one with all its arguments (its module
    imported), the others by name and help only."""
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        if command.name == chosen:
            command.load().register(sub)  # (its parser's help line is never shown: it is chosen)
        else:  # listed; its arguments are known once it is chosen
            sub.add_parser(command.name, help=command.help, add_help=False)


def resolve_named_files(args: argparse.Namespace) -> None:
    """``--model`` and ``--cycle`` of whichever command takes them: a file as given, else the path of
    the packaged model or drive cycle of that name (``pm10kw``, ``varied_drive``).

    Raises
    ------
    UsageError
        Neither a file nor a packaged name; the message lists the packaged names.
    """
    from ..shipped import cycle_file, model_file

    for dest, resolve in (("model", model_file), ("cycle", cycle_file)):
        value = getattr(args, dest, None)
        if isinstance(value, str):
            setattr(args, dest, resolve(value))
