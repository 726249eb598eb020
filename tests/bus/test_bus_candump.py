"""Recording to candump -L, decoding it with ``python -m cantools decode``, reading it back."""

from __future__ import annotations

import asyncio
import math
import subprocess
import sys

import pytest

from thermal_edge.bus import CandumpFormatError, CandumpReader, CanTransport, FrameCodec, read_candump

from bus_testlib import DBC_PATH, REPO

INV_FRAMES = {
    "INV_Currents": dict(INV_Id=-12.35, INV_Iq=250.0, INV_IphRms=180.55),
    "INV_Mechanics": dict(INV_Speed=-1500.5, INV_Torque=42.3, INV_Udc=650.1),
    "INV_StatorTemps": dict(INV_T_WindingSlot=110.2, INV_T_EndWinding=math.nan, INV_T_Housing=55.0,
                            INV_S_WindingSlot=0, INV_S_EndWinding=1, INV_S_Housing=3),
    "INV_AmbientTemps": dict(INV_T_Ambient=25.0, INV_T_Coolant=40.4, INV_S_Ambient=0, INV_S_Coolant=2),
}
TE_FRAMES = {
    "TE_Limits": dict(TE_TorqueLimit=150.0, TE_CurrentLimit=200.05, TE_DerateActive=1, TE_DerateReason=3),
    "TE_Estimates": dict(TE_T_HotSpot=130.1, TE_T_HotSpotUpper=138.6, TE_T_Magnet=math.nan, TE_T_MagnetUpper=95.0),
    "TE_Forecast": dict(TE_TimeToLimit=65535, TE_LookaheadCurrent=150.5, TE_Horizon=600),
    "TE_Status": dict(TE_State=2, TE_PredErrRms=1.23, TE_AdaptCount=17, TE_ParamVersion=4),
}
ROUNDS = 20


def _same(decoded: dict, sent: dict) -> bool:
    return all(
        (math.isnan(v) and math.isnan(decoded[k])) or decoded[k] == pytest.approx(v, abs=1e-9)
        for k, v in sent.items()
    )


@pytest.fixture
def recorded_log(tmp_path, virtual_channel):
    path = tmp_path / "logs" / "te.log"

    async def run() -> int:
        cfg = {"interface": "virtual", "channel": virtual_channel}
        te = CanTransport({**cfg, "node": "TE", "record_path": path}, FrameCodec(DBC_PATH))
        inv = CanTransport({**cfg, "node": "INV"}, FrameCodec(DBC_PATH))
        async with te, inv:
            for _ in range(ROUNDS):
                for name, values in INV_FRAMES.items():
                    assert inv.send(name, values)
                for name, values in TE_FRAMES.items():
                    assert te.send(name, values)
                await asyncio.sleep(0.001)
            await asyncio.sleep(0.05)
            written = te.recorder.frames_written
        return written

    written = asyncio.run(run())
    assert written == 2 * 4 * ROUNDS
    return path


def test_recorded_log_is_candump_L(recorded_log):
    lines = recorded_log.read_text().splitlines()
    assert len(lines) == 2 * 4 * ROUNDS
    assert sum(line.endswith(" R") for line in lines) == 4 * ROUNDS  # received from the inverter
    assert sum(line.endswith(" T") for line in lines) == 4 * ROUNDS  # sent by thermal_edge
    assert all(line.startswith("(") and " can0 " in line for line in lines)


@pytest.mark.parametrize("single_line", [True, False], ids=["single-line", "multi-line"])
def test_cantools_decode_cli_decodes_every_frame(recorded_log, single_line):
    cmd = [sys.executable, "-m", "cantools", "decode", str(DBC_PATH)] + (["--single-line"] if single_line else [])
    with recorded_log.open() as stdin:
        proc = subprocess.run(cmd, stdin=stdin, capture_output=True, text=True, cwd=REPO, timeout=60)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    for bad in ("Unknown frame id", "Undecodable", "Wrong data size", "rror"):
        assert bad not in out, bad
    frame_lines = [line for line in out.splitlines() if line.startswith("(")]
    assert len(frame_lines) == 2 * 4 * ROUNDS
    assert all(line.rstrip().endswith("::") or " :: " in line for line in frame_lines)
    names = list(INV_FRAMES) + list(TE_FRAMES)
    for name in names:
        assert out.count(f"{name}(") == ROUNDS, name
    if single_line:
        assert "INV_S_EndWinding: open_circuit" in out and "INV_T_EndWinding: no_value" in out
        assert "TE_DerateReason: look_ahead" in out and "TE_TimeToLimit: not_within_horizon" in out


def test_read_back_through_candump_reader(recorded_log):
    frames = read_candump(recorded_log, FrameCodec(DBC_PATH))
    assert len(frames) == 2 * 4 * ROUNDS
    for frame in frames:
        sent = INV_FRAMES.get(frame.name) or TE_FRAMES[frame.name]
        assert _same(frame.signals, sent), frame
        assert frame.is_rx == (frame.name in INV_FRAMES)
        assert frame.timestamp is not None and frame.timestamp > 1e9
    for name in list(INV_FRAMES) + list(TE_FRAMES):
        assert [f.counter for f in frames if f.name == name] == [i % 16 for i in range(ROUNDS)]
    times = [f.timestamp for f in frames]
    assert times == sorted(times)

    reader = CandumpReader(recorded_log, FrameCodec(DBC_PATH), include_tx=False)
    rx_only = list(reader)
    assert {f.name for f in rx_only} == set(INV_FRAMES) and len(rx_only) == 4 * ROUNDS
    assert reader.codec.stats.dropped_total == 0 and reader.codec.stats.lost == 0


def test_damaged_log(tmp_path, recorded_log):
    lines = recorded_log.read_text().splitlines()
    # line 3: flip a payload bit (CRC error), line 5: truncated, plus garbage and a real candump line without R/T
    ts, ch, frame, direction = lines[2].split()
    can_id, data = frame.split("#")
    corrupt = f"{ts} {ch} {can_id}#{int(data[:2], 16) ^ 0x01:02X}{data[2:]} {direction}"
    damaged = lines[:2] + [corrupt, lines[3], lines[4][:-9], "this is not candump", ""] + lines[5:]
    damaged.append(f"(1700000000.000000) vcan0 {lines[-1].split()[2]}")  # repeat of the last frame, no R/T
    path = tmp_path / "damaged.log"
    path.write_text("\n".join(damaged) + "\n")

    codec = FrameCodec(DBC_PATH)
    reader = CandumpReader(path, codec)
    frames = list(reader)
    assert [n for n, _ in reader.malformed_lines] == [5, 6]
    assert codec.stats.crc == 1
    assert codec.stats.counter_repeat == 0 and codec.stats.counter_resync == 1  # the old timestamp resyncs
    assert len(frames) == len(lines) - 2 + 1  # minus corrupt and truncated, plus the extra one
    with pytest.raises(CandumpFormatError, match=r"damaged\.log:5:"):
        read_candump(path, FrameCodec(DBC_PATH), strict=True)


def test_not_a_candump_log(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("hello\nworld\n")
    with pytest.raises(CandumpFormatError, match=r"notes\.txt:1:"):
        read_candump(path)
    with pytest.raises(FileNotFoundError, match="missing.log"):
        read_candump(tmp_path / "missing.log")
    empty = tmp_path / "empty.log"
    empty.write_text("")
    assert read_candump(empty) == []
