"""``fleet calibrate``'s task: one machine's parameters from its own runs, with their uncertainty.

The project's offline calibration (:func:`thermal_edge.estimation.calibrate.calibrate`: global
search, then SQP with the analytic gradient; Fisher-information uncertainty) on the machine's
runs. The machines of a fleet share one design, so the fit starts at the design's values and
the fleet's defaults keep the global search short and the optimiser's steps coarse: a
manufacturing spread of a few per cent is a local problem, and 30 s steps hold the minutes-long
thermal dynamics (the inputs averaged over each step, currents as RMS).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..estimation.calibrate import calibrate
from .results import row
from .runs import Machine
from .task import cached_model, read_machine_runs, run_machine

#: samples per optimiser step (1 Hz runs: 30 s steps)
DECIMATE = 30
#: differential-evolution generations and population multiplier
GENERATIONS = 1
POPSIZE = 1


def calibrate_machine(
    machine: Machine, model_path: str, data_dir: str | None = None, fmt: str = "csv", id_column: str | None = None,
    params: Sequence[str] | None = None, sensors: Sequence[str] | None = None, decimation: int = DECIMATE,
    generations: int = GENERATIONS, popsize: int = POPSIZE, seed: int = 0, can_config: str | None = None,
) -> list[dict[str, Any]]:
    """Calibrate one machine: a ``parameter`` row per fitted parameter (or one ``error`` row).

    Parameters
    ----------
    machine : Machine
        The machine and its run files (read on the worker).
    model_path, data_dir : str
        The design's model file and its tables' directory (paths the worker can read).
    params, sensors : sequence of str, optional
        Parameters to fit (default: the model's adaptable ones) and sensors to fit to (default:
        all in the runs).
    decimation, generations, popsize, seed : int
        As :func:`thermal_edge.estimation.calibrate.calibrate`.
    can_config : str, optional
        The service configuration that decodes the machine's CAN logs (default: the shipped one).
    """

    def job() -> list[dict[str, Any]]:
        model = cached_model(model_path, data_dir)
        runs = read_machine_runs(machine, fmt, id_column, can_config)
        res = calibrate(model, runs, params, sensors, decimation, generations, popsize, seed)
        unc = res.uncertainty
        common = dict(machine=machine.id, kind="parameter", residual_k=float(np.sqrt(unc.sigma2)),
                      objective=res.objective_final, samples=sum(len(r) for r in runs), runs=";".join(machine.runs))
        return [row(name=n, value=float(res.values[i]), nominal=float(res.start[i]), rel_std=float(unc.rel_std[i]),
                    identifiable=bool(unc.identifiable[i]), **common) for i, n in enumerate(res.names)]

    return run_machine(job, machine)
