"""CAN log files in every format python-can knows: record live traffic, read it back.

The format is chosen by the file's suffix, as ``python -m can.logger`` and ``python -m can.player``
do: ``.log`` (``candump -L``, can-utils), ``.asc`` (Vector ASCII), ``.blf`` (Vector binary),
``.trc`` (PEAK), ``.csv`` (python-can's CSV), ``.mf4`` (ASAM MDF, with ``asammdf`` installed), each
text format also gzip-compressed (``.log.gz``, ``.asc.gz``...). Writing is python-can's
python-can's writers (by suffix, as :func:`can.Logger`) and :class:`can.SizedRotatingLogger`,
reading its readers (as :func:`can.LogReader`).

- :class:`LogRecorder` -- records the service's RX/TX traffic: timestamps never decrease, frames
  sent before the time is known (timestamp 0, python-can's "none") are written at the first
  known time, so a log never starts in 1970; with ``max_bytes`` it rotates at that size, gzips
  the closed text files (BLF compresses itself) and keeps the newest ``keep`` of them. A write
  error is counted and logged, never raised.
- :class:`FrameLogReader`, :func:`read_log` -- the decoded frames of a log, for replay; a damaged
  ``candump`` line or a truncated binary log is skipped (counted in ``malformed_lines``) or, with
  ``strict``, refused with file and line.
- :func:`log_messages` -- the raw python-can messages of a log, timestamps in s since the epoch.

Timestamps read back are rounded to 1 µs, the resolution of ``candump`` and ASC logs, so that a
run gives the same times whichever format it was stored in (BLF stores ns offsets from a start
in whole ms, ASC µs offsets from a start in whole ms).
"""

from __future__ import annotations

import gzip
import importlib.util
import logging
import math
import os
import re
import shutil
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator
from datetime import datetime
from pathlib import Path
from typing import IO, Any

import can
from can.io.logger import MESSAGE_WRITERS, SizedRotatingLogger
from can.io.player import MESSAGE_READERS

from ..errors import ThermalEdgeError
from .codec import DecodedFrame, FrameCodec

__all__ = [
    "DEFAULT_KEEP",
    "DEFAULT_MAX_BYTES",
    "GZIP_SUFFIXES",
    "ROTATING_SUFFIXES",
    "FrameLogReader",
    "LogFormatError",
    "LogRecorder",
    "check_recording",
    "log_messages",
    "log_suffix",
    "read_log",
    "readable_suffixes",
]

log = logging.getLogger(__name__)

#: Size at which the service's recording rotates, bytes (about 1.7 h of the DBC's traffic as candump).
DEFAULT_MAX_BYTES = 64 * 2**20
#: Rotated files a recording keeps besides the one being written (with ``max_bytes``).
DEFAULT_KEEP = 10
#: Formats :class:`can.SizedRotatingLogger` can rotate (it needs the writer's file size).
ROTATING_SUFFIXES = frozenset({".asc", ".blf", ".csv", ".log"})
#: Text formats: read and written gzipped too, and their rotated files gzipped (BLF compresses itself).
GZIP_SUFFIXES = frozenset({".asc", ".csv", ".log", ".trc"})
#: Not CAN logs for this project: python-can's SQLite tables and its plain-text printer.
_EXCLUDED = frozenset({".db", ".txt"})
#: Frames without a time kept until the first one with a time (older ones are dropped, counted).
UNSTAMPED_MAX = 1000
#: Resolution of timestamps read back, decimal places of s (1 µs).
_TIME_DECIMALS = 6

_CANDUMP_LINE = re.compile(
    r"^\(\d+(\.\d+)?\)\s+\S+\s+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#"
    r"((#[0-9A-Fa-f])?([0-9A-Fa-f]{2})*|R\d*)(\s+[RTrt])?$"
)


