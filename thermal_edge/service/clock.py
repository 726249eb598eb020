"""Clocks that drive the 1 Hz tick.

- :class:`WallClock` -- on hardware: ticks at wall-clock second boundaries (``time.time``), timed
  with the event loop's monotonic clock so that a wall-clock step does not burst ticks.
- :class:`FrameClock` -- for replays and accelerated simulation: time is the timestamp of the
  frames received; a tick happens when a frame's timestamp crosses the next tick boundary, so the
  tick sees exactly the frames of its interval, however fast or slow they arrive. The boundaries
  crossed come as :class:`Boundaries`, constant in memory however far a timestamp jumps; a jump
  (a tick or more back, more than ``max_catchup_s`` ahead) is judged by the frames after it
  (:class:`FrameClock`).

Both put tick boundaries at integer multiples of the tick period (``floor(t / period) * period``),
so a replay of a log ticks at the same instants as the live run that recorded it.
"""
from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Iterator, Sequence
from typing import overload

__all__ = ["Boundaries", "Clock", "FrameClock", "FrameClockStats", "WallClock", "first_boundary"]

log = logging.getLogger(__name__)


def first_boundary(t: float, period: float) -> float:
    """The first tick boundary strictly after ``t``."""
    return (math.floor(t / period) + 1) * period


class Clock:
    """Common interface: ``now()`` in seconds since the epoch."""

    period: float = 1.0

    def now(self) -> float:  # pragma: no cover - interface
        raise NotImplementedError

    def behind(self, ts: float | None) -> float:
        """How far a frame stamped ``ts`` lies behind the clock, s: 0 here (a frame is of the time
        it arrives); :class:`FrameClock` measures it."""
        return 0.0


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


class FrameClockStats:
    """What the frame clock saw of timestamps out of order (counters since the start).

    ``behind``: frames stamped earlier than the clock (time going backwards), of which ``jitter``
    by less than a tick (harmless: the frame is used, the clock ignores its stamp); ``behind_max_s``
    the largest such step back, s. ``joined``: backward jumps of a tick or more that the frames
    after them kept to (a new recording segment): the clock continued on them without a gap,
    ``joined_s`` the time taken out in all, s. ``ignored`` / ``ignored_frames``: jumps (a tick or
    more back, or more than ``max_catchup_s`` ahead) that the frames after them contradicted (a
    corrupt stamp): the clock ignored their stamps (their data was used). ``ahead``: jumps more
    than ``max_catchup_s`` ahead that the frames after them kept to (a gap in the frames, bridged
    by the engine).
    """

    __slots__ = ("behind", "jitter", "behind_max_s", "joined", "joined_s", "ignored", "ignored_frames", "ahead")

    def __init__(self) -> None:
        self.behind = self.jitter = self.joined = self.ignored = self.ignored_frames = self.ahead = 0
        self.behind_max_s = self.joined_s = 0.0

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in self.__slots__}


class Boundaries(Sequence[float]):
    """Tick boundaries ``k * period`` for the ``k`` of a :class:`range`, in constant memory
    whatever their number (a timestamp years ahead crosses billions): ``len()``, iteration,
    indexing and slicing (a slice is a :class:`Boundaries` again), equal to any sequence of the
    same values."""

    __slots__ = ("_ks", "period")

    def __init__(self, ks: range, period: float) -> None:
        self._ks, self.period = ks, float(period)

    def __len__(self) -> int:
        return len(self._ks)

    @overload
    def __getitem__(self, i: int) -> float: ...

    @overload
    def __getitem__(self, i: slice) -> Boundaries: ...

    def __getitem__(self, i: int | slice) -> float | Boundaries:
        if isinstance(i, slice):
            return Boundaries(self._ks[i], self.period)
        return self._ks[i] * self.period

    def __iter__(self) -> Iterator[float]:
        p = self.period
        for k in self._ks:
            yield k * p

    def __eq__(self, other: object) -> bool:
        if isinstance(other, Boundaries):
            return self._ks == other._ks and (self.period == other.period or not self._ks)
        if isinstance(other, (list, tuple)):
            return len(other) == len(self) and all(a == b for a, b in zip(self, other))
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        if not self._ks:
            return "Boundaries([])"
        return f"Boundaries(first={self[0]!r}, count={len(self)}, period={self.period!r})"


