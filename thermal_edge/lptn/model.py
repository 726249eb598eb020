"""Typed machine model: the validated, flattened form of a machine model file.

Arc elements are already expanded into dynamic nodes, algebraic mid-/face-points and edges;
constants are inlined. Everything numeric downstream (:mod:`.network`) works from this object.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .expr import Expr


class ModelError(ValueError):
    """A machine model file that is invalid; the message names the file and the key."""


@dataclass(frozen=True)
class Parameter:
    """A named thermal parameter with its nominal value, bounds and unit."""

    name: str
    value: float
    lower: float
    upper: float
    unit: str = ""
    adaptable: bool = False
    doc: str = ""


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

    def parameter_index(self, names: "list[str] | tuple[str, ...]") -> np.ndarray:
        """Indices of the named parameters; raises ``KeyError`` naming an unknown one."""
        idx = {p.name: i for i, p in enumerate(self.parameters)}
        missing = [n for n in names if n not in idx]
        if missing:
            raise KeyError(f"unknown parameter(s) {', '.join(missing)} in model {self.name}")
        return np.array([idx[n] for n in names], dtype=int)

    def node_index(self, node: str) -> int:
        try:
            return self.nodes.index(node)
        except ValueError:
            raise KeyError(f"unknown node {node!r} in model {self.name}") from None

    def with_parameters(self, values: dict[str, float]) -> "Model":
        """A copy whose nominal values are replaced; a value outside the bounds widens them (a
        simulated plant may lie outside what the estimator is allowed to search)."""
        ps = []
        for p in self.parameters:
            if p.name in values:
                v = float(values[p.name])
                ps.append(Parameter(p.name, v, min(p.lower, v), max(p.upper, v), p.unit, p.adaptable, p.doc))
            else:
                ps.append(p)
        unknown = set(values) - {p.name for p in self.parameters}
        if unknown:
            raise KeyError(f"unknown parameter(s) {', '.join(sorted(unknown))} in model {self.name}")
        from dataclasses import replace

        return replace(self, parameters=tuple(ps))
