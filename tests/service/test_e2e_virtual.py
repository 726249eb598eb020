"""End to end in one process over the python-can ``virtual`` bus: the simulated machine (plant =
pm10kw nominal) and the service (its model off by the paper's Table 4 variations) through the 3 h
overload cycle, accelerated, closed loop. The run is recorded to a candump -L log, which must
decode with cantools and replay to the same estimates."""
from __future__ import annotations

import asyncio
import math
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from svc_testlib import (
    DBC,
    HANG_S,
    REPO,
    T0,
    async_wait_until,
    edge_raw,
    emulator_config,
    env,
    final_parameters,
    heldout_rms,
    open_loop_true_max,
    table4_model_params,
    write_yaml,
)

from thermal_edge.config import load_config
from thermal_edge.service import EdgeService, replay_candump
from thermal_edge.sim.inverter import InverterEmulator

REPLAY_PREFIX_S = 5400.0  # the replay check runs over the first 90 min (adaptations applied)


@dataclass
class Run:
    cfg: Any
    state_dir: Path
    log: Path
    summary: Any
    ticks: dict[float, np.ndarray] = field(default_factory=dict)
    codec_stats: dict[str, Any] = field(default_factory=dict)
    metrics_text: str = ""
    accepted: int = 0
    runs: int = 0
    wall_s: float = 0.0
    decode: subprocess.Popen[bytes] | None = None
    decode_out: Path | None = None


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Run:
    tmp = tmp_path_factory.mktemp("e2e_virtual")
    channel = f"te-e2e-{time.monotonic_ns()}"
    log = tmp / "run.log"
    raw = edge_raw(tmp / "state", {"interface": "virtual", "channel": channel}, table4=True, adapt=True, record=log,
                   metrics_port=0)
    cfg = load_config(write_yaml(tmp / "edge.yaml", raw))

    async def main() -> Run:
        svc = EdgeService(cfg)
        await svc.start()
        r = Run(cfg, tmp / "state", log, None)
        svc.on_tick.append(lambda out: r.ticks.__setitem__(out.t, out.estimate.copy()))
        # the emulator waits for the service however long a busy host holds it (a hang guard, not a
        # time-out it gives up at), with the simulated limits time-out alone: a pause of this process is
        # no time of the plant's, and an emulator that ran ahead without limits would overheat it itself
        emu = InverterEmulator(emulator_config(limits_timeout_s=math.inf, flow_timeout_s=HANG_S),
                               {"interface": "virtual", "channel": channel, "preserve_timestamps": True})
        t = time.monotonic()
        r.summary = await emu.run()
        r.wall_s = time.monotonic() - t
        want = r.summary.frames_sent["INV_Currents"]
        await async_wait_until(lambda: svc.codec.stats.received["INV_Currents"] >= want, HANG_S)  # frames still in flight
        await svc.stop()
        r.codec_stats = svc.codec.stats.as_dict()
        r.metrics_text = svc.metrics.text()
        r.accepted, r.runs = svc.engine.adapt_accepted, svc.engine.adapt_runs
        return r

    r = asyncio.run(main())
    # cantools decodes the whole log in the background while the other checks run
    r.decode_out = tmp / "decoded.txt"
    with open(log, "rb") as fin, open(r.decode_out, "wb") as fout:
        r.decode = subprocess.Popen([sys.executable, "-m", "cantools", "decode", "-s", str(DBC)], stdin=fin, stdout=fout,
                                    stderr=subprocess.PIPE, env=env(), cwd=str(REPO))
    return r


def test_service_adapts_heldout_error_halves(run):
    before = heldout_rms(table4_model_params())
    after = heldout_rms(final_parameters(run.state_dir))
    print(f"held-out RMS before {before:.3f} K, after {after:.3f} K; accepted {run.accepted}/{run.runs}")
    assert run.accepted >= 1
    assert after <= 0.5 * before


def test_closed_loop_keeps_the_true_hot_spot_below_its_maximum(run):
    warn, mx = run.cfg.limit_band(next(lim for lim in _model().limits if lim.name == "hot_spot"))
    closed = run.summary.true_max_c["hot_spot"]
    open_ = open_loop_true_max("end_winding_2")
    print(f"true hot spot max: closed loop {closed:.1f} degC, open loop {open_:.1f} degC (max {mx:g}); "
          f"emulator flow waits {run.summary.flow_waits} ({run.summary.flow_wait_wall_s:.1f} s), "
          f"given up {run.summary.flow_timeouts}; run {run.wall_s:.1f} s")
    assert closed < mx < open_
    _, mmax = run.cfg.limit_band(next(lim for lim in _model().limits if lim.name == "magnet"))
    assert run.summary.true_max_c["magnet"] < mmax
    assert run.summary.limited_s > 600  # the service really derated the machine


