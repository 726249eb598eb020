"""The bad-input table: every case exits 2 with one line on stderr that names the file and the
row/column, key or option at fault and the cause, and no traceback (``thermal-edge`` run as a
user runs it, in this process).

The cases break one thing each, the way a test-bench export, a hand-edited file or a typed option
goes wrong: a run CSV (from a good simulated run of a two-node model, ``conftest.good_run``), a
model file (from the two-node model), ``edge.yaml`` (from the shipped one, ``run --check``), a CAN
log (from a simulated recording), and every numeric, list and path option of every command. State
files are not read by an offline command: their refusals are listed at the end (the service moves
such a file aside with one log line and starts from the model, ``tests/service/test_persistence.py``).
"""
from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml
from cmd_testlib import CYCLE, MODELS, ROOT, TWO_NODE, te, te_here

from thermal_edge.lptn import load_model
from thermal_edge.service.persistence import FORMAT, VERSION, StateError, decode

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
        replay(g, model=OVERFLOW), str(OVERFLOW), ["from sample", "node 'winding'", "speed_rpm = "]),
    "overflowing loss law, replay --adapt": lambda tmp, g: (
        replay(g, "--adapt", model=OVERFLOW), str(OVERFLOW), ["from sample", "node 'winding'"]),
    "overflowing loss law, calibrate": lambda tmp, g: (calibrate(g, model=OVERFLOW), str(OVERFLOW), ["overflows"]),
    "overflowing loss law, discover": lambda tmp, g: (
        ["discover", "--model", OVERFLOW, "--run", g, "--quiet"], str(OVERFLOW), ["from sample", "node 'winding'"]),
    "kelvin, discover": lambda tmp, g: (
        ["discover", "--model", TWO_NODE, "--run", p := _map(g, tmp / "k.csv", "housing", lambda x: x + 273.15), "--quiet"],
        str(p), ["column 'housing'", "kelvin"]),
    "kelvin, fleet calibrate": lambda tmp, g: (
        ["fleet", "calibrate", "--model", TWO_NODE, p := _map(g, tmp / "m2.csv", "housing", lambda x: x + 273.15),
         "--out", tmp / "f.parquet", "--workers", "1"], str(p), ["column 'housing'", "kelvin"]),  # its only machine
    "a directory as the run": lambda tmp, g: (replay(_dir(tmp / "runs")), str(tmp / "runs"), ["is a directory"]),
    "no such run file": lambda tmp, g: (replay(tmp / "nope.csv"), str(tmp / "nope.csv"), ["No such file"]),
    "--set outside the bounds": lambda tmp, g: (replay(g, "--set", "R_wh=9"), "--set R_wh=9", ["bound"]),
    "--plot with an unknown suffix": lambda tmp, g: (replay(g, "--plot", tmp / "f.txt"), "--plot", [".png"]),
    "--out with an unknown suffix": lambda tmp, g: (replay(g, "--out", tmp / "f.xlsx"), "--out", [".csv", ".parquet"]),
    "--max-time not positive": lambda tmp, g: (calibrate(g, extra=("--max-time", "0")), "error: argument --max-time:", ["> 0 s"]),
}



# -- run CSVs: units, ranges, separators, gaps -------------------------------------------------------
def _sep(good: Path, out: Path, sep: str) -> Path:
    header, rows = _table(good)
    out.write_text("\n".join(sep.join(r) for r in [header, *rows]) + "\n")
    return out


RUN_CASES: dict[str, Callable[[Path, Path], tuple[list[object], str, list[str]]]] = {
    "current in mA": lambda tmp, g: (replay(p := _map(g, tmp / "ma.csv", "i_rms", lambda x: 1000 * x)),
                                     str(p), ["column 'i_rms'", "looks like mA"]),
    "current in mA, calibrate": lambda tmp, g: (calibrate(p := _map(g, tmp / "ma.csv", "i_rms", lambda x: 1000 * x)),
                                                str(p), ["column 'i_rms'", "mA"]),
    "negative RMS current": lambda tmp, g: (replay(p := _cell(g, tmp / "neg.csv", 40, "i_rms", "-7.1")),
                                            str(p), ["column 'i_rms', sample 41", "-7.1 A is outside"]),
    "RMS current negative throughout": lambda tmp, g: (replay(p := _map(g, tmp / "neg.csv", "i_rms", lambda x: -x)),
                                                       str(p), ["column 'i_rms', sample 1", "outside the plausible 0"]),
    "a 1e6 A sample": lambda tmp, g: (replay(p := _cell(g, tmp / "spike.csv", 500, "i_rms", "1e6")),
                                      str(p), ["column 'i_rms', sample 501", "1e+06 A is outside"]),
    "a 1e6 A sample, discover": lambda tmp, g: (
        ["discover", "--model", TWO_NODE, "--run", p := _cell(g, tmp / "spike.csv", 500, "i_rms", "1e6"), "--quiet"],
        str(p), ["column 'i_rms', sample 501"]),
    "nan in the current column": lambda tmp, g: (replay(p := _cell(g, tmp / "nan.csv", 200, "i_rms", "nan")),
                                                 str(p), ["column 'i_rms', sample 201", "not measured"]),
    "empty cell in the current column": lambda tmp, g: (replay(p := _cell(g, tmp / "gap.csv", 7, "i_rms", "")),
                                                        str(p), ["column 'i_rms', sample 8", "not measured"]),
    "nan in the current column, --adapt": lambda tmp, g: (
        replay(p := _cell(g, tmp / "nan.csv", 200, "i_rms", "nan"), "--adapt"), str(p), ["column 'i_rms'", "not measured"]),
    "nan in the current column, calibrate": lambda tmp, g: (
        calibrate(p := _cell(g, tmp / "nan.csv", 200, "i_rms", "NaN")), str(p), ["column 'i_rms'", "not measured"]),
    "nan in the speed column": lambda tmp, g: (replay(p := _cell(g, tmp / "nan.csv", 3, "speed_rpm", "NA")),
                                               str(p), ["column 'speed_rpm', sample 4", "not measured"]),
    "speed in rpm x 1000": lambda tmp, g: (replay(p := _cell(g, tmp / "fast.csv", 3, "speed_rpm", "6e5")),
                                           str(p), ["column 'speed_rpm', sample 4", "outside the plausible"]),
    "ambient in kelvin at one sample": lambda tmp, g: (replay(p := _cell(g, tmp / "k1.csv", 9, "ambient_c", "298.15")),
                                                       str(p), ["column 'ambient_c', sample 10", "looks like kelvin"]),
    "ambient of 150 degC": lambda tmp, g: (replay(p := _cell(g, tmp / "hot.csv", 9, "ambient_c", "150")),
                                           str(p), ["column 'ambient_c', sample 10", "outside the plausible"]),
    "sensor reading of 900 degC": lambda tmp, g: (replay(p := _cell(g, tmp / "900.csv", 9, "winding_t", "900")),
                                                  str(p), ["column 'winding_t', sample 10", "outside the plausible"]),
    "sensor reading of 5000 degC": lambda tmp, g: (replay(p := _cell(g, tmp / "5000.csv", 9, "winding_t", "5000")),
                                                   str(p), ["column 'winding_t', sample 10", "outside the plausible"]),
    "sensor in kelvin, --adapt": lambda tmp, g: (
        replay(p := _map(g, tmp / "k.csv", "winding_t", lambda x: x + 273.15), "--adapt"), str(p), ["kelvin"]),
    "semicolon-separated export": lambda tmp, g: (replay(p := _sep(g, tmp / "semi.csv", ";")),
                                                  str(p), ["line 1", "semicolons"]),
    "semicolon-separated export, calibrate": lambda tmp, g: (calibrate(p := _sep(g, tmp / "semi.csv", ";")),
                                                             str(p), ["semicolons"]),
    "tab-separated export": lambda tmp, g: (replay(p := _sep(g, tmp / "tab.csv", "\t")), str(p), ["tabs"]),
    "tab-separated export, discover": lambda tmp, g: (
        ["discover", "--model", TWO_NODE, "--run", p := _sep(g, tmp / "tab.csv", "\t"), "--quiet"], str(p), ["tabs"]),
    "a row with a value too many": lambda tmp, g: (replay(p := _cell(g, tmp / "wide.csv", 4, "t", "4,5")),
                                                   str(p), ["line 6", "the header has"]),
    "infinite value": lambda tmp, g: (replay(p := _cell(g, tmp / "inf.csv", 4, "housing", "inf")),
                                      str(p), ["line 6, column 'housing'", "infinite"]),
    "time nan": lambda tmp, g: (replay(p := _cell(g, tmp / "tnan.csv", 4, "t", "nan")),
                                str(p), ["line 6, column 't'", "finite and increasing"]),
    "time repeated": lambda tmp, g: (replay(p := _cell(g, tmp / "trep.csv", 4, "t", "3")),
                                     str(p), ["line 6, column 't'", "increasing"]),
    "a column twice": lambda tmp, g: (replay(p := _rename(g, tmp / "dup.csv", "housing", "winding_t")),
                                      str(p), ["'winding_t'", "more than once"]),
    "time in ms, discover": lambda tmp, g: (
        ["discover", "--model", TWO_NODE, "--run", p := _map(g, tmp / "ms.csv", "t", lambda x: 1000 * x), "--quiet"],
        str(p), ["column 't'", "milliseconds"]),
    "one sample": lambda tmp, g: (replay(p := _write(tmp / "one.csv", _table(g)[0], _table(g)[1][:1])),
                                  str(p), ["1 sample(s)"]),
    "two samples, calibrate": lambda tmp, g: (calibrate(p := _write(tmp / "two.csv", _table(g)[0], _table(g)[1][:2])),
                                              str(p), ["too short to calibrate", "3 parameters"]),
    "ten samples, calibrate": lambda tmp, g: (calibrate(p := _write(tmp / "ten.csv", _table(g)[0], _table(g)[1][:10])),
                                              str(p), ["too short to calibrate"]),
    "the run is a model file": lambda tmp, g: (replay(TWO_NODE), str(TWO_NODE), ["values, the header has"]),
    "Paderborn data read as csv, calibrate": lambda tmp, g: (
        calibrate(p := _rename(_drop(g, tmp / "pb.csv", "speed_rpm"), tmp / "pb.csv", "t", "motor_speed")),
        str(p), ["--format paderborn"]),
    "no such run, calibrate": lambda tmp, g: (calibrate(tmp / "nope.csv"), str(tmp / "nope.csv"), ["No such file"]),
    "no such run, discover": lambda tmp, g: (["discover", "--model", TWO_NODE, "--run", tmp / "nope.csv"],
                                             str(tmp / "nope.csv"), ["No such file"]),
    "no such run, fleet": lambda tmp, g: (["fleet", "calibrate", "--model", TWO_NODE, tmp / "nope.csv", "--out",
                                           tmp / "f.parquet", "--workers", "1"], str(tmp / "nope.csv"), ["no such file"]),
    "binary run, calibrate": lambda tmp, g: (calibrate(tmp / "bin.csv"), str(tmp / "bin.csv"), ["binary file"]),
    "UTF-16 run, discover": lambda tmp, g: (["discover", "--model", TWO_NODE, "--run", tmp / "u16.csv"],
                                            str(tmp / "u16.csv"), ["UTF-16"]),
    "a directory as the run, calibrate": lambda tmp, g: (calibrate(tmp), str(tmp), ["is a directory"]),
}


