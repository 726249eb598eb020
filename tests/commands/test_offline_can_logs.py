"""From a CAN recording to everything offline: a log recorded by ``thermal-edge demo --record`` is
exported to a run CSV (checked against a reduction of the log's frames made here, with cantools and
numpy), replayed with ``--plot``/``--out``, and ``calibrate`` and ``discover`` give the same result
on the log as on its run CSV, within what the CSV's rounding can move."""
from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import cantools
import numpy as np
import pytest
from cmd_testlib import MODELS, te_here

from thermal_edge.bus.frames import DEFAULT_DBC_PATH
from thermal_edge.config import load_config
from thermal_edge.data import read_run
from thermal_edge.lptn import load_model
from thermal_edge.shipped import config_path

CONFIG = config_path("edge.yaml")
MODEL = config_path("machines", "pm10kw.yaml")
DBC = DEFAULT_DBC_PATH  # the CAN matrix the example configuration names (codec.dbc: null)
#: simulated seconds recorded: the overload cycle's first load step, heating from ambient
DURATION_S = 150
#: the run CSV's values have 6 significant digits: each is off by at most this, relative
CSV_REL = 5e-6
_LINE = re.compile(r"^\((?P<ts>[\d.]+)\)\s+\S+\s+(?P<id>[0-9A-Fa-f]+)#(?P<data>[0-9A-Fa-f]*)\s+(?P<dir>[RT])$")


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A short closed-loop run of the demo, its bus traffic recorded as a candump -L log."""
    d = tmp_path_factory.mktemp("recording")
    log = d / "drive.log"
    r = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "demo", "--duration", str(DURATION_S), "--speed", "150",
                        "--quiet", "--metrics-port", "0", "--record", str(log)],
                       capture_output=True, text=True, timeout=300, cwd=d,
                       env={"OPENBLAS_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "TMPDIR": str(d)})
    assert r.returncode == 0, r.stderr[-2000:]
    assert log.stat().st_size > 0
    return log


@pytest.fixture(scope="module")
def exported(recording) -> Path:
    out = recording.with_name("run.csv")
    r = te_here("export", recording, "--config", CONFIG, "--out", out)
    assert r.returncode == 0, r.stderr
    assert "0 dropped by the integrity checks" in r.stderr, r.stderr
    return out


def _reduce_frames(log: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The per-tick run the service should see, computed here from the log's received frames:
    ticks at whole seconds crossed by the frames' stamps; the current the RMS of the d/q amplitudes
    over each tick's time (each frame's value held until the next), speed (rounded to 1 rpm) and
    torque the same time means; the temperatures the latest reading before the tick's end. Ticks
    before every input had a frame are left out."""
    cfg = load_config(CONFIG)
    db = cantools.database.load_file(str(DBC))
    frames: dict[str, list[tuple[float, dict]]] = {}
    for line in log.read_text().splitlines():
        m = _LINE.match(line.strip())
        assert m, line
        if m["dir"] != "R":  # the service's own frames
            continue
        msg = db.get_message_by_frame_id(int(m["id"], 16))
        frames.setdefault(msg.name, []).append((float(m["ts"]), msg.decode(bytes.fromhex(m["data"]), decode_choices=False)))
    first_ts = min(v[0][0] for v in frames.values())
    last_ts = max(v[-1][0] for v in frames.values())
    ticks = np.arange(math.floor(first_ts) + 1, math.floor(last_ts) + 1, dtype=float)
    series = {}
    for name, spec in cfg.inputs.items():
        ts = np.array([f[0] for f in frames[spec.frame]])
        sig = [f[1] for f in frames[spec.frame]]
        if spec.reduce == "dq_rms":
            x = np.array([0.5 * (s[spec.signals[0]] ** 2 + s[spec.signals[1]] ** 2) for s in sig])
        else:
            x = np.array([s[spec.signals[0]] for s in sig], dtype=float)
        series[name] = (spec, ts, x)
    start = max(ts[0] for _, ts, _ in series.values())
    ticks = ticks[ticks > start]  # a frame stamped on a boundary belongs to the tick after it
    cols: dict[str, np.ndarray] = {}
    for name, (spec, ts, x) in series.items():
        if spec.reduce == "latest":
            cols[name] = x[np.searchsorted(ts, ticks, side="left") - 1]
            continue
        ends = np.append(ts[1:], np.inf)
        vals = []
        for t in ticks:
            dur = np.clip(np.minimum(ends, t) - np.maximum(ts, t - 1.0), 0.0, None)
            mean = float(np.sum(x * dur) / np.sum(dur))
            v = math.sqrt(mean) if spec.reduce in ("rms", "dq_rms") else mean
            vals.append(round(v / spec.resolution) * spec.resolution if spec.resolution else v)
        cols[name] = np.array(vals)
    for name, spec in cfg.sensors.items():
        ts = np.array([f[0] for f in frames[spec.frame]])
        x = np.array([f[1][spec.signal] for f in frames[spec.frame]], dtype=float)
        cols[name] = x[np.searchsorted(ts, ticks, side="left") - 1]
    return ticks, cols


