"""The model's vocabulary: what an input or a node *is*, independent of what a file calls it.

A machine model file names its inputs freely (``i_rms``, ``n_mech`` …) and says what each one
is with ``role:``; nodes may say so too. Every other part of the package asks the model by role
(:meth:`thermal_edge.lptn.model.Model.input_name`, :meth:`~thermal_edge.lptn.model.Model.nodes_with`,
:meth:`~thermal_edge.lptn.model.Model.at_rest`) instead of writing a column name.

Only data that has no model (a simulated drive cycle, a recorded data set before a model is
chosen) uses :data:`DEFAULT_COLUMNS`: the one place the usual column names are written.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np


class Role(StrEnum):
    """What an input column measures (its unit is part of the role)."""

    CURRENT = "current"  #: RMS phase current, A (≥ 0)
    CURRENT_D = "current_d"  #: d-axis current amplitude, A
    CURRENT_Q = "current_q"  #: q-axis current amplitude, A (sign of the torque)
    SPEED = "speed"  #: mechanical speed, rpm (signed)
    TORQUE = "torque"  #: shaft torque, Nm (signed)
    AMBIENT = "ambient"  #: ambient air temperature, °C
    COOLANT = "coolant"  #: coolant temperature, °C

    @property
    def is_temperature(self) -> bool:
        """A boundary temperature: it keeps its value when the machine stops."""
        return self in (Role.AMBIENT, Role.COOLANT)

    @property
    def default_column(self) -> str:
        """The column name used for this role in data that has no model (:data:`DEFAULT_COLUMNS`)."""
        return DEFAULT_COLUMNS[self]

    @property
    def plausible(self) -> Plausible:
        """The unit of this role's values and the range a machine's values lie in
        (:data:`~thermal_edge.lptn.vocabulary.PLAUSIBLE`)."""
        return PLAUSIBLE[self]


#: Column names of data without a model (simulated cycles, converted data sets): the only place
#: these names are written outside the model files.
DEFAULT_COLUMNS: dict[Role, str] = {
    Role.CURRENT: "i_rms",
    Role.CURRENT_D: "i_d",
    Role.CURRENT_Q: "i_q",
    Role.SPEED: "speed_rpm",
    Role.TORQUE: "torque_nm",
    Role.AMBIENT: "ambient_c",
    Role.COOLANT: "coolant_c",
}


@dataclass(frozen=True)
class OtherUnit:
    """A unit a value is often given in by mistake, and how it converts: ``ours = x * scale + offset``."""

    name: str
    scale: float = 1.0
    offset: float = 0.0

    def convert(self, x: float | np.ndarray) -> float | np.ndarray:
        return x * self.scale + self.offset


KELVIN = OtherUnit("kelvin", 1.0, -273.15)
MILLIAMPERE = OtherUnit("mA", 1e-3)


@dataclass(frozen=True)
class Plausible:
    """The unit of a quantity and the range every value of a machine lies in; outside it a value
    is a unit, scaling or sensor error, and when it is plausible in one of :attr:`others` the
    message says that unit ("428 °C looks like kelvin").

    Attributes
    ----------
    unit : str
        The unit the package works in (what files and frames must give).
    lo, hi : float
        Inclusive bounds of a plausible value, in ``unit``.
    others : tuple of OtherUnit
        Units the value is often given in by mistake.
    whole_above : float, optional
        A whole series whose every value lies above this is in another unit, although each
        value alone is plausible (temperatures: no machine stays above 200 °C for a whole run,
        and no recording in kelvin goes below 200 K).
    """

    unit: str
    lo: float
    hi: float
    others: tuple[OtherUnit, ...] = ()
    whole_above: float | None = None
    what: str = field(default="", compare=False)

    def _range(self) -> str:
        return f"the plausible {self.lo:g} to {self.hi:g} {self.unit}"

    def problem(self, x: float) -> str | None:
        """Why the single value ``x`` cannot be right (None: plausible), naming the unit it
        looks like when it is plausible in one of :attr:`others`."""
        if not math.isfinite(x):
            return f"{x} is not a number"
        if self.lo <= x <= self.hi:
            return None
        for other in self.others:
            y = float(other.convert(x))
            if self.lo <= y <= self.hi:
                return f"{x:g} {self.unit} looks like {other.name} ({y:.4g} {self.unit}); give it in {self.unit}"
        return f"{x:g} {self.unit} is outside {self._range()}"

    def series_problem(self, x: np.ndarray) -> tuple[int | None, str] | None:
        """Why the series ``x`` cannot be right, and the index of the value at fault (None when the
        whole series is: a unit error); None when plausible. NaN (not measured) is skipped.

        A whole series is in another unit when it is plausible there and either every value lies
        above :attr:`whole_above` or at least :data:`UNIT_SHARE` of the values are outside the
        range here; otherwise the first value outside the range is named (a spike, a sign error).
        """
        x = np.asarray(x, dtype=float)
        finite = x[np.isfinite(x)]
        if finite.size == 0:
            return None
        out = (finite < self.lo) | (finite > self.hi)
        whole = self.whole_above is not None and bool(finite.min() > self.whole_above)
        if whole or out.any():
            for other in self.others:
                y = other.convert(finite)
                if bool(np.all((y >= self.lo) & (y <= self.hi))) and (whole or out.mean() >= UNIT_SHARE):
                    return None, (f"{finite.min():.6g} to {finite.max():.6g} looks like {other.name} "
                                  f"({float(np.min(y)):.4g} to {float(np.max(y)):.4g} {self.unit}); give it in {self.unit}")
        if not out.any():
            return None
        k = int(np.flatnonzero(np.isfinite(x) & ((x < self.lo) | (x > self.hi)))[0])
        why = f"{x[k]:g} {self.unit} is outside {self._range()}"
        inside = finite[~out]
        for other in self.others:  # one sample in another unit: it converts into the span of the rest
            y = float(other.convert(x[k]))
            if self.lo <= y <= self.hi and inside.size and inside.min() - SPAN_MARGIN <= y <= inside.max() + SPAN_MARGIN:
                return k, f"{why}; it looks like {other.name} ({y:.4g} {self.unit})"
        return k, why


#: How far a single value converted from another unit may lie outside the span of the rest of its
#: series and still be named as given in that unit (in the series' unit: K, A).
SPAN_MARGIN = 5.0
#: Share of a series outside the plausible range from which the series, rather than a sample of
#: it, is in the wrong unit (a current in mA idles in range, a spike is one sample).
UNIT_SHARE = 0.1

#: Temperatures of a machine and its surroundings (nodes, sensors, ambient, coolant), °C. No
#: machine runs below -60 °C; above 300 °C its insulation and magnets are destroyed.
TEMPERATURE = Plausible("degC", -60.0, 300.0, (KELVIN,), whole_above=200.0, what="temperature")
#: Derating limits (``warn_c``, ``max_c``) of a node, °C: insulation classes reach 240 °C and
#: magnets less; below 20 °C a machine would derate at rest.
LIMIT = Plausible("degC", 20.0, 250.0, (KELVIN,), what="limit temperature")

#: Plausible values of each input role, in the role's unit.
PLAUSIBLE: dict[Role, Plausible] = {
    # RMS: never negative; 4 kA covers the largest traction inverters
    Role.CURRENT: Plausible("A", 0.0, 4000.0, (MILLIAMPERE,), what="RMS current"),
    Role.CURRENT_D: Plausible("A", -5000.0, 5000.0, (MILLIAMPERE,), what="d-axis current"),
    Role.CURRENT_Q: Plausible("A", -5000.0, 5000.0, (MILLIAMPERE,), what="q-axis current"),
    # high-speed machines (spindles, turbo compressors) reach 100,000 rpm
    Role.SPEED: Plausible("rpm", -100000.0, 100000.0, what="speed"),
    Role.TORQUE: Plausible("Nm", -50000.0, 50000.0, what="torque"),
    # the air around a machine (a hot engine bay, a desert) stays below 100 degC, its coolant below 150 degC
    Role.AMBIENT: Plausible("degC", -60.0, 100.0, (KELVIN,), whole_above=TEMPERATURE.whole_above, what="ambient temperature"),
    Role.COOLANT: Plausible("degC", -60.0, 150.0, (KELVIN,), whole_above=TEMPERATURE.whole_above, what="coolant temperature"),
}

#: How a model file or a DBC may write each unit the package works in (compared without case).
UNIT_SPELLINGS: dict[str, frozenset[str]] = {
    "A": frozenset({"A", "A rms", "Arms", "A_rms", "A RMS"}),
    "rpm": frozenset({"rpm", "1/min", "min^-1", "min-1", "r/min", "rev/min", "U/min"}),
    "Nm": frozenset({"Nm", "N m", "N*m", "N·m", "N.m"}),
    "degC": frozenset({"degC", "°C", "C", "deg C", "celsius", "deg_C"}),
    "V": frozenset({"V", "volt"}),
}

#: Units a DBC (or a file) often declares in place of the package's, and how they convert into it
#: (``ours = x * scale + offset``), by the package's unit; compared without case. Other units are
#: refused without a conversion.
FOREIGN_UNITS: dict[str, dict[str, OtherUnit]] = {
    "rpm": {u: OtherUnit(u, 60.0 / (2.0 * np.pi)) for u in ("rad/s", "rad/sec")}
           | {u: OtherUnit(u, 60.0) for u in ("rev/s", "rps")},
    "degC": {"K": OtherUnit("K", 1.0, -273.15), "kelvin": OtherUnit("kelvin", 1.0, -273.15)}
            | {u: OtherUnit(u, 5.0 / 9.0, -32.0 * 5.0 / 9.0) for u in ("degF", "°F", "F", "deg F")},
    "A": {"mA": OtherUnit("mA", 1e-3), "kA": OtherUnit("kA", 1e3)},
    "Nm": {"kNm": OtherUnit("kNm", 1e3), "Ncm": OtherUnit("Ncm", 1e-2), "mNm": OtherUnit("mNm", 1e-3)},
    "V": {"mV": OtherUnit("mV", 1e-3), "kV": OtherUnit("kV", 1e3)},
}


def _unit_key(unit: str) -> str:
    # a DBC saved in UTF-8 and read as cp1252 (cantools' default) spells the degree sign "Â°"
    return unit.strip().replace("Â°", "°").casefold()


def is_unit(want: str, unit: str) -> bool:
    """Whether ``unit`` (as a file declares it) is a spelling of the package's unit ``want``."""
    u = _unit_key(unit)
    return any(u == x.casefold() for x in UNIT_SPELLINGS.get(want, frozenset({want})))


