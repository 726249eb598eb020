"""The service as on a drive: wall clock, real time. Ticks at 1 Hz from the timer, TE_Limits every
100 ms and the 1 s frames from cyclic senders, metrics on 127.0.0.1, watchdog pings while ticking."""
from __future__ import annotations

import asyncio
import time
import urllib.request

import pytest
from svc_testlib import NotifySocket, async_wait_until, edge_raw, emulator_config, write_yaml

from thermal_edge.bus import DerateReason
from thermal_edge.config import load_config
from thermal_edge.service import EdgeService
from thermal_edge.service.systemd import SystemdNotifier
from thermal_edge.sim.inverter import InverterEmulator

#: generous upper bound of every wait on a condition (a hang guard, not a performance bound), s
HANG_S = 120.0
#: the input time-outs of these runs: the longest the configuration takes, beyond a busy host's stalls
#: (staleness is tested elsewhere)
TIMEOUTS = {"INV_Currents": 10.0, "INV_Mechanics": 10.0, "INV_StatorTemps": 10.0, "INV_AmbientTemps": 10.0}


@pytest.mark.async_timeout(300)
async def test_real_time_service_on_the_wall_clock(tmp_path, channel):
    """The counts are waited for (a busy host delays ticks and frames, it must not stop them) and
    bounded above by what their cadence allows in the time measured here: the wall clock's ticks,
    fixed-rate senders and the watchdog never run faster than their period."""
    raw = edge_raw(tmp_path / "state", {"interface": "virtual", "channel": channel}, table4=False, adapt=False,
                   metrics_port=0, clock={"mode": "wall"}, timeouts=TIMEOUTS)
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", raw))
    notify = NotifySocket(tmp_path / "notify")
    notify.start_thread()
    svc = EdgeService(cfg, notifier=SystemdNotifier({"NOTIFY_SOCKET": notify.address, "WATCHDOG_USEC": "600000"}))
    ticks: list[float] = []
    svc.on_tick.append(lambda out: ticks.append(out.t))
    t_start = time.monotonic()
    await svc.start()
    try:
        host, port = svc.metrics_address
        assert host == "127.0.0.1"
        emu = InverterEmulator(emulator_config(duration_s=3600.0, speed=1.0, t0=time.time(), current_period_s=0.01,
                                               temperature_period_s=0.1, plant_dt_s=0.1, flow_control=False),
                               {"interface": "virtual", "channel": channel, "preserve_timestamps": True})
        t = time.monotonic()
        task = asyncio.get_running_loop().create_task(emu.run())
        got = emu.summary.frames_received

        def enough() -> bool:
            return (svc.engine.ticks >= 4 and got.get("TE_Limits", 0) >= 30 and got.get("TE_Status", 0) >= 3
                    and list(notify.messages).count("WATCHDOG=1") >= 6)

        waited = await async_wait_until(enough, HANG_S)
        emu.stop()
        s = await asyncio.wait_for(task, HANG_S)
        emu_s = time.monotonic() - t
        body = await asyncio.get_running_loop().run_in_executor(
            None, lambda: urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=HANG_S).read().decode())
    finally:
        await svc.stop()
        run_s = time.monotonic() - t_start
        notify.close()
    assert waited, (svc.engine.ticks, got, list(notify.messages).count("WATCHDOG=1"))
    assert emu.elapsed <= emu_s + 0.05  # the emulator runs in real time, never ahead of it
    # 1 Hz on whole boundaries of the wall clock, missed ones skipped, never more than the time allows
    assert svc.engine.ticks == len(ticks) <= run_s + 1
    assert all(t == round(t) for t in ticks) and all(b > a for a, b in zip(ticks, ticks[1:]))
    assert s.frames_received["TE_Limits"] <= run_s / 0.1 + 2  # every 100 ms
    assert s.frames_received["TE_Status"] <= run_s + 1  # every second
    assert s.rx_lost == 0 and svc.codec.stats.lost == 0
    assert svc.engine.last.initialized
    # a cold start: the limit climbs from the safe start value at the rise rate, nothing is faulty
    assert s.limits_received and emu.last_reason in (DerateReason.STARTING, DerateReason.RECOVERING, DerateReason.NONE)
    assert "thermal_edge_up 1.0" in body and "thermal_edge_ticks_total" in body
    msgs = list(notify.messages)
    assert msgs[0].startswith("READY=1") and msgs.count("WATCHDOG=1") <= run_s / 0.3 + 1  # every 0.3 s while ticking
    assert msgs[-1].startswith("STOPPING=1")


@pytest.mark.async_timeout(300)
async def test_te_limits_keep_their_cadence_while_the_event_loop_is_blocked(tmp_path, channel, unit_nice):
    """A tick that blocks the loop (a slow adaptation step, a stuck callback), twice: TE_Limits,
    received by an independent python-can bus (stamped with the wall clock when sent), goes on while
    the loop cannot run. The tick blocks until five TE_Limits sent after it began have arrived: a
    sender on the loop could send none, and the tick would block until the hang guard. The largest
    gap a busy host leaves is the fault bench's figure (``benchmarks/faults``, the 300 ms contract)."""
    import threading

    import can

    raw = edge_raw(tmp_path / "state", {"interface": "virtual", "channel": channel}, table4=False, adapt=False,
                   clock={"mode": "wall"}, timeouts=TIMEOUTS)
    svc = EdgeService(load_config(write_yaml(tmp_path / "edge.yaml", raw)))
    rx = can.Bus(interface="virtual", channel=channel)
    stamps: list[float] = []
    arrived = threading.Condition()
    blocked: list[tuple[float, float, bool]] = []  # (began, ended, the frames came) per blocking tick

    def block(out):  # runs on the event loop, inside the tick
        if len(blocked) < 2:
            began = time.time()
            with arrived:
                came = arrived.wait_for(lambda: sum(t > began for t in stamps) >= 5, HANG_S)
            blocked.append((began, time.time(), came))

    svc.on_tick.append(block)
    done = threading.Event()

    def receive() -> None:  # in a thread of the test: the service's loop runs meanwhile
        end = time.monotonic() + HANG_S
        while not done.is_set() and time.monotonic() < end:
            msg = rx.recv(timeout=0.05)
            if msg is not None and msg.arbitration_id == 0x2A0:
                with arrived:
                    stamps.append(msg.timestamp)
                    arrived.notify_all()

    await svc.start()
    try:
        reader = asyncio.get_running_loop().run_in_executor(None, receive)
        assert await async_wait_until(lambda: len(blocked) == 2 and sum(t > blocked[1][1] for t in stamps) >= 3,
                                      3 * HANG_S), blocked
    finally:
        done.set()
        await svc.stop()
        await reader
        rx.shutdown()
    assert [came for _, _, came in blocked] == [True, True]  # the frames came while the loop was blocked, twice
    for began, ended, _ in blocked:
        assert sum(began < t < ended for t in stamps) >= 5
