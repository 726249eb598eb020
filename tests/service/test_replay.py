"""``thermal-edge simulate --format can`` (and its old name ``candump``) and replaying logs through the service pipeline."""
from __future__ import annotations

import subprocess
import sys

import cantools
import numpy as np
import pytest
from svc_testlib import CYCLES, DBC, MODEL, REPO, edge_raw, env, write_yaml

from thermal_edge.bus import read_log as read_candump
from thermal_edge.config import load_config
from thermal_edge.service import replay_candump
from thermal_edge.sim.inverter import write_log as write_candump


@pytest.mark.parametrize("fmt", ["can", "candump"])  # candump: the option's old name, still taken
def test_simulate_writes_a_decodable_candump_log(tmp_path, fmt):
    out = tmp_path / "run.log"
    proc = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "simulate", "--model", str(MODEL), "--cycle",
                           str(CYCLES / "rated_heat_cool.yaml"), "--out", str(out), "--format", fmt, "--duration", "60",
                           "--current-period", "0.1"], capture_output=True, text=True, env=env(), cwd=str(REPO), timeout=60)
    assert proc.returncode == 0, proc.stderr
    lines = out.read_text().splitlines()
    assert f"wrote {out}: {len(lines)} frames over 60 s" in proc.stdout
    assert len(lines) == 60 * (10 + 10 + 10 + 10)  # currents and mechanics at 0.1 s, temperatures at 0.1 s
    db = cantools.database.load_file(str(DBC))
    names = set()
    for ln in lines[:400]:
        ts, chan, frame, flag = ln.split()
        fid, data = frame.split("#")
        names.add(db.decode_message(int(fid, 16), bytes.fromhex(data)) and db.get_message_by_frame_id(int(fid, 16)).name)
    assert names == {"INV_Currents", "INV_Mechanics", "INV_StatorTemps", "INV_AmbientTemps"}
    frames = read_candump(out)  # counters and CRCs are good
    assert len(frames) == len(lines)


def test_replay_of_a_simulated_log_tracks_the_sensors_and_bridges_gaps(tmp_path):
    a, b = tmp_path / "a.log", tmp_path / "b.log"
    write_candump(MODEL, CYCLES / "rated_heat_cool.yaml", a, duration_s=300, t0=1.7e9, current_period_s=0.1,
                  temperature_period_s=1.0)
    write_candump(MODEL, CYCLES / "rated_heat_cool.yaml", b, duration_s=120, t0=1.7e9 + 3600, current_period_s=0.1,
                  temperature_period_s=1.0, seed=1)
    log = tmp_path / "ab.log"
    log.write_text(a.read_text() + b.read_text())  # an hour without frames in between
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", edge_raw(tmp_path / "state", {"interface": "virtual"}, table4=False,
                                                                  adapt=False)))
    res = replay_candump(log, cfg, keep_outputs=True)
    assert 400 < len(res.t) < 430  # 300 + 120 ticks, not 3600 more
    assert res.frame_stats["lost"] == 0 and res.frame_stats["crc"] == 0
    assert np.all(np.isfinite(res.estimate))
    # the estimate of the measured end winding follows its readings
    frames = [f for f in read_candump(a) if f.name == "INV_StatorTemps"]
    y = {round(f.timestamp): f.signals["INV_T_EndWinding"] for f in frames}
    k = res.nodes.index("end_winding_1")
    errs = [abs(res.estimate[i, k] - y[int(t) - 1]) for i, t in enumerate(res.t) if int(t) - 1 in y and t > 1.7e9 + 30]
    assert max(errs) < 1.0
    # after the hour-long gap the state was cooled at standstill, then corrected by the readings
    i_gap = int(np.argmax(np.diff(res.t) > 100)) + 1
    assert res.t[i_gap] - res.t[i_gap - 1] > 3000
    hs = res.nodes.index("end_winding_2")
    assert res.estimate[i_gap, hs] < res.estimate[i_gap - 1, hs]


def test_replay_summary_for_the_command_line(tmp_path):
    from thermal_edge.service.replay import format_summary, replay_summary

    log = tmp_path / "run.log"
    write_candump(MODEL, CYCLES / "rated_heat_cool.yaml", log, duration_s=90, current_period_s=0.1, temperature_period_s=1.0)
    cfg = write_yaml(tmp_path / "edge.yaml", edge_raw(tmp_path / "state", {"interface": "virtual"}, table4=False, adapt=False))
    s = replay_summary(log, cfg)
    assert s["ticks"] == 89 and s["frames_lost"] == 0 and s["model"] == "pm10kw"
    assert set(s["max_estimate_c"]) == {"hot_spot", "magnet"}
    text = format_summary(s)
    assert "89 ticks" in text and "hot_spot" in text