# -- model files: encodings, units, limits, the network ---------------------------------------------
def _model(tmp: Path, name: str, old: str = "", new: str = "", text: str | None = None, encoding: str = "utf-8") -> Path:
    """The two-node model with ``old`` replaced by ``new`` (or ``text`` itself), written as ``name``."""
    src = TWO_NODE.read_text()
    if old:
        assert old in src, old
    body = text if text is not None else src.replace(old, new)
    out = tmp / name
    out.write_bytes(body.encode(encoding))
    return out


LATIN1 = "# Kühlung: Gehäuse\n"


MODEL_CASES: dict[str, Callable[[Path, Path], tuple[list[object], str, list[str]]]] = {
    "model with a Latin-1 comment, replay": lambda tmp, g: (
        replay(g, model=_model(tmp, "l1.yaml", text=LATIN1 + TWO_NODE.read_text(), encoding="latin-1")),
        "l1.yaml", ["line 1, column 4 (byte 3)", "not UTF-8"]),
    "model with a Latin-1 comment, simulate": lambda tmp, g: (
        ["simulate", "--model", _model(tmp, "l1.yaml", text=LATIN1 + TWO_NODE.read_text(), encoding="latin-1"),
         "--cycle", CYCLE, "--out", tmp / "o.csv"], "l1.yaml", ["not UTF-8"]),
    "model with a Latin-1 comment, calibrate": lambda tmp, g: (
        calibrate(g, model=_model(tmp, "l1.yaml", text=LATIN1 + TWO_NODE.read_text(), encoding="latin-1")),
        "l1.yaml", ["not UTF-8"]),
    "model with a Latin-1 comment, discover": lambda tmp, g: (
        ["discover", "--model", _model(tmp, "l1.yaml", text=LATIN1 + TWO_NODE.read_text(), encoding="latin-1"),
         "--run", g], "l1.yaml", ["not UTF-8"]),
    "model with a Latin-1 comment, fleet": lambda tmp, g: (
        ["fleet", "calibrate", "--model", _model(tmp, "l1.yaml", text=LATIN1 + TWO_NODE.read_text(), encoding="latin-1"),
         g, "--out", tmp / "f.parquet", "--workers", "1"], "l1.yaml", ["not UTF-8"]),
    "binary model, replay": lambda tmp, g: (replay(g, model=tmp / "bin.yaml"), "bin.yaml", ["binary file"]),
    "binary model, simulate": lambda tmp, g: (["simulate", "--model", tmp / "bin.yaml", "--cycle", CYCLE, "--out",
                                               tmp / "o.csv"], "bin.yaml", ["binary file"]),
    "binary model, calibrate": lambda tmp, g: (calibrate(g, model=tmp / "bin.yaml"), "bin.yaml", ["binary file"]),
    "no such model": lambda tmp, g: (replay(g, model=tmp / "nope.yaml"), str(tmp / "nope.yaml"), ["no such file"]),
    "no such model, discover": lambda tmp, g: (["discover", "--model", tmp / "nope.yaml", "--run", g],
                                               str(tmp / "nope.yaml"), ["no such file"]),
    "a directory as the model": lambda tmp, g: (replay(g, model=tmp), str(tmp), ["is a directory"]),
    "empty model": lambda tmp, g: (replay(g, model=_model(tmp, "e.yaml", text="")), "e.yaml", ["expected a mapping"]),
    "model is a list": lambda tmp, g: (replay(g, model=_model(tmp, "l.yaml", text="- a\n- b\n")), "l.yaml", ["mapping"]),
    "limits in kelvin": lambda tmp, g: (
        replay(g, model=_model(tmp, "k.yaml", "warn_c: 140, max_c: 155", "warn_c: 413, max_c: 428")),
        "k.yaml", ["limits.hot_spot.warn_c", "413 degC looks like kelvin"]),
    "limit max in kelvin": lambda tmp, g: (
        ["simulate", "--model", _model(tmp, "k.yaml", "max_c: 155", "max_c: 428"), "--cycle", CYCLE, "--out", tmp / "o.csv"],
        "k.yaml", ["limits.hot_spot.max_c", "looks like kelvin"]),
    "limit below room temperature": lambda tmp, g: (
        replay(g, model=_model(tmp, "c.yaml", "warn_c: 140, max_c: 155", "warn_c: 5, max_c: 15")),
        "c.yaml", ["limits.hot_spot.warn_c", "outside the plausible"]),
    "limit warn above max": lambda tmp, g: (
        replay(g, model=_model(tmp, "w.yaml", "warn_c: 140, max_c: 155", "warn_c: 160, max_c: 155")),
        "w.yaml", ["limits.hot_spot", "must be below max_c"]),
    "current input declared in mA": lambda tmp, g: (
        replay(g, model=_model(tmp, "ma.yaml", "i_rms: {role: current, unit: A}", "i_rms: {role: current, unit: mA}")),
        "ma.yaml", ["inputs.i_rms.unit", "'mA' is not the unit of role 'current'"]),
    "ambient input declared in K": lambda tmp, g: (
        replay(g, model=_model(tmp, "k.yaml", "ambient_c: {role: ambient, unit: degC}", "ambient_c: {role: ambient, unit: K}")),
        "k.yaml", ["inputs.ambient_c.unit", "degC"]),
    "disconnected node": lambda tmp, g: (
        replay(g, model=_model(tmp, "d.yaml", "  - {between: [winding, housing_n], r: R_wh}\n", "")),
        "d.yaml", ["nodes[0]", "node 'winding' is not connected to any boundary"]),
    "disconnected node, simulate": lambda tmp, g: (
        ["simulate", "--model", _model(tmp, "d.yaml", "  - {between: [housing_n, ambient], r: R_ha}\n", ""),
         "--cycle", CYCLE, "--out", tmp / "o.csv"], "d.yaml", ["not connected to any boundary"]),
    "unknown role": lambda tmp, g: (
        replay(g, model=_model(tmp, "r.yaml", "role: current", "role: curent")), "r.yaml",
        ["inputs.i_rms.role", "did you mean 'current'"]),
    "unknown section": lambda tmp, g: (replay(g, model=_model(tmp, "s.yaml", "sensors:", "sensor:")), "s.yaml",
                                       ["sensor", "unknown section"]),
    "key given twice": lambda tmp, g: (replay(g, model=_model(tmp, "t.yaml", "name: two_node", "name: two_node\nname: x")),
                                       "t.yaml", ["appears twice"]),
    "a law that does not parse": lambda tmp, g: (
        replay(g, model=_model(tmp, "p.yaml", "3 * R_s * i_rms ** 2", "3 * R_s * (i_rms ** 2")), "p.yaml", ["losses[0].power"]),
    "a law naming an unknown input": lambda tmp, g: (
        replay(g, model=_model(tmp, "u.yaml", "3 * R_s * i_rms ** 2", "3 * R_s * i_rsm ** 2")), "u.yaml",
        ["losses[0].power", "i_rsm"]),
    "parameter outside its bounds": lambda tmp, g: (
        replay(g, model=_model(tmp, "b.yaml", "C_w: {value: 2000,", "C_w: {value: 200000,")), "b.yaml",
        ["parameters.C_w", "outside [min, max]"]),
    "parameter min not positive": lambda tmp, g: (
        replay(g, model=_model(tmp, "m.yaml", "min: 200, max: 20000", "min: -200, max: 20000")), "m.yaml",
        ["parameters.C_w.min", "must be positive"]),
    "a limit given as a word": lambda tmp, g: (
        replay(g, model=_model(tmp, "w.yaml", "warn_c: 140", 'warn_c: "hot"')), "w.yaml",
        ["limits.hot_spot.warn_c", "expected a number", "'hot'"]),
    "sensor on an unknown node": lambda tmp, g: (
        replay(g, model=_model(tmp, "n.yaml", "winding_t: {node: winding}", "winding_t: {node: windin}")), "n.yaml",
        ["sensors.winding_t.node", "'windin'"]),
    "invalid YAML": lambda tmp, g: (replay(g, model=_model(tmp, "y.yaml", text="name: [x\n")), "y.yaml",
                                    ["not valid YAML"]),
    "a loss law reaching 1e299": lambda tmp, g: (
        replay(g, model=(m := _model(tmp, "big.yaml", "3 * R_s * i_rms ** 2", "1e299 * (1 + i_rms)"))),
        str(m), ["diverges", "node 'winding'", "overflows"]),
    "a loss law reaching 1e299, calibrate": lambda tmp, g: (
        calibrate(g, model=(m := _model(tmp, "big.yaml", "3 * R_s * i_rms ** 2", "1e299 * (1 + i_rms)"))),
        str(m), ["node 'winding'", "overflows"]),
    "a loss law reaching 1e6 W, replay --adapt": lambda tmp, g: (
        replay(g, "--adapt", model=(m := _model(tmp, "big.yaml", "3 * R_s * i_rms ** 2", "1e6 * (1 + i_rms)"))),
        str(m), ["diverges", "node 'winding'"]),
}


