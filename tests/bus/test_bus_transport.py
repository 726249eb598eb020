"""CanTransport on python-can's in-process ``virtual`` bus: receive, cyclic send, reconnection, config."""

from __future__ import annotations

import asyncio
import logging

import can
import pytest
from bus_testlib import DBC_PATH
from waiting import async_wait_until

from thermal_edge.bus import (
    DEFAULT_UDP_MULTICAST_GROUP,
    BusConfig,
    BusConfigError,
    CanTransport,
    DerateReason,
    FrameCodec,
    bus_kwargs,
    create_bus,
)

LIMITS = dict(TE_TorqueLimit=120.5, TE_CurrentLimit=88.25, TE_DerateActive=1, TE_DerateReason=DerateReason.WINDING)
SAFE = dict(TE_TorqueLimit=20.0, TE_CurrentLimit=10.0, TE_DerateActive=1, TE_DerateReason=DerateReason.MODEL_FAULT)


def _cfg(channel: str, node: str, **extra) -> dict:
    return {"interface": "virtual", "channel": channel, "node": node,
            "reconnect_min_s": 0.02, "reconnect_max_s": 0.1, **extra}


#: generous upper bound of every wait on a condition (a hang guard, not a performance bound), s
HANG_S = 60.0


async def _until(predicate, timeout: float = HANG_S, step: float = 0.005) -> bool:
    return await async_wait_until(predicate, timeout, step)


# ----------------------------------------------------------------- configuration
def test_udp_multicast_forces_hop_limit_zero(caplog):
    with caplog.at_level(logging.WARNING):
        kw = bus_kwargs({"interface": "udp_multicast", "hop_limit": 5, "port": 50000})
    assert kw["hop_limit"] == 0
    assert "hop_limit" in caplog.text
    assert kw["channel"] == DEFAULT_UDP_MULTICAST_GROUP and kw["port"] == 50000
    assert "bitrate" not in kw
    kw = bus_kwargs(BusConfig(interface="udp_multicast", options={"hop_limit": 1}))
    assert kw["hop_limit"] == 0


def test_default_multicast_group_is_python_cans_ipv4_group():
    """IPv4 because Linux's loopback carries IPv4 multicast only (see thermal_edge.bus.udp)."""
    import ipaddress

    from can.interfaces.udp_multicast import UdpMulticastBus

    group = ipaddress.ip_address(DEFAULT_UDP_MULTICAST_GROUP)
    assert DEFAULT_UDP_MULTICAST_GROUP == UdpMulticastBus.DEFAULT_GROUP_IPv4
    assert group.version == 4 and group.is_multicast and group in ipaddress.ip_network("239.0.0.0/8")


@pytest.mark.parametrize("channel", ["192.168.1.20", "fd00::1", "example.org", "can0"])
def test_udp_multicast_refuses_unicast_or_names(channel):
    with pytest.raises(BusConfigError, match="bus.channel"):
        bus_kwargs({"interface": "udp_multicast", "channel": channel})


def test_config_from_mapping():
    cfg = BusConfig.from_mapping({"interface": "socketcan", "channel": "can0", "bitrate": 250000,
                                  "fd": False, "options": {"receive_own_messages": False}})
    assert cfg.options == {"fd": False, "receive_own_messages": False}
    assert bus_kwargs(cfg) == {"interface": "socketcan", "channel": "can0", "bitrate": 250000,
                               "fd": False, "receive_own_messages": False}
    assert bus_kwargs({"interface": "virtual"})["channel"] == "thermal_edge"
    with pytest.raises(BusConfigError, match="bus.bitrate"):
        BusConfig(bitrate=-5)
    with pytest.raises(BusConfigError, match="bus.reconnect_min_s"):
        BusConfig.from_mapping({"reconnect_min_s": 0})


# ---------------------------------------------------------------- receive / send
async def test_back_to_back_virtual(virtual_channel):
    queue: asyncio.Queue = asyncio.Queue()
    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH), queue=queue)
    inv = CanTransport(_cfg(virtual_channel, "INV"), FrameCodec(DBC_PATH))
    async with te, inv:
        n = 300
        for i in range(n):  # back to back, no pacing
            assert inv.send("INV_Currents", dict(INV_Id=i * 0.05, INV_Iq=-i * 0.05, INV_IphRms=i * 0.1))
        inv.send("INV_StatorTemps", dict(INV_T_WindingSlot=95.5, INV_T_EndWinding=float("nan"), INV_T_Housing=60.1,
                                         INV_S_WindingSlot=0, INV_S_EndWinding=3, INV_S_Housing=0))
        frames = [await asyncio.wait_for(queue.get(), HANG_S) for _ in range(n + 1)]
    currents = [f for f in frames if f.name == "INV_Currents"]
    assert [f.counter for f in currents] == [i % 16 for i in range(n)]
    assert [f.signals["INV_Id"] for f in currents] == pytest.approx([i * 0.05 for i in range(n)])
    temps = frames[-1]
    assert temps.name == "INV_StatorTemps" and temps.signals["INV_T_WindingSlot"] == pytest.approx(95.5)
    assert temps.signals["INV_T_EndWinding"] != temps.signals["INV_T_EndWinding"]  # NaN
    assert all(f.timestamp is not None and f.is_rx for f in frames)
    assert te.codec.stats.dropped_total == 0 and te.codec.stats.lost == 0
    assert te.codec.stats.received["INV_Currents"] == n
    assert inv.stats.tx_frames == n + 1 and te.stats.rx_messages == n + 1 and te.stats.bus_errors == 0


