"""Bad input never crashes the service, and stale or faulty input and a diverged model force the
safe limit with the right reason on the bus (as the inverter sees it: the emulator's received
TE_Limits). One process, python-can ``virtual`` bus, frame clock, accelerated."""
from __future__ import annotations

import asyncio
import math
import time

import can
import numpy as np
import pytest
from svc_testlib import MAX_LEAD_S, PLANT_DT_S, running, scrape, sim_until

from thermal_edge.bus import DerateReason, FrameCodec, SensorStatus, TeState

SAFE = 10.0


#: simulated time from the tick that decides a limit to the emulator's record of it: the tick itself,
#: the emulator's lead over the service, and the plant step in which the emulator drains the frame
ARRIVES_WITHIN_S = 1.0 + MAX_LEAD_S + PLANT_DT_S


def reasons_since(emu, t_rel: float) -> list[tuple[float, float, int]]:
    """TE_Limits values in force from ``t_rel`` (simulated, since the start) on: the one received last
    before it, and every change after it (the emulator logs changes)."""
    log = [(t - emu.t0, cur, r) for t, cur, tq, r in emu.limit_log]
    before = [e for e in log if e[0] < t_rel]
    return before[-1:] + [e for e in log if e[0] >= t_rel]


@pytest.mark.async_timeout(60)
async def test_malformed_frames_unknown_ids_and_a_corrupt_state_file(tmp_path, channel, caplog):
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "state.json").write_text('{"format": "thermal_edge.state", "version": 1, "T": [1, 2')  # torn
    async with running(tmp_path, channel, metrics=True) as (svc, emu):
        await sim_until(emu, 60)
        codec = FrameCodec()
        good = codec.encode("INV_Currents", {"INV_Id": 0.0, "INV_Iq": 20.0, "INV_IphRms": 14.1}, counter=3)
        bad_crc = bytes(good[:7]) + bytes([good[7] ^ 0x5A])
        emu.inject(0x0A0, bad_crc)  # wrong CRC
        emu.inject(0x0A0, good[:4])  # wrong DLC
        emu.inject(0x123, bytes(8))  # unknown identifier
        emu.inject(0x18FF00A0, bytes(8), extended=True)  # 29-bit identifier
        emu.inject(0x0B0, b"", remote=True)  # remote frame
        emu.inject(0x0B0, b"\xff" * 8)  # garbage on a known identifier
        await sim_until(emu, 120)
        m = scrape(svc.metrics.port)
        assert m['thermal_edge_frames_dropped_total{reason="crc"}'] >= 2
        assert m['thermal_edge_frames_dropped_total{reason="dlc"}'] >= 2  # short + remote
        assert m['thermal_edge_frames_dropped_total{reason="unknown_id"}'] >= 2  # unknown + extended
        assert m["thermal_edge_state_load_errors_total"] == 1
        assert m["thermal_edge_state_code"] == int(TeState.NOMINAL)
        # the journal says so too: a WARNING line with the count by reason (at most one a minute)
        said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "frame(s) dropped" in r.getMessage()]
        assert said and all("crc" in ln or "dlc" in ln or "unknown_id" in ln for ln in said), said
        dropped = sum(v for k, v in m.items() if k.startswith("thermal_edge_frames_dropped_total"))
        assert sum(int(ln.split()[0]) for ln in said) == dropped
        ticks = svc.engine.ticks
        await sim_until(emu, 150)
        assert svc.engine.ticks > ticks  # still ticking
    aside = list((tmp_path / "state").glob("state.json.corrupt-*"))
    assert len(aside) == 1 and (tmp_path / "state" / "state.json").is_file()  # a good state was written since


