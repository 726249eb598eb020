"""Steady states and initial states of a model.

``steady_state`` solves ``A T + W [U; P(T)] = 0`` (temperature-dependent losses by fixed-point
iteration, which converges while the loss feedback gain ``R_th · ∂P/∂T`` is below 1).
``initial_state`` fills the nodes nobody measures for the first sample: measured nodes keep
their readings and the others take the loss-free steady state given them (heat flows between
the measured nodes and the boundaries), which is the physical guess for a machine at rest.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .losses import LossLaws
from .model import Model, ModelError
from .network import Network


def _point(net: Network, theta: np.ndarray, inputs: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    op = {k: np.array([float(inputs[k])]) for k in net.model.inputs if k in inputs}
    cont = net.continuous(theta, op, K=1)
    U = np.array([float(inputs[c]) for c in net.model.boundaries.values()])
    return cont.A[0], cont.W[0], U


def steady_state(
    model: Model, inputs: Mapping[str, float], theta: np.ndarray | None = None, tol: float = 1e-10, max_iter: int = 500
) -> tuple[np.ndarray, np.ndarray]:
    """Steady node temperatures (°C) and losses (W) at constant inputs.

    Parameters
    ----------
    model : Model
    inputs : mapping
        One value per model input (e.g. ``speed_rpm``, ``i_rms``, ``ambient_c``).
    theta : ndarray, optional
        Parameter vector; default nominal.

    Raises
    ------
    ModelError
        A loss law that is not finite at these inputs (named by its key), or a loss feedback that
        does not converge (thermal runaway at these inputs).
    """
    theta = model.nominal() if theta is None else np.asarray(theta, dtype=float)
    net = Network(model)
    A, W, U = _point(net, theta, inputs)
    env = net.env(theta, {k: np.asarray(float(v)) for k, v in inputs.items()})
    laws = LossLaws(model)
    nb = len(U)
    T = np.full(len(model.nodes), float(np.mean(U)) if nb else 20.0)
    for _ in range(max_iter):
        with np.errstate(all="ignore"):
            P = laws.power(env, T)
        law = laws.not_finite(P)
        if law is not None:
            raise ModelError(f"{model.where}: {law} at {_at(model, inputs)} (a logarithm of 0, a division by 0?): "
                             "no steady state")
        T_new = np.linalg.solve(A, -W @ np.concatenate([U, P]))
        if np.max(np.abs(T_new - T)) < tol:
            return T_new, P
        T = T_new
    raise ModelError(f"{model.where}: no steady state at {_at(model, inputs)}: the losses' feedback on the "
                     "temperatures does not converge (thermal runaway at these inputs?)")


def _at(model: Model, inputs: Mapping[str, float]) -> str:
    """The model's inputs of ``inputs``, for a message."""
    return ", ".join(f"{k} = {float(v):g}" for k, v in inputs.items() if k in model.inputs)


def initial_state(
    model: Model, inputs: Mapping[str, float], measured: Mapping[str, float], theta: np.ndarray | None = None,
    net: Network | None = None, rest_inputs: Mapping[str, float] | None = None,
) -> np.ndarray:
    """Initial node temperatures (°C) from the sensors' first readings.

    Parameters
    ----------
    inputs : mapping
        First-sample inputs (boundary temperatures at least).
    measured : mapping
        Sensor name -> reading (°C); NaN readings are ignored.
    net : Network, optional
        A network of ``model`` already built (saves compiling the laws again).
    rest_inputs : mapping, optional
        Inputs of the machine at rest (no speed, no current). With them the unmeasured nodes
        also carry the heat flows the loss laws give at rest (a warmer ambient, radiation …),
        by two fixed-point passes for temperature-dependent laws; without them, none.
    """
    theta = model.nominal() if theta is None else np.asarray(theta, dtype=float)
    net = net or Network(model)
    A, W, U = _point(net, theta, inputs)
    n = len(model.nodes)
    T = np.full(n, np.nan)
    for s, v in measured.items():
        if s in model.sensors and np.isfinite(v):
            T[model.node_index(model.sensors[s])] = float(v)
    known = np.isfinite(T)
    if known.all():
        return T
    u = ~known
    rhs = -(A[np.ix_(u, known)] @ T[known]) - W[u, : len(U)] @ U
    T[u] = np.linalg.solve(A[np.ix_(u, u)], rhs)
    if rest_inputs is not None and model.losses:
        env = net.env(theta, {c: np.array(float(v)) for c, v in rest_inputs.items()})
        laws = LossLaws(model)
        for _ in range(2):
            P = laws.power(env, T)
            if not np.all(np.isfinite(P)):
                break
            T[u] = np.linalg.solve(A[np.ix_(u, u)], rhs - W[u, len(U):] @ P)
    return T
