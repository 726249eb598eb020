"""State file: atomic writes, corrupt files never crash, cool-down over the downtime, hot restart."""
from __future__ import annotations

import json
import logging
import math
import os

import numpy as np
import pytest

from svc_testlib import EDGE_YAML, REPO, write_yaml
from thermal_edge.bus import DecodedFrame
from thermal_edge.config import config_from_mapping
from thermal_edge.lptn import Simulator, steady_state
from thermal_edge.service.engine import ThermalEngine
from thermal_edge.service.persistence import PersistedState, StateStore, cool_down


def state_for(model, T=None) -> PersistedState:
    T = np.linspace(30, 120, len(model.nodes)) if T is None else T
    return PersistedState(model=model.name, saved_at=1000.0, parameters={"R_e_hous": 8.5}, param_version=3,
                          adapt_runs=5, decisions=[{"t": 900.0, "accepted": True, "candidate_error_k": None}],
                          nodes=list(model.nodes), T=[float(x) for x in T], sigma=[0.5] * len(T),
                          T_pred=[float(x) for x in T], P=np.eye(len(T)).tolist(), inputs={"ambient_c": 25.0})


def test_roundtrip_is_atomic_and_complete(tmp_path, model):
    store = StateStore(tmp_path / "state", model)
    st = state_for(model)
    assert store.save(st)
    assert not [p for p in (tmp_path / "state").iterdir() if p.name != "state.json"]  # no temp file left
    back = StateStore(tmp_path / "state", model).load()
    assert back is not None and back.T == st.T and back.parameters == {"R_e_hous": 8.5} and back.param_version == 3
    assert back.P == st.P and back.decisions == st.decisions


def test_a_failed_write_keeps_the_old_file(tmp_path, model, monkeypatch):
    store = StateStore(tmp_path, model)
    store.save(state_for(model))
    before = (tmp_path / "state.json").read_bytes()

    def boom(fd):  # the disk fails while writing the new state
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", boom)
    assert store.save(state_for(model, np.full(len(model.nodes), 99.0))) is False
    assert store.save_errors == 1
    assert (tmp_path / "state.json").read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name != "state.json"]


@pytest.mark.parametrize("content, why", [
    (b"{not json", "not valid JSON"),
    (b"\xff\xfe\x00garbage", "cannot read"),
    (json.dumps({"format": "thermal_edge.state", "version": 1, "model": "other", "saved_at": 1}).encode(), "model 'other'"),
    (json.dumps({"format": "thermal_edge.state", "version": 99}).encode(), "version 99"),
    (b"[]", "not a JSON object"),
])
def test_corrupt_state_is_reported_counted_and_moved_aside(tmp_path, model, caplog, content, why):
    (tmp_path / "state.json").write_bytes(content)
    store = StateStore(tmp_path, model)
    with caplog.at_level(logging.ERROR):
        assert store.load() is None
    assert store.load_errors == 1
    assert why in caplog.text and "state.json" in caplog.text
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("state.json.corrupt-")]
    assert len(aside) == 1 and aside[0].read_bytes() == content
    assert not (tmp_path / "state.json").exists()


def test_non_finite_or_out_of_bounds_values_are_rejected(tmp_path, model):
    st = state_for(model)
    raw = st.as_json()
    raw["T"][3] = None
    (tmp_path / "state.json").write_text(json.dumps(raw))
    assert StateStore(tmp_path, model).load() is None
    raw = state_for(model).as_json()
    raw["parameters"]["R_e_hous"] = 1e6
    (tmp_path / "state.json").write_text(json.dumps(raw))
    store = StateStore(tmp_path, model)
    assert store.load() is None and "outside its bounds" in (store.last_error or "")


def test_cool_down_matches_a_fine_step_simulation(model):
    hot, _ = steady_state(model, {"speed_rpm": 900.0, "i_rms": 22.0, "torque_nm": 123.0, "ambient_c": 25.0})
    downtime = 1234.0
    T1, Phi = cool_down(model, model.nominal(), hot, downtime, {"ambient_c": 22.0})
    n = int(downtime)
    cols = {"speed_rpm": np.zeros(n + 1), "i_rms": np.zeros(n + 1), "torque_nm": np.zeros(n + 1),
            "ambient_c": np.full(n + 1, 22.0)}
    ref = Simulator(model).simulate(model.nominal(), cols, downtime / n, hot).T[-1]
    assert np.max(np.abs(T1 - ref)) < 1e-6
    assert np.all(T1 < hot) and np.all(T1 > 22.0)
    assert Phi.shape == (len(hot), len(hot))