@pytest.mark.async_timeout(60)
async def test_open_circuit_and_implausible_sensors_force_the_safe_limit(tmp_path, channel):
    async with running(tmp_path, channel) as (svc, emu):
        await sim_until(emu, 300)
        assert emu.last_reason in (DerateReason.NONE, DerateReason.LOOK_AHEAD)
        emu.sensor_status["end_winding"] = int(SensorStatus.OPEN_CIRCUIT)
        t_fault = emu.elapsed
        await sim_until(emu, t_fault + 20)
        seen = reasons_since(emu, t_fault + 3 + ARRIVES_WITHIN_S)
        assert seen and all(r == DerateReason.SENSOR_FAULT and cur <= SAFE for _, cur, r in seen)
        assert svc.engine.last.state == TeState.DEGRADED
        assert svc.engine.accumulator.bad_readings["open_circuit"] == 1
        # back to valid: the limit recovers slowly, no longer for a sensor fault
        emu.sensor_status.clear()
        t_ok = emu.elapsed
        await sim_until(emu, t_ok + 60)
        assert emu.last_reason != DerateReason.SENSOR_FAULT and emu.current_limit > SAFE
        # an implausible reading (valid status, 400 degC saturates to 359.4 > 250) is a sensor fault too
        emu.sensor_offset["housing"] = 400.0
        t_bad = emu.elapsed
        await sim_until(emu, t_bad + 10)
        assert emu.last_reason == DerateReason.SENSOR_FAULT and emu.current_limit <= SAFE
        assert svc.engine.accumulator.bad_readings["out_of_range"] >= 1


@pytest.mark.async_timeout(60)
async def test_stator_sensors_not_fitted_force_the_safe_limit(tmp_path, channel):
    async with running(tmp_path, channel, metrics=True) as (svc, emu):
        await sim_until(emu, 120)
        for sensor in ("slot_winding", "end_winding", "housing"):
            emu.sensor_status[sensor] = int(SensorStatus.NOT_FITTED)
        t_fault = emu.elapsed
        await sim_until(emu, t_fault + 10)
        seen = reasons_since(emu, t_fault + 3 + ARRIVES_WITHIN_S)
        assert seen and all(r == DerateReason.SENSOR_FAULT and cur <= SAFE for _, cur, r in seen)
        m = scrape(svc.metrics.port)
        for sensor in ("slot_winding", "end_winding", "housing"):
            assert m[f'thermal_edge_sensor_fault{{kind="not_fitted",sensor="{sensor}"}}'] == 1.0
        assert m['thermal_edge_bad_readings_total{kind="not_fitted"}'] == 3  # one per sensor entering the fault
        emu.sensor_status.clear()
        t_ok = emu.elapsed
        await sim_until(emu, t_ok + 60)
        assert emu.last_reason != DerateReason.SENSOR_FAULT and emu.current_limit > SAFE


@pytest.mark.async_timeout(60)
async def test_stale_temperatures_force_the_safe_limit(tmp_path, channel):
    async with running(tmp_path, channel) as (svc, emu):
        await sim_until(emu, 200)
        emu.paused.add("INV_StatorTemps")
        t_stop = emu.elapsed
        await sim_until(emu, t_stop + 15)
        seen = reasons_since(emu, t_stop + 3 + ARRIVES_WITHIN_S)  # the 3 s timeout, then the limit's way
        assert seen and all(r == DerateReason.STALE_INPUT and cur <= SAFE for _, cur, r in seen)
        assert svc.engine.last.stale == ["INV_StatorTemps"]
        emu.paused.clear()
        await sim_until(emu, emu.elapsed + 60)
        assert emu.last_reason != DerateReason.STALE_INPUT


@pytest.mark.async_timeout(60)
async def test_inverter_silent_limits_still_sent_with_the_safe_value(tmp_path, channel):
    async with running(tmp_path, channel, transmit={"bus_silence_s": 0.5}) as (svc, emu):
        await sim_until(emu, 200)
        listener = can.Bus(interface="virtual", channel=channel)
        codec = FrameCodec()
        try:
            emu.stop()  # the inverter goes silent: no frames, no ticks (frame clock)
            # TE_Limits keeps coming (its cadence: test_wall_clock), and once the bus has been silent for
            # bus_silence_s (wall clock: a busy host may call a silence early, before frames still queued
            # arrive), with the safe limit for stale input: ten in a row waited for (a generous hang guard)
            run: list[dict] = []
            stale: list[dict] = []
            end = time.monotonic() + 60.0
            while len(run) < 10 and time.monotonic() < end:
                msg = listener.recv(0)
                if msg is None:
                    await asyncio.sleep(0.01)
                    continue
                f = codec.decode_message(msg)
                if f is None or f.name != "TE_Limits":
                    continue
                if f.signals["TE_DerateReason"] == DerateReason.STALE_INPUT:
                    run.append(f.signals)
                    stale.append(f.signals)
                else:
                    run.clear()
            assert len(run) == 10
            assert all(s["TE_CurrentLimit"] <= SAFE for s in stale)
        finally:
            listener.shutdown()


