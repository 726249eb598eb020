"""``thermal-edge demo`` cleans up after itself: its own temporary state directory is gone when it
ends; a ``--state-dir`` given by the user is kept, with the state saved on stop."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from cmd_testlib import four_node_machine
from own_ports import own_tcp_port


def _free_port() -> int:
    """A TCP port held by this test process (the metrics endpoint binds with SO_REUSEADDR): no other
    process, a second suite beside this one included, takes it meanwhile."""
    return own_tcp_port()


def _demo(tmp: Path, *extra: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "TMPDIR": str(tmp), "OPENBLAS_NUM_THREADS": "1"}  # mkdtemp's directory: this test's
    if cwd is not None:  # the package from this checkout, wherever the command runs
        env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[2]), env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-m", "thermal_edge.cli", "demo", "--duration", "120", "--speed", "300",
                           "--quiet", "--metrics-port", str(_free_port()), *extra],
                          capture_output=True, text=True, timeout=180, env=env, cwd=cwd)


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


@pytest.mark.parametrize("relative", [False, True])
def test_a_state_directory_given_by_the_user_is_kept(tmp_path, relative):
    """Kept, with the state saved on stop; a relative one is relative to where the command runs
    (not to the packaged example configuration's directory, inside the installed package)."""
    mine = tmp_path / "mine"
    r = _demo(tmp_path, "--state-dir", "mine" if relative else str(mine), cwd=tmp_path if relative else None)
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




def test_the_demo_runs_a_configuration_for_another_machine(tmp_path):
    """A user's own 4-node model (sensors ``winding_t`` and ``housing`` on the inverter's slot-winding
    and housing PT100s), its configuration from ``config example --model`` with its own signals and
    drive: the demo runs it (the Table 4 start names pm10kw's parameters: it says so and starts at the
    plant's values), the simulated inverter sends the PT100s the configuration maps, and no tick is
    a sensor fault."""
    _, edge = four_node_machine(tmp_path)
    r = _demo(tmp_path, "--config", str(edge), "--state-dir", str(tmp_path / "st"))
    assert r.returncode == 0, r.stderr[-2000:]
    assert ("model four_node has not the parameters the Table 4 start moves (k_r_sw, k_c_sw, c_p_sw, R_e_hous): "
            "the service starts at the plant's values") in r.stdout, r.stdout
    assert "model at the plant" in r.stdout and re.search(r"^done: .* simulated", r.stdout, re.M), r.stdout[-2000:]
    assert "sensor_fault" not in r.stdout + r.stderr and "not_fitted" not in r.stdout + r.stderr, r.stdout[-2000:]
    assert "no reading of" not in r.stdout



#: runs ``thermal-edge demo`` for the simulated seconds given, one after the other in this process,
#: and prints what its emulator kept per simulated second: trace rows, estimates and limits received
_KEPT_PER_RUN = """
import json, sys
from thermal_edge.cli import main
from thermal_edge.sim.inverter import InverterEmulator
emulators, run = [], InverterEmulator.run
def recording_run(self, *a, **kw):
    emulators.append(self)
    return run(self, *a, **kw)
InverterEmulator.run = recording_run
kept = []
for seconds in sys.argv[1:]:
    assert main(["demo", "--duration", seconds, "--speed", "1000", "--quiet", "--no-table4", "--metrics-port", "0"]) == 0
    e = emulators[-1]
    kept.append([e.elapsed, len(e.trace_t) + len(e.trace_T) + len(e.trace_i), len(e.estimates), len(e.limit_log)])
print(json.dumps(kept))
"""


def test_the_demos_simulated_machine_keeps_nothing_per_second(tmp_path):
    """A demo on a show floor runs for days: its simulated inverter keeps no trace of the plant and no
    log of what the service sends (what grew by 1 kB a simulated second), however long it runs."""
    env = {**os.environ, "TMPDIR": str(tmp_path), "OPENBLAS_NUM_THREADS": "1"}
    r = subprocess.run([sys.executable, "-c", _KEPT_PER_RUN, "60", "120"], capture_output=True, text=True, timeout=180,
                       env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    (t1, *kept1), (t2, *kept2) = json.loads(r.stdout.splitlines()[-1])
    assert t2 > t1 >= 59.0  # both ran, the second twice as long
    assert kept1 == kept2 == [0, 0, 0]
