"""Ports kept for this test process (tests of every directory import it)."""
from __future__ import annotations

import socket

#: the sockets holding the ports handed out, open until the process ends
_HELD: list[socket.socket] = []


def _own_port(kind: socket.SocketKind) -> int:
    s = socket.socket(socket.AF_INET, kind)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind(("127.0.0.1", 0))
    _HELD.append(s)
    return int(s.getsockname()[1])


def own_udp_port() -> int:
    """A UDP port that no other process gets while this one runs.

    A port found free and let go may be handed out again at once to another process that binds
    port 0: another xdist worker, or a second suite running beside this one, whose
    ``udp_multicast`` traffic would then reach this test's buses. So the port stays bound on
    127.0.0.1 with ``SO_REUSEADDR`` until the process ends: the kernel never picks it for a bind
    to port 0 (those set no ``SO_REUSEADDR``), while the ``udp_multicast`` buses of this test and
    of the processes it starts (they all set it) open it freely. Nothing is sent to 127.0.0.1
    on it.
    """
    return _own_port(socket.SOCK_DGRAM)


def own_tcp_port() -> int:
    """A TCP port on 127.0.0.1 for a server this test starts, no other process's while this one runs.

    Held as :func:`own_udp_port` holds its port, bound and never listening: a server that sets
    ``SO_REUSEADDR`` (the service's metrics endpoint does) binds and listens on it, nobody else
    can bind it, and the kernel picks it neither for a bind to port 0 nor for an outgoing
    connection.
    """
    return _own_port(socket.SOCK_STREAM)
