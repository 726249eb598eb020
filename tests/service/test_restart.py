"""Restart: SIGKILL the service of a hot machine mid-run, start it again; its first estimates are
within 2 K of the plant's true node temperatures (the saved state, cooled over the downtime with
the model, corrected by the first readings), while a start from the readings alone is not."""
from __future__ import annotations

import json
import signal
import subprocess
import time

import numpy as np
import pytest
from svc_testlib import HANG_S, MODEL, REPO, T0, NotifySocket, edge_raw, emulator_cmd, env, start_service, wait_until, write_yaml

from thermal_edge.service.persistence import LOCKNAME


def saved_at(path) -> float:
    try:
        return float(json.loads(path.read_text())["saved_at"])
    except (OSError, ValueError, KeyError):
        return -1.0


def test_restart_after_sigkill_starts_from_the_cooled_saved_state(tmp_path, udp_port):
    from thermal_edge.lptn import initial_state, load_model

    model = load_model(MODEL)
    state = tmp_path / "state"
    bus = {"interface": "udp_multicast", "port": udp_port}
    cfg_a = write_yaml(tmp_path / "a.yaml", edge_raw(state, bus, table4=False, adapt=False, save_interval_s=10.0))
    # the restarted service saves once, right after its first tick, so its first estimates can be read
    cfg_b = write_yaml(tmp_path / "b.yaml", edge_raw(state, bus, table4=False, adapt=False, save_interval_s=86400.0))
    state_file = state / "state.json"
    notify = NotifySocket(tmp_path / "notify")
    notify.start_thread()
    emu = svc = None
    try:
        svc = start_service(cfg_a, notify, log=tmp_path / "a.log")
        assert notify.wait_for("READY=1", HANG_S)
        # without TE_Limits the inverter's own protection trips the drive (fallback 0 A: standstill);
        # it runs on for 5 simulated minutes without a service, then waits for service B however
        # long B takes to start on a busy host
        emu = subprocess.Popen(emulator_cmd(udp_port, tmp_path / "summary.json", tmp_path / "trace.npz", duration=3300.0,
                                            fallback_current=0.0, speed=300.0, flow_timeout=0.5, max_free=300.0),
                               env=env(), cwd=str(REPO), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        assert wait_until(lambda: saved_at(state_file) >= T0 + 2400, HANG_S), "service A did not get to 40 min"
        svc.send_signal(signal.SIGKILL)
        svc.wait(HANG_S)
        last_a = saved_at(state_file)
        svc = start_service(cfg_b, None, log=tmp_path / "b.log")
        assert wait_until(lambda: saved_at(state_file) > last_a, HANG_S), (tmp_path / "b.log").read_text()
        time.sleep(0.1)  # the file is replaced atomically; read the first save
        first = json.loads(state_file.read_text())
        _, err = emu.communicate(timeout=4 * HANG_S)  # B keeps answering: the emulator finishes its cycle with it
        assert emu.returncode == 0, err.decode()
        svc.send_signal(signal.SIGKILL)
        svc.wait(HANG_S)
    finally:
        for p in (svc, emu):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        notify.close()

    trace = np.load(tmp_path / "trace.npz")
    t_first = float(first["saved_at"])
    k = int(np.argmin(np.abs(trace["t"] - t_first)))
    assert abs(trace["t"][k] - t_first) < 0.5
    truth = trace["T"][k]
    est = np.array(first["T"])
    downtime = t_first - last_a
    hs = model.node_index("end_winding_2")
    err = np.abs(est - truth)
    print(f"restart after {downtime:.0f} s: max |estimate - true| {err.max():.2f} K over {len(err)} nodes "
          f"(worst {model.nodes[int(np.argmax(err))]}); "
          f"true hot spot {truth[hs]:.1f} degC, estimate {est[hs]:.1f} degC")
    assert downtime > 30  # a real downtime, cooled over with the model
    assert truth[hs] - trace["ambient"][k] > 30  # still a hot machine
    assert err.max() < 2.0
    # the same readings without the saved state: the unmeasured nodes would be far off
    y = {s: float(truth[model.node_index(n)]) for s, n in model.sensors.items()}
    naive = initial_state(model, {"speed_rpm": 0.0, "i_rms": 0.0, "torque_nm": 0.0, "ambient_c": float(trace["ambient"][k])}, y)
    assert np.abs(naive - truth).max() > 2.0
    # the restarted service's first TE_Estimates as the inverter saw them (hot spot, magnet)
    est_t = trace["est_ts"]
    after = np.nonzero(est_t >= t_first - 0.5)[0]
    assert len(after) > 0
    j = after[0]
    kk = int(np.argmin(np.abs(trace["t"] - est_t[j])))
    assert abs(trace["est_hot_spot"][j] - trace["T"][kk][hs]) < 2.0
    assert abs(trace["est_magnet"][j] - trace["T"][kk][model.node_index("magnet_2")]) < 2.0


def _corrupt(kind: str, state, model) -> bytes | None:
    """Put a broken state where the service keeps its state; returns the bytes written (if a file)."""
    state.mkdir(parents=True, exist_ok=True)
    path = state / "state.json"
    if kind == "directory":
        path.mkdir()
        return None
    if kind == "256 MiB":
        with open(path, "wb") as f:  # sparse
            f.write(b'{"format": "thermal_edge.state", "decisions": [')
            f.truncate(256 * 1024 * 1024)
        return None
    data = {
        "100,000 nested [": b"[" * 100_000,
        "5,000-digit number": b'{"format": "thermal_edge.state", "version": 1, "model": "pm10kw", "saved_at": '
                              + b"9" * 5000 + b', "parameters": {}}',
        'decisions: "abc"': json.dumps({"format": "thermal_edge.state", "version": 1, "model": model.name, "saved_at": 1.0,
                                        "parameters": {}, "decisions": "abc"}).encode(),
    }[kind]
    path.write_bytes(data)
    return data


@pytest.mark.parametrize("kind", ["100,000 nested [", "5,000-digit number", 'decisions: "abc"', "directory", "256 MiB"])
def test_the_service_starts_fresh_on_a_corrupt_state_file(tmp_path, kind):
    """A corrupt state file at the level of the process: ready, one log line naming the file, the file moved
    aside, a clean stop that saves a loadable state; never a traceback, never exit 1."""
    from thermal_edge.lptn import load_model
    from thermal_edge.service.persistence import StateStore

    model = load_model(MODEL)
    state = tmp_path / "state"
    data = _corrupt(kind, state, model)
    (state / "state.json.tmp-999").write_bytes(b'{"format"')  # and a save killed half-way
    cfg = write_yaml(tmp_path / "edge.yaml", edge_raw(state, {"interface": "virtual", "channel": "t"}, table4=False, adapt=False))
    notify = NotifySocket(tmp_path / "notify")
    notify.start_thread()
    svc = start_service(cfg, notify, log=tmp_path / "svc.log")
    try:
        ready = notify.wait_for("READY=1", HANG_S)
        svc.send_signal(signal.SIGTERM)
        rc = svc.wait(30)
    finally:
        if svc.poll() is None:
            svc.kill()
            svc.wait()
        notify.close()
    log = (tmp_path / "svc.log").read_text()
    assert ready and rc == 0, log
    assert "Traceback" not in log
    unusable = [ln for ln in log.splitlines() if "is unusable" in ln]
    assert len(unusable) == 1 and str(state / "state.json") in unusable[0], log
    assert "left by an interrupted save" in log and not (state / "state.json.tmp-999").exists()
    aside = [p for p in state.iterdir() if p.name.startswith("state.json.corrupt-")]
    assert len(aside) == 1
    if data is not None:
        assert aside[0].read_bytes() == data
    store = StateStore(state, model)
    assert store.load() is not None and store.load_errors == 0  # the stop saved a state that loads


def test_a_state_saved_with_round_off_below_a_bound_is_restored(tmp_path):
    """A parameter adapted onto its bound, at the level of the process: a file written by the earlier release with
    c_p_ew = exp(log(300)) = 299.99999999999994 (bounds [300, 900]) keeps every learned parameter
    and the thermal state; the next save holds the bound itself."""
    from thermal_edge.lptn import load_model, steady_state

    model = load_model(MODEL)
    state = tmp_path / "state"
    state.mkdir()
    T, _ = steady_state(model, {"speed_rpm": 900.0, "i_rms": 20.0, "torque_nm": 112.0, "ambient_c": 25.0})
    learned = {"c_p_ew": float(np.exp(np.log(300.0))), "R_e_hous": 7.25, "k_r_sw": 4.5}
    saved = {"format": "thermal_edge.state", "version": 1, "model": model.name, "saved_at": 5000.0, "parameters": learned,
             "param_version": 4, "adapt_runs": 9, "decisions": [{"t": 4000.0, "accepted": True}],
             "nodes": list(model.nodes), "T": [float(x) for x in T], "sigma": [0.4] * len(T),
             "T_pred": [float(x) for x in T], "P": (np.eye(len(T)) * 0.16).tolist(), "inputs": {"ambient_c": 25.0},
             "saved_wall": time.time()}
    (state / "state.json").write_text(json.dumps(saved))
    assert "299.99999999999994" in (state / "state.json").read_text()
    cfg = write_yaml(tmp_path / "edge.yaml", edge_raw(state, {"interface": "virtual", "channel": "t"}, table4=False, adapt=False))
    notify = NotifySocket(tmp_path / "notify")
    notify.start_thread()
    svc = start_service(cfg, notify, log=tmp_path / "svc.log")
    try:
        ready = notify.wait_for("READY=1", HANG_S)
        svc.send_signal(signal.SIGTERM)
        rc = svc.wait(30)
    finally:
        if svc.poll() is None:
            svc.kill()
            svc.wait()
        notify.close()
    log = (tmp_path / "svc.log").read_text()
    assert ready and rc == 0 and "is unusable" not in log, log
    back = json.loads((state / "state.json").read_text())
    assert back["parameters"] == {**learned, "c_p_ew": 300.0}
    assert back["param_version"] == 4 and back["adapt_runs"] == 9 and back["decisions"] == saved["decisions"]
    assert back["T"] == saved["T"] and back["P"] == saved["P"]  # not yet running: the loaded state kept as it was
    assert not [p for p in state.iterdir() if p.name not in ("state.json", LOCKNAME)]  # nothing moved aside
