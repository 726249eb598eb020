"""A shadow observer: the Kalman filter run over the recorded samples with parameters other than
those in use, so that a challenger is judged from a state consistent with its own parameters.

The service's observer runs with the parameters in use. Its estimate of the nodes no sensor reads
settles where those parameters put them: a model that is not the machine compensates part of its
parameter error in the unmeasured states. Predicting from that state favours the parameters in use;
a challenger at the window's optimum predicted the next 30 min of the closed-loop demo from it at
0.28-0.34 K RMS against 0.11 K from its own state. A shadow observer with the challenger's
parameters gives the state the service's observer would have if they were in use, and the judge
scores both parameter sets each from the estimate of an observer run with them (the same filter,
the same start, the same readings).
"""
from __future__ import annotations

import bisect
from collections.abc import Mapping

import numpy as np

from ..lptn import Model
from .observer import Observer

__all__ = ["ShadowObserver"]


class ShadowObserver:
    """A Kalman filter with fixed parameters that follows the recorded samples.

    Parameters
    ----------
    model : Model
    theta : ndarray
        The parameters it runs with.
    dt : float
        Sample period, s.
    t0 : float
        Time of the sample it starts at, s.
    T0 : ndarray
        Node temperatures at ``t0`` (an estimate after that sample's readings), °C.
    inputs0 : mapping
        The inputs of the interval after ``t0``.
    q_k, r_k, p0_k : float
        Process noise σ per step, measurement noise σ and initial σ, K (the service's observer's).
    """

    def __init__(self, model: Model, theta: np.ndarray, dt: float, t0: float, T0: np.ndarray,
                 inputs0: Mapping[str, float], q_k: float = 0.02, r_k: float = 0.15, p0_k: float = 2.0) -> None:
        self.obs = Observer(model, np.asarray(T0, dtype=float), theta, dt, q_k, r_k, p0_k, spread={})
        self.times: list[float] = [float(t0)]
        self.states: list[np.ndarray] = [self.obs.T.copy()]
        self._inputs = dict(inputs0)

    @property
    def t(self) -> float:
        """Time of the last sample followed, s."""
        return self.times[-1]

    def follow(self, t: np.ndarray, inputs: Mapping[str, np.ndarray], measured: Mapping[str, np.ndarray]) -> None:
        """Step over the samples at ``t`` (s) later than :attr:`t`: predict with the inputs of the
        interval before each, correct with its readings (NaN: not read)."""
        for k in np.flatnonzero(np.asarray(t) > self.t + 1e-9):
            self.obs.predict(self._inputs)
            self.obs.update({s: float(v[k]) for s, v in measured.items()})
            self._inputs = {c: float(v[k]) for c, v in inputs.items()}
            self.times.append(float(t[k]))
            self.states.append(self.obs.T.copy())

    def state_at(self, t: float) -> np.ndarray:
        """The estimate at the first sample followed at or after ``t`` (s), °C."""
        k = min(bisect.bisect_left(self.times, float(t) - 1e-9), len(self.times) - 1)
        return self.states[k].copy()

    def forget_before(self, t: float) -> None:
        """Drop the estimates of samples before ``t`` (s) (those no period starts at any more)."""
        k = bisect.bisect_left(self.times, float(t) - 1e-9)
        k = min(k, len(self.times) - 1)
        if k > 0:
            del self.times[:k]
            del self.states[:k]