# -- edge.yaml (run --check, demo) ------------------------------------------------------------------
def _edge(tmp: Path, edit: Callable[[dict], object] | None = None, name: str = "edge.yaml") -> Path:
    """The shipped edge.yaml with absolute paths and a state directory under ``tmp``, edited by ``edit``."""
    raw = yaml.safe_load((ROOT / "config" / "edge.yaml").read_text(encoding="utf-8"))
    raw["model"]["path"] = str(ROOT / "config" / "machines" / "pm10kw.yaml")
    raw["state"]["dir"] = str(tmp / "state")
    if edit is not None:
        edit(raw)
    out = tmp / name
    out.write_text(yaml.safe_dump(raw))
    return out


def _put(raw: dict, key: str, value: object) -> dict:
    *path, last = key.split(".")
    d = raw
    for k in path:
        d = d[k]
    d[last] = value
    return raw


def check(cfg: Path) -> list[object]:
    return ["run", "--check", "--config", cfg]


CONFIG_CASES: dict[str, Callable[[Path, Path], tuple[list[object], str, list[str]]]] = {
    "edge.yaml: a limit raised above the machine's": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "derating.limits.hot_spot", {"warn_c": 230, "max_c": 250}))),
        "derating.limits.hot_spot.max_c", ["250 degC is above the machine's 155 degC (pm10kw.yaml: limits.hot_spot.max_c)",
                                           "may lower a limit, not raise it"]),
    "edge.yaml: limits in kelvin": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "derating.limits.hot_spot", {"warn_c": 413, "max_c": 428}))),
        "derating.limits.hot_spot.warn_c", ["413 degC looks like kelvin"]),
    "edge.yaml: max_c in kelvin": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "derating.limits.magnet.max_c", 393.15))),
        "derating.limits.magnet.max_c", ["looks like kelvin"]),
    "edge.yaml: valid_range_c in kelvin": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "signals.valid_range_c", [233, 523]))),
        "signals.valid_range_c", ["523 degC looks like kelvin"]),
    "edge.yaml: valid_range_c above room temperature": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "signals.valid_range_c", [233, 290]))),
        "signals.valid_range_c", ["does not contain 20 degC", "kelvin"]),
    "edge.yaml: bitrate in kbit/s": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "bus.bitrate", 500))), "bus.bitrate", ["kbit/s typed?", "500000"]),
    "edge.yaml: bitrate of 10 Mbit/s": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "bus.bitrate", 10_000_000))), "bus.bitrate", ["outside"]),
    "edge.yaml: a timeout in ms": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "timeouts.INV_Currents", 500))), "timeouts.INV_Currents",
        ["ms typed? 500 ms is 0.5 s"]),
    "edge.yaml: tick in ms": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "clock.tick_s", 1000))), "clock.tick_s", ["ms typed? 1000 ms is 1 s"]),
    "edge.yaml: max current in mA": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "derating.max_current_a", 40000))), "derating.max_current_a", ["looks like mA"]),
    "edge.yaml: safe current negative": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "derating.safe_current_a", -10))), "derating.safe_current_a", ["positive"]),
    "edge.yaml: Latin-1 comment": lambda tmp, g: (
        check(_latin1(_edge(tmp))), "edge.yaml", ["not UTF-8", "byte"]),
    "edge.yaml: binary": lambda tmp, g: (check(tmp / "bin.yaml"), "bin.yaml", ["binary file"]),
    "edge.yaml: missing": lambda tmp, g: (check(tmp / "nope.yaml"), str(tmp / "nope.yaml"), ["No such file"]),
    "edge.yaml: a list": lambda tmp, g: (check(_model(tmp, "list.yaml", text="- 1\n")), "list.yaml", ["mapping"]),
    "edge.yaml: unknown key": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "derating.max_curent_a", 40))), "derating.max_curent_a", ["did you mean"]),
    "edge.yaml: a string for a number": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "derating.max_current_a", "40 A"))), "derating.max_current_a",
        ["expected a number"]),
    "edge.yaml: model in kelvin limits": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "model.path", str(_model(tmp, "k.yaml", "max_c: 155", "max_c: 428"))))),
        "model.path", ["k.yaml", "looks like kelvin"]),
    "edge.yaml: model with a Latin-1 comment": lambda tmp, g: (
        check(_edge(tmp, lambda r: _put(r, "model.path", str(_model(tmp, "l1.yaml", text=LATIN1 + TWO_NODE.read_text(),
                                                                      encoding="latin-1"))))),
        "model.path", ["l1.yaml", "not UTF-8"]),
    "demo: edge.yaml with a Latin-1 comment": lambda tmp, g: (
        ["demo", "--config", _latin1(_edge(tmp))], "edge.yaml", ["not UTF-8"]),
    "demo: edge.yaml missing": lambda tmp, g: (["demo", "--config", tmp / "nope.yaml"], "nope.yaml", ["No such file"]),
    "demo: limits in kelvin": lambda tmp, g: (
        ["demo", "--config", _edge(tmp, lambda r: _put(r, "derating.limits.hot_spot", {"warn_c": 413, "max_c": 428}))],
        "derating.limits.hot_spot.warn_c", ["kelvin"]),
    "monitor --bus: edge.yaml with bitrate in kbit/s": lambda tmp, g: (
        ["monitor", "--bus", "--once", "--config", _edge(tmp, lambda r: _put(r, "bus.bitrate", 250))],
        "bus.bitrate", ["kbit/s"]),
}