def foreign_unit(want: str, unit: str) -> OtherUnit | None:
    """The conversion into ``want`` of ``unit`` when it is a unit often declared in its place
    (:data:`FOREIGN_UNITS`); None otherwise."""
    u = _unit_key(unit)
    return next((o for k, o in FOREIGN_UNITS.get(want, {}).items() if k.casefold() == u), None)


#: the SI units of a network's quantities (capacity, conductance, resistance, power, heat-transfer
#: coefficients, conductivity, specific heat, length): a model file gives its values in these
NETWORK_UNITS = ("J/K", "W/K", "K/W", "W", "W/(m^2 K)", "W/(m K)", "J/(kg K)", "m")
#: prefixes a file may put on them by habit, and their factor to the SI unit
_PREFIXES = {"k": 1e3, "M": 1e6, "m": 1e-3, "c": 1e-2, "µ": 1e-6, "u": 1e-6}


def scaled_unit(unit: str) -> tuple[str, float] | None:
    """``(SI unit, factor)`` for a prefixed spelling of one of :data:`NETWORK_UNITS` (``kJ/K`` is
    1000 J/K; ``mm`` 0.001 m); None otherwise (the SI unit itself, or a unit this does not know).

    >>> scaled_unit("kJ/K"), scaled_unit("J/K"), scaled_unit("mm")
    (('J/K', 1000.0), None, ('m', 0.001))
    """
    u = unit.strip()
    for base in NETWORK_UNITS:
        if len(u) == len(base) + 1 and u.endswith(base) and u[0] in _PREFIXES:
            if base == "m" and u[0] == "M":  # "Mm" is no length a machine has
                continue
            return base, _PREFIXES[u[0]]
    return None