async def test_cyclic_limits_reach_the_inverter(virtual_channel):
    got = []
    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH))
    inv = CanTransport(_cfg(virtual_channel, "INV"), FrameCodec(DBC_PATH), on_frame=got.append)
    async with inv, te:
        sender = te.start_cyclic("TE_Limits", lambda: LIMITS, period_s=0.01)
        assert sender.period_s == 0.01
        assert te.start_cyclic("TE_Status", lambda: dict(TE_State=1, TE_PredErrRms=0.5, TE_AdaptCount=2,
                                                          TE_ParamVersion=3)).period_s == pytest.approx(1.0)
        assert await _until(lambda: sum(f.name == "TE_Limits" for f in got) >= 20)
    limits = [f for f in got if f.name == "TE_Limits"]
    assert limits[0].signals == pytest.approx(dict(LIMITS))
    assert all(f.lost_before == 0 for f in limits)
    # never faster than the period: a fixed-rate schedule that skips missed periods puts at most
    # (span / period) + 3 frames into a span (the first may be late, its successor then due at once);
    # how close to the period a busy host keeps it is the fault bench's figure
    span = limits[-1].timestamp - limits[0].timestamp
    assert len(limits) <= span / 0.01 + 3, (len(limits), span)
    assert any(f.name == "TE_Status" for f in got)  # first cyclic frame goes out immediately


async def test_async_callback_and_callback_errors(virtual_channel):
    seen = []

    async def slow(frame):
        await asyncio.sleep(0)
        seen.append(frame.counter)
        if frame.counter == 2:
            raise RuntimeError("consumer bug")

    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH), on_frame=slow)
    inv = CanTransport(_cfg(virtual_channel, "INV"), FrameCodec(DBC_PATH))
    async with te, inv:
        for _ in range(5):
            inv.send("INV_Mechanics", dict(INV_Speed=1000, INV_Torque=10, INV_Udc=400))
        assert await _until(lambda: len(seen) == 5)
    assert seen == [0, 1, 2, 3, 4] and te.stats.callback_errors == 1


async def test_provider_failure_sends_fallback(virtual_channel):
    got = []
    calls = {"n": 0}

    def provider():
        calls["n"] += 1
        if calls["n"] % 2 == 0:
            raise ZeroDivisionError("model blew up")
        if calls["n"] % 3 == 0:
            return {"TE_TorqueLimit": 1.0}  # incomplete: cannot be encoded
        return LIMITS

    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH))
    inv = CanTransport(_cfg(virtual_channel, "INV"), FrameCodec(DBC_PATH), on_frame=got.append)
    async with inv, te:
        te.start_cyclic("TE_Limits", provider, period_s=0.005, fallback=lambda: SAFE)
        assert await _until(lambda: len(got) >= 12)
    reasons = [f.signals["TE_DerateReason"] for f in got]
    assert DerateReason.MODEL_FAULT in reasons and DerateReason.WINDING in reasons
    assert te.stats.provider_errors >= 6 and te.stats.fallback_sent == te.stats.provider_errors
    assert all(f.lost_before == 0 for f in got)  # one frame per period, no gaps


async def test_no_fallback_skips_the_period(virtual_channel):
    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH))
    async with te:
        sender = te.start_cyclic("TE_Limits", lambda: None, period_s=0.005)
        assert await _until(lambda: te.stats.provider_errors >= 3)
        assert sender.attempts == 0 and te.stats.tx_frames == 0


# ------------------------------------------------------------------ reconnection
class _Flaky:
    """Bus factory: the first ``fail_opens`` opens fail like a missing interface."""

    def __init__(self, fail_opens: int) -> None:
        self.fail_opens = fail_opens
        self.opened: list[can.BusABC] = []

    def __call__(self, config: BusConfig) -> can.BusABC:
        if self.fail_opens > 0:
            self.fail_opens -= 1
            raise can.CanInitializationError("interface down")
        bus = create_bus(config)
        self.opened.append(bus)
        return bus


class _SendFailBus(can.BusABC):
    """A virtual bus whose sends fail while ``broken`` (like ENETDOWN)."""

    broken = False

    def __init__(self, channel: str) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        super().__init__(channel=channel)

    def send(self, msg, timeout=None):
        if _SendFailBus.broken:
            raise can.CanOperationError("network is down")
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout):
        return self._inner.recv(timeout), False

    def shutdown(self):
        super().shutdown()
        self._inner.shutdown()


