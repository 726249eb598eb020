"""``thermal-edge bench`` runs the benchmarks that work from an installed package, and each returns
a typed result; the benchmarks that need a checkout live in ``benchmarks/`` (``make bench-*``)."""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import typing

from thermal_edge.commands import bench as bench_command

BENCHES = ("jacobian", "paper", "service", "protection", "real", "adaptation", "fleet", "magnet", "ladder")


def _subcommands() -> set[str]:
    sub = argparse.ArgumentParser().add_subparsers()
    bench_command.register(sub)
    which = next(a for a in sub.choices["bench"]._actions if isinstance(a, argparse._SubParsersAction))
    return set(which.choices)


def test_the_bench_command_offers_the_installed_benches_only() -> None:
    assert _subcommands() == set(BENCHES)


def test_every_bench_returns_a_dataclass() -> None:
    for name in BENCHES:
        run = importlib.import_module(f"thermal_edge.bench.{name}").run
        result = typing.get_type_hints(run)["return"]
        assert dataclasses.is_dataclass(result), (name, result)