#: A line of plain ``candump can0`` output (no ``-L``): ``  can0  123   [8]  11 22 33 44 55 66 77 88``.
_PLAIN_CANDUMP_LINE = re.compile(r"^\S+\s+[0-9A-Fa-f]{3,8}\s+\[\d+\]")
#: ``candump -ta``/``-td``/``-tz`` output: a stamp in brackets, then the plain line (a display
#: format; ``-td`` stamps are differences, ``-tz`` from zero: not the log format)
_TIMED_CANDUMP_LINE = re.compile(r"^\(\S+\)\s+\S+\s+[0-9A-Fa-f]{3,8}\s+\[\d+\]")
#: The header python-can writes first in its CSV logs (and reads by position).
_CSV_HEADER = "timestamp,arbitration_id,extended,remote,error,dlc,data"
#: Latest time stamp taken as seconds since the epoch (the year 2286): a larger one is in ms or µs.
MAX_EPOCH_S = 1e10
#: Share of the first :data:`TIME_BASE_MESSAGES` steps that may go back in time (frames of several
#: interfaces merged by a logger can be a little out of order): more is a reversed or shuffled log.
#: A single jump back (a log concatenated from two recordings, a clock stepped while recording) is
#: not refused here: the frame clock judges it by the frames after it, as live.
MAX_BACK_SHARE = 0.25
#: Gaps between repeats of one frame that judge the time base: if the most frequent frame of the
#: first of them repeats less often than every :data:`MAX_MEDIAN_GAP_S` (median), the log is
#: stamped in ms (a drive's bus carries frames every few ms; 10 ms frames stamped in ms look 10 s
#: apart).
TIME_BASE_MESSAGES = 200
MAX_MEDIAN_GAP_S = 5.0


class LogFormatError(ThermalEdgeError, ValueError):
    """A file is not a CAN log of the format its suffix names (the message names file and line)."""


def _format_available(suffix: str) -> bool:
    return suffix != ".mf4" or importlib.util.find_spec("asammdf") is not None


def readable_suffixes() -> tuple[str, ...]:
    """The log suffixes this installation reads (``.mf4`` only with ``asammdf``), sorted."""
    return tuple(sorted(s for s in MESSAGE_READERS if s not in _EXCLUDED and _format_available(s)))


def log_suffix(path: str | os.PathLike[str], *, write: bool = False) -> str:
    """The format suffix of a log file (``".log"`` for ``run.log`` and ``run.log.gz``).

    Raises
    ------
    LogFormatError
        A suffix python-can cannot read (or write), naming the ones it can; ``.mf4`` without
        ``asammdf``; a gzipped binary format.
    """
    p = Path(path)
    suffixes = [s.lower() for s in p.suffixes]
    gz = bool(suffixes) and suffixes[-1] == ".gz"
    suffix = suffixes[-2] if gz and len(suffixes) >= 2 else (suffixes[-1] if suffixes and not gz else "")
    known = MESSAGE_WRITERS if write else MESSAGE_READERS
    if suffix not in known or suffix in _EXCLUDED:
        raise LogFormatError(f"{p}: unknown CAN log format {''.join(p.suffixes) or '(no suffix)'!r}; known: "
                             + ", ".join(readable_suffixes()) + " (text formats also .gz)")
    if not _format_available(suffix):
        raise LogFormatError(f"{p}: MF4 logs need asammdf: pip install thermal-edge[mf4]")
    if gz and suffix not in GZIP_SUFFIXES:
        raise LogFormatError(f"{p}: {suffix} cannot be gzipped (python-can reads gzip for text formats only)")
    return suffix


def check_recording(path: str | Path, max_bytes: int) -> str:
    """The format suffix of a recording to ``path`` rotated at ``max_bytes`` (0: never).

    Raises
    ------
    LogFormatError
        A format python-can cannot write, or a size cap on one it cannot rotate.
    """
    suffix = log_suffix(path, write=True)
    if max_bytes and (suffix not in ROTATING_SUFFIXES or Path(path).suffix.lower() == ".gz"):
        raise LogFormatError(f"{path}: a size-capped recording must be one of {', '.join(sorted(ROTATING_SUFFIXES))} "
                             "(the closed files are gzipped), or max_bytes 0")
    return suffix


