"""Bus configuration and construction of the python-can bus.

``udp_multicast`` is opened as :class:`~thermal_edge.bus.udp.LocalUdpMulticastBus`: hop limit 0,
bound to the group, sent on the loopback interface, taking only datagrams whose source is an
address of this host (on whichever interface they arrive: a stock python-can bus of this host
sends through the default one), so nothing leaves this host and nothing from beyond it is
received. The channel must be a multicast group.

A configuration is checked completely before anything is opened: an unknown key (named with
the closest valid one), an interface python-can does not offer, a wrong type. The python-can
keyword arguments of the chosen interface's bus class (``port``, ``fd``, ``preserve_timestamps``
...) may be given next to the known keys; anything else goes under ``options:``, passed to
``can.Bus`` unchecked.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import inspect
import ipaddress
import logging
import socket
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import can
import can.interfaces

from ..errors import ThermalEdgeError
from .logs import DEFAULT_KEEP, DEFAULT_MAX_BYTES, LogFormatError, check_recording
from .udp import IPV6_REFUSED, RECEIVE_QUEUE_BYTES, LocalUdpMulticastBus, enlarge_receive_queue

__all__ = [
    "DEFAULT_UDP_MULTICAST_GROUP",
    "DEFAULT_UDP_MULTICAST_PORT",
    "DEFAULT_VIRTUAL_CHANNEL",
    "RECEIVE_QUEUE_BYTES",
    "BusConfig",
    "BusConfigError",
    "bus_kwargs",
    "create_bus",
    "enlarge_receive_queue",
    "interface_keywords",
]

log = logging.getLogger(__name__)

#: python-can's default IPv4 group for ``udp_multicast`` (administratively scoped 239/8); only
#: IPv4 groups are taken (:data:`thermal_edge.bus.udp.IPV6_REFUSED` says why).
DEFAULT_UDP_MULTICAST_GROUP = can.interfaces.udp_multicast.UdpMulticastBus.DEFAULT_GROUP_IPv4
#: python-can's default UDP port for ``udp_multicast``.
DEFAULT_UDP_MULTICAST_PORT = 43113
#: Channel name used for the in-process ``virtual`` interface when none is given.
DEFAULT_VIRTUAL_CHANNEL = "thermal_edge"

_NO_BITRATE_INTERFACES = frozenset({"virtual", "udp_multicast"})
#: Bus classes of this package that replace python-can's for an interface name.
_OWN_BUS_CLASSES: dict[str, type[can.BusABC]] = {"udp_multicast": LocalUdpMulticastBus}


class BusConfigError(ThermalEdgeError, ValueError):
    """The bus configuration is invalid.

    Attributes
    ----------
    key : str
        Dotted path of the offending key (``"bus.chanel"``), for a loader to prefix its file name.
    """

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key


def _did_you_mean(word: str, candidates: Iterable[str]) -> str:
    close = difflib.get_close_matches(word, sorted(candidates), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


@functools.cache
def interface_keywords(interface: str) -> frozenset[str]:
    """Named keyword arguments of the bus class of a python-can interface.

    Parameters
    ----------
    interface : str
        python-can interface name (``"socketcan"``, ``"udp_multicast"`` ...).

    Returns
    -------
    frozenset of str
        Parameter names of the class's ``__init__`` (``**kwargs`` excluded); empty if the
        class cannot be imported here (a vendor driver missing): then only ``options:`` passes
        arguments to it.
    """
    cls = _OWN_BUS_CLASSES.get(interface)
    if cls is None:
        try:
            module, name = can.interfaces.BACKENDS[interface]
            cls = getattr(importlib.import_module(module), name)
        except Exception:
            return frozenset()
    params = inspect.signature(cls.__init__).parameters.values()
    return frozenset(p.name for p in params
                     if p.name != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL))


@dataclass
class BusConfig:
    """How to reach the CAN bus.

    Attributes
    ----------
    interface : str
        python-can interface (one of ``can.interfaces.VALID_INTERFACES``): ``"socketcan"``
        on the drive, ``"virtual"`` (one process) or ``"udp_multicast"`` (several processes
        on this host) in tests.
    channel : str or int or None
        Interface channel (``"can0"``, a virtual bus name, a multicast group).
        None picks a default per interface.
    bitrate : int or None
        Bit rate in bit/s (ignored by ``virtual`` and ``udp_multicast``).
    node : str or None
        This node's name in the DBC (``"TE"`` for the service, ``"INV"`` for an
        inverter emulator). Received frames that this node itself transmits are
        ignored as own echoes (``udp_multicast`` loops them back), and on interfaces that
        filter in the kernel (SocketCAN) only the frames this node receives are let in.
        None: keep all.
    record_path : str or Path or None
        If set, all RX and TX traffic is recorded to this CAN log, in the format of its suffix
        (``.log`` candump -L, ``.asc``, ``.blf``, ... see :mod:`thermal_edge.bus.logs`).
    record_channel : str
        Interface name written into the recorded log lines.
    record_max_bytes : int
        Rotate the recording at this size, bytes (0: never); closed text files are gzipped.
    record_keep : int
        Rotated recordings kept besides the one being written (the oldest are deleted).
    send_timeout_s : float
        Time a send may block, in s.
    reconnect_min_s, reconnect_max_s : float
        Backoff between reconnection attempts, in s (doubles up to the maximum).
    options : dict
        Further keyword arguments for ``can.Bus``: the interface's own ones given next to the
        known keys, plus everything under ``options:`` (passed unchecked).
    """

    interface: str = "virtual"
    channel: str | int | None = None
    bitrate: int | None = 500_000
    node: str | None = "TE"
    record_path: str | Path | None = None
    record_channel: str = "can0"
    record_max_bytes: int = DEFAULT_MAX_BYTES
    record_keep: int = DEFAULT_KEEP
    send_timeout_s: float = 0.05
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.interface, str) or not self.interface:
            raise BusConfigError("bus.interface", f"expected a python-can interface name, got {self.interface!r}")
        if self.interface not in can.interfaces.VALID_INTERFACES:
            raise BusConfigError(
                "bus.interface",
                f"unknown python-can interface {self.interface!r}"
                f"{_did_you_mean(self.interface, can.interfaces.VALID_INTERFACES)}; python-can offers "
                + ", ".join(sorted(can.interfaces.VALID_INTERFACES)),
            )
        if self.bitrate is not None and (
            isinstance(self.bitrate, bool) or not isinstance(self.bitrate, int) or self.bitrate <= 0
        ):
            raise BusConfigError("bus.bitrate", f"expected a positive integer (bit/s), got {self.bitrate!r}")
        for name in ("send_timeout_s", "reconnect_min_s", "reconnect_max_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0:
                raise BusConfigError(f"bus.{name}", f"expected a positive number of seconds, got {value!r}")
        for name in ("record_max_bytes", "record_keep"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise BusConfigError(f"bus.{name}", f"expected a whole number >= 0, got {value!r}")
        if self.record_path is not None:
            try:
                check_recording(self.record_path, self.record_max_bytes)
            except LogFormatError as exc:
                raise BusConfigError("bus.record_path", str(exc)) from None
        if self.reconnect_max_s < self.reconnect_min_s:
            raise BusConfigError("bus.reconnect_max_s", "must not be below bus.reconnect_min_s")
        if not isinstance(self.options, Mapping):
            raise BusConfigError("bus.options", f"expected a mapping, got {type(self.options).__name__}")
        self.options = dict(self.options)
        if self.interface == "udp_multicast" and self.channel is not None:
            _check_multicast_group(self.channel)  # at load, not only when the bus opens

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> BusConfig:
        """Build from a configuration mapping (e.g. the ``bus:`` section of a YAML file).

        Known keys fill the fields; the named keyword arguments of the interface's bus class
        (see :func:`interface_keywords`) and the entries of ``options`` go to :attr:`options`.

        Raises
        ------
        BusConfigError
            Any other key (named, with the closest valid key), or an invalid value.
        """
        if not isinstance(mapping, Mapping):
            raise BusConfigError("bus", f"expected a mapping, got {type(mapping).__name__}")
        known = {f.name for f in fields(cls)} - {"options"}
        interface = mapping.get("interface", cls.interface)
        if isinstance(interface, str) and interface not in can.interfaces.VALID_INTERFACES:
            cls(interface=interface)  # raises the interface error before any key error
        shorthand = interface_keywords(interface) - known if isinstance(interface, str) else frozenset()
        for key in mapping:
            if key not in known and key not in shorthand and key != "options":
                raise BusConfigError(
                    f"bus.{key}",
                    f"unknown key '{key}' under bus:{_did_you_mean(str(key), known | shorthand | {'options'})}"
                    " (keyword arguments of other python-can interfaces go under bus.options)",
                )
        extra = mapping.get("options") or {}
        if not isinstance(extra, Mapping):
            raise BusConfigError("bus.options", f"expected a mapping, got {type(extra).__name__}")
        options = {k: v for k, v in mapping.items() if k in shorthand}
        clash = set(options) & set(extra)
        if clash:
            key = sorted(clash)[0]
            raise BusConfigError(f"bus.options.{key}", "given twice, under bus: and under bus.options:")
        return cls(**{k: v for k, v in mapping.items() if k in known}, options={**options, **extra})

    @classmethod
    def coerce(cls, config: BusConfig | Mapping[str, Any]) -> BusConfig:
        """Return ``config`` itself if it is a :class:`BusConfig`, else :meth:`from_mapping` of it."""
        return config if isinstance(config, BusConfig) else cls.from_mapping(config)


def _check_multicast_group(channel: Any) -> str:
    try:
        address = ipaddress.ip_address(str(channel))
    except ValueError:
        raise BusConfigError("bus.channel", f"{channel!r} is not an IP multicast group address") from None
    if not address.is_multicast:
        raise BusConfigError(
            "bus.channel", f"{channel} is not a multicast group (udp_multicast only sends to groups on this host)"
        )
    if address.version == 6:
        raise BusConfigError("bus.channel", f"{address} is an IPv6 group; udp_multicast takes an IPv4 group "
                             f"(e.g. {DEFAULT_UDP_MULTICAST_GROUP}): {IPV6_REFUSED}")
    return str(address)


def bus_kwargs(config: BusConfig | Mapping[str, Any]) -> dict[str, Any]:
    """Keyword arguments for ``can.Bus`` from a configuration (pure, no I/O).

    Parameters
    ----------
    config : BusConfig or mapping
        The bus configuration.

    Returns
    -------
    dict
        ``interface``, ``channel``, ``bitrate`` (where meaningful) and the
        options. For ``udp_multicast``: ``hop_limit`` is always 0, the channel is
        checked to be a multicast group (default :data:`DEFAULT_UDP_MULTICAST_GROUP`),
        ``port`` defaults to python-can's.

    Raises
    ------
    BusConfigError
        Invalid configuration.
    """
    cfg = BusConfig.coerce(config)
    kwargs: dict[str, Any] = dict(cfg.options)
    kwargs["interface"] = cfg.interface
    channel = cfg.channel
    if cfg.interface == "udp_multicast":
        channel = _check_multicast_group(channel if channel is not None else DEFAULT_UDP_MULTICAST_GROUP)
        requested = kwargs.get("hop_limit", 0)
        if requested != 0:
            log.warning("bus.hop_limit=%r ignored: udp_multicast always uses hop_limit=0 (stays on this host)", requested)
        kwargs["hop_limit"] = 0
        kwargs.setdefault("port", DEFAULT_UDP_MULTICAST_PORT)
    elif cfg.interface == "virtual" and channel is None:
        channel = DEFAULT_VIRTUAL_CHANNEL
    if channel is not None:
        kwargs["channel"] = channel
    if cfg.bitrate is not None and cfg.interface not in _NO_BITRATE_INTERFACES:
        kwargs["bitrate"] = cfg.bitrate
    return kwargs


def create_bus(config: BusConfig | Mapping[str, Any]) -> can.BusABC:
    """Open a python-can bus for a configuration.

    Parameters
    ----------
    config : BusConfig or mapping
        The bus configuration (see :func:`bus_kwargs` for what is forced).

    Returns
    -------
    can.BusABC
        The open bus; the caller shuts it down. ``udp_multicast`` is a
        :class:`~thermal_edge.bus.udp.LocalUdpMulticastBus` (this host only, a 4 MiB receive
        buffer so that short stalls of the receiver drop nothing). With ``preserve_timestamps:
        true`` (``virtual``, ``udp_multicast``) the receiver keeps the sender's timestamps: how
        simulated time travels with the frames of the emulator and the service.

    Raises
    ------
    BusConfigError
        Invalid configuration.
    can.CanError, OSError
        The interface could not be opened.
    """
    kwargs = bus_kwargs(config)
    own = _OWN_BUS_CLASSES.get(kwargs["interface"])
    if own is not None:
        bus: can.BusABC = own(**{k: v for k, v in kwargs.items() if k != "interface"})
    else:
        bus = can.Bus(**kwargs)
    if kwargs["interface"] == "udp_multicast":
        assert isinstance(bus, LocalUdpMulticastBus)  # _OWN_BUS_CLASSES opens it
        _assert_hop_limit_zero(bus)
    elif kwargs["interface"] == "socketcan":
        sock = getattr(bus, "socket", None)
        if sock is not None:  # None: python-can internals changed; the default queue stays
            enlarge_receive_queue(sock)
    return bus


def _assert_hop_limit_zero(bus: LocalUdpMulticastBus) -> None:
    """Double-check on the socket itself that nothing can leave the host."""
    hops = bus.socket.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)
    if hops != 0:
        bus.shutdown()
        raise can.CanInitializationError(f"udp_multicast socket has hop limit {hops}, refusing to use it")