def _latin1(path: Path) -> Path:
    path.write_bytes(LATIN1.encode("latin-1") + path.read_bytes())
    return path


# -- CAN logs (replay --format can) ------------------------------------------------------------------
def can_replay(log: Path) -> list[object]:
    return ["replay", "--format", "can", "--run", log]


def _log_lines(log: Path, out: Path, f: Callable[[list[str]], list[str]]) -> Path:
    out.write_text("\n".join(f(log.read_text().splitlines()[:3000])) + "\n")
    return out


def _restamp(lines: list[str], g: Callable[[float], float]) -> list[str]:
    out = []
    for ln in lines:
        t, rest = ln.split(" ", 1)
        out.append(f"({g(float(t.strip('()'))):.6f}) {rest}")
    return out


LOG_CASES: dict[str, Callable[[Path, Path], tuple[list[object], str, list[str]]]] = {
    "CAN log stamped in ms since the epoch": lambda tmp, g: (
        can_replay(p := _log_lines(tmp / "s.log", tmp / "ms.log", lambda ls: _restamp(ls, lambda t: 1000 * t))),
        str(p), ["message 1", "stamped in ms"]),
    "CAN log stamped in ms from its start": lambda tmp, g: (
        can_replay(p := _log_lines(tmp / "s.log", tmp / "msrel.log",
                                   lambda ls: _restamp(ls, lambda t: 1000 * (t - 1.7e9)))), str(p), ["stamped in ms"]),
    "CAN log stamped in µs": lambda tmp, g: (
        can_replay(p := _log_lines(tmp / "s.log", tmp / "us.log", lambda ls: _restamp(ls, lambda t: 1e6 * t))),
        str(p), ["stamped in ms or µs"]),
    "reversed CAN log": lambda tmp, g: (can_replay(p := _log_lines(tmp / "s.log", tmp / "rev.log", lambda ls: ls[::-1])),
                                        str(p), ["time runs backwards"]),
    "shuffled CAN log": lambda tmp, g: (
        can_replay(p := _log_lines(tmp / "s.log", tmp / "shuf.log",
                                   lambda ls: [ls[i] for i in np.random.default_rng(4).permutation(len(ls))])),
        str(p), ["time runs backwards"]),
    "BLF cut in half": lambda tmp, g: (can_replay(tmp / "half.blf"), str(tmp / "half.blf"), ["cut short"]),
    "candump -ta display output": lambda tmp, g: (can_replay(tmp / "timed.log"), str(tmp / "timed.log"),
                                                  [":1:", "-ta, -td or -tz", "record with candump -L"]),
    "plain candump output without -L": lambda tmp, g: (can_replay(tmp / "plain.log"), str(tmp / "plain.log"),
                                                       ["line 1" if False else ":1:", "candump -L"]),
    "a run CSV given with --format can": lambda tmp, g: (can_replay(g), str(g), ["not python-can's CSV log",
                                                                                 "without --format can"]),
    "no such CAN log": lambda tmp, g: (can_replay(tmp / "nope.log"), str(tmp / "nope.log"), ["no such CAN log"]),
    "unknown log suffix": lambda tmp, g: (can_replay(tmp / "notes.txt"), str(tmp / "notes.txt"), ["unknown CAN log format"]),
    "binary file as a .blf": lambda tmp, g: (can_replay(tmp / "bin.blf"), str(tmp / "bin.blf"), ["not a .blf log"]),
    "text that is no log": lambda tmp, g: (can_replay(tmp / "notes.log"), str(tmp / "notes.log"), ["not a .log log"]),
    "CAN log of one frame": lambda tmp, g: (
        can_replay(p := _log_lines(tmp / "s.log", tmp / "one.log", lambda ls: ls[:1])), str(p),
        ["1 frame(s)", "not one tick", "too short"]),
    "CAN log of another bus": lambda tmp, g: (
        can_replay(p := _log_lines(tmp / "s.log", tmp / "foreign.log",
                                   lambda ls: [ln.replace(" can0 0", " can0 7").replace(" vcan0 0", " vcan0 7") for ln in ls])),
        str(p), ["no frame of the drive's CAN matrix", "3000 frame(s) with other identifiers"]),
    "an empty TRC log": lambda tmp, g: (can_replay(_text(tmp / "empty.trc", "")), "empty.trc", ["not a .trc log"]),
    "CAN log with a missing edge.yaml": lambda tmp, g: (
        [*can_replay(tmp / "s.log"), "--config", tmp / "nope.yaml"], str(tmp / "nope.yaml"), ["No such file"]),
}


