"""Readings that drift low together are not believed: the commissioned model's prediction.

A reference common to every PT100 drifting low (the inverter's excitation current or ADC reference)
passes every check made against the readings themselves: the observer follows them, a restart
starts from them, the adaptation learns a machine that cools better. The engine runs the model
file's own parameters on open loop beside them; here the plant is that model (stepped
independently), so the gap the engine must act on is computed a second way: the plant's true
sensor temperatures minus the readings, i.e. the drift itself."""
from __future__ import annotations

import json
import math

import numpy as np
from test_persistence import _engine_config, _feed

from thermal_edge.bus import DerateReason
from thermal_edge.lptn import Stepper
from thermal_edge.service.engine import ThermalEngine
from thermal_edge.service.estimate import COMMISSIONED_BLOCK
from thermal_edge.service.persistence import PersistedState

SAFE = 10.0
OP = {"speed_rpm": 900.0, "ambient_c": 25.0}


def _drift(k: int, start: int, rate_k_per_s: float, cap_k: float) -> float:
    return min(max(k - start, 0) * rate_k_per_s, cap_k)


def _run(eng, model, ticks: range, T: np.ndarray, drift, demand_a: float = 40.0, states: list | None = None):
    """Closed loop: the plant (nominal parameters) draws min(demand, the engine's limit); its sensor
    nodes, less ``drift(k)`` K, are the readings. Returns the outputs, the plant's state and the
    drift of each tick; ``states``, when given, receives the plant's state of each tick."""
    st = Stepper(model, model.nominal(), 1.0)
    outs, drifts = [], []
    limit = 0.0
    for k in ticks:
        i = min(demand_a, limit)
        T, _ = st.step(T, {**OP, "i_rms": i, "torque_nm": 5.6 * i})
        d = drift(k)
        out = _feed(eng, model, 1000.0 + k, T - d, i=i, speed=OP["speed_rpm"])
        limit = out.limits.current_a
        outs.append(out)
        if states is not None:
            states.append(T)
        drifts.append(d)
    return outs, T, drifts


def test_a_drift_common_to_every_pt100_is_not_believed_and_the_limit_stays_safe(tmp_path, model, caplog):
    """Every reading drifts low at 2 K/min from 5 min on, up to 40 K (below the 40 K the open-loop
    check against the model in use needs). The first tick the engine refuses the readings is the
    ``prediction_error_ticks``-th tick of a drift beyond ``commissioned_gap_k`` (the plant is the
    commissioned model, so the gap is the drift), within the block of ticks the prediction steps
    over, the safe
    limit holds while the drift lasts, one count, one ERROR line; when the readings are right
    again they are trusted within a tick."""
    import logging

    cfg = _engine_config(tmp_path)
    fc = cfg.derating.faults
    eng = ThermalEngine(cfg, model, None, worker_mode="sync")
    T0 = np.full(len(model.nodes), 25.0)
    start, rate, cap = 300, 2.0 / 60.0, 40.0
    plant: list = []
    with caplog.at_level(logging.INFO):
        outs, T, drifts = _run(eng, model, range(1, 1801), T0, lambda k: _drift(k, start, rate, cap), states=plant)
        over = [n for n, d in enumerate(drifts) if d > fc.commissioned_gap_k]
        expected = over[fc.prediction_error_ticks - 1]
        refused = next(n for n, o in enumerate(outs) if o.limits.reason == DerateReason.MODEL_FAULT)
        # the prediction steps once a block of ticks: up to a block late, one tick early (the readings' half-tick lead)
        assert expected - 1 <= refused <= expected + COMMISSIONED_BLOCK, (refused, expected)
        assert all(o.limits.current_a <= SAFE and o.limits.reason == DerateReason.MODEL_FAULT for o in outs[refused:])
        assert eng.commissioned.count == 1 and eng.health.faults == 0
        # the gap it reports is the drift (the plant is the commissioned model)
        assert eng.commissioned.gap is not None and abs(eng.commissioned.gap[1] - cap) < 1.0
        # nor are estimates published from them: the hot spot is never shown below the plant's, less
        # the commissioned prediction's stepping once a block of ticks (the readings lie 20-40 K low)
        hot = model.node_index(next(lim.node for lim in model.limits if lim.name == "hot_spot"))
        short = max(plant[n][hot] - o.estimate[hot] for n, o in enumerate(outs) if n >= refused)
        assert short < 2.0, short
        # the adapter is given no reading while they are not believed
        assert all(math.isnan(v) for v in eng._prev_sample[1].values())
        back, _, _ = _run(eng, model, range(1801, 1861), T, lambda k: 0.0)
    assert back[1].limits.reason != DerateReason.MODEL_FAULT
    assert back[-1].limits.current_a > SAFE
    said = [(r.levelname, r.getMessage()) for r in caplog.records if "commissioned model" in r.getMessage()
            and r.name == "thermal_edge.service.health"]
    assert [lv for lv, _ in said] == ["ERROR", "NOTICE"], said
    # before the refusal, the drift under the gap was held at the commissioned floor (a WARNING)
    floored = [r for r in caplog.records if r.name == "thermal_edge.service.engine" and "commissioned model's" in
               r.getMessage() and r.levelname == "WARNING"]
    assert floored and floored[0].created <= next(r.created for r in caplog.records if r.levelname == "ERROR")
    assert "below the commissioned model's prediction" in said[0][1]


