"""``replay --format can --out`` reproduces what the service sent: a log recorded by ``thermal-edge
demo --record`` is decoded here with cantools (the service's own ``TE_Estimates`` frames, ``T``
lines), and every tick's estimates and upper bands in the replay's table equal the frame's signals
within the signal's resolution; the magnet's upper band is the observer's band raised to the mean
of the last readings of the housing PT100 (which bounds the magnet from below), computed here from
the table's own columns."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
import yaml
from cmd_testlib import te_here

from thermal_edge.bus.frames import DEFAULT_DBC_PATH
from thermal_edge.data import read_run
from thermal_edge.service.derating import FLOOR_TICKS
from thermal_edge.service.flux_input import OUTCOMES

#: simulated seconds recorded: long enough for the overload to heat the housing PT100 above the
#: magnet's observer band (from ~250 s on in the demo's cycle)
DURATION_S = 420
#: the per-tick table's values have 6 significant digits: each is off by at most this (K, < 1000 °C)
CSV_ABS = 5e-4
#: TE_Estimates signal -> the replay's column
COLUMNS = {"TE_T_HotSpot": "hot_spot_observer", "TE_T_HotSpotUpper": "hot_spot_upper",
           "TE_T_Magnet": "magnet_observer", "TE_T_MagnetUpper": "magnet_upper"}


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """The demo's closed loop, its bus traffic recorded. ``--no-table4``: the service's model at the
    packaged configuration's parameters, so that the replay with that configuration is the service
    that ran (the demo's default start, off by the paper's Table 4, is in no configuration file)."""
    d = tmp_path_factory.mktemp("recording")
    log = d / "drive.log"
    r = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "demo", "--no-table4", "--duration", str(DURATION_S),
                        "--speed", "200", "--quiet", "--metrics-port", "0", "--record", str(log)],
                       capture_output=True, text=True, timeout=600, cwd=d,
                       env={"OPENBLAS_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "TMPDIR": str(d)})
    assert r.returncode == 0, r.stderr[-2000:]
    return log


def _sent_estimates(log: Path) -> dict[float, dict[str, float]]:
    """The service's TE_Estimates frames of the log by timestamp (s since the epoch), decoded by cantools."""
    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))
    msg = db.get_message_by_name("TE_Estimates")
    sent = {}
    for m in can.LogReader(str(log)):
        if m.arbitration_id == msg.frame_id and not m.is_rx:
            sent[round(m.timestamp, 3)] = msg.decode(m.data, decode_choices=False)
    return sent


def _assert_reproduced(recording: Path, out: Path):
    """Every tick's TE_Estimates signals in the replay's table ``out`` as the service sent them; the table."""
    ticks = read_run(out)
    t0 = float(re.search(r"first tick at ([\d.]+) s since the epoch", out.read_text()).group(1))
    sent = _sent_estimates(recording)
    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))
    msg = db.get_message_by_name("TE_Estimates")
    no_value = {s: msg.get_signal_by_name(s).scale * 4095 + msg.get_signal_by_name(s).offset for s in COLUMNS}
    compared = 0
    for k, t in enumerate(ticks.t):
        frame = sent.get(round(t0 + float(t), 3))
        assert frame is not None, f"no TE_Estimates sent at the tick t={t:g} s"
        for sig, col in COLUMNS.items():
            v, mine = frame[sig], ticks.column(col)[k]
            if v == pytest.approx(no_value[sig]):  # "no value": not initialised yet
                assert not np.isfinite(mine), f"t={t:g} s {sig}: no value sent, replay {col} {mine}"
                continue
            tol = msg.get_signal_by_name(sig).scale / 2 + CSV_ABS
            assert abs(mine - v) <= tol, f"t={t:g} s {sig}: sent {v}, replay {col} {mine}"
            compared += 1
    assert compared >= 4 * (len(ticks) - 1) and len(ticks) >= DURATION_S - 5  # initialised from the first tick
    assert len(sent) == len(ticks)  # one TE_Estimates per tick with the frame clock, none the replay lacks
    return ticks