@pytest.mark.slow  # a demo run (about 10 s) and the commands on it
def test_export_is_the_ticks_of_the_logs_frames(recording, exported):
    cfg = load_config(CONFIG)
    header = next(line for line in exported.read_text().splitlines() if not line.startswith("#"))
    assert header.split(",") == ["t", *cfg.inputs, *cfg.sensors]
    run = read_run(exported)
    ticks, cols = _reduce_frames(recording)
    assert len(run) == len(ticks) and DURATION_S - 3 <= len(ticks) <= DURATION_S
    np.testing.assert_array_equal(run.t, ticks - ticks[0])
    for name, expected in cols.items():
        np.testing.assert_allclose(run.column(name), expected, rtol=CSV_REL, atol=1e-12, err_msg=name)


@pytest.mark.slow  # a demo run (about 10 s) and the commands on it
@pytest.mark.parametrize("suffix", [".blf", ".asc.gz", ".csv"])
def test_the_recording_in_another_format_exports_the_same_run(recording, exported, tmp_path, suffix):
    """python-can's own converter (``can.LogReader`` into ``can.Logger``) writes the recording in
    another format; its export is the same run (the formats keep the timestamps to 1 µs or better)."""
    import can

    other = tmp_path / f"drive{suffix}"
    with can.Logger(str(other)) as writer:
        for msg in can.LogReader(str(recording)):
            writer.on_message_received(msg)
    r = te_here("export", other, "--out", tmp_path / "other.csv")
    assert r.returncode == 0, r.stderr
    a, b = read_run(exported), read_run(tmp_path / "other.csv")
    np.testing.assert_array_equal(a.t, b.t)
    for c in a.columns:
        np.testing.assert_array_equal(a.columns[c], b.columns[c], err_msg=c)


def _error_k(log_run, csv_run, model) -> float:
    """How far, K, the CSV's rounding can move a predicted or measured temperature: the readings'
    own rounding, and the prediction's through the inputs' (copper loss ~ i², so twice the
    current's relative rounding, on the largest temperature rise of the run)."""
    sensors = [s for s in model.sensors if s in csv_run.columns]
    t_max = max(float(np.nanmax(np.abs(csv_run.column(s)))) for s in sensors)
    rise = max(float(np.nanmax(csv_run.column(s)) - np.nanmin(csv_run.column(s))) for s in sensors)
    measured = max(float(np.nanmax(np.abs(log_run.column(s) - csv_run.column(s)))) for s in sensors)
    assert measured <= CSV_REL * t_max
    return CSV_REL * t_max + 2 * CSV_REL * rise


def _fit(out: Path, stdout: str, names: list[str]) -> tuple[dict[str, float], dict[str, float], float, dict[str, str]]:
    """The fitted values (the written model), their 1σ, the residual σ and the identifiable column
    (the printed table)."""
    model = load_model(out)
    values = {n: v for n, v in zip(model.parameter_names, model.nominal()) if n in names}
    rows = {m[1]: (float(m[2]) / 100, m[3])
            for m in re.finditer(r"^\s*(\S+)\s+\S+\s+\S+\s+\S+\s+\S+\s+(\S+)\s+(yes|not identifiable)$", stdout, re.M)}
    sigma = float(re.search(r"residual σ (\S+) K", stdout)[1])
    return values, {n: rows[n][0] * abs(values[n]) for n in names}, sigma, {n: rows[n][1] for n in names}


