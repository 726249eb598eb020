"""Restart: SIGKILL the service of a hot machine mid-run, start it again; its first estimates are
within 2 K of the plant's true node temperatures (the saved state, cooled over the downtime with
the model, corrected by the first readings), while a start from the readings alone is not."""
from __future__ import annotations

import json
import signal
import subprocess
import time

import numpy as np

from svc_testlib import (MODEL, REPO, T0, NotifySocket, edge_raw, emulator_cmd, env, start_service, wait_until,
                         write_yaml)


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
    cfg_b = write_yaml(tmp_path / "b.yaml", edge_raw(state, bus, table4=False, adapt=False, save_interval_s=1e9))
    state_file = state / "state.json"
    notify = NotifySocket(tmp_path / "notify")
    notify.start_thread()
    emu = svc = None
    try:
        svc = start_service(cfg_a, notify, log=tmp_path / "a.log")
        assert notify.wait_for("READY=1", 60)
        # without TE_Limits the inverter's own protection trips the drive (fallback 0 A: standstill)
        emu = subprocess.Popen(emulator_cmd(udp_port, tmp_path / "summary.json", tmp_path / "trace.npz", duration=3300.0,
                                            fallback_current=0.0, speed=300.0, flow_timeout=0.5),
                               env=env(), cwd=str(REPO), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        assert wait_until(lambda: saved_at(state_file) >= T0 + 2400, 120), "service A did not get to 40 min"
        svc.send_signal(signal.SIGKILL)
        svc.wait(10)
        last_a = saved_at(state_file)
        svc = start_service(cfg_b, None, log=tmp_path / "b.log")
        assert wait_until(lambda: saved_at(state_file) > last_a, 60), (tmp_path / "b.log").read_text()
        time.sleep(0.1)  # the file is replaced atomically; read the first save
        first = json.loads(state_file.read_text())
        svc.send_signal(signal.SIGKILL)  # no final save: keep the first one
        svc.wait(10)
        _, err = emu.communicate(timeout=120)
        assert emu.returncode == 0, err.decode()
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
