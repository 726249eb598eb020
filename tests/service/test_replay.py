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


def _live_tick_outputs_at_the_end(tmp_path, monkeypatch, duration_s: float) -> tuple[int, int]:
    """(ticks, TickOutput objects alive when the last frame has been read) of a summary-only replay."""
    import gc

    from thermal_edge.service.engine import ThermalEngine
    from thermal_edge.service.outputs import TickOutput
    from thermal_edge.service.replay import replay_log

    log = tmp_path / f"run{duration_s:g}.log"
    write_candump(MODEL, CYCLES / "rated_heat_cool.yaml", log, duration_s=duration_s, current_period_s=0.1,
                  temperature_period_s=1.0)
    cfg = write_yaml(tmp_path / "edge.yaml", edge_raw(tmp_path / "state", {"interface": "virtual"}, table4=False, adapt=False))
    alive: list[int] = []
    close = ThermalEngine.close

    def counting_close(engine: ThermalEngine) -> None:  # the replay's loop is over, its locals still held
        gc.collect()
        alive.append(sum(1 for o in gc.get_objects() if isinstance(o, TickOutput)))
        close(engine)

    monkeypatch.setattr(ThermalEngine, "close", counting_close)
    res, _ = replay_log(log, cfg, per_tick=False)
    assert len(res.t) == 0 and res.estimate.shape == (0, len(res.nodes))  # nothing per tick returned either
    return res.totals.ticks, alive[0]


def test_a_summary_only_replay_keeps_nothing_per_tick(tmp_path, monkeypatch):
    ticks1, alive1 = _live_tick_outputs_at_the_end(tmp_path, monkeypatch, 200.0)
    ticks2, alive2 = _live_tick_outputs_at_the_end(tmp_path, monkeypatch, 400.0)
    assert (ticks1, ticks2) == (199, 399)
    assert alive2 == alive1 <= 2  # the engine's last output (and the one being folded in), not one per tick


def test_the_streamed_summary_is_the_summary_of_the_per_tick_arrays(tmp_path):
    from thermal_edge.lptn import load_model
    from thermal_edge.service.replay import replay_summary

    log = tmp_path / "run.log"
    write_candump(MODEL, CYCLES / "rated_heat_cool.yaml", log, duration_s=240, current_period_s=0.1,
                  temperature_period_s=1.0)
    cfg_path = write_yaml(tmp_path / "edge.yaml", edge_raw(tmp_path / "state", {"interface": "virtual"}, table4=False,
                                                           adapt=False))
    s = replay_summary(log, cfg_path)
    full = replay_candump(log, load_config(cfg_path))  # every tick's arrays, the summary computed from them here
    model = load_model(MODEL)
    assert s["ticks"] == len(full.t) == full.totals.ticks
    assert (s["t_first"], s["t_last"]) == (full.t[0], full.t[-1])
    assert s["final_estimate_c"] == dict(zip(full.nodes, full.estimate[-1].tolist()))
    assert s["max_estimate_c"] == {lim.name: float(np.nanmax(full.node(lim.node))) for lim in model.limits}
    assert s["min_current_limit_a"] == float(np.min(full.current_limit_a))
