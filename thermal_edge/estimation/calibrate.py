"""Offline calibration (the paper's §3): global search, then SQP from the best point found.

scipy's ``differential_evolution`` stands in for the paper's genetic algorithm over the log-
parameters within their bounds (objective values only), then SLSQP with the analytic gradient
polishes the result. Several runs are fitted together: the objective is the sum of each run's
weighted prediction error, every run starting from its own measured initial state.
"""
from __future__ import annotations

import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import OptimizeResult, differential_evolution, minimize

from ..data import Run, RunError
from ..lptn import Model, ModelError, Simulator
from .common import ParamSpace, decimate, window_from_arrays
from .objective import Objective
from .predict import model_inputs, sensor_columns, start_with_directions
from .uncertainty import MIN_RESIDUAL_DOF, Uncertainty, estimate_uncertainty

#: Differential evolution's own convergence test: the population's spread of objective values
#: below this share of their mean (scipy's ``tol``; its default).
TOL = 0.01
#: Generations the best objective may go without improving by :data:`MIN_IMPROVEMENT` before the
#: global search stops (a run that starts near its optimum stays there from the first generation).
PATIENCE = 3
#: Relative improvement of the best objective that counts as progress.
MIN_IMPROVEMENT = 1e-4


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
    generations: int = 0  #: differential-evolution generations run
    stopped: str = ""  #: why the global search stopped


class _Sum:
    """Sum of per-run objectives over the same parameter space."""

    def __init__(self, objectives: list[Objective]) -> None:
        self.objs = objectives

    def value(self, phi: np.ndarray, keep: bool = False) -> float:
        """The summed objective; ``keep``: each run's simulation kept for the gradient at ``phi``
        (:meth:`~.objective.Objective.evaluate`), which the SQP asks for at the points it accepts."""
        return float(sum(o.evaluate(phi, derivatives=False, keep=keep).value for o in self.objs))

    def grad(self, phi: np.ndarray) -> np.ndarray:
        return np.sum([o.evaluate(phi).grad for o in self.objs], axis=0)


#: s: a fit starts each run from the line through its first half minute of readings, not from one
#: noisy sample (:func:`~.predict.start_reading`)
START_SPAN_S = 30.0


