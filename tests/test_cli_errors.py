"""The command line's error contract: a user error is one line and exit 2; anything else is a bug
and shows its traceback; ``--debug`` shows the traceback of a user error too."""
from __future__ import annotations

import subprocess
import sys

import pytest

from thermal_edge.cli import main
from thermal_edge.errors import ThermalEdgeError, UsageError

#: runs the CLI with ``config example`` replaced by a function that raises what the argument names
RAISING = """
import sys
import thermal_edge.commands.config as c
from thermal_edge.errors import UsageError
def boom(args):
    raise {exc}
c.run_example = boom
from thermal_edge.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _run(exc: str, *argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", RAISING.format(exc=exc), *argv], capture_output=True, text=True,
                          timeout=120)


def test_a_bug_inside_a_command_shows_its_traceback():
    r = _run("KeyError('R_xx')", "config", "example")
    assert r.returncode == 1
    assert "Traceback (most recent call last)" in r.stderr and "KeyError: 'R_xx'" in r.stderr


def test_a_user_error_is_one_line_and_exit_2():
    r = _run("UsageError('--model pm11: no such file')", "config", "example")
    assert r.returncode == 2
    assert r.stderr.splitlines() == ["thermal-edge config example: error: --model pm11: no such file"]


def test_under_systemd_the_error_line_carries_the_journals_err_priority(tmp_path):
    """stderr being the journal (``JOURNAL_STREAM`` names its device and inode, as systemd sets it):
    the one line that says why the unit stopped is filed at priority 3, ``journalctl -p warning``
    shows it; an argparse error too. On any other stderr the line stays plain."""
    import os

    err = tmp_path / "journal"
    for argv, line in ((("config", "example"), "thermal-edge config example: error: --model pm11: no such file"),
                       (("config", "example", "--nosuch"), "thermal-edge config example: error: unrecognized arguments: "
                                                           "--nosuch")):
        with open(err, "w") as fh:
            st = os.fstat(fh.fileno())
            r = subprocess.run([sys.executable, "-c", RAISING.format(exc="UsageError('--model pm11: no such file')"), *argv],
                               stderr=fh, stdout=subprocess.DEVNULL, timeout=120,
                               env={**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
        assert r.returncode == 2 and err.read_text().splitlines() == [f"<3>{line}"]
    r = _run("UsageError('--model pm11: no such file')", "config", "example")
    assert r.stderr.splitlines() == ["thermal-edge config example: error: --model pm11: no such file"]


def test_debug_shows_the_traceback_of_a_user_error():
    r = _run("UsageError('--model pm11: no such file')", "--debug", "config", "example")
    assert r.returncode == 1
    assert "Traceback (most recent call last)" in r.stderr and "UsageError: --model pm11" in r.stderr


def test_every_user_error_class_derives_from_the_one_base():
    from thermal_edge.bus.logs import LogFormatError
    from thermal_edge.config import ConfigError
    from thermal_edge.data import RunError
    from thermal_edge.lptn import ModelError

    for cls in (ConfigError, ModelError, RunError, LogFormatError, UsageError):
        assert issubclass(cls, ThermalEdgeError), cls
    assert not issubclass(KeyError, ThermalEdgeError) and not issubclass(FileNotFoundError, ThermalEdgeError)


def test_in_process_a_user_error_returns_2_and_debug_raises(tmp_path, capsys):
    missing = str(tmp_path / "nope.yaml")
    argv = ["simulate", "--model", missing, "--cycle", "overload", "--out", str(tmp_path / "run.csv")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.yaml" in err[0] and "--model" in err[0]
    with pytest.raises(ThermalEdgeError):
        main(["--debug", *argv])


def test_run_check_honours_debug(tmp_path, capsys):
    missing = str(tmp_path / "nope.yaml")
    assert main(["run", "--check", "--config", missing]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    with pytest.raises((ThermalEdgeError, OSError)):
        main(["--debug", "run", "--check", "--config", missing])


@pytest.mark.parametrize(("argv", "prog"), [
    (["replay", "--model", "pm10kw", "--run", "x.csv", "--bogus"], "thermal-edge replay"),
    (["config", "example", "--bogus", "1"], "thermal-edge config example"),
    (["bench", "jacobian", "--bogus"], "thermal-edge bench jacobian"),
])
def test_an_unknown_option_is_named_by_the_command_that_does_not_know_it(argv, prog, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"{prog}: error: unrecognized arguments: --bogus"), err
