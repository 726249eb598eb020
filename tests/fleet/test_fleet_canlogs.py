"""The fleet reads its machines' CAN logs (every format of the bus module) as runs: decoded with the
DBC and reduced per tick by the service configuration's signal mapping."""
from __future__ import annotations

import gzip
import shutil

import numpy as np
import pytest

from thermal_edge.config import load_config
from thermal_edge.data import RunError, write_run
from thermal_edge.fleet.evaluate import evaluate_machine
from thermal_edge.fleet.runs import find_machines
from thermal_edge.fleet.task import read_machine_runs
from thermal_edge.lptn import Role, load_model
from thermal_edge.service.logruns import read_log_runs
from thermal_edge.shipped import config_path
from thermal_edge.sim.inverter import EmulatorConfig, InverterEmulator

MODEL = config_path("machines", "pm10kw.yaml")
CYCLE = config_path("cycles", "rated_heat_cool.yaml")
T0 = 1_700_000_000.0
DURATION_S = 600.0


def read_can_runs(path):
    """The runs of a CAN log decoded with the shipped service configuration (the fleet's default)."""
    return read_log_runs(path, load_config(config_path("edge.yaml")))


def _emulate(path, **cfg) -> InverterEmulator:
    """The inverter's frames of an open-loop run written to ``path``; the emulator keeps the truth."""
    settings = dict(model_path=MODEL, cycle_path=CYCLE, duration_s=DURATION_S, t0=T0, current_period_s=0.1,
                    temperature_period_s=1.0, closed_loop=False, trace_every_s=1.0)
    emu = InverterEmulator(EmulatorConfig(**{**settings, **cfg}))
    emu.write_log(path)
    return emu


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet_logs")
    model = load_model(MODEL)
    nominal = dict(zip(model.parameter_names, model.nominal()))
    (d / "m1").mkdir()
    (d / "m2").mkdir()
    healthy = _emulate(d / "m1" / "drive.log", seed=1)
    for suffix in (".asc.gz", ".blf"):  # the same run in other formats
        _emulate(d / f"same{suffix}", seed=1)
    faulty = _emulate(d / "m2" / "drive.blf", seed=2, params={"R_e_hous": 3.0 * nominal["R_e_hous"]})
    return d, model, healthy, faulty


def test_a_can_log_becomes_the_runs_columns_per_tick(logs):
    d, model, emu, _ = logs
    (run,) = read_can_runs(d / "m1" / "drive.log")
    assert set(run.columns) == set(model.inputs) | set(model.sensors)
    assert run.dt == 1.0 and DURATION_S - 3 <= len(run) <= DURATION_S
    assert float(run.meta["epoch_s"]) == T0 + 1.0  # the first whole tick
    tr = emu.trace()  # the truth, every simulated second from t0
    k = (float(run.meta["epoch_s"]) + run.t - T0).astype(int) - 1  # the tick ending at t covers [t - 1, t)
    # inputs: the applied current (RMS over the tick) and the ambient the emulator drove
    np.testing.assert_allclose(run.column(model.input_name(Role.CURRENT)), tr["i_applied"][k], rtol=1e-3, atol=0.1)
    np.testing.assert_allclose(run.column(model.input_name(Role.AMBIENT)), tr["ambient"][k], atol=0.35)
    # sensors: the PT100 readings (0.1 K noise and steps) of the true node temperatures
    for sensor, node in model.sensors.items():
        truth = tr["T"][k + 1, model.node_index(node)]
        err = run.column(sensor) - truth
        assert np.nanmax(np.abs(err)) < 0.6 and abs(np.nanmean(err)) < 0.1, sensor


def test_every_log_format_gives_the_same_run(logs):
    d = logs[0]
    (ref,) = read_can_runs(d / "m1" / "drive.log")
    for name in ("same.asc.gz", "same.blf"):
        (run,) = read_can_runs(d / name)
        np.testing.assert_array_equal(run.t, ref.t)
        for c in ref.columns:
            np.testing.assert_array_equal(run.columns[c], ref.columns[c], err_msg=f"{name} {c}")


