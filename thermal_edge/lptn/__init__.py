"""The thermal model: pure numpy/scipy, no I/O beyond loading a model file.

Load a machine model, simulate it, and get exact parameter sensitivities::

    model = load_model("config/machines/pm10kw.yaml")
    sim = Simulator(model)
    traj = sim.simulate(model.nominal(), inputs, dt=1.0, T0=T0, wrt=model.adaptable)
"""
from .discretise import (
    Discrete,
    DiscreteDerivatives,
    EulerDerivatives,
    NotPassive,
    UnstableDiscretisation,
    ZohDerivatives,
    discretise,
)
from .expr import ExprError, parse
from .loader import load_model
from .model import Limit, MissingInputError, Model, ModelError, Parameter, ParameterError
from .network import Continuous, Network
from .simulate import SimulatedRun, Simulator, Trajectory
from .steady import initial_state, steady_state
from .stepper import Stepper, cool_down
from .vocabulary import DEFAULT_COLUMNS, NodeRole, Role, temperature_name

__all__ = [
    "Continuous", "DEFAULT_COLUMNS", "Discrete", "DiscreteDerivatives", "EulerDerivatives", "ExprError", "Limit",
    "MissingInputError", "Model", "ModelError", "Network", "NodeRole", "NotPassive", "Parameter", "ParameterError", "Role",
    "SimulatedRun", "Simulator", "Stepper", "Trajectory", "UnstableDiscretisation", "ZohDerivatives", "cool_down",
    "discretise", "initial_state", "load_model", "parse", "steady_state", "temperature_name",
]