def calibrate(
    model: Model, runs: Sequence[Run], names: Sequence[str] | None = None, sensors: Sequence[str] | None = None,
    decimation: int = 1, maxiter: int = 30, popsize: int = 10, seed: int = 0, sqp_iter: int = 30,
    progress: Callable[[int, int, float], None] | None = None, patience: int = PATIENCE,
    max_time_s: float | None = None,
) -> CalibrationResult:
    """Fit ``names`` (default: the adaptable parameters) to the runs.

    The global search stops at ``maxiter`` generations, when its population has converged
    (:data:`TOL`), when the best objective has not improved by :data:`MIN_IMPROVEMENT` (relative)
    for ``patience`` generations, or after ``max_time_s``; the SQP polish then runs within what
    is left of ``max_time_s``.

    Parameters
    ----------
    decimation : int
        Samples per optimiser step (inputs averaged, currents as RMS).
    maxiter, popsize, seed : int
        Differential-evolution generations (at most), population multiplier and seed.
    sqp_iter : int
        SQP iterations of the polish.
    progress : callable, optional
        ``progress(generation, maxiter, best objective)`` after every generation.
    patience : int
        Generations without progress before the global search stops.
    max_time_s : float, optional
        Wall-time budget of the whole fit, s.

    Raises
    ------
    ModelError
        The objective at the starting parameters is not finite (a law of the model overflows).
    RunError
        The runs hold fewer than the parameters plus :data:`~.uncertainty.MIN_RESIDUAL_DOF`
        readings: nothing could be told about the parameters.
    """
    t0 = time.perf_counter()
    names = tuple(names or model.adaptable)
    sim = Simulator(model)
    space = ParamSpace(model, names, model.nominal())
    objs = []
    for run in runs:
        meas = sensor_columns(model, run, sensors)
        T0, free = start_with_directions(model, run, span_s=START_SPAN_S)
        win = window_from_arrays(model, model_inputs(model, run), meas, T0, run.dt, run.t)
        objs.append(Objective(sim, space, decimate(win, decimation), list(meas), "uniform", start_free=free))
    n_obs = sum(int(np.count_nonzero(np.isfinite(y))) for o in objs for y in o.window.measured.values())
    fitted = len(names) + sum(o.nuisance for o in objs)  # with each run's start offsets
    if n_obs - fitted < MIN_RESIDUAL_DOF:
        raise RunError(f"{', '.join(r.source for r in runs)}: too short to calibrate: {n_obs} readings (samples x "
                       f"sensors, {decimation} sample(s) per step) for {len(names)} parameters and "
                       f"{fitted - len(names)} start offsets; at least {fitted + MIN_RESIDUAL_DOF} needed (with fewer "
                       "the fit matches them whatever the parameters)")
    total = _Sum(objs)
    phi0 = np.log(space.values())
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        f0 = total.value(phi0)
    if not np.isfinite(f0):
        raise ModelError(f"{model.path}: the prediction error at the starting parameters is {f0}: a loss or "
                         "conductance law of the model overflows on these runs (replay shows where)")
    best = [f0]  # the best objective when progress was last made
    gen, idle, why = [0], [0], ["generations exhausted"]

    def timed_out() -> bool:
        return max_time_s is not None and time.perf_counter() - t0 >= max_time_s

    def cb(intermediate_result: OptimizeResult) -> bool:  # scipy passes it by this name
        gen[0] += 1
        fun = float(intermediate_result.fun)
        if progress:
            progress(gen[0], maxiter, fun)
        if fun < best[0] * (1.0 - MIN_IMPROVEMENT):
            best[0], idle[0] = fun, 0
        else:
            idle[0] += 1
        if idle[0] >= patience:
            why[0] = f"no improvement above {MIN_IMPROVEMENT:g} (relative) in {patience} generations"
            return True
        if timed_out():
            why[0] = f"--max-time {max_time_s:g} s reached"
            return True
        return False

    de = differential_evolution(total.value, space.log_bounds(), maxiter=maxiter, popsize=popsize, seed=seed,
                                polish=False, x0=phi0, callback=cb, tol=TOL)
    if de.success and gen[0] < maxiter and "callback" not in str(de.message).lower():
        why[0] = f"population converged (spread below {TOL:g} of the mean)"

    def sqp_cb(intermediate_result: OptimizeResult) -> None:
        if timed_out():
            raise StopIteration

    res = minimize(lambda phi: total.value(phi, keep=True), de.x, jac=total.grad, method="SLSQP", bounds=space.log_bounds(),
                   options={"maxiter": sqp_iter, "ftol": 1e-14}, callback=sqp_cb)
    phi = res.x if total.value(res.x) <= de.fun else de.x
    values = np.exp(phi)
    final_space = ParamSpace(model, names, space.full(values))
    o = Objective(sim, final_space, objs[0].window, objs[0].sensors, "uniform", start_free=objs[0].start_free)
    unc = estimate_uncertainty(o, o.evaluate(phi))
    return CalibrationResult(names, space.values(), values, f0, float(de.fun), total.value(phi),
                             int(de.nfev) + int(res.nfev), time.perf_counter() - t0, unc, gen[0], why[0])


_VALUE = re.compile(r"^(?P<head>\s+(?P<name>[A-Za-z_][A-Za-z0-9_]*):\s*\{\s*value:\s*)(?P<value>[^,}]+)(?P<tail>.*)$")


def write_calibrated(model_path: str | Path, values: dict[str, float], out_path: str | Path, note: str = "") -> None:
    """Copy a model file with new nominal parameter values, keeping its comments and layout.

    Only ``name: {value: …, …}`` lines under ``parameters:`` are rewritten.

    Raises
    ------
    KeyError
        If a parameter's line is not in that form (the file is then left unwritten).
    """
    lines = Path(model_path).read_text(encoding="utf-8").splitlines()
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
    Path(out_path).write_text("\n".join(header + out) + "\n", encoding="utf-8")
