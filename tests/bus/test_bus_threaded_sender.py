"""``start_cyclic(thread=True)``: TE_Limits from its own thread, whatever the event loop does.

Sharing the event loop with metrics, ticks and adaptation, TE_Limits would be delayed by a
busy loop beyond the inverter's 300 ms timeout. The frames are received on an
independent python-can bus and placed against the moments the loop was blocked (the virtual bus
stamps a frame with the wall clock when it is sent). Whether the cadence holds 300 ms on a busy
host is the fault bench's figure (``benchmarks/faults``); here it is which sender sends at all
while the loop cannot run.
"""

from __future__ import annotations

import asyncio
import threading
import time

import can
import pytest
from bus_testlib import DBC_PATH
from waiting import async_wait_until, wait_until

from thermal_edge.bus import BusConfig, CanTransport, DerateReason, FrameCodec, create_bus

LIMITS = dict(TE_TorqueLimit=80.0, TE_CurrentLimit=40.0, TE_DerateActive=0, TE_DerateReason=DerateReason.NONE)


class _Watch(threading.Thread):
    """Independent receiver on its own virtual bus: send times of every TE_Limits."""

    def __init__(self, channel: str) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.times: list[float] = []
        self.stop = threading.Event()
        self._lock = threading.Condition()

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None and msg.arbitration_id == 0x2A0:
                with self._lock:
                    self.times.append(msg.timestamp)
                    self._lock.notify_all()

    def wait_after(self, t: float, n: int, timeout: float) -> bool:
        """Wait (blocking the calling thread) until ``n`` TE_Limits sent after ``t`` arrived."""
        with self._lock:
            return self._lock.wait_for(lambda: sum(x > t for x in self.times) >= n, timeout)

    def between(self, t0: float, t1: float) -> int:
        with self._lock:
            return sum(t0 < x < t1 for x in self.times)

    def close(self) -> list[float]:
        self.stop.set()
        self.join(2.0)
        while (msg := self.bus.recv(0)) is not None:  # what was still queued
            if msg.arbitration_id == 0x2A0:
                self.times.append(msg.timestamp)
        self.bus.shutdown()
        return self.times


#: generous upper bound of every wait on a condition (a hang guard, not a performance bound), s
HANG_S = 60.0


def _cfg(channel: str) -> dict:
    return {"interface": "virtual", "channel": channel, "node": "TE", "reconnect_min_s": 0.02, "reconnect_max_s": 0.1}


@pytest.mark.parametrize("thread", [True, False], ids=["thread", "asyncio"])
async def test_blocked_event_loop_does_not_delay_a_threaded_sender(virtual_channel, thread, unit_nice):
    watch = _Watch(virtual_channel)
    watch.start()
    te = CanTransport(_cfg(virtual_channel), FrameCodec(DBC_PATH))
    async with te:
        sender = te.start_cyclic("TE_Limits", lambda: LIMITS, thread=thread)
        assert await asyncio.to_thread(watch.wait_after, 0.0, 3, HANG_S)  # it runs
        # a coroutine that blocks the loop (a slow tick, a stalled metrics handler): the threaded
        # sender's frames arrive meanwhile, the loop's cannot
        t_block = time.time()
        if thread:
            during = watch.wait_after(t_block, 5, HANG_S)
        else:
            time.sleep(1.0)  # ten periods
        t_free = time.time()
        assert await asyncio.to_thread(watch.wait_after, t_free, 3, HANG_S)  # and it goes on
        await sender.stop()
        assert not sender.running
    times = watch.close()
    sent_while_blocked = sum(t_block < t < t_free for t in times)
    print(f"\n{'thread' if thread else 'asyncio'} sender: {len(times)} TE_Limits, {sent_while_blocked} while the loop was "
          f"blocked for {t_free - t_block:.2f} s")
    if thread:
        assert during and sent_while_blocked >= 5
    else:  # the defect, shown: the loop's sender stops while the loop is blocked
        assert sent_while_blocked == 0
    assert len(times) == te.stats.tx_frames == sender.sent  # and every frame sent arrived


