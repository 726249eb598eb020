"""Arguments shared by several sub-commands."""
from __future__ import annotations

import argparse

from ..errors import UsageError
from ..lptn import Model, ModelError, ParameterError, load_model
from .options import positive_s


def add_model_args(p: argparse.ArgumentParser, required: bool = True, discretisation: bool = False) -> None:
    """``--model`` and ``--data-dir``; with ``discretisation`` also ``--method`` and ``--max-substep``
    (only for commands that pass them on)."""
    p.add_argument("--model", required=required, help="machine model: a file, or the name of a packaged one (pm10kw, paderborn4)")
    p.add_argument("--data-dir", help="directory of the model's table files (overrides the model's data_dir)")
    if discretisation:
        p.add_argument("--method", choices=("zoh", "euler"), help="discretisation (default: the model's)")
        p.add_argument("--max-substep", type=positive_s, help="Euler sub-step limit, s (default: the model's)")


def model_from_args(args: argparse.Namespace) -> Model:
    return load_model(args.model, data_dir=args.data_dir)


def add_set_arg(p: argparse.ArgumentParser, *aliases: str) -> None:
    """``--set NAME=VALUE`` (repeatable; ``aliases`` are other spellings of the same option):
    a parameter value, in its unit, as ``model.parameters`` in ``edge.yaml``."""
    p.add_argument("--set", *aliases, dest="set", action="append", default=[], metavar="NAME=VALUE",
                   help="parameter value within the model's bounds (repeatable), as model.parameters in edge.yaml")


def split_sets(items: list[str]) -> dict[str, float]:
    """``--set`` items as {name: value} (syntax only); :class:`ModelError` names a malformed item."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            v = float(value)
        except ValueError:
            v = None
        if not sep or not name.strip() or v is None:
            raise ModelError(f"--set {item!r}: expected NAME=VALUE with a number")
        out[name.strip()] = v
    return out


def check_sets(model: Model, values: dict[str, float]) -> dict[str, float]:
    """``values`` checked against the model (known name, finite, within its bounds); raises
    :class:`ModelError` with one line naming the offending ``--set``."""
    for name, v in values.items():
        try:
            model.check_parameters({name: v})
        except ParameterError as exc:
            raise ModelError(f"--set {name}={v:g}: {exc}") from None
    return values


def parse_sets(model: Model, items: list[str]) -> dict[str, float]:
    """``--set`` items as {name: value}, checked against the model."""
    return check_sets(model, split_sets(items))


def model_with_sets(model: Model, items: list[str]) -> Model:
    """The model with ``--set`` values as its nominal values (and the adapter's prior)."""
    sets = parse_sets(model, items)
    return model.with_parameters(sets) if sets else model


def check_param_names(model: Model, names: list[str] | None, option: str = "--params") -> list[str] | None:
    """``--params`` checked against the model: every name one of its parameters (a :class:`UsageError`
    naming the option, the unknown name and the closest known one otherwise)."""
    import difflib

    known = [p.name for p in model.parameters]
    for n in names or ():
        if n not in known:
            close = difflib.get_close_matches(n, known, n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else f" (has: {', '.join(known)})"
            raise UsageError(f"{option} {n!r}: model {model.name} has no such parameter{hint}")
    return names
