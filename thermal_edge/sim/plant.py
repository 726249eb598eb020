"""The simulated machine ("plant"): a machine model with its own (possibly aging) parameters,
started at rest, stepped in time (the inverter emulator) or run over a whole run of inputs
(``simulate``), observed through PT100-like sensors (:mod:`.sensors`)."""
from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..data import Run
from ..lptn import Model, Simulator, Stepper, Trajectory, steady_state
from ..lptn.loader import ModelError, build_model, read_yaml
from .sensors import pt100


class Plant:
    """The simulated machine: ``model`` built with the plant's own parameter values.

    Parameters
    ----------
    model : Model
        The machine model; ``params`` (absolute values) replace its nominal ones, and may lie
        outside its search bounds (a plant is what it is).
    params : mapping
        Parameter name -> value.
    dt : float
        Step of :meth:`step`, s.
    aging : mapping, optional
        Parameter name -> relative change per simulated hour (:meth:`age`).
    T0 : ndarray, optional
        Initial node temperatures, °C; default: the steady state at rest
        (:meth:`~thermal_edge.lptn.Model.at_rest`) with ``rest_inputs``' temperatures.
    rest_inputs : mapping, optional
        Inputs whose temperature inputs (°C) define the rest state (required without ``T0``).
    """

    def __init__(self, model: Model, params: Mapping[str, float], dt: float, aging: Mapping[str, float] | None = None,
                 T0: np.ndarray | None = None, rest_inputs: Mapping[str, float] | None = None) -> None:
        self.base = model.with_parameters(dict(params), widen_bounds=True)
        self.model = self.base
        self.theta0 = self.base.nominal()
        self.aging = dict(aging or {})
        self._aging_idx = self.base.parameter_index(list(self.aging)) if self.aging else np.zeros(0, dtype=int)
        self.dt = float(dt)
        self._stepper: Stepper | None = None  # made on the first step: a whole-run simulation needs none
        if T0 is None:
            T0, _ = steady_state(self.base, self.base.at_rest(rest_inputs or {}))
        self.T = np.asarray(T0, dtype=float).copy()

    @property
    def stepper(self) -> Stepper:
        if self._stepper is None:
            self._stepper = Stepper(self.base, self.theta0, self.dt)
        return self._stepper

    def age(self, hours: float) -> None:
        """Apply the aging rates for ``hours`` of simulated time since the start."""
        if not self.aging:
            return
        th = self.theta0.copy()
        lo, hi = self.base.bounds()
        for rate, i in zip(self.aging.values(), self._aging_idx):
            th[i] = min(max(self.theta0[i] * (1.0 + rate * hours), lo[i]), hi[i])
        self.stepper.set_parameters(th)

    @property
    def theta(self) -> np.ndarray:
        """The plant's parameter vector now (aged)."""
        return self.stepper.theta

    def step(self, inputs: Mapping[str, float]) -> np.ndarray:
        """Advance by ``dt`` with these inputs; the node temperatures after it, °C."""
        self.T, _ = self.stepper.step(self.T, inputs)
        return self.T

    def node(self, name: str) -> float:
        """The true temperature of one node now, °C."""
        return float(self.T[self.base.node_index(name)])

    def simulate(self, inputs: Run) -> Trajectory:
        """The node temperatures over a whole run of inputs from the current state (no aging)."""
        cols = {c: inputs.columns[c] for c in self.model.inputs}
        return Simulator(self.model).simulate(self.theta0, cols, inputs.dt, self.T)


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
        Initial node temperatures, °C; default: at rest at the run's first temperatures.
    noise_k, resolution_k : float
        PT100 noise σ and quantisation, K.
    all_nodes : bool
        Also write every node's true temperature as a ``T_<node>`` column.
    """
    first = {c: float(inputs.columns[c][0]) for c in model.inputs}
    plant = Plant(model, params or {}, inputs.dt, T0=T0, rest_inputs=first)
    traj = plant.simulate(inputs)
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