# --------------------------------------------------------------------------------------------- read
class _CheckedLines:
    """Line source for ``CanutilsLogReader`` that skips (or, strict, rejects) malformed lines."""

    def __init__(self, path: Path, strict: bool, malformed: list[tuple[int, str]]) -> None:
        self._path = path
        self._strict = strict
        self._malformed = malformed
        opener: Any = gzip.open if path.suffix.lower() == ".gz" else open
        self._file: IO[str] = opener(path, "rt", encoding="ascii", errors="replace")

    def __iter__(self) -> Iterator[str]:
        for lineno, line in enumerate(self._file, start=1):
            text = line.strip()
            if not text or text.startswith(("#", ";")):
                continue
            if _CANDUMP_LINE.match(text):
                yield text
                continue
            if _TIMED_CANDUMP_LINE.match(text):
                raise LogFormatError(f"{self._path}:{lineno}: candump display output ({text[:40]!r}: -ta, -td or -tz), "
                                     "not its log format; record with candump -L (the log format: '(time) can0 123#...')")
            if _PLAIN_CANDUMP_LINE.match(text):  # no time stamps: nothing can be replayed from it
                raise LogFormatError(f"{self._path}:{lineno}: candump output without time stamps ({text[:40]!r}); "
                                     "record with candump -L (the log format: '(time) can0 123#...')")
            if self._strict:
                raise LogFormatError(f"{self._path}:{lineno}: not a candump -L line: {text[:80]!r}")
            self._malformed.append((lineno, text[:200]))

    def close(self) -> None:
        self._file.close()


class _TextLines:
    """Line source of a text log (ASC, CSV, TRC) for python-can's reader, which stops for good at
    the first line it cannot parse: this source knows the number of the line it handed out last
    and, once the first message is read, the lines before it (the header), so that a reader can be
    started again after the damaged line (:meth:`resume`) with the header handed out first."""

    def __init__(self, file: IO[str]) -> None:
        self._file = file
        self.lineno = 0  #: number of the file's line handed out last
        self._before: list[str] | None = []  # lines up to the first message (None: header known)
        self._header: list[str] = []
        self._again: deque[str] = deque()

    def __iter__(self) -> _TextLines:
        return self

    def __next__(self) -> str:
        if self._again:
            return self._again.popleft()
        line = next(self._file)
        self.lineno += 1
        if self._before is not None:
            self._before.append(line)
        return line

    def readline(self) -> str:
        return next(self, "")

    def first_message(self) -> None:
        """The reader has just returned its first message: what came before its line is the header."""
        if self._before is not None:
            self._header, self._before = self._before[:-1], None

    def resume(self) -> None:
        """Hand out the header again, then the lines after the one handed out last."""
        self._again = deque(self._header)

    def close(self) -> None:
        self._file.close()


def _reader(path: Path, suffix: str, strict: bool, malformed: list[tuple[int, str]],
            lines: _TextLines | None = None) -> can.io.generic.MessageReader:
    if suffix == ".log":
        return can.CanutilsLogReader(_CheckedLines(path, strict, malformed))  # type: ignore[arg-type]  # it only iterates lines
    # python-can's registry, opened here because can.LogReader drops the keyword arguments of a
    # .gz file (4.6.1), and ASC needs one: absolute times, the header's start plus each offset
    kwargs = {"relative_timestamp": False} if suffix == ".asc" else {}
    file: Any = path
    if lines is not None:  # the text readers only iterate their file (and call next() on it)
        file = lines
    elif path.suffix.lower() == ".gz":
        file = gzip.open(path, "rt" if suffix in GZIP_SUFFIXES else "rb")
    return MESSAGE_READERS[suffix](file, **kwargs)