def unit_problem(role: Role, unit: str) -> str | None:
    """Why ``unit`` (as a model file writes an input's unit) is not the unit of ``role``; None if it is."""
    want = role.plausible.unit
    if is_unit(want, unit):
        return None
    return f"{unit!r} is not the unit of role {role.value!r}: its values must be in {want}"


def temperature_problems(values: Sequence[float]) -> str | None:
    """Why a set of node temperatures (a saved state, °C) cannot be right; None when plausible."""
    found = TEMPERATURE.series_problem(np.asarray(values, dtype=float))
    if found is None:
        return None
    k, why = found
    return why if k is None else f"value {k + 1}: {why}"


class NodeRole(StrEnum):
    """What part of the machine a node is (several nodes may share a role)."""

    WINDING = "winding"  #: copper: slot or end winding, coil
    YOKE = "yoke"  #: stator back iron
    TOOTH = "tooth"  #: stator tooth body or tip
    MAGNET = "magnet"  #: permanent magnet
    ROTOR_IRON = "rotor_iron"  #: rotor lamination
    SHAFT = "shaft"  #: shaft (and its bearings)
    HOUSING = "housing"  #: frame, housing, fins
    END_CAP = "end_cap"  #: end shield: frame that carries a bearing
    AIR = "air"  #: internal air (air gap, end space)
    STRUCTURE = "structure"  #: other solid parts (retaining plates, wedges)


