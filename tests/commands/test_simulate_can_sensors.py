"""``simulate --format can`` of another machine's model: its sensors go into the simulated
inverter's PT100 signals as the service configuration maps them (``--config``), checked by
decoding the log with python-can and cantools; without it, a note names the sensors the log
cannot carry."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import can
import cantools
from cmd_testlib import four_node_machine

from thermal_edge.bus.frames import DEFAULT_DBC_PATH


def _statuses(log: Path) -> set[tuple[str, str]]:
    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))
    seen = set()
    for msg in can.LogReader(str(log)):
        if msg.arbitration_id == db.get_message_by_name("INV_StatorTemps").frame_id:
            sig = db.decode_message(msg.arbitration_id, msg.data)
            seen.add((str(sig["INV_S_WindingSlot"]), str(sig["INV_S_Housing"])))
    return seen


def _simulate(model: Path, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "thermal_edge.cli", "simulate", "--model", str(model), "--cycle",
                           "overload", "--duration", "30", "--format", "can", "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=300)


def test_the_configuration_maps_the_models_sensors_into_the_log(tmp_path):
    model, edge = four_node_machine(tmp_path)
    r = _simulate(model, tmp_path / "mapped.log", "--config", str(edge))
    assert r.returncode == 0, r.stderr
    assert "no reading of" not in r.stdout
    assert _statuses(tmp_path / "mapped.log") == {("valid", "valid")}
    r = _simulate(model, tmp_path / "default.log")
    assert r.returncode == 0, r.stderr
    assert "note: the log carries no reading of winding_t" in r.stdout and "--config EDGE_YAML" in r.stdout
    assert _statuses(tmp_path / "default.log") == {("not_fitted", "valid")}
