"""``udp_multicast`` kept on this host: python-can's wire format, frames from this host only.

python-can's ``UdpMulticastBus`` binds its socket to the wildcard address and joins the group
on the default interface (eth0), so unicast datagrams to 127.0.0.1 or to the host's own
address, and multicasts from the network, are all taken as CAN frames. :class:`LocalUdpMulticastBus`
speaks the same datagrams (msgpack, see ``can.interfaces.udp_multicast.utils``) but

- binds to the group address itself: a unicast datagram to any address of the host never
  reaches it;
- sends through the loopback interface with hop limit (TTL) 0 and multicast loop on: nothing it
  sends leaves the host;
- takes a datagram as a frame only if its **source address is one of this host's own
  addresses**, on whichever local interface it arrives. A stock python-can ``udp_multicast`` bus
  on this host (``python -m can.player``, a user's script, with ``hop_limit=0``) sends through
  the default interface, and the kernel loops its datagrams back *on that interface* with that
  interface's address as source: to hear it, an IPv4 group is joined on every interface that
  has an IPv4 address, and the source check keeps everything else out. Linux drops a packet
  from the network that claims one of this host's addresses as its source (a "martian source";
  unless ``net.ipv4.conf.*.accept_local`` is set), so the source address tells a sender of this
  host from one beyond it. A refused datagram is counted (:attr:`LocalUdpMulticastBus.refused`),
  not raised. Interfaces that appear after the bus opened are not joined.

Another interface is sent through only if the configuration names it (``multicast_interface``).
The group is an IPv4 one (:data:`IPV6_REFUSED` says why an IPv6 group is refused at open).
"""

from __future__ import annotations

import fcntl
import ipaddress
import logging
import select
import socket
import struct
import time
from typing import Any

import can
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import is_msgpack_installed, unpack_message

__all__ = ["IPV6_REFUSED", "LOOPBACK_INTERFACE", "RECEIVE_QUEUE_BYTES", "LocalUdpMulticastBus", "UndecodableDatagram",
           "enlarge_receive_queue", "is_own_address"]

log = logging.getLogger(__name__)

#: Interface the group is joined on and sent through unless configured otherwise.
LOOPBACK_INTERFACE = "lo"
#: Why an IPv6 group is refused: what keeps the bus on this host works for IPv4 only.
IPV6_REFUSED = ("Linux's loopback interface carries no IPv6 multicast, and python-can's own udp_multicast senders "
                "on this host (can.player, scripts) reach the service only over IPv4, whose group is joined on every "
                "interface with the sources checked to be this host's")
#: Largest datagram read (python-can's own buffer size); longer ones are truncated and undecodable.
MAX_DATAGRAM_BYTES = 4096
# Linux socket options missing from Python's socket module
_IP_MULTICAST_ALL = 49
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@ll")
#: ``struct ip_mreqn``: group, local address (any), interface index
_IP_MREQN = struct.Struct("@4s4si")
#: How long a source address judged own or foreign is believed before it is looked up again, s
#: (an address the host gains or loses, e.g. by DHCP, is seen within this long).
_SOURCE_VERDICT_S = 10.0
#: Least time between two warnings about refused datagrams, s (the count is exact).
_REFUSED_WARN_INTERVAL_S = 10.0


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


class UndecodableDatagram(can.CanOperationError):
    """One received datagram is not a python-can message; the socket itself is fine."""


