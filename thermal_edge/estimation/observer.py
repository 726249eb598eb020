"""State observer: a linear Kalman filter on the node temperatures with the parameters fixed.

It gives the service its best current estimate of every node (the unmeasured hot spot and
magnets included) while the adapter fixes the model: the prediction ``T⁺ = Φ T + Γ w(T)`` with
the linearised loss feedback for the covariance, and an update with whichever sensors report
(NaN readings are skipped). The covariance also gives each node's state uncertainty.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ..lptn import Model, Stepper
from ..lptn.loader import temperature_name


class Observer:
    """Kalman filter over node temperatures.

    Parameters
    ----------
    model : Model
    T0 : ndarray
        Initial estimate, °C.
    theta : ndarray, optional
        Parameters (default nominal); change them with :meth:`set_parameters`.
    dt : float
        Step, s.
    q_k : float
        Process noise σ per step and node, K (model error).
    r_k : float
        Measurement noise σ, K.
    p0_k : float
        Initial σ of the estimate, K.
    """

    def __init__(self, model: Model, T0: np.ndarray, theta: np.ndarray | None = None, dt: float = 1.0,
                 q_k: float = 0.02, r_k: float = 0.15, p0_k: float = 2.0) -> None:
        self.model = model
        self.stepper = Stepper(model, theta, dt)
        self.T = np.asarray(T0, dtype=float).copy()
        n = len(model.nodes)
        self.P = np.eye(n) * p0_k**2
        self.Q = np.eye(n) * q_k**2
        self.r2 = r_k**2
        self.rows = {s: model.node_index(node) for s, node in model.sensors.items()}
        nb = len(model.boundaries)
        self._nb = nb
        self._dT = [{i: loss.power.diff(temperature_name(x)).compile() for i, x in enumerate(model.nodes)
                     if temperature_name(x) in loss.power.free()} for loss in model.losses]

    def set_parameters(self, theta: np.ndarray) -> None:
        self.stepper.set_parameters(theta)

    def predict(self, inputs: Mapping[str, float]) -> np.ndarray:
        """Advance one step with these inputs; returns the predicted temperatures."""
        Phi, Gam = self.stepper.matrices(inputs)
        T_next, _ = self.stepper.step(self.T, inputs)
        M = Phi.copy()
        if any(self._dT):
            env = self.stepper.net.env(self.stepper.theta, {k: np.asarray(float(v)) for k, v in inputs.items()})
            env.update(zip((temperature_name(x) for x in self.model.nodes), map(float, self.T)))
            GP = Gam[:, self._nb:]
            for li, d in enumerate(self._dT):
                for i, g in d.items():
                    M[:, i] += GP[:, li] * float(g(env))
        self.P = M @ self.P @ M.T + self.Q
        self.T = T_next
        return self.T

    def update(self, measured: Mapping[str, float]) -> np.ndarray:
        """Correct the estimate with the sensors that report (NaN or unknown ones are ignored)."""
        idx = [self.rows[s] for s, v in measured.items() if s in self.rows and np.isfinite(v)]
        if not idx:
            return self.T
        y = np.array([float(measured[s]) for s, v in measured.items() if s in self.rows and np.isfinite(v)])
        S = self.P[np.ix_(idx, idx)] + np.eye(len(idx)) * self.r2
        K = np.linalg.solve(S, self.P[idx, :]).T
        self.T = self.T + K @ (y - self.T[idx])
        self.P = self.P - K @ self.P[idx, :]
        self.P = 0.5 * (self.P + self.P.T)
        return self.T

    def std(self) -> np.ndarray:
        """Standard deviation of each node's estimate, K."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))
