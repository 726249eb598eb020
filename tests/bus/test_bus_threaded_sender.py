"""``start_cyclic(thread=True)``: TE_Limits from its own thread, whatever the event loop does.

Issue 14, defect 5: TE_Limits shared the event loop with metrics, ticks and adaptation, and a
busy loop delayed it beyond the inverter's 300 ms timeout. The gaps are measured from receive
time stamps on an independent python-can bus.
"""

from __future__ import annotations

import asyncio
import threading
import time

import can
import pytest
from bus_testlib import DBC_PATH

from thermal_edge.bus import BusConfig, CanTransport, DerateReason, FrameCodec, create_bus

LIMITS = dict(TE_TorqueLimit=80.0, TE_CurrentLimit=40.0, TE_DerateActive=0, TE_DerateReason=DerateReason.NONE)


class _Watch(threading.Thread):
    """Independent receiver on its own virtual bus: receive times of every TE_Limits."""

    def __init__(self, channel: str) -> None:
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.times: list[float] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None and msg.arbitration_id == 0x2A0:
                self.times.append(msg.timestamp)

    def gaps(self) -> list[float]:
        self.stop.set()
        self.join(2.0)
        while (msg := self.bus.recv(0)) is not None:  # what was still queued
            if msg.arbitration_id == 0x2A0:
                self.times.append(msg.timestamp)
        self.bus.shutdown()
        return [b - a for a, b in zip(self.times, self.times[1:])]


def _cfg(channel: str) -> dict:
    return {"interface": "virtual", "channel": channel, "node": "TE", "reconnect_min_s": 0.02, "reconnect_max_s": 0.1}


@pytest.mark.parametrize("thread", [True, False], ids=["thread", "asyncio"])
async def test_blocked_event_loop_does_not_delay_a_threaded_sender(virtual_channel, thread, unit_nice):
    watch = _Watch(virtual_channel)
    watch.start()
    te = CanTransport(_cfg(virtual_channel), FrameCodec(DBC_PATH))
    async with te:
        sender = te.start_cyclic("TE_Limits", lambda: LIMITS, thread=thread)
        await asyncio.sleep(0.5)
        time.sleep(1.0)  # a coroutine that blocks the loop (a slow tick, a stalled metrics handler)
        await asyncio.sleep(0.5)
        await sender.stop()
        assert not sender.running
    gaps = watch.gaps()
    print(f"\n{'thread' if thread else 'asyncio'} sender: {len(gaps) + 1} TE_Limits, max gap {max(gaps) * 1e3:.0f} ms")
    if thread:
        assert len(gaps) >= 18 and max(gaps) < 0.15
        assert te.stats.cyclic_overruns == 0
    else:  # the defect, shown: the loop's sender stops while the loop is blocked
        assert max(gaps) > 0.9


async def test_threaded_sender_survives_reconnects(virtual_channel):
    """Buses closed under the sender's feet (the loop reopens them meanwhile): sends that hit a
    torn-down bus count as tx_failed, nothing raises, and the cadence goes on."""
    opened: list[can.BusABC] = []

    def factory(cfg: BusConfig) -> can.BusABC:
        bus = create_bus(cfg)
        opened.append(bus)
        return bus

    watch = _Watch(virtual_channel)
    watch.start()
    te = CanTransport(_cfg(virtual_channel), FrameCodec(DBC_PATH), bus_factory=factory)
    async with te:
        sender = te.start_cyclic("TE_Limits", lambda: LIMITS, period_s=0.002, thread=True)
        for _ in range(5):
            await asyncio.sleep(0.1)
            opened[-1].shutdown()  # receive and send on it now fail
            n = len(opened)
            loop = asyncio.get_running_loop()
            end = loop.time() + 3.0
            while len(opened) == n and loop.time() < end:
                await asyncio.sleep(0.005)
        await asyncio.sleep(0.1)
        assert sender.running
    watch.gaps()
    assert te.stats.reconnects == 5
    assert te.stats.tx_failed >= 1 and te.stats.tx_frames >= 100
    assert sender.sent == te.stats.tx_frames and sender.attempts == te.stats.tx_frames + te.stats.tx_failed
    assert len(watch.times) == te.stats.tx_frames  # every frame the transport counts as sent arrived


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
            te.start_cyclic("TE_Limits", lambda: LIMITS, period_s=0.0005, thread=True)
            for i in range(2000):
                te.send("TE_Limits", LIMITS)
                if i % 20 == 0:
                    await asyncio.sleep(0)
            await asyncio.sleep(0.2)
    finally:
        sys.setswitchinterval(interval)
    n = te.stats.tx_frames
    assert n > 2000 and te.stats.tx_failed == 0
    assert rx.codec.stats.lost == 0 and rx.codec.stats.counter_repeat == 0
    assert len(got) == n
