"""Shared pieces of the estimators: parameter space in logs, estimation windows, decimation, results.

Parameters are optimised in ``φ = log θ`` within ``[log L, log U]`` so that a conductivity of
2 W/(m·K) and a resistance of 9 K/W are scaled alike; a sensitivity ``∂T/∂θ`` becomes
``∂T/∂φ = θ ∂T/∂θ``.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..lptn import Model, Role


@dataclass
class ParamSpace:
    """The parameters being estimated, as a subset of a model's parameter vector.

    Attributes
    ----------
    names : tuple of str
        Estimated parameters.
    theta0 : ndarray
        Full parameter vector the subset is inserted into (the other parameters stay fixed).
    prior : ndarray
        Offline (prior) values of the estimated parameters, for the MAP penalty.
    """

    model: Model
    names: tuple[str, ...]
    theta0: np.ndarray
    prior: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        self.index = self.model.parameter_index(self.names)
        lo, hi = self.model.bounds()
        self.lower, self.upper = lo[self.index], hi[self.index]
        if not len(self.prior):
            self.prior = self.model.nominal()[self.index]

    @property
    def size(self) -> int:
        return len(self.names)

    def values(self) -> np.ndarray:
        """Current values of the estimated parameters."""
        return self.theta0[self.index].copy()

    def full(self, sub: np.ndarray) -> np.ndarray:
        """The full parameter vector with the subset replaced."""
        th = self.theta0.copy()
        th[self.index] = sub
        return th

    def from_log(self, phi: np.ndarray) -> np.ndarray:
        return np.exp(phi)

    def log_bounds(self) -> list[tuple[float, float]]:
        return list(zip(np.log(self.lower), np.log(self.upper)))


@dataclass
class Window:
    """An estimation window: inputs, measurements and the state at its first sample.

    Attributes
    ----------
    inputs : dict
        Model input columns (N,).
    measured : dict
        Sensor name -> readings (N,), °C (NaN = missing).
    T0 : ndarray
        Node temperatures at the first sample, °C.
    dt : float
        Sample period, s.
    t : ndarray
        Sample times, s.
    rms : tuple of str
        Inputs that :func:`decimate` averages as RMS (the current: copper losses go with its square).
    """

    inputs: dict[str, np.ndarray]
    measured: dict[str, np.ndarray]
    T0: np.ndarray
    dt: float
    t: np.ndarray
    rms: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.t)


def rms_inputs(model: Model) -> tuple[str, ...]:
    """The inputs of ``model`` that a window averages as RMS: its current (if it has one)."""
    current = model.find_input(Role.CURRENT)
    return () if current is None else (current,)


def decimate(window: Window, factor: int) -> Window:
    """Coarser window for the optimiser: ``factor`` samples per step.

    Over each new step the inputs are averaged (the window's :attr:`~Window.rms` inputs, the
    current, as RMS: the root of the mean square, so that copper losses are kept), measurements
    are taken at the step boundaries. With inputs that
    are constant over each new step the ZOH model on the coarse grid is exact.
    """
    if factor <= 1:
        return window
    N = len(window)
    m = (N - 1) // factor
    idx = np.arange(m + 1) * factor
    out = {}
    for k, v in window.inputs.items():
        seg = v[: m * factor].reshape(m, factor)
        mean = np.sqrt(np.mean(seg**2, axis=1)) if k in window.rms else seg.mean(axis=1)
        out[k] = np.append(mean, v[m * factor])
    meas = {s: y[idx] for s, y in window.measured.items()}
    return Window(out, meas, window.T0, window.dt * factor, window.t[idx], window.rms)


@dataclass
class FitResult:
    """Outcome of one estimation run (any method)."""

    method: str
    names: tuple[str, ...]
    values: np.ndarray
    objective_before: float
    objective_after: float
    iterations: int
    evaluations: int
    wall_s: float
    message: str = ""

    def as_dict(self) -> dict[str, object]:
        return {
            "method": self.method,
            "params": dict(zip(self.names, map(float, self.values))),
            "objective_before": self.objective_before,
            "objective_after": self.objective_after,
            "iterations": self.iterations,
            "evaluations": self.evaluations,
            "wall_s": self.wall_s,
            "message": self.message,
        }


def window_from_arrays(
    model: Model, inputs: Mapping[str, np.ndarray], measured: Mapping[str, np.ndarray], T0: np.ndarray, dt: float,
    t: np.ndarray | None = None,
) -> Window:
    """A :class:`Window` from plain arrays (inputs restricted to the model's)."""
    n = len(next(iter(inputs.values())))
    return Window(
        {c: np.asarray(inputs[c], dtype=float) for c in model.inputs},
        {s: np.asarray(v, dtype=float) for s, v in measured.items()},
        np.asarray(T0, dtype=float),
        float(dt),
        np.arange(n) * dt if t is None else np.asarray(t, dtype=float),
        rms_inputs(model),
    )
