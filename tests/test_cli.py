"""The ``thermal-edge`` command as a user runs it: subprocesses, exit codes, one-line errors."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from thermal_edge.data import read_run

ROOT = Path(__file__).resolve().parents[1]
PADERBORN = ROOT.parent / "shared" / "data" / "paderborn"
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


def cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "thermal_edge.cli", *args], capture_output=True, text=True,
                          cwd=ROOT, env=ENV, timeout=timeout)


def test_help_lists_the_commands():
    out = cli("--help")
    assert out.returncode == 0
    for cmd in ("simulate", "replay", "calibrate", "bench", "demo"):
        assert cmd in out.stdout


@pytest.mark.parametrize("args, needle", [
    (["replay", "--model", "nope.yaml", "--run", "x.csv"], "nope.yaml: cannot read"),
    (["simulate", "--model", "config/machines/pm10kw.yaml", "--cycle", "nope.yaml", "--out", "/tmp/x.csv"], "nope.yaml"),
    (["simulate", "--model", "config/machines/pm10kw.yaml", "--cycle", "config/cycles/overload.yaml",
      "--out", "/tmp/x.csv", "--param", "R_e_hous"], "NAME=VALUE"),
])
def test_bad_input_is_one_line_and_exit_2(args, needle):
    out = cli(*args)
    assert out.returncode == 2
    assert needle in out.stderr and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


def test_broken_model_names_file_and_key(tmp_path):
    bad = tmp_path / "broken.yaml"
    text = (ROOT / "config" / "machines" / "pm10kw.yaml").read_text().replace("value: 9.1", "value: -9.1", 1)
    bad.write_text(text)
    out = cli("replay", "--model", str(bad), "--run", "x.csv")
    assert out.returncode == 2 and out.stderr.startswith("thermal-edge replay: error: broken.yaml: parameters.R_e_hous")


def test_simulate_then_replay_round_trip(tmp_path):
    run = tmp_path / "run.csv"
    out = cli("simulate", "--model", "config/machines/pm10kw.yaml", "--cycle", "config/cycles/rated_heat_cool.yaml",
              "--duration", "1800", "--noise", "0", "--resolution", "0", "--out", str(run))
    assert out.returncode == 0, out.stderr
    rec = read_run(run)
    assert len(rec) == 1801 and rec.dt == pytest.approx(1.0)
    assert {"speed_rpm", "i_rms", "ambient_c", "slot_winding", "end_winding", "housing"} <= set(rec.columns)
    assert np.all(np.diff(rec.columns["slot_winding"][:600]) > -1e-3)  # heating up at rated load
    out = cli("replay", "--model", "config/machines/pm10kw.yaml", "--run", str(run), "--no-adapt", "--json")
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert set(res) >= {"mse", "mean_mse", "max_abs"}
    # the model replays its own noise-free simulation; CSV rounding to 6 digits is all that differs
    assert res["mean_mse"] < 1e-4


@pytest.mark.skipif(not (PADERBORN / "run_a.csv").exists(), reason=f"Paderborn data not found in {PADERBORN}")
def test_paderborn_replay_reproduces_the_reference():
    out = cli("replay", "--model", "config/machines/paderborn4.yaml", "--run", str(PADERBORN / "run_a.csv"),
              "--format", "paderborn", "--no-adapt", "--json")
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert 1.6 <= res["mean_mse"] <= 2.0
    assert set(res["mse"]) == {"pm", "stator_yoke", "stator_tooth", "stator_winding"}
    assert max(res["max_abs"].values()) == pytest.approx(3.8, abs=0.3)


@pytest.mark.skipif(not (PADERBORN / "run_a.csv").exists(), reason=f"Paderborn data not found in {PADERBORN}")
def test_paderborn_replay_with_adaptation_scores_unseen_sensors():
    out = cli("replay", "--model", "config/machines/paderborn4.yaml", "--run", str(PADERBORN / "run_a.csv"),
              "--format", "paderborn", "--adapt", "--sensors", "stator_winding,stator_yoke", "--decimate", "8", "--json")
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert set(res["mse"]) == {"pm", "stator_yoke", "stator_tooth", "stator_winding"}
    assert res["adapted_from"] == ["stator_winding", "stator_yoke"]
    assert res["decisions"] and all("accepted" in d for d in res["decisions"])