@pytest.mark.slow  # a demo run (about 10 s) and the commands on it
def test_calibrate_on_the_log_and_on_its_csv_agree(recording, exported, tmp_path):
    from thermal_edge.service.logruns import read_log_runs

    names = ["R_e_hous", "k_r_sw"]
    common = ["--model", MODEL, "--params", ",".join(names), "--generations", "3", "--popsize", "5"]
    a = te_here("calibrate", *common, "--run", recording, "--format", "can", "--config", CONFIG, "--out", tmp_path / "a.yaml")
    b = te_here("calibrate", *common, "--run", exported, "--out", tmp_path / "b.yaml")
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    assert re.search(r"drive\.log: \d+ frames of the drive's CAN matrix, 0 dropped", a.stdout), a.stdout
    va, sa, sigma, ia = _fit(tmp_path / "a.yaml", a.stdout, names)
    vb, _, _, ib = _fit(tmp_path / "b.yaml", b.stdout, names)
    assert ia == ib
    # the rounding moves every residual by at most eps: the fit (least squares, N residuals) moves
    # a parameter by at most its 1σ / σ_residual x sqrt(N) x eps (Cauchy-Schwarz on the
    # linearised solution; the printed 1σ counts correlated residuals, so it is the larger)
    model = load_model(MODEL)
    (log_run,) = read_log_runs(recording, load_config(CONFIG))
    eps = _error_k(log_run, read_run(exported), model)
    n_res = len(log_run) * len(model.sensors)
    for n in names:
        tol = sa[n] / sigma * math.sqrt(n_res) * eps
        assert abs(va[n] - vb[n]) <= tol, (n, va[n], vb[n], tol)


@pytest.mark.slow  # a demo run (about 10 s) and the commands on it
def test_discover_on_the_log_and_on_its_csv_agree(recording, exported):
    from thermal_edge.service.logruns import read_log_runs

    a = te_here("discover", "--model", MODEL, "--run", recording, "--format", "can", "--max-rounds", "1", "--json")
    b = te_here("discover", "--model", MODEL, "--run", exported, "--max-rounds", "1", "--json")
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    da, db = json.loads(a.stdout), json.loads(b.stdout)
    assert da["verdict"] == db["verdict"] and da["effects_added"] == db["effects_added"]
    # a gap is an RMS of residuals: the rounding moves it by at most eps (the refit's shift of the
    # optimum changes it only to second order)
    (log_run,) = read_log_runs(recording, load_config(CONFIG))
    eps = _error_k(log_run, read_run(exported), load_model(MODEL))
    for key in ("gap_before", "gap_after", "gap_nominal"):
        assert abs(da[key] - db[key]) <= eps, (key, da[key], db[key], eps)
    for s, v in da["per_sensor_after"].items():
        assert abs(v - db["per_sensor_after"][s]) <= eps * math.sqrt(len(da["per_sensor_after"])), s


