"""Counters of the CAN layer: frame integrity drops and transport health.

Plain counters, no I/O; the service exports them as metrics.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, fields

__all__ = ["DROP_REASONS", "DROP_REPORT_INTERVAL_S", "DropReport", "FrameStats", "TransportStats"]

#: Reasons for which the codec drops a received frame.
DROP_REASONS: tuple[str, ...] = (
    "crc",
    "counter_repeat",
    "unknown_id",
    "dlc",
    "decode_error",
    "fd",
)


@dataclass
class FrameStats:
    """Frame counters of one :class:`~thermal_edge.bus.codec.FrameCodec`.

    Attributes
    ----------
    crc, counter_repeat, unknown_id, dlc, decode_error, fd : int
        Received frames dropped, by reason: wrong CRC; alive counter equal to
        the previous accepted one; identifier not in the DBC (or extended,
        remote or error frame); data length not the DBC's; anything else that
        could not be decoded (bad input types included); a CAN FD frame on an
        identifier the DBC defines as classic CAN (a gateway or inverter set
        up for FD, whose layout the matrix does not describe).
    lost : int
        Frames missing before an accepted one, from its time stamp, cycle time and
        alive counter together (see :meth:`FrameCodec.decode`); a gap that turns out to
        be a late sender catching up is taken back.
    counter_resync : int
        Accepted frames whose counter was not judged because the previous one
        of that frame was too long ago (``resync_after_cycles`` cycle times).
    clamped : int
        Signal values saturated to the DBC range when encoding.
    received, sent : collections.Counter
        Accepted received frames and encoded frames, per frame name.
    dropped_by_frame, lost_by_frame : collections.Counter
        Drops and lost frames per frame name (known identifiers only).
    """

    crc: int = 0
    counter_repeat: int = 0
    unknown_id: int = 0
    dlc: int = 0
    decode_error: int = 0
    fd: int = 0
    lost: int = 0
    counter_resync: int = 0
    clamped: int = 0
    received: Counter[str] = field(default_factory=Counter)
    sent: Counter[str] = field(default_factory=Counter)
    dropped_by_frame: Counter[str] = field(default_factory=Counter)
    lost_by_frame: Counter[str] = field(default_factory=Counter)

    @property
    def dropped(self) -> dict[str, int]:
        """Drops by reason, every reason of :data:`DROP_REASONS` present."""
        return {reason: getattr(self, reason) for reason in DROP_REASONS}

    @property
    def dropped_total(self) -> int:
        """All dropped received frames."""
        return sum(self.dropped.values())

    def count_drop(self, reason: str, frame_name: str | None = None) -> None:
        """Count one dropped frame.

        Parameters
        ----------
        reason : str
            One of :data:`DROP_REASONS`.
        frame_name : str, optional
            Frame name if the identifier is known.
        """
        if reason not in DROP_REASONS:
            raise ValueError(f"unknown drop reason {reason!r}")
        setattr(self, reason, getattr(self, reason) + 1)
        if frame_name is not None:
            self.dropped_by_frame[frame_name] += 1

    def as_dict(self) -> dict[str, object]:
        """Snapshot as plain ``dict`` (counters copied to ``dict``)."""
        out: dict[str, object] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = dict(value) if isinstance(value, Counter) else value
        return out


#: Least time between two log lines about dropped frames, s: a flood of bad frames is one line a
#: minute in the journal, with the count by reason (the metrics count every frame).
DROP_REPORT_INTERVAL_S = 60.0


class DropReport:
    """The received frames dropped since the last report, by reason, at most once per ``interval_s``.

    Plain bookkeeping on a :class:`FrameStats`; the caller logs the line :meth:`due` returns.
    """

    def __init__(self, stats: FrameStats, interval_s: float = DROP_REPORT_INTERVAL_S) -> None:
        self.stats = stats
        self.interval_s = float(interval_s)
        self._reported = dict(stats.dropped)
        self._at: float | None = None

    def due(self, now: float) -> str | None:
        """The line to log at ``now`` (s, any monotonic clock): the drops since the last line by
        reason, and the frames they were of; None when there were none or the last line is younger
        than the interval."""
        if self._at is not None and now - self._at < self.interval_s:
            return None
        dropped = self.stats.dropped
        new = {k: v - self._reported.get(k, 0) for k, v in dropped.items() if v > self._reported.get(k, 0)}
        if not new:
            return None
        since = "since the start" if self._at is None else f"in the last {now - self._at:.0f} s"
        self._reported, self._at = dict(dropped), now
        frames = ", ".join(f"{k} {v}" for k, v in self.stats.dropped_by_frame.most_common(4))
        return (f"{sum(new.values())} received frame(s) dropped {since}: "
                + ", ".join(f"{k} {v}" for k, v in new.items())
                + (f" (in all, by frame: {frames})" if frames else "") + "; thermal_edge_frames_dropped_total counts them")


@dataclass
class TransportStats:
    """Health counters of one :class:`~thermal_edge.bus.transport.CanTransport`.

    Attributes
    ----------
    bus_errors : int
        Errors raised by the bus (open, receive or send failed, bus closed/down).
    reconnects : int
        Successful (re)opens of the bus after the first one.
    tx_frames : int
        Frames handed to the bus without error.
    tx_failed : int
        Frames not sent: bus down or send error.
    rx_messages : int
        Raw messages received from the bus (before integrity checks, own echoes
        excluded).
    rx_undecodable : int
        Received messages the bus could not turn into a CAN message (a datagram that is not
        python-can's format, a malformed frame); each is skipped, the bus stays open.
    own_echo : int
        Received messages ignored as this node's own frames looped back (``udp_multicast``
        loops a sender's frames back): one of its identifiers with data it sent.
    foreign_own_id : int
        Received messages with one of this node's identifiers and data it did not send: another
        node sends this node's frames (two sources of ``TE_Limits``); never obeyed, logged.
    provider_errors : int
        Cyclic-frame providers that raised or returned unusable signals.
    fallback_sent : int
        Cyclic frames sent from the fallback values instead of the provider's.
    cyclic_overruns : int
        Cyclic periods missed because the sender (loop or thread) was late by more than a period.
    callback_errors : int
        Frame callbacks that raised.
    queue_overflow : int
        Decoded frames dropped because the output queue was full.
    """

    bus_errors: int = 0
    reconnects: int = 0
    tx_frames: int = 0
    tx_failed: int = 0
    rx_messages: int = 0
    rx_undecodable: int = 0
    own_echo: int = 0
    foreign_own_id: int = 0
    provider_errors: int = 0
    fallback_sent: int = 0
    cyclic_overruns: int = 0
    callback_errors: int = 0
    queue_overflow: int = 0

    def as_dict(self) -> dict[str, int]:
        """Snapshot as plain ``dict``."""
        return {f.name: getattr(self, f.name) for f in fields(self)}
