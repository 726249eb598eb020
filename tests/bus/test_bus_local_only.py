"""The ``udp_multicast`` bus of ``create_bus`` takes frames from this host only (issue 14, defect 7).

python-can's own bus binds 0.0.0.0 and joins the group on eth0: unicast datagrams to 127.0.0.1
and to the host's own address, and multicasts arriving on eth0, were all taken as CAN frames.
Each of these is sent here in python-can's wire format; none may be received, while a frame
from a second bus of this host is.
"""

from __future__ import annotations

import socket

import can
import pytest
from can.interfaces.udp_multicast.utils import pack_message

from thermal_edge.bus import DEFAULT_UDP_MULTICAST_GROUP, create_bus

PROBE = can.Message(arbitration_id=0x0A0, data=bytes(range(8)), is_extended_id=False)


def _own_address(family: int) -> str | None:
    """This host's non-loopback address of a family (the one its default route would use)."""
    target = ("198.51.100.1", 9) if family == socket.AF_INET else ("2001:db8::1", 9)  # documentation ranges
    with socket.socket(family, socket.SOCK_DGRAM) as s:
        try:
            s.connect(target)  # route lookup only, nothing is sent
        except OSError:
            return None
        address = s.getsockname()[0]
    return None if address in ("0.0.0.0", "::", "127.0.0.1", "::1") else address


def _received(bus: can.BusABC, within_s: float = 0.3) -> list[can.Message]:
    out = []
    while (msg := bus.recv(within_s)) is not None:
        out.append(msg)
    return out


def test_socket_is_bound_to_the_group_on_loopback(udp_port):
    bus = create_bus({"interface": "udp_multicast", "port": udp_port})
    try:
        sock = bus.socket
        assert sock.getsockname() == (DEFAULT_UDP_MULTICAST_GROUP, udp_port)  # not 0.0.0.0
        assert sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0
        assert sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP) == 1
        assert socket.inet_ntoa(sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4)) == "127.0.0.1"
        assert sock.getsockopt(socket.IPPROTO_IP, 49) == 0  # IP_MULTICAST_ALL off: own memberships only
    finally:
        bus.shutdown()


@pytest.mark.parametrize("target", ["127.0.0.1", "own IPv4", "::1", "own IPv6"])
def test_unicast_datagrams_are_not_received(udp_port, target):
    family = socket.AF_INET6 if "6" in target or ":" in target else socket.AF_INET
    address = target if target[0].isdigit() or target.startswith(":") else _own_address(family)
    if address is None:
        pytest.skip(f"this host has no non-loopback {target[4:]} address to send to")
    bus = create_bus({"interface": "udp_multicast", "port": udp_port})
    peer = create_bus({"interface": "udp_multicast", "port": udp_port})
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            for _ in range(5):
                s.sendto(pack_message(PROBE), (address, udp_port))
        assert _received(bus) == [], f"a unicast datagram to {address}:{udp_port} was taken as a CAN frame"
        peer.send(PROBE)  # ... while a frame from this host's bus arrives
        got = _received(bus)
        assert len(got) == 1 and got[0].arbitration_id == 0x0A0 and bytes(got[0].data) == bytes(range(8))
    finally:
        bus.shutdown()
        peer.shutdown()


def test_multicast_arriving_on_a_network_interface_is_not_received(udp_port):
    """A multicast to the group that comes in on eth0 (as one from the network would: sent here
    through eth0 and looped back by the kernel on that interface) is not taken."""
    own = _own_address(socket.AF_INET)
    if own is None:
        pytest.skip("this host has no non-loopback IPv4 address")
    bus = create_bus({"interface": "udp_multicast", "port": udp_port})
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(own))
            # something else on this host listening on eth0, so that the kernel accepts the group there
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as listener:
                listener.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                                    socket.inet_aton(DEFAULT_UDP_MULTICAST_GROUP) + socket.inet_aton(own))
                for _ in range(5):
                    s.sendto(pack_message(PROBE), (DEFAULT_UDP_MULTICAST_GROUP, udp_port))
                assert _received(bus) == []
    finally:
        bus.shutdown()


def test_ipv6_group_needs_a_multicast_route_on_loopback(udp_port):
    """An IPv6 group is kept on ``lo`` too; where ``lo`` has no IPv6 multicast route (Linux's
    default) the bus refuses to open, saying so, instead of failing every send."""
    try:
        bus = create_bus({"interface": "udp_multicast", "channel": "ff15::7468:6572", "port": udp_port})
    except can.CanInitializationError as exc:
        assert "no IPv6 multicast route through lo" in str(exc) and "239.74.163.2" in str(exc)
        return
    try:  # a host whose loopback does carry IPv6 multicast
        assert bus.socket.getsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS) == 0
        assert bus.socket.getsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_IF) == socket.if_nametoindex("lo")
    finally:
        bus.shutdown()
