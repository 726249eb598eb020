"""A message the bus cannot unpack is counted and skipped; only a bus that is gone is reopened.

Issue 14, defect 1: on ``udp_multicast`` one undecodable datagram closed the bus and reopened
it with backoff, and ``TE_Limits`` stopped for up to 5 s. Here garbage datagrams come from a
raw UDP socket while the transport sends ``TE_Limits``; the gaps are measured from receive
time stamps on an independent python-can bus.
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import can
import msgpack
import pytest
from bus_testlib import DBC_PATH

from thermal_edge.bus import DEFAULT_UDP_MULTICAST_GROUP, CanTransport, DerateReason, FrameCodec
from thermal_edge.bus.transport import RX_ERROR_RUN_LIMIT

LIMITS = dict(TE_TorqueLimit=50.0, TE_CurrentLimit=30.0, TE_DerateActive=0, TE_DerateReason=DerateReason.NONE)


def _pycan_dict(**over) -> dict:
    """A message in python-can's udp_multicast wire format (``pack_message``'s fields)."""
    msg = {"timestamp": 0.0, "arbitration_id": 0x0A0, "is_extended_id": False, "is_remote_frame": False,
           "is_error_frame": False, "channel": None, "dlc": 8, "data": bytes(8), "is_fd": False,
           "bitrate_switch": False, "error_state_indicator": False}
    msg.update(over)
    return msg


#: Datagrams python-can cannot unpack, as in the issue: not msgpack, a 12-byte classic frame,
#: standard ID 0x800, plus an empty datagram and msgpack of a list.
GARBAGE = [
    b"this is not msgpack",
    msgpack.packb(_pycan_dict(data=bytes(12), dlc=12), use_bin_type=True),
    msgpack.packb(_pycan_dict(arbitration_id=0x800), use_bin_type=True),
    b"",
    msgpack.packb([1, 2, 3], use_bin_type=True),
]
#: The issue's remote frame with data: python-can 4.6 unpacks it (a remote frame of INV_Currents),
#: so it reaches the codec, which drops it as ``dlc`` (a remote frame has no data of ours).
REMOTE_WITH_DATA = msgpack.packb(_pycan_dict(is_remote_frame=True, data=bytes(8)), use_bin_type=True)


def _garbage_sender(port: int) -> socket.socket:
    """A raw UDP socket sending to the group through loopback (hop limit 0)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    return s


