"""Typed machine model: the validated, flattened form of a machine model file.

Arc elements are already expanded into dynamic nodes, algebraic mid-/face-points and edges;
constants are inlined. Everything numeric downstream (:mod:`.network`) works from this object.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import ThermalEdgeError
from .expr import Expr
from .vocabulary import NodeRole, Role


class ModelError(ThermalEdgeError, ValueError):
    """A machine model file that is invalid, or a model that lacks what a command needs of it
    (an input of a role, a node); the message names the file or model and the key."""


class MissingInputError(ThermalEdgeError, ValueError):
    """A run or an operating point lacks inputs the model needs.

    Attributes
    ----------
    missing : tuple of str
        The input names that are missing, in the model's order.
    """

    def __init__(self, message: str, missing: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.missing = missing


#: Relative distance from a bound within which a value counts as on it: ``exp(log(300))`` is
#: 299.99999999999994, and a parameter adapted onto its bound must stay usable.
BOUND_ROUNDOFF_REL = 1e-9


class ParameterError(ThermalEdgeError, ValueError):
    """A parameter value outside its bounds, not a finite number, or an unknown parameter name.

    The message names the parameter, the value and the bounds (or, for an unknown name, the
    closest known name); the attributes carry the same facts for callers that add a file and key.

    Attributes
    ----------
    name : str
        The parameter as given.
    value : float or None
        The offending value (None for an unknown name).
    bounds : tuple of float or None
        ``(lower, upper)`` of a known parameter.
    suggestion : str or None
        The closest known parameter name for an unknown one.
    problem : str
        The message without the leading ``parameter NAME``: what a caller puts after its own key.
    """

    def __init__(self, name: str, problem: str, *, value: float | None = None,
                 bounds: tuple[float, float] | None = None, suggestion: str | None = None) -> None:
        super().__init__(f"parameter {name}: {problem}")
        self.name, self.problem, self.value, self.bounds, self.suggestion = name, problem, value, bounds, suggestion


#: Relative spread (σ of log θ) of a parameter whose model file states none: offline values of
#: LPTN parameters are rarely known better than about 10 %.
DEFAULT_SPREAD = 0.1


@dataclass(frozen=True)
class Parameter:
    """A named thermal parameter with its nominal value, bounds, unit and relative spread
    ``spread`` (σ of ``log θ``: how far the machine at hand may differ from the nominal value)."""

    name: str
    value: float
    lower: float
    upper: float
    unit: str = ""
    adaptable: bool = False
    doc: str = ""
    spread: float = DEFAULT_SPREAD


@dataclass(frozen=True)
class Edge:
    """A conductance law ``g`` (W/K) between two points, or a point (``a``) and a boundary (``b``)."""

    a: str
    b: str
    g: Expr
    key: str  # where it came from in the file, for messages


@dataclass(frozen=True)
class Loss:
    """A loss law (W) injected into a point."""

    point: str
    power: Expr
    key: str


@dataclass(frozen=True)
class Limit:
    """A limited node for derating: linear derate from ``warn_c`` to ``max_c`` (°C)."""

    name: str
    node: str
    warn_c: float
    max_c: float


@dataclass(frozen=True)
class Discretisation:
    """Default discretisation of a model: ``zoh`` or ``euler`` with an optional sub-step limit (s)."""

    method: str = "zoh"
    max_substep_s: float | None = None


@dataclass(frozen=True)
class Model:
    """A flattened LPTN machine model.

    Attributes
    ----------
    nodes : tuple of str
        Dynamic nodes (with heat capacity), in state order.
    capacities : tuple of Expr
        Capacity law (J/K) of each dynamic node, in parameters only.
    points : tuple of str
        Algebraic points (no capacity), eliminated by Schur complement.
    boundaries : dict
        Boundary name -> input column giving its temperature (°C).
    input_roles : dict
        Input name -> its :class:`~thermal_edge.lptn.vocabulary.Role` (inputs without ``role:``
        are absent); ask with :meth:`input_name` rather than reading it.
    node_roles : dict
        Node name -> its :class:`~thermal_edge.lptn.vocabulary.NodeRole`; ask with :meth:`nodes_with`.
    """

    name: str
    path: Path | None
    description: str
    inputs: tuple[str, ...]
    derived: dict[str, Expr]
    boundaries: dict[str, str]
    parameters: tuple[Parameter, ...]
    nodes: tuple[str, ...]
    capacities: tuple[Expr, ...]
    points: tuple[str, ...]
    edges: tuple[Edge, ...]
    losses: tuple[Loss, ...]
    sensors: dict[str, str]
    limits: tuple[Limit, ...] = ()
    discretisation: Discretisation = field(default_factory=Discretisation)
    drive: dict[str, float] = field(default_factory=dict)
    input_roles: dict[str, Role] = field(default_factory=dict)
    node_roles: dict[str, NodeRole] = field(default_factory=dict)

    @property
    def where(self) -> str:
        """The model file's name for a message, or ``model NAME`` for a model built from a document."""
        return self.path.name if self.path is not None else f"model {self.name}"

    def find_input(self, role: Role) -> str | None:
        """The input that has ``role``, or None when the model has none."""
        return next((k for k, r in self.input_roles.items() if r is role), None)

    def input_name(self, role: Role) -> str:
        """The input that has ``role``.

        Raises
        ------
        ModelError
            The model has no input with that role (the message names the model's file and its inputs).
        """
        name = self.find_input(role)
        if name is None:
            roles = ", ".join(f"{k} ({r.value})" for k, r in self.input_roles.items())
            where = f"{self.path.name}: " if self.path is not None else ""
            raise ModelError(f"{where}model {self.name} has no input with role {role.value!r} "
                             f"(its inputs: {roles or 'none with a role'})")
        return name

    @property
    def temperature_inputs(self) -> tuple[str, ...]:
        """Inputs that are temperatures: boundary columns and inputs with a temperature role."""
        bounds = set(self.boundaries.values())
        return tuple(k for k in self.inputs if k in bounds or (k in self.input_roles and self.input_roles[k].is_temperature))

    def at_rest(self, inputs: Mapping[str, float]) -> dict[str, float]:
        """The inputs of the machine at rest: every temperature input as in ``inputs``, all else 0.

        The one definition of standstill (cool-down after a stop, the initial steady state of a
        simulation, a benchmark's starting point): no current, speed or torque, the boundary
        temperatures held.

        Parameters
        ----------
        inputs : mapping
            Input name -> value; only the temperature inputs (°C) are read.

        Raises
        ------
        ValueError
            A temperature input missing from ``inputs`` or not finite.
        """
        temperatures = self.temperature_inputs
        out = {k: 0.0 for k in self.inputs}
        for k in temperatures:
            v = inputs.get(k)
            if v is None or not math.isfinite(float(v)):
                raise ValueError(f"the machine at rest needs the value of temperature input {k!r} (got {v!r})")
            out[k] = float(v)
        return out

    def nodes_with(self, *roles: NodeRole) -> tuple[str, ...]:
        """Nodes (in state order) whose role is one of ``roles``."""
        return tuple(x for x in self.nodes if self.node_roles.get(x) in roles)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def adaptable(self) -> tuple[str, ...]:
        """Names of the parameters the online adapter may change."""
        return tuple(p.name for p in self.parameters if p.adaptable)

    def nominal(self) -> np.ndarray:
        """Nominal parameter vector in declaration order."""
        return np.array([p.value for p in self.parameters], dtype=float)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper parameter bounds in declaration order."""
        return (
            np.array([p.lower for p in self.parameters], dtype=float),
            np.array([p.upper for p in self.parameters], dtype=float),
        )

    def parameter_index(self, names: list[str] | tuple[str, ...]) -> np.ndarray:
        """Indices of the named parameters.

        Raises
        ------
        ParameterError
            A name the model does not have (the first such; the message names the model).
        """
        idx = {p.name: i for i, p in enumerate(self.parameters)}
        missing = [n for n in names if n not in idx]
        if missing:
            raise ParameterError(missing[0], f"unknown in model {self.name} (unknown: {', '.join(missing)}; "
                                             f"known: {', '.join(idx)})")
        return np.array([idx[n] for n in names], dtype=int)

    def node_index(self, node: str) -> int:
        """Index of ``node`` in the state vector; :class:`ModelError` naming the model for an unknown one."""
        try:
            return self.nodes.index(node)
        except ValueError:
            raise ModelError(f"unknown node {node!r} in model {self.name}") from None

    def check_parameters(self, values: Mapping[str, object]) -> None:
        """Check parameter values against the model: known names, finite numbers within the bounds.

        Pure (no I/O); the bounds are the model file's, and only the model file can widen them.

        Parameters
        ----------
        values : mapping
            Parameter name -> value, in the parameter's unit (see :class:`Parameter`).

        Raises
        ------
        ParameterError
            For the first offending entry (in the order given): unknown name (with the closest
            known name), a value that is not a finite number, or one outside ``[lower, upper]``.
        """
        by_name = {p.name: p for p in self.parameters}
        for name, v in values.items():
            p = by_name.get(name)
            if p is None:
                close = difflib.get_close_matches(str(name), list(by_name), n=1, cutoff=0.6)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise ParameterError(str(name), f"model {self.name} has no parameter {name!r}{hint}",
                                     suggestion=close[0] if close else None)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
                raise ParameterError(name, f"expected a finite number, got {v!r}", bounds=(p.lower, p.upper))
            if not p.lower <= float(v) <= p.upper:
                shown = f"{float(v):g}" if float(f"{float(v):g}") == v else repr(float(v))  # 299.99999999999994, not 300
                raise ParameterError(name, f"{shown} is outside the model's bounds [{p.lower:g}, {p.upper:g}]"
                                           f"{f' {p.unit}' if p.unit else ''}",
                                     value=float(v), bounds=(p.lower, p.upper))

    def snap_to_bounds(self, values: Mapping[str, float], rel: float = BOUND_ROUNDOFF_REL) -> dict[str, float]:
        """``values`` with every known parameter within ``rel`` (relative) outside a bound set onto it.

        Round-off of a bound (``exp(log(L))`` a few ulp below ``L``) is not a departure from it;
        anything further out is left as it is for :meth:`check_parameters` to refuse.
        """
        by_name = {p.name: p for p in self.parameters}
        out = dict(values)
        for name, v in values.items():
            p = by_name.get(name)
            if p is None or isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                continue
            for bound in (p.lower, p.upper):
                if abs(v - bound) <= rel * max(abs(bound), np.finfo(float).tiny):
                    out[name] = float(bound)
        return out

    def with_parameters(self, values: Mapping[str, float], *, widen_bounds: bool = False) -> Model:
        """A copy whose nominal values are replaced.

        Parameters
        ----------
        values : mapping
            Parameter name -> new nominal value.
        widen_bounds : bool, optional
            Only for a simulated *plant* (which may lie outside what the estimator may search):
            a value outside the bounds widens them. Default False: such a value is refused.

        Raises
        ------
        ParameterError
            An unknown name, or (unless ``widen_bounds``) a value outside the bounds.
        """
        if widen_bounds:
            unknown = [n for n in values if n not in self.parameter_names]
            if unknown:
                self.check_parameters({unknown[0]: values[unknown[0]]})
        else:
            self.check_parameters(values)
        ps = []
        for p in self.parameters:
            if p.name in values:
                v = float(values[p.name])
                ps.append(replace(p, value=v, lower=min(p.lower, v), upper=max(p.upper, v)))
            else:
                ps.append(p)
        return replace(self, parameters=tuple(ps))
