"""Input accumulation per tick, against direct computations on the same frame values."""
from __future__ import annotations

import math

import numpy as np
import pytest
from svc_testlib import EDGE_YAML

from thermal_edge.bus import DecodedFrame, SensorStatus
from thermal_edge.config import load_config
from thermal_edge.lptn import Role, load_model
from thermal_edge.service.clock import FrameClock, first_boundary
from thermal_edge.service.inputs import InputAccumulator


def frame(name: str, t: float, **signals: float) -> DecodedFrame:
    return DecodedFrame(name, 0, dict(signals), 0, t)


def zoh_mean(times: list[float], values: list[float | None], t_end: float) -> float:
    """The mean over time of values held from their frame to the next (None: a bad frame, whose
    time counts for nothing) up to ``t_end``, by explicit durations."""
    ends = [*times[1:], t_end]
    kept = [(v, e - t) for t, e, v in zip(times, ends, values) if v is not None]
    return sum(v * d for v, d in kept) / sum(d for _, d in kept)


def stator(t: float, slot=60.0, end=62.0, hous=40.0, s_slot=0, s_end=0, s_hous=0) -> DecodedFrame:
    return frame("INV_StatorTemps", t, INV_T_WindingSlot=slot, INV_T_EndWinding=end, INV_T_Housing=hous,
                 INV_S_WindingSlot=s_slot, INV_S_EndWinding=s_end, INV_S_Housing=s_hous)


def ambient(t: float, amb=25.0, status=0) -> DecodedFrame:
    return frame("INV_AmbientTemps", t, INV_T_Ambient=amb, INV_T_Coolant=math.nan, INV_S_Ambient=status,
                 INV_S_Coolant=int(SensorStatus.NOT_FITTED))


def accumulator(cfg) -> InputAccumulator:
    """The accumulator as the service builds it: with its model's input roles."""
    return InputAccumulator(cfg, load_model(cfg.model.path).input_roles)


@pytest.fixture
def acc() -> InputAccumulator:
    return accumulator(load_config(EDGE_YAML))


def test_current_is_the_root_mean_square_over_every_frame(acc):
    rng = np.random.default_rng(1)
    iq = 20 + 15 * np.sin(np.arange(100) / 3.0)  # strongly varying current within the tick
    idd = rng.normal(0, 3, 100)
    speed = 900 + rng.normal(0, 4, 100)
    for k in range(100):
        t = 10.0 + k * 0.01
        acc.add(frame("INV_Currents", t, INV_Id=idd[k], INV_Iq=iq[k], INV_IphRms=0.0), t)
        acc.add(frame("INV_Mechanics", t, INV_Speed=speed[k], INV_Torque=iq[k] * 3, INV_Udc=560.0), t)
    acc.add(stator(10.5), 10.5)
    acc.add(ambient(10.5), 10.5)
    ti = acc.take(11.0)
    expected = math.sqrt(np.mean(idd**2 + iq**2) / 2)  # peak d/q -> RMS phase current, mean square
    square_of_mean = math.sqrt(np.mean(idd) ** 2 + np.mean(iq) ** 2) / math.sqrt(2)
    assert ti.inputs["i_rms"] == pytest.approx(expected, rel=1e-12)
    assert abs(expected - square_of_mean) > 0.5  # the distinction matters here
    assert ti.inputs["speed_rpm"] == round(np.mean(speed))  # mean, rounded to the 1 rpm resolution
    assert ti.inputs["torque_nm"] == pytest.approx(np.mean(iq * 3))
    assert ti.inputs["ambient_c"] == 25.0
    assert ti.measured == {"slot_winding": 60.0, "end_winding": 62.0, "housing": 40.0}
    assert ti.ages["slot_winding"] == pytest.approx(0.5)
    assert ti.frames["INV_Currents"] == 100 and not ti.stale and not ti.faults
    # the next tick starts afresh; without current frames the value is held and flagged stale after the timeout
    ti2 = acc.take(12.0)
    assert ti2.inputs["i_rms"] == ti.inputs["i_rms"] and "i_rms" not in ti2.fresh
    assert "INV_Currents" in ti2.stale  # 1 s > 0.5 s timeout


