"""``fleet evaluate``'s task: a model replayed open-loop over every run of one machine, its errors
per sensor (the regression check before a new model version is rolled out).

The model is the given design, or with per-machine parameters (from ``fleet calibrate``) each
machine's own calibrated one. A machine with several runs is scored over all of them: the errors
of every run (each predicted from its own measured initial state) pooled per sensor.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..estimation.predict import open_loop, sensor_columns
from .results import row
from .runs import Machine
from .task import cached_model, read_machine_runs, run_machine


def evaluate_machine(
    machine: Machine, params: Mapping[str, float] | None, model_path: str, data_dir: str | None = None,
    fmt: str = "csv", id_column: str | None = None, can_config: str | None = None,
) -> list[dict[str, Any]]:
    """Replay the model over one machine's runs: a ``sensor`` row per sensor (or one ``error`` row).

    Parameters
    ----------
    params : mapping, optional
        Parameter values replacing the model's (the machine's calibration); ``None``: the model's.
    can_config : str, optional
        The service configuration that decodes the machine's CAN logs (default: the shipped one).
    """

    def job() -> list[dict[str, Any]]:
        model = cached_model(model_path, data_dir)
        theta = model.nominal().copy()
        if params:
            theta[model.parameter_index(list(params))] = list(params.values())
        runs = read_machine_runs(machine, fmt, id_column, can_config)
        sq: dict[str, float] = {}
        count: dict[str, int] = {}
        worst: dict[str, float] = {}
        for run in runs:
            _, scores = open_loop(model, run, theta=theta)
            for s, y in sensor_columns(model, run).items():
                n = int(np.count_nonzero(np.isfinite(y)))  # the samples the run's score is over
                if n:
                    sq[s] = sq.get(s, 0.0) + scores.mse[s] * n
                    count[s] = count.get(s, 0) + n
                    worst[s] = max(worst.get(s, 0.0), scores.max_abs[s])
        samples = sum(len(r) for r in runs)
        out = []
        for s in sq:
            mse = sq[s] / count[s]
            out.append(row(machine=machine.id, kind="sensor", name=s, value=float(np.sqrt(mse)), mse_k2=mse,
                           rms_k=float(np.sqrt(mse)), max_abs_k=worst[s], samples=samples, runs=";".join(machine.runs)))
        return out

    return run_machine(job, machine)
