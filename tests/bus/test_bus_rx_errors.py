"""A message the bus cannot unpack is counted and skipped; only a bus that is gone is reopened.

Closing and reopening the bus (with backoff) on one undecodable ``udp_multicast`` datagram would
stop ``TE_Limits`` for seconds. Here garbage datagrams come from a
raw UDP socket while the transport sends ``TE_Limits``, received by an independent python-can bus
(kernel receive stamps) and placed against the moments the garbage was sent. How long the gaps are
on a busy host is the fault bench's figure (``benchmarks/faults``, group ``bad_frames``).
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time

import can
import msgpack
import pytest
from bus_testlib import DBC_PATH, udp_socket_drops
from waiting import wait_until

from thermal_edge.bus import DEFAULT_UDP_MULTICAST_GROUP, CanTransport, DerateReason, FrameCodec
from thermal_edge.bus.transport import RX_ERROR_RUN_LIMIT, RX_WARN_INTERVAL_S
from thermal_edge.bus.udp import enlarge_receive_queue

LIMITS = dict(TE_TorqueLimit=50.0, TE_CurrentLimit=30.0, TE_DerateActive=0, TE_DerateReason=DerateReason.NONE)


def _pycan_dict(**over) -> dict:
    """A message in python-can's udp_multicast wire format (``pack_message``'s fields)."""
    msg = {"timestamp": 0.0, "arbitration_id": 0x0A0, "is_extended_id": False, "is_remote_frame": False,
           "is_error_frame": False, "channel": None, "dlc": 8, "data": bytes(8), "is_fd": False,
           "bitrate_switch": False, "error_state_indicator": False}
    msg.update(over)
    return msg


#: Datagrams python-can cannot unpack: not msgpack, a 12-byte classic frame,
#: standard ID 0x800, plus an empty datagram and msgpack of a list.
GARBAGE = [
    b"this is not msgpack",
    msgpack.packb(_pycan_dict(data=bytes(12), dlc=12), use_bin_type=True),
    msgpack.packb(_pycan_dict(arbitration_id=0x800), use_bin_type=True),
    b"",
    msgpack.packb([1, 2, 3], use_bin_type=True),
]
#: A remote frame with data: python-can 4.6 unpacks it (a remote frame of INV_Currents),
#: so it reaches the codec, which drops it as ``dlc`` (a remote frame has no data of ours).
REMOTE_WITH_DATA = msgpack.packb(_pycan_dict(is_remote_frame=True, data=bytes(8)), use_bin_type=True)


def _garbage_sender(port: int) -> socket.socket:
    """A raw UDP socket sending to the group through loopback (hop limit 0)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    return s


#: generous upper bound of every wait on a condition (a hang guard, not a performance bound), s
HANG_S = 60.0


class _LimitsWatch(threading.Thread):
    """Independent receiver: kernel receive times of every TE_Limits on a plain python-can bus."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="udp_multicast", channel=DEFAULT_UDP_MULTICAST_GROUP, port=port, hop_limit=0)
        enlarge_receive_queue(self.bus._multicast._socket)  # the garbage floods this bus as well
        self.times: list[float] = []
        self.errors = 0
        self.stop = threading.Event()
        self._dropped: int | None = None  # once closed

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                msg = self.bus.recv(0.05)
            except can.CanOperationError:  # the garbage reaches this bus as well
                self.errors += 1
                continue
            if msg is not None and msg.arbitration_id == 0x2A0:
                self.times.append(msg.timestamp)

    def drops(self) -> int:
        """TE_Limits and garbage the kernel dropped for want of room in this bus's queue."""
        return self._dropped if self._dropped is not None else udp_socket_drops(self.bus._multicast._socket)

    def close(self, expected: int) -> list[float]:
        """Stop once ``expected`` TE_Limits arrived or were dropped by this socket's kernel queue."""
        _wait(lambda: len(self.times) + self.drops() >= expected)
        self.stop.set()
        self.join(HANG_S)
        self._dropped = self.drops()
        self.bus.shutdown()
        return self.times


def _wait(predicate) -> bool:
    return wait_until(predicate, HANG_S, 0.01)


async def test_undecodable_datagrams_do_not_stop_te_limits(udp_port, caplog):
    watch = _LimitsWatch(udp_port)
    watch.start()
    garbage = _garbage_sender(udp_port)
    te = CanTransport({"interface": "udp_multicast", "port": udp_port, "node": "TE"}, FrameCodec(DBC_PATH))
    sent = tx = 0
    sent_at: list[float] = []
    try:
        async with te:
            te.start_cyclic("TE_Limits", lambda: LIMITS)  # DBC cycle, 100 ms
            await asyncio.sleep(0.5)
            for _ in range(4):  # four rounds of every kind, 0.15 s apart (faster than a sender every 0.6 s)
                for datagram in GARBAGE + [REMOTE_WITH_DATA]:
                    sent_at.append(time.time())
                    garbage.sendto(datagram, (DEFAULT_UDP_MULTICAST_GROUP, udp_port))
                    sent += datagram is not REMOTE_WITH_DATA
                    await asyncio.sleep(0.15)
            await asyncio.sleep(0.5)
            stats = te.stats.as_dict()
            tx = te.stats.tx_frames
    finally:
        garbage.close()
        times = watch.close(tx)
    # the loop's sender is due again within one period (100 ms) of its last frame, before the next
    # datagram (150 ms after the one before): each interval between two datagrams holds a TE_Limits,
    # whatever the host's speed, unless the bus was closed, reopened or the sender stopped
    between = [sum(a < t < b for t in times) for a, b in zip(sent_at, sent_at[1:])]
    print(f"\nTE_Limits received {len(times)} of {tx}, per interval between two datagrams {between}; "
          f"{sent} garbage datagrams, counted {stats['rx_undecodable']}")
    assert watch.drops() == 0 and len(times) == tx  # the independent bus got every TE_Limits sent
    assert min(between) >= 1
    assert stats["rx_undecodable"] == sent == 4 * len(GARBAGE)
    assert te.codec.stats.dlc == 4 and te.codec.stats.dropped_total == 4
    assert stats["reconnects"] == 0 and stats["bus_errors"] == 0 and stats["tx_failed"] == 0
    assert watch.errors >= sent - 1  # the independent bus saw the same garbage (it counts empty ones too)
    warnings = [r.created for r in caplog.records if "undecodable" in r.getMessage()]
    # rate-limited: one line, not one per datagram; another only after RX_WARN_INTERVAL_S (a busy host
    # may stretch the test past it)
    assert warnings and all(b - a >= RX_WARN_INTERVAL_S - 0.01 for a, b in zip(warnings, warnings[1:]))