def test_rms_mode_uses_the_phase_current_signal(tmp_path):
    import yaml
    from svc_testlib import REPO, write_yaml

    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["model"]["path"] = str(REPO / "config" / "machines" / "pm10kw.yaml")
    raw["codec"]["dbc"] = str(REPO / "dbc" / "thermal_edge.dbc")
    raw["signals"]["inputs"]["i_rms"] = {"frame": "INV_Currents", "reduce": "rms", "signal": "INV_IphRms"}
    acc = accumulator(load_config(write_yaml(tmp_path / "edge.yaml", raw)))
    vals, times = [10.0, 20.0, 30.0], [0.0, 0.01, 0.02]
    for t, v in zip(times, vals):
        acc.add(frame("INV_Currents", t, INV_Id=0.0, INV_Iq=0.0, INV_IphRms=v), t)
    # the mean square over time: the last value holds the rest of the tick
    expected = math.sqrt(zoh_mean(times, list(np.square(vals)), 1.0))
    assert acc.take(1.0).inputs["i_rms"] == pytest.approx(expected) and expected > 29.0


def test_sensor_faults_are_flagged_and_counted(acc):
    acc.add(ambient(0.1), 0.1)
    acc.add(stator(0.1, s_end=int(SensorStatus.OPEN_CIRCUIT), end=math.nan), 0.1)
    ti = acc.take(1.0)
    assert ti.faults == {"end_winding": "open_circuit"}
    assert math.isnan(ti.measured["end_winding"]) and ti.measured["slot_winding"] == 60.0
    acc.add(stator(1.1, s_slot=int(SensorStatus.SHORT_CIRCUIT)), 1.1)
    acc.add(stator(1.2, hous=300.0), 1.2)  # valid status, implausible value
    ti = acc.take(2.0)
    assert ti.faults["slot_winding"] == "short_circuit" and ti.faults["housing"] == "out_of_range"
    assert "end_winding" not in ti.faults  # it reported a valid value again
    assert acc.bad_readings == {"open_circuit": 1, "short_circuit": 1, "out_of_range": 1}
    # a required sensor "not fitted" is a fault: the model must not run blind on it
    acc.add(stator(2.1, s_hous=int(SensorStatus.NOT_FITTED), hous=math.nan), 2.1)
    ti = acc.take(3.0)
    assert ti.faults == {"housing": "not_fitted"} and math.isnan(ti.measured["housing"])
    assert acc.bad_readings["not_fitted"] == 1


def test_not_fitted_is_a_fault_only_for_a_required_sensor(tmp_path):
    import yaml
    from svc_testlib import REPO, write_yaml

    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["model"]["path"] = str(REPO / "config" / "machines" / "pm10kw.yaml")
    raw["codec"]["dbc"] = str(REPO / "dbc" / "thermal_edge.dbc")
    raw["signals"]["sensors"]["housing"]["required"] = False
    acc = accumulator(load_config(write_yaml(tmp_path / "edge.yaml", raw)))
    nf = int(SensorStatus.NOT_FITTED)
    acc.add(ambient(0.1), 0.1)
    acc.add(stator(0.1, s_hous=nf, hous=math.nan), 0.1)
    ti = acc.take(1.0)
    assert not ti.faults and math.isnan(ti.measured["housing"]) and ti.measured["slot_winding"] == 60.0
    # all three stator sensors "not fitted": the two required ones are faults
    acc.add(stator(1.1, s_slot=nf, s_end=nf, s_hous=nf, slot=math.nan, end=math.nan, hous=math.nan), 1.1)
    ti = acc.take(2.0)
    assert ti.faults == {"slot_winding": "not_fitted", "end_winding": "not_fitted"}
    assert all(math.isnan(v) for v in ti.measured.values())


def test_stale_sensor_values_are_not_used(acc):
    acc.add(stator(0.0), 0.0)
    acc.add(ambient(0.0), 0.0)
    assert acc.take(1.0).measured["housing"] == 40.0
    ti = acc.take(5.0)  # the temperature frames stopped: older than their 1 s timeout
    assert all(math.isnan(v) for v in ti.measured.values())
    assert set(ti.stale) >= {"INV_StatorTemps", "INV_AmbientTemps"}
    assert ti.inputs["ambient_c"] == 25.0  # the model keeps running on the last ambient
    assert ti.ages["housing"] == pytest.approx(5.0)