def test_no_frame_lost_or_corrupted(run):
    st = run.codec_stats
    assert st["lost"] == 0 and st["crc"] == 0 and sum(st[k] for k in ("counter_repeat", "unknown_id", "dlc", "decode_error")) == 0
    assert st["counter_resync"] == 0  # every counter was judged
    s = run.summary
    assert s.rx_lost == 0 and sum(s.rx_dropped.values()) == 0 and s.send_failures == 0
    for name, n in s.frames_sent.items():
        assert st["received"][name] == n, name
    # one per tick over the 3 h (10,800 ticks); the emulator stops at the end of its cycle, so
    # the service's last few TE_Status frames can still be in flight (seen: 10,789)
    assert s.frames_received["TE_Status"] >= 10780


def test_candump_log_decodes_with_cantools(run):
    assert run.decode is not None
    _, err = run.decode.communicate(timeout=120)
    assert run.decode.returncode == 0, err.decode()
    lines = run.decode_out.read_text().splitlines()
    n_log = sum(1 for _ in open(run.log))
    assert len(lines) == n_log > 250_000
    good = re.compile(r"^\(\d+\.\d+\) can0 [0-9A-F]{3}#[0-9A-F]{16} [RT] :: (INV|TE)_\w+\(")
    bad = [ln for ln in lines if not good.match(ln)]
    assert not bad, bad[:3]
    # TE_AdaptCount carries the adaptations accepted since start, as the matrix says (not the runs)
    counts = [int(m[1]) for ln in lines if (m := re.search(r"TE_Status\(.*TE_AdaptCount: (\d+)", ln))]
    assert counts and counts[-1] == run.accepted < run.runs, (counts[-1:], run.accepted, run.runs)


def test_replay_of_the_log_gives_the_same_estimates(run, tmp_path):
    prefix = tmp_path / "prefix.log"
    end = T0 + REPLAY_PREFIX_S
    with open(run.log) as fin, open(prefix, "w") as fout:
        for line in fin:
            if float(line[1:line.index(")")]) >= end:
                break
            fout.write(line)
    res = replay_candump(prefix, run.cfg)
    assert len(res.t) > REPLAY_PREFIX_S - 5
    assert sum(1 for d in res.decisions if d.get("accepted")) >= 1  # adaptation inside the replayed part
    live = np.array([run.ticks[t] for t in res.t])
    assert np.array_equal(live, res.estimate)  # bit for bit


def test_metrics_cover_the_service(run):
    text = run.metrics_text
    for family in ("thermal_edge_node_estimate_celsius", "thermal_edge_node_prediction_celsius",
                   "thermal_edge_sensor_measurement_celsius", "thermal_edge_prediction_error_celsius",
                   "thermal_edge_prediction_error_rms_celsius", "thermal_edge_parameter_value", "thermal_edge_parameter_band",
                   "thermal_edge_adaptation_runs_total", "thermal_edge_adaptation_accepted_total",
                   "thermal_edge_adaptation_rejected_total", "thermal_edge_adaptation_duration_seconds_bucket",
                   "thermal_edge_frames_received_total", "thermal_edge_frames_sent_total", "thermal_edge_frames_dropped_total",
                   "thermal_edge_tick_duration_seconds_bucket", "thermal_edge_tick_lateness_seconds_bucket",
                   "thermal_edge_current_limit_amperes", "thermal_edge_torque_limit_newton_meters", "thermal_edge_derate_reason",
                   "thermal_edge_state", "thermal_edge_build_info", "thermal_edge_time_to_limit_seconds",
                   "thermal_edge_lookahead_current_amperes"):
        assert f"\n{family}" in text, family
    model = _model()
    for node in model.nodes:
        assert f'thermal_edge_node_estimate_celsius{{node="{node}"}}' in text
    assert 'thermal_edge_parameter_band{bound="upper",parameter="R_e_hous"}' in text
    assert 'thermal_edge_sensor_measurement_celsius{node="end_winding_1",sensor="end_winding"}' in text


def _model():
    from svc_testlib import MODEL

    from thermal_edge.lptn import load_model

    return load_model(MODEL)
