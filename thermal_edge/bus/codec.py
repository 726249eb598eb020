"""Encode and decode the frames of ``dbc/thermal_edge.dbc`` with their protection.

:class:`FrameCodec` wraps the cantools database. ``encode`` fills the alive
counter and the CRC; ``decode`` checks length, CRC and counter and never raises:
a frame that fails a check is dropped (``None``) and counted by reason in a
:class:`~thermal_edge.bus.stats.FrameStats`.

Values are in the DBC's physical units (A, rpm, Nm, V, degC, s, K). A
temperature whose raw value is the DBC's ``NoValueRaw`` (0xFFF) decodes to NaN,
and NaN encodes to it.
"""

from __future__ import annotations

import logging
import math
import numbers
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path
from typing import Any, Protocol

import cantools
from cantools.database.can import Message as _DbcMessage
from cantools.database.can import Signal as _DbcSignal

from ..errors import ThermalEdgeError
from .crc import frame_crc, frame_crc_function
from .frames import COUNTER_SUFFIX, CRC_SUFFIX, DEFAULT_DBC_PATH
from .stats import FrameStats

__all__ = [
    "DbcError",
    "DecodedFrame",
    "FrameCodec",
    "FrameEncodeError",
    "MessageLike",
]

log = logging.getLogger(__name__)

FrameRef = str | int
COUNTER_START_BIT, COUNTER_BITS = 48, 4
CRC_START_BIT, CRC_BITS = 56, 8
_NO_VALUE_ATTRIBUTE = "NoValueRaw"
_CYCLE_ATTRIBUTE = "GenMsgCycleTime"
#: Frame periods between two frames of an identifier from which their time stamps decide how
#: often the 4-bit counter wrapped (3/4 of a wrap: bursts of up to 11 frames keep their count).
_WRAP_FROM_PERIODS = 12.0
#: Frame periods after a gap that added counter wraps during which the sender is watched for
#: catching up (frames faster than its cycle); a late sender that does takes the wraps back.
_CATCH_UP_PERIODS = 64
#: Frames over which a sender's time per frame is averaged (plain mean up to then, then running).
_PACE_FRAMES = 64
#: Gaps seen before the pace is trusted, and the band around the DBC cycle it must lie in.
_PACE_MIN_GAPS = 8
_PACE_BAND = (0.5, 2.0)
#: Cycles a sender's time stamps may run early; time counts a counter wrap only from 16 minus
#: this many periods beyond the counter step (a late sender is never counted as lost frames).
_WRAP_EARLY_CYCLES = 2.0
#: A repeated counter this many of the sender's own frame times after its last frame is no
#: duplicate (a duplicate follows at once) but a sender that restarted its counter (a reset).
_REPEAT_WITHIN_PACES = 3.0


def _keeps_cycle(pace: tuple[float, int] | None, cycle: float) -> bool:
    """True if a sender's running mean time per frame is near its DBC cycle.

    Time stamps can count counter wraps only for a sender that keeps its cycle; one that sends
    at another rate (an accelerated emulator at 10x the cycle, a load test at 1/40 of it) would
    have every ordinary gap taken for a hole (or a hole for an ordinary gap).
    """
    return pace is not None and pace[1] >= _PACE_MIN_GAPS and _PACE_BAND[0] <= pace[0] / cycle <= _PACE_BAND[1]


class DbcError(ThermalEdgeError, ValueError):
    """The DBC cannot be loaded or breaks the conventions of the CAN matrix."""


class FrameEncodeError(ThermalEdgeError, ValueError):
    """Signals given to :meth:`FrameCodec.encode` do not fit the frame."""