class _LoopbackMulticastSocket:
    """The socket of one :class:`LocalUdpMulticastBus` (send and receive, kernel timestamps)."""

    def __init__(self, group: str, port: int, interface: str, rcvbuf_bytes: int) -> None:
        try:
            address = ipaddress.ip_address(group)
        except ValueError:
            raise can.CanInitializationError(f"udp_multicast: {group!r} is not an IP multicast group address") from None
        if address.version == 6:
            raise can.CanInitializationError(f"udp_multicast: {address} is an IPv6 group; an IPv4 group is needed "
                                             f"(e.g. {UdpMulticastBus.DEFAULT_GROUP_IPv4}): {IPV6_REFUSED}")
        self.group, self.port = str(address), int(port)
        family = socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            if rcvbuf_bytes:
                enlarge_receive_queue(sock, rcvbuf_bytes)
            group_bin = socket.inet_pton(family, self.group)
            if_addr = _ipv4_of_interface(interface)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(if_addr))
            sock.setsockopt(socket.IPPROTO_IP, _IP_MULTICAST_ALL, 0)
            sock.bind((self.group, self.port))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, group_bin + socket.inet_aton(if_addr))
            self.joined = [interface, *_join_other_interfaces(sock, group_bin, interface)]
            self._destination: tuple[Any, ...] = (self.group, self.port)
        except OSError as exc:
            sock.close()
            raise can.CanInitializationError(
                f"udp_multicast: cannot open group {self.group} port {self.port} on {interface}: {exc}"
            ) from exc
        self.family = family
        self.sock = sock
        self._ancillary = socket.CMSG_SPACE(_TIMESPEC.size)

    def send(self, data: bytes, timeout: float | None) -> None:
        """Send one datagram, waiting up to ``timeout`` s (None: as long as it takes) while the
        socket's send buffer is full (a burst on loopback fills it until the kernel delivers)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                sent = self.sock.sendto(data, socket.MSG_DONTWAIT, self._destination)
                break
            except BlockingIOError:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise can.CanTimeoutError("udp_multicast send buffer full") from None
                select.select([], [self.sock], [], left)
            except OSError as exc:
                raise can.CanOperationError(f"udp_multicast send failed: {exc}") from exc
        if sent < len(data):
            raise can.CanTimeoutError("udp_multicast datagram sent in part")

    def recv(self) -> tuple[bytes, float, str] | None:
        """One datagram, its kernel receive time (s) and its source address; None if none is
        waiting (never blocks)."""
        try:
            data, ancillary, _flags, addr = self.sock.recvmsg(MAX_DATAGRAM_BYTES, self._ancillary, socket.MSG_DONTWAIT)
        except (BlockingIOError, InterruptedError):
            return None
        source = str(addr[0]) if addr else ""
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
                sec, nsec = _TIMESPEC.unpack_from(payload)
                return data, sec + nsec * 1e-9, source
        return data, time.time(), source

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError as exc:
            log.debug("udp_multicast close: %s", exc)


def _ipv4_of_interface(name: str) -> str:
    """IPv4 address of a network interface (127.0.0.1 for ``lo``)."""
    if name == LOOPBACK_INTERFACE:
        return "127.0.0.1"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            packed = fcntl.ioctl(s.fileno(), 0x8915, struct.pack("256s", name.encode()[:15]))  # SIOCGIFADDR
        except OSError as exc:
            raise OSError(exc.errno, f"interface {name!r} has no IPv4 address") from None
    return socket.inet_ntoa(packed[20:24])


def _join_other_interfaces(sock: socket.socket, group_bin: bytes, joined: str) -> list[str]:
    """Join an IPv4 group on every interface but ``joined`` that takes it (up, multicast, an IPv4
    address); the names of those joined. An interface that refuses is skipped: nothing of this
    host sends through it."""
    out = []
    for index, name in socket.if_nameindex():
        if name == joined:
            continue
        try:
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, _IP_MREQN.pack(group_bin, bytes(4), index))
        except OSError as exc:
            log.debug("udp_multicast: group not joined on %s: %s", name, exc)
            continue
        out.append(name)
    return out


def is_own_address(address: str) -> bool:
    """True if ``address`` is one of this host's own IP addresses.

    A loopback address always is. For any other, the kernel's route to it decides: the route to
    an address of this host is a local one whose preferred source is the address itself, while a
    route to any other host has one of this host's addresses as source (``connect`` on a UDP
    socket looks the route up and sends nothing).

    Parameters
    ----------
    address : str
        IPv4 or IPv6 address (an IPv6 one may carry ``%scope``).

    Returns
    -------
    bool
    """
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])
    except ValueError:
        return False
    if ip.is_loopback:
        return True
    if ip.is_multicast or ip.is_unspecified:
        return False
    family = socket.AF_INET6 if ip.version == 6 else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as probe:
            target = socket.getaddrinfo(address, 9, family, socket.SOCK_DGRAM, 0, socket.AI_NUMERICHOST)[0][4]
            probe.connect(target)
            source = probe.getsockname()[0]
    except OSError:  # no route: not an address of this host
        return False
    return bool(ipaddress.ip_address(str(source).split("%", 1)[0]) == ip)


class _SourceCheck:
    """:func:`is_own_address` with its verdicts remembered for :data:`_SOURCE_VERDICT_S`."""

    def __init__(self) -> None:
        self._verdicts: dict[str, tuple[bool, float]] = {}

    def __call__(self, address: str) -> bool:
        now = time.monotonic()
        verdict = self._verdicts.get(address)
        if verdict is None or now - verdict[1] > _SOURCE_VERDICT_S:
            if len(self._verdicts) > 1024:  # a flood of forged sources must not grow it without bound
                self._verdicts.clear()
            verdict = (is_own_address(address), now)
            self._verdicts[address] = verdict
        return verdict[0]


class LocalUdpMulticastBus(UdpMulticastBus):
    """python-can ``udp_multicast`` that only talks to processes of this host.

    Parameters
    ----------
    channel : str
        IPv4 multicast group (``224.0.0.0/4``; an IPv6 group is refused: :data:`IPV6_REFUSED`).
    port : int
        UDP port.
    hop_limit : int
        Must be 0 (accepted for python-can compatibility; anything else is refused).
    fd : bool
        Accept CAN FD messages (python-can's meaning).
    preserve_timestamps : bool
        Keep the sender's message timestamp (simulated time travels with the frames);
        otherwise the kernel's receive time (s, POSIX) is the timestamp.
    rcvbuf_bytes : int
        Kernel receive queue asked for, bytes (0 keeps the system default).
    multicast_interface : str
        Interface sent through (default ``lo``: this host only). The group is joined on it and on
        every other interface too, for the datagrams of this host's own addresses that the kernel
        loops back there (all others are refused).
    **kwargs
        Passed to ``can.BusABC`` (``can_filters`` ...).

    Notes
    -----
    A datagram that is not a python-can message raises :class:`UndecodableDatagram` from
    ``recv`` (the datagram is consumed; the next ``recv`` goes on); errors of the socket itself
    raise ``can.CanOperationError`` with the ``OSError`` as cause.
    """

    # in place of python-can's socket wrapper, whose send() the inherited send() calls: the same
    # call, so a duck type, not a subclass of that class
    _multicast: _LoopbackMulticastSocket  # type: ignore[assignment]

    def __init__(
        self,
        channel: str = UdpMulticastBus.DEFAULT_GROUP_IPv4,
        port: int = 43113,
        hop_limit: int = 0,
        receive_own_messages: bool = False,
        fd: bool = True,
        *,
        preserve_timestamps: bool = False,
        rcvbuf_bytes: int = RECEIVE_QUEUE_BYTES,
        multicast_interface: str = LOOPBACK_INTERFACE,
        **kwargs: Any,
    ) -> None:
        is_msgpack_installed()
        if receive_own_messages:
            raise can.CanInterfaceNotImplementedError("receiving own messages is not implemented")
        if hop_limit != 0:
            raise can.CanInitializationError(f"udp_multicast: hop_limit {hop_limit} refused, only 0 (this host)")
        # the socket first: a bus whose socket cannot open never was a bus (no shutdown warning)
        self._multicast = _LoopbackMulticastSocket(str(channel), port, multicast_interface, rcvbuf_bytes)
        try:
            can.BusABC.__init__(self, channel, **kwargs)
        except Exception:
            self._multicast.close()
            raise
        self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20
        self.preserve_timestamps = bool(preserve_timestamps)
        self.multicast_interface = multicast_interface
        self.channel_info = f"udp_multicast {self._multicast.group}:{port} on {multicast_interface}"
        #: Datagrams refused because their source is not an address of this host.
        self.refused = 0
        self._own_source = _SourceCheck()
        self._refused_warned_at = -float("inf")

    @property
    def socket(self) -> socket.socket:
        """The UDP socket (for checks of its options)."""
        return self._multicast.sock

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if timeout is None or timeout > 0:
            try:
                ready, _, _ = select.select([self._multicast.sock], [], [], timeout)
            except (OSError, ValueError) as exc:  # closed socket (fd -1) or interface gone
                raise can.CanOperationError(f"udp_multicast wait failed: {exc}") from OSError(str(exc))
            if not ready:
                return None, False
        try:
            got = self._multicast.recv()
        except OSError as exc:
            raise can.CanOperationError(f"udp_multicast receive failed: {exc}") from exc
        if got is None:
            return None, False
        data, kernel_ts, source = got
        if not self._own_source(source):
            self.refused += 1
            now = time.monotonic()
            if now - self._refused_warned_at >= _REFUSED_WARN_INTERVAL_S:
                self._refused_warned_at = now
                log.warning("udp_multicast: datagram from %s refused: not an address of this host (%d refused so far)",
                            source or "an unknown source", self.refused)
            return None, False
        try:
            msg = unpack_message(data, check=True)
        except Exception as exc:
            raise UndecodableDatagram(f"undecodable datagram ({len(data)} bytes): {type(exc).__name__}: {exc}") from None
        if not (self.preserve_timestamps and msg.timestamp):
            msg.timestamp = kernel_ts
        if self._can_protocol is not can.CanProtocol.CAN_FD and msg.is_fd:
            return None, False
        return msg, False

    def fileno(self) -> int:
        return self._multicast.sock.fileno()

    def shutdown(self) -> None:
        can.BusABC.shutdown(self)
        self._multicast.close()
