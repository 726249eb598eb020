"""``thermal-edge config example``: the example service configuration that ships with the package
(every key, commented, for ``socketcan`` on ``can0``), printed for a user to start from::

    thermal-edge config example > /etc/thermal-edge/edge.yaml
    thermal-edge run --check --config /etc/thermal-edge/edge.yaml

Its model is named (``pm10kw``), so the copy works wherever it is written.
"""
from __future__ import annotations

import argparse
import sys

from ..shipped import example_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    which = p.add_subparsers(dest="config", required=True, metavar="WHAT")
    ex = which.add_parser("example", help="print the example edge.yaml (every key, commented)")
    ex.set_defaults(func=run_example)


def run_example(args: argparse.Namespace) -> int:
    sys.stdout.write(example_config())
    return 0
