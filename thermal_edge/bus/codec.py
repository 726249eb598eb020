"""Encode and decode the frames of a DBC with their protection.

:class:`FrameCodec` wraps the cantools database. ``encode`` fills the alive
counter and the CRC; ``decode`` checks length, CRC and counter and never raises:
a frame that fails a check is dropped (``None``) and counted by reason in a
:class:`~thermal_edge.bus.stats.FrameStats`.

Each frame's protection (:class:`~thermal_edge.bus.protection.FrameProtection`) is the CAN
matrix's where the frame carries its ``<frame>_Counter`` (bit 48, 4 bits) and ``<frame>_CRC``
(byte 7), else what the caller declares for it (another inverter's own matrix: another counter,
another CRC, or none). With ``service_frames`` the service's own frames (``TE_*``) are always
those of the shipped DBC, whatever DBC holds the inverter's frames.

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
from .crc import frame_crc_function, protection_crc_function
from .frames import COUNTER_SUFFIX, CRC_SUFFIX, DEFAULT_DBC_PATH, NODE_THERMAL_EDGE
from .protection import FrameProtection
from .stats import FrameStats

__all__ = [
    "DbcError",
    "DecodedFrame",
    "FrameCodec",
    "FrameEncodeError",
    "MessageLike",
    "ProtectionError",
]

log = logging.getLogger(__name__)

FrameRef = str | int
COUNTER_START_BIT, COUNTER_BITS = 48, 4
CRC_START_BIT, CRC_BITS = 56, 8
_NO_VALUE_ATTRIBUTE = "NoValueRaw"
_CYCLE_ATTRIBUTE = "GenMsgCycleTime"
#: Share of a counter wrap (frame periods between two frames of an identifier) from which their
#: time stamps decide how often the counter wrapped (3/4: with the matrix's 4-bit counter, 12
#: periods; bursts of up to 11 frames keep their count).
_WRAP_FROM_SHARE = 0.75
#: Counter wraps after a gap that added wraps during which the sender is watched for catching up
#: (frames faster than its cycle; 64 periods of a 4-bit counter); a late sender that does takes the
#: wraps back.
_CATCH_UP_WRAPS = 4
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


class ProtectionError(DbcError):
    """A frame's declared protection does not fit its DBC frame.

    Attributes
    ----------
    frame : str
        The frame's name (for a loader to name its key, ``codec.protection.<frame>``).
    """

    def __init__(self, frame: str, message: str) -> None:
        super().__init__(message)
        self.frame = frame


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
        Alive counter of the frame (0..15 on the matrix's frames); -1 for a frame without one.
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
    decimals: int | None  # decimals of factor and offset: decoded values are rounded to them (None: a float signal)
    # decoding without cantools (little-endian integer signals: every signal of the matrix)
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
    protection: FrameProtection | None  # None: not declared (decoded unchecked; the service refuses to read it)
    undeclared: str  # why it has none
    counter: _SignalSpec | None
    counter_mod: int  # 2**counter width
    crc_byte: int  # payload byte of the CRC (-1: none)
    crc: Callable[[bytes | bytearray], int] | None
    fast: bool  # every signal a little-endian integer: decoded from one integer, without cantools
    cycle_time_s: float | None
    senders: frozenset[str]
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
    decimals = None if sig.is_float else max(
        0, *(-int(Decimal(str(v)).normalize().as_tuple().exponent) for v in (sig.scale, sig.offset)))
    return _SignalSpec(sig.name, sig, raw_min, raw_max, no_value, identity, decimals, sig.start,
                       (1 << sig.length) - 1, (1 << (sig.length - 1)) if sig.is_signed else 0,
                       float(sig.scale), float(sig.offset))


def _unsupported(msg: _DbcMessage) -> str | None:
    """Why the codec cannot use a frame of a DBC, None if it can."""
    if msg.is_extended_frame or msg.frame_id > 0x7FF:
        return "it has a 29-bit identifier (only 11-bit identifiers are supported)"
    if msg.is_multiplexed():
        return "it is multiplexed (not supported)"
    if getattr(msg, "is_container", False):
        return "it is a container frame (not supported)"
    return None


def _matrix_protection(msg: _DbcMessage) -> tuple[FrameProtection | None, str]:
    """The CAN matrix's protection if the frame carries its counter and CRC where the matrix puts
    them; else None and why not."""
    sigs = {s.name: s for s in msg.signals}
    counter, crc = sigs.get(msg.name + COUNTER_SUFFIX), sigs.get(msg.name + CRC_SUFFIX)
    matrix = (f"the CAN matrix's {msg.name}{COUNTER_SUFFIX} (bit {COUNTER_START_BIT}, {COUNTER_BITS} bits) and "
              f"{msg.name}{CRC_SUFFIX} (bit {CRC_START_BIT}, {CRC_BITS} bits, DLC 8)")
    if counter is None or crc is None:
        return None, f"it has neither {matrix} nor a declared protection"
    if msg.length != 8 or (counter.start, counter.length, counter.byte_order, counter.is_signed) != (
            COUNTER_START_BIT, COUNTER_BITS, "little_endian", False) or (
            crc.start, crc.length, crc.byte_order, crc.is_signed) != (CRC_START_BIT, CRC_BITS, "little_endian", False):
        return None, f"its counter and CRC are not where the CAN matrix puts them: {matrix}; declare its protection"
    return FrameProtection.matrix(msg.name, msg.frame_id), ""


def _crc_byte(msg: _DbcMessage, sig: _DbcSignal) -> int | None:
    """The payload byte the 8-bit signal ``sig`` fills exactly, None if it spans two."""
    zero = {s.name: 0 for s in msg.signals}
    try:
        probe = msg.encode({**zero, sig.name: 0xFF}, scaling=False, strict=False)
    except Exception:
        return None
    full = [i for i, b in enumerate(probe) if b]
    return full[0] if len(full) == 1 and probe[full[0]] == 0xFF else None


def _frame_spec(msg: _DbcMessage, path: Path, protection: FrameProtection | None) -> _FrameSpec:
    where = f"{path}: frame {msg.name} (0x{msg.frame_id:03X})"
    undeclared = ""
    if protection is None:
        protection, undeclared = _matrix_protection(msg)
    sigs = {s.name: s for s in msg.signals}

    def bad(problem: str) -> ProtectionError:
        return ProtectionError(msg.name, f"{where}: protection {protection.describe() if protection else 'none'}: "
                               f"{problem}")

    counter_sig = crc_sig = None
    crc_byte, crc_fn = -1, None
    if protection is not None and protection.counter is not None:
        counter_sig = sigs.get(protection.counter)
        if counter_sig is None:
            raise bad(f"no signal {protection.counter!r} in the frame")
        if counter_sig.is_signed or counter_sig.is_float or not 1 <= counter_sig.length <= 16 \
                or float(counter_sig.scale) != 1.0 or float(counter_sig.offset) != 0.0:
            raise bad(f"the counter {counter_sig.name} must be an unsigned integer of 1 to 16 bits, factor 1, offset 0")
    if protection is not None and protection.crc is not None:
        crc_sig = sigs.get(protection.crc)
        if crc_sig is None:
            raise bad(f"no signal {protection.crc!r} in the frame")
        found = _crc_byte(msg, crc_sig) if crc_sig.length == 8 and not crc_sig.is_signed else None
        if found is None:
            raise bad(f"the CRC {crc_sig.name} must be an unsigned 8-bit signal filling one payload byte")
        crc_byte = found
        if protection == FrameProtection.matrix(msg.name, msg.frame_id) and crc_byte == 7 and msg.length == 8:
            crc_fn = frame_crc_function(msg.frame_id)  # the matrix's: unrolled, the data ID pre-computed
        else:
            crc_fn = protection_crc_function(protection.crc_algorithm, protection.data_id, crc_byte)
    skip = {s.name for s in (counter_sig, crc_sig) if s is not None}
    specs = tuple(_signal_spec(s) for s in msg.signals if s.name not in skip)
    fast = all(s.byte_order == "little_endian" and not s.is_float for s in msg.signals)
    cycle: int | float | str | None = msg.cycle_time  # a DBC attribute's value may be of any of these
    if cycle is None and msg.dbc is not None and _CYCLE_ATTRIBUTE in msg.dbc.attributes:
        cycle = msg.dbc.attributes[_CYCLE_ATTRIBUTE].value
    return _FrameSpec(
        name=msg.name,
        frame_id=msg.frame_id,
        length=msg.length,
        message=msg,
        signals=specs,
        protection=protection,
        undeclared=undeclared,
        counter=_signal_spec(counter_sig) if counter_sig is not None else None,
        counter_mod=1 << counter_sig.length if counter_sig is not None else 0,
        crc_byte=crc_byte,
        crc=crc_fn,
        fast=fast,
        cycle_time_s=float(cycle) / 1000.0 if cycle else None,
        senders=frozenset(msg.senders or ()),
        by_name={s.name: s for s in specs},
    )


def _layout(msg: _DbcMessage) -> tuple[Any, ...]:
    """What makes two DBC frames the same on the wire."""
    return (msg.name, msg.frame_id, msg.length, tuple(sorted(
        (s.name, s.start, s.length, s.byte_order, s.is_signed, float(s.scale), float(s.offset), s.minimum, s.maximum)
        for s in msg.signals)))


def dbc_encoding(path: Path) -> str:
    """The text encoding of the DBC at ``path``: UTF-8 where its bytes are valid UTF-8 (a unit
    such as ``°C`` written by a text editor), else cp1252 (what DBC editors write, and cantools'
    default). A cp1252 file with any byte above 127 is almost never valid UTF-8, so the order
    decides nothing else."""
    try:
        path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        return "cp1252"
    except OSError:  # cantools reports it, in the message the caller gives
        return "cp1252"
    return "utf-8"


def _load_dbc(path: Path) -> cantools.database.can.Database:
    try:
        db = cantools.database.load_file(str(path), strict=True, encoding=dbc_encoding(path))
    except Exception as exc:  # cantools raises many types; report one line
        raise DbcError(f"{path}: cannot load DBC: {exc}") from exc
    if not isinstance(db, cantools.database.can.Database):
        raise DbcError(f"{path}: not a CAN database")
    return db


#: Cycle times after which a silent sender is taken to have restarted (its counter not judged): long
#: enough that a real hole is counted as lost frames (from the time stamps), not forgiven.
DEFAULT_RESYNC_AFTER_CYCLES = 1000.0


def _physical(s: _SignalSpec, r: float) -> float:
    """The physical value of a raw one (NaN for the signal's "no value" code)."""
    if r == s.no_value_raw:
        return math.nan
    if s.identity:
        return r
    if s.decimals is None:
        return r * s.scale + s.offset
    return round(r * s.scale + s.offset, s.decimals)


def _did_you_mean(word: str, candidates: set[str]) -> str:
    import difflib

    close = difflib.get_close_matches(word, sorted(candidates), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


class FrameCodec:
    """DBC-based encoder/decoder with alive counter and CRC handling.

    Parameters
    ----------
    dbc_path : str or Path, optional
        The DBC to load (strict mode). Defaults to the project's
        ``dbc/thermal_edge.dbc``. Frames the codec cannot use (29-bit identifiers,
        multiplexed) are left out and named by :meth:`unsupported`.
    protection : mapping of str to FrameProtection, optional
        Declared protection per frame name, for frames that do not carry the CAN
        matrix's counter and CRC (``FrameProtection()``: none). A frame neither
        declared nor the matrix's is decoded unchecked and :meth:`protection` says so
        (None).
    service_frames : bool, optional
        Take the service's own frames (those the shipped DBC has node ``TE`` send)
        from the shipped DBC, with the matrix's protection, beside the frames of
        ``dbc_path``. A frame of ``dbc_path`` with the name or identifier of one of
        them must be that very frame (a copy of the shipped DBC).
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
        If the DBC cannot be loaded, or clashes with the service's own frames.
    ProtectionError
        A declared protection that does not fit its frame (named in ``frame``).

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
        protection: Mapping[str, FrameProtection] | None = None,
        service_frames: bool = False,
        stats: FrameStats | None = None,
        resync_after_cycles: float = DEFAULT_RESYNC_AFTER_CYCLES,
        wraps_from_time: bool = True,
    ) -> None:
        self._path = Path(dbc_path)
        self._db = _load_dbc(self._path)
        messages: list[tuple[_DbcMessage, Path]] = [(m, self._path) for m in self._db.messages]
        own: set[str] = set()
        if service_frames and self._path.resolve() != Path(DEFAULT_DBC_PATH).resolve():
            shipped = [m for m in _load_dbc(Path(DEFAULT_DBC_PATH)).messages if NODE_THERMAL_EDGE in (m.senders or ())]
            by_name, by_id = {m.name: m for m in shipped}, {m.frame_id: m for m in shipped}
            for msg, _ in messages:
                mine = by_name.get(msg.name) or by_id.get(msg.frame_id)
                if mine is not None and _layout(msg) != _layout(mine):
                    raise DbcError(f"{self._path}: frame {msg.name} (0x{msg.frame_id:03X}) clashes with the service's "
                                   f"own frame {mine.name} (0x{mine.frame_id:03X}), which it sends as the CAN matrix "
                                   "defines it: rename or remove it from this DBC")
            messages = [(m, p) for m, p in messages if m.name not in by_name] + [(m, Path(DEFAULT_DBC_PATH)) for m in shipped]
            own = set(by_name)
        elif service_frames:
            own = {m.name for m in self._db.messages if NODE_THERMAL_EDGE in (m.senders or ())}
        declared = dict(protection or {})
        names = {m.name for m, _ in messages}
        for name in declared:
            if name not in names:
                raise ProtectionError(name, f"{self._path}: no frame {name!r} to protect{_did_you_mean(name, names)}")
            if name in own:
                raise ProtectionError(name, f"{self._path}: {name} is the service's own frame: it keeps the CAN "
                                            "matrix's protection")
        self._frames: dict[int, _FrameSpec] = {}
        self._by_name: dict[str, _FrameSpec] = {}
        self._unsupported: dict[str, str] = {}
        for msg, path in messages:
            why = _unsupported(msg)
            if why is not None:
                if msg.name in declared:
                    raise ProtectionError(msg.name, f"{path}: frame {msg.name} cannot be read: {why}")
                self._unsupported[msg.name] = why
                continue
            spec = _frame_spec(msg, path, declared.get(msg.name))
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

    def unsupported(self, frame: str) -> str | None:
        """Why a frame of the DBC was left out (``"it has a 29-bit identifier ..."``), None if it was not."""
        return self._unsupported.get(frame)

    def protection(self, frame: FrameRef) -> FrameProtection | None:
        """The protection a frame is checked with (``FrameProtection()``: none declared); None for a
        frame with neither the CAN matrix's counter and CRC nor a declaration (KeyError if unknown)."""
        return self._spec(frame).protection

    def protection_problem(self, frame: FrameRef) -> str:
        """Why a frame has no protection (:meth:`protection` None), empty if it has one."""
        return self._spec(frame).undeclared

    def message(self, frame: FrameRef) -> _DbcMessage:
        """The cantools message of a frame (KeyError if unknown)."""
        return self._spec(frame).message

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
    def _raw_value(self, frame: _FrameSpec, spec: _SignalSpec, value: Any) -> int | float:
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
        if sig.is_float:
            return (x - spec.offset) / spec.scale
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
        protection_names = {s.name for s in (spec.counter,) if s is not None}
        if spec.protection is not None and spec.protection.crc is not None:
            protection_names.add(spec.protection.crc)
        unknown = set(signals) - set(spec.by_name) - protection_names
        if unknown:
            raise FrameEncodeError(f"{spec.name}: unknown signal(s) {', '.join(sorted(unknown))}")
        missing = [s.name for s in spec.signals if s.name not in signals]
        if missing:
            raise FrameEncodeError(f"{spec.name}: missing signal(s) {', '.join(missing)}")
        raw: dict[str, int | float] = {s.name: self._raw_value(spec, s, signals[s.name]) for s in spec.signals}
        if spec.crc is not None:
            assert spec.protection is not None and spec.protection.crc is not None  # a CRC is declared with it
            raw[spec.protection.crc] = 0
        with self._lock:
            value = 0
            if spec.counter is not None:
                if counter is None:
                    value = self._tx_counter.get(spec.frame_id, 0)
                else:
                    if not 0 <= int(counter) < spec.counter_mod:
                        raise FrameEncodeError(f"{spec.name}: counter {counter} outside 0..{spec.counter_mod - 1}")
                    value = int(counter)
                raw[spec.counter.name] = value
            try:
                data = bytearray(spec.message.encode(raw, scaling=False, strict=True))
            except Exception as exc:
                raise FrameEncodeError(f"{spec.name}: {exc}") from exc
            if spec.counter is not None:
                self._tx_counter[spec.frame_id] = (value + 1) % spec.counter_mod
            self.stats.sent[spec.name] += 1
        if spec.crc is not None:
            data[spec.crc_byte] = spec.crc(bytes(data))
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
        if spec.crc is not None and payload[spec.crc_byte] != spec.crc(bytes(payload)):
            with self._lock:
                self.stats.count_drop("crc", spec.name)
            return None
        values: dict[str, float] = {}
        counter = -1
        if spec.fast:
            word = int.from_bytes(payload, "little")
            for s in spec.signals:
                r = (word >> s.start) & s.mask
                if s.sign_bit and r & s.sign_bit:
                    r -= s.sign_bit << 1
                if r == s.no_value_raw:  # _physical, inlined: the receive path's hot loop
                    values[s.name] = math.nan
                elif s.identity:
                    values[s.name] = r
                else:
                    values[s.name] = round(r * s.scale + s.offset, s.decimals)
            if spec.counter is not None:
                counter = (word >> spec.counter.start) & spec.counter.mask
        else:  # big-endian or float signals: cantools unpacks the raw values
            raws = spec.message.decode(bytes(payload), decode_choices=False, scaling=False)
            assert isinstance(raws, dict)  # a plain frame (containers are left out at load)
            for s in spec.signals:
                raw = raws[s.name]
                assert isinstance(raw, (int, float))  # raw values (no choices decoded)
                values[s.name] = _physical(s, raw)
            if spec.counter is not None:
                raw = raws[spec.counter.name]
                assert isinstance(raw, int)
                counter = raw
        ts = float(timestamp) if timestamp is not None else None
        if spec.counter is None:  # nothing to judge: repeats and losses cannot be seen
            with self._lock:
                self.stats.received[spec.name] += 1
            return DecodedFrame(spec.name, spec.frame_id, values, counter, ts, 0, bool(is_rx))
        mod = spec.counter_mod
        with self._lock:
            lost = 0
            last = self._rx_last.get(spec.frame_id)
            pace = None  # running mean of the time per frame (s) and how many gaps it has seen
            # wraps the last gap added that a catch-up would take back: (wraps, the gap frame's
            # time stamp, frame periods since it), until the sender is seen to keep its cadence
            owed: tuple[int, float, int] | None = None
            if last is not None:
                last_counter, last_ts, pace, owed = last
                step = (counter - last_counter) % mod
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
                    if (self._wraps_from_time and dt is not None and cycle and dt / cycle >= _WRAP_FROM_SHARE * mod
                            and _keeps_cycle(pace, cycle)):
                        # rounded down: a sender that is late (a busy host) makes dt longer, never
                        # shorter, than its frame periods; only early jitter needs the allowance
                        wraps = mod * max(0, math.floor((dt / cycle - step + _WRAP_EARLY_CYCLES) / mod))
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
                            owed = (owed_wraps, t_gap, periods) if periods < _CATCH_UP_WRAPS * mod else None
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
        frames as ``dlc``, CAN FD frames on a frame the DBC defines as classic
        CAN as ``fd``; everything else goes through :meth:`decode`.
        """
        try:
            if getattr(msg, "is_error_frame", False) or getattr(msg, "is_extended_id", False):
                with self._lock:
                    self.stats.count_drop("unknown_id")
                return None
            if getattr(msg, "is_fd", False):
                spec = self._frames.get(msg.arbitration_id)
                if spec is not None and not getattr(spec.message, "is_fd", False):
                    with self._lock:
                        self.stats.count_drop("fd", spec.name)
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
