"""The offline bad-input table: every case exits 2 with one line on stderr that names the file and
the row/column or key at fault, and no traceback (``thermal-edge`` run as a user runs it).

Each case starts from a good simulated run of a two-node model (``conftest.good_run``) and breaks
one thing, the way a test-bench export or a hand-edited file goes wrong.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from cmd_testlib import MODELS, ROOT, TWO_NODE, te, te_here

OVERFLOW = MODELS / "overflow.yaml"  # the two-node model with a loss law exp(speed_rpm): inf above ~710 rpm
OTHER = MODELS / "other_sensors.yaml"  # the two-node model whose sensors have other names


def _table(path: Path) -> tuple[list[str], list[list[str]]]:
    lines = [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    return lines[0].split(","), [ln.split(",") for ln in lines[1:]]


def _write(path: Path, header: list[str], rows: list[list[str]], encoding: str = "utf-8", comment: str = "") -> Path:
    text = comment + "\n".join(",".join(r) for r in [header, *rows]) + "\n"
    path.write_bytes(text.encode(encoding))
    return path


def _map(good: Path, out: Path, column: str, f: Callable[[float], float]) -> Path:
    """The good run with ``f`` applied to every value of ``column``."""
    header, rows = _table(good)
    j = header.index(column)
    for r in rows:
        r[j] = f"{f(float(r[j])):.6g}"
    return _write(out, header, rows)


def _rename(good: Path, out: Path, old: str, new: str) -> Path:
    header, rows = _table(good)
    return _write(out, [new if h == old else h for h in header], rows)


def _drop(good: Path, out: Path, column: str) -> Path:
    header, rows = _table(good)
    j = header.index(column)
    return _write(out, header[:j] + header[j + 1:], [r[:j] + r[j + 1:] for r in rows])


def _cell(good: Path, out: Path, row: int, column: str, value: str, encoding: str = "utf-8", comment: str = "") -> Path:
    """The good run with data row ``row`` (0-based), ``column`` set to ``value``."""
    header, rows = _table(good)
    rows[row][header.index(column)] = value
    return _write(out, header, rows, encoding, comment)


def replay(run: Path, *extra: object, model: Path = TWO_NODE) -> list[object]:
    return ["replay", "--model", model, "--run", run, *extra]


def calibrate(*runs: Path, model: Path = TWO_NODE, extra: tuple[object, ...] = ()) -> list[object]:
    return ["calibrate", "--model", model, "--run", *runs, "--out", runs[0].with_suffix(".yaml"),
            "--generations", "2", "--popsize", "3", "--decimate", "10", *extra]


# Each case: (tmp, good run) -> (command line, the file or key the message must name, fragments it must hold).
CASES: dict[str, Callable[[Path, Path], tuple[list[object], str, list[str]]]] = {
    "sensor in kelvin": lambda tmp, g: (replay(p := _map(g, tmp / "k.csv", "housing", lambda x: x + 273.15)),
                                        str(p), ["column 'housing'", "kelvin"]),
    "ambient input in kelvin": lambda tmp, g: (replay(p := _map(g, tmp / "k.csv", "ambient_c", lambda x: x + 273.15)),
                                               str(p), ["column 'ambient_c'", "kelvin"]),
    "time in milliseconds": lambda tmp, g: (replay(p := _map(g, tmp / "ms.csv", "t", lambda x: 1000 * x)),
                                            str(p), ["column 't'", "milliseconds"]),
    "time in ms, calibrate": lambda tmp, g: (calibrate(g, p := _map(g, tmp / "ms.csv", "t", lambda x: 1000 * x)),
                                             str(p), ["column 't'", "milliseconds"]),
    "sensor in kelvin, second run of calibrate": lambda tmp, g: (
        calibrate(g, p := _map(g, tmp / "k.csv", "winding_t", lambda x: x + 273.15)), str(p), ["column 'winding_t'", "kelvin"]),
    "implausible reading": lambda tmp, g: (replay(p := _cell(g, tmp / "cold.csv", 99, "housing", "-90")),
                                           str(p), ["column 'housing', sample 100", "t = 99 s"]),
    "empty file": lambda tmp, g: (replay(p := _write(tmp / "empty.csv", [], [])), str(p), ["empty"]),
    "header only": lambda tmp, g: (replay(p := _write(tmp / "h.csv", _table(g)[0], [])), str(p), ["no data rows"]),
    "binary file": lambda tmp, g: (replay(p := tmp / "bin.csv"), str(p), ["binary file"]),
    "UTF-16 export": lambda tmp, g: (replay(p := tmp / "u16.csv"), str(p), ["UTF-16"]),
    "cp1252 export, unit in a cell": lambda tmp, g: (
        replay(p := _cell(g, tmp / "w.csv", 5, "ambient_c", "25 °C", "cp1252", "# Prüfstand 3, Temperaturen in °C\n")),
        str(p), ["line 8, column 'ambient_c'", "not a number: '25 °C'"]),
    "Latin-1 export, text in a cell": lambda tmp, g: (
        replay(p := _cell(g, tmp / "l.csv", 0, "housing", "Prüfstand", "latin-1")),
        str(p), ["line 2, column 'housing'", "'Prüfstand'"]),
    "decimal comma": lambda tmp, g: (replay(p := _cell(g, tmp / "dc.csv", 3, "i_rms", '"7,1"')),
                                     str(p), ["line 5, column 'i_rms'", "'7,1'", "decimal comma"]),
    "misspelt sensor column": lambda tmp, g: (replay(p := _rename(g, tmp / "typo.csv", "housing", "housng")),
                                              str(p), ["column 'housng'", "did you mean 'housing'"]),
    "missing input column": lambda tmp, g: (replay(p := _drop(g, tmp / "noi.csv", "i_rms")),
                                            str(p), ["no column 'i_rms'", "needs input"]),
    "misspelt input column": lambda tmp, g: (replay(p := _rename(g, tmp / "ityp.csv", "i_rms", "i_rsm")),
                                             str(p), ["no column 'i_rms'", "did you mean 'i_rsm'"]),
    "no time column": lambda tmp, g: (replay(p := _drop(g, tmp / "not.csv", "t")), str(p), ["no column 't'"]),
    "time backwards": lambda tmp, g: (replay(p := _cell(g, tmp / "back.csv", 10, "t", "3")),
                                      str(p), ["line 12, column 't'", "increasing"]),
    "uneven sample times": lambda tmp, g: (replay(p := _cell(g, tmp / "gap.csv", 10, "t", "9.5")),
                                           str(p), ["column 't', sample 11", "uniformly"]),
    "sensor for the adapter not in the run": lambda tmp, g: (
        replay(p := _drop(g, tmp / "nos.csv", "winding_t"), "--adapt", "--sensors", "winding_t"),
        str(p), ["no column 'winding_t'", "--sensors"]),
    "--sensors names no sensor of the model": lambda tmp, g: (
        replay(g, "--adapt", "--sensors", "stator_winding"), str(g), ["--sensors 'stator_winding'", "no such sensor"]),
    "wrong model: none of its sensors in the run": lambda tmp, g: (
        replay(g, model=OTHER), str(g), ["none of model other_sensors's sensors", "wrong model"]),
    "wrong --format: a Paderborn file read as csv": lambda tmp, g: (
        replay(p := _rename(_drop(g, tmp / "pb.csv", "speed_rpm"), tmp / "pb.csv", "t", "motor_speed")),
        str(p), ["no column 't'", "--format paderborn"]),
    "wrong --format: a candump log read as csv": lambda tmp, g: (
        replay(p := tmp / "log.csv"), str(p), ["line 1", "candump -L log", "--format can"]),
    "wrong --format: a CSV run read as candump": lambda tmp, g: (
        replay(p := tmp / "bin.log", "--format", "can", model=ROOT / "config" / "machines" / "pm10kw.yaml"),
        str(p), []),  # the CAN log reader's own message
    "overflowing loss law, replay": lambda tmp, g: (
        replay(g, model=OVERFLOW), str(OVERFLOW), ["not finite from sample", "node 'winding'", "speed_rpm = "]),
    "overflowing loss law, replay --adapt": lambda tmp, g: (
        replay(g, "--adapt", model=OVERFLOW), str(OVERFLOW), ["not finite from sample", "node 'winding'"]),
    "overflowing loss law, calibrate": lambda tmp, g: (calibrate(g, model=OVERFLOW), str(OVERFLOW), ["overflows"]),
    "overflowing loss law, discover": lambda tmp, g: (
        ["discover", "--model", OVERFLOW, "--run", g, "--quiet"], str(OVERFLOW), ["not finite from sample", "node 'winding'"]),
    "kelvin, discover": lambda tmp, g: (
        ["discover", "--model", TWO_NODE, "--run", p := _map(g, tmp / "k.csv", "housing", lambda x: x + 273.15), "--quiet"],
        str(p), ["column 'housing'", "kelvin"]),
    "kelvin, fleet calibrate": lambda tmp, g: (
        ["fleet", "calibrate", "--model", TWO_NODE, p := _map(g, tmp / "m2.csv", "housing", lambda x: x + 273.15),
         "--out", tmp / "f.parquet", "--workers", "1"], str(p), ["column 'housing'", "kelvin"]),  # its only machine
    "a directory as the run": lambda tmp, g: (replay(tmp), str(tmp), ["is a directory"]),
    "no such run file": lambda tmp, g: (replay(tmp / "nope.csv"), str(tmp / "nope.csv"), ["No such file"]),
    "--set outside the bounds": lambda tmp, g: (replay(g, "--set", "R_wh=9"), "--set R_wh=9", ["bound"]),
    "--plot with an unknown suffix": lambda tmp, g: (replay(g, "--plot", tmp / "f.txt"), "--plot", [".png"]),
    "--out with an unknown suffix": lambda tmp, g: (replay(g, "--out", tmp / "f.xlsx"), "--out", [".csv", ".parquet"]),
    "--max-time not positive": lambda tmp, g: (calibrate(g, extra=("--max-time", "0")), "error: argument --max-time:", ["> 0 s"]),
}


@pytest.fixture
def files(tmp_path: Path, good_run: Path) -> Path:
    """The test's directory, with the files no mutation of the good run makes."""
    (tmp_path / "bin.csv").write_bytes(bytes(range(256)) * 40)
    (tmp_path / "bin.log").write_bytes(bytes(range(256)) * 40)
    (tmp_path / "u16.csv").write_bytes(good_run.read_text().encode("utf-16"))
    (tmp_path / "log.csv").write_text("(1700000000.000000) can0 101#0000000000000000\n"
                                      "(1700000000.010000) can0 101#0100000000000000\n")
    return tmp_path


