"""The ``udp_multicast`` bus of ``create_bus`` takes frames from this host only.

python-can's own bus binds 0.0.0.0 and joins the group on eth0: unicast datagrams to 127.0.0.1
and to the host's own address, and multicasts from the network, are all taken as CAN frames.
Here unicasts are sent in python-can's wire format and none may be received; a multicast whose
source is not an address of this host is refused and counted; while a frame from a second bus
of this host is received, on whichever interface it arrives (python-can's own bus sends through
the default one).
"""

from __future__ import annotations

import socket
import time

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


def _received(bus: can.BusABC, expect: int = 0, within_s: float = 0.3) -> list[can.Message]:
    """The messages waiting for ``bus``: the ``expect`` ones waited for (a generous hang guard: the
    kernel may deliver late on a busy host), then any more that come within ``within_s``."""
    out: list[can.Message] = []
    end = time.monotonic() + 60.0
    while len(out) < expect and time.monotonic() < end:
        if (msg := bus.recv(0.1)) is not None:
            out.append(msg)
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
        got = _received(bus, 1)
        assert len(got) == 1 and got[0].arbitration_id == 0x0A0 and bytes(got[0].data) == bytes(range(8))
    finally:
        bus.shutdown()
        peer.shutdown()


def test_multicast_from_this_host_through_a_network_interface_is_received(udp_port):
    """A multicast that a process of this host sends through eth0 (as python-can's own bus does:
    it sends through the default interface) comes back on eth0 with eth0's address as source:
    a frame of this host, taken."""
    own = _own_address(socket.AF_INET)
    if own is None:
        pytest.skip("this host has no non-loopback IPv4 address")
    bus = create_bus({"interface": "udp_multicast", "port": udp_port})
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(own))
            for _ in range(5):
                s.sendto(pack_message(PROBE), (DEFAULT_UDP_MULTICAST_GROUP, udp_port))
        got = _received(bus, 5)
        assert len(got) == 5 and all(bytes(m.data) == bytes(range(8)) for m in got)
        assert bus.refused == 0
    finally:
        bus.shutdown()


def test_a_stock_python_can_bus_of_this_host_is_heard(udp_port):
    """python-can's own ``udp_multicast`` bus (default interface, hop limit 0) reaches ours."""
    from can.interfaces.udp_multicast import UdpMulticastBus

    bus = create_bus({"interface": "udp_multicast", "port": udp_port})
    stock = UdpMulticastBus(channel=DEFAULT_UDP_MULTICAST_GROUP, port=udp_port, hop_limit=0)
    try:
        for k in range(7):
            stock.send(can.Message(arbitration_id=0x0A0 + k, data=bytes([k] * 8), is_extended_id=False))
        got = _received(bus, 7)
        assert [m.arbitration_id for m in got] == [0x0A0 + k for k in range(7)]
    finally:
        stock.shutdown()
        bus.shutdown()


class _ForgedSocket:
    """Stands in for the bus's socket: hands out datagrams from given source addresses, as the
    kernel would (this test cannot send from an address the host does not have)."""

    def __init__(self, datagrams: list[tuple[bytes, tuple[str, int]]]) -> None:
        self.datagrams = list(datagrams)

    def recvmsg(self, bufsize: int, ancbufsize: int, flags: int = 0):
        if not self.datagrams:
            raise BlockingIOError
        data, addr = self.datagrams.pop(0)
        return data, [], 0, addr


@pytest.mark.parametrize("source", ["198.51.100.7", "192.0.2.1", "203.0.113.9", "2001:db8::7", "fe80::1%lo", "", "garbage"])
def test_a_datagram_from_an_address_of_another_host_is_refused_and_counted(udp_port, source):
    bus = create_bus({"interface": "udp_multicast", "port": udp_port})
    real = bus._multicast.sock
    try:
        own = _own_address(socket.AF_INET)
        if source == "192.0.2.1" and own == source:
            pytest.skip("this host has that address")
        bus._multicast.sock = _ForgedSocket([(pack_message(PROBE), (source, 43113)) for _ in range(3)]
                                            + [(pack_message(PROBE), ("127.0.0.1", 43113))])
        got = [bus.recv(0) for _ in range(4)]
        assert got[:3] == [None, None, None] and bus.refused == 3
        assert got[3] is not None and got[3].arbitration_id == 0x0A0  # from this host: taken
    finally:
        bus._multicast.sock = real
        bus.shutdown()


