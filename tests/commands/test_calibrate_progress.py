"""calibrate stops when its global search stops improving (or at --max-time) and says why; the
progress bar is drawn on a terminal only."""
from __future__ import annotations

import fcntl
import importlib
import os
import pty
import re
import struct
import subprocess
import sys
import termios

import pytest
from cmd_testlib import TWO_NODE, te, te_here

from thermal_edge.data import read_run
from thermal_edge.estimation.calibrate import MIN_IMPROVEMENT, calibrate
from thermal_edge.lptn import load_model

#: The model's parameters the run was simulated with (two_node.yaml's values).
TRUE = {"C_w": 2000.0, "R_wh": 0.05, "R_ha": 0.1}
GENERATIONS = 30


def _objective_line(out: str) -> re.Match[str]:
    m = re.search(r"after global search (\S+) \((\d+) generations: (.*?)\), after SQP (\S+);", out)
    assert m, out
    return m


def _fit(run, out, *sets: str) -> tuple[dict[str, float], re.Match[str]]:
    args = [a for s in sets for a in ("--set", s)]
    r = te("calibrate", "--model", TWO_NODE, "--run", run, "--out", out, *args,
           "--generations", GENERATIONS, "--popsize", 5, "--decimate", 5)
    assert r.returncode == 0, r.stderr
    assert r.stderr == ""  # no progress bar when stderr is not a terminal
    fitted = load_model(out)
    return dict(zip(fitted.parameter_names, fitted.nominal())), _objective_line(r.stdout)


def test_a_wrong_start_is_fitted_and_the_search_stops_when_it_stops_improving(good_run, tmp_path):
    """From a start 2x off the search ends where it ends from the plant's own values, and stops
    well before its 30 generations, saying why."""
    ref, _ = _fit(good_run, tmp_path / "ref.yaml")
    values, m = _fit(good_run, tmp_path / "cal.yaml", "R_ha=0.2", "R_wh=0.1")
    generations, why = int(m.group(2)), m.group(3)
    assert generations < GENERATIONS
    assert why.startswith(("no improvement above", "population converged")), why
    for name in TRUE:
        assert values[name] == pytest.approx(ref[name], rel=0.02), name
    for name in ("R_wh", "R_ha"):  # the plant's resistances (C_w shows only in the two load steps: fitted 12 % low)
        assert values[name] == pytest.approx(TRUE[name], rel=0.05), name


def test_the_stop_rule_counts_generations_without_progress(good_run):
    """Library level: with a patience of 2 the search runs at most 2 generations past the last one
    that improved the best objective by MIN_IMPROVEMENT (recorded by the progress callback)."""
    model = load_model(TWO_NODE)
    best: list[float] = []
    res = calibrate(model, [read_run(good_run)], decimation=5, maxiter=GENERATIONS, popsize=5, seed=3,
                    progress=lambda done, total, f: best.append(f), patience=2)
    assert res.generations == len(best) < GENERATIONS
    if res.stopped.startswith("no improvement"):
        ref, idle = res.objective_start, 0  # progress is judged against the best when it was last made
        for f in best[:-1]:
            ref, idle = (f, 0) if f < ref * (1 - MIN_IMPROVEMENT) else (ref, idle + 1)
            assert idle < 2  # it would have stopped here
        assert not best[-1] < ref * (1 - MIN_IMPROVEMENT) and idle + 1 == 2
    else:
        assert res.stopped.startswith("population converged")
    assert res.objective_final <= res.objective_global <= res.objective_start


class _SlowClock:
    """A ``time`` module whose ``perf_counter`` advances :attr:`STEP_S` at every read: the fit reads
    the clock once at its start and once after each generation, so ``--max-time 1`` is reached after
    the third generation on any host, however fast."""

    STEP_S = 0.4

    def __init__(self) -> None:
        self.reads = 0

    def perf_counter(self) -> float:
        self.reads += 1
        return (self.reads - 1) * self.STEP_S


def test_max_time_stops_the_search(good_run, tmp_path, monkeypatch):
    """The time budget stops the global search where neither the generations nor the patience would."""
    clock = _SlowClock()
    monkeypatch.setattr(importlib.import_module("thermal_edge.estimation.calibrate"), "time", clock)
    r = te_here("calibrate", "--model", TWO_NODE, "--run", good_run, "--out", tmp_path / "c.yaml", "--set", "R_ha=0.2",
                "--generations", 1000, "--patience", 1000, "--popsize", 5, "--max-time", 1)
    assert r.returncode == 0, r.stderr
    m = _objective_line(r.stdout)
    assert m.group(3) == "--max-time 1 s reached"
    assert int(m.group(2)) == 3  # reads at 0.4, 0.8, 1.2 s after the start: the third reaches 1 s
    assert clock.reads >= 5  # the start, three generations, the polish's first check (and the wall time)


def test_the_progress_bar_on_a_terminal(good_run, tmp_path):
    """stderr on a pseudo-terminal of 100 columns: tqdm's bar with the generation count and the best objective."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 100, 0, 0))
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    p = subprocess.Popen([sys.executable, "-m", "thermal_edge.cli", "calibrate", "--model", str(TWO_NODE), "--run",
                          str(good_run), "--out", str(tmp_path / "c.yaml"), "--popsize", "5", "--decimate", "5"],
                         stdout=subprocess.PIPE, stderr=slave, env=env)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # the child closed its end
            break
        if not data:
            break
        chunks.append(data)
    p.wait(timeout=300)
    os.close(master)
    assert p.returncode == 0
    err = b"".join(chunks).decode(errors="replace")
    assert re.search(r"calibrate: global search: +\d+%\|.*\| \d+/30 \[", err), err
    assert "generation/s" in err and "best objective" in err
