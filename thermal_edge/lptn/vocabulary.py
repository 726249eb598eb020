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
from enum import StrEnum


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
    "BEARING_SIDE", "DEFAULT_COLUMNS", "FRAME", "NodeRole", "Role", "STATOR_IRON", "TEMP_PREFIX", "parse_role",
    "temperature_name",
]