def test_own_addresses_are_told_from_others_as_the_host_lists_them():
    """:func:`is_own_address` against the host's own list of addresses (``ip -o addr``)."""
    import ipaddress
    import shutil
    import subprocess

    from thermal_edge.bus.udp import is_own_address

    if shutil.which("ip") is None:
        pytest.skip("no ip command to list this host's addresses")
    listed = subprocess.run(["ip", "-o", "addr"], capture_output=True, text=True, check=True).stdout.split()
    own = [w.split("/")[0] for i, w in enumerate(listed) if i and listed[i - 1] in ("inet", "inet6")]
    own = [a for a in own if not ipaddress.ip_address(a).is_link_local]  # need a scope to be named
    assert own
    for address in own:
        assert is_own_address(address), address
    networks = [ipaddress.ip_interface(w) for i, w in enumerate(listed) if i and listed[i - 1] == "inet"]
    for net in networks:  # other hosts of this host's own networks (all of 127/8 is this host's), and beyond
        if net.ip.is_loopback:
            continue
        for other in list(net.network.hosts())[:4]:
            assert is_own_address(str(other)) == (str(other) in own), other
    for other in ("198.51.100.7", "8.8.8.8", "2001:db8::7", "224.0.0.1", "0.0.0.0", "not an address"):
        assert not is_own_address(other), other
    assert is_own_address("127.0.0.1") and is_own_address("127.3.4.5") and is_own_address("::1")


#: IPv6 groups of every scope: interface-local, link-local (python-can's example ff02::), site-local,
#: python-can's own default IPv6 group
IPV6_GROUPS = ("ff01::1:2", "ff02::1:3", "ff05::1:3", "ff15::7468:6572",
               can.interfaces.udp_multicast.UdpMulticastBus.DEFAULT_GROUP_IPv6)


@pytest.mark.parametrize("group", IPV6_GROUPS)
def test_an_ipv6_group_is_refused_with_the_reason(group: str, udp_port: int) -> None:
    """What keeps the bus on this host (the loopback interface, the IPv4 group joined everywhere
    with the sources checked) works for IPv4 only: an IPv6 group is refused, in the configuration
    (the key named) and by the bus class itself, before any socket is bound."""
    from thermal_edge.bus import BusConfig, BusConfigError, LocalUdpMulticastBus

    with pytest.raises(BusConfigError) as info:
        BusConfig.from_mapping({"interface": "udp_multicast", "channel": group, "port": udp_port})
    text = str(info.value)
    assert "bus.channel" in text and "IPv6 group" in text and DEFAULT_UDP_MULTICAST_GROUP in text and "\n" not in text
    with pytest.raises(can.CanInitializationError, match="IPv6 group; an IPv4 group is needed"):
        LocalUdpMulticastBus(group, udp_port)
    with pytest.raises(BusConfigError, match="IPv6 group"):
        create_bus({"interface": "udp_multicast", "channel": group, "port": udp_port, "hop_limit": 0})
    # nothing was left bound: the same port opens for an IPv4 group at once
    bus = LocalUdpMulticastBus(DEFAULT_UDP_MULTICAST_GROUP, udp_port)
    bus.shutdown()


def test_the_ipv4_group_stays_on_this_host(udp_port: int) -> None:
    """The IPv4 bus: hop limit 0, sent through ``lo``, joined on ``lo`` first."""
    bus = create_bus({"interface": "udp_multicast", "channel": DEFAULT_UDP_MULTICAST_GROUP, "port": udp_port})
    try:
        assert bus.socket.family == socket.AF_INET
        assert bus.socket.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0
        assert bus.socket.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF) == 0x0100007F  # 127.0.0.1
        assert bus._multicast.joined[0] == "lo"
    finally:
        bus.shutdown()

