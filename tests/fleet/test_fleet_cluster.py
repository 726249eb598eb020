"""The fleet commands on a real Dask cluster: ``dask scheduler`` and ``dask worker`` started as their
own processes on 127.0.0.1, plus the embedded LocalCluster; results checked against the project's
calibration and replay called directly on the same runs."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from own_ports import own_tcp_port

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from thermal_edge.cli import main
from thermal_edge.data import read_run
from thermal_edge.estimation.calibrate import calibrate
from thermal_edge.estimation.predict import open_loop
from thermal_edge.fleet.results import read_table
from thermal_edge.lptn import load_model
from thermal_edge.sim.fleet import read_manifest

ROOT = Path(__file__).resolve().parents[2]
MODEL = str(ROOT / "config" / "machines" / "pm10kw.yaml")
CYCLE = str(ROOT / "config" / "cycles" / "varied_drive.yaml")
DASK = str(Path(sys.executable).parent / "dask")
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
# small and cheap: 8 machines of 1 h, 3 parameters, 60 s optimiser steps
PARAMS = "R_e_hous,r_ins_sw,c_p_hous"
FIT = ["--params", PARAMS, "--decimate", "60", "--no-progress"]


def _free_port() -> int:
    """A TCP port held by this test process (dask's scheduler binds with SO_REUSEADDR): no other
    process, a second suite beside this one included, takes it meanwhile."""
    return own_tcp_port()


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fleet")
    assert main(["simulate", "--model", MODEL, "--cycle", CYCLE, "--fleet", "8", "--faulty", "2", "--duration", "3600",
                 "--seed", "3", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """A ``dask scheduler`` and a ``dask worker`` (2 processes) on 127.0.0.1, as separate processes."""
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    logs = tmp_path_factory.mktemp("dask")
    procs = [subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                              stdout=open(logs / "scheduler.log", "w"), stderr=subprocess.STDOUT, env=ENV)]
    deadline = time.monotonic() + 300  # a hang guard: a busy host starts it late
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            time.sleep(0.2)
    procs.append(subprocess.Popen([DASK, "worker", addr, "--host", "127.0.0.1", "--nworkers", "2", "--nthreads", "1",
                                   "--no-dashboard"], stdout=open(logs / "worker.log", "w"), stderr=subprocess.STDOUT,
                                  env=ENV))
    yield addr
    for p in reversed(procs):
        p.terminate()
    for p in reversed(procs):
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()


@pytest.fixture(scope="module")
def calibrated(fleet, scheduler, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cal") / "cal.parquet"
    assert main(["fleet", "calibrate", "--model", MODEL, str(fleet / "*.csv"), "--out", str(out),
                 "--scheduler", scheduler, "--workers", "2", *FIT]) == 0
    return out


def test_calibrate_on_a_separate_scheduler_and_worker_matches_the_direct_calibration(fleet, calibrated):
    rows = read_table(calibrated)
    assert {r["kind"] for r in rows} == {"parameter"}
    assert sorted({r["machine"] for r in rows}) == [f"m{i}" for i in range(8)]
    assert all(len([r for r in rows if r["machine"] == m]) == 3 for m in {r["machine"] for r in rows})
    # the same machine calibrated here, without Dask: the same numbers
    model = load_model(MODEL)
    res = calibrate(model, [read_run(fleet / "m2.csv")], PARAMS.split(","), None, 60, 1, 1, 0)
    got = {r["name"]: r for r in rows if r["machine"] == "m2"}
    for i, n in enumerate(res.names):
        assert got[n]["value"] == pytest.approx(res.values[i], rel=1e-9)
        assert got[n]["rel_std"] == pytest.approx(res.uncertainty.rel_std[i], rel=1e-6)
    assert got["R_e_hous"]["samples"] == 3601 and got["R_e_hous"]["worker_peak_mb"] > 10
    assert (calibrated.with_suffix(".md")).read_text().startswith("# Fleet calibration")


def test_evaluate_with_each_machines_calibration_on_the_cluster(fleet, calibrated, scheduler, tmp_path):
    out = tmp_path / "eval.parquet"
    assert main(["fleet", "evaluate", "--model", MODEL, str(fleet / "*.csv"), "--calibrated", str(calibrated),
                 "--out", str(out), "--scheduler", scheduler, "--no-progress"]) == 0
    rows = read_table(out)
    assert {r["name"] for r in rows} == {"slot_winding", "end_winding", "housing"}
    # independent: the machine's open-loop prediction with its calibrated parameters, errors by hand
    model = load_model(MODEL)
    fitted = {r["name"]: r["value"] for r in read_table(calibrated) if r["machine"] == "m5"}
    theta = model.nominal().copy()
    theta[model.parameter_index(list(fitted))] = list(fitted.values())
    run = read_run(fleet / "m5.csv")
    traj, _ = open_loop(model, run, theta=theta)
    for r in (r for r in rows if r["machine"] == "m5"):
        e = traj.node(model.sensors[r["name"]]) - run.columns[r["name"]]
        assert r["rms_k"] == pytest.approx(np.sqrt(np.mean(e**2)), rel=1e-9)
        assert r["max_abs_k"] == pytest.approx(np.max(np.abs(e)), rel=1e-9)
    # with the design's parameters the faulty machines fit worse than with their own
    nominal = tmp_path / "nominal.parquet"
    assert main(["fleet", "evaluate", "--model", MODEL, str(fleet / "*.csv"), "--out", str(nominal),
                 "--workers", "1", "--no-progress"]) == 0
    bad = [m["id"] for m in read_manifest(fleet)["machines"] if m["fault"]]
    for m in bad:
        own = max(r["rms_k"] for r in rows if r["machine"] == m)
        design = max(r["rms_k"] for r in read_table(nominal) if r["machine"] == m)
        assert design > 2 * own


def test_screen_names_the_faulty_machines_with_their_parameter(fleet, calibrated, tmp_path, capsys):
    out = tmp_path / "screen.parquet"
    assert main(["fleet", "screen", "--table", str(calibrated), "--out", str(out)]) == 0
    rows = read_table(out)
    flagged = {(r["machine"], r["name"]) for r in rows if r["outlier"]}
    truth = {(m["id"], m["fault"]["parameter"]) for m in read_manifest(fleet)["machines"] if m["fault"]}
    assert truth <= flagged
    report = out.with_suffix(".md").read_text()
    for machine, param in truth:
        assert f"| {machine} | {param} |" in report
        assert (tmp_path / "screen-plots" / f"outlier-{machine}.png").stat().st_size > 1000
    assert (tmp_path / "screen-plots" / "param-R_e_hous.png").exists()
    assert "machine  parameter" in capsys.readouterr().out


def test_a_broken_run_is_an_error_row_not_a_failed_fleet(fleet, scheduler, tmp_path):
    broken = tmp_path / "runs"
    broken.mkdir()
    (broken / "good.csv").write_bytes((fleet / "m0.csv").read_bytes())
    (broken / "bad.csv").write_text("t,speed_rpm\n0,abc\n")
    out = tmp_path / "eval.parquet"
    assert main(["fleet", "evaluate", "--model", MODEL, str(broken / "*.csv"), "--out", str(out),
                 "--scheduler", scheduler, "--no-progress"]) == 0
    rows = read_table(out)
    err = [r for r in rows if r["kind"] == "error"]
    assert [(r["machine"], r["name"]) for r in err] == [("bad", "RunError")] and "not a number" in err[0]["message"]
    assert {r["machine"] for r in rows if r["kind"] == "sensor"} == {"good"}
    assert "| bad | RunError |" in out.with_suffix(".md").read_text()


def test_without_dask_the_command_says_how_to_install_it(tmp_path):
    code = ("import sys; sys.modules['distributed'] = None\n"  # as if the extra were not installed
            "from thermal_edge.cli import main\n"
            f"sys.exit(main(['fleet', 'calibrate', '--model', {MODEL!r}, 'x.csv', '--out', 'x.parquet']))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        "thermal-edge fleet calibrate: error: distributed not installed: pip install thermal-edge[fleet]"]


def test_an_unreachable_scheduler_is_one_line(fleet, tmp_path, capsys):
    assert main(["fleet", "evaluate", "--model", MODEL, str(fleet / "m0.csv"), "--out", str(tmp_path / "x.parquet"),
                 "--scheduler", f"tcp://127.0.0.1:{_free_port()}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("thermal-edge fleet evaluate: error: cannot reach the Dask scheduler at tcp://127.0.0.1:")
