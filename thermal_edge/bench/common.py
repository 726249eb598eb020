"""Shared pieces of the benchmarks: progress and timing."""
from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from typing import Protocol


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