def test_malformed_frame_is_counted_not_raised(acc):
    acc.add(frame("INV_Currents", 0.0, INV_Id=1.0), 0.0)  # signals missing
    acc.add(frame("INV_Unknown", 0.0), 0.0)  # not mapped: ignored
    assert acc.malformed == 1


def test_frame_clock_ticks_at_boundaries_crossed():
    c = FrameClock(1.0)
    assert c.observe(100.2) == []
    assert c.observe(100.9) == []
    assert c.observe(101.0) == [101.0]
    assert c.observe(100.5) == []  # backwards: ignored for the clock
    assert c.observe(104.3) == [102.0, 103.0, 104.0]
    assert first_boundary(7.0, 1.0) == 8.0 and first_boundary(7.2, 0.5) == 7.5


def test_absurd_currents_and_speeds_are_bad_readings_left_out_of_the_mean(acc):
    """1000 A, the d/q signals' 1638 A and +-16000 rpm: each frame out of its
    plausible range (3 x the 40 A maximum current; +-6000 rpm) is left out of the tick's mean, the
    input is faulty (``out_of_range``) for that tick and counted once per entry into the fault."""
    cfg = load_config(EDGE_YAML)
    assert (cfg.signals.valid_current_factor * cfg.derating.max_current_a, cfg.signals.valid_speed_rpm) == (120.0, 6000.0)
    good_iq, good_speed = 30.0 * math.sqrt(2), 900.0  # 30 A rms on q
    for k in range(10):
        t = 10.0 + 0.1 * k
        absurd = k in (3, 7)
        iq = 1000.0 * math.sqrt(2) if k == 3 else 1638.35 if k == 7 else good_iq
        speed = 16000.0 if k == 3 else -16000.0 if k == 7 else good_speed
        acc.add(frame("INV_Currents", t, INV_Id=0.0, INV_Iq=iq, INV_IphRms=0.0), t)
        acc.add(frame("INV_Mechanics", t, INV_Speed=speed, INV_Torque=100.0, INV_Udc=560.0), t)
        assert absurd or iq == good_iq
    acc.add(stator(10.5), 10.5)
    acc.add(ambient(10.5), 10.5)
    ti = acc.take(11.0)
    assert ti.inputs["i_rms"] == pytest.approx(30.0) and ti.inputs["speed_rpm"] == 900.0  # the 8 plausible frames
    assert ti.faults == {"i_rms": "out_of_range", "speed_rpm": "out_of_range"}
    assert acc.bad_readings["out_of_range"] == 2  # one per input entering the fault
    assert {"i_rms", "speed_rpm"} <= set(acc.fault_sources)
    # a tick of only absurd frames: the input holds its last value, still faulty, not counted again
    acc.add(frame("INV_Currents", 11.2, INV_Id=0.0, INV_Iq=1000.0, INV_IphRms=0.0), 11.2)
    ti = acc.take(12.0)
    assert ti.inputs["i_rms"] == pytest.approx(30.0) and ti.faults == {"i_rms": "out_of_range"}
    assert acc.bad_readings["out_of_range"] == 2
    # plausible again (just inside the ranges): no fault
    acc.add(frame("INV_Currents", 12.2, INV_Id=0.0, INV_Iq=119.9 * math.sqrt(2), INV_IphRms=0.0), 12.2)
    acc.add(frame("INV_Mechanics", 12.2, INV_Speed=-6000.0, INV_Torque=0.0, INV_Udc=560.0), 12.2)
    ti = acc.take(13.0)
    # the speed held 900 rpm from its last frame (10.9 s) until 12.2 s: 0.2 s of this tick
    assert not ti.faults and ti.inputs["i_rms"] == pytest.approx(119.9)
    assert ti.inputs["speed_rpm"] == pytest.approx(zoh_mean([12.0, 12.2], [900.0, -6000.0], 13.0))


