"""Progress of the long benchmarks: what each one counts, and the bars drawn on a terminal only."""
from __future__ import annotations

import io
import os
import re
import sys

import pytest

from thermal_edge.bench import jacobian
from thermal_edge.commands.progress import StageBars


class _Recorder:
    def __init__(self) -> None:
        self.calls: list[tuple[str, float, float, str]] = []

    def __call__(self, stage: str, done: float, total: float, unit: str) -> None:
        self.calls.append((stage, done, total, unit))


def test_jacobian_counts_every_round_and_every_parameter():
    rec = _Recorder()
    r = jacobian.run(repeat=2, hours=0.05, progress=rec)
    stages = [c[0] for c in rec.calls]
    assert stages[0] == "timed rounds" and stages[-1] == "central differences"
    rounds = [c for c in rec.calls if c[0] == "timed rounds"]
    diffs = [c for c in rec.calls if c[0] == "central differences"]
    # a count made from the result: the rounds it timed and the parameters it checked
    assert [c[1] for c in rounds] == list(range(len(r.analytic_runs_s) + 1))
    assert [c[1] for c in diffs] == list(range(r.params + 1))
    assert all(c[2] == c[1] for c in (rounds[-1], diffs[-1]))  # each stage ends complete


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_stage_bars_draw_one_bar_per_stage_on_a_terminal(monkeypatch):
    term = _Tty()
    monkeypatch.setattr(sys, "stderr", term)
    with StageBars("bench x") as progress:
        for k in range(4):
            progress("first part", k, 3, "round")
        progress("second part", 0.0, 2.0, "h")
        progress("second part", 2.0, 2.0, "h")
    text = term.getvalue()
    assert re.search(r"bench x: first part: 100%.*3/3", text)
    assert re.search(r"bench x: second part: 100%.*2(\.0)?/2", text)


def test_stage_bars_draw_nothing_when_stderr_is_not_a_terminal(monkeypatch):
    plain = io.StringIO()
    monkeypatch.setattr(sys, "stderr", plain)
    with StageBars("bench x") as progress:
        progress("a part", 1, 2, "round")
    assert plain.getvalue() == ""


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="no pseudo-terminal on this platform")
def test_bench_jacobian_shows_its_bars_on_a_terminal():
    import fcntl
    import struct
    import subprocess
    import termios
    import threading

    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))  # a terminal has a size
    chunks: list[bytes] = []

    def drain() -> None:  # read as it comes: a full pty buffer would block the child
        while True:
            try:
                b = os.read(master, 65536)
            except OSError:
                return
            if not b:
                return
            chunks.append(b)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        proc = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "bench", "jacobian", "--repeat", "1", "--hours", "0.25",
                               "--json"],
                              stdout=subprocess.PIPE, stderr=slave, timeout=300,
                              env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    finally:
        os.close(slave)
        reader.join(timeout=10)
        os.close(master)
    assert proc.returncode == 0
    err = b"".join(chunks).decode(errors="replace")
    assert "bench jacobian: timed rounds" in err and "bench jacobian: central differences" in err
    assert re.search(r"central differences: 100%.*14/14", err)  # the model's 14 adaptable parameters
    assert '"speedup"' in proc.stdout.decode()  # the JSON on stdout is untouched by the bars
