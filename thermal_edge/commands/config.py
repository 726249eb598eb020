"""``thermal-edge config example``: the example service configuration that ships with the package
(every key, commented, for ``socketcan`` on ``can0``), printed for a user to start from::

    thermal-edge config example > /etc/thermal-edge/edge.yaml
    thermal-edge run --check --config /etc/thermal-edge/edge.yaml

``thermal-edge config dbc`` prints the CAN matrix the package ships (the frames the service reads
and sends), for ``cantools`` and ``candump`` on a machine without a checkout::

    thermal-edge config dbc > thermal_edge.dbc
    candump -L can0 | python -m cantools decode thermal_edge.dbc

``thermal-edge config model NAME`` prints a packaged machine model, for a copy the user edits;
``thermal-edge config unit`` prints the systemd unit the package ships::

    thermal-edge config model pm10kw > /etc/thermal-edge/machines/pm10kw.yaml
    thermal-edge config unit > /etc/systemd/system/thermal-edge.service

``thermal-edge config deploy DIR`` writes the deployment files the package ships into ``DIR``: the
systemd unit, ``vcan.service`` and ``80-can0.network`` (``systemd/``), the Prometheus scrape
configuration, alert rules and their unit tests (``prometheus/``), the Grafana dashboard and its
provisioning (``grafana/``)::

    thermal-edge config deploy /tmp/thermal-edge-deploy

``thermal-edge config readme`` prints the README the package was built with (from its installed
metadata: a wheel carries no checkout), for the file the unit's ``Documentation=`` names::

    sudo install -d /opt/thermal-edge/share/thermal-edge
    thermal-edge config readme | sudo tee /opt/thermal-edge/share/thermal-edge/README.md >/dev/null

``thermal-edge config inverter-example DIR`` writes the worked example of an inverter with a CAN
matrix of its own (the Acme MC-7: its ``edge.yaml`` and ``acme-mc7.dbc``) into ``DIR``.

Its model is named (``pm10kw``), so the copy works wherever it is written. ``--model`` writes
another model instead, e.g. a copy of the model beside the configuration that the user edits
(``--model machines/pm10kw.yaml``, relative to the configuration file's directory).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

from ..errors import UsageError
from ..shipped import MACHINES, config_path, example_config, model_file, names

#: the files of the worked example of a foreign inverter (``resources/examples/acme-mc7``)
INVERTER_EXAMPLE = ("examples", "acme-mc7", ("edge.yaml", "acme-mc7.dbc"))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    which = p.add_subparsers(dest="config", required=True, metavar="WHAT")
    ex = which.add_parser("example", help="print the example edge.yaml (every key, commented)")
    ex.add_argument("--model", dest="model_path", metavar="PATH", default=None,
                    help="the model the printed configuration names (a file relative to the configuration's "
                         "directory, or a packaged model's name); default: the packaged pm10kw. The example's "
                         "signals, sensors and flux nodes are pm10kw's: only pm10kw (or a copy of it) maps onto "
                         "them; another model (paderborn4 too) needs its own signals: section")
    ex.set_defaults(func=run_example)
    dbc = which.add_parser("dbc", help="print the CAN matrix the package ships (thermal_edge.dbc)")
    dbc.set_defaults(func=run_dbc)
    mdl = which.add_parser("model", help="print a packaged machine model (for a copy to edit)")
    mdl.add_argument("name", metavar="NAME", help=f"a packaged model: {', '.join(names(MACHINES))}")
    mdl.set_defaults(func=run_model)
    readme = which.add_parser("readme", help="print the README the package was built with (the unit's Documentation=)")
    readme.set_defaults(func=run_readme)
    unit = which.add_parser("unit", help="print the systemd unit (thermal-edge.service)")
    unit.set_defaults(func=run_unit)
    dep = which.add_parser("deploy", help="write the deployment files (systemd, Prometheus, Grafana) into DIR")
    dep.add_argument("dir", metavar="DIR", help="a directory (made if missing); files there of the same names are "
                                                "not overwritten")
    dep.set_defaults(func=run_deploy)
    inv = which.add_parser("inverter-example", help="write the Acme MC-7 example (edge.yaml, acme-mc7.dbc) into DIR")
    inv.add_argument("dir", metavar="DIR", help="a directory (made if missing); files there of the same names are "
                                                "not overwritten")
    inv.set_defaults(func=run_inverter_example)


#: the example's ``model.path`` line: its value is what ``--model`` replaces
_MODEL_PATH = re.compile(r"^(model:\n  path: )(\S+)", re.M)


def with_model(text: str, model: str) -> str:
    """The example configuration ``text`` with its ``model.path`` set to ``model``."""
    if not model or any(not c.isprintable() for c in model):
        raise UsageError(f"--model {model!r}: a path of printable characters")
    # a path YAML would not read as itself (spaces, a leading quote or bracket, ': ', ' #') goes in
    # double quotes: a JSON string is a YAML double-quoted scalar
    plain = not any(c.isspace() for c in model) and model[:1] not in "{[&*!|>'\"%@`#-?:,]}" and ": " not in model
    value = model if plain else json.dumps(model)
    new, n = _MODEL_PATH.subn(lambda m: m.group(1) + value, text, count=1)
    if n != 1:  # the packaged example is tested to have the line; this guards a hand-edited copy
        raise RuntimeError("the example configuration has no 'model:' / 'path:' line")
    return new


def run_example(args: argparse.Namespace) -> int:
    text = example_config()
    if args.model_path is not None:  # not ``model``: that name is resolved to a file for every command
        text = with_model(text, args.model_path)
    sys.stdout.write(text)
    return 0


def run_dbc(args: argparse.Namespace) -> int:
    from ..bus.frames import DEFAULT_DBC_PATH

    sys.stdout.write(Path(DEFAULT_DBC_PATH).read_text(encoding="utf-8"))
    return 0


def run_model(args: argparse.Namespace) -> int:
    if args.name.removesuffix(".yaml") not in names(MACHINES):
        raise UsageError(f"NAME {args.name}: not a packaged model (packaged: {', '.join(names(MACHINES))})")
    sys.stdout.write(Path(model_file(args.name, "NAME")).read_text(encoding="utf-8"))
    return 0


def run_readme(args: argparse.Namespace) -> int:
    from importlib.metadata import PackageNotFoundError, metadata

    try:
        text = metadata("thermal_edge").get_payload()  # type: ignore[attr-defined]  # the long description
    except PackageNotFoundError:
        text = None
    if not text:
        raise UsageError("readme: this installation of thermal_edge carries no README in its metadata "
                         "(run from a source tree without `pip install`?)")
    sys.stdout.write(str(text))
    return 0


def run_unit(args: argparse.Namespace) -> int:
    sys.stdout.write(config_path("deploy", "systemd", "thermal-edge.service").read_text(encoding="utf-8"))
    return 0


def deploy_files() -> list[tuple[str, ...]]:
    """The packaged deployment files, each as its path parts under ``deploy/`` (sorted)."""
    from importlib import resources

    out: list[tuple[str, ...]] = []

    def walk(node: Any, parts: tuple[str, ...]) -> None:
        for child in node.iterdir():
            if child.is_dir():
                walk(child, (*parts, child.name))
            elif not child.name.startswith(".") and not child.name.endswith(".pyc"):
                out.append((*parts, child.name))

    walk(resources.files("thermal_edge.resources").joinpath("deploy"), ())
    return sorted(out)


def run_deploy(args: argparse.Namespace) -> int:
    out = Path(args.dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"DIR {out}: not a directory")
    files = deploy_files()
    taken = ["/".join(f) for f in files if (out.joinpath(*f)).exists()]
    if taken:
        raise UsageError(f"DIR {out}: {', '.join(taken)} already there (not overwritten)")
    try:
        for f in files:
            (out.joinpath(*f[:-1])).mkdir(parents=True, exist_ok=True)
            out.joinpath(*f).write_bytes(config_path("deploy", *f).read_bytes())
    except OSError as exc:
        raise UsageError(f"DIR {out}: {exc.strerror or exc}") from None
    print(f"wrote {len(files)} files into {out}: {', '.join('/'.join(f) for f in files)}", file=sys.stderr)
    return 0


def run_inverter_example(args: argparse.Namespace) -> int:
    folder, name, files = INVERTER_EXAMPLE
    out = Path(args.dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"DIR {out}: not a directory")
    taken = [f for f in files if (out / f).exists()]
    if taken:
        raise UsageError(f"DIR {out}: {', '.join(taken)} already there (not overwritten)")
    try:
        out.mkdir(parents=True, exist_ok=True)
        for f in files:
            text = config_path(folder, name, f).read_text(encoding="utf-8")
            if f == "edge.yaml":  # its model beside the package's files: by its packaged name, wherever written
                text = with_model(text, "pm10kw")
            (out / f).write_text(text, encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"DIR {out}: {exc.strerror or exc}") from None
    print(f"wrote {', '.join(str(out / f) for f in files)}; check with: thermal-edge run --check --config {out / 'edge.yaml'}",
          file=sys.stderr)
    return 0
