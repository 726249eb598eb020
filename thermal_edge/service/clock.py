"""Clocks that drive the 1 Hz tick.

- :class:`WallClock` -- on hardware: ticks at wall-clock second boundaries (``time.time``), timed
  with the event loop's monotonic clock so that a wall-clock step does not burst ticks.
- :class:`FrameClock` -- for replays and accelerated simulation: time is the timestamp of the
  frames received; a tick happens when a frame's timestamp crosses the next tick boundary, so the
  tick sees exactly the frames of its interval, however fast or slow they arrive.

Both put tick boundaries at integer multiples of the tick period (``floor(t / period) * period``),
so a replay of a log ticks at the same instants as the live run that recorded it.
"""
from __future__ import annotations

import asyncio
import math
import time

__all__ = ["Clock", "FrameClock", "WallClock", "first_boundary"]


def first_boundary(t: float, period: float) -> float:
    """The first tick boundary strictly after ``t``."""
    return (math.floor(t / period) + 1) * period


class Clock:
    """Common interface: ``now()`` in seconds since the epoch."""

    period: float = 1.0

    def now(self) -> float:  # pragma: no cover - interface
        raise NotImplementedError


class WallClock(Clock):
    """Wall clock (``time.time``); :meth:`wait_next_tick` sleeps to the next boundary."""

    def __init__(self, period: float = 1.0) -> None:
        self.period = float(period)
        self._next: float | None = None

    def now(self) -> float:
        return time.time()

    def next_boundary(self) -> float:
        if self._next is None:
            self._next = first_boundary(self.now(), self.period)
        return self._next

    async def wait_next_tick(self) -> tuple[float, float]:
        """Sleep until the next boundary; returns (boundary time, lateness in s).

        If the loop was late by whole periods, the missed boundaries are skipped (one tick then
        covers the longer interval) instead of bursting.
        """
        target = self.next_boundary()
        delay = target - self.now()
        if delay > 0:
            await asyncio.sleep(delay)
        now = self.now()
        lateness = max(0.0, now - target)
        if lateness >= self.period:  # skip whole missed periods
            target = math.floor(now / self.period) * self.period
        self._next = target + self.period
        return target, lateness


class FrameClock(Clock):
    """Time given by frame timestamps.

    :meth:`observe` is called with each frame's timestamp before the frame is accumulated; it
    returns the tick boundaries crossed (in order) that must be processed first. Timestamps that go
    backwards are ignored for the clock (the frame is still used).
    """

    def __init__(self, period: float = 1.0) -> None:
        self.period = float(period)
        self._now: float | None = None
        self._next: float | None = None

    @property
    def started(self) -> bool:
        return self._now is not None

    def now(self) -> float:
        return self._now if self._now is not None else time.time()

    def observe(self, ts: float | None) -> list[float]:
        """Advance to a frame timestamp; return the boundaries crossed (oldest first)."""
        if ts is None or not math.isfinite(ts):
            return []
        if self._now is None:
            self._now = ts
            self._next = first_boundary(ts, self.period)
            return []
        if ts <= self._now:
            return []
        self._now = ts
        out: list[float] = []
        assert self._next is not None
        while self._next <= ts:
            out.append(self._next)
            self._next += self.period
        return out
