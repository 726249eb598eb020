"""Log lines for the journal: priorities read back from the stream, the rate limit counted."""
from __future__ import annotations

import io
import logging
import os
import re

import pytest

from thermal_edge.service.journal import NOTICE, JournalFormatter, RateLimit, notice, setup_logging, stream_is_journal

# syslog(3) priorities, written out independently of the module's table
SYSLOG = {"CRITICAL": 2, "ERROR": 3, "WARNING": 4, "NOTICE": 5, "INFO": 6, "DEBUG": 7}


def test_each_level_gets_its_syslog_priority_on_every_line():
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JournalFormatter("%(levelname)s %(message)s"))
    log = logging.getLogger("te.test.journal")
    log.propagate = False
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)
    try:
        log.debug("d")
        log.info("i")
        notice(log, "n")
        log.warning("w")
        log.error("two\nlines")
        log.critical("c")
    finally:
        log.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 7
    for line in lines:
        m = re.match(r"<(\d)>(\w+) ", line)
        if m is None:  # the continuation line of the error keeps the error's priority
            assert line == "<3>lines"
            continue
        assert int(m.group(1)) == SYSLOG[m.group(2)]
    assert logging.getLevelName(NOTICE) == "NOTICE"


def test_the_prefix_is_written_only_when_stderr_is_the_journal_stream(tmp_path, monkeypatch):
    path = tmp_path / "stderr"
    with open(path, "w") as f:
        st = os.fstat(f.fileno())
        assert stream_is_journal(f, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
        assert not stream_is_journal(f, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"})
        assert not stream_is_journal(f, {})
        assert not stream_is_journal(io.StringIO(), {"JOURNAL_STREAM": "1:2"})  # no file descriptor
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        root = logging.getLogger()
        saved = root.handlers[:], root.level
        try:
            setup_logging("info", f)
            logging.getLogger("te.test").warning("hot")
            logging.getLogger("te.test").debug("not shown")
            f.flush()
        finally:
            root.handlers[:] = saved[0]
            root.setLevel(saved[1])
    assert path.read_text().splitlines() == ["<4>WARNING te.test: hot"]


@pytest.mark.parametrize("burst, window, events", [(5, 60.0, 100), (3, 10.0, 7)])
def test_a_flapping_call_site_is_limited_and_the_suppressed_lines_are_reported(burst, window, events):
    now = [0.0]
    limit = RateLimit(burst=burst, window_s=window, clock=lambda: now[0])
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.addFilter(limit)
    log = logging.getLogger(f"te.test.flap{burst}")
    log.propagate = False
    log.addHandler(handler)
    try:
        for k in range(events):  # one event a second, all from one call site
            now[0] = float(k)
            log.warning("input %s stale", "INV_Currents")
        log.warning("another call site")  # not limited by the first one's window
        now[0] = 1000.0
        log.warning("input %s stale", "INV_Currents")
    finally:
        log.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    # counted by hand: per window of `window` s, `burst` lines pass; the rest are dropped
    windows = [list(range(start, min(start + int(window), events))) for start in range(0, events, int(window))]
    passed = sum(min(burst, len(w)) for w in windows)
    dropped_in_last = max(0, len(windows[-1]) - burst)
    assert limit.dropped_total == events - passed
    assert len(lines) == passed + 2
    assert lines[-2] == "another call site"
    assert lines[-1] == f"input INV_Currents stale [{dropped_in_last} similar line(s) suppressed]" if dropped_in_last \
        else lines[-1] == "input INV_Currents stale"