class _LimitsWatch(threading.Thread):
    """Independent receiver: receive times of every TE_Limits on a plain python-can bus."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="udp_multicast", channel=DEFAULT_UDP_MULTICAST_GROUP, port=port, hop_limit=0)
        self.times: list[float] = []
        self.errors = 0
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                msg = self.bus.recv(0.05)
            except can.CanOperationError:  # the garbage reaches this bus as well
                self.errors += 1
                continue
            if msg is not None and msg.arbitration_id == 0x2A0:
                self.times.append(msg.timestamp)

    def close(self) -> list[float]:
        self.stop.set()
        self.join(2.0)
        self.bus.shutdown()
        return self.times


async def test_undecodable_datagrams_do_not_stop_te_limits(udp_port, caplog):
    watch = _LimitsWatch(udp_port)
    watch.start()
    garbage = _garbage_sender(udp_port)
    te = CanTransport({"interface": "udp_multicast", "port": udp_port, "node": "TE"}, FrameCodec(DBC_PATH))
    sent = 0
    try:
        async with te:
            te.start_cyclic("TE_Limits", lambda: LIMITS)  # DBC cycle, 100 ms
            await asyncio.sleep(0.5)
            for _ in range(4):  # four rounds of every kind, 0.15 s apart (the 0.6 s and faster)
                for datagram in GARBAGE + [REMOTE_WITH_DATA]:
                    garbage.sendto(datagram, (DEFAULT_UDP_MULTICAST_GROUP, udp_port))
                    sent += datagram is not REMOTE_WITH_DATA
                    await asyncio.sleep(0.15)
            await asyncio.sleep(0.5)
            stats = te.stats.as_dict()
    finally:
        garbage.close()
        times = watch.close()
    gaps = [b - a for a, b in zip(times, times[1:])]
    print(f"\nTE_Limits received {len(times)}, gaps: max {max(gaps) * 1e3:.0f} ms, "
          f"mean {sum(gaps) / len(gaps) * 1e3:.0f} ms; {sent} garbage datagrams, counted {stats['rx_undecodable']}")
    assert len(times) >= 30
    assert max(gaps) < 0.3  # the inverter's timeout; ~0.1 s expected
    assert stats["rx_undecodable"] == sent == 4 * len(GARBAGE)
    assert te.codec.stats.dlc == 4 and te.codec.stats.dropped_total == 4
    assert stats["reconnects"] == 0 and stats["bus_errors"] == 0 and stats["tx_failed"] == 0
    assert watch.errors >= sent - 1  # the independent bus saw the same garbage (it counts empty ones too)
    warnings = [r for r in caplog.records if "undecodable" in r.getMessage()]
    assert 1 <= len(warnings) <= 2  # rate-limited: one line, not one per datagram


async def test_a_flood_of_undecodable_datagrams_never_reopens_the_bus(udp_port):
    """3,000 undecodable datagrams a second for 2 s, nothing valid in between (the fault bench's flood:
    runs of 50 and more used to count as a dead bus, and each reopen silenced TE_Limits)."""
    watch = _LimitsWatch(udp_port)
    watch.start()
    garbage = _garbage_sender(udp_port)
    te = CanTransport({"interface": "udp_multicast", "port": udp_port, "node": "TE"}, FrameCodec(DBC_PATH))
    sent = 0

    def flood() -> None:
        nonlocal sent
        t0 = time.monotonic()
        while (elapsed := time.monotonic() - t0) < 2.0:
            while sent < 3000 * elapsed:
                garbage.sendto(GARBAGE[sent % len(GARBAGE)], (DEFAULT_UDP_MULTICAST_GROUP, udp_port))
                sent += 1
            time.sleep(0.001)

    try:
        async with te:
            te.start_cyclic("TE_Limits", lambda: LIMITS, thread=True)
            await asyncio.sleep(0.3)
            await asyncio.get_running_loop().run_in_executor(None, flood)
            await asyncio.sleep(0.5)
            stats = te.stats.as_dict()
    finally:
        garbage.close()
        times = watch.close()
    gaps = [b - a for a, b in zip(times, times[1:])]
    assert sent >= 5000
    assert stats["reconnects"] == 0 and stats["bus_errors"] == 0
    assert stats["rx_undecodable"] == sent  # every one counted, none lost in a reopen
    assert max(gaps) < 0.3, f"largest TE_Limits gap {max(gaps):.3f} s"


class _ErrorBus(can.BusABC):
    """A virtual bus whose receive raises instead of returning messages while ``failing``.

    ``kind`` picks what the error looks like: ``"message"`` (one bad message, like python-can's
    unpack error) or ``"socket"`` (an OSError underneath: the bus itself is broken).
    """

    failing = False
    kind = "message"

    def __init__(self, channel: str) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        super().__init__(channel=channel)

    def send(self, msg, timeout=None):
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout):
        if _ErrorBus.failing:
            time.sleep(0.001)
            if _ErrorBus.kind == "socket":
                raise can.CanOperationError("receive failed") from OSError(100, "Network is down")
            raise can.CanOperationError("could not unpack received message") from ValueError("bad")
        return self._inner.recv(timeout), False

    def shutdown(self):
        super().shutdown()
        self._inner.shutdown()


def _cfg(channel: str, node: str) -> dict:
    return {"interface": "virtual", "channel": channel, "node": node, "reconnect_min_s": 0.02, "reconnect_max_s": 0.1}


@pytest.mark.parametrize("kind", ["message", "socket"])
async def test_only_a_broken_bus_is_reopened(virtual_channel, kind):
    """Message errors in a row up to the limit keep the bus; an OSError underneath, or an
    endless run of errors, reopens it."""
    _ErrorBus.failing, _ErrorBus.kind = False, kind
    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH),
                      bus_factory=lambda cfg: _ErrorBus(cfg.channel))
    try:
        async with te:
            assert await te.wait_connected(2.0)
            _ErrorBus.failing = True
            loop = asyncio.get_running_loop()
            end = loop.time() + 5.0
            while te.stats.bus_errors == 0 and loop.time() < end:
                await asyncio.sleep(0.005)
            _ErrorBus.failing = False
            end = loop.time() + 5.0
            while te.stats.reconnects == 0 and loop.time() < end:
                await asyncio.sleep(0.005)
    finally:
        _ErrorBus.failing = False
    assert te.stats.bus_errors == 1 and te.stats.reconnects == 1
    if kind == "socket":
        assert te.stats.rx_undecodable == 0  # the first error already means the bus is gone
    else:
        assert te.stats.rx_undecodable == RX_ERROR_RUN_LIMIT - 1  # then the run counts as a dead bus