def _engine_config(tmp_path):
    import yaml

    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["model"]["path"] = str(REPO / "config" / "machines" / "pm10kw.yaml")
    raw["codec"]["dbc"] = str(REPO / "dbc" / "thermal_edge.dbc")
    raw["clock"]["mode"] = "frame"
    raw["adaptation"]["enabled"] = False
    raw["state"] = {"dir": str(tmp_path)}
    return config_from_mapping(raw, write_yaml(tmp_path / "edge.yaml", raw))


def _feed(engine, model, t, T_true, amb=25.0, i=0.0, speed=0.0):
    """One tick of frames whose readings are the true sensor nodes (no noise)."""
    y = {s: float(T_true[model.node_index(n)]) for s, n in model.sensors.items()}
    for k in range(10):
        ts = t - 1 + 0.1 * k
        engine.add_frame(DecodedFrame("INV_Currents", 0xA0, {"INV_Id": 0.0, "INV_Iq": math.sqrt(2) * i, "INV_IphRms": i}, 0, ts), ts)
        engine.add_frame(DecodedFrame("INV_Mechanics", 0xA1, {"INV_Speed": speed, "INV_Torque": 5.6 * i, "INV_Udc": 560.0}, 0, ts), ts)
    engine.add_frame(DecodedFrame("INV_StatorTemps", 0xB0, {"INV_T_WindingSlot": y["slot_winding"], "INV_T_EndWinding": y["end_winding"],
                                                           "INV_T_Housing": y["housing"], "INV_S_WindingSlot": 0, "INV_S_EndWinding": 0,
                                                           "INV_S_Housing": 0}, 0, t - 0.5), t - 0.5)
    engine.add_frame(DecodedFrame("INV_AmbientTemps", 0xB1, {"INV_T_Ambient": amb, "INV_T_Coolant": math.nan, "INV_S_Ambient": 0,
                                                            "INV_S_Coolant": 3}, 0, t - 0.5), t - 0.5)
    return engine.tick(t)


def test_restart_of_a_hot_machine_cools_the_saved_state_and_corrects_it(tmp_path, model):
    cfg = _engine_config(tmp_path)
    hot, _ = steady_state(model, {"speed_rpm": 900.0, "i_rms": 24.0, "torque_nm": 134.0, "ambient_c": 25.0})
    saved = PersistedState(model=model.name, saved_at=10_000.0, parameters={}, nodes=list(model.nodes),
                           T=[float(x) for x in hot], sigma=[0.3] * len(hot), P=(np.eye(len(hot)) * 0.09).tolist(),
                           inputs={"ambient_c": 25.0, "speed_rpm": 900.0, "i_rms": 24.0, "torque_nm": 134.0})
    downtime = 600.0
    truth, _ = cool_down(model, model.nominal(), hot, downtime, {"ambient_c": 25.0})  # the machine stood still
    eng = ThermalEngine(cfg, model, saved, worker_mode="sync")
    out = _feed(eng, model, 10_000.0 + downtime, truth)
    assert out.initialized
    assert eng.restart_info["downtime_s"] == pytest.approx(downtime)
    assert np.max(np.abs(out.estimate - truth)) < 0.5
    hs = model.node_index("end_winding_2")
    assert out.estimate[hs] > 100  # not restarted from ambient
    # without the saved state the unmeasured nodes would be guessed from the readings only
    fresh = _feed(ThermalEngine(cfg, model, None, worker_mode="sync"), model, 10_000.0 + downtime, truth)
    assert np.max(np.abs(fresh.estimate - truth)) > np.max(np.abs(out.estimate - truth))


def test_engine_persists_what_it_restores(tmp_path, model):
    cfg = _engine_config(tmp_path)
    eng = ThermalEngine(cfg, model, None, worker_mode="sync")
    T, _ = steady_state(model, {"speed_rpm": 600.0, "i_rms": 12.0, "torque_nm": 67.0, "ambient_c": 25.0})
    for k in range(1, 6):
        out = _feed(eng, model, 500.0 + k, T, i=12.0, speed=600.0)
    st = eng.persisted(out.t)
    store = StateStore(tmp_path / "s", model)
    assert store.save(st)
    back = store.load()
    assert back is not None and np.allclose(back.T, out.estimate) and back.saved_at == out.t