#: Groups of node roles that parts of the package treat alike.
STATOR_IRON: frozenset[NodeRole] = frozenset({NodeRole.YOKE, NodeRole.TOOTH})
#: Nodes that carry bearing friction (the shaft and the end shields that hold the bearings).
BEARING_SIDE: frozenset[NodeRole] = frozenset({NodeRole.SHAFT, NodeRole.END_CAP})
#: Nodes on the outside of the machine (they exchange heat with the ambient air).
FRAME: frozenset[NodeRole] = frozenset({NodeRole.HOUSING, NodeRole.END_CAP})

#: Prefix of a node temperature in the law grammar: ``T.sw`` is the temperature of node ``sw``.
TEMP_PREFIX = "T."


def temperature_name(node: str) -> str:
    """The law name of a node temperature, ``T.<node>``."""
    return TEMP_PREFIX + node


def parse_role(value: object, kind: type[Role] | type[NodeRole]) -> Role | NodeRole:
    """The role named by ``value``; ``ValueError`` naming the closest known role otherwise.

    Parameters
    ----------
    value : object
        The role as written in a model file (``current``, ``winding`` …).
    kind : Role or NodeRole
        Which vocabulary.
    """
    known = [r.value for r in kind]
    try:
        return kind(str(value))
    except ValueError:
        close = difflib.get_close_matches(str(value), known, n=1, cutoff=0.5)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown role {value!r}{hint}; known: {', '.join(known)}") from None


__all__ = [
    "BEARING_SIDE", "DEFAULT_COLUMNS", "FRAME", "KELVIN", "LIMIT", "MILLIAMPERE", "PLAUSIBLE", "TEMPERATURE", "NodeRole",
    "OtherUnit", "Plausible", "Role", "STATOR_IRON", "TEMP_PREFIX", "UNIT_SHARE", "UNIT_SPELLINGS", "parse_role",
    "temperature_name", "temperature_problems", "unit_problem", "NETWORK_UNITS", "scaled_unit",
]
