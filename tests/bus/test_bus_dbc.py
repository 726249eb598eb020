"""dbc/thermal_edge.dbc against the CAN matrix (parsed from can-matrix.md, not from the DBC)."""

from __future__ import annotations

import math
import re

import cantools
import pytest
from bus_testlib import DBC_PATH, MATRIX_PATH

from thermal_edge.bus import DerateReason, SensorStatus, TeState
from thermal_edge.bus.frames import DEFAULT_DBC_PATH


@pytest.fixture(scope="module")
def db():
    return cantools.database.load_file(str(DBC_PATH), strict=True)


def _norm(label: str) -> str:
    return re.sub(r"[\s\-]+", "_", label.strip().lower())


def _enum_from_text(text: str) -> dict[int, str]:
    return {int(n): _norm(label) for n, label in re.findall(r"(\d+)\s+([A-Za-z][A-Za-z \-]*?)(?=,|$|\.)", text)}


def _unit(matrix_unit: str) -> str:
    first = matrix_unit.split()[0].rstrip(":")
    return {"°C": "degC"}.get(first, first)


def test_default_path_is_the_project_dbc():
    """The package ships the DBC; the repository's dbc/thermal_edge.dbc is the same file."""
    assert DEFAULT_DBC_PATH.resolve() == DBC_PATH.resolve()
    assert DBC_PATH.is_file() and DEFAULT_DBC_PATH.is_file()


def test_strict_load_and_nodes(db, added_frames):
    assert {n.name for n in db.nodes} == {"INV", "TE"}
    assert len(db.messages) == 8 + len({r.frame for r in added_frames})


def test_frames_match_matrix(db, matrix):
    frames = {(r.frame_id, r.frame, r.sender, r.cycle_ms) for r in matrix}
    assert len(frames) == 8
    for frame_id, name, sender, cycle_ms in frames:
        msg = db.get_message_by_frame_id(frame_id)
        assert msg.name == name
        assert msg.length == 8
        assert not msg.is_extended_frame
        assert msg.senders == [sender]
        assert msg.cycle_time == cycle_ms
        assert msg.dbc.attributes["GenMsgCycleTime"].value == cycle_ms
        receiver = "TE" if sender == "INV" else "INV"
        for sig in msg.signals:
            assert sig.receivers == [receiver], sig.name
    extra = {m.frame_id for m in db.messages} - {f[0] for f in frames}
    assert all(0x2D0 <= fid <= 0x2FF for fid in extra), "extra frames must be in 0x2D0-0x2FF"


def test_signals_match_matrix(db, matrix):
    for row in matrix:
        sig = db.get_message_by_name(row.frame).get_signal_by_name(row.name)
        assert sig.start == row.start, row.name
        assert sig.length == row.bits, row.name
        assert sig.is_signed is row.signed, row.name
        assert sig.byte_order == "little_endian", row.name
        assert float(sig.scale) == pytest.approx(row.factor, rel=0, abs=1e-12), row.name
        assert float(sig.offset) == pytest.approx(row.offset, rel=0, abs=1e-12), row.name
        assert sig.unit == _unit(row.unit), row.name


def test_no_signal_outside_matrix(db, matrix):
    for name in {r.frame for r in matrix}:
        msg = db.get_message_by_name(name)
        expected = {r.name for r in matrix if r.frame == name} | {f"{name}_Counter", f"{name}_CRC"}
        assert {s.name for s in msg.signals} == expected


def test_counter_and_crc_signals(db):
    for msg in db.messages:
        counter = msg.get_signal_by_name(f"{msg.name}_Counter")
        crc = msg.get_signal_by_name(f"{msg.name}_CRC")
        assert (counter.start, counter.length, counter.is_signed, counter.byte_order) == (48, 4, False, "little_endian")
        assert (crc.start, crc.length, crc.is_signed, crc.byte_order) == (56, 8, False, "little_endian")
        assert (counter.minimum, counter.maximum) == (0, 15)
        assert (crc.minimum, crc.maximum) == (0, 255)


def test_ranges(db, matrix):
    """Min/max = the raw range of the field, scaled; temperatures stop below 0xFFF; enums at their last value."""
    for row in matrix:
        sig = db.get_message_by_name(row.frame).get_signal_by_name(row.name)
        lo, hi = (-(2 ** (row.bits - 1)), 2 ** (row.bits - 1) - 1) if row.signed else (0, 2**row.bits - 1)
        if row.unit.startswith("°C"):
            hi = 0xFFE  # 0xFFF = no value
        if row.unit.startswith("enum"):
            hi = max(_enum_from_text(row.unit.split(":", 1)[1]))
        assert sig.minimum == pytest.approx(lo * row.factor + row.offset, abs=1e-9), row.name
        assert sig.maximum == pytest.approx(hi * row.factor + row.offset, abs=1e-9), row.name
    temp = db.get_message_by_name("INV_StatorTemps").get_signal_by_name("INV_T_WindingSlot")
    assert (temp.minimum, temp.maximum) == (-50, pytest.approx(359.4))


