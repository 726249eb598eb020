"""``thermal-edge config example``: the example service configuration that ships with the package
(every key, commented, for ``socketcan`` on ``can0``), printed for a user to start from::

    thermal-edge config example > /etc/thermal-edge/edge.yaml
    thermal-edge run --check --config /etc/thermal-edge/edge.yaml

Its model is named (``pm10kw``), so the copy works wherever it is written. ``--model`` writes
another model instead, e.g. a copy of the model beside the configuration that the user edits
(``--model machines/pm10kw.yaml``, relative to the configuration file's directory).
"""
from __future__ import annotations

import argparse
import re
import sys

from ..errors import UsageError
from ..shipped import example_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    which = p.add_subparsers(dest="config", required=True, metavar="WHAT")
    ex = which.add_parser("example", help="print the example edge.yaml (every key, commented)")
    ex.add_argument("--model", dest="model_path", metavar="PATH", default=None,
                    help="the model the printed configuration names (a file relative to the configuration's "
                         "directory, or a packaged model's name); default: the packaged pm10kw")
    ex.set_defaults(func=run_example)


#: the example's ``model.path`` line: its value is what ``--model`` replaces
_MODEL_PATH = re.compile(r"^(model:\n  path: )(\S+)", re.M)


def with_model(text: str, model: str) -> str:
    """The example configuration ``text`` with its ``model.path`` set to ``model``."""
    if any(c.isspace() for c in model) or model[:1] in "{[&*!|>'\"%@`#":
        raise UsageError(f"--model {model!r}: write a plain path without spaces or YAML punctuation")
    new, n = _MODEL_PATH.subn(lambda m: m.group(1) + model, text, count=1)
    if n != 1:  # the packaged example is tested to have the line; this guards a hand-edited copy
        raise RuntimeError("the example configuration has no 'model:' / 'path:' line")
    return new


def run_example(args: argparse.Namespace) -> int:
    text = example_config()
    if args.model_path is not None:  # not ``model``: that name is resolved to a file for every command
        text = with_model(text, args.model_path)
    sys.stdout.write(text)
    return 0
