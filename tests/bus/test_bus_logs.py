"""CAN logs: recording in every python-can format (candump -L, ASC, BLF, TRC, CSV, gzip), decoding
with ``python -m cantools decode`` and can-utils' ``log2asc``, reading back, rotation at a size cap."""

from __future__ import annotations

import asyncio
import gzip
import logging
import math
import re
import shutil
import subprocess
import sys
import time

import can
import pytest
from bus_testlib import DBC_PATH, REPO

from thermal_edge.bus import (
    BusConfig,
    BusConfigError,
    CanTransport,
    FrameCodec,
    FrameLogReader,
    LogFormatError,
    LogRecorder,
    log_messages,
    read_log,
    readable_suffixes,
)

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


def _record(path, channel, **bus) -> CanTransport:
    """Send ROUNDS of every frame from an inverter and from thermal_edge, recording at thermal_edge."""

    async def run() -> CanTransport:
        cfg = {"interface": "virtual", "channel": channel}
        te = CanTransport({**cfg, "node": "TE", "record_path": path, **bus}, FrameCodec(DBC_PATH))
        inv = CanTransport({**cfg, "node": "INV"}, FrameCodec(DBC_PATH))
        async with te, inv:
            for _ in range(ROUNDS):
                for name, values in INV_FRAMES.items():
                    assert inv.send(name, values)
                for name, values in TE_FRAMES.items():
                    assert te.send(name, values)
                await asyncio.sleep(0.001)
            # the inverter's frames reach the recorder through the reader thread: wait for all of
            # them (a generous hang guard; a busy host hands them over late)
            end = time.monotonic() + 60.0
            while te.stats.rx_messages < 4 * ROUNDS and time.monotonic() < end:
                await asyncio.sleep(0.01)
            te.written = te.recorder.frames_written
        return te

    return asyncio.run(run())


@pytest.fixture
def recorded_log(tmp_path, virtual_channel):
    path = tmp_path / "logs" / "te.log"
    assert _record(path, virtual_channel).written == 2 * 4 * ROUNDS
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
    frames = read_log(recorded_log, FrameCodec(DBC_PATH))
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

    reader = FrameLogReader(recorded_log, FrameCodec(DBC_PATH), include_tx=False)
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
    last_t = lines[-1].split()[0]
    damaged.append(f"{last_t} vcan0 {lines[-1].split()[2]}")  # repeat of the last frame, no R/T
    path = tmp_path / "damaged.log"
    path.write_text("\n".join(damaged) + "\n")

    codec = FrameCodec(DBC_PATH)
    reader = FrameLogReader(path, codec)
    frames = list(reader)
    assert [n for n, _ in reader.malformed_lines] == [5, 6]
    assert codec.stats.crc == 1
    assert codec.stats.counter_repeat == 1  # the repeat of the last frame: its counter again
    assert len(frames) == len(lines) - 2  # minus corrupt and truncated (the repeat is dropped)
    with pytest.raises(LogFormatError, match=r"damaged\.log:5:"):
        read_log(path, FrameCodec(DBC_PATH), strict=True)
    # one frame stamped long before the one ahead of it is passed on: the frame clock judges a jump
    # by the frames after it (a corrupt stamp, or a clock stepped while recording), as it does live
    path.write_text("\n".join([*damaged[:-1], f"(1700000000.000000) vcan0 {lines[-1].split()[2]}"]) + "\n")
    assert len(list(read_log(path, FrameCodec(DBC_PATH)))) == len(frames) + 1
    # a log whose every step goes back is a reversed log, not a recording
    path.write_text("\n".join(lines[::-1]) + "\n")
    with pytest.raises(LogFormatError, match=r"damaged\.log: time runs backwards in \d+ of its first \d+ steps"):
        list(read_log(path, FrameCodec(DBC_PATH)))


def test_not_a_candump_log(tmp_path):
    path = tmp_path / "notes.log"
    path.write_text("hello\nworld\n")
    with pytest.raises(LogFormatError, match=r"notes\.log:1:"):
        read_log(path)
    with pytest.raises(LogFormatError, match="missing.log: no such CAN log"):
        read_log(tmp_path / "missing.log")
    empty = tmp_path / "empty.log"
    empty.write_text("")
    assert read_log(empty) == []


