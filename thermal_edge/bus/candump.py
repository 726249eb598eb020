"""``candump -L`` log files: record live traffic, read it back for replay.

Writing and reading use python-can's ``CanutilsLogWriter`` / ``CanutilsLogReader``
(``(1700000000.123456) can0 0A0#0011223344556677 R``); the files decode with
``python -m cantools decode dbc/thermal_edge.dbc``.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import can

from .codec import DecodedFrame, FrameCodec

__all__ = ["CandumpFormatError", "CandumpReader", "CandumpRecorder", "read_candump"]

log = logging.getLogger(__name__)

_LINE = re.compile(
    r"^\(\d+(\.\d+)?\)\s+\S+\s+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#"
    r"((#[0-9A-Fa-f])?([0-9A-Fa-f]{2})*|R\d*)(\s+[RTrt])?$"
)


class CandumpFormatError(ValueError):
    """A file is not a ``candump -L`` log (the message names file and line)."""


class CandumpRecorder:
    """Record CAN messages to a ``candump -L`` file (RX marked ``R``, TX ``T``).

    Parameters
    ----------
    path : str or Path
        Log file; parent directories are created.
    channel : str, optional
        Interface name written into each line (default ``"can0"``).
    append : bool, optional
        Append instead of truncating.
    flush_interval_s : float, optional
        The file is flushed at most this often while writing, in s, and on close.

    Notes
    -----
    Thread-safe. Write errors (disk full, ...) are logged and counted in
    :attr:`write_errors`, never raised.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        channel: str = "can0",
        append: bool = False,
        flush_interval_s: float = 1.0,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.channel = channel
        self.frames_written = 0
        self.write_errors = 0
        self._flush_interval = float(flush_interval_s)
        self._last_flush = time.monotonic()
        self._last_timestamp: float | None = None
        self._lock = threading.Lock()
        self._writer: can.CanutilsLogWriter | None = can.CanutilsLogWriter(self.path, channel=channel, append=append)

    def write(self, msg: can.Message) -> None:
        """Append one message (its ``is_rx`` flag selects R/T).

        The line's timestamp is the message's (s since the epoch; now if it has
        none), raised if needed so that timestamps never decrease in the file.
        """
        with self._lock:
            if self._writer is None:
                return
            try:
                # Lines are written in processing order; keep their timestamps non-decreasing
                # (a received frame can carry a kernel time older than a frame just sent).
                timestamp = msg.timestamp if msg.timestamp else time.time()
                if self._last_timestamp is not None and timestamp < self._last_timestamp:
                    timestamp = self._last_timestamp
                self._last_timestamp = timestamp
                line = can.Message(
                    timestamp=timestamp,
                    arbitration_id=msg.arbitration_id,
                    is_extended_id=msg.is_extended_id,
                    is_remote_frame=msg.is_remote_frame,
                    is_error_frame=msg.is_error_frame,
                    is_fd=msg.is_fd,
                    is_rx=msg.is_rx,
                    dlc=msg.dlc,
                    data=msg.data,
                    channel=self.channel,
                    check=False,
                )
                self._writer.on_message_received(line)
                self.frames_written += 1
                now = time.monotonic()
                if now - self._last_flush >= self._flush_interval:
                    self._writer.file.flush()
                    self._last_flush = now
            except Exception as exc:  # never let recording break the bus
                self.write_errors += 1
                if self.write_errors == 1:
                    log.error("cannot record CAN traffic to %s: %s", self.path, exc)

    __call__ = write

    def flush(self) -> None:
        """Flush buffered lines to the file."""
        with self._lock:
            if self._writer is not None:
                try:
                    self._writer.file.flush()
                except Exception as exc:
                    self.write_errors += 1
                    log.error("cannot flush %s: %s", self.path, exc)

    def close(self) -> None:
        """Flush and close the file (idempotent)."""
        with self._lock:
            writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.stop()
            except Exception as exc:
                log.error("cannot close %s: %s", self.path, exc)

    def __enter__(self) -> CandumpRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _CheckedLines:
    """File-like line source for CanutilsLogReader that skips (or rejects) malformed lines."""

    def __init__(self, path: Path, strict: bool, malformed: list[tuple[int, str]]) -> None:
        self._path = path
        self._strict = strict
        self._malformed = malformed
        self._file: IO[str] = path.open("r", encoding="ascii", errors="replace")

    def __iter__(self) -> Iterator[str]:
        for lineno, line in enumerate(self._file, start=1):
            text = line.strip()
            if not text or text.startswith(("#", ";")):
                continue
            if _LINE.match(text):
                yield text
                continue
            if self._strict:
                raise CandumpFormatError(f"{self._path}:{lineno}: not a candump -L line: {text[:80]!r}")
            self._malformed.append((lineno, text[:200]))

    def close(self) -> None:
        self._file.close()


class CandumpReader:
    """Iterate over the decoded frames of a ``candump -L`` log, for replay.

    Parameters
    ----------
    path : str or Path
        The log file.
    codec : FrameCodec, optional
        Codec to decode with (a fresh one on the project DBC by default); its
        ``stats`` count the frames dropped by the integrity checks.
    include_tx : bool, optional
        Also yield frames marked ``T`` (sent by the recording node). Default True.
    strict : bool, optional
        Raise :class:`CandumpFormatError` on the first malformed line instead of
        skipping it (skipped lines are listed in :attr:`malformed_lines`).

    Notes
    -----
    Frames come in file order; ``DecodedFrame.timestamp`` is the log time in s.
    A non-empty file without a single valid line raises :class:`CandumpFormatError`.
    """

    def __init__(
        self,
        path: str | Path,
        codec: FrameCodec | None = None,
        *,
        include_tx: bool = True,
        strict: bool = False,
    ) -> None:
        self.path = Path(path)
        self.codec = codec if codec is not None else FrameCodec()
        self.include_tx = include_tx
        self.strict = strict
        #: (line number, text) of every skipped malformed line of the last iteration.
        self.malformed_lines: list[tuple[int, str]] = []
        #: Raw messages read in the last iteration (TX included).
        self.messages_read = 0

    def messages(self) -> Iterator[can.Message]:
        """Raw python-can messages of the log, in file order."""
        self.malformed_lines = []
        self.messages_read = 0
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: no such candump log")
        source = _CheckedLines(self.path, self.strict, self.malformed_lines)
        reader = can.CanutilsLogReader(source)  # type: ignore[arg-type]  # any line iterable with close()
        try:
            for msg in reader:
                self.messages_read += 1
                yield msg
        finally:
            source.close()
        if self.messages_read == 0 and self.malformed_lines:
            lineno, text = self.malformed_lines[0]
            raise CandumpFormatError(f"{self.path}:{lineno}: not a candump -L log: {text[:80]!r}")

    def __iter__(self) -> Iterator[DecodedFrame]:
        for msg in self.messages():
            if not self.include_tx and not msg.is_rx:
                continue
            frame = self.codec.decode_message(msg)
            if frame is not None:
                yield frame


def read_candump(
    path: str | Path,
    codec: FrameCodec | None = None,
    *,
    include_tx: bool = True,
    strict: bool = False,
) -> list[DecodedFrame]:
    """Read all decoded frames of a ``candump -L`` log (see :class:`CandumpReader`)."""
    return list(CandumpReader(path, codec, include_tx=include_tx, strict=strict))