def _text_lines(path: Path, suffix: str) -> _TextLines | None:
    """The line source of a text log other than candump's (None for a binary one). Undecodable
    bytes become U+FFFD: their line is then one that does not parse, skipped like any other."""
    if suffix == ".log" or suffix not in GZIP_SUFFIXES:
        return None
    opener: Any = gzip.open if path.suffix.lower() == ".gz" else open
    return _TextLines(opener(path, "rt", encoding="utf-8", errors="replace"))


def log_messages(path: str | Path, *, strict: bool = False,
                 malformed: list[tuple[int, str]] | None = None) -> Iterator[can.Message]:
    """The raw python-can messages of a CAN log, in file order (format by suffix).

    Parameters
    ----------
    path : str or Path
        The log.
    strict : bool
        Raise :class:`LogFormatError` on the first damaged line or record instead of skipping it.
    malformed : list, optional
        Receives (line number, text) of every skipped line (line 0: a damaged record of a
        binary log, after which the rest of the file is unreadable).

    Raises
    ------
    LogFormatError
        No such file; unknown suffix, or a non-empty file with not one readable message; plain
        ``candump`` output (no ``-L``); a CSV that is not python-can's; a BLF cut short; time
        stamps not in seconds since the epoch (ms or µs), or running backwards in most of the
        first steps (a reversed or shuffled log).
    """
    p = Path(path)
    suffix = log_suffix(p)
    if not p.exists():
        raise LogFormatError(f"{p}: no such CAN log")
    if not p.is_file():
        raise LogFormatError(f"{p}: not a file")
    if suffix == ".csv":
        _check_csv_header(p)
    bad = malformed if malformed is not None else []
    n = 0
    lines = None
    try:
        lines = _text_lines(p, suffix)
        reader = _reader(p, suffix, strict, bad, lines)
    except LogFormatError:
        raise
    except Exception as exc:  # python-can refusing the header of a file that is no such log
        if lines is not None:
            lines.close()
        raise LogFormatError(f"{p}: not a {suffix} log: {type(exc).__name__}: {exc}") from None
    if suffix == ".blf" and p.suffix.lower() != ".gz":
        _check_blf_size(p, reader)
    times = _TimeBase(p)
    pending: list[can.Message] = []
    with reader, _SkippedTrcLines(bad, lines):
        it = iter(reader)
        while True:
            try:
                msg = next(it)
            except StopIteration:
                break
            except LogFormatError:
                raise
            except Exception as exc:  # a damaged line or record
                where = lines.lineno if lines is not None else 0
                if strict or n == 0:
                    at = f":{where}" if where else ""
                    raise LogFormatError(f"{p}{at}: damaged {suffix} log after {n} messages: "
                                         f"{type(exc).__name__}: {exc}") from None
                bad.append((where, f"{type(exc).__name__}: {exc}"[:200]))
                if lines is not None:  # a text log: its reader starts again after the damaged line
                    lines.resume()
                    it = iter(_reader(p, suffix, strict, bad, lines))
                    continue
                # a binary record: nothing after it can be trusted
                log.warning("%s: damaged after %d messages, rest skipped: %s", p, n, exc)
                break
            if n == 0 and lines is not None:
                lines.first_message()
            msg.timestamp = round(float(msg.timestamp), _TIME_DECIMALS)
            n += 1
            times.check(msg.timestamp, n, msg.arbitration_id)
            if times.judged:
                yield from pending
                pending.clear()
                yield msg
            else:  # held back until the time base is judged: nothing is replayed from a log in ms
                pending.append(msg)
    times.finish()
    yield from pending
    if n == 0 and bad:
        lineno, text = bad[0]
        raise LogFormatError(f"{p}{f':{lineno}' if lineno else ''}: not a {suffix} log: {text[:80]!r}")


