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
    (["replay", "--model", "nope.yaml", "--run", "x.csv"], "--model nope.yaml: no such file, nor a packaged model"),
    (["simulate", "--model", "config/machines/pm10kw.yaml", "--cycle", "nope.yaml", "--out", "/tmp/x.csv"], "nope.yaml"),
    (["simulate", "--model", "pm11", "--cycle", "overload", "--out", "/tmp/x.csv"], "(packaged: paderborn4, pm10kw)"),
    (["simulate", "--model", "pm10kw", "--cycle", "overlaod", "--out", "/tmp/x.csv"], "--cycle overlaod: no such file"),
    (["demo", "--cycle", "sub/overload"], "packaged: commissioning, heldout_drive, overload,"),
    (["simulate", "--model", "config/machines/pm10kw.yaml", "--cycle", "config/cycles/overload.yaml",
      "--out", "/tmp/x.csv", "--param", "R_e_hous"], "NAME=VALUE"),
])
def test_bad_input_is_one_line_and_exit_2(args, needle):
    out = cli(*args)
    assert out.returncode == 2
    assert needle in out.stderr and "Traceback" not in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


def test_packaged_model_and_cycle_by_name_are_the_files(tmp_path):
    """``--model pm10kw --cycle rated_heat_cool`` from a directory without such files simulates
    exactly what the packaged files' paths do."""
    by_path, by_name = tmp_path / "path.csv", tmp_path / "name.csv"
    common = ("--duration", "600", "--noise", "0", "--resolution", "0")
    a = cli("simulate", "--model", str(ROOT / "config" / "machines" / "pm10kw.yaml"),
            "--cycle", str(ROOT / "config" / "cycles" / "rated_heat_cool.yaml"), *common, "--out", str(by_path))
    b = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "simulate", "--model", "pm10kw", "--cycle",
                        "rated_heat_cool.yaml", *common, "--out", str(by_name)], capture_output=True, text=True,
                       cwd=tmp_path, env=ENV, timeout=300)
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    def rows(p: Path) -> list[str]:  # the data (the header comment repeats the command line)
        return [line for line in p.read_text().splitlines() if not line.startswith("#")]

    assert rows(by_name) == rows(by_path) and len(read_run(by_name)) == 601


def test_bench_real_finds_the_data_by_option_or_variable_and_skips_visibly(tmp_path):
    """``bench real`` reads the Paderborn data from ``--data-dir``, else ``$THERMAL_EDGE_DATA_DIR``,
    else ``../shared/data/paderborn`` of the working directory, and says where it looked."""
    by_option = cli("bench", "real", "--data-dir", str(tmp_path / "a"))
    by_variable = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "bench", "real"], capture_output=True, text=True,
                                 cwd=tmp_path, env={**ENV, "THERMAL_EDGE_DATA_DIR": str(tmp_path / "b")}, timeout=300)
    env = {k: v for k, v in ENV.items() if k != "THERMAL_EDGE_DATA_DIR"}
    by_default = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "bench", "real"], capture_output=True, text=True,
                                cwd=tmp_path, env=env, timeout=300)
    for out, where in ((by_option, tmp_path / "a"), (by_variable, tmp_path / "b"),
                       (by_default, Path("..") / "shared" / "data" / "paderborn")):
        assert out.returncode == 0, out.stderr
        assert f"bench real skipped: {where / 'run_a.csv'} not found" in out.stdout


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
              "--data-dir", str(PADERBORN), "--format", "paderborn", "--no-adapt", "--json")
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert 1.6 <= res["mean_mse"] <= 2.0
    assert set(res["mse"]) == {"pm", "stator_yoke", "stator_tooth", "stator_winding"}
    assert max(res["max_abs"].values()) == pytest.approx(3.8, abs=0.3)


@pytest.mark.skipif(not (PADERBORN / "run_a.csv").exists(), reason=f"Paderborn data not found in {PADERBORN}")
def test_paderborn_replay_with_adaptation_scores_unseen_sensors():
    out = cli("replay", "--model", "config/machines/paderborn4.yaml", "--run", str(PADERBORN / "run_a.csv"),
              "--data-dir", str(PADERBORN), "--format", "paderborn", "--adapt", "--sensors", "stator_winding,stator_yoke",
              "--decimate", "8", "--json")
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert set(res["mse"]) == {"pm", "stator_yoke", "stator_tooth", "stator_winding"}
    assert res["adapted_from"] == ["stator_winding", "stator_yoke"]
    assert res["decisions"] and all("accepted" in d for d in res["decisions"])


