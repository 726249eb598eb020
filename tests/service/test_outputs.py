"""Frame contents, the limits between ticks and the metrics of a service that has not ticked yet,
each against an independent statement of the rule."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from svc_testlib import DBC, edge_raw, write_yaml

from thermal_edge.bus import DerateReason, FrameCodec, TeState
from thermal_edge.config import DeratingConfig, load_config
from thermal_edge.service.derating import STALL_TICKS, DeratingPolicy, Limits, NodeBand
from thermal_edge.service.inputs import FAULT_KINDS
from thermal_edge.service.outputs import TickOutput

NAN, INF = math.nan, math.inf


def _hand_clamped(out: TickOutput) -> dict[str, dict[str, float]]:
    """The frame contents as the engine wrote them before the codec's saturation was relied on:
    every DBC range clamped by hand (the ranges of dbc/thermal_edge.dbc)."""
    def temp(x: float) -> float:
        return min(x, 359.4) if math.isfinite(x) else NAN

    hs, mg = out.hot_spot, out.magnet
    ttl, la, e = out.time_to_limit_s, out.lookahead_a, out.pred_err_rms
    return {
        "TE_Estimates": {"TE_T_HotSpot": temp(hs.estimate_c), "TE_T_HotSpotUpper": temp(hs.upper_c),
                         "TE_T_Magnet": temp(mg.estimate_c), "TE_T_MagnetUpper": temp(mg.upper_c)},
        "TE_Forecast": {"TE_TimeToLimit": 65535.0 if not math.isfinite(ttl) or ttl >= 65535 else max(0.0, ttl),
                        "TE_LookaheadCurrent": 3276.75 if not math.isfinite(la) else min(max(la, 0.0), 3276.75),
                        "TE_Horizon": out.horizon_s},
        "TE_Status": {"TE_State": int(out.state),
                      "TE_PredErrRms": (0.0 if math.isnan(e) and out.state != TeState.FAULT
                                        else min(e, 655.35) if math.isfinite(e) else 655.35),
                      "TE_AdaptCount": out.adapt_accepted % 65536, "TE_ParamVersion": out.param_version % 256},
    }


def _output(temp: float, ttl: float, la: float, err: float, state: TeState) -> TickOutput:
    n = 3
    band = NodeBand("hot_spot", temp, temp + 1.0, 140.0, 155.0, DerateReason.WINDING)
    return TickOutput(t=0.0, state=state, limits=Limits(40.0, 220.0, DerateReason.NONE, False), initialized=True,
                      estimate=np.zeros(n), sigma=np.zeros(n), prediction=np.zeros(n), measured={}, inputs={},
                      pred_error={}, pred_err_rms=err, bands=[band], lookahead_a=la, time_to_limit_s=ttl,
                      horizon_s=1800.0, adapt_runs=90000, adapt_accepted=70000, adapt_rejected=0, param_version=300,
                      forced=[], stale=[], faults={}, hot_spot=band, magnet=band)


def test_frames_from_the_codecs_saturation_equal_the_hand_clamped_ones():
    """Out-of-range, infinite and NaN values: the bytes on the bus are the same as with the hand
    clamps the engine used to apply (the codec saturates to the DBC range instead)."""
    codec = FrameCodec(DBC)
    temps = (-60.0, 25.0, 359.4, 359.5, 400.0, 1e6, INF, -INF, NAN)
    ttls = (-5.0, 0.0, 120.0, 65535.0, 1e7, INF, NAN)
    las = (-3.0, 0.0, 31.5, 3276.75, 5000.0, INF, -INF, NAN)
    errs = (0.0, 1.25, 655.35, 1000.0, INF, NAN)
    cases = 0
    for temp, ttl, la, err, state in itertools.product(temps, ttls, las, errs, (TeState.NOMINAL, TeState.FAULT)):
        out = _output(temp, ttl, la, err, state)
        ref = _hand_clamped(out)
        got = {"TE_Estimates": out.estimates_signals(), "TE_Forecast": out.forecast_signals(),
               "TE_Status": out.status_signals()}
        for frame in ref:
            assert codec.encode(frame, got[frame], counter=0) == codec.encode(frame, ref[frame], counter=0), \
                (frame, temp, ttl, la, err)
        cases += 1
    assert cases == len(temps) * len(ttls) * len(las) * len(errs) * 2


def _policy() -> DeratingPolicy:
    cfg = DeratingConfig(max_current_a=40.0, max_torque_nm=220.0, safe_current_a=10.0)
    return DeratingPolicy(cfg, kt_nm_per_arms=5.6, tick_s=1.0, bus_silence_s=2.0)


@pytest.mark.parametrize("last_a", [4.0, 25.0])
def test_between_ticks_silence_and_stall_force_the_safe_limit_never_above_the_last(last_a):
    p = _policy()
    last = Limits(last_a, 5.6 * last_a, DerateReason.WINDING, True)
    safe_a, safe_nm = 10.0, 56.0  # safe_current_a, kt * safe_current_a
    assert p.between_ticks(last, 1.9, 0.5) == last  # frames and ticks on time
    assert p.between_ticks(last, None, None) == last  # silence expected (frame clock waiting), ticks follow frames
    silent = p.between_ticks(last, 2.1, 0.5)
    assert silent.reason == DerateReason.STALE_INPUT and silent.active
    assert silent.current_a == min(last_a, safe_a) and silent.torque_nm == min(5.6 * last_a, safe_nm)
    stalled = p.between_ticks(last, 0.1, STALL_TICKS * 1.0 + 0.01)
    assert stalled.reason == DerateReason.MODEL_FAULT and stalled.current_a == min(last_a, safe_a)
    assert p.between_ticks(last, 0.1, STALL_TICKS * 1.0) == last  # three periods: still on time
    # before the first tick: starting, or stale once the bus has been silent since the start
    assert p.between_ticks(None, 0.5, None) == Limits(safe_a, safe_nm, DerateReason.STARTING, True)
    assert p.between_ticks(None, 2.5, None) == Limits(safe_a, safe_nm, DerateReason.STALE_INPUT, True)


def test_alerted_series_exist_at_zero_before_the_first_tick(tmp_path):
    """Every labelled counter and flag an alert rule reads is there from the first scrape, 0 for
    each known label value (increase() needs the series before its first event)."""
    from thermal_edge.bus.stats import DROP_REASONS
    from thermal_edge.service import EdgeService

    cfg = load_config(write_yaml(tmp_path / "edge.yaml", edge_raw(tmp_path / "state", {"interface": "virtual",
                                                                                         "channel": "te-outputs"})))
    svc = EdgeService(cfg, serve_metrics=False)
    try:
        samples = {}
        for fam in text_string_to_metric_families(svc.metrics.text()):
            for s in fam.samples:
                samples[(s.name, tuple(sorted(s.labels.items())))] = s.value
    finally:
        svc.engine.close()
    frames = list(cfg.timeouts)
    assert len(frames) == 4
    for f in frames:
        assert samples[("thermal_edge_input_stale", (("frame", f),))] == 0
        assert samples[("thermal_edge_frames_lost_total", (("frame", f),))] == 0
        assert samples[("thermal_edge_frames_received_total", (("frame", f),))] == 0
    for f in ("TE_Limits", "TE_Estimates", "TE_Forecast", "TE_Status"):
        assert samples[("thermal_edge_frames_sent_total", (("frame", f),))] == 0
    for r in DROP_REASONS:
        assert samples[("thermal_edge_frames_dropped_total", (("reason", r),))] == 0
    required = [s for s, spec in cfg.sensors.items() if spec.required]
    assert required
    for s in required:
        for kind in FAULT_KINDS:
            assert samples[("thermal_edge_sensor_fault", (("kind", kind), ("sensor", s)))] == 0
    for kind in FAULT_KINDS:
        assert samples[("thermal_edge_bad_readings_total", (("kind", kind),))] == 0
    for r in DerateReason:
        key = ("thermal_edge_derate_reason", (("thermal_edge_derate_reason", r.name.lower()),))
        assert samples[key] == float(r == DerateReason.STARTING)
    for name in ("model_faults", "adaptation_failures", "adaptation_runs", "adaptation_accepted", "state_save_errors"):
        assert samples[(f"thermal_edge_{name}_total", ())] == 0


def test_no_lookahead_current_is_advised_before_the_model_is_initialised(tmp_path):
    """Before the first tick (and until the model is initialised) TE_LookaheadCurrent decodes, with
    the DBC through cantools, as 0 A, not as the range's top that an unknown value saturates to."""
    import cantools

    from thermal_edge.service.engine import ThermalEngine

    cfg = load_config(write_yaml(tmp_path / "edge.yaml", edge_raw(tmp_path / "state", {"interface": "virtual"},
                                                                   table4=False, adapt=False)))
    eng = ThermalEngine(cfg, worker_mode="sync")
    try:
        out = eng.placeholder(0.0)
        assert not out.initialized and math.isinf(out.lookahead_a)
        db = cantools.database.load_file(str(DBC))
        data = FrameCodec(DBC).encode("TE_Forecast", out.forecast_signals(), counter=0)
        assert db.decode_message("TE_Forecast", data, decode_choices=False)["TE_LookaheadCurrent"] == 0.0
        ready = _output(80.0, 600.0, 31.5, 0.5, TeState.NOMINAL)  # initialised: the look-ahead as computed
        data = FrameCodec(DBC).encode("TE_Forecast", ready.forecast_signals(), counter=0)
        assert db.decode_message("TE_Forecast", data, decode_choices=False)["TE_LookaheadCurrent"] == 31.5
    finally:
        eng.close()