def test_a_silence_in_the_log_ends_a_run(logs, tmp_path):
    d = logs[0]
    later = tmp_path / "later.log"
    _emulate(later, seed=5, t0=T0 + 3600.0, duration_s=120.0)
    both = tmp_path / "both.log.gz"
    with gzip.open(both, "wt") as out:
        out.write((d / "m1" / "drive.log").read_text() + later.read_text())
    first, second = read_can_runs(both)
    assert len(first) >= DURATION_S - 3 and 115 <= len(second) <= 120
    assert second.source == f"{both}#1" and float(second.meta["epoch_s"]) == T0 + 3601.0


def test_a_silence_after_less_than_a_tick_of_frames_is_no_drive_data(logs, tmp_path):
    """Half a second of frames, 21 s without any, then the drive: the frames before the silence
    make no tick, and no tick bridges the silence with their values; the one run starts with the
    drive's own first whole tick."""
    d = logs[0]
    lines = (d / "m1" / "drive.log").read_text().splitlines()
    early = [ln for ln in lines if float(ln.split()[0].strip("()")) < T0 + 0.5]
    later = tmp_path / "later.log"
    _emulate(later, seed=5, t0=T0 + 22.0, duration_s=120.0)
    both = tmp_path / "gap.log"
    both.write_text("\n".join(early) + "\n" + later.read_text())
    (run,) = read_can_runs(both)
    (alone,) = read_can_runs(later)
    assert early and float(run.meta["epoch_s"]) == T0 + 23.0 == float(alone.meta["epoch_s"])
    np.testing.assert_array_equal(run.t, alone.t)
    for c in alone.columns:
        np.testing.assert_array_equal(run.columns[c], alone.columns[c], err_msg=c)


def test_machines_from_directories_of_logs_and_csvs(logs, tmp_path):
    d = logs[0]
    fleet = tmp_path / "fleet"
    shutil.copytree(d / "m1", fleet / "m1")
    (run,) = read_can_runs(d / "m1" / "drive.log")
    write_run(fleet / "m1" / "bench.csv", run)  # a bench run of the same machine, as a CSV
    shutil.copy(d / "same.asc.gz", fleet / "m7.asc.gz")
    machines = find_machines([str(fleet / "m1"), str(fleet / "m7.asc.gz")])
    assert [(m.id, len(m.runs)) for m in machines] == [("m1", 2), ("m7", 1)]
    runs = read_machine_runs(machines[0], "csv", None)
    assert len(runs) == 2 and all(len(r) == len(run) for r in runs)
    np.testing.assert_allclose(runs[0].column("housing"), runs[1].column("housing"), atol=1e-9)
    with pytest.raises(RunError, match=r"m7\.asc\.gz: a CAN log has no columns"):
        find_machines([str(fleet / "m7.asc.gz")], id_column="machine")


def test_a_log_without_the_configurations_frames_is_refused(tmp_path):
    empty = tmp_path / "other.log"
    empty.write_text("(1700000000.000000) can0 7FF#00 R\n")
    with pytest.raises(RunError, match=r"other\.log: 0 frames .* no run in this CAN log"):
        read_can_runs(empty)
    bad = tmp_path / "bad.asc"
    bad.write_bytes(b"\x00\x01 not an asc file")
    with pytest.raises(RunError, match=r"bad\.asc"):
        read_can_runs(bad)


def test_fleet_evaluate_on_can_logs_finds_the_faulty_housing(logs):
    d, model, _, _ = logs
    machines = find_machines([str(d / "m1"), str(d / "m2")])
    rms = {m.id: {r["name"]: r["rms_k"] for r in evaluate_machine(m, None, str(MODEL))} for m in machines}
    assert set(rms["m1"]) == set(model.sensors)
    assert max(rms["m1"].values()) < 0.3  # the model is this machine: noise and steps only
    # the housing-to-ambient path is off: the housing sensor errs most, and well above the noise
    assert rms["m2"]["housing"] == max(rms["m2"].values()) and rms["m2"]["housing"] > 3 * rms["m1"]["housing"], rms


def test_a_broken_config_for_the_can_logs_is_refused_before_any_task(logs, tmp_path):
    from cli_in_process import te_here

    d = logs[0]
    broken = tmp_path / "edge.yaml"
    broken.write_text("signals: [not, a, mapping]\n")
    r = te_here("fleet", "evaluate", "--model", MODEL, str(d / "m1"), "--config", broken, "--out", tmp_path / "x.parquet",
                "--workers", "1", "--no-progress")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "edge.yaml" in r.stderr, r.stderr
    assert not (tmp_path / "x.parquet").exists()
