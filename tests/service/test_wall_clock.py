"""The service as on a drive: wall clock, real time. Ticks at 1 Hz from the timer, TE_Limits every
100 ms and the 1 s frames from cyclic senders, metrics on 127.0.0.1, watchdog pings while ticking."""
from __future__ import annotations

import asyncio
import time
import urllib.request

import pytest
from svc_testlib import NotifySocket, edge_raw, emulator_config, write_yaml

from thermal_edge.bus import DerateReason
from thermal_edge.config import load_config
from thermal_edge.service import EdgeService
from thermal_edge.service.systemd import SystemdNotifier
from thermal_edge.sim.inverter import InverterEmulator


@pytest.mark.async_timeout(40)
async def test_real_time_service_on_the_wall_clock(tmp_path, channel):
    raw = edge_raw(tmp_path / "state", {"interface": "virtual", "channel": channel}, table4=False, adapt=False,
                   metrics_port=0, clock={"mode": "wall"})
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", raw))
    notify = NotifySocket(tmp_path / "notify")
    notify.start_thread()
    svc = EdgeService(cfg, notifier=SystemdNotifier({"NOTIFY_SOCKET": notify.address, "WATCHDOG_USEC": "600000"}))
    t_start = time.monotonic()
    await svc.start()
    try:
        host, port = svc.metrics_address
        assert host == "127.0.0.1"
        emu = InverterEmulator(emulator_config(duration_s=4.5, speed=1.0, t0=time.time(), current_period_s=0.01,
                                               temperature_period_s=0.1, plant_dt_s=0.1, flow_control=False),
                               {"interface": "virtual", "channel": channel, "preserve_timestamps": True})
        t = time.monotonic()
        s = await emu.run()
        emu_s = time.monotonic() - t
        body = await asyncio.get_running_loop().run_in_executor(
            None, lambda: urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode())
    finally:
        await svc.stop()
        run_s = time.monotonic() - t_start
        notify.close()
    # the counts against the time measured here: at most what their cadence allows in that time (the
    # clock is the wall's, never faster), at least half of it (a generous bound: a busy host delays
    # ticks and frames, it must not stop them)
    assert emu_s >= 4.5 - 0.05  # the emulator runs in real time
    assert run_s / 2 <= svc.engine.ticks <= run_s + 1  # 1 Hz
    assert emu_s / 0.1 / 2 <= s.frames_received["TE_Limits"] <= run_s / 0.1 + 2  # every 100 ms
    assert emu_s / 2 <= s.frames_received["TE_Status"] <= run_s + 1  # every second
    assert s.rx_lost == 0 and svc.codec.stats.lost == 0
    assert svc.max_lateness_s < 1.0  # no tick late by a whole period (how late depends on the host's load)
    assert svc.engine.last.initialized
    # 4.5 s after a cold start the limit still climbs from the safe start value at the rise rate
    assert s.limits_received and emu.last_reason in (DerateReason.STARTING, DerateReason.RECOVERING, DerateReason.NONE)
    assert "thermal_edge_up 1.0" in body and "thermal_edge_ticks_total" in body
    msgs = list(notify.messages)
    assert msgs[0].startswith("READY=1") and msgs.count("WATCHDOG=1") >= run_s / 0.3 / 2  # every 0.3 s while ticking
    assert msgs[-1].startswith("STOPPING=1")


@pytest.mark.async_timeout(40)
async def test_te_limits_keep_their_cadence_while_the_event_loop_is_blocked(tmp_path, channel, unit_nice):
    """A tick that blocks the loop for 1 s (a slow adaptation step, a stuck callback): TE_Limits,
    received by an independent python-can bus and timed by its receive stamps, never pauses."""
    import can

    raw = edge_raw(tmp_path / "state", {"interface": "virtual", "channel": channel}, table4=False, adapt=False,
                   clock={"mode": "wall"})
    svc = EdgeService(load_config(write_yaml(tmp_path / "edge.yaml", raw)))
    blocked = []

    def block(out):  # runs on the event loop, inside the tick
        if len(blocked) < 2:
            t0 = time.monotonic()
            time.sleep(1.0)
            blocked.append(time.monotonic() - t0)

    svc.on_tick.append(block)
    rx = can.Bus(interface="virtual", channel=channel)
    stamps: list[float] = []

    def receive(seconds: float) -> None:  # in a thread of the test: the service's loop runs meanwhile
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            msg = rx.recv(timeout=0.05)
            if msg is not None and msg.arbitration_id == 0x2A0:
                stamps.append(msg.timestamp)

    await svc.start()
    try:
        await asyncio.get_running_loop().run_in_executor(None, receive, 4.5)
    finally:
        await svc.stop()
        rx.shutdown()
    assert len(blocked) == 2 and min(blocked) >= 1.0  # the loop really was blocked, twice
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    # below the inverter's 300 ms drop-out (what the product promises, the fault bench's GAP_S),
    # far below the 1 s the loop is blocked; 1.5 periods (150 ms) failed once at 154 ms with a
    # second suite beside this one
    assert len(stamps) >= 30 and max(gaps) < 0.3, f"largest TE_Limits gap {max(gaps):.3f} s"
