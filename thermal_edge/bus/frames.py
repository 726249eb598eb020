"""Names and enumerations of the thermal_edge CAN matrix (``dbc/thermal_edge.dbc``).

Frame and signal names here are the DBC's; the enumerations mirror its value
tables (a test checks that they agree).
"""

from __future__ import annotations

import enum
from pathlib import Path

__all__ = [
    "COUNTER_SUFFIX",
    "CRC_SUFFIX",
    "DEFAULT_DBC_PATH",
    "INV_AMBIENT_TEMPS",
    "INV_CURRENTS",
    "INV_MECHANICS",
    "INV_STATOR_TEMPS",
    "INV_VOLTAGES",
    "NODE_INVERTER",
    "NODE_THERMAL_EDGE",
    "TE_ESTIMATES",
    "TE_FORECAST",
    "TE_LIMITS",
    "TE_STATUS",
    "TIME_TO_LIMIT_NOT_WITHIN_HORIZON_S",
    "DerateReason",
    "SensorStatus",
    "TeState",
]

#: The DBC shipped inside the package (``<repo>/dbc/thermal_edge.dbc`` links to it).
DEFAULT_DBC_PATH: Path = Path(__file__).resolve().parent / "thermal_edge.dbc"

#: Node names (``BU_``) of the DBC.
NODE_INVERTER = "INV"
NODE_THERMAL_EDGE = "TE"

# inverter -> thermal_edge
INV_CURRENTS = "INV_Currents"  # 0x0A0, 10 ms
INV_MECHANICS = "INV_Mechanics"  # 0x0A1, 10 ms
INV_STATOR_TEMPS = "INV_StatorTemps"  # 0x0B0, 100 ms
INV_AMBIENT_TEMPS = "INV_AmbientTemps"  # 0x0B1, 100 ms
#: optional, appended to the shared matrix (docs/can-matrix-additions.md): the dq voltage references
INV_VOLTAGES = "INV_Voltages"  # 0x2D0, 10 ms
# thermal_edge -> inverter
TE_LIMITS = "TE_Limits"  # 0x2A0, 100 ms
TE_ESTIMATES = "TE_Estimates"  # 0x2B0, 1000 ms
TE_FORECAST = "TE_Forecast"  # 0x2B1, 1000 ms
TE_STATUS = "TE_Status"  # 0x2C0, 1000 ms

#: Every frame's alive counter signal is ``<frame>_Counter`` (bit 48, 4 bits) ...
COUNTER_SUFFIX = "_Counter"
#: ... and its CRC signal ``<frame>_CRC`` (bit 56, 8 bits).
CRC_SUFFIX = "_CRC"

#: TE_TimeToLimit value meaning "no limit reached within the horizon" (s).
TIME_TO_LIMIT_NOT_WITHIN_HORIZON_S = 65535


class SensorStatus(enum.IntEnum):
    """Status of a temperature sensor (``INV_S_*``, 2 bits)."""

    VALID = 0
    OPEN_CIRCUIT = 1
    SHORT_CIRCUIT = 2
    NOT_FITTED = 3


class DerateReason(enum.IntEnum):
    """Why thermal_edge reduces the limits (``TE_DerateReason``, 4 bits)."""

    NONE = 0
    WINDING = 1
    MAGNET = 2
    LOOK_AHEAD = 3
    SENSOR_FAULT = 4
    STALE_INPUT = 5
    MODEL_FAULT = 6
    STARTING = 7
    #: the limit climbs back (rise rate) after a reduction whose cause has gone; appended to the
    #: shared CAN matrix's 0-7 (documented in docs/can-matrix-additions.md)
    RECOVERING = 8


class TeState(enum.IntEnum):
    """State of the thermal_edge service (``TE_State``, 4 bits)."""

    STARTING = 0
    NOMINAL = 1
    ADAPTING = 2
    DEGRADED = 3
    FAULT = 4