def test_an_absurd_torque_is_a_bad_reading_left_out_of_the_mean(acc):
    """The torque signal's +-3276.8 Nm (beyond 3 x the 220 Nm maximum torque, the range the
    torque input is found by its role in the model): left out of the tick's mean, the input faulty
    (``out_of_range``) and counted, as an absurd current or speed is."""
    cfg = load_config(EDGE_YAML)
    torque = load_model(cfg.model.path).find_input(Role.TORQUE)
    assert cfg.signals.valid_torque_factor * cfg.derating.max_torque_nm == 660.0
    values = [100.0, 3276.7, 100.0, -3276.8, 100.0, 659.0]
    times = [20.0 + 0.1 * k for k in range(len(values))]
    for t, v in zip(times, values):
        acc.add(frame("INV_Mechanics", t, INV_Speed=900.0, INV_Torque=v, INV_Udc=560.0), t)
    acc.add(frame("INV_Currents", 20.5, INV_Id=0.0, INV_Iq=20.0, INV_IphRms=0.0), 20.5)
    acc.add(stator(20.5), 20.5)
    acc.add(ambient(20.5), 20.5)
    ti = acc.take(21.0)
    assert ti.inputs[torque] == pytest.approx(zoh_mean(times, [v if abs(v) <= 660.0 else None for v in values], 21.0))
    assert ti.faults == {torque: "out_of_range"}
    assert acc.bad_readings["out_of_range"] == 1



def test_a_burst_of_frames_weighs_the_time_it_spans_not_its_count(acc):
    """40 A rms every 10 ms, and once a second 2,000 INV_Currents frames at 0 A within 2 ms (valid
    counters and CRC). Averaged per frame the model would see 8.7 A (a 21st of the copper loss) and
    the limit rise to the maximum; over time it is 40 A within the burst's share of the second."""
    t0 = 100.0
    acc.take(t0)
    times, values = [], []
    for k in range(100):  # the inverter's 10 ms cycle
        t = t0 + 0.01 * k
        times.append(t)
        values.append(40.0)
        acc.add(frame("INV_Currents", t, INV_Id=0.0, INV_Iq=40.0 * math.sqrt(2), INV_IphRms=40.0), t)
        if k == 50:  # the burst, between two inverter frames
            for j in range(2000):
                tb = t + 1e-6 * (j + 1)
                times.append(tb)
                values.append(0.0)
                acc.add(frame("INV_Currents", tb, INV_Id=0.0, INV_Iq=0.0, INV_IphRms=0.0), tb)
    i_rms = acc.take(t0 + 1.0).inputs["i_rms"]
    per_frame = math.sqrt(np.mean(np.square(values)))
    assert per_frame < 10.0  # what the frame count alone gives
    assert i_rms == pytest.approx(math.sqrt(zoh_mean(times, list(np.square(values)), t0 + 1.0)))
    assert i_rms > 39.0


def test_a_reading_that_arrives_after_the_boundary_is_age_zero_not_negative(acc):
    """On the wall clock a tick runs a moment after its boundary and takes the readings that came
    meanwhile: their age at the tick is 0, never negative."""
    acc.add(stator(9.4), 9.4)
    acc.add(ambient(9.4), 9.4)
    assert acc.take(10.0).ages["slot_winding"] == pytest.approx(0.6)
    acc.add(stator(11.003), 11.003)  # 3 ms after the boundary of the tick below, before it ran
    ti = acc.take(11.0)
    assert ti.ages["slot_winding"] == 0.0 and ti.ages["ambient_c"] == pytest.approx(1.6)
    assert all(a >= 0 for a in ti.ages.values())


