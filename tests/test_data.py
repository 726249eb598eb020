"""Run files: what a test bench exports is read or refused in one line naming file, line and column."""
from __future__ import annotations

import math

import numpy as np
import pytest

from thermal_edge.data import RunError, check_run, describe, read_run

GOOD = "t,i_rms,speed_rpm,ambient_c,housing\n0,10,900,25,30.5\n1,11,900,25,30.6\n2,12,900,25,30.7\n"


def test_utf8_and_windows_1252_exports_read_alike(tmp_path):
    header = "# Prüfstand 3, Temperaturen in °C\n"
    (tmp_path / "u.csv").write_bytes((header + GOOD).encode("utf-8"))
    (tmp_path / "w.csv").write_bytes((header + GOOD).encode("cp1252"))
    (tmp_path / "b.csv").write_bytes(b"\xef\xbb\xbf" + GOOD.encode())  # UTF-8 with a BOM (Excel)
    runs = [read_run(tmp_path / n) for n in ("u.csv", "w.csv", "b.csv")]
    for r in runs:
        assert list(r.columns) == ["i_rms", "speed_rpm", "ambient_c", "housing"]
        np.testing.assert_array_equal(r.t, [0, 1, 2])
        np.testing.assert_array_equal(r.columns["housing"], [30.5, 30.6, 30.7])


@pytest.mark.parametrize("name, content, expected", [
    ("binary", b"\x00\x01\x02CAN\x00" * 100, "binary file"),
    ("empty", b"", "empty"),
    ("header only", b"t,i_rms\n", "no data rows"),
    ("comments only", b"# nothing\n\n", "empty"),
    ("text in a number", GOOD.replace("30.6", "30.6x").encode(), "line 3, column 'housing': not a number"),
    ("short row", GOOD.replace("1,11,900,25,30.6", "1,11,900").encode(), "line 3: 3 values"),
    ("duplicate column", b"t,a,a\n0,1,2\n1,1,2\n", "'a'"),
    ("no time column", b"i_rms,housing\n1,2\n3,4\n", "no column 't'"),
    ("time backwards", b"t,x\n0,1\n2,1\n1,1\n", "line 4, column 't'"),
    ("infinite value", GOOD.replace("30.6", "inf").encode(), "line 3, column 'housing'"),
])
def test_a_bad_file_is_refused_naming_where(tmp_path, name, content, expected):
    path = tmp_path / "run.csv"
    path.write_bytes(content)
    with pytest.raises(RunError) as info:
        read_run(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and expected in msg and "\n" not in msg


def test_a_directory_is_refused(tmp_path):
    with pytest.raises(RunError, match="is a directory"):
        read_run(tmp_path)


def _run(tmp_path, t, housing):
    path = tmp_path / "r.csv"
    rows = "\n".join(f"{a},{b}" for a, b in zip(t, housing))
    path.write_text("t,housing\n" + rows + "\n")
    return read_run(path)


def test_units_that_cannot_be_right_are_refused(tmp_path):
    n = 50
    t = np.arange(n, dtype=float)
    ok = _run(tmp_path, t, 30 + 0.1 * t)
    check_run(ok, ["housing"])  # plausible: passes
    with pytest.raises(RunError, match="milliseconds"):
        check_run(_run(tmp_path, 1000 * t, 30 + 0.1 * t), ["housing"])
    with pytest.raises(RunError, match="kelvin"):
        check_run(_run(tmp_path, t, 303.15 + 0.1 * t), ["housing"])
    bad = 30 + 0.1 * t
    bad[17] = -90.0
    with pytest.raises(RunError, match=r"sample 18 \(t = 17 s\)"):
        check_run(_run(tmp_path, t, bad), ["housing"])
    nan = np.full(n, math.nan)  # a column that was never measured is not judged
    check_run(_run(tmp_path, t, nan), ["housing"])


def test_the_summary_names_period_duration_columns_and_ranges(tmp_path):
    path = tmp_path / "run.csv"
    path.write_text(GOOD)
    text = describe(read_run(path), ["i_rms", "housing"])
    assert "3 samples every 1 s" in text and "i_rms 10..12" in text and "housing 30.5..30.7" in text
    assert "ignored: speed_rpm, ambient_c" in text


def test_the_encoding_policy_names_the_first_byte_that_is_not_utf8(tmp_path):
    """Line, column and byte offset of the first byte that is not UTF-8, counted here another way
    (the text before it); runs fall back to Windows-1252, models and configurations do not."""
    import pytest

    from thermal_edge.data import read_run
    from thermal_edge.lptn import ModelError, load_model

    text = "name: x\ninputs: {a: {}}\n# Gehäuse: Kühlung\n"
    raw = text.encode("latin-1")
    bad = raw.index("ä".encode("latin-1"))
    line = raw[:bad].count(b"\n") + 1
    column = bad - raw[:bad].rfind(b"\n")
    (tmp_path / "m.yaml").write_bytes(raw)
    with pytest.raises(ModelError, match=rf"^m\.yaml: line {line}, column {column} \(byte {bad}\): not UTF-8 \(byte 0xe4\)"):
        load_model(tmp_path / "m.yaml")
    (tmp_path / "r.csv").write_bytes("# Gehäuse\nt,x\n0,1\n1,2\n".encode("latin-1"))
    assert read_run(tmp_path / "r.csv").columns["x"].tolist() == [1.0, 2.0]
