"""Shared pieces of the benchmarks: repository paths, timing, tables."""
from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Callable, Sequence

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config"


def config_path(*parts: str) -> Path:
    """A file under the repository's ``config/`` directory."""
    return CONFIG.joinpath(*parts)


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, list[float], object]:
    """Median wall time (s) over ``repeat`` calls, all times, and the last result."""
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, out


def timed_together(fns: Sequence[Callable[[], object]], repeat: int) -> list[tuple[float, list[float], object]]:
    """:func:`timed` for several functions called in turn (round-robin), so that a change in the
    machine's speed during the run (a shared machine) falls on all of them alike."""
    times: list[list[float]] = [[] for _ in fns]
    outs: list[object] = [None] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            t0 = time.perf_counter()
            outs[i] = fn()
            times[i].append(time.perf_counter() - t0)
    return [(statistics.median(t), t, out) for t, out in zip(times, outs)]


def table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A plain-text table with right-aligned columns."""
    cells = [[str(h) for h in headers]] + [[_fmt(v) for v in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
