"""State file: atomic writes, corrupt files never crash, cool-down over the downtime, hot restart."""
from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path

import numpy as np
import pytest
from svc_testlib import EDGE_YAML, MODEL, REPO, write_yaml

from thermal_edge.bus import DecodedFrame
from thermal_edge.config import config_from_mapping
from thermal_edge.lptn import Simulator, cool_down, load_model, steady_state
from thermal_edge.service.engine import ThermalEngine
from thermal_edge.service.persistence import KEEP_CORRUPT, PersistedState, StateStore


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


@pytest.mark.parametrize("offset_s, level, words", [(-3600.0, logging.INFO, "3600 s ago"),
                                                     (30 * 86400.0, logging.WARNING, "2592000 s in the future")])
def test_a_load_says_what_it_loaded_and_a_state_from_the_future_is_a_warning(tmp_path, model, caplog, offset_s, level,
                                                                            words):
    """Every load is one line with the state's age by this host's clock, its parameter version and
    what it holds; a state saved 30 days in the future (a clock set wrong) is a WARNING."""
    import time

    st = state_for(model)
    st.saved_wall = time.time() + offset_s
    assert StateStore(tmp_path, model).save(st)
    with caplog.at_level(logging.INFO, logger="thermal_edge.service.persistence"):
        assert StateStore(tmp_path, model).load() is not None
    said = [r for r in caplog.records if r.getMessage().startswith("loaded state file")]
    assert len(said) == 1 and said[0].levelno == level, [r.getMessage() for r in caplog.records]
    msg = said[0].getMessage()
    assert words in msg.replace(f"{abs(offset_s) + 1:.0f} s", f"{abs(offset_s):.0f} s")
    assert f"parameter version {st.param_version}, 1 learned parameter(s), the thermal state of {len(model.nodes)} nodes" in msg


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


def valid_raw(model) -> dict:
    return state_for(model).as_json()


def edited(m, **fields) -> bytes:
    raw = valid_raw(m)
    raw.update(fields)
    return json.dumps(raw).encode()


def deep_decisions(model, depth: int) -> bytes:
    raw = valid_raw(model)
    raw["decisions"] = [{"x": json.loads("[" * depth + "]" * depth)}]
    return json.dumps(raw).encode()


def with_p(model, P) -> bytes:
    raw = valid_raw(model)
    raw["P"] = P
    return json.dumps(raw).encode()


def other_nodes(model) -> bytes:
    raw = valid_raw(model)
    raw["nodes"] = list(reversed(raw["nodes"]))
    return json.dumps(raw).encode()


def nan_literal(model) -> bytes:
    raw = valid_raw(model)
    raw["T"][3] = 1.5
    return json.dumps(raw).encode().replace(b"1.5", b"NaN", 1)