class MessageLike(Protocol):
    """What :meth:`FrameCodec.decode_message` reads from a message (python-can's ``can.Message`` fits)."""

    arbitration_id: int
    data: Any
    timestamp: float
    is_extended_id: bool
    is_error_frame: bool
    is_remote_frame: bool
    is_rx: bool


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    """One accepted received frame.

    Attributes
    ----------
    name : str
        Frame name in the DBC (e.g. ``"INV_Currents"``).
    frame_id : int
        11-bit CAN identifier.
    signals : dict of str to float
        Physical values of the frame's signals in DBC units (counter and CRC
        excluded). Temperatures without value are NaN; enumerations, flags and
        counts are ``int``.
    counter : int
        Alive counter of the frame, 0..15.
    timestamp : float or None
        Reception (or log) time in seconds (POSIX epoch for live buses), if known.
    lost_before : int
        Frames of this identifier missing just before this one (counter gap).
    is_rx : bool
        False for frames this node transmitted (read back from a log).
    """

    name: str
    frame_id: int
    signals: dict[str, float]
    counter: int
    timestamp: float | None = None
    lost_before: int = 0
    is_rx: bool = True


@dataclass(frozen=True, slots=True)
class _SignalSpec:
    name: str
    signal: _DbcSignal
    raw_min: int
    raw_max: int
    no_value_raw: int | None
    identity: bool  # factor 1, offset 0: physical value is the raw integer
    decimals: int  # decimals of factor and offset: decoded values are rounded to them
    # decoding without cantools (every signal of the matrix is little-endian, checked at load)
    start: int
    mask: int
    sign_bit: int  # 1 << (length - 1) for signed signals, 0 for unsigned
    scale: float
    offset: float


@dataclass(frozen=True, slots=True)
class _FrameSpec:
    name: str
    frame_id: int
    length: int
    message: _DbcMessage
    signals: tuple[_SignalSpec, ...]
    counter_name: str
    crc_name: str
    cycle_time_s: float | None
    senders: frozenset[str]
    crc: Callable[[bytes | bytearray], int]
    by_name: dict[str, _SignalSpec] = field(default_factory=dict)


def _bit_range(sig: _DbcSignal) -> tuple[int, int]:
    if sig.is_signed:
        return -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    return 0, (1 << sig.length) - 1


def _raw_limits(sig: _DbcSignal) -> tuple[int, int]:
    lo, hi = _bit_range(sig)
    scale, offset = float(sig.scale), float(sig.offset)
    if sig.minimum is not None:
        lo = max(lo, math.ceil((float(sig.minimum) - offset) / scale - 1e-6))
    if sig.maximum is not None:
        hi = min(hi, math.floor((float(sig.maximum) - offset) / scale + 1e-6))
    return lo, hi


def _signal_spec(sig: _DbcSignal) -> _SignalSpec:
    no_value: int | None = None
    if sig.dbc is not None and _NO_VALUE_ATTRIBUTE in sig.dbc.attributes:
        value = int(sig.dbc.attributes[_NO_VALUE_ATTRIBUTE].value)
        no_value = value if value >= 0 else None
    raw_min, raw_max = _raw_limits(sig)
    identity = float(sig.scale) == 1.0 and float(sig.offset) == 0.0
    decimals = max(0, *(-int(Decimal(str(v)).normalize().as_tuple().exponent) for v in (sig.scale, sig.offset)))
    return _SignalSpec(sig.name, sig, raw_min, raw_max, no_value, identity, decimals, sig.start,
                       (1 << sig.length) - 1, (1 << (sig.length - 1)) if sig.is_signed else 0,
                       float(sig.scale), float(sig.offset))