def test_readings_above_the_commissioned_model_are_believed(tmp_path, model):
    """A machine that runs hotter than its model file says (readings 30 K above): believed, the
    limit follows them down; no refusal."""
    cfg = _engine_config(tmp_path)
    eng = ThermalEngine(cfg, model, None, worker_mode="sync")
    outs, _, _ = _run(eng, model, range(1, 1201), np.full(len(model.nodes), 25.0),
                      lambda k: -_drift(k, 300, 0.05, 30.0))
    assert eng.commissioned.count == 0
    assert eng.commissioned.gap is not None and eng.commissioned.gap[1] < 0
    assert all(o.limits.reason != DerateReason.MODEL_FAULT for o in outs)


def test_a_restart_keeps_the_commissioned_prediction(tmp_path, model):
    """The service restarts while the readings drift: the commissioned prediction is saved and
    restored (cooled over the downtime), so the restarted engine does not start it from the drifted
    readings and refuses them again within ``prediction_error_ticks`` ticks."""
    cfg = _engine_config(tmp_path)
    fc = cfg.derating.faults
    eng = ThermalEngine(cfg, model, None, worker_mode="sync")
    drift = lambda k: _drift(k, 300, 2.0 / 60.0, 40.0)  # noqa: E731
    outs, T, _ = _run(eng, model, range(1, 1201), np.full(len(model.nodes), 25.0), drift)
    assert eng.commissioned.active
    saved = eng.persisted(1000.0 + 1200)
    eng.close()
    assert len(saved.T_commissioned) == len(model.nodes)
    # through the state file's own validation, as a restart reads it
    restored = PersistedState.from_json(json.loads(json.dumps(saved.as_json())), model)
    again = ThermalEngine(cfg, model, restored, worker_mode="sync")
    outs2, _, _ = _run(again, model, range(1201, 1201 + 2 * fc.prediction_error_ticks), T, drift, demand_a=0.0)
    again.close()
    assert again.commissioned.count == 1
    assert outs2[-1].limits.reason == DerateReason.MODEL_FAULT and outs2[-1].limits.current_a <= SAFE
    # without the saved prediction the restart would start it from the drifted readings: nothing refused
    fresh = ThermalEngine(cfg, model, None, worker_mode="sync")
    outs3, _, _ = _run(fresh, model, range(1201, 1201 + 2 * fc.prediction_error_ticks), T, drift, demand_a=0.0)
    fresh.close()
    assert fresh.commissioned.count == 0