# (case, content builder, words of the log line); every one: one log line naming the file, a
# count, the file moved aside unchanged, a fresh start -- never an exception. (An unknown parameter
# name is no longer one of them: it is dropped and the rest kept, see
# test_an_unknown_parameter_is_dropped_and_every_known_one_kept.)
CORRUPT_STATE = [
    ("100,000 nested [", lambda m: b"[" * 100_000, "nested 100000 deep"),
    ("8 MiB of nested [ (at the cap)", lambda m: b"[" * (8 * 1024 * 1024), "nested"),
    ("nesting 20 deep inside a decision", lambda m: deep_decisions(m, 20), "nested"),
    ("5,000-digit number", lambda m: edited(m).replace(b'"saved_at": 1000.0', b'"saved_at": ' + b"9" * 5000), "5000 digits"),
    ("5,000-digit float", lambda m: edited(m).replace(b'"saved_at": 1000.0', b'"saved_at": 0.' + b"1" * 5000), "characters"),
    ("1e999 (overflows to inf)", lambda m: edited(m).replace(b'"saved_at": 1000.0', b'"saved_at": 1e999'), "out of range"),
    ("NaN literal", nan_literal, "NaN is not a number"),
    ('decisions: "abc"', lambda m: edited(m, decisions="abc"), "decisions: expected a list"),
    ("decisions: [1, 2]", lambda m: edited(m, decisions=[1, 2]), "decisions[0]: expected an object"),
    ("parameter as a string", lambda m: edited(m, parameters={"R_e_hous": "8.5"}), "parameters.R_e_hous: expected a number"),
    ("parameter outside its bounds", lambda m: edited(m, parameters={"R_e_hous": 1e6}), "outside the model's bounds"),
    ("param_version true", lambda m: edited(m, param_version=True), "param_version: expected a non-negative integer"),
    ("adapt_runs -1", lambda m: edited(m, adapt_runs=-1), "adapt_runs"),
    ("T holds null", lambda m: edited(m, T=[None] * len(m.nodes)), "T[0]: expected a number"),
    ("T is an object", lambda m: edited(m, T={"a": 1}), "T: expected a list"),
    ("temperatures of 900 degC", lambda m: edited(m, T=[900.0] * len(m.nodes)), "temperatures outside"),
    # well-formed but no machine's state (a doctored file must not be used as it is)
    ("the magnet at -99 degC", lambda m: edited(m, T=[-99.0 if "magnet" in n else 40.0 for n in m.nodes]),
     "temperatures outside -60..300 degC"),
    ("a state in kelvin", lambda m: edited(m, T=[300.0 + k for k in range(len(m.nodes))]), "looks like kelvin"),
    ("a cold state in kelvin", lambda m: edited(m, T=[293.0] * len(m.nodes)), "looks like kelvin"),
    ("ambient input in kelvin", lambda m: edited(m, inputs={"ambient_c": 298.15}), "inputs.ambient_c"),
    ("every variance zero", lambda m: with_p(m, [[0.0] * len(m.nodes) for _ in m.nodes]), "P has a variance of zero or less"),
    ("P of the wrong shape", lambda m: with_p(m, [[1.0]]), "P is not"),
    ("P rows not lists", lambda m: with_p(m, [1.0] * len(m.nodes)), "P[0]: expected a list"),
    ("node list of another order", other_nodes, "node list differs"),
    ("inputs a list", lambda m: edited(m, inputs=[25.0]), "inputs: expected an object"),
    ("unknown field", lambda m: edited(m, extra_field=1), "unknown field 'extra_field'"),
    ("saved_at missing", lambda m: json.dumps({k: v for k, v in valid_raw(m).items() if k != "saved_at"}).encode(),
     "missing field 'saved_at'"),
    ("another model", lambda m: edited(m, model="other"), "model 'other'"),
    ("version 99", lambda m: edited(m, version=99), "version 99"),
    ("foreign JSON document", lambda m: b'{"name": "left-pad", "version": "1.3.0", "dependencies": {}}', "not a state file"),
    ("a JSON list", lambda m: b"[]", "not a state file: a JSON list"),
    ("a JSON string", lambda m: b'"' + b'\\"' * 100_000 + b'"', "not a state file: a JSON str"),
    ("300,000 values", lambda m: b'{"a": [' + b"1," * 300_000 + b"1]}", "values (at most"),
    ("truncated", lambda m: edited(m)[: len(edited(m)) // 2], "not valid JSON"),
    ("binary", lambda m: b"\xff\xfe\x00garbage\x00\x01", "not UTF-8"),
    ("empty", lambda m: b"", "empty file"),
    ("whitespace only", lambda m: b" \n\t\n", "empty file"),
]


def check_refused(tmp_path, store, caplog, why):
    assert store.load_errors == 1
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(lines) == 1, lines
    assert why in lines[0] and str(tmp_path / "state.json") in lines[0], lines[0]
    assert not (tmp_path / "state.json").exists()
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("state.json.corrupt-")]
    assert len(aside) == 1 and aside == store.quarantined
    return aside[0]


@pytest.mark.parametrize("case, content, why", CORRUPT_STATE, ids=[c[0] for c in CORRUPT_STATE])
def test_corrupt_state_is_reported_counted_and_moved_aside(tmp_path, model, caplog, case, content, why):
    data = content(model)
    (tmp_path / "state.json").write_bytes(data)
    store = StateStore(tmp_path, model)
    with caplog.at_level(logging.ERROR):
        assert store.load() is None
    assert check_refused(tmp_path, store, caplog, why).read_bytes() == data  # kept for forensics
    assert store.save(state_for(model)) and StateStore(tmp_path, model).load() is not None  # and it starts afresh


def test_a_256_mib_file_is_refused_without_reading_it(tmp_path, model, caplog):
    with open(tmp_path / "state.json", "wb") as f:  # sparse: no disk used
        f.write(b'{"format": "thermal_edge.state", "decisions": [')
        f.truncate(256 * 1024 * 1024)
    store = StateStore(tmp_path, model)
    with caplog.at_level(logging.ERROR):
        assert store.load() is None
    aside = check_refused(tmp_path, store, caplog, "268435456 bytes, larger than 8 MiB (not read)")
    assert aside.stat().st_size == 256 * 1024 * 1024


@pytest.mark.parametrize("kind", ["directory", "fifo", "dangling symlink"])
def test_something_else_than_a_file_is_moved_aside(tmp_path, model, caplog, kind):
    path = tmp_path / "state.json"
    if kind == "directory":
        path.mkdir()
        (path / "inside").write_text("x")
    elif kind == "fifo":
        os.mkfifo(path)  # opening it would block the start for good
    else:
        path.symlink_to(tmp_path / "nowhere")
    store = StateStore(tmp_path, model)
    with caplog.at_level(logging.ERROR):
        assert store.load() is None
    why = {"directory": "a directory, not a file", "fifo": "not a regular file",
           "dangling symlink": "a symbolic link to nothing"}[kind]
    check_refused(tmp_path, store, caplog, why)
    assert store.save(state_for(model)) and StateStore(tmp_path, model).load() is not None


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads a file whatever its mode")
def test_an_unreadable_file_is_moved_aside(tmp_path, model, caplog):
    (tmp_path / "state.json").write_bytes(json.dumps(valid_raw(model)).encode())
    os.chmod(tmp_path / "state.json", 0)
    store = StateStore(tmp_path, model)
    with caplog.at_level(logging.ERROR):
        assert store.load() is None
    check_refused(tmp_path, store, caplog, "cannot read")


def test_only_the_newest_corrupt_files_are_kept(tmp_path, model):
    for k in range(KEEP_CORRUPT + 3):
        (tmp_path / "state.json").write_bytes(b"corrupt %d" % k)
        assert StateStore(tmp_path, model).load() is None
    kept = sorted(p.read_bytes() for p in tmp_path.iterdir() if p.name.startswith("state.json.corrupt-"))
    assert kept == [b"corrupt %d" % k for k in range(3, KEEP_CORRUPT + 3)]


def test_temporary_files_of_an_interrupted_save_are_removed_at_start(tmp_path, model, caplog):
    store = StateStore(tmp_path, model)
    assert store.save(state_for(model))
    (tmp_path / "state.json.tmp-4242").write_bytes(b'{"format": "thermal_')  # killed mid-write
    (tmp_path / ".state.json.77.tmp").write_bytes(b"")  # the earlier naming
    (tmp_path / "state.json.tmpfoo").write_bytes(b"x")
    (tmp_path / "unrelated.tmp").write_bytes(b"x")
    store = StateStore(tmp_path, model)
    with caplog.at_level(logging.WARNING):
        assert store.load() is not None
    assert store.temp_removed == 3 and caplog.text.count("left by an interrupted save") == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json", "unrelated.tmp"]


SAVER = r"""
import sys, numpy as np
sys.path[:0] = [sys.argv[2], sys.argv[2] + "/.."]  # tests/service and tests/ (own_ports)
from test_persistence import state_for
from thermal_edge.lptn import load_model
from thermal_edge.service.persistence import StateStore
model = load_model(sys.argv[3])
store = StateStore(sys.argv[1], model)
k = 0
while True:
    k += 1
    st = state_for(model, np.full(len(model.nodes), 20.0 + k % 100))
    st.decisions = [{"k": k, "pad": "x" * 200}] * 300  # a larger file: a longer write to be killed in
    store.save(st)
    if k == 1:  # one complete state exists before any kill (a busy host can take > 0.3 s to get here)
        print("saving", flush=True)
"""


def test_sigkill_during_saves_always_leaves_a_loadable_state(tmp_path, model):
    """12 SIGKILLs at random moments of a process saving in a loop: the next load always gets a
    complete state and removes what the killed save left."""
    import random
    import signal
    import subprocess
    import sys
    import time

    from svc_testlib import MODEL, env

    rng = random.Random(1)
    removed = 0
    for _ in range(12):
        proc = subprocess.Popen([sys.executable, "-c", SAVER, str(tmp_path), str(Path(__file__).parent), str(MODEL)],
                                env=env(), stdout=subprocess.PIPE)
        assert proc.stdout.readline() == b"saving\n"
        time.sleep(rng.uniform(0.0, 0.3))
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        store = StateStore(tmp_path, model)
        back = store.load()
        assert back is not None and store.load_errors == 0, store.last_error
        assert len(back.decisions) == 300 and len(set(back.T)) == 1
        removed += store.temp_removed
        assert [p.name for p in tmp_path.iterdir()] == ["state.json"]
    print(f"12 SIGKILLs during saves: every state loadable; {removed} temporary files of interrupted saves removed")


RSS = r"""
import resource, sys
from thermal_edge.lptn import load_model
from thermal_edge.service.persistence import StateStore
store = StateStore(sys.argv[1], load_model(sys.argv[2]))
assert store.load() is None and store.load_errors == int(sys.argv[3])
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""


def test_refusing_a_huge_or_hostile_file_costs_little_memory(tmp_path, model):
    """Peak RSS of a process that loads the model and refuses the file, against the same process
    with no state file (ru_maxrss is the process's high-water mark: what a memory cap sees)."""
    import subprocess
    import sys

    from svc_testlib import MODEL, env

    cap = 8 * 1024 * 1024
    cases = {
        "no state file (baseline)": b"",
        "256 MiB (sparse)": None,
        "8 MiB of [": b"[" * cap,
        "8 MiB of escaped quotes": b'"' + b'\\"' * (cap // 2 - 1) + b'"',
        "8 MiB of numbers": b"[" + b"1.5," * (cap // 4 - 1) + b"1]",
        "8 MiB string": b'{"format": "' + b"x" * (cap - 20) + b'"}',
    }
    rows = []
    for name, data in cases.items():
        d = tmp_path / str(len(rows))
        d.mkdir()
        if data != b"":
            with open(d / "state.json", "wb") as f:
                if data is None:
                    f.truncate(256 * 1024 * 1024)
                else:
                    f.write(data)
        out = subprocess.run([sys.executable, "-c", RSS, str(d), str(MODEL), "0" if data == b"" else "1"], env=env(),
                             capture_output=True, check=True)
        rows.append((name, float(out.stdout.decode().strip())))
    base = rows[0][1]
    print("\n| state file | peak RSS (MiB) | above baseline (MiB) |\n|---|---|---|")
    for name, mib in rows:
        print(f"| {name} | {mib:.1f} | {mib - base:+.1f} |")
    assert rows[1][1] - base < 4.0  # never read
    assert max(mib for _, mib in rows) - base < 64.0  # a few copies of an 8 MiB file at most


def test_a_parameter_adapted_onto_its_bound_saves_and_loads_back(tmp_path, model, caplog):
    """exp(log(300)) = 299.99999999999994 below c_p_ew's bound 300 must not lose the state."""
    at_bound = float(np.exp(np.log(300.0)))
    assert at_bound < 300.0
    st = state_for(model)
    st.parameters = {"c_p_ew": at_bound, "R_e_hous": float(np.exp(np.log(30.0))), "r_ins_sw": 0.013}
    store = StateStore(tmp_path, model)
    assert store.save(st) and store.save_refused == 0
    back = StateStore(tmp_path, model).load()
    assert back is not None
    assert back.parameters == {"c_p_ew": 300.0, "R_e_hous": 30.0, "r_ins_sw": 0.013}
    assert back.T == st.T and back.P == st.P and back.sigma == st.sigma and back.decisions == st.decisions
    # a file written with the round-off (before this fix) loads too
    raw = st.as_json()
    (tmp_path / "state.json").write_text(json.dumps(raw))
    assert repr(at_bound) in (tmp_path / "state.json").read_text()
    back = StateStore(tmp_path, model).load()
    assert back is not None and back.parameters["c_p_ew"] == 300.0 and back.T == st.T


@pytest.mark.parametrize("spoil, why", [
    (lambda st: st.parameters.__setitem__("c_p_ew", 299.0), "outside the model's bounds"),
    (lambda st: st.T.__setitem__(0, 900.0), "temperatures outside"),
    (lambda st: st.T.__setitem__(0, math.nan), "cannot be written as JSON"),
    (lambda st: st.__setattr__("nodes", st.nodes[:-1]), "node list differs"),
    (lambda st: st.decisions.append({"x": json.loads("[" * 30 + "]" * 30)}), "nested"),
])
def test_a_state_that_would_not_load_is_not_saved(tmp_path, model, caplog, spoil, why):
    store = StateStore(tmp_path, model)
    assert store.save(state_for(model))
    before = (tmp_path / "state.json").read_bytes()
    bad = state_for(model)
    spoil(bad)
    with caplog.at_level(logging.ERROR):
        assert store.save(bad) is False
    assert store.save_refused == 1 and store.save_errors == 1 and store.saves == 1
    assert why in caplog.text and "state.json" in caplog.text and "keeping the previous file" in caplog.text
    assert (tmp_path / "state.json").read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["state.json"]


def test_save_then_load_is_the_identity_for_any_state_within_the_bounds(tmp_path, model):
    """Property: 300 random states (parameters log-uniform within the bounds, on them, a round-off
    off them; random temperatures, covariances, decisions) save, load back equal (parameters
    within 1e-12 relative of the value clipped into its bounds, the rest exactly), and no save is
    refused."""
    rng = np.random.default_rng(20261124)
    lo, hi = model.bounds()
    names = model.parameter_names
    n = len(model.nodes)
    store = StateStore(tmp_path, model)
    for trial in range(300):
        params = {}
        for i in rng.choice(len(names), size=rng.integers(0, len(names) + 1), replace=False):
            kind = rng.integers(4)
            if kind == 0:
                v = float(np.exp(rng.uniform(np.log(lo[i]), np.log(hi[i]))))
            elif kind == 1:
                v = float(np.exp(np.log(lo[i] if rng.random() < 0.5 else hi[i])))  # a bound through the log space
            elif kind == 2:
                b = lo[i] if rng.random() < 0.5 else hi[i]
                v = float(b * (1 + (-1 if b == lo[i] else 1) * rng.uniform(0, 1e-10)))  # round-off beyond it
            else:
                v = float(lo[i] if rng.random() < 0.5 else hi[i])
            params[names[i]] = v
        A = rng.normal(size=(n, n))
        T = rng.uniform(-40.0, 250.0, n)
        st = PersistedState(model=model.name, saved_at=float(rng.uniform(0, 2e9)), parameters=params,
                            param_version=int(rng.integers(0, 1000)), adapt_runs=int(rng.integers(0, 10**6)),
                            decisions=[{"t": float(rng.normal()), "accepted": bool(rng.random() < 0.5), "why": "é\"\\[{",
                                        "params": {"c_p_ew": float(rng.uniform(300, 900))}, "none": None}]
                            * int(rng.integers(0, 5)),
                            nodes=list(model.nodes), T=T.tolist(), sigma=rng.uniform(0, 5, n).tolist(),
                            T_pred=(T + rng.normal(size=n)).tolist(), P=(A @ A.T).tolist(),
                            inputs={"ambient_c": float(rng.uniform(-40, 60))}, saved_wall=float(rng.uniform(0, 2e9)))
        assert store.save(st), store.last_error
        back = StateStore(tmp_path, model).load()
        assert back is not None, trial
        assert back.parameters.keys() == params.keys()
        for k, v in params.items():
            i = names.index(k)
            assert back.parameters[k] == pytest.approx(min(max(v, lo[i]), hi[i]), rel=1e-12, abs=0)
            assert lo[i] <= back.parameters[k] <= hi[i]
        for f in ("saved_at", "param_version", "adapt_runs", "decisions", "nodes", "T", "sigma", "T_pred", "P",
                  "inputs", "saved_wall"):
            assert getattr(back, f) == getattr(st, f), f
    assert store.save_refused == 0 and store.save_errors == 0


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
        engine.add_frame(DecodedFrame("INV_Currents", 0xA0, {"INV_Id": 0.0, "INV_Iq": math.sqrt(2) * i, "INV_IphRms": i},
                                      0, ts), ts)
        engine.add_frame(DecodedFrame("INV_Mechanics", 0xA1, {"INV_Speed": speed, "INV_Torque": 5.6 * i, "INV_Udc": 560.0},
                                      0, ts), ts)
    engine.add_frame(DecodedFrame("INV_StatorTemps", 0xB0,
                                  {"INV_T_WindingSlot": y["slot_winding"], "INV_T_EndWinding": y["end_winding"],
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


def test_a_state_saved_in_the_future_starts_the_temperatures_from_the_readings(tmp_path, model, caplog):
    """The clock set back (an RTC reset, a replay of an earlier log): the hot state's age is unknown,
    so its temperatures are not used (no phantom hot machine, no sensor judged stuck against it);
    the learned parameters are kept."""
    cfg = _engine_config(tmp_path)
    hot, _ = steady_state(model, {"speed_rpm": 900.0, "i_rms": 24.0, "torque_nm": 134.0, "ambient_c": 25.0})
    cold, _ = steady_state(model, {"speed_rpm": 0.0, "i_rms": 0.0, "torque_nm": 0.0, "ambient_c": 25.0})
    saved = PersistedState(model=model.name, saved_at=50_000.0, parameters={"R_e_hous": 8.5}, nodes=list(model.nodes),
                           T=[float(x) for x in hot], sigma=[0.3] * len(hot), P=(np.eye(len(hot)) * 0.09).tolist(),
                           inputs={"ambient_c": 25.0, "speed_rpm": 900.0, "i_rms": 24.0, "torque_nm": 134.0})
    eng = ThermalEngine(cfg, model, saved, worker_mode="sync")
    with caplog.at_level(logging.WARNING):
        out = _feed(eng, model, 10_000.0, cold)  # 40,000 s before the state was saved
    assert out.initialized and eng.restart_info["downtime_s"] == pytest.approx(-40_000.0)
    assert np.max(np.abs(out.estimate - cold)) < 0.5  # from the readings of a cold machine, not the hot state
    assert float(eng.adaptation.theta[model.parameter_index(["R_e_hous"])[0]]) == 8.5
    said = [r.getMessage() for r in caplog.records if "in the future" in r.getMessage()]
    assert said == ["saved state is 40000 s in the future (clock changed?): its age is unknown, the temperatures start "
                    "from the readings (the learned parameters are kept)"]


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


# ------------------------------------------------------------------------------------------
# one unknown parameter name must not cost every learned parameter
def test_an_unknown_parameter_is_dropped_and_every_known_one_kept(tmp_path, model, caplog):
    known = {"R_e_hous": 8.5, "c_p_ew": 330.0}
    (tmp_path / "state.json").write_bytes(edited(model, parameters={**known, "R_nosuch": 1.0, "R_e_house": 9.0}))
    store = StateStore(tmp_path, model)
    with caplog.at_level(logging.WARNING):
        st = store.load()
    assert st is not None and st.parameters == known and st.T == state_for(model).T
    assert store.params_dropped == 2 and store.load_errors == 0 and not store.quarantined
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "R_e_house, R_nosuch" in warnings[0] and str(tmp_path / "state.json") in warnings[0]
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert [p.name for p in tmp_path.iterdir()] == ["state.json"]  # not moved aside


@pytest.mark.parametrize("how", ["model file", "edge.yaml"])
def test_a_parameter_learned_from_another_model_value_is_dropped(tmp_path, model, caplog, how):
    """R_e_hous was learned (8.5) from the model's 9.1; the model now says 4.5 (a new model file, or a
    calibrated value given in edge.yaml's model.parameters: both make the model the service runs).
    The learned 8.5 belongs to the old start: dropped with one WARNING naming it and both model
    values, counted; c_p_ew, whose model value did not change, is kept, and so is the thermal state.
    A state saved before model values were kept with it keeps every learned value."""
    learned = {"R_e_hous": 8.5, "c_p_ew": 330.0}
    (tmp_path / "state.json").write_bytes(edited(model, parameters=learned, nominal={"R_e_hous": 9.1, "c_p_ew": 505.0}))
    if how == "edge.yaml":
        now = model.with_parameters({"R_e_hous": 4.5})
    else:
        text = MODEL.read_text()
        assert "R_e_hous: {value: 9.1," in text
        (tmp_path / "pm10kw.yaml").write_text(text.replace("R_e_hous: {value: 9.1,", "R_e_hous: {value: 4.5,"))
        now = load_model(tmp_path / "pm10kw.yaml")
    store = StateStore(tmp_path, now)
    with caplog.at_level(logging.WARNING):
        st = store.load()
    assert st is not None and st.parameters == {"c_p_ew": 330.0} and st.T == state_for(model).T
    assert store.params_dropped == 1 and store.load_errors == 0
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "R_e_hous learned 8.5 from 9.1, the model now says 4.5" in warnings[0], warnings
    # the model unchanged: both kept; a state without model values (an older file): both kept
    for nominal in ({"R_e_hous": 9.1, "c_p_ew": 505.0}, None):
        extra = {"nominal": nominal} if nominal is not None else {}
        (tmp_path / "state.json").write_bytes(edited(model, parameters=learned, **extra))
        again = StateStore(tmp_path, model)
        assert again.load().parameters == learned and again.params_dropped == 0


def test_the_engine_saves_the_model_value_each_parameter_was_learned_from(tmp_path, model):
    """What :meth:`ThermalEngine.persisted` saves names, for every learned parameter, the model's value
    (the service model's: edge.yaml's model.parameters applied); the state round-trips through the file."""
    cfg = _engine_config(tmp_path)
    now = model.with_parameters({"R_e_hous": 4.5})
    eng = ThermalEngine(cfg, now, None, worker_mode="sync")
    eng.adaptation._theta[now.parameter_index(["c_p_ew"])[0]] = 330.0
    st = eng.persisted(1000.0)
    eng.close()
    assert st.parameters == {"c_p_ew": 330.0} and st.nominal == {"c_p_ew": 505.0}
    store = StateStore(tmp_path / "s", now)
    assert store.save(st) and store.load().nominal == {"c_p_ew": 505.0}


def test_an_unknown_parameter_beside_a_bad_value_still_refuses_the_file(tmp_path, model, caplog):
    (tmp_path / "state.json").write_bytes(edited(model, parameters={"R_nosuch": 1.0, "R_e_hous": 1e6}))
    store = StateStore(tmp_path, model)
    with caplog.at_level(logging.ERROR):
        assert store.load() is None
    check_refused(tmp_path, store, caplog, "outside the model's bounds")


def test_a_state_with_an_unknown_parameter_is_never_saved(tmp_path, model, caplog):
    store = StateStore(tmp_path, model)
    bad = state_for(model)
    bad.parameters["R_nosuch"] = 1.0
    with caplog.at_level(logging.ERROR):
        assert store.save(bad) is False
    assert store.save_refused == 1 and "has no parameter 'R_nosuch'" in caplog.text
    assert not (tmp_path / "state.json").exists()


# failed saves are visible without a flood; an unwritable directory is said at start
def test_failed_saves_are_logged_at_1_2_4_8_and_when_they_work_again(tmp_path, model, caplog):
    store = StateStore(tmp_path, model)
    assert store.save(state_for(model))
    blocker = tmp_path / f"state.json.tmp-{os.getpid()}"
    blocker.mkdir()  # a real failure: the temporary file's name is a directory (EISDIR), as root too
    with caplog.at_level(logging.WARNING):
        results = [store.save(state_for(model)) for _ in range(20)]
        blocker.rmdir()
        assert store.save(state_for(model))
    assert results == [False] * 20 and store.save_errors == 20 and store.failing == 0 and store.saves == 2
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert [int(e.split(" failed in a row")[0].rsplit("(", 1)[1]) for e in errors] == [1, 2, 4, 8, 16]
    assert all("cannot save state to" in e and "Is a directory" in e and "keeping the previous file" in e for e in errors)
    assert "20 in all" not in caplog.text and "next report after 32" in errors[-1]
    again = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert again == [f"state saved again to {tmp_path / 'state.json'} after 20 failed save(s) in a row"]


def test_the_log_backs_off_to_every_64th_failure():
    from thermal_edge.service.persistence import _worth_logging

    assert [n for n in range(1, 300) if _worth_logging(n)] == [1, 2, 4, 8, 16, 32, 64, 128, 192, 256]


def test_probe_says_when_the_state_directory_cannot_be_written(tmp_path, model, caplog):
    good = StateStore(tmp_path / "new" / "state", model)
    assert good.probe() and (tmp_path / "new" / "state").is_dir() and not list((tmp_path / "new" / "state").iterdir())
    under_a_file = tmp_path / "a-file"
    under_a_file.write_text("x")
    store = StateStore(under_a_file / "state", model)
    with caplog.at_level(logging.ERROR):
        assert store.probe() is False
    assert store.failing == 1 and store.save_errors == 1
    assert f"cannot write the state directory {under_a_file / 'state'}" in caplog.text
    assert "protects without persistence; every save retries" in caplog.text


# ------------------------------------------------------------------------------------------
# the single-instance lock: whatever is in the state directory, the service starts and protects
@pytest.mark.parametrize("what", ["directory", "fifo", "symlink"])
def test_a_lock_path_that_is_no_lock_file_is_named_and_the_service_starts(tmp_path, caplog, what):
    from thermal_edge.service.persistence import LOCKNAME, StateLock

    lock = tmp_path / LOCKNAME
    if what == "directory":
        lock.mkdir()
    elif what == "fifo":
        os.mkfifo(lock)
    else:
        lock.symlink_to(tmp_path / "elsewhere")
    with caplog.at_level(logging.WARNING):
        held = StateLock(tmp_path).acquire()
    assert held is False
    kind = {"directory": "a directory", "fifo": "a FIFO", "symlink": "a symbolic link"}[what]
    assert [r.getMessage() for r in caplog.records] == [
        f"cannot lock the state directory through {lock}: it is {kind}, not a lock file (remove it); the service runs "
        "without the lock that keeps a second service off this directory"]


def test_a_lock_file_a_full_disk_cannot_take_the_pid_is_held_all_the_same(tmp_path, monkeypatch):
    """The pid only names the holder for a second service's message: a full disk that refuses it
    (an empty lock file left by an earlier start on that disk) leaves the lock held."""
    import errno

    from thermal_edge.service.persistence import LOCKNAME, StateLock

    real_write = os.write

    def full(fd, data):
        if os.path.basename(os.readlink(f"/proc/self/fd/{fd}")) == LOCKNAME:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", full)
    (tmp_path / LOCKNAME).write_text("")
    a = StateLock(tmp_path)
    assert a.acquire() is True
    monkeypatch.setattr(os, "write", real_write)
    # another process is refused while it is held (the pid unknown)
    import subprocess
    import sys

    code = ("import sys; from thermal_edge.service.persistence import StateLock, StateDirInUse\n"
            f"try:\n    StateLock({str(tmp_path)!r}).acquire()\nexcept StateDirInUse as e:\n    print(e); sys.exit(7)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 7 and "in use by another thermal-edge (pid unknown)" in r.stdout, r.stdout + r.stderr
    a.release()


def test_a_state_a_refused_configuration_would_move_aside_stays_in_place(tmp_path, model):
    """A deferred load refuses the file (another model's) without touching it; :meth:`settle` moves
    it once the configuration is accepted: a refused configuration leaves the directory as it was."""
    (tmp_path / "state.json").write_bytes(edited(model, model="another"))
    store = StateStore(tmp_path, model)
    assert store.load(defer=True) is None
    assert [p.name for p in tmp_path.iterdir()] == ["state.json"] and store.load_errors == 0
    store.settle()
    assert store.load_errors == 1 and len(store.quarantined) == 1 and not (tmp_path / "state.json").exists()


def test_a_refused_configuration_leaves_the_learned_state_in_place(tmp_path, model):
    """edge.yaml pointed at another model by mistake: the service refuses the configuration (its
    signals do not fit that model) and the state file of the machine it protected is where it was,
    for the corrected configuration's start."""
    from svc_testlib import edge_raw

    from thermal_edge.config import ConfigError
    from thermal_edge.service.service import EdgeService

    state = tmp_path / "state"
    state.mkdir()
    (state / "state.json").write_bytes(edited(model))  # pm10kw's
    raw = edge_raw(state, {"interface": "virtual", "channel": "refused"}, table4=False, adapt=False)
    raw["model"]["path"] = str(REPO / "tests" / "commands" / "models" / "two_node.yaml")
    with pytest.raises(ConfigError):
        EdgeService(config_from_mapping(raw, path=tmp_path / "edge.yaml"))
    assert sorted(p.name for p in state.iterdir() if p.name != "lock") == ["state.json"]
