"""A silent bus with the frame clock: no frames, hence no ticks, yet TE_Limits carries the safe limit
(the derating policy between ticks). The metrics, the log and the frame must say the same: the
limits the bus carries, every input stale, how long the bus has been silent. Checked against an
independent listener that decodes TE_Limits with cantools and the packaged DBC."""
from __future__ import annotations

import asyncio
import logging
import time
from importlib import resources

import can
import cantools
import pytest
from svc_testlib import running, scrape, sim_until

from thermal_edge.bus import DerateReason, FrameCodec

SAFE_A = 10.0


def _limits_on_the_bus(listener: can.BusABC, db, seconds: float) -> list[dict]:
    """TE_Limits decoded by cantools from what ``listener`` receives in the next ``seconds``."""
    msg_def = db.get_message_by_name("TE_Limits")
    got, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        msg = listener.recv(0.05)
        if msg is not None and msg.arbitration_id == msg_def.frame_id:
            got.append(msg_def.decode(msg.data, decode_choices=False))
    return got


@pytest.mark.async_timeout(90)
async def test_a_silent_bus_shows_in_the_metrics_and_the_log_as_on_the_bus(tmp_path, channel, caplog):
    caplog.set_level(logging.INFO, logger="thermal_edge")
    with resources.as_file(resources.files("thermal_edge.bus") / "thermal_edge.dbc") as dbc:
        db = cantools.database.load_file(str(dbc))
    async with running(tmp_path, channel, metrics=True, transmit={"bus_silence_s": 0.5}) as (svc, emu):
        await sim_until(emu, 200)
        port = svc.metrics_address[1]
        before = await asyncio.to_thread(scrape, port)
        assert before["thermal_edge_current_limit_amperes"] > SAFE_A  # the machine cold: full current
        assert before["thermal_edge_bus_silent_seconds"] == 0.0
        listener = can.Bus(interface="virtual", channel=channel)
        try:
            # a busy host can leave the emulator's frames apart by more than bus_silence_s while it
            # warms up: that silence was said and ended before; this one is judged from here on
            said_before = len(caplog.records)
            emu.stop()  # the inverter goes silent: no frames, no ticks (frame clock)
            await asyncio.sleep(1.5)
            ticks = svc.engine.ticks  # the frames in flight ticked; none come after them
            while listener.recv(0) is not None:  # what was queued before
                pass
            frames = await asyncio.to_thread(_limits_on_the_bus, listener, db, 0.6)
            m = await asyncio.to_thread(scrape, port)
            assert svc.engine.ticks == ticks  # no tick since: only the policy between ticks speaks
            assert frames and all(f["TE_DerateReason"] == DerateReason.STALE_INPUT for f in frames)
            sent = frames[-1]
            assert m["thermal_edge_current_limit_amperes"] == pytest.approx(sent["TE_CurrentLimit"], abs=0.05)
            assert m["thermal_edge_torque_limit_newton_meters"] == pytest.approx(sent["TE_TorqueLimit"], abs=0.2)
            assert sent["TE_CurrentLimit"] <= SAFE_A
            assert m["thermal_edge_derate_reason_code"] == int(DerateReason.STALE_INPUT)
            assert m['thermal_edge_derate_reason{thermal_edge_derate_reason="stale_input"}'] == 1.0
            stale = {k: v for k, v in m.items() if k.startswith("thermal_edge_input_stale{")}
            assert stale and all(v == 1.0 for v in stale.values())
            assert m["thermal_edge_bus_silent_seconds"] > 1.5
            warned = [r for r in caplog.records[said_before:] if "the bus is silent" in r.getMessage()]
            assert len(warned) == 1 and warned[0].levelno == logging.WARNING

            # frames again (two counters: whichever the codec last saw, one of them is a new frame)
            codec = FrameCodec()
            for c in (0, 1):
                listener.send(can.Message(arbitration_id=codec.frame_id("INV_Currents"), is_extended_id=False,
                                          data=codec.encode("INV_Currents", {"INV_Id": 0.0, "INV_Iq": 0.0,
                                                                             "INV_IphRms": 0.0}, counter=c)))
            deadline = time.monotonic() + 30  # a hang guard: the next TE_Limits period says it
            while time.monotonic() < deadline and not any("frames accepted again" in r.getMessage()
                                                          for r in caplog.records[said_before:]):
                await asyncio.sleep(0.05)
            m = await asyncio.to_thread(scrape, port)
            assert m["thermal_edge_bus_silent_seconds"] == 0.0
            assert [r.getMessage() for r in caplog.records[said_before:] if "the bus is silent" in r.getMessage()] == \
                [warned[0].getMessage()]  # said once
            assert any("frames accepted again" in r.getMessage() for r in caplog.records[said_before:])
        finally:
            listener.shutdown()