# -- options: every numeric, list and path option, refused by the parser before any work -------------
Case = Callable[[Path, Path], tuple[list[object], str, list[str]]]


def _opt(command: list[str], option: str, value: str, fragment: str) -> Case:
    def case(tmp: Path, g: Path) -> tuple[list[object], str, list[str]]:
        argv = [str(a).replace("{run}", str(g)).replace("{tmp}", str(tmp)) for a in command]
        v = value.replace("{tmp}", str(tmp))
        return [*argv, option, v], f"argument {option}:", [fragment]
    return case


REPLAY = ["replay", "--model", str(TWO_NODE), "--run", "{run}"]
CALIBRATE = ["calibrate", "--model", str(TWO_NODE), "--run", "{run}", "--out", "{tmp}/c.yaml"]
CALIBRATE_NO_OUT = ["calibrate", "--model", str(TWO_NODE), "--run", "{run}"]
DISCOVER = ["discover", "--model", str(TWO_NODE), "--run", "{run}"]
SIMULATE = ["simulate", "--model", str(TWO_NODE), "--cycle", str(CYCLE), "--out", "{tmp}/o.csv"]
SIMULATE_NO_OUT = ["simulate", "--model", str(TWO_NODE), "--cycle", str(CYCLE)]
DEMO = ["demo"]
MONITOR = ["monitor"]
FLEET = ["fleet", "calibrate", "--model", str(TWO_NODE), "{run}", "--out", "{tmp}/f.parquet"]
FLEET_NO_OUT = ["fleet", "calibrate", "--model", str(TWO_NODE), "{run}"]
SCREEN = ["fleet", "screen", "--table", "{tmp}/t.parquet", "--out", "{tmp}/f.parquet"]

OPTION_CASES = {
    f"{c[0]}{' ' + c[1] if c[0] == 'fleet' else ''} {o} {v}": _opt(c, o, v, f)
    for c, o, v, f in [
        (REPLAY, "--threshold", "nan", "finite"), (REPLAY, "--threshold", "-1", ">= 0 K"),
        (REPLAY, "--threshold", "inf", "finite"), (REPLAY, "--threshold", "1K", "expected a number"),
        (REPLAY, "--decimate", "0", ">= 1"), (REPLAY, "--decimate", "-3", ">= 1"), (REPLAY, "--decimate", "1.5", "integer"),
        (REPLAY, "--period", "-5", "> 0 s"), (REPLAY, "--period", "0", "> 0 s"), (REPLAY, "--period", "nan", "finite"),
        (REPLAY, "--sensors", ",", "names"), (REPLAY, "--sensors", "winding_t,,housing", "empty name"),
        (REPLAY, "--max-substep", "0", "> 0 s"), (REPLAY, "--plot", "{tmp}/missing/f.png", "does not exist"),
        (REPLAY, "--out", "{tmp}/missing/f.csv", "does not exist"), (REPLAY, "--out", "{tmp}", "is a directory"),
        (CALIBRATE, "--generations", "-1", ">= 1"), (CALIBRATE, "--generations", "0", ">= 1"),
        (CALIBRATE, "--popsize", "0", ">= 1"), (CALIBRATE, "--decimate", "0", ">= 1"), (CALIBRATE, "--seed", "-1", ">= 0"),
        (CALIBRATE, "--patience", "0", ">= 1"), (CALIBRATE, "--max-time", "-1", "> 0 s"),
        (CALIBRATE, "--max-time", "nan", "finite"), (CALIBRATE, "--params", ",", "names"),
        (CALIBRATE, "--sensors", " , ", "names"), (CALIBRATE_NO_OUT, "--out", "/missing/dir/x.yaml", "does not exist"),
        (CALIBRATE_NO_OUT, "--out", "{tmp}", "is a directory"),
        (DISCOVER, "--train-fraction", "1.5", "< 1"), (DISCOVER, "--train-fraction", "0", "> 0"),
        (DISCOVER, "--train-fraction", "1", "< 1"), (DISCOVER, "--max-rounds", "0", ">= 1"),
        (DISCOVER, "--min-improvement", "1", "< 1"), (DISCOVER, "--min-improvement", "-0.1", ">= 0"),
        (DISCOVER, "--min-gain", "-1", ">= 0 K"), (DISCOVER, "--fit-step", "0", "> 0 s"),
        (DISCOVER, "--out", "{tmp}/bin.csv", "existing file"),
        (DISCOVER, "--model-out", "{tmp}/missing/m.yaml", "does not exist"),
        (DISCOVER, "--effects", ",", "names"),
        (SIMULATE, "--duration", "-10", "> 0 s"), (SIMULATE, "--duration", "0", "> 0 s"), (SIMULATE, "--noise", "-1", ">= 0 K"),
        (SIMULATE, "--resolution", "nan", "finite"), (SIMULATE, "--current-period", "0", ">= 0.001 s"),
        (SIMULATE, "--temperature-period", "-1", ">= 0.001 s"), (SIMULATE, "--t0", "1.7e12", "<= 1e+10 s"),
        (SIMULATE, "--seed", "-1", ">= 0"), (SIMULATE, "--fleet", "0", ">= 1"), (SIMULATE, "--faulty", "-1", ">= 0"),
        (SIMULATE_NO_OUT, "--out", "{tmp}/missing/o.csv", "does not exist"),
        (DEMO, "--speed", "0", "> 0"), (DEMO, "--speed", "-1", "> 0"), (DEMO, "--speed", "nan", "finite"),
        (DEMO, "--duration", "0", "> 0 s"), (DEMO, "--current-period", "0", ">= 0.001 s"),
        (DEMO, "--metrics-port", "70000", "<= 65535"), (DEMO, "--metrics-port", "-1", ">= 0"),
        (DEMO, "--metrics-address", "localhost", "not an IP address"),
        (DEMO, "--record", "{tmp}/missing/x.log", "does not exist"),
        (DEMO, "--state-dir", "{tmp}/bin.csv", "existing file"),
        (MONITOR, "--interval", "0", ">= 0.05 s"), (MONITOR, "--interval", "-1", ">= 0.05 s"),
        (MONITOR, "--count", "-1", ">= 1"), (MONITOR, "--count", "0", ">= 1"),
        (FLEET, "--workers", "0", ">= 1"), (FLEET, "--generations", "-1", ">= 1"), (FLEET, "--popsize", "0", ">= 1"),
        (FLEET, "--decimate", "0", ">= 1"), (FLEET_NO_OUT, "--out", "{tmp}/missing/f.parquet", "does not exist"),
        (SCREEN, "--threshold", "0", "> 0"), (SCREEN, "--threshold", "nan", "finite"),
        (["run", "--config", "{tmp}/edge.yaml"], "--log-level", "loud", "invalid choice"),
    ]
}
OPTION_CASES.update({
    "bench jacobian --repeat 0": _opt(["bench", "jacobian"], "--repeat", "0", ">= 1"),
    "bench service --hours 0": _opt(["bench", "service"], "--hours", "0", ">= 0.0166667 h"),
    "bench protection --jobs 0": _opt(["bench", "protection"], "--jobs", "0", ">= 1"),
    "calibrate --params naming no parameter": lambda tmp, g: ([*calibrate(g), "--params", "R_hw"], "--params 'R_hw'",
                                                              ["no such parameter", "did you mean 'R_wh'"]),
    "fleet calibrate --params naming no parameter": lambda tmp, g: (
        ["fleet", "calibrate", "--model", TWO_NODE, g, "--out", tmp / "f.parquet", "--params", "nope"], "--params 'nope'",
        ["no such parameter"]),
    "fleet evaluate --calibrated missing": lambda tmp, g: (
        ["fleet", "evaluate", "--model", TWO_NODE, g, "--out", tmp / "f.parquet", "--calibrated", tmp / "nope.parquet"],
        "--calibrated", ["nope.parquet", "no such result table"]),
    "fleet screen --table missing": lambda tmp, g: (
        ["fleet", "screen", "--table", tmp / "nope.parquet", "--out", tmp / "f.parquet"], "--table", ["no such result table"]),
    "simulate --fleet of a model without the faults' parameters": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--out", tmp / "fleet", "--fleet", "2", "--faulty", "1"],
        "--fleet", ["has no parameter(s)"]),
    "simulate --faulty above --fleet": lambda tmp, g: (
        ["simulate", "--model", ROOT / "config" / "machines" / "pm10kw.yaml", "--cycle", CYCLE, "--out", tmp / "fleet",
         "--fleet", "2", "--faulty", "5"], "--faulty 5", ["more than the --fleet"]),
    "simulate --out a directory": lambda tmp, g: (["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--out", tmp],
                                                   f"--out {tmp}", ["a directory"]),
    "simulate --out not a .csv": lambda tmp, g: (["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--out", tmp / "o.xyz"],
                                                 f"--out {tmp / 'o.xyz'}", ["a .csv file name"]),
    "simulate --effect unknown": lambda tmp, g: (["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--out", tmp / "o.csv",
                                                  "--effect", "nope"], "effect 'nope'", ["unknown"]),
    "simulate --set not a number": lambda tmp, g: (["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--out", tmp / "o.csv",
                                                    "--set", "R_wh=abc"], "--set 'R_wh=abc'", ["NAME=VALUE"]),
    "simulate --effect of an absurd magnitude": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--duration", "60", "--out", tmp / "o.csv",
         "--effect", "ambient_offset=dT=1e300"], "the simulated plant (with --effect)", ["diverges", "node 'winding'"]),
    "replay --set an unknown parameter": lambda tmp, g: (replay(g, "--set", "nope=1"), "--set nope=1", ["no parameter"]),
    "a cycle with a Latin-1 comment": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", _latin1(_copy(CYCLE, tmp / "c.yaml")), "--out", tmp / "o.csv"],
        "c.yaml", ["not UTF-8"]),
    "no such cycle": lambda tmp, g: (["simulate", "--model", TWO_NODE, "--cycle", tmp / "nope.yaml", "--out", tmp / "o.csv"],
                                     str(tmp / "nope.yaml"), ["no such file"]),
    "a model given as the cycle": lambda tmp, g: (["simulate", "--model", TWO_NODE, "--cycle", TWO_NODE, "--out",
                                                   tmp / "o.csv"], "two_node.yaml", ["segments"]),
    "a binary cycle": lambda tmp, g: (["simulate", "--model", TWO_NODE, "--cycle", tmp / "bin.yaml", "--out", tmp / "o.csv"],
                                      "bin.yaml", ["binary file"]),
})