class _SkippedTrcLines(logging.Filter):
    """While a TRC log is read: python-can's reader skips a line it cannot parse with a WARNING of
    its own; the line is counted with the damaged ones (its number, its text) instead of printed."""

    _LOGGER = "can.io.trc"

    def __init__(self, bad: list[tuple[int, str]], lines: _TextLines | None) -> None:
        super().__init__()
        self._bad, self._lines = bad, lines

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING and "Failed to parse" in record.getMessage():
            self._bad.append((self._lines.lineno if self._lines is not None else 0, record.getMessage()[:200]))
            return False
        return True

    def __enter__(self) -> _SkippedTrcLines:
        logging.getLogger(self._LOGGER).addFilter(self)
        return self

    def __exit__(self, *exc: object) -> None:
        logging.getLogger(self._LOGGER).removeFilter(self)


def _check_csv_header(p: Path) -> None:
    """python-can's CSV log starts with its header; any other CSV (a run CSV) is refused by name."""
    opener: Any = gzip.open if p.suffix.lower() == ".gz" else open
    try:
        with opener(p, "rt", encoding="utf-8", errors="replace") as fh:
            first = fh.readline().strip()
    except OSError as exc:
        raise LogFormatError(f"{p}: cannot read: {exc.strerror or exc}") from None
    if first and first.replace(" ", "") != _CSV_HEADER:
        raise LogFormatError(f"{p}:1: not python-can's CSV log (its header is {_CSV_HEADER!r}, this file's "
                             f"{first[:40]!r}); a run CSV is read without --format can")


def _check_blf_size(p: Path, reader: Any) -> None:
    """A BLF whose header states a larger file than there is was cut short (python-can's reader
    stops at the cut without a word)."""
    stated, actual = int(getattr(reader, "file_size", 0) or 0), p.stat().st_size
    if stated > actual:
        raise LogFormatError(f"{p}: cut short: its header says {stated} bytes ({getattr(reader, 'object_count', '?')} "
                             f"objects), the file has {actual}; copy the whole file")