def test_unknown_or_unreadable_formats_are_named(tmp_path):
    notes = tmp_path / "notes.txt"
    notes.write_text("hello\n")
    with pytest.raises(LogFormatError, match=r"notes\.txt: unknown CAN log format '\.txt'; known: \.asc, \.blf"):
        read_log(notes)
    with pytest.raises(LogFormatError, match=r"x\.blf\.gz: \.blf cannot be gzipped"):
        LogRecorder(tmp_path / "x.blf.gz")
    fake = tmp_path / "fake.blf"
    fake.write_bytes(b"\x00not a blf file at all" * 10)
    with pytest.raises(LogFormatError, match=r"fake\.blf: not a \.blf log"):
        read_log(fake)
    with pytest.raises(BusConfigError, match=r"bus\.record_path: .*can\.xyz: unknown CAN log format"):
        BusConfig(record_path=tmp_path / "can.xyz")
    with pytest.raises(BusConfigError, match=r"bus\.record_max_bytes: expected a whole number"):
        BusConfig(record_path=tmp_path / "can.log", record_max_bytes=-1)
    with pytest.raises(LogFormatError, match=r"size-capped recording must be one of"):
        LogRecorder(tmp_path / "can.log.gz", max_bytes=1000)
    if ".mf4" not in readable_suffixes():  # asammdf not installed: said how to get it
        with pytest.raises(LogFormatError, match=r"MF4 logs need asammdf: pip install thermal-edge\[mf4\]"):
            LogRecorder(tmp_path / "can.mf4")


#: formats that keep the direction of a frame (python-can's CSV has no column for it)
DIRECTED = {".log", ".asc", ".blf", ".trc", ".log.gz", ".asc.gz"}


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".trc", ".csv", ".log.gz", ".asc.gz", ".csv.gz"])
def test_every_format_records_and_reads_back(tmp_path, virtual_channel, suffix):
    path = tmp_path / f"te{suffix}"
    te = _record(path, virtual_channel, record_max_bytes=0)  # .trc and .gz cannot rotate: no cap
    assert te.written == 2 * 4 * ROUNDS
    if suffix.endswith(".gz"):
        with gzip.open(path, "rb") as fh:
            assert fh.read(1)  # a real gzip stream
    frames = read_log(path, FrameCodec(DBC_PATH))
    assert len(frames) == 2 * 4 * ROUNDS
    for frame in frames:
        assert _same(frame.signals, INV_FRAMES.get(frame.name) or TE_FRAMES[frame.name]), frame
        assert frame.timestamp is not None and frame.timestamp > 1e9
        if suffix in DIRECTED:
            assert frame.is_rx == (frame.name in INV_FRAMES)
    for name in list(INV_FRAMES) + list(TE_FRAMES):
        assert [f.counter for f in frames if f.name == name] == [i % 16 for i in range(ROUNDS)]
    times = [f.timestamp for f in frames]
    assert times == sorted(times)
    if suffix in DIRECTED:
        rx = list(FrameLogReader(path, FrameCodec(DBC_PATH), include_tx=False))
        assert {f.name for f in rx} == set(INV_FRAMES) and len(rx) == 4 * ROUNDS


#: a damaged line of each text format: (line of the data, what is replaced, by what) -- a digit of
#: the DLC, of the identifier, a letter in the DLC column
DAMAGE = {".asc": ("d 8", "d Z"), ".csv": (",0x", ",0xZ"), ".trc": (" 8 ", " Z "), ".log": ("#", "!")}


