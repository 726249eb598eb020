"""Log lines for the journal: syslog priorities and a rate limit against flooding.

Under systemd the service's stderr goes to the journal, which reads a ``<N>`` prefix as the
line's priority (``SyslogLevelPrefix=``, on by default), so ``journalctl -p warning`` shows the
safety events. The prefix is written only when stderr *is* the journal stream (systemd sets
``JOURNAL_STREAM`` to its ``device:inode``), so a terminal sees plain lines.

Python's levels map to syslog priorities: CRITICAL 2 (crit), ERROR 3 (err), WARNING 4
(warning), NOTICE 5 (notice: a normal but significant event, such as a change of derate
reason), INFO 6, DEBUG 7.

Every line goes through :class:`~thermal_edge.log_rate.RateLimit`: a flapping input must not
flood the journal. Callers log every event and never rate-limit themselves.
"""
from __future__ import annotations

import logging
import sys
from typing import IO, Any

from ..log_rate import RateLimit, StderrHandler, stream_is_journal

__all__ = ["NOTICE", "PRIORITY", "JournalFormatter", "RateLimit", "notice", "priority", "setup_logging",
           "stream_is_journal"]

#: Python level for syslog's "notice" (5): between INFO (20) and WARNING (30).
NOTICE = 25
logging.addLevelName(NOTICE, "NOTICE")

#: Python level -> syslog priority.
PRIORITY = {logging.CRITICAL: 2, logging.ERROR: 3, logging.WARNING: 4, NOTICE: 5, logging.INFO: 6, logging.DEBUG: 7}


def priority(levelno: int) -> int:
    """Syslog priority (0-7) of a Python log level: the priority of the nearest level at or below it."""
    best = 7
    for lvl, prio in sorted(PRIORITY.items()):
        if levelno >= lvl:
            best = prio
    return best


def notice(logger: logging.Logger, msg: str, *args: Any) -> None:
    """Log ``msg % args`` at NOTICE (syslog priority 5)."""
    logger.log(NOTICE, msg, *args)


class JournalFormatter(logging.Formatter):
    """Prefixes each line of a record with ``<N>``, its syslog priority."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        prefix = f"<{priority(record.levelno)}>"
        return "\n".join(prefix + line for line in text.splitlines() or [""])


def setup_logging(level: str | int, stream: IO[str] | None = None) -> logging.Handler:
    """Configure the root logger for the service: priorities for the journal, rate limit, level.

    Parameters
    ----------
    level : str or int
        Lowest level logged ("debug", "info", "notice", "warning", "error" or a number).
    stream : file, optional
        Where lines go (default stderr).

    Returns
    -------
    logging.Handler
        The installed handler (its filter is the :class:`RateLimit`).
    """
    journal = stream_is_journal(stream if stream is not None else sys.stderr)
    if journal:  # the journal adds the time
        formatter: logging.Formatter = JournalFormatter("%(levelname)s %(name)s: %(message)s")
    else:
        formatter = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    handler = logging.StreamHandler(stream) if stream is not None else StderrHandler()
    handler.setFormatter(formatter)
    handler.addFilter(RateLimit())
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level if isinstance(level, int) else logging.getLevelName(level.upper()))
    return handler