def test_the_table_has_at_least_20_cases():
    assert len(CASES) >= 20


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_refused_in_one_line(case, files, good_run):
    argv, names, fragments = CASES[case](files, good_run)
    r = te_here(*argv)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2, (r.returncode, r.stdout[-2000:], r.stderr[-2000:])
    assert "Traceback" not in r.stderr + r.stdout
    assert len(lines) == 1, r.stderr
    line = lines[0]
    assert line.startswith(f"thermal-edge {argv[0]}"), line
    assert names in line, line
    for f in fragments:
        assert f in line, (f, line)
    assert not any(w in r.stdout.split() for w in ("inf", "nan", "-inf")), r.stdout


@pytest.mark.parametrize("case", ["sensor in kelvin", "time in ms, calibrate"])
def test_the_installed_command_refuses_as_the_table_does(case, files, good_run):
    """The table runs in this process (:func:`te_here`); the command a user runs, in its own
    process, gives the same exit status and line."""
    argv, _, _ = CASES[case](files, good_run)
    here, there = te_here(*argv), te(*argv)
    assert (there.returncode, there.stderr.strip()) == (here.returncode, here.stderr.strip()) == (2, here.stderr.strip())
    assert len(here.stderr.strip().splitlines()) == 1


def test_utf8_cp1252_and_latin1_exports_replay_alike(good_run, tmp_path):
    """The same run as a UTF-8 (with BOM), a Windows-1252 and a Latin-1 export with '°C' and
    'Prüfstand' in its header comment: the same scores, exit 0."""
    header, rows = _table(good_run)
    comment = "# Prüfstand 3, Temperaturen in °C\n"
    outs = []
    for name, enc in (("u.csv", "utf-8-sig"), ("w.csv", "cp1252"), ("l.csv", "latin-1")):
        r = te(*replay(_write(tmp_path / name, header, rows, enc, comment), "--json"))
        assert r.returncode == 0, r.stderr
        outs.append(r.stdout.split('"mse"')[1])
    assert outs[0] == outs[1] == outs[2]


def test_the_summary_comes_before_the_scores(good_run):
    """The data summary: samples, the sample period, the duration, columns used (with ranges) and ignored."""
    r = te(*replay(good_run))
    assert r.returncode == 0, r.stderr
    first = r.stdout.splitlines()[0]
    _, rows = _table(good_run)
    t = np.array([float(x[0]) for x in rows])
    assert first.startswith(f"{good_run}: {len(rows)} samples every 1 s ({(t[-1] - t[0]) / 3600:.2f} h)")
    assert "used: speed_rpm " in first and "housing " in first and "ignored: torque_nm" in first