def _copy(src: Path, dst: Path) -> Path:
    dst.write_bytes(src.read_bytes())
    return dst


OPTION_CASES["monitor --metrics not a URL"] = _opt(["monitor", "--once"], "--metrics", "notaurl", "http:// URL")
OPTION_CASES["fleet screen --table not Parquet"] = lambda tmp, g: (
    ["fleet", "screen", "--table", g, "--out", tmp / "f.parquet"], f"--table {g}", ["not a Parquet table"])
OPTION_CASES["monitor --bus without a bus"] = lambda tmp, g: (["monitor", "--bus", "--once"], "--bus", ["--interface"])
OPTION_CASES["monitor --bus where there is no such interface"] = lambda tmp, g: (
    ["monitor", "--bus", "--once", "--interface", "no_such_interface", "--channel", "x"], "--bus", ["no_such_interface"])

def _simulate(model: Path, tmp: Path) -> list[object]:
    """``simulate`` of ``model`` over the test cycle into the test's directory."""
    return ["simulate", "--model", model, "--cycle", CYCLE, "--out", tmp / "o.csv"]


def _log_law(tmp: Path) -> Path:
    """The two-node model with a copper loss plus ``log(speed_rpm / 600)``: -inf at standstill."""
    return _model(tmp, "log.yaml", "power: 3 * R_s * i_rms ** 2}", 'power: "3 * R_s * i_rms ** 2 + log(speed_rpm / 600)"}')


def _stopped(good: Path, out: Path) -> Path:
    """The good run with the machine at standstill for ten samples from sample 100."""
    header, rows = _table(good)
    i = header.index("speed_rpm")
    return _write(out, header, [[("0" if 100 <= k < 110 and j == i else v) for j, v in enumerate(r)]
                                for k, r in enumerate(rows)])


def _dir(path: Path) -> Path:
    path.mkdir(exist_ok=True)
    return path


