"""Arguments shared by several sub-commands."""
from __future__ import annotations

import argparse

from ..lptn import Model, load_model


def add_model_args(p: argparse.ArgumentParser, required: bool = True, discretisation: bool = False) -> None:
    """``--model`` and ``--data-dir``; with ``discretisation`` also ``--method`` and ``--max-substep``
    (only for commands that pass them on)."""
    p.add_argument("--model", required=required, help="machine model file (config/machines/*.yaml)")
    p.add_argument("--data-dir", help="directory of the model's table files (overrides the model's data_dir)")
    if discretisation:
        p.add_argument("--method", choices=("zoh", "euler"), help="discretisation (default: the model's)")
        p.add_argument("--max-substep", type=float, help="Euler sub-step limit, s (default: the model's)")


def model_from_args(args: argparse.Namespace) -> Model:
    return load_model(args.model, data_dir=args.data_dir)
