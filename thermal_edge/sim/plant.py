"""The simulated machine ("plant"): a machine model with its own parameters, driven by a run's
inputs, observed through PT100-like sensors."""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..data import Run
from ..lptn import Model, Simulator, Trajectory, steady_state
from ..lptn.loader import ModelError, build_model, read_yaml
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


def plant_model(model: Model, changes: Mapping[str, float]) -> Model:
    """The machine built differently from ``model``: parameters and constants set to new values.

    A parameter (the model's ``parameters``) gets a new nominal value; a constant (``constants``,
    e.g. ``R20_phase``, the winding resistance, so a winding conductivity) is replaced in the model
    file's text and the model rebuilt, so everything derived from it follows.

    Parameters
    ----------
    model : Model
        The model as the service knows it (loaded from a file).
    changes : mapping
        Name -> absolute value.

    Raises
    ------
    ModelError
        A name that is neither a parameter nor a constant of the model file (naming the bounds
        is the model's job: a parameter outside its bounds is refused by ``with_parameters``).
    """
    params = {k: float(v) for k, v in changes.items() if k in model.parameter_names}
    consts = {k: float(v) for k, v in changes.items() if k not in params}
    if consts:
        if model.path is None:
            raise ModelError(f"{model.name}: constants {sorted(consts)} can only be changed in a model loaded from a file")
        raw = copy.deepcopy(read_yaml(model.path, ModelError))
        known = raw.get("constants") or {}
        unknown = sorted(set(consts) - set(known))
        if unknown:
            raise ModelError(f"{model.path.name}: {unknown[0]}: neither a parameter nor a constant of the model")
        raw["constants"] = {**known, **consts}
        model = build_model(raw, fname=model.path.name, path=model.path)
    return model.with_parameters(params, widen_bounds=True) if params else model


def nominal_values(model: Model) -> dict[str, float]:
    """Every parameter's nominal value and every numeric constant of the model file, by name."""
    out = dict(zip(model.parameter_names, (float(v) for v in model.nominal())))
    if model.path is not None:
        for k, v in (read_yaml(model.path, ModelError).get("constants") or {}).items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                out.setdefault(k, float(v))
    return out