def test_sensor_age_metric_is_the_ticks_own_age_whatever_arrived_since(tmp_path):
    """``thermal_edge_sensor_age_seconds`` between two ticks: a reading that came after the last
    tick must not make the age negative (as the last tick's time minus the newest reading would)."""
    from prometheus_client.parser import text_string_to_metric_families
    from svc_testlib import edge_raw, write_yaml

    from thermal_edge.service.engine import ThermalEngine
    from thermal_edge.service.metrics import ServiceMetrics

    cfg = load_config(write_yaml(tmp_path / "edge.yaml", edge_raw(tmp_path / "state", {"interface": "virtual"},
                                                                   table4=False, adapt=False)))
    eng = ThermalEngine(cfg, worker_mode="sync")
    m = ServiceMetrics()
    m.attach(eng)
    try:
        last_stator = None
        for k in range(30):  # 3 s of frames at 10 Hz, stator temperatures every 0.4 s, ticks each second
            t = 100.0 + 0.1 * k
            if k and k % 10 == 0:
                eng.tick(t)
            eng.add_frame(frame("INV_Currents", t, INV_Id=0.0, INV_Iq=20.0, INV_IphRms=14.1), t)
            eng.add_frame(frame("INV_Mechanics", t, INV_Speed=900.0, INV_Torque=50.0, INV_Udc=560.0), t)
            eng.add_frame(ambient(t), t)
            if k % 4 == 0:
                eng.add_frame(stator(t), t)
                if t < 102.0 - 1e-9:  # added before the tick at 102.0 ran
                    last_stator = t
        # the last tick was at 102.0; stator frames came at 102.0, 102.4 and 102.8 after it
        ages = {s.labels["sensor"]: s.value for fam in text_string_to_metric_families(m.text())
                for s in fam.samples if s.name == "thermal_edge_sensor_age_seconds"}
        assert set(ages) == {"slot_winding", "end_winding", "housing"}
        assert last_stator is not None
        for a in ages.values():
            assert a == pytest.approx(102.0 - last_stator) and a >= 0
    finally:
        eng.close()


@pytest.mark.parametrize("dq, turns", [("amplitude_invariant", 2 / 3), ("power_invariant", math.sqrt(2 / 3)),
                                       ("rms_scaled", 2 / 3 / math.sqrt(2))])
def test_each_dq_convention_gives_the_rms_of_the_phase_currents(tmp_path, dq, turns):
    """d/q currents from three phase currents by the convention's Clarke/Park transform (scaled by
    ``turns``); the RMS phase current over the tick must be that of the phase currents themselves."""
    import yaml
    from svc_testlib import REPO, write_yaml

    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["model"]["path"] = str(REPO / "config" / "machines" / "pm10kw.yaml")
    raw["signals"]["inputs"]["i_rms"]["dq"] = dq
    acc = accumulator(load_config(write_yaml(tmp_path / "edge.yaml", raw)))
    times = np.arange(100) * 0.01
    amplitude = 30 + 10 * np.sin(times * 7)  # a current that varies within the tick
    squares = []
    for t, a in zip(times, amplitude):
        theta = 2 * math.pi * 50 * t
        abc = [a * math.cos(theta - k * 2 * math.pi / 3) for k in range(3)]
        # Clarke then Park, rotating with the current: i_q carries it
        alpha = turns * (abc[0] - 0.5 * abc[1] - 0.5 * abc[2])
        beta = turns * (math.sqrt(3) / 2) * (abc[1] - abc[2])
        d = alpha * math.cos(theta) + beta * math.sin(theta)
        q = -alpha * math.sin(theta) + beta * math.cos(theta)
        squares.append(sum(x * x for x in abc) / 3)  # the phases' mean square at this instant
        acc.add(frame("INV_Currents", 10.0 + t, INV_Id=d, INV_Iq=q, INV_IphRms=0.0), 10.0 + t)
    expected = math.sqrt(zoh_mean(list(10.0 + times), squares, 11.0))
    assert acc.take(11.0).inputs["i_rms"] == pytest.approx(expected, rel=1e-9)


