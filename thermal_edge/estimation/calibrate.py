"""Offline calibration (the paper's §3): global search, then SQP from the best point found.

scipy's ``differential_evolution`` stands in for the paper's genetic algorithm over the log-
parameters within their bounds (objective values only), then SLSQP with the analytic gradient
polishes the result. Several runs are fitted together: the objective is the sum of each run's
weighted prediction error, every run starting from its own measured initial state.
"""
from __future__ import annotations

import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import differential_evolution, minimize

from ..data import Run
from ..lptn import Model, Simulator
from .common import ParamSpace, decimate, window_from_arrays
from .objective import Objective
from .predict import initial_from_run, model_inputs, sensor_columns
from .uncertainty import Uncertainty, estimate_uncertainty


@dataclass
class CalibrationResult:
    names: tuple[str, ...]
    start: np.ndarray
    values: np.ndarray
    objective_start: float
    objective_global: float
    objective_final: float
    evaluations: int
    wall_s: float
    uncertainty: Uncertainty


class _Sum:
    """Sum of per-run objectives over the same parameter space."""

    def __init__(self, objectives: list[Objective]) -> None:
        self.objs = objectives

    def value(self, phi: np.ndarray) -> float:
        return float(sum(o.value(phi) for o in self.objs))

    def grad(self, phi: np.ndarray) -> np.ndarray:
        return np.sum([o.evaluate(phi).grad for o in self.objs], axis=0)


def progress_bar(stream=sys.stderr) -> Callable[[int, int, float], None]:  # type: ignore[no-untyped-def]
    """A one-line text progress bar: ``bar(done, total, best)``."""

    def bar(done: int, total: int, best: float) -> None:
        width = 30
        k = int(width * min(done, total) / max(total, 1))
        stream.write(f"\r[{'#' * k}{'.' * (width - k)}] {done}/{total} generations, best objective {best:.4g}")
        if done >= total:
            stream.write("\n")
        stream.flush()

    return bar


def calibrate(
    model: Model, runs: Sequence[Run], names: Sequence[str] | None = None, sensors: Sequence[str] | None = None,
    decimation: int = 1, maxiter: int = 30, popsize: int = 10, seed: int = 0, sqp_iter: int = 30,
    progress: Callable[[int, int, float], None] | None = None,
) -> CalibrationResult:
    """Fit ``names`` (default: the adaptable parameters) to the runs.

    Parameters
    ----------
    decimation : int
        Samples per optimiser step (inputs averaged, currents as RMS).
    maxiter, popsize, seed : int
        Differential-evolution generations, population multiplier and seed.
    sqp_iter : int
        SQP iterations of the polish.
    """
    t0 = time.perf_counter()
    names = tuple(names or model.adaptable)
    sim = Simulator(model)
    space = ParamSpace(model, names, model.nominal())
    objs = []
    for run in runs:
        meas = sensor_columns(model, run, sensors)
        win = window_from_arrays(model, model_inputs(model, run), meas, initial_from_run(model, run), run.dt, run.t)
        objs.append(Objective(sim, space, decimate(win, decimation), list(meas), "uniform"))
    total = _Sum(objs)
    phi0 = np.log(space.values())
    f0 = total.value(phi0)
    gen = [0]

    def cb(xk: np.ndarray, convergence: float = 0.0) -> None:
        gen[0] += 1
        if progress:
            progress(gen[0], maxiter, total.value(xk))

    de = differential_evolution(total.value, space.log_bounds(), maxiter=maxiter, popsize=popsize, seed=seed,
                                polish=False, x0=phi0, callback=cb, tol=1e-8)
    if progress and gen[0] < maxiter:
        progress(maxiter, maxiter, float(de.fun))
    res = minimize(total.value, de.x, jac=total.grad, method="SLSQP", bounds=space.log_bounds(),
                   options={"maxiter": sqp_iter, "ftol": 1e-14})
    phi = res.x if total.value(res.x) <= de.fun else de.x
    values = np.exp(phi)
    final_space = ParamSpace(model, names, space.full(values))
    o = Objective(sim, final_space, objs[0].window, objs[0].sensors, "uniform")
    unc = estimate_uncertainty(o, o.evaluate(phi))
    return CalibrationResult(names, space.values(), values, f0, float(de.fun), total.value(phi),
                             int(de.nfev) + int(res.nfev), time.perf_counter() - t0, unc)


_VALUE = re.compile(r"^(?P<head>\s+(?P<name>[A-Za-z_][A-Za-z0-9_]*):\s*\{\s*value:\s*)(?P<value>[^,}]+)(?P<tail>.*)$")


def write_calibrated(model_path: str | Path, values: dict[str, float], out_path: str | Path, note: str = "") -> None:
    """Copy a model file with new nominal parameter values, keeping its comments and layout.

    Only ``name: {value: …, …}`` lines under ``parameters:`` are rewritten.

    Raises
    ------
    KeyError
        If a parameter's line is not in that form (the file is then left unwritten).
    """
    lines = Path(model_path).read_text().splitlines()
    out, in_params, done = [], False, set()
    for line in lines:
        if re.match(r"^\S", line):
            in_params = line.startswith("parameters:")
        dd = re.match(r"^data_dir:\s*(\S+)(.*)$", line)
        if dd and not Path(dd.group(1)).is_absolute():  # keep the tables reachable from the new place
            target = (Path(model_path).resolve().parent / dd.group(1)).resolve()
            line = f"data_dir: {os.path.relpath(target, Path(out_path).resolve().parent)}{dd.group(2)}"
        m = _VALUE.match(line) if in_params else None
        if m and m.group("name") in values:
            line = f"{m.group('head')}{values[m.group('name')]:.6g}{m.group('tail')}"
            done.add(m.group("name"))
        out.append(line)
    missing = set(values) - done
    if missing:
        raise KeyError(f"{model_path}: parameters.{sorted(missing)[0]}: not written as 'name: {{value: ..., ...}}'")
    header = [f"# calibrated by thermal-edge calibrate from {Path(model_path).name}" + (f": {note}" if note else "")]
    Path(out_path).write_text("\n".join(header + out) + "\n")
