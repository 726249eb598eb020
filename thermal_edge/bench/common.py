"""Shared pieces of the benchmarks: progress, timing, where the real data is."""
from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

#: the Paderborn data set (``run_a.csv`` and the tables of the packaged ``paderborn4`` model) is
#: never part of the package: its directory comes from ``--data-dir``, else this variable (the one
#: the model loader reads for table files), else :data:`PADERBORN_DEFAULT`
DATA_DIR_ENV = "THERMAL_EDGE_DATA_DIR"
#: relative to the working directory: a checkout beside the data set's ``shared/`` folder
PADERBORN_DEFAULT = Path("..") / "shared" / "data" / "paderborn"


def paderborn_dir(given: str | os.PathLike[str] | None = None) -> Path:
    """The Paderborn data set's directory: ``given``, else ``$THERMAL_EDGE_DATA_DIR``, else
    ``../shared/data/paderborn`` relative to the working directory (the benches skip, saying
    where they looked, when ``run_a.csv`` is not there)."""
    return Path(given or os.environ.get(DATA_DIR_ENV) or PADERBORN_DEFAULT)


class Progress(Protocol):
    """How a benchmark reports how far it is: ``progress(stage, done, total, unit)``.

    ``stage`` names the part running now (a new name starts a new part); ``done`` of ``total``
    units (``unit``: "round", "tick", "h" …) are finished. The command draws it (a bar on a
    terminal); the benchmark only counts.
    """

    def __call__(self, stage: str, done: float, total: float, unit: str) -> object: ...


def no_progress(stage: str, done: float, total: float, unit: str) -> None:
    """The :class:`Progress` of a benchmark run without a reader (tests, ``--json`` in a pipe)."""


def sample_counter(progress: Progress, stage: str, total: int) -> Callable[[int], None]:
    """A per-sample ``progress(1)`` callback (as :func:`~thermal_edge.estimation.online.run_online`
    takes) that reports to a benchmark's :class:`Progress` every 100 samples."""
    done = 0

    def count(n: int) -> None:
        nonlocal done
        done += n
        if done % 100 == 0 or done == total:  # a bar redrawn per sample would cost more than the sample
            progress(stage, done, total, "sample")

    return count


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, list[float], object]:
    """Median wall time (s) over ``repeat`` calls, all times, and the last result."""
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, out


def timed_together(fns: Sequence[Callable[[], object]], repeat: int,
                   progress: Progress = no_progress) -> list[tuple[float, list[float], object]]:
    """:func:`timed` for several functions called in turn (round-robin), so that a change in the
    machine's speed during the run (a shared machine) falls on all of them alike; ``progress`` after
    every round."""
    times: list[list[float]] = [[] for _ in fns]
    outs: list[object] = [None] * len(fns)
    for r in range(repeat):
        progress("timed rounds", r, repeat, "round")
        for i, fn in enumerate(fns):
            t0 = time.perf_counter()
            outs[i] = fn()
            times[i].append(time.perf_counter() - t0)
    progress("timed rounds", repeat, repeat, "round")
    return [(statistics.median(t), t, out) for t, out in zip(times, outs)]
