"""Open-loop prediction of a recorded run and its per-sensor scores.

The prediction starts from the measured initial state (:func:`thermal_edge.lptn.initial_state`)
and runs the model open-loop on the run's inputs; scores compare it with every sensor column the
run has (NaN samples skipped).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..data import Run, RunError
from ..lptn import Model, Simulator, Trajectory, initial_state


def model_inputs(model: Model, run: Run) -> dict[str, np.ndarray]:
    """The run's columns that the model takes as inputs; :class:`RunError` names a missing one."""
    missing = [c for c in model.inputs if c not in run.columns]
    if missing:
        raise RunError(f"{run.source}: model {model.name} needs input column(s) {', '.join(missing)}")
    return {c: run.columns[c] for c in model.inputs}


def sensor_columns(model: Model, run: Run, sensors: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """Measured sensor series present in both model and run (optionally only ``sensors``)."""
    names = [s for s in model.sensors if s in run.columns] if sensors is None else list(sensors)
    unknown = [s for s in names if s not in model.sensors]
    if unknown:
        raise RunError(f"model {model.name} has no sensor(s) {', '.join(unknown)} (has: {', '.join(model.sensors)})")
    absent = [s for s in names if s not in run.columns]
    if absent:
        raise RunError(f"{run.source}: no column for sensor(s) {', '.join(absent)}")
    return {s: run.columns[s] for s in names}


def start_reading(values: np.ndarray, t: np.ndarray, k: int = 0, span_s: float = 0.0) -> float:
    """A sensor's reading at sample ``k``: the sample itself, or with ``span_s`` (s) the value at
    ``t[k]`` of the straight line fitted to the readings of the ``span_s`` after it (at least three:
    else the sample). One reading's noise would otherwise start an open-loop prediction off by it
    and bias a fit for as long as the slowest mode remembers it; over half a minute a machine's
    temperatures are straight to well within a PT100's noise."""
    x = float(values[k])
    if span_s <= 0.0:
        return x
    sel = (t >= t[k]) & (t <= t[k] + span_s) & np.isfinite(values)
    if np.count_nonzero(sel) < 3:
        return x
    slope, at_k = np.polyfit(t[sel] - t[k], values[sel], 1)
    return float(at_k)


def _start(model: Model, run: Run, k: int, span_s: float) -> tuple[dict[str, float], dict[str, float]]:
    """The inputs at sample ``k`` and each sensor's reading there (:func:`start_reading`)."""
    inp = {c: float(v[k]) for c, v in model_inputs(model, run).items()}
    t = np.asarray(run.t, dtype=float)
    meas = {s: start_reading(np.asarray(v, dtype=float), t, k, span_s) for s, v in sensor_columns(model, run).items()}
    return inp, meas


def initial_from_run(model: Model, run: Run, theta: np.ndarray | None = None, k: int = 0,
                     span_s: float = 0.0) -> np.ndarray:
    """Node temperatures at sample ``k`` from the sensor readings there (:func:`start_reading`:
    with ``span_s``, the straight line through the ``span_s`` after it)."""
    return initial_state(model, *_start(model, run, k, span_s), theta)


def start_with_directions(model: Model, run: Run, theta: np.ndarray | None = None, k: int = 0,
                          span_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`initial_from_run`'s node temperatures (n,), °C, and how they move per kelvin of each
    sensor's start reading (those that are finite): (n, sensors read), K/K. The unmeasured nodes
    follow the measured ones (the initial state is linear in the readings), so these are the
    directions in which a start reading's noise moves the whole initial state."""
    inp, meas = _start(model, run, k, span_s)
    base = initial_state(model, inp, meas, theta)
    cols = [initial_state(model, inp, {**meas, s: v + 1.0}, theta) - base for s, v in meas.items() if np.isfinite(v)]
    return base, np.column_stack(cols) if cols else np.zeros((len(base), 0))


@dataclass
class Scores:
    """Per-sensor prediction errors: MSE (K²), RMS (K) and max abs error (K)."""

    mse: dict[str, float]
    rms: dict[str, float]
    max_abs: dict[str, float]

    @property
    def mean_mse(self) -> float:
        """Mean of the MSE over the sensors with a measured sample (NaN when none has one), K²."""
        measured = [v for v in self.mse.values() if np.isfinite(v)]
        return float(np.mean(measured)) if measured else float("nan")

    def as_dict(self) -> dict[str, object]:
        return {"mse": self.mse, "mean_mse": self.mean_mse, "rms": self.rms, "max_abs": self.max_abs}


def score(model: Model, traj: Trajectory, measured: dict[str, np.ndarray], start: int = 0) -> Scores:
    """Compare a trajectory with measured sensor series from sample ``start`` on."""
    mse, rms, mx = {}, {}, {}
    for s, y in measured.items():
        e = traj.node(model.sensors[s])[start:] - y[start:]
        e = e[np.isfinite(e)]
        mse[s] = float(np.mean(e**2)) if len(e) else float("nan")
        rms[s] = float(np.sqrt(mse[s]))
        mx[s] = float(np.max(np.abs(e))) if len(e) else float("nan")
    return Scores(mse, rms, mx)


def open_loop(
    model: Model, run: Run, theta: np.ndarray | None = None, method: str | None = None, max_substep: float | None = None
) -> tuple[Trajectory, Scores]:
    """Predict a run open-loop from its measured initial state and score every sensor it has."""
    theta = model.nominal() if theta is None else theta
    sim = Simulator(model, method, max_substep)
    traj = sim.simulate(theta, model_inputs(model, run), run.dt, initial_from_run(model, run, theta))
    return traj, score(model, traj, sensor_columns(model, run))
