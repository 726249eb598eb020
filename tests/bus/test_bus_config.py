"""Bus configuration: details python-can leaves to the caller, and a strict ``bus:`` section."""

import can
import pytest
import yaml
from bus_testlib import REPO

from thermal_edge.bus import BusConfig, BusConfigError, bus_kwargs


def test_socketcan_receive_queue_is_enlarged():
    """A SocketCAN bus asks for a multi-second receive queue: as root (CAP_NET_ADMIN) the full
    size, otherwise as much as ``net.core.rmem_max`` allows. Checked on a real socket."""
    import os
    import socket

    from thermal_edge.bus.busconfig import RECEIVE_QUEUE_BYTES, enlarge_receive_queue

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        before = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        enlarge_receive_queue(sock)
        after = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)  # Linux reports twice the request
    rmem_max = int(open("/proc/sys/net/core/rmem_max").read())
    want = RECEIVE_QUEUE_BYTES if os.geteuid() == 0 else min(RECEIVE_QUEUE_BYTES, rmem_max)
    assert after >= want > 0, (before, after, want)


# ------------------------------------------------------- strict bus: section

@pytest.mark.parametrize(
    "mapping, key, message",
    [
        ({"interface": "udp_multicast", "chanel": "239.1.2.3"}, "bus.chanel",
         "unknown key 'chanel' under bus: (did you mean 'channel'?)"),
        ({"interface": "socketcan", "bitrat": 500000}, "bus.bitrat", "(did you mean 'bitrate'?)"),
        ({"interface": "udp_multicast", "prot": 5000}, "bus.prot", "(did you mean 'port'?)"),
        ({"interface": "udp_multicast", "preserve_timestamp": True}, "bus.preserve_timestamp",
         "(did you mean 'preserve_timestamps'?)"),
        ({"interface": "socketcan", "reconect_max_s": 3}, "bus.reconect_max_s", "(did you mean 'reconnect_max_s'?)"),
        ({"interface": "socketcan", "xyz": 1}, "bus.xyz", "unknown key 'xyz' under bus:"),
        ({"interface": "socketcann"}, "bus.interface",
         "unknown python-can interface 'socketcann' (did you mean 'socketcan'?)"),
        ({"interface": "udp-multicast"}, "bus.interface", "(did you mean 'udp_multicast'?)"),
        ({"interface": "virtual", "options": [1]}, "bus.options", "expected a mapping"),
        ({"interface": "udp_multicast", "port": 1, "options": {"port": 2}}, "bus.options.port", "given twice"),
        ({"interface": "virtual", "bitrate": True}, "bus.bitrate", "positive integer"),
    ],
)
def test_bad_bus_sections_are_named(mapping, key, message):
    with pytest.raises(BusConfigError) as info:
        BusConfig.from_mapping(mapping)
    assert info.value.key == key
    assert message in str(info.value) and str(info.value).startswith(f"{key}: ")


def test_every_interface_python_can_offers_is_accepted():
    for interface in sorted(can.interfaces.VALID_INTERFACES):
        assert BusConfig.from_mapping({"interface": interface}).interface == interface


def test_interface_keywords_next_to_the_known_keys_and_options_pass_through():
    cfg = BusConfig.from_mapping({"interface": "socketcan", "channel": "can0", "receive_own_messages": False,
                                  "options": {"vendor_specific": 3}})
    assert cfg.options == {"receive_own_messages": False, "vendor_specific": 3}  # options: unchecked
    kw = bus_kwargs({"interface": "udp_multicast", "port": 47001, "preserve_timestamps": True,
                     "rcvbuf_bytes": 1 << 20, "multicast_interface": "lo"})
    assert kw["port"] == 47001 and kw["preserve_timestamps"] is True and kw["multicast_interface"] == "lo"


@pytest.mark.parametrize("path", ["config/edge.yaml", "deploy/compose/edge-sim.yaml"])
def test_shipped_configurations_still_load(path):
    raw = yaml.safe_load((REPO / path).read_text(encoding="utf-8"))
    cfg = BusConfig.from_mapping({"node": "TE", **raw["bus"]})
    assert cfg.interface in ("socketcan", "udp_multicast")