async def test_threaded_sender_survives_reconnects(virtual_channel):
    """Buses closed under the sender's feet (the loop reopens them meanwhile): sends that hit a
    torn-down bus count as tx_failed, nothing raises, and the cadence goes on."""
    opened: list[can.BusABC] = []
    te: CanTransport | None = None

    def factory(cfg: BusConfig) -> can.BusABC:
        if opened:  # a reopen: not before the sender thread has met the torn-down bus
            assert _wait(lambda: te.stats.tx_failed > failed_at_close, HANG_S)
        bus = create_bus(cfg)
        opened.append(bus)
        return bus

    watch = _Watch(virtual_channel)
    watch.start()
    te = CanTransport(_cfg(virtual_channel), FrameCodec(DBC_PATH), bus_factory=factory)
    async with te:
        sender = te.start_cyclic("TE_Limits", lambda: LIMITS, period_s=0.002, thread=True)
        for _ in range(5):
            sent = sender.sent
            assert await _until(lambda sent=sent: sender.sent >= sent + 20)  # frames on this bus
            failed_at_close = te.stats.tx_failed
            n = len(opened)
            opened[-1].shutdown()  # receive and send on it now fail
            assert await _until(lambda n=n: len(opened) > n)
        sent = sender.sent
        assert await _until(lambda: sender.sent >= sent + 20)  # and on the last one
        assert sender.running
    watch.close()
    assert te.stats.reconnects == 5
    assert te.stats.tx_failed >= 5 and te.stats.tx_frames >= 6 * 20
    assert sender.sent == te.stats.tx_frames and sender.attempts == te.stats.tx_frames + te.stats.tx_failed
    assert len(watch.times) == te.stats.tx_frames  # every frame the transport counts as sent arrived


def _wait(predicate, timeout: float) -> bool:
    return wait_until(predicate, timeout, 0.001)


async def _until(predicate, timeout: float = HANG_S) -> bool:
    return await async_wait_until(predicate, timeout, 0.002)


def test_coroutine_provider_is_refused_for_a_thread():
    from thermal_edge.bus import CyclicSender

    async def provider():
        return LIMITS

    with pytest.raises(TypeError, match="plain provider"):
        CyclicSender(FrameCodec(DBC_PATH), lambda i, d: True, "TE_Limits", provider, thread=True)


async def test_frames_of_one_id_from_thread_and_loop_leave_in_counter_order(virtual_channel):
    """TE_Limits from the sender thread and immediate sends of it from the loop share the alive
    counter: each frame is encoded and sent in one step, so the receiver sees no counter jump
    (a frame that overtook another showed up as 14 lost and then 1 lost)."""
    import sys

    got = []
    rx = CanTransport({**_cfg(virtual_channel), "node": "INV"}, FrameCodec(DBC_PATH), on_frame=got.append)
    te = CanTransport(_cfg(virtual_channel), FrameCodec(DBC_PATH))
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as a busy machine does (without the lock: ~3,000 lost)
    try:
        async with rx, te:
            sender = te.start_cyclic("TE_Limits", lambda: LIMITS, period_s=0.0005, thread=True)
            for i in range(2000):
                te.send("TE_Limits", LIMITS)
                if i % 20 == 0:
                    await asyncio.sleep(0)
            assert await _until(lambda: sender.sent >= 10)  # the thread's frames among them
            await sender.stop()
            assert await _until(lambda: len(got) >= te.stats.tx_frames)  # all delivered
    finally:
        sys.setswitchinterval(interval)
    n = te.stats.tx_frames
    assert n > 2000 and te.stats.tx_failed == 0
    assert rx.codec.stats.lost == 0 and rx.codec.stats.counter_repeat == 0
    assert len(got) == n


def test_on_sent_gets_the_interval_between_frames_the_sink_accepted(monkeypatch):
    """The cadence as the bus saw it (``thermal_edge_limits_send_interval_seconds``): after each
    frame the sink accepted, the time since the one accepted before, on a clock set here; a frame
    the sink refused is no send, so the next interval spans it."""
    from thermal_edge.bus import cyclic

    clock = iter([0.0, 0.1, 0.35, 0.45, 0.6])
    monkeypatch.setattr(cyclic.time, "monotonic", lambda: next(clock))
    accepted = iter([True, True, True, False, True, True])
    sink_calls: list[int] = []

    def sink(frame_id: int, data: bytes) -> bool:
        sink_calls.append(frame_id)
        return next(accepted)

    got: list[float] = []
    s = cyclic.CyclicSender(FrameCodec(DBC_PATH), sink, "TE_Limits", lambda: LIMITS, period_s=0.1,
                            on_sent=got.append)
    for _ in range(6):
        s.send_once_sync()
    # accepted at 0.0, 0.1, 0.35, (refused), 0.45, 0.6
    assert got == pytest.approx([0.1, 0.25, 0.1, 0.15]) and len(sink_calls) == 6 and s.sent == 5
