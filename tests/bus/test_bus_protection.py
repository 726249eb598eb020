"""Declared end-to-end protection of another inverter's frames: counters of other widths and
byte orders, CRC-8s of the catalogue over a data ID, none; the service's own frames kept; frames
the codec cannot read left out with the reason. Frames are built independently (cantools for the
layout, crccheck for the CRC)."""
from __future__ import annotations

import math
from pathlib import Path

import cantools
import pytest
from bus_testlib import DBC_PATH
from crccheck import crc as crccheck

from thermal_edge.bus import DbcError, FrameCodec
from thermal_edge.bus.codec import ProtectionError
from thermal_edge.bus.crc import CRC8_ALGORITHMS, crc8
from thermal_edge.bus.protection import FrameProtection

DMC_DBC = """VERSION ""

NS_ :

BS_:

BU_: DMC VCU

BO_ 256 DMC_Fast: 8 DMC
 SG_ DMC_Crc : 0|8@1+ (1,0) [0|255] "" VCU
 SG_ DMC_Alive : 8|4@1+ (1,0) [0|15] "" VCU
 SG_ DMC_Value : 16|16@1- (0.1,0) [-3276.8|3276.7] "A" VCU

BO_ 257 DMC_Moto: 4 DMC
 SG_ DMC_Speed : 7|16@0- (0.5,0) [-16384|16383.5] "rpm" VCU
 SG_ DMC_Count : 23|3@0+ (1,0) [0|7] "" VCU

BO_ 258 DMC_Plain: 2 DMC
 SG_ DMC_Temp : 0|16@1+ (0.1,-40) [-40|6513.5] "degC" VCU

BO_ 2365587712 DMC_Ext: 8 DMC
 SG_ DMC_Code : 0|16@1+ (1,0) [0|65535] "" VCU

BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 256 10;
BA_ "GenMsgCycleTime" BO_ 257 10;
BA_ "GenMsgCycleTime" BO_ 258 100;
"""
PROTECTION = {
    "DMC_Fast": FrameProtection(counter="DMC_Alive", crc="DMC_Crc", crc_algorithm="crc8_autosar", data_id=0x0321),
    "DMC_Moto": FrameProtection(counter="DMC_Count"),
    "DMC_Plain": FrameProtection(),
}
REFERENCE = {"crc8_sae_j1850": crccheck.Crc8SaeJ1850, "crc8_autosar": crccheck.Crc8Autosar,
             "crc8_gsm_a": crccheck.Crc8GsmA, "crc8_smbus": crccheck.Crc8Smbus}


@pytest.fixture
def dmc(tmp_path: Path) -> Path:
    p = tmp_path / "dmc.dbc"
    p.write_text(DMC_DBC)
    return p


def fast(db, value: float, alive: int, *, good_crc: bool = True) -> bytes:
    data = bytearray(db.get_message_by_name("DMC_Fast").encode({"DMC_Crc": 0, "DMC_Alive": alive, "DMC_Value": value}))
    data[0] = crccheck.Crc8Autosar.calc(bytes([0x21, 0x03]) + bytes(data[1:])) ^ (0 if good_crc else 1)
    return bytes(data)


@pytest.mark.parametrize("name", sorted(CRC8_ALGORITHMS))
def test_every_crc_of_the_catalogue_is_crcchecks(name):
    ref = REFERENCE[name]
    assert crc8(name, b"123456789") == CRC8_ALGORITHMS[name].check == ref.calc(b"123456789")
    for n in range(0, 40, 3):
        data = bytes((i * 37 + n) % 256 for i in range(n))
        assert crc8(name, data) == ref.calc(data)


def test_declared_counter_and_crc_are_checked(dmc):
    db = cantools.database.load_file(str(dmc))
    codec = FrameCodec(dmc, protection=PROTECTION)
    got = codec.decode(0x100, fast(db, -12.3, 0), timestamp=1.0)
    assert got is not None and got.signals == {"DMC_Value": -12.3} and got.counter == 0
    assert codec.decode(0x100, fast(db, 5.0, 1, good_crc=False), timestamp=1.01) is None
    assert codec.stats.dropped["crc"] == 1
    assert codec.decode(0x100, fast(db, 5.0, 0), timestamp=1.02) is None  # counter repeated
    assert codec.stats.dropped["counter_repeat"] == 1
    got = codec.decode(0x100, fast(db, 5.0, 4), timestamp=1.04)  # 1, 2, 3 missing
    assert got is not None and got.lost_before == 3 and codec.stats.lost == 3
    # the codec's own encoding is the independent one, byte for byte
    assert codec.encode("DMC_Fast", {"DMC_Value": -12.3}, counter=7) == fast(db, -12.3, 7)


def test_a_3_bit_big_endian_counter_wraps_at_8(dmc):
    db = cantools.database.load_file(str(dmc))
    moto = db.get_message_by_name("DMC_Moto")
    codec = FrameCodec(dmc, protection=PROTECTION)
    seen = []
    for k, count in enumerate([5, 6, 7, 0, 1, 3]):  # a wrap, then one frame missing
        got = codec.decode(0x101, moto.encode({"DMC_Speed": -1500.5 + k, "DMC_Count": count}), timestamp=k * 0.01)
        assert got is not None
        seen.append((got.signals["DMC_Speed"], got.counter, got.lost_before))
    assert seen == [(-1500.5, 5, 0), (-1499.5, 6, 0), (-1498.5, 7, 0), (-1497.5, 0, 0), (-1496.5, 1, 0), (-1495.5, 3, 1)]
    data = codec.encode("DMC_Moto", {"DMC_Speed": 42.5}, counter=6)
    assert moto.decode(data) == {"DMC_Speed": 42.5, "DMC_Count": 6}
    with pytest.raises(ValueError, match="outside 0..7"):
        codec.encode("DMC_Moto", {"DMC_Speed": 1.0}, counter=8)


