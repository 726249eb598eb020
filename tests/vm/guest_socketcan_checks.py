"""Checks that run INSIDE the VM (by ``vm.pytest("tests/vm/guest_socketcan_checks.py")``).

The file name does not match ``test_*.py`` on purpose: the host's pytest never
collects it; pytest in the guest collects it because it is named explicitly.
On a host without the VM every check skips.
"""

from __future__ import annotations

import os
import socket
import struct

import pytest

pytestmark = pytest.mark.skipif(
    os.environ.get("THERMAL_EDGE_IN_VM") != "1", reason="runs only inside the SocketCAN VM (vm.pytest)"
)

CAN_FRAME = struct.Struct("=IB3x8s")  # struct can_frame: id, dlc, pad, data


def test_raw_af_can_socket_loopback():
    tx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    rx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    with tx, rx:
        rx.bind(("vcan0",))
        tx.bind(("vcan0",))
        rx.settimeout(5)
        tx.send(CAN_FRAME.pack(0x2C0, 8, bytes(range(8))))
        can_id, dlc, data = CAN_FRAME.unpack(rx.recv(CAN_FRAME.size))
    assert (can_id, dlc, data) == (0x2C0, 8, bytes(range(8)))


def test_python_can_socketcan_two_buses_with_filter():
    import can

    with (
        can.Bus(interface="socketcan", channel="vcan0") as tx,
        can.Bus(interface="socketcan", channel="vcan0", can_filters=[{"can_id": 0x0A0, "can_mask": 0x7FF}]) as rx,
    ):
        tx.send(can.Message(arbitration_id=0x0A1, data=b"\x00" * 8, is_extended_id=False))  # filtered out
        tx.send(can.Message(arbitration_id=0x0A0, data=bytes.fromhex("C80070FEF40103EA"), is_extended_id=False))
        msg = rx.recv(timeout=5)
        assert msg is not None
        assert (msg.arbitration_id, bytes(msg.data)) == (0x0A0, bytes.fromhex("C80070FEF40103EA"))
        assert msg.channel == "vcan0"
        assert rx.recv(timeout=0.2) is None