def test_value_tables(db, matrix):
    text = MATRIX_PATH.read_text(encoding="utf-8")
    status_line = re.search(r"Sensor status[^:]*:\s*(.*)", text).group(1)
    status = _enum_from_text(status_line)
    assert status == {0: "valid", 1: "open_circuit", 2: "short_circuit", 3: "not_fitted"}
    enums = {r.name: _enum_from_text(r.unit.split(":", 1)[1]) for r in matrix if r.unit.startswith("enum")}
    for row in matrix:
        sig = db.get_message_by_name(row.frame).get_signal_by_name(row.name)
        if row.unit == "status":
            assert {int(k): str(v) for k, v in sig.choices.items()} == status, row.name
        elif row.name in enums:
            assert {int(k): str(v) for k, v in sig.choices.items()} == enums[row.name], row.name
    assert {m.value: _norm(m.name) for m in SensorStatus} == status
    assert {m.value: _norm(m.name) for m in DerateReason} == enums["TE_DerateReason"]
    assert {m.value: _norm(m.name) for m in TeState} == enums["TE_State"]


def test_no_value_code_of_temperatures(db, matrix):
    for row in matrix:
        if not row.unit.startswith("°C"):
            continue
        sig = db.get_message_by_name(row.frame).get_signal_by_name(row.name)
        assert sig.dbc.attributes["NoValueRaw"].value == 0xFFF, row.name
        assert "0xFFF" in sig.comment and "NaN" in sig.comment, row.name
        assert str(sig.choices[0xFFF]) == "no_value"


def test_comments_everywhere(db):
    for msg in db.messages:
        assert msg.comment and len(msg.comment) > 10, msg.name
        for sig in msg.signals:
            assert sig.comment and len(sig.comment) > 10, sig.name


def test_attribute_definitions_in_file():
    text = DBC_PATH.read_text(encoding="ascii")
    assert re.search(r'^BA_DEF_ BO_ "GenMsgCycleTime" INT 0 \d+;', text, re.M)
    assert re.search(r'^BA_DEF_DEF_ "GenMsgCycleTime" 0;', text, re.M)
    n_frames = len(cantools.database.load_file(str(DBC_PATH)).messages)
    assert len(re.findall(r'^BA_ "GenMsgCycleTime" BO_ \d+ \d+;', text, re.M)) == n_frames
    assert re.search(r"^BU_: INV TE\s*$", text, re.M)
    assert re.search(r"^VAL_TABLE_ SensorStatus ", text, re.M)


def test_added_frames_match_the_additions_table(db, added_frames):
    """The appended frames as docs/can-matrix-additions.md states them: ID in 0x2D0-0x2FF, sender,
    cycle, every signal's layout and scaling, and nothing else but the counter and CRC."""
    for row in added_frames:
        assert 0x2D0 <= row.frame_id <= 0x2FF, row.frame
        msg = db.get_message_by_frame_id(row.frame_id)
        assert (msg.name, msg.senders, msg.cycle_time, msg.length) == (row.frame, [row.sender], row.cycle_ms, 8)
        sig = msg.get_signal_by_name(row.name)
        assert (sig.start, sig.length, sig.is_signed, sig.byte_order) == (row.start, row.bits, row.signed, "little_endian")
        assert float(sig.scale) == pytest.approx(row.factor) and float(sig.offset) == pytest.approx(row.offset)
        assert sig.unit == _unit(row.unit)
        assert sig.receivers == ["TE" if row.sender == "INV" else "INV"]
        lo, hi = (-(2 ** (row.bits - 1)), 2 ** (row.bits - 1) - 1) if row.signed else (0, 2**row.bits - 1)
        assert (sig.minimum, sig.maximum) == (pytest.approx(lo * row.factor), pytest.approx(hi * row.factor))
    for name in {r.frame for r in added_frames}:
        expected = {r.name for r in added_frames if r.frame == name} | {f"{name}_Counter", f"{name}_CRC"}
        assert {s.name for s in db.get_message_by_name(name).signals} == expected


def test_matrix_parser_sees_both_directions(matrix):
    assert {r.sender for r in matrix} == {"INV", "TE"}
    assert math.isclose(sum(r.bits for r in matrix if r.frame == "INV_StatorTemps"), 42)