def _text(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _cycle(tmp: Path, name: str, dt_s: str = "1", speed: str = "600") -> Path:
    return _text(tmp / name, f"name: c\ndt_s: {dt_s}\nsegments:\n  - {{duration_s: 60, speed_rpm: {speed}, torque_nm: 40}}\n")


def _no_sensor_data(good: Path, out: Path) -> Path:
    """The good run with every sensor column present but never measured (nan throughout)."""
    header, rows = _table(good)
    cols = [header.index(c) for c in ("winding_t", "housing")]
    return _write(out, header, [[("nan" if j in cols else v) for j, v in enumerate(r)] for r in rows])


def _flux_run(good: Path, out: Path) -> Path:
    """The good run with the columns ``flux`` reads (dq voltages, a magnet and a winding temperature)."""
    header, rows = _table(good)
    w = header.index("winding_t")
    return _write(out, [*header, "pm", "u_d_v", "u_q_v", "stator_winding"], [[*r, r[w], "-20", "150", r[w]] for r in rows])


#: refusals of cycles, torque constants, runs without sensor data, flux files and IPv6 groups
MORE_CASES: dict[str, Callable[[Path, Path], tuple[list[object], str, list[str]]]] = {
    "a cycle's ambient in kelvin": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", _text(tmp / "k.yaml", "name: c\nambient_c: 298.15\nsegments:\n"
                                                          "  - {duration_s: 60, speed_rpm: 600, torque_nm: 40}\n"),
         "--out", tmp / "o.csv"], "k.yaml", ["ambient_c", "looks like kelvin (25 degC)"]),
    "a cycle's ramp longer than its segment": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", _text(tmp / "r.yaml", "name: c\nsegments:\n"
                                                          "  - {duration_s: 60, speed_rpm: 600, torque_nm: 40}\n"
                                                          "  - {duration_s: 30, speed_rpm: 900, torque_nm: 40, ramp_s: 90}\n"),
         "--out", tmp / "o.csv"], "r.yaml", ["segments[1].ramp_s", "segment's duration_s (30 s)"]),
    "a negative capacity, simulate": lambda tmp, g: (
        _simulate(_model(tmp, "c.yaml", "capacity: C_w}", 'capacity: "-C_w"}'), tmp), "c.yaml",
        ["nodes[0].capacity", "must be positive, is -2000 J/K"]),
    "a capacity zero at a bound, replay": lambda tmp, g: (
        replay(g, model=_model(tmp, "c.yaml", "capacity: C_w}", 'capacity: "C_w - 200"}')), "c.yaml",
        ["nodes[0].capacity", "is 0 J/K at C_w = 200 (its min)"]),
    "a resistance of zero, simulate": lambda tmp, g: (
        _simulate(_model(tmp, "r.yaml", "r: R_ha}", "r: 0}"), tmp), "r.yaml",
        ["conductances[1].r", "must be positive, is 0 K/W"]),
    "a resistance given as g, simulate": lambda tmp, g: (
        _simulate(_model(tmp, "g.yaml", "r: R_ha}", "g: R_ha}"), tmp), "g.yaml",
        ["conductances[1].g", "parameter R_ha is in K/W, a resistance: give it as r: R_ha"]),
    "a capacity in kJ/K, simulate": lambda tmp, g: (
        _simulate(_model(tmp, "kj.yaml", "C_w: {value: 2000, min: 200, max: 20000, unit: J/K",
                         "C_w: {value: 2, min: 0.2, max: 20, unit: kJ/K"), tmp), "kj.yaml",
        ["parameters.C_w.unit", "give the values in J/K (2 kJ/K = 2000 J/K)"]),
    "an adaptable parameter nothing reads, replay": lambda tmp, g: (
        replay(g, model=_model(tmp, "u.yaml", "  R_s:", "  K_x: {value: 1, min: 0.5, max: 2, adaptable: true}\n  R_s:")),
        "u.yaml", ["parameters.K_x.adaptable", "nothing can be learned about it"]),
    "a loss law of log(0) at rest, simulate": lambda tmp, g: (
        _simulate(_log_law(tmp), tmp), "log.yaml",
        ["losses[0].power is -inf at speed_rpm = 0", "a logarithm of 0, a division by 0?", "no steady state"]),
    "a loss law of log(0) at some samples, replay": lambda tmp, g: (
        replay(_stopped(g, tmp / "stopped.csv"), model=_log_law(tmp)), "log.yaml",
        ["the open-loop prediction is not finite", "losses[0].power is -inf (a logarithm of 0", "at speed_rpm = 0"]),
    "a model without sensors, replay": lambda tmp, g: (
        replay(g, model=_model(tmp, "ns.yaml", "sensors:\n  winding_t: {node: winding}\n  housing: {node: housing_n}\n", "")),
        "ns.yaml", ["sensors: model two_node declares no sensors", "can be compared with it"]),
    "simulate --effect with a negative time constant": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--out", tmp / "o.csv", "--effect",
         "sensor_lag:winding_t=tau=-5"], "--effect 'sensor_lag:winding_t=tau=-5'", ["tau must be > 0 s"]),
    "a cycle value not a number": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", _cycle(tmp, "nan.yaml", speed=".nan"), "--out", tmp / "o.csv"],
        "nan.yaml", ["segments[0].speed_rpm", "finite number"]),
    "a cycle stepped in ns": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", _cycle(tmp, "ns.yaml", dt_s="1e-9"), "--out", tmp / "o.csv"],
        "ns.yaml", ["dt_s", "6e+10 samples", "in seconds"]),
    "simulate --duration of 1e12 s": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--duration", "1e12", "--out", tmp / "o.csv"],
        "--duration 1e+12 s", ["1e+12 samples", "2 kB a sample"]),
    "simulate --duration of 1e7 s": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--duration", "1e7", "--out", tmp / "o.csv"],
        "--duration 1e+07 s", ["1e+07 samples", "more than 1e+06"]),
    "simulate --format can --duration of 1e12 s": lambda tmp, g: (
        ["simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--duration", "1e12", "--format", "can", "--out",
         tmp / "o.log"], "--duration 1e+12 s", ["samples", "in seconds"]),
    "torque constant zero, simulate": lambda tmp, g: (
        ["simulate", "--model", _model(tmp, "kt.yaml", "kt_nm_per_arms: 5.6", "kt_nm_per_arms: 0"), "--cycle", CYCLE,
         "--out", tmp / "o.csv"], "kt.yaml", ["drive.kt_nm_per_arms", "must be positive"]),
    "torque constant negative, replay": lambda tmp, g: (
        replay(g, model=_model(tmp, "kt.yaml", "kt_nm_per_arms: 5.6", "kt_nm_per_arms: -5.6")), "kt.yaml",
        ["drive.kt_nm_per_arms", "must be positive"]),
    "no torque constant, simulate": lambda tmp, g: (
        ["simulate", "--model", _model(tmp, "nokt.yaml", "drive:\n  kt_nm_per_arms: 5.6\n", ""), "--cycle", CYCLE,
         "--out", tmp / "o.csv"], "nokt.yaml", ["--model", "drive.kt_nm_per_arms is missing"]),
    "no sensor ever measured, discover": lambda tmp, g: (
        ["discover", "--model", TWO_NODE, "--run", p := _no_sensor_data(g, tmp / "nos.csv"), "--no-report"], str(p),
        ["none of the sensors", "measured sample"]),
    "ten samples, discover": lambda tmp, g: (
        ["discover", "--model", TWO_NODE, "--run", p := _write(tmp / "ten.csv", _table(g)[0], _table(g)[1][:10]),
         "--no-report"], str(p), ["10 samples", "too few for discovery"]),
    "flux score: a JSON list": lambda tmp, g: (
        ["flux", "score", _text(tmp / "l.json", "[1, 2]"), _flux_run(g, tmp / "f.csv")], "l.json",
        ["holds a list, not an object"]),
    "flux score: a JSON object without the parameters": lambda tmp, g: (
        ["flux", "score", _text(tmp / "e.json", "{}"), _flux_run(g, tmp / "f.csv")], "e.json",
        ["flux model: no params, sigma, pole_pairs"]),
    "flux calibrate --pole-pairs 0": lambda tmp, g: (
        ["flux", "calibrate", _flux_run(g, tmp / "f.csv"), "--out", tmp / "f.json", "--pole-pairs", "0"], "--pole-pairs",
        ["integer >= 1"]),
    "flux calibrate with a negative resistance prior": lambda tmp, g: (
        ["flux", "calibrate", _flux_run(g, tmp / "f.csv"), "--out", tmp / "f.json", "--pole-pairs", "4", "--magnet-column",
         "pm", "--prior", "r20=-0.25,0.05"], "--prior r20=-0.25,0.05", ["r20 is positive (ohm), got a MEAN of -0.25"]),
    "flux calibrate on a run without voltages": lambda tmp, g: (
        ["flux", "calibrate", g, "--out", tmp / "f.json", "--pole-pairs", "4", "--magnet-column", "housing"], str(g),
        ["no column(s) u_d_v, u_q_v"]),
    "edge.yaml: an IPv6 udp_multicast group": lambda tmp, g: (
        check(_edge(tmp, lambda r: r["bus"].update(interface="udp_multicast", channel="ff15::7468:6572", port=43113))),
        "bus.channel", ["IPv6 group", "239.74.163.2"]),
}

CASES.update(RUN_CASES)
CASES.update(MODEL_CASES)
CASES.update(CONFIG_CASES)
CASES.update(LOG_CASES)
CASES.update(OPTION_CASES)
CASES.update(MORE_CASES)