FLOOD_N = 6000  # undecodable datagrams
FLOOD_RATE = 3000.0  # per s at most


async def test_a_flood_of_undecodable_datagrams_never_reopens_the_bus(udp_port):
    """6,000 undecodable datagrams at up to 3,000 a second, nothing valid in between (the fault bench's
    flood: runs of 50 and more used to count as a dead bus, and each reopen silenced TE_Limits)."""
    watch = _LimitsWatch(udp_port)
    watch.start()
    garbage = _garbage_sender(udp_port)
    te = CanTransport({"interface": "udp_multicast", "port": udp_port, "node": "TE"}, FrameCodec(DBC_PATH))
    sent = tx = 0
    window: list[float] = []

    def flood() -> None:
        nonlocal sent
        window.append(time.time())
        t0 = time.monotonic()
        while sent < FLOOD_N:
            while sent < min(FLOOD_N, FLOOD_RATE * (time.monotonic() - t0)):
                garbage.sendto(GARBAGE[sent % len(GARBAGE)], (DEFAULT_UDP_MULTICAST_GROUP, udp_port))
                sent += 1
            time.sleep(0.001)
        window.append(time.time())

    try:
        async with te:
            sender = te.start_cyclic("TE_Limits", lambda: LIMITS, thread=True)
            await asyncio.sleep(0.3)
            await asyncio.get_running_loop().run_in_executor(None, flood)
            # every datagram read and counted, or dropped by the kernel for want of room
            te_drops = lambda: udp_socket_drops(te.bus.socket)  # noqa: E731
            assert await asyncio.to_thread(_wait, lambda: te.stats.rx_undecodable + te_drops() >= sent)
            before = sender.sent
            assert await asyncio.to_thread(_wait, lambda: sender.sent >= before + 3)  # and it goes on
            stats = te.stats.as_dict()
            dropped = te_drops()
            tx = te.stats.tx_frames
    finally:
        garbage.close()
        times = watch.close(tx)
    during = sum(window[0] < t < window[1] for t in times)
    print(f"\n{sent} datagrams in {window[1] - window[0]:.2f} s: {stats['rx_undecodable']} counted, {dropped} dropped by "
          f"the kernel; TE_Limits {len(times)} received of {tx} ({watch.drops()} dropped), {during} during the flood")
    assert sent == FLOOD_N and window[1] - window[0] >= FLOOD_N / FLOOD_RATE - 0.01
    assert stats["reconnects"] == 0 and stats["bus_errors"] == 0 and stats["tx_failed"] == 0
    assert stats["rx_undecodable"] + dropped == sent  # every one counted, none lost in a reopen
    assert stats["rx_undecodable"] > 0
    assert len(times) + watch.drops() == tx  # every TE_Limits sent reached the independent bus or its full queue
    # the threaded sender went on during the flood (seconds long: FLOOD_N / FLOOD_RATE at least)
    assert during >= 1


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


async def test_the_emulator_skips_undecodable_datagrams(udp_port):
    """The inverter emulator reads the same group as the service: datagrams that are no CAN message
    are skipped and counted, and it runs its cycle to the end instead of stopping the simulated
    inverter (which the service would then see as a silent bus)."""
    from thermal_edge.sim.inverter import EmulatorConfig, InverterEmulator

    emu = InverterEmulator(EmulatorConfig(t0=0.0, duration_s=30.0, speed=10.0, flow_control=False, closed_loop=False,
                                          current_period_s=0.1, temperature_period_s=1.0, plant_dt_s=0.5,
                                          trace_every_s=1e9, record_estimates=False),
                           {"interface": "udp_multicast", "port": udp_port})
    garbage = _garbage_sender(udp_port)
    undecodable = list(GARBAGE)
    try:
        run = asyncio.create_task(emu.run())
        await asyncio.sleep(0.5)
        for datagram in undecodable:
            garbage.sendto(datagram, (DEFAULT_UDP_MULTICAST_GROUP, udp_port))
            await asyncio.sleep(0.05)
        summary = await asyncio.wait_for(run, HANG_S)
    finally:
        garbage.close()
    assert summary.sim_seconds == pytest.approx(30.0, abs=1.0)
    # each one skipped and counted (a loopback datagram the kernel dropped is not counted)
    assert 1 <= summary.rx_undecodable <= len(undecodable)