def _frame_spec(msg: _DbcMessage, path: Path) -> _FrameSpec:
    where = f"{path}: frame {msg.name} (0x{msg.frame_id:03X})"
    if msg.is_extended_frame or msg.frame_id > 0x7FF:
        raise DbcError(f"{where}: only 11-bit identifiers are allowed")
    if msg.length != 8:
        raise DbcError(f"{where}: DLC {msg.length}, the CAN matrix requires 8")
    counter_name, crc_name = msg.name + COUNTER_SUFFIX, msg.name + CRC_SUFFIX
    for name, start, bits in ((counter_name, COUNTER_START_BIT, COUNTER_BITS), (crc_name, CRC_START_BIT, CRC_BITS)):
        try:
            sig = msg.get_signal_by_name(name)
        except KeyError:
            raise DbcError(f"{where}: signal {name} missing") from None
        if (sig.start, sig.length, sig.byte_order, sig.is_signed) != (start, bits, "little_endian", False):
            raise DbcError(f"{where}: signal {name} must be unsigned little-endian at bit {start}, {bits} bits")
    for sig in msg.signals:
        if sig.byte_order != "little_endian":
            raise DbcError(f"{where}: signal {sig.name} is big-endian; the CAN matrix uses little-endian only")
    cycle: int | float | str | None = msg.cycle_time  # a DBC attribute's value may be of any of these
    if cycle is None and msg.dbc is not None and _CYCLE_ATTRIBUTE in msg.dbc.attributes:
        cycle = msg.dbc.attributes[_CYCLE_ATTRIBUTE].value
    specs = tuple(_signal_spec(s) for s in msg.signals if s.name not in (counter_name, crc_name))
    return _FrameSpec(
        name=msg.name,
        frame_id=msg.frame_id,
        length=msg.length,
        message=msg,
        signals=specs,
        counter_name=counter_name,
        crc_name=crc_name,
        cycle_time_s=float(cycle) / 1000.0 if cycle else None,
        senders=frozenset(msg.senders or ()),
        crc=frame_crc_function(msg.frame_id),
        by_name={s.name: s for s in specs},
    )


#: Cycle times after which a silent sender is taken to have restarted (its counter not judged): long
#: enough that a real hole is counted as lost frames (from the time stamps), not forgiven.
DEFAULT_RESYNC_AFTER_CYCLES = 1000.0


