"""The package as a stranger installs it: the wheel of the repository (``pip wheel --no-deps`` of
what the Docker build sees), installed with its dependencies into a fresh venv in a temporary
directory, every command run from a working directory outside the checkout with the checkout off
``sys.path`` -- so a command that reads the source tree instead of its package data fails here.

The results are judged on their content: the columns and rows of the simulated run, the replay's
scores, the calibrated file, the effect discovery names, the metrics the demo serves, the
Jacobian's size and accuracy, the example configuration byte for byte.
"""
from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import deploylib as dl
import pytest
import yaml

RESOURCES = dl.REPO / "thermal_edge" / "resources"
SENSORS = ("slot_winding", "end_winding", "housing")
#: metrics the demo must serve (service, bus, model, derating, look-ahead, adaptation: one of each part)
DEMO_METRICS = ("thermal_edge_build_info", "thermal_edge_ticks_total", "thermal_edge_frames_received_total",
                "thermal_edge_node_estimate_celsius", "thermal_edge_current_limit_amperes",
                "thermal_edge_lookahead_current_amperes", "thermal_edge_adaptation_runs_total")


@dataclass
class Installed:
    """The fresh venv with the wheel in it, and a scratch working directory outside the checkout."""

    venv: Path
    work: Path
    wheel: Path

    @property
    def exe(self) -> Path:
        return self.venv / "bin" / "thermal-edge"

    def env(self) -> dict[str, str]:
        e = dl.env()
        for k in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "THERMAL_EDGE_DATA_DIR", "PYTHONSTARTUP"):
            e.pop(k, None)
        e["PATH"] = f"{self.venv / 'bin'}{os.pathsep}{e.get('PATH', '')}"
        return e

    def run(self, *args: str, timeout: float = 300, check: bool = True) -> subprocess.CompletedProcess[str]:
        r = subprocess.run([str(self.exe), *args], cwd=self.work, env=self.env(), capture_output=True, text=True,
                           timeout=timeout)
        assert r.returncode == 0 or not check, \
            f"thermal-edge {' '.join(args)}: exit {r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
        return r


def _outside_checkout(path: Path) -> bool:
    return not path.resolve().is_relative_to(dl.REPO.resolve())


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Installed]:
    root = tmp_path_factory.mktemp("wheel")
    assert _outside_checkout(root), root
    ctx = dl.build_context(root / "ctx")  # as the Dockerfile's build stage: no build/ or egg-info in the checkout
    wheels = root / "wheels"
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(wheels), str(ctx)],
                       capture_output=True, text=True, timeout=600, env=dl.env())
    assert r.returncode == 0, r.stdout + r.stderr
    (wheel,) = wheels.glob("thermal_edge-*.whl")
    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    r = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet", str(wheel)],
                       capture_output=True, text=True, timeout=900, env=dl.env())
    assert r.returncode == 0, r.stdout + r.stderr
    work = root / "work"
    work.mkdir()
    yield Installed(venv, work, wheel)


