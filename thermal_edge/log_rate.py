"""A rate limit on log lines, for every logger of the package: a flapping input must not flood the
journal, nor a replay at 100x the terminal.

The limiter counts lines per call site (logger, level, message template); after ``burst`` lines
within ``window_s`` it drops further lines of that site until the window ends, then reports how
many it dropped on the next line it lets through. It imports nothing of the package, so that the
command line can install it before any command is chosen.
"""
from __future__ import annotations

import logging
import os
import sys
import time
from typing import IO, Any

__all__ = ["RateLimit", "stream_is_journal", "warnings_to_stderr"]


def stream_is_journal(stream: IO[str], environ: dict[str, str] | None = None) -> bool:
    """True if ``stream`` is the journal's stream (systemd sets ``JOURNAL_STREAM`` to its device:inode)."""
    env = os.environ if environ is None else environ
    js = env.get("JOURNAL_STREAM", "")
    try:
        dev, ino = (int(x) for x in js.split(":"))
        st = os.fstat(stream.fileno())
    except (ValueError, OSError, AttributeError):
        return False
    return st.st_dev == dev and st.st_ino == ino


class RateLimit(logging.Filter):
    """Lets at most ``burst`` lines per call site through in each window of ``window_s`` seconds.

    Parameters
    ----------
    burst : int
        Lines of one call site allowed per window.
    window_s : float
        Window length in s (monotonic clock).
    clock : callable, optional
        Time source in s (tests).
    """

    def __init__(self, burst: int = 5, window_s: float = 60.0, clock: Any = time.monotonic) -> None:
        super().__init__()
        self.burst = int(burst)
        self.window_s = float(window_s)
        self._clock = clock
        #: call site -> [window start, lines let through in it, lines dropped since the last one let through]
        self._sites: dict[tuple[str, int, str], list[float]] = {}
        self.dropped_total = 0

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.name, record.levelno, str(record.msg))
        now = self._clock()
        site = self._sites.get(key)
        if site is None or now - site[0] >= self.window_s:
            dropped = int(site[2]) if site is not None else 0
            self._sites[key] = [now, 1, 0]
            if len(self._sites) > 4096:  # bounded: forget windows that have ended
                self._sites = {k: v for k, v in self._sites.items() if now - v[0] < self.window_s}
            if dropped:
                record.msg = f"{record.msg} [{dropped} similar line(s) suppressed]"
            return True
        if site[1] < self.burst:
            site[1] += 1
            return True
        site[2] += 1
        self.dropped_total += 1
        return False


class StderrHandler(logging.StreamHandler):
    """A stream handler that writes to ``sys.stderr`` as it is when a record is emitted, not as it
    was when the handler was made: a program that embeds the CLI (a test runner capturing output)
    replaces and closes ``sys.stderr`` between calls, and a handler holding an old one would fail."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:  # the stream is always the current stderr
        pass


def warnings_to_stderr() -> None:
    """Warnings of every command to stderr through a :class:`RateLimit`, unless the root logger
    has a handler already (an embedding program's, the test runner's). ``run`` replaces it with
    its own for the journal, with the same limit."""
    root = logging.getLogger()
    if root.handlers:
        return
    handler = StderrHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    handler.addFilter(RateLimit())
    root.addHandler(handler)
