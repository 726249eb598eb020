"""One step at a time: the model as the service runs it at 1 Hz.

The service advances the model by one tick with that tick's inputs. The discretisation depends
on the parameters and on the inputs that enter conductances (speed, coolant, …); it is cached per
exact operating point, and the cache is dropped when the parameters change.
"""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping

import numpy as np

from .discretise import discretise
from .expr import Value
from .losses import LossLaws
from .model import Model
from .network import Network


class Stepper:
    """Advance node temperatures by one step of ``dt`` seconds.

    Parameters
    ----------
    model : Model
    theta : ndarray, optional
        Parameter vector (default nominal).
    dt : float
        Step, s.
    cache_size : int
        Distinct operating points kept.
    """

    def __init__(self, model: Model, theta: np.ndarray | None = None, dt: float = 1.0, method: str | None = None,
                 max_substep: float | None = None, cache_size: int = 512) -> None:
        self.model = model
        self.net = Network(model)
        self.dt = float(dt)
        self.method = method or model.discretisation.method
        self.max_substep = max_substep if max_substep is not None else model.discretisation.max_substep_s
        self.cache_size = cache_size
        self._cache: OrderedDict[tuple[float, ...], tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self.theta = model.nominal() if theta is None else np.asarray(theta, dtype=float)
        self.loss_laws = LossLaws(model)
        self.n_bound = len(model.boundaries)

    def set_parameters(self, theta: np.ndarray) -> None:
        """Use new parameters (drops the cached discretisations)."""
        self.theta = np.asarray(theta, dtype=float).copy()
        self._cache.clear()

    def matrices(self, inputs: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """``Φ`` (n, n) and ``Γ`` (n, nb + n_loss) at this operating point."""
        key = tuple(float(inputs[k]) for k in self.net.matrix_inputs)
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        op = {k: np.array([v]) for k, v in zip(self.net.matrix_inputs, key)}
        d = discretise(self.net.continuous(self.theta, op, K=1), self.dt, self.method, self.max_substep)
        hit = (d.Phi[0], d.Gam[0])
        self._cache[key] = hit
        if len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return hit

    def boundary(self, inputs: Mapping[str, float]) -> np.ndarray:
        """Boundary temperatures (°C) from the inputs."""
        return np.array([float(inputs[c]) for c in self.model.boundaries.values()])

    def env(self, inputs: Mapping[str, float]) -> dict[str, Value]:
        """The law environment (parameters, inputs, derived inputs) of one tick's inputs.

        The inputs are numpy scalars: arithmetic on them is several times cheaper than on 0-d
        arrays and follows the same IEEE rules (a division by zero gives ``inf``, not an exception).
        """
        return self.net.env(self.theta, {k: np.float64(v) for k, v in inputs.items()})

    def losses(self, T: np.ndarray, inputs: Mapping[str, float]) -> np.ndarray:
        """Loss of every loss source (W) at node temperatures ``T`` and these inputs."""
        return self.loss_laws.power(self.env(inputs), np.asarray(T, dtype=float))

    def step(self, T: np.ndarray, inputs: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """Temperatures after one step (°C) and the losses used over it (W)."""
        Phi, Gam = self.matrices(inputs)
        P = self.losses(T, inputs)
        return Phi @ T + Gam @ np.concatenate([self.boundary(inputs), P]), P


def cool_down(model: Model, theta: np.ndarray, T: np.ndarray, downtime_s: float,
              inputs: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Node temperatures after ``downtime_s`` with the machine at rest, and the transition matrix.

    At rest is :meth:`Model.at_rest`: no current, speed or torque, the temperature inputs held at
    their values in ``inputs`` (the last ones seen). One exact zero-order-hold step of the whole
    downtime (the inputs are held), so any downtime costs one discretisation.

    Parameters
    ----------
    theta : ndarray
        Parameter vector.
    T : ndarray
        Node temperatures at the stop, °C.
    downtime_s : float
        Time at rest, s (≤ 0: nothing changes).
    inputs : mapping
        The last inputs; only the temperature inputs are read (°C).

    Returns
    -------
    T1 : ndarray
        Node temperatures after the downtime, °C.
    Phi : ndarray
        ``Φ`` of the downtime (n, n), to carry a covariance over it.

    Raises
    ------
    ValueError
        A temperature input missing from ``inputs`` or not finite.
    """
    if downtime_s <= 0:
        return np.asarray(T, dtype=float).copy(), np.eye(len(model.nodes))
    u = model.at_rest(inputs)
    st = Stepper(model, theta, float(downtime_s), method="zoh")
    Phi, _ = st.matrices(u)
    T1, _ = st.step(np.asarray(T, dtype=float), u)
    return T1, Phi