class _TimeBase:
    """Checks that a log's time stamps are seconds since the epoch, in order (module constants)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.last: float | None = None
        self.last_by_id: dict[int, float] = {}
        self.gaps: dict[int, list[float]] = {}
        self.collected = 0
        self.steps = 0
        self.back = 0
        self.judged = False

    def check(self, t: float, n: int, frame_id: int) -> None:
        if t > MAX_EPOCH_S:
            raise LogFormatError(f"{self.path}: message {n}: time stamp {t:.6g} is after the year 2286 as seconds "
                                 "since the epoch; stamped in ms or µs? (a CAN log's times are in s)")
        if self.judged:
            return
        if self.last is not None:
            self.steps += 1
            self.back += t < self.last
        self.last = t
        before = self.last_by_id.get(frame_id)
        self.last_by_id[frame_id] = t
        if before is not None:
            self.gaps.setdefault(frame_id, []).append(t - before)
            self.collected += 1
            if self.collected >= TIME_BASE_MESSAGES:
                self.finish()

    def finish(self) -> None:
        """Judge the time base by the fastest frame's period (the median of its gaps)."""
        if self.judged:
            return
        if self.steps >= 10 and self.back > MAX_BACK_SHARE * self.steps:
            raise LogFormatError(f"{self.path}: time runs backwards in {self.back} of its first {self.steps} steps; "
                                 "a reversed or shuffled log? (a CAN log's times rise)")
        periods = [sorted(g)[len(g) // 2] for g in self.gaps.values() if len(g) >= 5]
        if periods and min(periods) > MAX_MEDIAN_GAP_S:
            raise LogFormatError(f"{self.path}: its most frequent frame repeats every {min(periods):.6g} s (median); "
                                 "stamped in ms? (a CAN log's times are in s)")
        self.judged = self.collected >= TIME_BASE_MESSAGES


class FrameLogReader:
    """Iterate over the decoded frames of a CAN log (any format python-can reads), for replay.

    Parameters
    ----------
    path : str or Path
        The log file; its suffix names the format.
    codec : FrameCodec, optional
        Codec to decode with (a fresh one on the project DBC by default); its ``stats`` count
        the frames dropped by the integrity checks.
    include_tx : bool, optional
        Also yield frames the recording node sent (candump ``T``, ASC/BLF/TRC ``Tx``). Formats
        without a direction (python-can's CSV, MF4 without it) mark every frame received.
    strict : bool, optional
        Raise :class:`LogFormatError` on the first damaged line instead of skipping it (skipped
        lines are listed in :attr:`malformed_lines`).

    Notes
    -----
    Frames come in file order; ``DecodedFrame.timestamp`` is the log time in s since the epoch.
    """

    def __init__(self, path: str | os.PathLike[str], codec: FrameCodec | None = None, *, include_tx: bool = True,
                 strict: bool = False) -> None:
        self.path = Path(path)
        log_suffix(self.path)  # an unknown format is refused before anything is read
        self.codec = codec if codec is not None else FrameCodec()
        self.include_tx = include_tx
        self.strict = strict
        #: (line number, text) of every skipped damaged line of the last iteration.
        self.malformed_lines: list[tuple[int, str]] = []
        #: Raw messages read in the last iteration (TX included).
        self.messages_read = 0

    def messages(self) -> Iterator[can.Message]:
        """Raw python-can messages of the log, in file order."""
        self.malformed_lines = []
        self.messages_read = 0
        for msg in log_messages(self.path, strict=self.strict, malformed=self.malformed_lines):
            self.messages_read += 1
            yield msg

    def __iter__(self) -> Iterator[DecodedFrame]:
        for msg in self.messages():
            if not self.include_tx and not msg.is_rx:
                continue
            frame = self.codec.decode_message(msg)
            if frame is not None:
                yield frame


def read_log(path: str | Path, codec: FrameCodec | None = None, *, include_tx: bool = True,
             strict: bool = False) -> list[DecodedFrame]:
    """All decoded frames of a CAN log (see :class:`FrameLogReader`)."""
    return list(FrameLogReader(path, codec, include_tx=include_tx, strict=strict))


# -------------------------------------------------------------------------------------------- write
class _ASCWriter(can.ASCWriter):
    """python-can's ASC writer, its start exact: python-can 4.6.1 writes the start's milliseconds
    unpadded (30 ms as ``.30``, which every reader takes for 300 ms) and measures the offsets from
    the first frame's exact time although the header can only say whole milliseconds. Here the
    start is the first frame's time floored to the millisecond (as python-can's BLF writer does),
    so that start + offset reads back as the frame's time."""

    def _format_header_datetime(self, dt: datetime) -> str:
        return dt.strftime(self.FORMAT_DATE.format(f"{dt.microsecond // 1000:03d}"))

    def log_event(self, message: str, timestamp: float | None = None) -> None:
        if not self.header_written:
            self.started = self.last_timestamp = math.floor((timestamp or 0.0) * 1000.0) / 1000.0
            start = self._format_header_datetime(datetime.fromtimestamp(self.started))
            self.file.write(f"Begin Triggerblock {start}\n")
            self.header_written = True
            super().log_event("Start of measurement")
        super().log_event(message, timestamp)


def _open_writer(path: str | Path, **kwargs: Any) -> can.io.generic.MessageWriter:
    """The python-can writer of a log file's suffix (``.gz``: a gzip stream of a text format)."""
    p = Path(path)
    suffix = log_suffix(p, write=True)
    cls = _ASCWriter if suffix == ".asc" else MESSAGE_WRITERS[suffix]
    if p.suffix.lower() == ".gz":
        assert issubclass(cls, can.io.generic.TextIOMessageWriter)  # log_suffix admits .gz for text formats only
        return cls(gzip.open(p, "wt"), **kwargs)
    return cls(p, **kwargs)


class _RotatingLogger(SizedRotatingLogger):
    """:class:`can.SizedRotatingLogger` opening its files with :func:`_open_writer` (the ASC fix)."""

    def _get_new_writer(self, filename: Any) -> Any:
        return _open_writer(filename, **self.writer_kwargs)


class LogRecorder:
    """Record CAN messages to a log in the format of the file's suffix (RX and TX marked).

    Parameters
    ----------
    path : str or Path
        Log file (``.log`` candump -L, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ``.mf4``; text
        formats also ``.gz``); parent directories are created.
    channel : str, optional
        Interface name written into each record (default ``"can0"``; ASC/BLF/TRC number it).
    max_bytes : int, optional
        Rotate when the file reaches this size, bytes (0: never; ``.log``, ``.asc``, ``.csv``,
        ``.blf`` only, not gzipped: the closed files are gzipped instead). A file left by an
        earlier run is rotated away first instead of being overwritten.
    keep : int, optional
        Rotated files kept (the oldest are deleted), besides the one being written.
    flush_interval_s : float, optional
        The file is flushed at most this often while writing, in s, and on close.

    Notes
    -----
    Thread-safe. Write errors (disk full, ...) are logged and counted in :attr:`write_errors`,
    never raised. A message without a time (timestamp 0) waits for the first message with one
    and is written at that time (at most :data:`UNSTAMPED_MAX` of them wait; older ones are
    dropped and counted in :attr:`unstamped_dropped`).
    """

    def __init__(self, path: str | os.PathLike[str], *, channel: str = "can0", max_bytes: int = 0, keep: int = DEFAULT_KEEP,
                 flush_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        suffix = check_recording(self.path, max_bytes)
        if max_bytes < 0 or keep < 0:
            raise ValueError(f"{self.path}: max_bytes and keep must not be negative")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.channel = channel
        self.max_bytes = int(max_bytes)
        self.keep = int(keep)
        self._compress = suffix in GZIP_SUFFIXES
        self.frames_written = 0
        self.write_errors = 0
        self.unstamped_dropped = 0
        self._flush_interval = float(flush_interval_s)
        self._last_flush = time.monotonic()
        self._last_timestamp: float | None = None
        self._unstamped: deque[can.Message] = deque()
        self._lock = threading.Lock()
        self._writer: can.io.generic.MessageWriter | None = None
        if self.max_bytes:
            if self.path.is_file() and self.path.stat().st_size > 0:
                self._rotate_aside()
            rotating = _RotatingLogger(self.path, max_bytes=self.max_bytes)
            rotating.namer = self._namer
            rotating.rotator = self._rotator
            self._writer = rotating
        else:
            self._writer = _open_writer(self.path)

    # -- rotation -------------------------------------------------------------------------------
    @property
    def rotated_files(self) -> list[Path]:
        """The closed files of this recording, oldest first."""
        stem = self.path.name.split(".")[0]
        suffix = "".join(self.path.suffixes[-1:])
        pattern = f"{stem}_*_#*{suffix}" + (".gz" if self._compress else "")
        # by age: a restart's counter begins again at 0
        return sorted(self.path.parent.glob(pattern), key=lambda f: (f.stat().st_mtime, f.name))

    @property
    def files_rotated(self) -> int:
        """Rotations since this recorder was opened."""
        return self._writer.rollover_count if isinstance(self._writer, SizedRotatingLogger) else 0

    def _rotated_name(self, when: float, count: int) -> Path:
        """``<stem>_<local time>_#<count><suffix>[.gz]``: sorts by time (python-can's scheme)."""
        stamp = time.strftime("%Y-%m-%dT%H%M%S", time.localtime(when))
        name = f"{self.path.name.split('.')[0]}_{stamp}_#{count:03}{self.path.suffixes[-1]}"
        return self.path.parent / (f"{name}.gz" if self._compress else name)

    def _namer(self, default: Any) -> str:
        count = self._writer.rollover_count if isinstance(self._writer, SizedRotatingLogger) else 0
        return str(self._rotated_name(time.time(), count))

    def _rotator(self, source: Any, dest: Any) -> None:
        """Move (gzip) the closed file to its rotated name, then delete the oldest beyond ``keep``."""
        src, dst = Path(source), Path(dest)
        if src.exists():
            if self._compress:
                with open(src, "rb") as fin, gzip.open(dst, "wb") as fout:
                    shutil.copyfileobj(fin, fout)
                src.unlink()
            else:
                src.rename(dst)
        old = self.rotated_files
        for f in old[: max(0, len(old) - self.keep)]:
            f.unlink(missing_ok=True)

    def _rotate_aside(self) -> None:
        """Rotate a file an earlier run left, so that a restart never overwrites its recording."""
        self._rotator(self.path, self._rotated_name(self.path.stat().st_mtime, 0))

    # -- writing ---------------------------------------------------------------------------------
    def write(self, msg: can.Message) -> None:
        """Append one message (its ``is_rx`` flag gives the direction).

        The record's time is the message's (s since the epoch, to the µs), raised if needed so that
        times never decrease in the file; a message without a time waits for the first one with one.
        """
        with self._lock:
            if self._writer is None:
                return
            try:
                if not msg.timestamp or msg.timestamp <= 0:
                    if self._last_timestamp is None:
                        if len(self._unstamped) >= UNSTAMPED_MAX:
                            self._unstamped.popleft()
                            self.unstamped_dropped += 1
                        self._unstamped.append(msg)
                        return
                    timestamp = self._last_timestamp
                else:  # to the µs of candump and ASC: every format then holds the same times
                    timestamp = round(float(msg.timestamp), _TIME_DECIMALS)
                # records go in processing order; keep their times non-decreasing (a received frame
                # can carry a kernel time older than a frame just sent)
                if self._last_timestamp is not None and timestamp < self._last_timestamp:
                    timestamp = self._last_timestamp
                self._last_timestamp = timestamp
                while self._unstamped:
                    self._write_one(self._unstamped.popleft(), timestamp)
                self._write_one(msg, timestamp)
                now = time.monotonic()
                if now - self._last_flush >= self._flush_interval:
                    self._flush_file()
                    self._last_flush = now
            except Exception as exc:  # never let recording break the bus
                self.write_errors += 1
                if self.write_errors == 1:
                    log.error("cannot record CAN traffic to %s: %s", self.path, exc)

    __call__ = write

    def _write_one(self, msg: can.Message, timestamp: float) -> None:
        assert self._writer is not None
        self._writer.on_message_received(can.Message(
            timestamp=timestamp, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
            is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, is_fd=msg.is_fd,
            is_rx=msg.is_rx, dlc=msg.dlc, data=msg.data, channel=self.channel, check=False))
        self.frames_written += 1

    def write_all(self, messages: Iterable[can.Message]) -> None:
        """Write messages in order (see :meth:`write`)."""
        for msg in messages:
            self.write(msg)

    def _flush_file(self) -> None:
        writer = self._writer.writer if isinstance(self._writer, SizedRotatingLogger) else self._writer
        file = getattr(writer, "file", None)
        if file is not None and not file.closed:
            file.flush()

    def flush(self) -> None:
        """Flush buffered records to the file (BLF and MF4 write whole blocks, on close)."""
        with self._lock:
            if self._writer is not None:
                try:
                    self._flush_file()
                except Exception as exc:
                    self.write_errors += 1
                    log.error("cannot flush %s: %s", self.path, exc)

    def close(self) -> None:
        """Write what waits for a time (at the wall clock's), flush and close (idempotent)."""
        with self._lock:
            writer = self._writer
            if writer is not None and self._unstamped:
                try:
                    t = time.time()
                    while self._unstamped:
                        self._write_one(self._unstamped.popleft(), t)
                except Exception as exc:
                    self.write_errors += 1
                    log.error("cannot record CAN traffic to %s: %s", self.path, exc)
            self._writer = None
        if writer is not None:
            try:
                writer.stop()
            except Exception as exc:
                log.error("cannot close %s: %s", self.path, exc)

    def __enter__(self) -> LogRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
