"""A UDP port kept for this test process (tests of every directory import it)."""
from __future__ import annotations

import socket

#: the sockets holding the ports handed out, open until the process ends
_HELD: list[socket.socket] = []


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
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind(("127.0.0.1", 0))
    _HELD.append(s)
    return int(s.getsockname()[1])
