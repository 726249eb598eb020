"""The simulated machine ("plant"): a machine model with its own parameters, driven by a run's
inputs, observed through PT100-like sensors."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..data import Run
from ..lptn import Model, Simulator, Trajectory, steady_state
from .sensors import pt100


@dataclass
class PlantResult:
    run: Run  # inputs + sensor readings (+ true node temperatures as ``T_<node>`` columns)
    truth: Trajectory


def simulate_plant(
    model: Model,
    inputs: Run,
    params: Mapping[str, float] | None = None,
    T0: np.ndarray | None = None,
    noise_k: float = 0.1,
    resolution_k: float = 0.1,
    seed: int = 0,
    all_nodes: bool = False,
) -> PlantResult:
    """Run the plant over a run of inputs and read its sensors.

    Parameters
    ----------
    model : Model
        The machine; ``params`` overrides its nominal values (the plant's "true" machine).
    inputs : Run
        Input columns (e.g. from :func:`thermal_edge.sim.cycles.cycle_run`).
    T0 : ndarray, optional
        Initial node temperatures, °C; default: at rest at the first ambient temperature.
    noise_k, resolution_k : float
        PT100 noise σ and quantisation, K.
    all_nodes : bool
        Also write every node's true temperature as a ``T_<node>`` column.
    """
    plant = model.with_parameters(dict(params or {}), widen_bounds=True)  # a plant may lie outside the search bounds
    cols = {c: inputs.columns[c] for c in model.inputs}
    if T0 is None:
        first = {c: float(v[0]) for c, v in cols.items()}
        first.update({c: 0.0 for c in ("i_rms", "speed_rpm", "torque_nm") if c in first})
        T0, _ = steady_state(plant, first)
    traj = Simulator(plant).simulate(plant.nominal(), cols, inputs.dt, T0)
    rng = np.random.default_rng(seed)
    out = dict(inputs.columns)
    for s, node in model.sensors.items():
        out[s] = pt100(traj.node(node), rng, noise_k, resolution_k)
    if all_nodes:
        for i, node in enumerate(model.nodes):
            out[f"T_{node}"] = traj.T[:, i]
    return PlantResult(Run(inputs.t, out, inputs.source), traj)