class FrameCodec:
    """DBC-based encoder/decoder with alive counter and CRC handling.

    Parameters
    ----------
    dbc_path : str or Path, optional
        The DBC to load (strict mode). Defaults to the project's
        ``dbc/thermal_edge.dbc``.
    stats : FrameStats, optional
        Where to count frames; a new one by default (see :attr:`stats`).
    resync_after_cycles : float, optional
        If two accepted frames of one identifier are more than this many cycle
        times apart (timestamps known), the sender is taken to have been silent or
        restarted: the gap is not counted as lost frames and the counter of the
        second is not judged (``counter_resync``). Below it, frames missing in
        between are counted as ``lost`` from the time stamps and the counter
        together (see :meth:`decode`). Default :data:`DEFAULT_RESYNC_AFTER_CYCLES`.
    wraps_from_time : bool, optional
        Let time stamps count the counter wraps of a long hole (default). Only right for a
        sender that transmits every cycle while alive (the inverter's frames); a receiver of
        frames that may pause without being lost (a service in simulated time bridging ticks)
        passes False and counts by the counter alone.

    Raises
    ------
    DbcError
        If the DBC cannot be loaded or a frame lacks the counter/CRC layout.

    Notes
    -----
    Encode and decode are thread-safe. Counters for transmission (one per
    frame, +1 mod 16 per :meth:`encode`) and for reception (last accepted
    counter per identifier) are kept apart.
    """

    def __init__(
        self,
        dbc_path: str | Path = DEFAULT_DBC_PATH,
        *,
        stats: FrameStats | None = None,
        resync_after_cycles: float = DEFAULT_RESYNC_AFTER_CYCLES,
        wraps_from_time: bool = True,
    ) -> None:
        self._path = Path(dbc_path)
        try:
            db = cantools.database.load_file(str(self._path), strict=True)
        except Exception as exc:  # cantools raises many types; report one line
            raise DbcError(f"{self._path}: cannot load DBC: {exc}") from exc
        if not isinstance(db, cantools.database.can.Database):
            raise DbcError(f"{self._path}: not a CAN database")
        self._db = db
        self._frames: dict[int, _FrameSpec] = {}
        self._by_name: dict[str, _FrameSpec] = {}
        for msg in self._db.messages:
            spec = _frame_spec(msg, self._path)
            self._frames[spec.frame_id] = spec
            self._by_name[spec.name] = spec
        self.stats: FrameStats = stats if stats is not None else FrameStats()
        self._resync_after = float(resync_after_cycles)
        self._wraps_from_time = bool(wraps_from_time)
        self._lock = threading.Lock()
        self._tx_counter: dict[int, int] = {}
        # last accepted counter, its time stamp (s), the sender's pace (see _keeps_cycle) and the
        # frames its time stamp added to the counter step
        self._rx_last: dict[int, tuple[int, float | None, tuple[float, int] | None, tuple[int, float, int] | None]] = {}

    # ------------------------------------------------------------------ lookup
    @property
    def dbc_path(self) -> Path:
        """Path of the loaded DBC."""
        return self._path

    @property
    def database(self) -> cantools.database.can.Database:
        """The cantools database (read only by convention)."""
        return self._db

    def _spec(self, frame: FrameRef) -> _FrameSpec:
        spec = self._by_name.get(frame) if isinstance(frame, str) else self._frames.get(frame)
        if spec is None:
            ref = frame if isinstance(frame, str) else f"0x{frame:X}"
            raise KeyError(f"frame {ref} is not in {self._path.name}")
        return spec

    def frame_id(self, frame: FrameRef) -> int:
        """CAN identifier of a frame given by name or identifier (KeyError if unknown)."""
        return self._spec(frame).frame_id

    def frame_name(self, frame: FrameRef) -> str:
        """Name of a frame given by name or identifier (KeyError if unknown)."""
        return self._spec(frame).name

    def cycle_time_s(self, frame: FrameRef) -> float | None:
        """Cycle time of a frame in seconds (``GenMsgCycleTime``), None if not cyclic."""
        return self._spec(frame).cycle_time_s

    def signal_names(self, frame: FrameRef) -> tuple[str, ...]:
        """Application signals of a frame (counter and CRC excluded), in DBC order."""
        return tuple(s.name for s in self._spec(frame).signals)

    def frame_ids(self) -> frozenset[int]:
        """Identifiers of all frames of the DBC."""
        return frozenset(self._frames)

    def frames_sent_by(self, node: str) -> frozenset[int]:
        """Identifiers of the frames whose DBC sender is ``node`` (e.g. ``"TE"``)."""
        return frozenset(fid for fid, s in self._frames.items() if node in s.senders)

    # ------------------------------------------------------------------ encode
    def _raw_value(self, frame: _FrameSpec, spec: _SignalSpec, value: Any) -> int:
        sig = spec.signal
        if isinstance(value, str) or type(value).__name__ == "NamedSignalValue":
            try:
                raw = sig.conversion.choice_to_number(str(value)) if sig.choices else None
            except KeyError:
                raw = None
            if raw is None:
                raise FrameEncodeError(f"{frame.name}.{spec.name}: {value!r} is not one of its named values")
            return int(raw)
        try:
            x = float(value)  # int, float, bool, IntEnum, numpy scalars and 0-d arrays
        except (TypeError, ValueError):
            raise FrameEncodeError(
                f"{frame.name}.{spec.name}: expected a number, got {type(value).__name__}"
            ) from None
        if math.isnan(x):
            if spec.no_value_raw is None:
                raise FrameEncodeError(f"{frame.name}.{spec.name}: NaN, and the signal has no 'no value' code")
            return spec.no_value_raw
        if math.isinf(x):  # deliberate saturation (e.g. TE_TimeToLimit = inf), not counted
            return spec.raw_max if x > 0 else spec.raw_min
        raw = round((x - float(sig.offset)) / float(sig.scale))
        if raw < spec.raw_min or raw > spec.raw_max:
            with self._lock:
                self.stats.clamped += 1
            log.debug("%s.%s: %r outside the DBC range, saturated", frame.name, spec.name, value)
            return min(max(raw, spec.raw_min), spec.raw_max)
        return int(raw)

    def encode(self, frame: FrameRef, signals: Mapping[str, Any], *, counter: int | None = None) -> bytes:
        """Encode one frame, alive counter and CRC included.

        Parameters
        ----------
        frame : str or int
            Frame name or CAN identifier.
        signals : mapping of str to number
            Physical value of every application signal of the frame, in DBC
            units (A, rpm, Nm, V, degC, s, K; enumerations as int, IntEnum or
            value-table name). NaN encodes a temperature as "no value" (0xFFF);
            values outside the DBC range (inf included) are saturated to it and
            counted in ``stats.clamped``. Counter/CRC entries are ignored.
        counter : int, optional
            Force the alive counter (0..15), for tests and emulators; by default
            the frame's transmit counter is used and advanced by 1 (mod 16).

        Returns
        -------
        bytes
            The 8 data bytes, CRC in byte 7.

        Raises
        ------
        KeyError
            Unknown frame.
        FrameEncodeError
            Missing or unknown signal, non-numeric value, or NaN on a signal
            without a "no value" code.
        """
        spec = self._spec(frame)
        if not isinstance(signals, Mapping):
            raise FrameEncodeError(f"{spec.name}: signals must be a mapping, got {type(signals).__name__}")
        unknown = set(signals) - set(spec.by_name) - {spec.counter_name, spec.crc_name}
        if unknown:
            raise FrameEncodeError(f"{spec.name}: unknown signal(s) {', '.join(sorted(unknown))}")
        missing = [s.name for s in spec.signals if s.name not in signals]
        if missing:
            raise FrameEncodeError(f"{spec.name}: missing signal(s) {', '.join(missing)}")
        raw = {s.name: self._raw_value(spec, s, signals[s.name]) for s in spec.signals}
        raw[spec.crc_name] = 0
        with self._lock:
            if counter is None:
                value = self._tx_counter.get(spec.frame_id, 0)
            else:
                if not 0 <= int(counter) <= 15:
                    raise FrameEncodeError(f"{spec.name}: counter {counter} outside 0..15")
                value = int(counter)
            raw[spec.counter_name] = value
            try:
                data = bytearray(spec.message.encode(raw, scaling=False, strict=True))
            except Exception as exc:
                raise FrameEncodeError(f"{spec.name}: {exc}") from exc
            self._tx_counter[spec.frame_id] = (value + 1) % 16
            self.stats.sent[spec.name] += 1
        data[7] = frame_crc(spec.frame_id, data)
        return bytes(data)

    # ------------------------------------------------------------------ decode
    def decode(
        self,
        arbitration_id: int,
        data: Any,
        *,
        timestamp: float | None = None,
        is_rx: bool = True,
        is_extended_id: bool = False,
    ) -> DecodedFrame | None:
        """Check and decode one received frame; never raises.

        Parameters
        ----------
        arbitration_id : int
            CAN identifier.
        data : bytes-like
            Frame data (must be exactly the DBC length, 8 bytes).
        timestamp : float, optional
            Reception time in seconds, used for counter resynchronisation and
            passed through.
        is_rx : bool, optional
            Passed through to :attr:`DecodedFrame.is_rx`.
        is_extended_id : bool, optional
            A 29-bit identifier is never one of ours (dropped as ``unknown_id``).

        Returns
        -------
        DecodedFrame or None
            None if the frame was dropped: unknown identifier, wrong length,
            wrong CRC, repeated counter or undecodable. Each drop is counted in
            :attr:`stats`; frames missing before this one are counted as ``lost``.

        Notes
        -----
        Lost frames: with the time stamps of this and the previous accepted frame of the
        identifier and its DBC cycle time ``T``, about ``dt / T`` frame periods have passed;
        the 4-bit counter fixes their number ``n`` modulo 16, so ``n`` is the counter step
        plus the whole number of counter wraps that brings it nearest to ``dt / T`` (exact
        while the timing jitter stays below 3/8 of a cycle), and ``n - 1`` frames are lost. A
        counter alone hides every multiple of 16 (a hole of 17 frames looks like one of 1).
        Time stamps only add wraps, only once they span 12 periods or more, and only for a
        sender whose mean time per frame (over about 64 frames, at least 8) lies within half
        and twice its DBC cycle: frames that arrive in bursts, without time stamps, or from a
        sender at another rate (an accelerated emulator, a load test) are judged by the
        counter step alone, which counts holes modulo 16. A sender that was late and catches up
        sends the frames after such a gap faster than its cycle: once, within 64 frame periods of
        the gap, its frames run more than 2 cycles ahead of the cadence the gap's frame started
        (more than its timing jitter can), the wraps counted for the gap are taken back from
        ``stats.lost`` (the ``lost_before`` already returned stays). A step of 0 is a repeated
        frame, dropped; it still counts as the sender's latest frame, so a sender whose counter is
        frozen is dropped for as long as it keeps sending (its input goes stale), and only a
        pause of ``resync_after_cycles`` or of 3 of its frame times before a repeated counter
        passes for a restarted sender.
        """
        try:
            return self._decode(arbitration_id, data, timestamp, is_rx, is_extended_id)
        except Exception:  # never raise on bad input
            log.debug("undecodable frame id=%r data=%r", arbitration_id, data, exc_info=True)
            with self._lock:
                self.stats.count_drop("decode_error")
            return None

    def _decode(
        self, arbitration_id: Any, data: Any, timestamp: float | None, is_rx: bool, is_extended_id: bool
    ) -> DecodedFrame | None:
        spec = None
        if not is_extended_id and isinstance(arbitration_id, numbers.Integral):
            spec = self._frames.get(int(arbitration_id))
        if spec is None:
            with self._lock:
                self.stats.count_drop("unknown_id")
            return None
        if type(data) is bytes or type(data) is bytearray:  # the usual case: no copy, no checks
            payload = data
        elif data is None or isinstance(data, str):
            payload = None
        else:
            try:
                payload = bytes(data)
            except (TypeError, ValueError):
                payload = None
        if payload is None:
            with self._lock:
                self.stats.count_drop("decode_error", spec.name)
            return None
        if len(payload) != spec.length:
            with self._lock:
                self.stats.count_drop("dlc", spec.name)
            return None
        if payload[7] != spec.crc(payload):
            with self._lock:
                self.stats.count_drop("crc", spec.name)
            return None
        word = int.from_bytes(payload, "little")
        values: dict[str, float] = {}
        for s in spec.signals:
            r = (word >> s.start) & s.mask
            if s.sign_bit and r & s.sign_bit:
                r -= s.sign_bit << 1
            if r == s.no_value_raw:
                values[s.name] = math.nan
            elif s.identity:
                values[s.name] = r
            else:
                values[s.name] = round(r * s.scale + s.offset, s.decimals)
        counter = (word >> COUNTER_START_BIT) & 0xF
        ts = float(timestamp) if timestamp is not None else None
        with self._lock:
            lost = 0
            last = self._rx_last.get(spec.frame_id)
            pace = None  # running mean of the time per frame (s) and how many gaps it has seen
            # wraps the last gap added that a catch-up would take back: (wraps, the gap frame's
            # time stamp, frame periods since it), until the sender is seen to keep its cadence
            owed: tuple[int, float, int] | None = None
            if last is not None:
                last_counter, last_ts, pace, owed = last
                step = (counter - last_counter) % 16
                cycle = spec.cycle_time_s
                dt = ts - last_ts if ts is not None and last_ts is not None else None
                if dt is not None and cycle and abs(dt) > self._resync_after * cycle:
                    self.stats.counter_resync += 1
                    pace, owed = None, None
                else:
                    # frame periods since the last one: the counter step plus the whole counter
                    # wraps that bring it nearest to the time stamps, once these span most of a
                    # wrap and the sender is seen to keep its DBC cycle; else the step alone
                    n, wraps = step, 0
                    if (self._wraps_from_time and dt is not None and cycle and dt / cycle >= _WRAP_FROM_PERIODS
                            and _keeps_cycle(pace, cycle)):
                        # rounded down: a sender that is late (a busy host) makes dt longer, never
                        # shorter, than its frame periods; only early jitter needs the allowance
                        wraps = 16 * max(0, math.floor((dt / cycle - step + _WRAP_EARLY_CYCLES) / 16))
                        n += wraps
                    if n == 0 and dt is not None and pace is not None and pace[1] >= _PACE_MIN_GAPS \
                            and dt > _REPEAT_WITHIN_PACES * max(pace[0], cycle or 0.0):
                        # the same counter long after the last frame, not explained by whole wraps:
                        # a sender that restarted its counter (an inverter reset), not a duplicate
                        self.stats.counter_resync += 1
                        n, pace = 1, None
                    if n == 0:
                        self.stats.count_drop("counter_repeat", spec.name)
                        # the repeat is the sender's latest sign of life: a sender whose counter is
                        # frozen (a hung task, its controller resending the last buffer) is never
                        # silent, so its repeats never pass for a restart or a resync
                        self._rx_last[spec.frame_id] = (last_counter, ts if ts is not None else last_ts, pace, owed)
                        return None
                    lost = n - 1
                    if lost:
                        self.stats.lost += lost
                        self.stats.lost_by_frame[spec.name] += lost
                    if owed is not None and ts is not None and cycle:  # owed wraps were counted from the cycle
                        owed_wraps, t_gap, periods = owed[0], owed[1], owed[2] + n
                        if ts - t_gap < (periods - _WRAP_EARLY_CYCLES) * cycle:
                            # ahead of the cadence by more than jitter: the sender was late and is
                            # catching up, the gap held no lost frames beyond its counter step
                            self.stats.lost -= owed_wraps
                            self.stats.lost_by_frame[spec.name] -= owed_wraps
                            owed = None
                        else:
                            owed = (owed_wraps, t_gap, periods) if periods < _CATCH_UP_PERIODS else None
                    if wraps and ts is not None:
                        owed = (wraps, ts, 0)
                    if dt is not None:  # signed: jitter that reorders time stamps averages out
                        gaps = 0 if pace is None else pace[1]
                        mean = 0.0 if pace is None else pace[0]
                        pace = (mean + (dt / n - mean) / min(gaps + 1, _PACE_FRAMES), gaps + 1)
            self._rx_last[spec.frame_id] = (counter, ts, pace, owed)
            self.stats.received[spec.name] += 1
        return DecodedFrame(spec.name, spec.frame_id, values, counter, ts, lost, bool(is_rx))

    def decode_message(self, msg: MessageLike) -> DecodedFrame | None:
        """Decode a python-can ``can.Message`` (or alike); never raises.

        Error frames and extended identifiers count as ``unknown_id``, remote
        frames as ``dlc``; everything else goes through :meth:`decode`.
        """
        try:
            if getattr(msg, "is_error_frame", False) or getattr(msg, "is_extended_id", False):
                with self._lock:
                    self.stats.count_drop("unknown_id")
                return None
            if getattr(msg, "is_remote_frame", False):
                spec = self._frames.get(msg.arbitration_id)
                with self._lock:
                    self.stats.count_drop("dlc" if spec else "unknown_id", spec.name if spec else None)
                return None
            return self.decode(
                msg.arbitration_id,
                msg.data,
                timestamp=getattr(msg, "timestamp", None),
                is_rx=getattr(msg, "is_rx", True),
            )
        except Exception:
            with self._lock:
                self.stats.count_drop("decode_error")
            return None