def test_a_refused_reading_names_the_unit_it_looks_like(acc, caplog):
    """A housing reading of 313.15 (40 °C in kelvin) is out of the valid range and plausible in
    kelvin; an RMS current of 20,000 (20 A in mA) is out of the current's range and plausible in mA;
    a winding at 900 °C is plausible in no unit. The sensor-fault log line carries the cause."""
    import logging

    from thermal_edge.bus.frames import DerateReason, TeState
    from thermal_edge.service.derating import Limits
    from thermal_edge.service.events import SafetyEvents

    acc.add(stator(10.0, hous=313.15, slot=900.0), 10.0)
    acc.add(frame("INV_Currents", 10.0, INV_Id=0.0, INV_Iq=20000.0 * math.sqrt(2), INV_IphRms=0.0), 10.0)
    ti = acc.take(11.0)
    assert ti.faults["housing"] == ti.faults["slot_winding"] == ti.faults["i_rms"] == "out_of_range"
    assert acc.refusal("housing") == "313.15 degC looks like kelvin (40 degC); give it in degC"
    assert acc.refusal("i_rms") == "20000 A looks like mA (20 A); give it in A"
    assert "looks like" not in acc.refusal("slot_winding") and "900" in acc.refusal("slot_winding")
    assert acc.refusal("end_winding") is None
    with caplog.at_level(logging.WARNING, logger="thermal_edge.service.events"):
        SafetyEvents().record(TeState.DEGRADED, Limits(10.0, 56.0, DerateReason.SENSOR_FAULT, True), [], ti.faults, acc.refusal)
    line = next(r.getMessage() for r in caplog.records if "sensor fault" in r.getMessage())
    assert "housing (out_of_range: 313.15 degC looks like kelvin (40 degC); give it in degC)" in line


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_current_frame_without_a_value_is_a_fault_not_the_last_value(acc, bad):
    """A float signal's NaN or inf (or a NoValueRaw) on a mean/rms input: frames keep coming, so the
    input never goes stale; the tick is faulty (``no_value``) instead of carrying the last value on."""
    good_iq = 30.0 * math.sqrt(2)
    for k in range(10):
        t = 10.0 + 0.1 * k
        acc.add(frame("INV_Currents", t, INV_Id=0.0, INV_Iq=good_iq, INV_IphRms=0.0), t)
    first = acc.take(11.0)
    assert first.inputs["i_rms"] == pytest.approx(30.0) and "i_rms" not in first.faults
    for k in range(10):
        t = 11.0 + 0.1 * k
        acc.add(frame("INV_Currents", t, INV_Id=0.0, INV_Iq=bad, INV_IphRms=0.0), t)
    second = acc.take(12.0)
    assert second.faults["i_rms"] == "no_value" and "i_rms" not in second.fresh
    assert acc.bad_readings["no_value"] == 10
    for k in range(10):
        t = 12.0 + 0.1 * k
        acc.add(frame("INV_Currents", t, INV_Id=0.0, INV_Iq=good_iq, INV_IphRms=0.0), t)
    third = acc.take(13.0)
    assert "i_rms" not in third.faults and third.inputs["i_rms"] == pytest.approx(30.0)
    assert "i_rms" in acc.fault_sources


def test_an_ambient_a_winding_could_read_is_refused_as_the_air(acc):
    """215 degC (an 8-bit channel's raw maximum: the sensor unplugged) is inside the PT100s' valid
    range but not the air's: the ambient input is faulty (out of range, counted), keeps its last
    value, and the stator readings stay as read; 95 degC air is read."""
    acc.add(ambient(0.1, amb=30.0), 0.1)
    acc.add(stator(0.1), 0.1)
    ti = acc.take(1.0)
    assert ti.inputs["ambient_c"] == 30.0 and not ti.faults
    acc.add(ambient(1.1, amb=215.0), 1.1)
    acc.add(stator(1.1), 1.1)
    ti = acc.take(2.0)
    assert ti.faults == {"ambient_c": "out_of_range"} and ti.inputs["ambient_c"] == 30.0
    assert acc.bad_readings["out_of_range"] == 1 and ti.measured["slot_winding"] == 60.0
    assert acc.refusal("ambient_c") == "215 degC is outside the plausible -40 to 100 degC"
    acc.add(ambient(2.1, amb=95.0), 2.1)
    acc.add(stator(2.1), 2.1)
    ti = acc.take(3.0)
    assert ti.inputs["ambient_c"] == 95.0 and not ti.faults


@pytest.mark.parametrize("code", [4, 15, 85.3, math.nan])
def test_a_status_code_the_matrix_does_not_define_is_a_fault_not_valid(acc, code):
    """Only 0 is valid: another inverter's wider status signal (a code 4 or 15), or a value that is
    no code at all, is a fault of that reading (``unknown_status``), counted once, its last good
    value kept out of the tick; the next valid reading is used again."""
    acc.add(ambient(0.1), 0.1)
    acc.add(stator(0.1, s_slot=code, slot=61.0), 0.1)
    ti = acc.take(1.0)
    assert ti.faults == {"slot_winding": "unknown_status"} and math.isnan(ti.measured["slot_winding"])
    assert ti.measured["end_winding"] == 62.0 and +acc.bad_readings == {"unknown_status": 1}
    acc.add(stator(1.1, slot=63.0), 1.1)
    ti = acc.take(2.0)
    assert ti.faults == {} and ti.measured["slot_winding"] == 63.0