class FrameClock(Clock):
    """Time given by frame timestamps.

    :meth:`observe` is called with each frame's timestamp before the frame is accumulated; it
    returns the tick boundaries crossed (in order, as :class:`Boundaries`: constant memory however
    many) that must be processed first. The caller's gap rule (the engine's ``ticks_for``) decides
    what to do with more than ``max_catchup_s`` of them.

    Timestamps out of order:

    - a frame stamped earlier than the clock by less than a tick (jitter between senders) is used,
      its stamp ignored for the clock, and counted (:attr:`stats`), nothing else;
    - a **jump** -- a frame a tick or more behind the clock, or more than ``max_catchup_s``
      ahead -- does not move the clock at once: it is judged by the frames after it. If they
      keep to the jump (:attr:`CONFIRM_FRAMES` frames or more within ``max_catchup_s`` of each
      other, covering a tick or more, and at least :attr:`CONFIRM_SHARE` of the frames a tick
      brought before it: a new segment brings its whole traffic, whereas stamps shuffled at
      random put a few frames in a row behind and then one on the clock's time again), it is
      taken: backwards, as a new recording segment joined on without a gap (the clock's time
      becomes the frame's timestamp plus an offset, so the clock never goes back and the segment
      is ticked through); ahead, as a gap in the frames (the boundaries crossed; the engine
      bridges them). If a frame keeps to the clock first, the jump was a corrupt stamp: its
      frames are ignored for the clock. Either way a WARNING line and a counter say so. Until a
      jump is judged, its frames are used at the clock's time (the caller adds them at
      :meth:`now`).
    """

    #: frames (the jump's first among them) that must keep to a jump before it is taken
    CONFIRM_FRAMES = 3
    #: share of the frames of the last full tick that must keep to a jump before it is taken
    CONFIRM_SHARE = 0.5

    def __init__(self, period: float = 1.0, max_catchup_s: float = 300.0) -> None:
        self.period = float(period)
        self.max_catchup_s = float(max_catchup_s)
        self.stats = FrameClockStats()
        self._now: float | None = None  # clock time of the latest frame taken
        self._k_next = 0  # the next boundary is _k_next * period
        self._offset = 0.0  # clock time = timestamp + offset (joined segments)
        self._jump: list[float] | None = None  # a jump being judged: [first, last clock time, frames]
        self._none = Boundaries(range(0), self.period)
        self._frames_tick = 0  # frames observed since the last boundary crossed
        self._frames_per_tick = 0  # frames observed in the last interval that ended at a boundary

    @property
    def started(self) -> bool:
        return self._now is not None

    @property
    def offset(self) -> float:
        """Clock time minus frame timestamp, s (0 unless a backward jump was joined on)."""
        return self._offset

    @property
    def judging(self) -> int:
        """Frames of a jump not judged yet (0: none)."""
        return int(self._jump[2]) if self._jump is not None else 0

    def now(self) -> float:
        return self._now if self._now is not None else time.time()

    def behind(self, ts: float | None) -> float:
        """How far a frame stamped ``ts`` lies behind the clock after :meth:`observe` took it, s
        (its timestamp on the clock's scale, joined segments' offset included): 0 for a frame
        that advanced the clock, under a tick for jitter, as far as it is for the frames of a jump
        being judged (used at the clock's time meanwhile) and for a corrupt stamp. 0 without a
        timestamp or before the first frame."""
        if ts is None or not math.isfinite(ts) or self._now is None:
            return 0.0
        return max(0.0, self._now - (float(ts) + self._offset))

    def observe(self, ts: float | None) -> Boundaries:
        """Advance to a frame timestamp; return the boundaries crossed (oldest first)."""
        if ts is None or not math.isfinite(ts):
            return self._none
        self._frames_tick += 1
        t = float(ts) + self._offset
        if self._now is None:
            self._now = t
            self._k_next = math.floor(t / self.period) + 1  # first_boundary(t)
            return self._none
        d = t - self._now
        if d < 0:
            st = self.stats
            st.behind += 1
            st.behind_max_s = max(st.behind_max_s, -d)
        if -self.period < d <= self.max_catchup_s:  # keeps to the clock
            if self._jump is not None:
                self._ignore_jump()
            if d <= 0:
                if d < 0:
                    self.stats.jitter += 1
                return self._none
            return self._advance(t)
        jump = self._jump
        if jump is not None and jump[1] - self.period < t <= jump[1] + self.max_catchup_s:
            jump[1] = max(jump[1], t)
            jump[2] += 1
        else:
            if jump is not None:
                self._ignore_jump()
            jump = self._jump = [t, t, 1.0]
        if jump[2] >= self._confirm_frames() and jump[1] - jump[0] >= self.period:
            return self._take_jump()
        return self._none

    def _confirm_frames(self) -> int:
        """Frames that must keep to a jump before it is taken (see the class docstring)."""
        return max(self.CONFIRM_FRAMES, math.ceil(self.CONFIRM_SHARE * self._frames_per_tick))

    def _advance(self, t: float) -> Boundaries:
        self._now = t
        p = self.period
        if self._k_next * p > t:
            return self._none
        self._frames_per_tick, self._frames_tick = self._frames_tick, 0
        k_last = math.floor(t / p)
        if (k_last + 1) * p <= t:  # round-off of the division
            k_last += 1
        ks = range(self._k_next, k_last + 1)
        self._k_next = k_last + 1
        return Boundaries(ks, p)

    def _take_jump(self) -> Boundaries:
        assert self._jump is not None and self._now is not None
        first, last, frames = self._jump
        self._jump = None
        st = self.stats
        if first < self._now:  # backwards: a new segment, joined on where the clock is
            shift = self._now - first
            self._offset += shift
            st.joined += 1
            st.joined_s += shift
            log.warning("frame timestamps went back %.3f s and %d frames kept to it: a new recording segment, "
                        "joined on at clock time %.3f without a gap (clock = timestamp %+.3f s from now on); "
                        "%d backward jump(s) so far", shift, int(frames), self._now, self._offset, st.joined)
            return self._advance(last + shift)
        st.ahead += 1
        log.warning("frame timestamps jumped %.0f s ahead of the frame clock and %d frames kept to it: "
                    "a gap in the frames", first - self._now, int(frames))
        return self._advance(last)

    def _ignore_jump(self) -> None:
        assert self._jump is not None and self._now is not None
        first, _, frames = self._jump
        self._jump = None
        st = self.stats
        st.ignored += 1
        st.ignored_frames += int(frames)
        log.warning("%d frame(s) stamped %+.3f s from the frame clock (at %.3f), then frames on the clock's time "
                    "again: a corrupt timestamp, ignored for the clock (the frames' data used); %d so far",
                    int(frames), first - self._now, self._now, st.ignored)