@pytest.mark.slow  # a demo run (about 10 s) and the commands on it
def test_replay_of_the_log_plots_and_writes_the_services_ticks(recording, exported, tmp_path):
    png, out = tmp_path / "replay.png", tmp_path / "ticks.csv"
    r = te_here("replay", "--format", "can", "--run", recording, "--config", CONFIG, "--plot", png, "--out", out, "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    ticks = read_run(out)
    assert len(ticks) == summary["ticks"]
    model = load_model(MODEL)
    for s in model.sensors:
        assert {f"{s}_{k}" for k in ("measured", "predicted", "observer", "band_low", "band_high")} <= set(ticks.columns)
    assert {"current_limit_a", "state", "reason", "adaptation", *model.inputs} <= set(ticks.columns)
    # the readings the service used are the exported run's, tick for tick (the replay also has
    # the ticks before every input had a value)
    run = read_run(exported)
    tail = slice(len(ticks) - len(run), None)
    for s in model.sensors:
        np.testing.assert_allclose(ticks.column(f"{s}_measured")[tail], run.column(s), rtol=CSV_REL, err_msg=s)
    np.testing.assert_allclose(ticks.column(model.inputs[0])[tail], run.column(model.inputs[0]), rtol=2 * CSV_REL)


@pytest.mark.slow  # a demo run (about 10 s) and the commands on it
def test_a_log_with_a_silence_exports_two_runs_and_discover_refuses_it(recording, tmp_path):
    later = "\n".join(re.sub(r"^\((\d+)", lambda m: f"({int(m[1]) + 3600}", line)
                      for line in recording.read_text().splitlines())
    both = tmp_path / "both.log"
    both.write_text(recording.read_text() + later + "\n")
    r = te_here("export", both, "--out", tmp_path / "run.csv")
    assert r.returncode == 0, r.stderr
    first, second = read_run(tmp_path / "run.csv"), read_run(tmp_path / "run-1.csv")
    assert len(first) == len(second) > 0
    d = te_here("discover", "--model", MODEL, "--run", both, "--format", "can")
    assert d.returncode == 2 and "2 runs" in d.stderr and "thermal-edge export" in d.stderr, d.stderr


@pytest.mark.parametrize("args, says", [
    (["export", "missing.log", "--out", "x.csv"], "missing.log: no such CAN log"),
    (["export", "LOG", "--out", "no/such/dir/x.csv"], "--out no/such/dir/x.csv: no such directory"),
    (["export", "LOG", "--out", "x.parquet"], "must end in .csv"),
    (["export", "run.txt", "--out", "x.csv"], "run.txt: unknown CAN log format"),
    (["export", "bad.asc", "--out", "x.csv"], "bad.asc: not one CAN frame read: an empty log, or not a .asc log"),
    (["export", "empty.blf", "--out", "x.csv"], "empty.blf: not a .blf log"),
    (["export", "LOG", "--out", "x.csv"], "drive.log: 0 frames of the configuration's CAN matrix, not two complete ticks"),
    (["calibrate", "--model", str(MODEL), "--run", "missing.blf", "--format", "can", "--out", "x.yaml"],
     "missing.blf: no such CAN log"),
    (["calibrate", "--model", str(MODELS / "other_sensors.yaml"), "--run", "SIM", "--format", "can",
      "--out", "x.yaml"], "a CAN log's columns are the inputs and sensors that the signals: of"),
    (["replay", "--format", "can", "--run", "LOG", "--adapt"], "--adapt: not for a CAN log"),
    (["replay", "--format", "can", "--run", "LOG", "--threshold", "0.2"], "--threshold: not for a CAN log"),
    (["replay", "--format", "can", "--run", "LOG", "--method", "euler"], "--method: not for a CAN log"),
])
def test_export_and_calibrate_refuse_with_one_line(tmp_path, monkeypatch, args, says):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "run.txt").write_text("t,i_rms\n0,1\n")
    (tmp_path / "drive.log").write_text("(1700000000.000000) can0 7FF#00 R\n")
    (tmp_path / "bad.asc").write_bytes(b"\x00\x01 not an asc file")
    (tmp_path / "empty.blf").write_bytes(b"")
    if "SIM" in args:  # a log of the drive the example configuration maps
        assert te_here("simulate", "--model", MODEL, "--cycle", config_path("cycles", "rated_heat_cool.yaml"), "--format",
                       "can", "--duration", "5", "--out", "sim.log").returncode == 0
    r = te_here(*["drive.log" if a == "LOG" else "sim.log" if a == "SIM" else a for a in args])
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and says in r.stderr, r.stderr


def test_the_simulators_can_log_exports_one_row_per_tick(tmp_path):
    """``simulate --format can`` (no service answers: open loop) to a BLF, exported: one row per
    whole second crossed after every input's first frame, counted from the frames' stamps."""
    import can

    log, out = tmp_path / "sim.blf", tmp_path / "sim.csv"
    r = te_here("simulate", "--model", MODEL, "--cycle", config_path("cycles", "rated_heat_cool.yaml"), "--format", "can",
                "--duration", "40", "--t0", "1700000000.25", "--out", log)
    assert r.returncode == 0, r.stderr
    r = te_here("export", log, "--out", out)
    assert r.returncode == 0, r.stderr
    cfg = load_config(CONFIG)
    db = cantools.database.load_file(str(DBC))
    first: dict[str, float] = {}
    last = -math.inf
    with can.BLFReader(str(log)) as reader:
        for msg in reader:
            name = db.get_message_by_frame_id(msg.arbitration_id).name
            first.setdefault(name, msg.timestamp)
            last = max(last, msg.timestamp)
    start = max(first[spec.frame] for spec in cfg.inputs.values())
    expected = math.floor(last) - math.floor(start)  # whole seconds T with start < T <= last
    run = read_run(out)
    assert list(run.columns) == [*cfg.inputs, *cfg.sensors]
    assert len(run) == expected and expected >= 38


GUIDE = Path(__file__).resolve().parents[2] / "docs" / "guide" / "offline-from-can-logs.md"


