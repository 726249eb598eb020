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


@pytest.mark.async_timeout(90)
async def test_safety_events_reach_the_journal_with_their_priorities(tmp_path, channel, monkeypatch):
    """The service's own log lines, on a stream the journal would read, during a sensor fault and its
    recovery: each event once, with the priority ``journalctl -p`` filters on."""
    from svc_testlib import running, sim_until

    from thermal_edge.bus import SensorStatus

    path = tmp_path / "stderr"
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    with open(path, "w") as f:
        st = os.fstat(f.fileno())
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        setup_logging("info", f)
        try:
            async with running(tmp_path, channel) as (svc, emu):
                await sim_until(emu, 120)
                emu.sensor_status["end_winding"] = int(SensorStatus.OPEN_CIRCUIT)
                t = emu.elapsed
                await sim_until(emu, t + 20)
                emu.sensor_status.clear()
                t = emu.elapsed
                await sim_until(emu, t + 20)
        finally:
            f.flush()
            root.handlers[:] = saved[0]
            root.setLevel(saved[1])
    lines = path.read_text().splitlines()
    assert lines and all(re.match(r"<[0-7]>", line) for line in lines)
    prio = {}
    for line in lines:
        m = re.match(r"<(\d)>(\w+) ([\w.]+): (.*)", line)
        assert m, line
        assert int(m.group(1)) == SYSLOG[m.group(2)]
        prio.setdefault(m.group(4).split(":")[0], []).append(int(m.group(1)))
    fault = [p for msg, p in prio.items() if msg.startswith("sensor fault") and "cleared" not in msg]
    cleared = [p for msg, p in prio.items() if msg.startswith("sensor fault cleared")]
    assert fault == [[4]], prio  # warning, once
    assert cleared == [[5]], prio  # notice, once
    reasons = [line for line in lines if "derate reason" in line and "sensor_fault" in line.split("->")[1]]
    assert len(reasons) == 1 and reasons[0].startswith("<4>"), reasons


def test_every_command_rate_limits_its_warnings():
    """A command that warns on every tick of a persisting condition (a replay or a demo at 100x)
    prints a few lines, not one per tick: the command line installs the rate limit before any
    command runs. Counted on the stderr of a real ``thermal-edge`` process."""
    import subprocess
    import sys

    code = (
        "import logging, thermal_edge.commands.config as c\n"
        "def warn_every_tick(args):\n"
        "    for k in range(200):\n"
        "        logging.getLogger('thermal_edge.probe').warning('the same condition at tick %d', k)\n"
        "    return 0\n"
        "c.run_example = warn_every_tick\n"
        "from thermal_edge import cli\n"
        "raise SystemExit(cli.main(['config', 'example']))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert lines == [f"WARNING thermal_edge.probe: the same condition at tick {k}" for k in range(RateLimit().burst)]


def test_the_stderr_handler_writes_to_stderr_as_it_is_now(monkeypatch):
    """A program embedding the CLI replaces sys.stderr and closes the old one between calls (a test
    runner does): the handler of the warnings and of ``run`` writes to the current one, never to a
    closed stream (a "Logging error" traceback on the next command's stderr)."""
    import io
    import logging

    from thermal_edge.log_rate import StderrHandler

    handler = StderrHandler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger = logging.getLogger("thermal_edge.test_stderr_handler")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        first = io.StringIO()
        monkeypatch.setattr("sys.stderr", first)
        logger.warning("one")
        first.close()
        second = io.StringIO()
        monkeypatch.setattr("sys.stderr", second)
        logger.warning("two")
        assert second.getvalue() == "two\n"
    finally:
        logger.removeHandler(handler)
