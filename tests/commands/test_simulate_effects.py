"""``simulate --effect`` says when the hidden effect cannot reach the gap it is meant to open: the
sensors' noiseless difference, computed here again with the model and the plant the run's header
names, is below 1 K."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _simulate(tmp: Path, effect: str) -> tuple[str, Path]:
    out = tmp / "run.csv"
    r = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "simulate", "--model", "config/machines/pm10kw.yaml",
                        "--cycle", "config/cycles/varied_drive.yaml", "--duration", "3600", "--effect", effect,
                        "--seed", "12", "--out", str(out)], capture_output=True, text=True, cwd=ROOT, timeout=300,
                       env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    return r.stdout, out


@pytest.mark.parametrize("effect,seen", [("contact_resistance:housing_1-end_cap_1", False),  # a flange with a parallel one
                                         ("copper_temperature", True)])
def test_simulate_says_when_no_sensor_sees_the_hidden_effect(tmp_path, effect, seen):
    from thermal_edge.data import read_run
    from thermal_edge.discovery import hidden
    from thermal_edge.lptn import load_model
    from thermal_edge.sim.cycles import cycle_run, load_cycle

    stdout, out = _simulate(tmp_path, effect)
    header = [ln for ln in out.read_text().splitlines() if ln.startswith("#")]
    note = [ln for ln in header if "no sensor of the model may see them" in ln]
    # the gap again, from the resolved effect the header records, with the sensors' own run
    resolved = re.search(r"hidden effects: (\S+?=\S+?)(?: \(|$)", "\n".join(header))
    assert resolved, header
    model = load_model(ROOT / "config/machines/pm10kw.yaml")
    raw = hidden.read_document(ROOT / "config/machines/pm10kw.yaml")
    build = hidden.builder(str(ROOT / "config/machines/pm10kw.yaml"), None)
    inputs = cycle_run(load_cycle(ROOT / "config/cycles/varied_drive.yaml"), model.drive["kt_nm_per_arms"], 3600.0)
    from thermal_edge.discovery import effects as E

    doc, _ = hidden.plant_document(raw, [resolved.group(1)], E.references(model, inputs.columns),
                                   build, inputs=inputs)
    gap = hidden.sensor_gap(model, build(doc), inputs)
    assert (gap >= hidden.MIN_GAP_K) == seen
    assert bool(note) == (not seen)
    assert ("no sensor of the model may see them" in stdout) == (not seen)
    if not seen:
        assert f"at most {gap:.2f} K RMS" in note[0]
    assert len(read_run(str(out), "csv")) == 3601