def test_an_unprotected_frame_is_taken_as_it_comes(dmc):
    """What protection none cannot see: a repeated frame and a corrupted one are both readings."""
    db = cantools.database.load_file(str(dmc))
    plain = db.get_message_by_name("DMC_Plain")
    codec = FrameCodec(dmc, protection=PROTECTION)
    data = plain.encode({"DMC_Temp": 85.3})
    assert [codec.decode(0x102, data).signals for _ in range(3)] == [{"DMC_Temp": 85.3}] * 3
    bad = bytes([data[0] ^ 0x10, data[1]])
    assert codec.decode(0x102, bad).signals["DMC_Temp"] != 85.3
    assert codec.decode(0x102, data[:1]) is None and codec.stats.dropped["dlc"] == 1  # the DBC's length still holds
    assert codec.protection("DMC_Plain") == FrameProtection() and codec.protection("DMC_Plain").unseen()


def test_frames_neither_declared_nor_the_matrixs_say_so(dmc):
    codec = FrameCodec(dmc)
    assert codec.protection("DMC_Fast") is None
    assert "nor a declared protection" in codec.protection_problem("DMC_Fast")
    assert "29-bit" in (codec.unsupported("DMC_Ext") or "")
    assert 0x8D000000 not in codec.frame_ids() and codec.decode(0x100, bytes(8)) is not None  # read, unchecked


@pytest.mark.parametrize("protection, match", [
    ({"DMC_Fsat": FrameProtection()}, "no frame 'DMC_Fsat' to protect .*did you mean 'DMC_Fast'"),
    ({"DMC_Fast": FrameProtection(counter="DMC_Alvie")}, "no signal 'DMC_Alvie'"),
    ({"DMC_Fast": FrameProtection(crc="DMC_Value")}, "must be an unsigned 8-bit signal filling one payload byte"),
    ({"DMC_Moto": FrameProtection(crc="DMC_Count")}, "must be an unsigned 8-bit signal"),
    ({"DMC_Fast": FrameProtection(counter="DMC_Value")}, "must be an unsigned integer"),
    ({"DMC_Ext": FrameProtection()}, "29-bit identifier"),
    ({"TE_Limits": FrameProtection()}, "the service's own frame"),
])
def test_a_protection_that_does_not_fit_is_refused_naming_the_frame(dmc, protection, match):
    with pytest.raises(ProtectionError, match=match) as err:
        FrameCodec(dmc, protection=protection, service_frames=True)
    assert err.value.frame == next(iter(protection))


def test_the_services_own_frames_come_from_the_shipped_dbc(dmc, tmp_path):
    codec = FrameCodec(dmc, protection=PROTECTION, service_frames=True)
    shipped = FrameCodec()
    for name in ("TE_Limits", "TE_Estimates", "TE_Forecast", "TE_Status"):
        assert codec.frame_id(name) == shipped.frame_id(name)
        signals = {s: 1.0 for s in codec.signal_names(name)}
        assert codec.encode(name, signals, counter=3) == shipped.encode(name, signals, counter=3)
    assert codec.frames_sent_by("TE") == shipped.frames_sent_by("TE")
    # a copy of the shipped DBC is welcome; a frame of the service's name or identifier that differs is not
    copy = tmp_path / "copy.dbc"
    copy.write_text(DBC_PATH.read_text())
    assert FrameCodec(copy, service_frames=True).frame_ids() == shipped.frame_ids()
    clash = tmp_path / "clash.dbc"
    clash.write_text(DMC_DBC.replace("BO_ 258 DMC_Plain: 2 DMC", "BO_ 672 DMC_Plain: 2 DMC"))  # 0x2A0, TE_Limits'
    with pytest.raises(DbcError, match="clashes with the service's own frame TE_Limits"):
        FrameCodec(clash, protection={"DMC_Plain": FrameProtection()}, service_frames=True)


def test_float_signals_decode_through_cantools(tmp_path):
    p = tmp_path / "f.dbc"
    p.write_text(DMC_DBC.replace('BA_DEF_ BO_', 'SIG_VALTYPE_ 258 DMC_Temp : 1;\nBA_DEF_ BO_').replace(
        " SG_ DMC_Temp : 0|16@1+ (0.1,-40) [-40|6513.5]", " SG_ DMC_Temp : 0|32@1- (1,0) [-100|1000]").replace(
        "BO_ 258 DMC_Plain: 2 DMC", "BO_ 258 DMC_Plain: 4 DMC"))
    db = cantools.database.load_file(str(p))
    codec = FrameCodec(p, protection={"DMC_Plain": FrameProtection()})
    got = codec.decode(0x102, db.get_message_by_name("DMC_Plain").encode({"DMC_Temp": 85.25}))
    assert got is not None and math.isclose(got.signals["DMC_Temp"], 85.25)
    assert codec.encode("DMC_Plain", {"DMC_Temp": 85.25}) == db.get_message_by_name("DMC_Plain").encode({"DMC_Temp": 85.25})