@pytest.mark.parametrize("suffix", [".asc", ".csv", ".trc", ".log", ".asc.gz", ".csv.gz", ".trc.gz"])
def test_a_damaged_line_of_a_text_log_is_skipped_and_the_rest_read(tmp_path, virtual_channel, suffix, caplog):
    """One line in the middle of a text log that does not parse: that frame is missing, every other
    one is read (python-can's own reader of the clean file counts them), the line is counted with its
    number; python-can's own warning about it is not printed. Strict reading refuses the line."""
    clean = tmp_path / f"clean{suffix}"
    _record(clean, virtual_channel, record_max_bytes=0)
    plain = suffix.removesuffix(".gz")
    opener = gzip.open if suffix.endswith(".gz") else open
    with opener(clean, "rt") as fh:
        lines = fh.read().split("\n")
    old, bad = DAMAGE[plain]
    data = [i for i, ln in enumerate(lines) if old in ln and not ln.lstrip().startswith((";", "date", "base"))]
    k = data[len(data) // 2]
    lines[k] = lines[k].replace(old, bad, 1)
    damaged = tmp_path / f"damaged{suffix}"
    with opener(damaged, "wt") as fh:
        fh.write("\n".join(lines))
    with can.LogReader(clean) if not suffix.endswith(".gz") else _python_can_gz(clean, plain) as ref:
        want = len(list(ref))
    caplog.set_level("INFO")
    codec = FrameCodec(DBC_PATH)
    reader = FrameLogReader(damaged, codec)
    frames = list(reader)
    assert len(frames) == want - 1 == 2 * 4 * ROUNDS - 1
    assert [n for n, _ in reader.malformed_lines] == [k + 1]
    assert not [r for r in caplog.records if r.name.startswith("can.io") and r.levelno >= logging.WARNING]
    assert [f.timestamp for f in frames] == sorted(f.timestamp for f in frames)
    with pytest.raises(LogFormatError, match=rf"damaged{re.escape(suffix)}:{k + 1}"):
        read_log(damaged, FrameCodec(DBC_PATH), strict=True)


def _python_can_gz(path, plain):  # python-can's reader of a gzipped text log (its own LogReader drops kwargs)
    from can.io.player import MESSAGE_READERS

    kwargs = {"relative_timestamp": False} if plain == ".asc" else {}
    return MESSAGE_READERS[plain](gzip.open(path, "rt"), **kwargs)


def _msg(ts: float, i: int, rx: bool = True) -> can.Message:
    return can.Message(timestamp=ts, arbitration_id=0x100 + i % 4, data=bytes([i % 256] * 8), is_extended_id=False,
                       is_rx=rx)


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_frames_sent_before_the_time_is_known_take_the_first_known_time(tmp_path, suffix):
    """The demo's TE_Limits went out before any frame set the clock: stamped 0 they must not put the
    log's start in 1970 (python-can's ASC and BLF writers take the first record's time as the start)."""
    path = tmp_path / f"demo{suffix}"
    t0 = 1_700_000_123.250_4  # not on a whole ms: ASC and BLF starts say whole ms only
    with LogRecorder(path) as rec:
        rec.write_all([_msg(0.0, i, rx=False) for i in range(3)])
        rec.write_all([_msg(t0 + 0.01 * i, 3 + i) for i in range(50)])
        rec.write(_msg(t0, 99, rx=False))  # a sent frame stamped behind the last one: raised to it
    assert rec.frames_written == 54 and rec.unstamped_dropped == 0 and rec.write_errors == 0
    times = [m.timestamp for m in log_messages(path)]
    assert len(times) == 54
    assert times[:4] == [t0] * 4
    assert times[4:53] == pytest.approx([t0 + 0.01 * i for i in range(1, 50)], abs=1e-6)
    assert times[53] == times[52]


@pytest.mark.skipif(shutil.which("log2asc") is None, reason="can-utils' log2asc not installed")
def test_can_utils_log2asc_reads_our_candump_log_with_one_header(tmp_path):
    path = tmp_path / "demo.log"
    t0 = 1_700_000_000.0
    with LogRecorder(path) as rec:
        rec.write(_msg(0.0, 0, rx=False))  # before the time is known (was stamped 0.000001)
        rec.write_all([_msg(t0 + 0.01 * i, i) for i in range(1, 100)])
    out = tmp_path / "demo.asc"
    proc = subprocess.run(["log2asc", "-I", str(path), "-O", str(out), "can0"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    headers = re.findall(r"^date (.*)$", text, flags=re.M)
    assert len(headers) == 1 and headers[0].endswith("2023"), headers  # 1.7e9 s is November 2023
    lines = [ln.split() for ln in text.splitlines() if ln.strip() and ln.split()[0][0].isdigit()]
    assert len(lines) == 100
    assert float(lines[0][0]) == 0.0 and float(lines[-1][0]) == pytest.approx(0.98, abs=1e-6)  # from the first known time
    assert sum(ln[3] == "Tx" for ln in lines) == 1 and sum(ln[3] == "Rx" for ln in lines) == 99


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_recording_rotates_at_its_cap_and_keeps_n_files(tmp_path, virtual_channel, suffix):
    cap, keep = 4000, 3
    path = tmp_path / "rec" / f"can{suffix}"
    te = _record(path, virtual_channel, record_max_bytes=cap, record_keep=keep)
    assert te.written == 2 * 4 * ROUNDS
    rotated = sorted(path.parent.glob(f"can_*_#*{suffix}" + (".gz" if suffix != ".blf" else "")))
    assert 1 <= len(rotated) <= keep
    assert sorted(p.name for p in path.parent.iterdir()) == sorted([path.name] + [p.name for p in rotated])
    for part in rotated:
        if suffix != ".blf":  # text: gzipped when closed, each at most the cap plus one record
            with gzip.open(part, "rb") as fh:
                assert len(fh.read()) <= cap + 200
        assert read_log(part, FrameCodec(DBC_PATH))  # every closed file reads on its own
    # with room for every file, nothing is lost and the files read back in order
    path2 = tmp_path / "all" / f"can{suffix}"
    te2 = _record(path2, virtual_channel, record_max_bytes=cap // 4, record_keep=1000)
    parts = sorted(path2.parent.glob("can_*_#*"), key=lambda p: int(re.search(r"#(\d+)", p.name).group(1)))
    assert len(parts) >= 2
    frames = [f for p in [*parts, path2] for f in read_log(p, FrameCodec(DBC_PATH))]
    assert len(frames) == te2.written == 2 * 4 * ROUNDS
    times = [f.timestamp for f in frames]
    assert times == sorted(times)


def test_a_restart_never_overwrites_the_last_recording(tmp_path):
    path = tmp_path / "can.log"
    with LogRecorder(path, max_bytes=10_000, keep=5) as rec:
        rec.write_all([_msg(1.7e9 + i, i) for i in range(20)])
    with LogRecorder(path, max_bytes=10_000, keep=5) as rec:
        rec.write_all([_msg(1.8e9 + i, i) for i in range(5)])
    (old,) = rec.rotated_files
    assert len(list(log_messages(old))) == 20 and len(list(log_messages(path))) == 5


def test_the_service_configuration_caps_its_recording(tmp_path):
    """``recording:`` of edge.yaml reaches the bus: its cap and count, its format checked at load."""
    import yaml

    from thermal_edge.config import ConfigError, load_config

    raw = yaml.safe_load((REPO / "config" / "edge.yaml").read_text())
    raw["state"] = {"dir": str(tmp_path / "state")}
    path = tmp_path / "edge.yaml"

    def load(recording: dict):
        raw["recording"] = recording
        path.write_text(yaml.safe_dump(raw))
        return load_config(path)

    bus = load({"candump": "rec/can.asc", "max_bytes": 5000, "keep": 2}).bus
    assert (bus.record_path, bus.record_max_bytes, bus.record_keep) == (tmp_path / "rec" / "can.asc", 5000, 2)
    assert load({"candump": "can.log"}).bus.record_max_bytes == 64 * 2**20  # capped unless told otherwise
    assert load({"candump": "can.trc", "max_bytes": 0}).bus.record_max_bytes == 0
    with pytest.raises(ConfigError, match=r"edge\.yaml: recording\.candump: .*can\.trc: a size-capped recording must be"):
        load({"candump": "can.trc"})
    with pytest.raises(ConfigError, match=r"edge\.yaml: recording\.candump: .*can\.xyz: unknown CAN log format"):
        load({"candump": "can.xyz"})


def test_a_recording_that_cannot_be_opened_leaves_the_bus_running(tmp_path, caplog):
    """The file system refuses the recording at start (here: its directory lies under a file, which
    the configuration check refuses, but a disk or a mount can do it after the check): one ERROR
    line, no recording, and the transport sends and receives on as without one."""
    (tmp_path / "a_file").write_text("x")
    channel = f"rec-refused-{tmp_path.name}"

    async def run() -> tuple[int, object]:
        te = CanTransport({"interface": "virtual", "channel": channel, "node": "TE",
                           "record_path": str(tmp_path / "a_file" / "can.log")}, FrameCodec(DBC_PATH))
        listener = can.Bus(interface="virtual", channel=channel)
        try:
            async with te:
                for _ in range(5):
                    assert te.send("TE_Limits", {"TE_TorqueLimit": 50.0, "TE_CurrentLimit": 30.0, "TE_DerateActive": 0,
                                                 "TE_DerateReason": 0})
                    await asyncio.sleep(0.01)
                got = 0
                while listener.recv(0.5) is not None:
                    got += 1
                return got, te.recorder
        finally:
            listener.shutdown()

    with caplog.at_level(logging.ERROR, logger="thermal_edge.bus.transport"):
        got, recorder = asyncio.run(run())
    assert got == 5 and recorder is None
    assert any("cannot be written" in r.getMessage() and r.levelno == logging.ERROR for r in caplog.records)
