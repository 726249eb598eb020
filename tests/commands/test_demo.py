"""``thermal-edge demo`` cleans up after itself: its own temporary state directory is gone when it
ends; a ``--state-dir`` given by the user is kept, with the state saved on stop."""
from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _demo(tmp: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "TMPDIR": str(tmp), "OPENBLAS_NUM_THREADS": "1"}  # mkdtemp's directory: this test's
    return subprocess.run([sys.executable, "-m", "thermal_edge.cli", "demo", "--duration", "120", "--speed", "300",
                           "--quiet", "--metrics-port", str(_free_port()), *extra],
                          capture_output=True, text=True, timeout=180, env=env)


def test_the_demo_removes_its_own_state_directory(tmp_path):
    r = _demo(tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    m = re.search(r"state: (\S+)", r.stdout)
    assert m, r.stdout
    used = Path(m.group(1))
    assert used.parent == tmp_path and used.name.startswith("thermal-edge-demo-")  # it did make one here
    assert re.search(r"^done: .* simulated", r.stdout, re.M), r.stdout[-2000:]
    assert not used.exists()
    assert list(tmp_path.iterdir()) == []


def test_a_state_directory_given_by_the_user_is_kept(tmp_path):
    mine = tmp_path / "mine"
    r = _demo(tmp_path, "--state-dir", str(mine))
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"state: {mine}" in r.stdout
    state = json.loads((mine / "state.json").read_text())
    assert state["format"] == "thermal_edge.state"


def test_demo_voltages_uses_the_configurations_calibration_and_says_which(tmp_path):
    """``demo --voltages`` commissions on a simulated bench run only when the configuration has no
    ``flux.calibration``; a user's own is used as it is, and the demo says which it runs."""
    import yaml

    r = _demo(tmp_path, "--voltages")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "voltages: commissioned on a simulated bench run of the plant" in r.stdout, r.stdout[-2000:]
    assert list(tmp_path.iterdir()) == []  # its commissioning file went with it

    from thermal_edge.bench.protection import flux_calibration
    from thermal_edge.lptn import load_model
    from thermal_edge.shipped import config_path, example_config

    mine = flux_calibration(load_model(config_path("machines", "pm10kw.yaml")), tmp_path / "mine.json")
    raw = yaml.safe_load(example_config())
    raw["flux"] = {**raw["flux"], "calibration": str(mine)}
    cfg = tmp_path / "edge.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    r = _demo(tmp_path, "--voltages", "--config", str(cfg))
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"voltages: the calibration of edge.yaml, {mine}" in r.stdout, r.stdout[-2000:]
    assert mine.exists()


def _frames_with_id(log: Path, frame_id: int) -> int:
    """Frames of this identifier in a candump -L log, counted from its text."""
    n = 0
    for line in log.read_text().splitlines():
        parts = line.split()
        if len(parts) >= 3 and "#" in parts[2] and int(parts[2].split("#")[0], 16) == frame_id:
            n += 1
    return n


def test_demo_without_voltages_sends_none_although_the_configuration_has_a_calibration(tmp_path):
    """As ``demo --help`` says, ``--voltages`` is what makes the inverter send INV_Voltages: a
    configuration with ``flux.calibration`` does not (with it, the same configuration does)."""
    import cantools
    import yaml

    from thermal_edge.bench.protection import flux_calibration
    from thermal_edge.bus.frames import DEFAULT_DBC_PATH
    from thermal_edge.lptn import load_model
    from thermal_edge.shipped import config_path, example_config

    mine = flux_calibration(load_model(config_path("machines", "pm10kw.yaml")), tmp_path / "mine.json")
    raw = yaml.safe_load(example_config())
    raw["flux"] = {**raw["flux"], "calibration": str(mine)}
    cfg = tmp_path / "edge.yaml"
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    voltages_id = cantools.database.load_file(str(DEFAULT_DBC_PATH)).get_message_by_name("INV_Voltages").frame_id
    counts = {}
    for extra in ((), ("--voltages",)):
        log = tmp_path / f"rec{len(extra)}.log"
        r = _demo(tmp_path, "--config", str(cfg), "--record", str(log), *extra)
        assert r.returncode == 0, r.stderr[-2000:]
        counts[extra] = _frames_with_id(log, voltages_id)
    assert counts[()] == 0 and counts[("--voltages",)] > 0, counts