def test_the_package_is_the_installed_one(installed: Installed) -> None:
    r = subprocess.run([str(installed.venv / "bin" / "python"), "-c",
                        "import thermal_edge, thermal_edge.shipped as s; print(thermal_edge.__file__); "
                        "print(s.config_path('edge.yaml'))"],
                       cwd=installed.work, env=installed.env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    for line in r.stdout.split():
        assert Path(line).resolve().is_relative_to(installed.venv.resolve()), line


def test_the_wheel_declares_its_licence(installed: Installed) -> None:
    """The licence as an SPDX expression (core metadata 2.4, PEP 639) with the LICENSE file shipped
    byte for byte, and not the deprecated free-text ``License:`` field."""
    import zipfile

    with zipfile.ZipFile(installed.wheel) as whl:
        info = next(n.split("/")[0] for n in whl.namelist() if n.endswith(".dist-info/METADATA"))
        meta = whl.read(f"{info}/METADATA").decode()
        shipped = whl.read(f"{info}/licenses/LICENSE")
    headers = meta.split("\n\n", 1)[0].splitlines()
    assert "License-Expression: Apache-2.0" in headers
    assert "License-File: LICENSE" in headers
    assert not any(h.startswith("License:") for h in headers), headers
    assert shipped == (dl.REPO / "LICENSE").read_bytes()


def test_config_example_then_run_check(installed: Installed) -> None:
    text = installed.run("config", "example").stdout
    assert text == (RESOURCES / "edge.yaml").read_text(encoding="utf-8")
    edge = installed.work / "edge.yaml"
    edge.write_text(text, encoding="utf-8")
    r = installed.run("run", "--check", "--config", str(edge))
    assert "ok" in r.stdout and "model pm10kw" in r.stdout and "39 nodes" in r.stdout, r.stdout


def test_config_dbc_and_the_inverter_example_from_the_wheel(installed: Installed) -> None:
    """Outside a checkout: the DBC the package ships decodes with cantools, and the MC-7 example
    written into a directory passes its own check there."""
    import cantools

    dbc = installed.work / "thermal_edge.dbc"
    dbc.write_text(installed.run("config", "dbc").stdout, encoding="utf-8")
    db = cantools.database.load_file(str(dbc))
    assert {"TE_Limits", "INV_Currents", "INV_StatorTemps"} <= {m.name for m in db.messages}
    out = installed.work / "mc7"
    installed.run("config", "inverter-example", str(out))
    r = installed.run("run", "--check", "--config", str(out / "edge.yaml"))
    assert "edge.yaml: ok (model pm10kw" in r.stdout and "MC7_Currents" in r.stdout, r.stdout


def test_the_machine_model_and_the_unit_from_the_wheel(installed: Installed) -> None:
    """Outside a checkout: the packaged model printed and written beside a configuration that names
    it by path passes the check (what the README's install steps do), and the unit printed is the
    repository's ``deploy/systemd/thermal-edge.service`` byte for byte, its ExecStart the
    install's command."""
    etc = installed.work / "etc"
    (etc / "machines").mkdir(parents=True)
    (etc / "machines" / "pm10kw.yaml").write_text(installed.run("config", "model", "pm10kw").stdout, encoding="utf-8")
    (etc / "edge.yaml").write_text(installed.run("config", "example", "--model", "machines/pm10kw.yaml").stdout,
                                   encoding="utf-8")
    r = installed.run("run", "--check", "--config", str(etc / "edge.yaml"))
    assert "edge.yaml: ok (model pm10kw, 39 nodes" in r.stdout, r.stdout
    unit = installed.run("config", "unit").stdout
    assert unit == (dl.REPO / "deploy" / "systemd" / "thermal-edge.service").read_text(encoding="utf-8")
    assert "ExecStart=/opt/thermal-edge/bin/thermal-edge run --config /etc/thermal-edge/edge.yaml" in unit.splitlines()


def test_the_deployment_files_from_the_wheel(installed: Installed) -> None:
    """``config deploy DIR`` from the installed wheel writes the repository's ``deploy/systemd``,
    ``deploy/prometheus`` and ``deploy/grafana`` files byte for byte (every one of them: the two
    trees are listed and compared), and refuses to overwrite them."""
    out = installed.work / "deploy"
    installed.run("config", "deploy", str(out))
    written = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    repo = sorted(p.relative_to(dl.REPO / "deploy") for d in ("systemd", "prometheus", "grafana")
                  for p in (dl.REPO / "deploy" / d).rglob("*") if p.is_file())
    assert written == repo and len(written) >= 9
    for rel in written:
        assert (out / rel).read_bytes() == (dl.REPO / "deploy" / rel).read_bytes(), rel
    again = installed.run("config", "deploy", str(out), check=False)
    assert again.returncode == 2 and "already there (not overwritten)" in again.stderr


def _csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    return list(rows[0]), rows


def test_simulate_replay_calibrate(installed: Installed) -> None:
    run = installed.work / "run.csv"
    installed.run("simulate", "--model", "pm10kw", "--cycle", "varied_drive", "--duration", "1800", "--out", str(run))
    cols, rows = _csv(run)
    assert len(rows) == 1801
    assert {"t", "speed_rpm", "i_rms", "torque_nm", "ambient_c", *SENSORS} <= set(cols)
    assert [float(r["t"]) for r in rows[:3]] == [0.0, 1.0, 2.0]
    assert max(float(r["slot_winding"]) for r in rows) > 40.0  # the machine heats up under the cycle

    rep = json.loads(installed.run("replay", "--model", "pm10kw", "--run", str(run), "--json").stdout)
    assert rep["samples"] == 1801 and set(rep["mse"]) == set(SENSORS)
    assert all(0.0 < v < 0.1 for v in rep["mse"].values()), rep["mse"]  # its own plant: the PT100 noise (σ 0.1 K)

    cal = installed.work / "cal.yaml"
    r = installed.run("calibrate", "--model", "pm10kw", "--run", str(run), "--params", "R_e_hous", "--generations", "3",
                      "--out", str(cal))
    assert f"wrote {cal}" in r.stdout
    doc = yaml.safe_load(cal.read_text())
    value = doc["parameters"]["R_e_hous"]["value"]
    assert math.isclose(value, 9.1, rel_tol=0.1), value  # the plant's own value, within the run's reach


def test_replay_of_a_can_log_with_the_packaged_configuration(installed: Installed) -> None:
    log = installed.work / "sim.log"
    installed.run("simulate", "--model", "pm10kw", "--cycle", "overload", "--duration", "120", "--format", "can",
                  "--out", str(log))
    with log.open() as fh:
        frames = sum(1 for line in fh if line.startswith("("))
    rep = json.loads(installed.run("replay", "--format", "can", "--run", str(log), "--json").stdout)
    assert rep["model"] == "pm10kw" and rep["frames"] == frames > 0
    assert rep["frames_lost"] == 0 and 110 <= rep["ticks"] <= 120


def test_discover_names_the_planted_effect(installed: Installed) -> None:
    run = installed.work / "fan.csv"
    installed.run("simulate", "--model", "pm10kw", "--cycle", "varied_drive", "--duration", "3600",
                  "--effect", "speed_convection:R_e_hous", "--seed", "1", "--out", str(run))
    r = installed.run("discover", "--model", "pm10kw", "--run", str(run), "--effects", "speed_convection,copper_temperature",
                      "--max-rounds", "1", "--json", "--quiet", timeout=600)
    d = json.loads(r.stdout)
    assert (d["named_effect"], d["target"]) == ("speed_convection", "R_e_hous"), d["verdict"]


def test_bench_jacobian(installed: Installed) -> None:
    d = json.loads(installed.run("bench", "jacobian", "--repeat", "1", "--hours", "0.25", "--json").stdout)
    assert (d["nodes"], d["params"], d["sensors"], d["samples"]) == (39, 14, 3, 901)
    assert d["max_rel_err"] < 1e-3 and d["closed_vs_stepped_max_rel"] < 1e-9


@pytest.mark.timeout(300)
def test_demo_serves_metrics(installed: Installed) -> None:
    port = dl.free_tcp_port()
    url = f"http://127.0.0.1:{port}/metrics"
    log = installed.work / "demo.log"
    with log.open("w") as out:
        proc = subprocess.Popen([str(installed.exe), "demo", "--metrics-port", str(port), "--speed", "30", "--quiet",
                                 "--state-dir", str(installed.work / "state")],
                                cwd=installed.work, env=installed.env(), stdout=out, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 180
        text, ticks = "", 0.0
        while time.monotonic() < deadline and ticks < 10:
            assert proc.poll() is None, log.read_text()
            try:
                text = dl.scrape(url)
                ticks = dl.sample_value(text, "thermal_edge_ticks_total") or 0.0
            except OSError:
                pass
            time.sleep(0.5)
        assert ticks >= 10, f"no ticks within the time-out\n{log.read_text()[-2000:]}"
        missing = [m for m in DEMO_METRICS if m not in dl.exposed_names(text)]
        assert not missing, missing
        assert (dl.sample_value(text, "thermal_edge_frames_received_total") or 0) > 0
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == 0, log.read_text()[-2000:]
