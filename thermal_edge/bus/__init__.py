"""CAN layer of thermal_edge: DBC codec with frame integrity, python-can transport, CAN logs.

Knows ``dbc/thermal_edge.dbc`` (and any other DBC it is given) and nothing of the thermal model.

- :class:`FrameCodec` -- encode (counter + CRC filled) / decode (DLC, CRC, counter
  checked; drops counted in :class:`FrameStats`; never raises).
- :class:`FrameProtection` -- a frame's end-to-end protection: the CAN matrix's counter and CRC,
  another counter or CRC-8 (:data:`CRC8_ALGORITHMS`), or none.
- :class:`CanTransport` -- asyncio receive (batched; a bad message is counted, not a dead
  bus)/transmit/record on one bus, reconnecting.
- :class:`CyclicSender` -- periodic frame from a provider, with fallback values, as an
  asyncio task or in its own thread.
- :class:`BusConfig`, :func:`create_bus` -- python-can bus from a checked configuration
  (unknown keys and interfaces named with the closest valid one).
- :class:`LocalUdpMulticastBus` -- ``udp_multicast`` of this host only, hop limit 0: nothing
  leaves this host, nothing from beyond it is received.
- :class:`LogRecorder`, :class:`FrameLogReader`, :func:`read_log` -- CAN logs in every format
  python-can knows (candump ``.log``, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ``.mf4``), by suffix;
  recordings rotate at a size cap.
- :func:`crc8_sae_j1850`, :func:`frame_crc`, :func:`data_id` -- the frame CRC.
"""

from .busconfig import (
    DEFAULT_UDP_MULTICAST_GROUP,
    DEFAULT_UDP_MULTICAST_PORT,
    BusConfig,
    BusConfigError,
    bus_kwargs,
    create_bus,
)
from .codec import DbcError, DecodedFrame, FrameCodec, FrameEncodeError, ProtectionError
from .crc import CRC8_ALGORITHMS, crc8_sae_j1850, data_id, frame_crc
from .cyclic import CyclicSender
from .frames import (
    DEFAULT_DBC_PATH,
    INV_AMBIENT_TEMPS,
    INV_CURRENTS,
    INV_MECHANICS,
    INV_STATOR_TEMPS,
    INV_VOLTAGES,
    NODE_INVERTER,
    NODE_THERMAL_EDGE,
    TE_ESTIMATES,
    TE_FORECAST,
    TE_LIMITS,
    TE_STATUS,
    TIME_TO_LIMIT_NOT_WITHIN_HORIZON_S,
    DerateReason,
    SensorStatus,
    TeState,
)
from .logs import FrameLogReader, LogFormatError, LogRecorder, log_messages, read_log, readable_suffixes
from .protection import FrameProtection
from .stats import DROP_REASONS, DropReport, FrameStats, TransportStats
from .transport import CanTransport
from .udp import LocalUdpMulticastBus, UndecodableDatagram

__all__ = [
    "CRC8_ALGORITHMS",
    "DEFAULT_DBC_PATH",
    "DEFAULT_UDP_MULTICAST_GROUP",
    "DEFAULT_UDP_MULTICAST_PORT",
    "DROP_REASONS",
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
    "BusConfig",
    "BusConfigError",
    "CanTransport",
    "CyclicSender",
    "DbcError",
    "DecodedFrame",
    "DerateReason",
    "DropReport",
    "FrameCodec",
    "FrameEncodeError",
    "FrameLogReader",
    "FrameProtection",
    "FrameStats",
    "LocalUdpMulticastBus",
    "LogFormatError",
    "LogRecorder",
    "ProtectionError",
    "SensorStatus",
    "TeState",
    "TransportStats",
    "UndecodableDatagram",
    "bus_kwargs",
    "crc8_sae_j1850",
    "create_bus",
    "data_id",
    "frame_crc",
    "log_messages",
    "read_log",
    "readable_suffixes",
]
