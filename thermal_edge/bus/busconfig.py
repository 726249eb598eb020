"""Bus configuration and construction of the python-can bus.

``udp_multicast`` always gets ``hop_limit=0`` (IPv6 hop limit / IPv4 TTL),
whatever the configuration says: with it the kernel loops every datagram back
to the sockets of this host and sends nothing out of any interface. The channel
must be a multicast group, so a unicast address off this machine can never be
configured.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import can

__all__ = [
    "DEFAULT_UDP_MULTICAST_GROUP",
    "DEFAULT_UDP_MULTICAST_PORT",
    "DEFAULT_VIRTUAL_CHANNEL",
    "BusConfig",
    "BusConfigError",
    "bus_kwargs",
    "create_bus",
]

log = logging.getLogger(__name__)

#: python-can's default group for ``udp_multicast`` (IPv6, site-local scope
#: ff15::/16, not link-local); with hop limit 0 it stays on this host.
DEFAULT_UDP_MULTICAST_GROUP = "ff15:7079:7468:6f6e:6465:6d6f:6d63:6173"
#: python-can's default UDP port for ``udp_multicast``.
DEFAULT_UDP_MULTICAST_PORT = 43113
#: Channel name used for the in-process ``virtual`` interface when none is given.
DEFAULT_VIRTUAL_CHANNEL = "thermal_edge"

_NO_BITRATE_INTERFACES = frozenset({"virtual", "udp_multicast"})


class BusConfigError(ValueError):
    """The bus configuration is invalid (names the offending key)."""


@dataclass
class BusConfig:
    """How to reach the CAN bus.

    Attributes
    ----------
    interface : str
        python-can interface: ``"socketcan"`` on the drive, ``"virtual"`` (one
        process) or ``"udp_multicast"`` (several processes on this host) in tests.
    channel : str or int or None
        Interface channel (``"can0"``, a virtual bus name, a multicast group).
        None picks a default per interface.
    bitrate : int or None
        Bit rate in bit/s (ignored by ``virtual`` and ``udp_multicast``).
    node : str or None
        This node's name in the DBC (``"TE"`` for the service, ``"INV"`` for an
        inverter emulator). Received frames that this node itself transmits are
        ignored as own echoes (``udp_multicast`` loops them back). None: keep all.
    record_path : str or Path or None
        If set, all RX and TX traffic is recorded to this ``candump -L`` file.
    record_channel : str
        Interface name written into the recorded log lines.
    send_timeout_s : float
        Time a send may block, in s.
    reconnect_min_s, reconnect_max_s : float
        Backoff between reconnection attempts, in s (doubles up to the maximum).
    options : dict
        Further keyword arguments for ``can.Bus`` (e.g. ``port``, ``fd``).
    """

    interface: str = "virtual"
    channel: str | int | None = None
    bitrate: int | None = 500_000
    node: str | None = "TE"
    record_path: str | Path | None = None
    record_channel: str = "can0"
    send_timeout_s: float = 0.05
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.interface, str) or not self.interface:
            raise BusConfigError(f"bus.interface: expected a python-can interface name, got {self.interface!r}")
        if self.bitrate is not None and (not isinstance(self.bitrate, int) or self.bitrate <= 0):
            raise BusConfigError(f"bus.bitrate: expected a positive integer (bit/s), got {self.bitrate!r}")
        for name in ("send_timeout_s", "reconnect_min_s", "reconnect_max_s"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or value <= 0:
                raise BusConfigError(f"bus.{name}: expected a positive number of seconds, got {value!r}")
        if self.reconnect_max_s < self.reconnect_min_s:
            raise BusConfigError("bus.reconnect_max_s: must not be below bus.reconnect_min_s")
        if not isinstance(self.options, Mapping):
            raise BusConfigError(f"bus.options: expected a mapping, got {type(self.options).__name__}")
        self.options = dict(self.options)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> BusConfig:
        """Build from a configuration mapping (e.g. the ``bus:`` section of a YAML file).

        Known keys fill the fields; ``options`` (or ``kwargs``) and every
        unknown key go to :attr:`options` for ``can.Bus``.
        """
        if not isinstance(mapping, Mapping):
            raise BusConfigError(f"bus: expected a mapping, got {type(mapping).__name__}")
        known = {f.name for f in fields(cls)} - {"options"}
        values = {k: v for k, v in mapping.items() if k in known}
        options: dict[str, Any] = {}
        for key in ("options", "kwargs"):
            extra = mapping.get(key) or {}
            if not isinstance(extra, Mapping):
                raise BusConfigError(f"bus.{key}: expected a mapping, got {type(extra).__name__}")
            options.update(extra)
        options.update({k: v for k, v in mapping.items() if k not in known and k not in ("options", "kwargs")})
        return cls(**values, options=options)

    @classmethod
    def coerce(cls, config: BusConfig | Mapping[str, Any]) -> BusConfig:
        """Return ``config`` itself if it is a :class:`BusConfig`, else :meth:`from_mapping` of it."""
        return config if isinstance(config, BusConfig) else cls.from_mapping(config)


def _check_multicast_group(channel: Any) -> str:
    try:
        address = ipaddress.ip_address(str(channel))
    except ValueError:
        raise BusConfigError(f"bus.channel: {channel!r} is not an IP multicast group address") from None
    if not address.is_multicast:
        raise BusConfigError(
            f"bus.channel: {channel} is not a multicast group (udp_multicast only sends to groups on this host)"
        )
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
        checked to be a multicast group, ``port`` defaults to python-can's.

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
        The open bus; the caller shuts it down.

    Raises
    ------
    BusConfigError
        Invalid configuration.
    can.CanError, OSError
        The interface could not be opened.
    """
    kwargs = bus_kwargs(config)
    bus = can.Bus(**kwargs)
    if kwargs["interface"] == "udp_multicast":
        _assert_hop_limit_zero(bus)
    elif kwargs["interface"] == "socketcan":
        sock = getattr(bus, "socket", None)
        if sock is not None:  # None: python-can internals changed; the default queue stays
            enlarge_receive_queue(sock)
    return bus


#: kernel receive queue asked for, bytes (a CAN frame takes about 1 kB of it on SocketCAN)
RECEIVE_QUEUE_BYTES = 4 << 20


def enlarge_receive_queue(sock: socket.socket, size: int = RECEIVE_QUEUE_BYTES) -> None:
    """Ask for a receive queue of several seconds of a busy bus (the default, ~200 kB, holds
    about one second at 200 frames/s), so that a loop busy for a moment loses no frames.

    ``SO_RCVBUFFORCE`` needs CAP_NET_ADMIN; without it ``SO_RCVBUF`` is capped by
    ``net.core.rmem_max`` (raise that sysctl on the edge computer for the full size).
    """
    for opt in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
        if opt is None:
            continue
        try:
            sock.setsockopt(socket.SOL_SOCKET, opt, int(size))
            return
        except OSError:
            continue


def _assert_hop_limit_zero(bus: can.BusABC) -> None:
    """Double-check on the socket itself that nothing can leave the host."""
    multicast = getattr(bus, "_multicast", None)
    sock = getattr(multicast, "_socket", None)
    if sock is None:  # python-can internals changed; the kwarg was still forced to 0
        return
    if sock.family == socket.AF_INET6:
        hops = sock.getsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS)
    else:
        hops = sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)
    if hops != 0:
        bus.shutdown()
        raise can.CanInitializationError(f"udp_multicast socket has hop limit {hops}, refusing to use it")