@pytest.mark.async_timeout(60)
async def test_diverged_model_forces_the_safe_limit_with_model_fault(tmp_path, channel):
    async with running(tmp_path, channel) as (svc, emu):
        await sim_until(emu, 300)
        for s in ("slot_winding", "end_winding", "housing"):  # readings far from anything the model can explain
            emu.sensor_offset[s] = 60.0
        t_bad = emu.elapsed
        await sim_until(emu, t_bad + 15)
        seen = reasons_since(emu, t_bad + 8 + ARRIVES_WITHIN_S)  # 5 ticks above 15 K
        assert seen and all(r == DerateReason.MODEL_FAULT and cur <= SAFE for _, cur, r in seen)
        assert svc.engine.model_faults >= 1
        assert svc.engine.last.state == TeState.FAULT  # within the 30 s hold after the fault


def test_non_finite_state_is_a_model_fault(tmp_path, model):
    """The engine alone: a NaN in the state (numerical breakdown) forces the safe limit at the next tick."""
    from test_persistence import _engine_config, _feed

    from thermal_edge.lptn import steady_state
    from thermal_edge.service.engine import ThermalEngine

    eng = ThermalEngine(_engine_config(tmp_path), model, None, worker_mode="sync")
    T, _ = steady_state(model, {"speed_rpm": 600.0, "i_rms": 12.0, "torque_nm": 67.0, "ambient_c": 25.0})
    for k in range(1, 4):
        out = _feed(eng, model, 100.0 + k, T, i=12.0, speed=600.0)
    assert out.limits.reason != DerateReason.MODEL_FAULT
    eng.estimate.observer.T[5] = math.nan
    out = _feed(eng, model, 104.0, T, i=12.0, speed=600.0)
    assert out.limits.reason == DerateReason.MODEL_FAULT and out.state == TeState.FAULT
    assert out.limits.current_a <= SAFE
    assert np.all(np.isfinite(eng.estimate.observer.T))  # restarted from the readings


def test_model_fault_reports_the_error_that_caused_it(tmp_path, model):
    """The tick that faults on the open-loop prediction error reports that error (the readings'
    60 K offset), not the error against the state re-initialised from those readings."""
    from test_persistence import _engine_config, _feed

    from thermal_edge.lptn import steady_state
    from thermal_edge.service.engine import ThermalEngine

    eng = ThermalEngine(_engine_config(tmp_path), model, None, worker_mode="sync")
    T, _ = steady_state(model, {"speed_rpm": 600.0, "i_rms": 12.0, "torque_nm": 67.0, "ambient_c": 25.0})
    for k in range(1, 4):
        out = _feed(eng, model, 100.0 + k, T, i=12.0, speed=600.0)
    assert out.limits.reason != DerateReason.MODEL_FAULT
    before = {s: out.prediction[model.node_index(n)] for s, n in model.sensors.items()}
    hot = T + 60.0  # every reading 60 K above anything the model predicts (limit: 40 K)
    ticks = eng.config.derating.faults.prediction_error_ticks  # in a row: a fault, not a glitch
    for k in range(ticks):  # not trusted from the first tick (the safe limit), a fault at the last
        out = _feed(eng, model, 104.0 + k, hot, i=12.0, speed=600.0)
        assert out.limits.reason == DerateReason.MODEL_FAULT and eng.health.faults == (k == ticks - 1)
    assert out.state == TeState.FAULT and out.limits.reason == DerateReason.MODEL_FAULT
    for s, n in model.sensors.items():
        # a few more 1 s steps from the steady state barely move the prediction
        assert out.pred_error[s] == pytest.approx(before[s] - hot[model.node_index(n)], abs=1.0)
        assert out.pred_error[s] < -55.0
    # the state was restarted from the readings: the next tick's error is small again
    out = _feed(eng, model, 104.0 + ticks, hot, i=12.0, speed=600.0)
    assert all(abs(e) < 5.0 for e in out.pred_error.values())