@pytest.mark.slow  # a demo run of 420 simulated s (about 15 s) and its replay
def test_replay_reproduces_the_te_estimates_the_service_sent(recording, tmp_path):
    out = tmp_path / "ticks.csv"
    r = te_here("replay", "--format", "can", "--run", recording, "--out", out)
    assert r.returncode == 0, r.stderr
    ticks = _assert_reproduced(recording, out)

    # the band sent on the magnet: the observer's band (symmetric about the estimate) raised to the
    # mean of the housing PT100's last FLOOR_TICKS readings, as the table's own columns give them
    est, lo, hi, up = (ticks.column(f"magnet_{c}") for c in ("observer", "band_low", "band_high", "upper"))
    housing = ticks.column("housing_measured")
    ok = np.isfinite(up)
    np.testing.assert_allclose((hi - est)[ok], (est - lo)[ok], atol=2 * CSV_ABS)
    readings = [float(v) for v in housing if np.isfinite(v)]
    seen = 0
    floor = np.full(len(ticks), np.nan)
    for k, v in enumerate(housing):
        if np.isfinite(v):
            seen += 1
        last = readings[max(0, seen - FLOOR_TICKS):seen]
        floor[k] = np.mean(last) if last else np.nan
    expected = np.fmax(hi, floor)
    np.testing.assert_allclose(up[ok], expected[ok], atol=2 * CSV_ABS)
    # the recording covers both: the observer's band binding, and the housing's readings above it
    raised = up[ok] > hi[ok] + 0.5
    assert 0.2 < np.mean(raised) < 0.8


@pytest.fixture(scope="module")
def voltage_recording(tmp_path_factory) -> tuple[Path, Path]:
    """The demo with the inverter's voltages, fused with a calibration commissioned on a simulated
    bench run and named in the configuration, so that the replay fuses what the service fused."""
    from thermal_edge.bench.protection import flux_calibration
    from thermal_edge.lptn import load_model
    from thermal_edge.shipped import config_path, example_config

    d = tmp_path_factory.mktemp("voltages")
    flux = flux_calibration(load_model(config_path("machines", "pm10kw.yaml")), d / "flux.json")
    raw = yaml.safe_load(example_config())
    raw["flux"] = {**(raw.get("flux") or {}), "calibration": str(flux)}
    cfg = d / "edge.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    log = d / "drive.log"
    r = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "demo", "--no-table4", "--duration", str(DURATION_S),
                        "--speed", "200", "--quiet", "--metrics-port", "0", "--voltages", "--config", str(cfg),
                        "--record", str(log)],
                       capture_output=True, text=True, timeout=600, cwd=d,
                       env={"OPENBLAS_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "TMPDIR": str(d)})
    assert r.returncode == 0, r.stderr[-2000:]
    return log, cfg


@pytest.mark.slow  # a demo run of 420 simulated s with the voltages' commissioning (about 25 s) and its replay
def test_replay_accounts_for_the_voltage_input(voltage_recording, tmp_path):
    """With the voltages fused, the replay still reproduces every TE_Estimates frame (the magnet
    included, which the fusion moves); it says per tick what became of the flux estimate, and its
    summary counts the same outcomes the table shows."""
    log, cfg = voltage_recording
    out = tmp_path / "ticks.csv"
    r = te_here("replay", "--format", "can", "--run", log, "--config", cfg, "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    ticks = _assert_reproduced(log, out)
    counts = json.loads(r.stdout)["voltage_input"]
    assert set(counts) == set(OUTCOMES)
    outcome = ticks.column("flux_outcome")
    per_tick = {name: int(np.sum(outcome == i)) for i, name in enumerate(OUTCOMES)}
    assert per_tick == counts
    # one outcome a tick, but for the first (no state to fuse into yet)
    assert sum(counts.values()) == np.sum(np.isfinite(outcome)) >= len(ticks) - 1
    assert counts["used"] > 0.9 * len(ticks)  # the overload cycle keeps the machine turning: informative
    used = outcome == OUTCOMES.index("used")
    magnet, sigma = ticks.column("flux_magnet"), ticks.column("flux_sigma")
    assert np.all(np.isfinite(magnet[used])) and np.all((sigma[used] > 0) & np.isfinite(sigma[used]))
    # what the voltages said of the magnet agrees with the observer they were fused into, within their σ
    gap = np.abs(magnet[used] - ticks.column("magnet_observer")[used])
    assert np.median(gap / sigma[used]) < 3.0

    r = te_here("replay", "--format", "can", "--run", log, "--config", cfg)
    assert r.returncode == 0 and f"voltage input: {counts['used']} tick(s) fused into the magnet" in r.stdout


@pytest.mark.slow
def test_replay_without_the_voltage_input_says_so(recording):
    r = te_here("replay", "--format", "can", "--run", recording)
    assert r.returncode == 0, r.stderr
    assert "voltage input: off (no flux.calibration" in r.stdout