# -- sub-commands load lazily --------------------------------------------------------------------
HEAVY = ("thermal_edge.discovery", "thermal_edge.bench", "scipy.optimize")


def loaded_modules(*args: str) -> list[str]:
    """Modules loaded by ``thermal-edge ARGS`` (run as the console script does), in a fresh interpreter."""
    code = ("import json, sys\n"
            "from thermal_edge.cli import main\n"
            f"sys.argv = ['thermal-edge', *{list(args)!r}]\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "print(json.dumps(sorted(sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=ENV, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("args", [["--help"], ["run", "--help"]])
def test_help_loads_no_other_command(args):
    mods = loaded_modules(*args)
    assert "argparse" in mods  # (the probe saw the interpreter's modules)
    heavy = [m for m in mods if m.startswith(HEAVY)]
    assert heavy == [], f"thermal-edge {' '.join(args)} loaded {heavy}"
    if args[0] == "run":  # only the chosen command's module
        from thermal_edge.commands import COMMANDS

        others = {f"thermal_edge.commands.{c.module}" for c in COMMANDS if c.name != "run"}
        assert not others & set(mods), sorted(others & set(mods))


def test_the_service_does_not_import_scipy_stats():
    """scipy.stats costs ~0.7 s of every service start; the adapter's t quantile comes from scipy.special."""
    code = "import json, sys\nimport thermal_edge.service\nprint(json.dumps(sorted(sys.modules)))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=ENV, timeout=120)
    assert out.returncode == 0, out.stderr
    mods = json.loads(out.stdout.strip().splitlines()[-1])
    assert "thermal_edge.estimation.adapter" in mods  # the probe saw the adapter loaded
    assert "scipy.stats" not in mods


def test_every_command_listed_and_loaded_when_chosen():
    from thermal_edge.commands import COMMANDS

    out = cli("--help")
    for c in COMMANDS:
        assert f"    {c.name} " in out.stdout or f"    {c.name}\n" in out.stdout, c.name
        sub = cli(c.name, "--help")
        assert sub.returncode == 0 and sub.stdout.startswith(f"usage: thermal-edge {c.name} "), sub.stderr
        assert "--help" in sub.stdout  # its own arguments, not the listing's placeholder


# -- run --check knows python-can ----------------------------------------------------------------
def edge_yaml(tmp_path: Path, bus: dict) -> Path:
    """The shipped config/edge.yaml with ``bus`` and absolute paths (written to ``tmp_path``)."""
    import yaml

    raw = yaml.safe_load((ROOT / "config" / "edge.yaml").read_text())
    raw["model"]["path"] = str(ROOT / "config" / "machines" / "pm10kw.yaml")
    raw["state"]["dir"] = str(tmp_path / "state")
    raw["bus"] = bus
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


@pytest.mark.parametrize("bus, line", [
    ({"interface": "socketcan", "chanel": "can0"},
     "edge.yaml: bus.chanel: unknown key 'chanel' under bus: (did you mean 'channel'?)"),
    ({"interface": "socketcann", "channel": "can0"},
     "edge.yaml: bus.interface: unknown python-can interface 'socketcann' (did you mean 'socketcan'?)"),
])
def test_run_check_names_bus_typos(tmp_path, bus, line):
    import can

    out = cli("run", "--check", "--config", str(edge_yaml(tmp_path, bus)))
    assert out.returncode == 2
    lines = out.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    assert lines[0].startswith(f"thermal-edge run: error: {line}"), lines[0]
    if "interface" in line:  # the interfaces python-can itself offers are named
        assert all(name in lines[0] for name in can.interfaces.VALID_INTERFACES)
    assert not (tmp_path / "state").exists()


def test_run_check_names_a_misspelt_required_key(tmp_path):
    path = edge_yaml(tmp_path, {"interface": "virtual"})
    path.write_text(path.read_text().replace("max_current_a:", "max_curent_a:"))
    out = cli("run", "--check", "--config", str(path))
    assert out.returncode == 2
    assert out.stderr.strip() == ("thermal-edge run: error: edge.yaml: derating.max_curent_a: unknown key "
                                  "(did you mean 'max_current_a'?)"), out.stderr


def test_run_check_says_when_the_state_dir_cannot_be_written_and_still_passes(tmp_path):
    """A state directory the file system refuses to write (``/proc/self``: nothing can be created
    there) is the host's state, not a configuration error: the service protects without saving, so
    ``--check`` passes (exit 0) and says so on stderr, naming the key; a writable one says nothing."""
    import yaml

    path = edge_yaml(tmp_path, {"interface": "virtual"})
    raw = yaml.safe_load(path.read_text())
    raw["state"]["dir"] = "/proc/self"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    out = cli("run", "--check", "--config", str(path))
    assert out.returncode == 0, out.stderr
    warned = [ln for ln in out.stderr.splitlines() if "state.dir" in ln]
    assert len(warned) == 1, out.stderr
    assert warned[0].startswith("edge.yaml: state.dir: warning: /proc/self cannot be written now ("), out.stderr
    ok = cli("run", "--check", "--config", str(edge_yaml(tmp_path, {"interface": "virtual"})))
    assert ok.returncode == 0 and "state.dir" not in ok.stderr, ok.stderr


@pytest.mark.parametrize("value", ["verbose", "trace"])
def test_run_refuses_a_log_level_from_the_environment_in_one_line(tmp_path, value):
    """argparse checks ``--log-level``'s choices but not a default from ``THERMAL_EDGE_LOG_LEVEL``
    (the shipped unit sets it): an unknown one is a user error naming the variable, not a traceback."""
    path = edge_yaml(tmp_path, {"interface": "virtual"})
    out = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "run", "--check", "--config", str(path)],
                         capture_output=True, text=True, cwd=ROOT, env={**ENV, "THERMAL_EDGE_LOG_LEVEL": value}, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr.strip() == (f"thermal-edge run: error: THERMAL_EDGE_LOG_LEVEL: {value!r} is not a log level "
                                  "(one of debug, info, notice, warning, error)")
    ok = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "run", "--check", "--config", str(path)],
                        capture_output=True, text=True, cwd=ROOT, env={**ENV, "THERMAL_EDGE_LOG_LEVEL": "WARNING"},
                        timeout=300)
    assert ok.returncode == 0, ok.stderr


@pytest.mark.parametrize("command", ["run --check", "config example", "config dbc"])
def test_output_into_a_closed_pipe_is_no_error(tmp_path, command):
    """``thermal-edge run --check | head -1`` and the like: the reader has gone before the command
    writes (here: the pipe's read end closed first, so the first write fails for certain). That is
    no error of the input: no ``error:`` line, no traceback, exit 0."""
    args = command.split() + (["--config", str(edge_yaml(tmp_path, {"interface": "virtual"}))] if "run" in command else [])
    r, w = os.pipe()
    os.close(r)
    try:
        out = subprocess.run([sys.executable, "-m", "thermal_edge.cli", *args], stdout=w, stderr=subprocess.PIPE,
                             text=True, cwd=ROOT, env=ENV, timeout=300)
    finally:
        os.close(w)
    assert out.returncode == 0 and out.stderr == "", out.stderr


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_shows_the_traceback_wherever_it_is_given(tmp_path, where):
    """``--debug`` before the command or after its options: a user error shows its traceback
    (the error class named), not "unrecognized arguments"."""
    args = ["replay", "--model", "pm10kw", "--run", str(tmp_path / "nope.csv")]
    out = cli(*(["--debug", *args] if where == "before" else [*args, "--debug"]))
    assert out.returncode != 0 and "Traceback" in out.stderr and "RunError" in out.stderr, out.stderr
    assert "unrecognized arguments" not in out.stderr


def test_calibrate_writes_a_model_file_only_as_yaml(tmp_path):
    out = cli("calibrate", "--model", "pm10kw", "--run", str(tmp_path / "r.csv"), "--out", str(tmp_path / "m.txt"))
    assert out.returncode == 2 and out.stderr.strip().endswith("m.txt: a model file ends in .yaml (or .yml)")
    assert not (tmp_path / "m.txt").exists()