def _guide_blocks(kind: str) -> list[str]:
    """The guide's fenced blocks of one kind (``sh``, ``text``), in order."""
    return re.findall(rf"^```{kind}\n(.*?)^```$", GUIDE.read_text(encoding="utf-8"), re.M | re.S)


@pytest.mark.slow  # the guide's demo recording and every command on it (about 40 s)
def test_the_guides_commands_run_and_print_what_it_shows(tmp_path):
    from own_ports import own_tcp_port

    port = str(own_tcp_port())  # held by this test process: no other process takes it meanwhile
    outputs = {}
    for block in _guide_blocks("sh"):
        (line,) = block.strip().splitlines()
        argv = line.split()
        assert argv[0] == "thermal-edge", line
        # the shipped files the guide names by their place in the source tree
        argv = [str(config_path(*a.split("/")[1:])) if a.startswith("config/") else a for a in argv[1:]]
        if argv[0] == "demo":  # the metrics port of a test: another may be busy
            argv += ["--metrics-port", port]
        r = subprocess.run([sys.executable, "-m", "thermal_edge.cli", *argv], capture_output=True, text=True,
                           timeout=600, cwd=tmp_path, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
        assert r.returncode == 0, (line, r.stderr[-2000:])
        outputs[argv[0]] = r.stdout + r.stderr
    assert {"demo", "export", "replay", "calibrate", "discover"} <= set(outputs)
    png = (tmp_path / "replay.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "calibrated.yaml").stat().st_size > 0 and (tmp_path / "ticks.csv").stat().st_size > 0
    (shown,) = _guide_blocks("text")
    for expected in shown.strip().splitlines():  # the counts vary by a tick or so: numbers are any number
        pattern = re.sub(r"\d+", r"\\d+", re.escape(expected))
        assert re.search(pattern, outputs["export"]), (expected, outputs["export"])


def test_a_foreign_inverters_recording_is_decoded_by_its_configuration(tmp_path):
    """A recording of the Acme MC-7 (its own DBC, power-invariant d/q currents, no counter or CRC)
    exported with its edge.yaml: the current is the RMS over each tick's time (i² averaged, not i),
    converted by the configuration's d/q convention; with the example configuration of this
    project's CAN matrix, the same log holds no frame of it."""
    import can

    example = config_path("examples", "acme-mc7", "edge.yaml")
    db = cantools.database.load_file(str(config_path("examples", "acme-mc7", "acme-mc7.dbc")))
    t0, seconds = 1_700_000_000.0, 12
    currents, motion = db.get_message_by_name("MC7_Currents"), db.get_message_by_name("MC7_Motion")
    stator, env = db.get_message_by_name("MC7_StatorTemps"), db.get_message_by_name("MC7_Environment")
    log = tmp_path / "mc7.log"
    sent: list[tuple[float, float]] = []  # (time, (i_d² + i_q²) / 3 as the frame carries it, DBC scaling and all)
    with can.Logger(str(log)) as writer:
        for k in range(seconds * 50):  # every 20 ms; the current alternates 10 A and 30 A rms
            t = t0 + 0.005 + k * 0.02
            i_rms = 10.0 if k % 2 == 0 else 30.0
            mag = math.sqrt(3) * i_rms  # power invariant: i_d² + i_q² = 3 I_rms²
            frames = [(currents, {"MC7_CurrentD": -mag * math.sin(0.4), "MC7_CurrentQ": mag * math.cos(0.4),
                                  "MC7_DcLinkVoltage": 560.0}),
                      (motion, {"MC7_MotorSpeed": 900.0, "MC7_TorqueEst": 50.0, "MC7_OperatingState": 2})]
            if k % 10 == 0:
                frames.append((stator, {"MC7_TempWindingU": 100.0 + k / 10, "MC7_TempWindingV": 101.0,
                                        "MC7_TempWindingW": 101.0}))
            if k % 25 == 0:
                frames.append((env, {"MC7_TempHousing": 60.0, "MC7_TempCoolantIn": 30.0, "MC7_TempAmbient": 25.0,
                                     "MC7_TempPowerStage": 50.0}))
            data = currents.encode(frames[0][1])
            dq = currents.decode(data)
            sent.append((t, (dq["MC7_CurrentD"] ** 2 + dq["MC7_CurrentQ"] ** 2) / 3))
            for msg, values in frames:
                writer.on_message_received(can.Message(timestamp=t, arbitration_id=msg.frame_id, is_extended_id=False,
                                                       data=msg.encode(values), channel="can0", is_rx=True))
    r = te_here("export", log, "--config", example, "--out", tmp_path / "mc7.csv")
    assert r.returncode == 0, r.stderr
    run = read_run(tmp_path / "mc7.csv")
    assert len(run) == seconds - 1  # the whole seconds after the first frames, up to the last
    # each frame's i² held until the next, averaged over the tick's second: about sqrt(500) A (25
    # frames at 10 A, 25 at 30 A), not the mean current 20 A
    ts, x = np.array([a for a, _ in sent]), np.array([b for _, b in sent])
    ends = np.append(ts[1:], np.inf)
    ticks = t0 + np.arange(1, seconds)
    expected = [math.sqrt(np.sum(x * np.clip(np.minimum(ends, T) - np.maximum(ts, T - 1), 0, None)) / np.sum(
        np.clip(np.minimum(ends, T) - np.maximum(ts, T - 1), 0, None))) for T in ticks]
    np.testing.assert_allclose(run.column("i_rms"), expected, rtol=CSV_REL)
    np.testing.assert_allclose(run.column("i_rms"), math.sqrt(500.0), rtol=0.01)
    np.testing.assert_allclose(run.column("housing"), 60.0)
    # the tick ending at t0 + n reads the last stator frame before it: sent at t0 + n - 0.195 (every
    # 0.2 s from t0 + 0.005, 1 K warmer each), the 5 n - 1 th
    np.testing.assert_allclose(run.column("slot_winding"), 100.0 + 5 * np.arange(1, seconds) - 1, atol=0.06)
    r = te_here("export", log, "--out", tmp_path / "native.csv")
    assert r.returncode == 2 and "0 frames of the configuration's CAN matrix" in r.stderr, r.stderr


def _config_with_dbc(tmp_path: Path, signal: str, scaling: str) -> Path:
    """The example configuration on the shipped CAN matrix with ``signal``'s factor and offset
    replaced (its unit kept): a recording of the shipped matrix read through a scaling error."""
    import yaml

    from benchmarks.faults.units import rescaled

    dbc = tmp_path / "wrong.dbc"
    dbc.write_text(rescaled(DBC.read_text(), signal, scaling))
    raw = yaml.safe_load(CONFIG.read_text())
    raw["codec"] = {**(raw.get("codec") or {}), "dbc": str(dbc)}
    raw["model"]["path"] = str(config_path("machines", "pm10kw.yaml"))
    cfg = tmp_path / "edge.yaml"
    cfg.write_text(yaml.safe_dump(raw))
    return cfg


def test_a_sensor_read_in_kelvin_is_named_not_exported_as_nan(recording, exported, tmp_path):
    """The housing PT100 decoded 273.15 K too high (an offset of -50 taken as +223.15): every
    reading is implausible in degC and plausible in kelvin. export refuses the log naming the sensor,
    its signal and the unit, with the reading converted back (within the recording's housing)."""
    cfg = _config_with_dbc(tmp_path, "INV_T_Housing", "0.1,223.15")
    r = te_here("export", recording, "--config", cfg, "--out", tmp_path / "x.csv")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    m = re.search(r"every reading of housing \(INV_StatorTemps INV_T_Housing\) was refused: (\S+) degC looks like "
                  r"kelvin \((\S+) degC\)", r.stderr)
    assert m, r.stderr
    housing = read_run(exported).column("housing")
    assert float(m[1]) == pytest.approx(float(m[2]) + 273.15, abs=0.01)
    assert housing.min() - 0.2 <= float(m[2]) <= housing.max() + 0.2


def test_currents_read_in_milliampere_are_named(recording, tmp_path):
    """The dq currents decoded 1000x too large: the RMS current is refused in every tick, and the
    line says why (mA) instead of only that no tick was complete."""
    cfg = _config_with_dbc(tmp_path, "INV_Id", "50,0")
    from benchmarks.faults.units import rescaled

    (tmp_path / "wrong.dbc").write_text(rescaled((tmp_path / "wrong.dbc").read_text(), "INV_Iq", "50,0"))
    r = te_here("export", recording, "--config", cfg, "--out", tmp_path / "x.csv")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "no run in this CAN log (i_rms (INV_Currents INV_Id/INV_Iq) refused: " in r.stderr
    assert re.search(r"refused: \S+ A looks like mA \(\S+ A\); give it in A\)", r.stderr), r.stderr


def test_a_replay_whose_sensor_frames_never_pass_their_crc_says_so(recording, tmp_path):
    """Every INV_StatorTemps frame with its CRC byte flipped: the observer never starts. The summary
    names the drops by reason (as many as the frames changed here) and says there is no estimate,
    instead of printing a NaN peak and a numpy warning."""
    changed = 0
    lines = []
    for line in recording.read_text().splitlines():
        m = re.match(r"^(\(\S+\) \S+ 0B0#)([0-9A-F]{14})([0-9A-F]{2})( R)?$", line)
        if m:
            line = f"{m[1]}{m[2]}{int(m[3], 16) ^ 0xFF:02X}{m[4] or ''}"
            changed += 1
        lines.append(line)
    log = tmp_path / "bad_crc.log"
    log.write_text("\n".join(lines) + "\n")
    assert changed > 100
    r = te_here("replay", "--format", "can", "--run", log)
    assert r.returncode == 0, r.stderr
    assert f"dropped {changed} (crc {changed})" in r.stdout
    assert "no estimate: the observer never started" in r.stdout
    assert "nan" not in r.stdout.lower() and "RuntimeWarning" not in r.stderr


def _judged_ticks(run_csv: Path) -> int:
    """Ticks whose torque takes a fifth of the maximum current or more (|T| / kt, kt and the maximum
    from the model and the example configuration): those the current is judged at, counted here
    from the exported run."""
    import yaml

    kt = float(load_model(MODEL).drive["kt_nm_per_arms"])
    max_a = float(yaml.safe_load(CONFIG.read_text())["derating"]["max_current_a"])
    return int(np.count_nonzero(np.abs(read_run(run_csv).column("torque_nm")) / kt >= 0.2 * max_a))


def test_a_current_scaled_ten_times_low_in_the_dbc_is_refused(recording, exported, tmp_path):
    """The dq currents decoded a tenth of the machine's (factor 0.005 for 0.05): plausible currents,
    copper losses a hundredth. Every tick the torque takes a sizeable current at reads below half of
    it: export refuses the log in one line naming the input, the rule and as many ticks as counted
    here from the good export."""
    cfg = _config_with_dbc(tmp_path, "INV_Id", "0.005,0")
    from benchmarks.faults.units import rescaled

    (tmp_path / "wrong.dbc").write_text(rescaled((tmp_path / "wrong.dbc").read_text(), "INV_Iq", "0.005,0"))
    r = te_here("export", recording, "--config", cfg, "--out", tmp_path / "x.csv")
    judged = _judged_ticks(exported)
    assert judged >= 10
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert (f"every one of the {judged} ticks judged reads i_rms (INV_Currents INV_Id/INV_Iq) below 0.5 of "
            "|torque_nm| / kt (kt 5.6 Nm/A): a scaling of the current in the DBC?") in r.stderr, r.stderr


def test_a_current_read_ten_times_low_for_a_while_is_said_and_exported(recording, exported, tmp_path):
    """From 60 s into the log the current frames carry a tenth (a second sender diluting them): the
    log is exported, and its summary line says at how many ticks the service would not believe the
    current: those of the judged ticks after the change, less the two its confirmation waits."""
    from benchmarks.faults.readings import _faulted

    t0 = float(recording.read_text().split(maxsplit=1)[0].strip("()"))
    low = tmp_path / "low.log"
    _faulted(recording, low, t0, lambda dt, c: {k: v * 0.1 for k, v in c.items()} if dt >= 60.0 else c,
             frame_name="INV_Currents", prefix="INV_I")
    r = te_here("export", low, "--config", CONFIG, "--out", tmp_path / "x.csv")
    assert r.returncode == 0, r.stderr
    m = re.search(r"; (\d+) ticks the service would not believe the current at \(i_rms \(INV_Currents INV_Id/INV_Iq\) "
                  r"below 0\.5 of \|torque_nm\| / kt \(kt 5\.6 Nm/A\) for 3 ticks or more", r.stderr)
    assert m, r.stderr
    good = read_run(exported)
    import yaml

    kt, max_a = 5.6, float(yaml.safe_load(CONFIG.read_text())["derating"]["max_current_a"])
    late = (good.t >= 61.0) & (np.abs(good.column("torque_nm")) / kt >= 0.2 * max_a)
    assert 0 < int(m[1]) and abs(int(m[1]) - (int(np.count_nonzero(late)) - 2)) <= 2, (m[1], np.count_nonzero(late))