async def test_reconnects_after_open_failures_and_closed_bus(virtual_channel):
    flaky = _Flaky(fail_opens=2)
    got = []
    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH), bus_factory=flaky)
    inv = CanTransport(_cfg(virtual_channel, "INV"), FrameCodec(DBC_PATH), on_frame=got.append)
    async with inv, te:
        te.start_cyclic("TE_Limits", lambda: LIMITS, period_s=0.005)
        assert await te.wait_connected(HANG_S)
        assert te.stats.bus_errors == 2  # the two failed opens
        assert await _until(lambda: len(got) >= 3)
        flaky.opened[-1].shutdown()  # bus closed under our feet: receive and send fail
        assert await _until(lambda: te.stats.reconnects >= 1)
        n = len(got)
        assert await _until(lambda: len(got) >= n + 5)  # TE_Limits flows again
    assert te.stats.bus_errors >= 3
    assert te.connected is False  # stopped
    assert len(flaky.opened) >= 2


async def test_send_errors_trigger_reconnect_and_cadence_survives(virtual_channel):
    _SendFailBus.broken = False
    got = []
    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH),
                      bus_factory=lambda cfg: _SendFailBus(cfg.channel))
    inv = CanTransport(_cfg(virtual_channel, "INV"), FrameCodec(DBC_PATH), on_frame=got.append)
    try:
        async with inv, te:
            sender = te.start_cyclic("TE_Limits", lambda: LIMITS, period_s=0.005)
            assert await _until(lambda: len(got) >= 3)
            _SendFailBus.broken = True
            assert await _until(lambda: te.stats.tx_failed >= 5)
            assert te.stats.bus_errors >= 1 and sender.running
            _SendFailBus.broken = False
            assert await _until(lambda: te.stats.reconnects >= 1)
            n = len(got)
            assert await _until(lambda: len(got) >= n + 3)
    finally:
        _SendFailBus.broken = False
    # the receiver saw the outage: as lost frames, or (an outage longer than the counter's judgement on a
    # busy host) as a resync of the alive counter
    assert sum(f.lost_before for f in got) + inv.codec.stats.counter_resync > 0
    assert inv.codec.stats.counter_repeat == 0


async def test_invalid_interface_raises_clearly(virtual_channel):
    with pytest.raises(BusConfigError, match=r"bus.interface: unknown python-can interface 'socketcann' "
                                             r"\(did you mean 'socketcan'\?\)"):
        CanTransport({"interface": "socketcann"}, FrameCodec(DBC_PATH))


# ----------------------------------------------------------------------- ID filters
class _KernelFilteredBus(can.BusABC):
    """A virtual bus that filters "in the kernel" as SocketCAN does (``_is_filtered`` after
    ``set_filters``); SocketCAN itself cannot run on this machine."""

    def __init__(self, channel: str) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        self.applied = []
        super().__init__(channel=channel)

    def _apply_filters(self, filters):
        self.applied.append(filters)
        self._is_filtered = filters is not None

    def send(self, msg, timeout=None):
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout):
        msg = self._inner.recv(timeout)
        if msg is not None and self._is_filtered and not self._matches_filters(msg):
            return None, True  # dropped "in the kernel": never seen above
        return msg, self._is_filtered

    def shutdown(self):
        super().shutdown()
        self._inner.shutdown()


async def test_kernel_filters_let_in_only_the_frames_this_node_receives(virtual_channel):
    buses = []
    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH),
                      bus_factory=lambda cfg: buses.append(_KernelFilteredBus(cfg.channel)) or buses[-1])
    async with te:
        assert await te.wait_connected(HANG_S)
        filters = buses[0].applied[-1]
        codec = te.codec
        assert {f["can_id"] for f in filters} == codec.frames_sent_by("INV") == {0x0A0, 0x0A1, 0x0B0, 0x0B1, 0x2D0}
        assert all(f["can_mask"] == 0x7FF and f["extended"] is False for f in filters)
        peer = can.Bus(interface="virtual", channel=virtual_channel)
        try:
            peer.send(can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False))  # foreign
            peer.send(can.Message(arbitration_id=0x0A0, data=FrameCodec(DBC_PATH).encode(
                "INV_Currents", dict(INV_Id=1.0, INV_Iq=2.0, INV_IphRms=3.0)), is_extended_id=False))
            assert await _until(lambda: te.codec.stats.received["INV_Currents"] == 1)
        finally:
            peer.shutdown()
    assert te.stats.rx_messages == 1 and te.codec.stats.unknown_id == 0  # the foreign frame never came up


async def test_software_filtering_interfaces_count_unknown_ids(virtual_channel):
    """Where filters would only run in Python (virtual, udp_multicast) none are kept: the codec's
    lookup is the filter and counts what it rejects."""
    te = CanTransport(_cfg(virtual_channel, "TE"), FrameCodec(DBC_PATH))
    async with te:
        assert te.bus.filters is None
        peer = can.Bus(interface="virtual", channel=virtual_channel)
        try:
            for fid in (0x123, 0x124, 0x7FF):
                peer.send(can.Message(arbitration_id=fid, data=bytes(8), is_extended_id=False))
            assert await _until(lambda: te.codec.stats.unknown_id == 3)
        finally:
            peer.shutdown()
    assert te.stats.rx_messages == 3