@pytest.fixture(scope="session")
def can_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated recording of the pm10kw drive (candump -L and BLF, 60 s), and a BLF cut in half."""
    d = tmp_path_factory.mktemp("logs")
    for suffix in (".log", ".blf"):
        r = te("simulate", "--model", ROOT / "config" / "machines" / "pm10kw.yaml", "--cycle", CYCLE, "--duration", 60,
               "--format", "can", "--out", d / f"s{suffix}")
        assert r.returncode == 0, r.stderr
    data = (d / "s.blf").read_bytes()
    (d / "half.blf").write_bytes(data[: len(data) // 2])
    return d


@pytest.fixture
def files(tmp_path: Path, good_run: Path) -> Path:
    """The test's directory, with the files no mutation of the good run makes."""
    (tmp_path / "bin.csv").write_bytes(bytes(range(256)) * 40)
    (tmp_path / "bin.log").write_bytes(bytes(range(256)) * 40)
    (tmp_path / "u16.csv").write_bytes(good_run.read_text().encode("utf-16"))
    (tmp_path / "log.csv").write_text("(1700000000.000000) can0 101#0000000000000000\n"
                                      "(1700000000.010000) can0 101#0100000000000000\n")
    (tmp_path / "bin.yaml").write_bytes(bytes(range(256)) * 40)
    (tmp_path / "bin.blf").write_bytes(bytes(range(256)) * 40)
    (tmp_path / "plain.log").write_text("  can0  101   [8]  00 00 00 00 00 00 00 00\n"
                                        "  can0  101   [8]  01 00 00 00 00 00 00 00\n")
    (tmp_path / "timed.log").write_text(" (1795782237.000000)  can0  2A0   [8]  30 02 C8 00 0F 00 00 80\n"
                                        " (1795782237.010000)  can0  0A0   [8]  00 00 17 02 7B 01 00 6F\n")
    (tmp_path / "notes.log").write_text("hello\nworld\n")
    (tmp_path / "notes.txt").write_text("hello\n")
    (tmp_path / "edge.yaml").write_text("")
    return tmp_path


@pytest.fixture
def logs_here(files: Path, can_logs: Path) -> Path:
    """The test's directory with the simulated CAN logs beside the other files."""
    for f in can_logs.iterdir():
        (files / f.name).symlink_to(f)
    return files


def test_the_table_has_at_least_150_cases():
    assert len(CASES) >= 150


#: Cases that run a fit or a discovery before their refusal could come (the rest take well under a second)
SLOW = {"time in ms, calibrate", "sensor in kelvin, second run of calibrate", "kelvin, discover", "kelvin, fleet calibrate",
        "overflowing loss law, discover", "a 1e6 A sample, discover", "tab-separated export, discover",
        "time in ms, discover", "model with a Latin-1 comment, fleet", "no such run, fleet"}


@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.slow) if c in SLOW else c for c in CASES])
def test_bad_input_is_refused_in_one_line(case, logs_here, good_run):
    files = logs_here
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


def test_a_sensor_never_measured_is_said_so_not_scored_nan(good_run, tmp_path):
    """A sensor column with no reading at all (every cell nan) is not an error of the run (the
    other sensor scores), but its score says so; the mean is over the measured sensors."""
    header, rows = _table(good_run)
    j = header.index("housing")
    run = _write(tmp_path / "nohousing.csv", header, [[*r[:j], "nan", *r[j + 1:]] for r in rows])
    r = te(*replay(run))
    assert r.returncode == 0, r.stderr
    table = r.stdout.splitlines()[-4:]
    assert table[2].split() == ["housing", "not", "measured"]
    assert table[1].split()[0] == "winding_t" and table[3].split()[1] == table[1].split()[1]  # mean = the one score
    assert "nan" not in r.stdout.split()


# -- state files: read by the service at start; each refusal one line naming the field ------------------
def _state(m, **fields) -> bytes:
    n = len(m.nodes)
    raw = {"format": FORMAT, "version": VERSION, "model": m.name, "saved_at": 1000.0, "parameters": {},
           "nodes": list(m.nodes), "T": [30.0] * n, "sigma": [0.5] * n, "T_pred": [30.0] * n,
           "inputs": {"ambient_c": 25.0, "i_rms": 0.0, "speed_rpm": 0.0}}
    raw.update(fields)
    return json.dumps(raw).encode()


STATE_CASES = {
    "nodes in kelvin": (lambda m: _state(m, T=[300.15, 310.0]), ["T:", "looks like kelvin"]),
    "a cold machine in kelvin": (lambda m: _state(m, T=[293.15, 293.15], T_pred=[293.15, 293.15]), ["looks like kelvin"]),
    "one node at 900 degC": (lambda m: _state(m, T=[30.0, 900.0]), ["T[1] (node 'housing_n')", "outside the plausible"]),
    "one node in kelvin": (lambda m: _state(m, T=[30.0, 303.15]), ["T[1] (node 'housing_n')", "looks like kelvin"]),
    "one node at -99 degC": (lambda m: _state(m, T=[-99.0, 30.0]), ["T[0] (node 'winding')", "outside the plausible"]),
    "prediction in kelvin": (lambda m: _state(m, T_pred=[303.0, 303.0]), ["T_pred", "kelvin"]),
    "ambient in kelvin": (lambda m: _state(m, inputs={"ambient_c": 298.15}), ["inputs.ambient_c", "looks like kelvin"]),
    "current in mA": (lambda m: _state(m, inputs={"i_rms": 20000.0}), ["inputs.i_rms", "looks like mA"]),
    "negative RMS current": (lambda m: _state(m, inputs={"i_rms": -3.0}), ["inputs.i_rms", "outside the plausible 0"]),
    "not UTF-8": (lambda m: b'{"format": "\xfc"}', ["not UTF-8 text (byte 12)"]),
    "another model's state": (lambda m: _state(m, model="pm10kw"), ["belongs to model"]),
}


@pytest.mark.parametrize("case", list(STATE_CASES))
def test_an_implausible_state_file_is_refused_in_one_line(case):
    model = load_model(TWO_NODE)
    make, fragments = STATE_CASES[case]
    with pytest.raises(StateError) as err:
        decode(make(model), model)
    line = str(err.value)
    assert len(line.splitlines()) == 1, line
    for f in fragments:
        assert f in line, (f, line)


def test_a_plausible_state_file_loads():
    """The counter-case of the table: the same state in degC is taken."""
    model = load_model(TWO_NODE)
    assert decode(_state(model), model).T == [30.0, 30.0]


#: the table of refusals in the commands guide: (case, command, exit status, the line on stderr)
GUIDE = ROOT / "docs" / "guide" / "commands.md"
GUIDE_ROWS = re.findall(r"^\| (.+?) \| `(.+?)` \| (\d) \| `(.+)` \|$", GUIDE.read_text(encoding="utf-8"), re.M)


def test_the_guides_table_has_rows():
    assert len(GUIDE_ROWS) >= 30 and all(case in CASES for case, *_ in GUIDE_ROWS)


@pytest.mark.parametrize("case, command, status, shown",
                         [pytest.param(*row, marks=pytest.mark.slow) if row[0] in SLOW else row for row in GUIDE_ROWS])
def test_the_guides_table_shows_what_each_case_prints(case, command, status, shown, logs_here, good_run):
    """Each row of the commands guide's table is the line its case prints now (the test's directory
    and the checkout left out of paths), so the manual cannot drift from the messages."""
    argv, _, _ = CASES[case](logs_here, good_run)
    r = te_here(*argv)
    line = r.stderr.strip()
    for where in (logs_here, good_run.parent, ROOT):
        line = line.replace(f"{where}/", "")
    assert (str(r.returncode), str(argv[0])) == (status, command)
    assert line == shown.replace("\\|", "|"), f"docs/guide/commands.md row {case!r} shows\n  {shown}\nthe case prints\n  {line}"

