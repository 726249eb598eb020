"""The service configuration (``edge.yaml``): YAML -> validated, typed dataclasses.
``thermal-edge config example`` prints the packaged example to start from.

The dataclasses below are the one home of every setting: its type, its default and what the file
may give for it (:func:`thermal_edge.settings.setting`: range, choices, a check). :func:`load_config`
reads the file generically from them -- types, defaults, nested sections, unknown keys refused with
the closest known one -- and ``deploy/docs`` renders the defaults from the same declarations.
:meth:`EdgeConfig.check_model` and :meth:`EdgeConfig.check_dbc` then check what needs the machine
model and the DBC (model inputs and sensors mapped, signal names present). Every error is a
:class:`ConfigError` whose message starts with the file name and the key, e.g.
``edge.yaml: derating.safe_current_a: must be positive, got -3``.

Relative paths in the file (model, state directory, recording) are relative to the directory of
the configuration file; ``model.path`` may instead name a model that ships with the package
(``pm10kw``), used when no file of that name is beside the configuration.
"""
from __future__ import annotations

import dataclasses
import difflib
import errno
import functools
import ipaddress
import logging
import math
import os
import tempfile
import types
import typing
from collections.abc import Iterable, Mapping
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .bus.busconfig import BusConfig, BusConfigError
from .bus.crc import CRC8_ALGORITHMS
from .bus.frames import DEFAULT_DBC_PATH, INV_CURRENTS, INV_VOLTAGES, NODE_THERMAL_EDGE, TE_LIMITS, DerateReason
from .bus.logs import DEFAULT_KEEP, DEFAULT_MAX_BYTES
from .bus.protection import FrameProtection
from .errors import ThermalEdgeError
from .lptn.vocabulary import LIMIT, TEMPERATURE, UNIT_SPELLINGS, NodeRole, Role, foreign_unit, is_unit
from .settings import AdapterConfig, setting, spec_of
from .shipped import MACHINES, find
from .yamlfile import read_document

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from .bus.codec import FrameCodec

#: Errors making ``state.dir`` that the file system's state or permissions decide, not the configuration:
#: the service starts without persistence and says so (:meth:`EdgeConfig.check_state_dir`).
_STATE_DIR_CONDITIONS = frozenset({errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EIO})

__all__ = [
    "AdaptationConfig",
    "ClockConfig",
    "CodecConfig",
    "ConfigError",
    "DeratingConfig",
    "EdgeConfig",
    "FaultConfig",
    "FluxConfig",
    "InputSignal",
    "LimitConfig",
    "LookaheadConfig",
    "MetricsConfig",
    "ModelConfig",
    "ObserverConfig",
    "RecordingConfig",
    "SensorSignal",
    "SignalsConfig",
    "StateConfig",
    "TransmitConfig",
    "config_from_mapping",
    "field_default",
    "file_key",
    "load_config",
    "without_none",
]

REDUCTIONS = ("mean", "rms", "dq_rms", "latest")
#: ``dq:`` of a ``dq_rms`` input: the scaling of the inverter's d/q transform, as the mean square of
#: the phase current per unit of ``i_d² + i_q²``. Amplitude-invariant (Clarke with 2/3: |i_dq| is the
#: phase current's peak) gives I_rms = sqrt((i_d² + i_q²) / 2); power-invariant (sqrt(2/3): i_d² + i_q²
#: is the sum of the three phases' squares) sqrt((i_d² + i_q²) / 3); RMS-scaled (|i_dq| is the RMS
#: phase current) sqrt(i_d² + i_q²).
DQ_SQUARE_SHARE = {"amplitude_invariant": 1 / 2, "power_invariant": 1 / 3, "rms_scaled": 1.0}
CLOCK_MODES = ("wall", "frame")
WORKERS = ("thread", "sync")
REASON_NAMES = {"winding": DerateReason.WINDING, "magnet": DerateReason.MAGNET}
#: The inverter treats TE_Limits as absent after this long without a valid frame, s (the CAN matrix).
INVERTER_LIMITS_TIMEOUT_S = 0.3
#: Longest TE_Limits period accepted, s: half the timeout, so that one lost or late frame still
#: leaves the next one inside it.
MAX_LIMITS_PERIOD_S = INVERTER_LIMITS_TIMEOUT_S / 2
#: Most adapter decisions kept in the state file (bounds its size below persistence.MAX_BYTES).
MAX_DECISIONS = 5000


class ConfigError(ThermalEdgeError, ValueError):
    """An invalid service configuration; the message names the file and the key."""


def default_reason(name: str) -> DerateReason:
    """The derate reason of a limited node the file does not give one for: by its name."""
    return DerateReason.MAGNET if "magnet" in name.lower() else DerateReason.WINDING


# -- readers and checks of fields that are not a plain value (used by the declarations below) ---
def _str_list(sec: _Section, k: str) -> tuple[str, ...] | None:
    v = sec.value(k)
    if v is None:
        return None
    if isinstance(v, str):
        v = [v]
    if not isinstance(v, list) or not all(isinstance(x, str) and x for x in v):
        raise sec.fail(k, f"expected a list of names, got {v!r}")
    return tuple(v)


def _input_signals(sec: _Section, k: str, values: dict[str, Any], default: Any) -> tuple[str, ...]:
    """``signals: [d, q]`` with ``reduce: dq_rms``, else one ``signal: NAME``."""
    reduce = values["reduce"]
    if reduce == "dq_rms":
        sigs = _str_list(sec, "signals")
        if sigs is None or len(sigs) != 2:
            raise sec.fail("signals", "dq_rms needs the two signals [d axis, q axis] (peak amplitudes)")
        if sec.has("signal"):
            raise sec.fail("signal", "use signals: [d, q] with reduce: dq_rms")
        return sigs
    sig = sec.string("signal", sec.value("signal"), required=True)
    if sec.has("signals"):
        raise sec.fail("signals", f"reduce: {reduce} takes one signal (signal: NAME)")
    return (sig,)


def _dq(sec: _Section, k: str, values: dict[str, Any], default: Any) -> str:
    """``dq:`` (the d/q transform's scaling) only with ``reduce: dq_rms``."""
    v = sec.string(k, sec.value(k), choices=tuple(DQ_SQUARE_SHARE))
    if v is not None and values["reduce"] != "dq_rms":
        raise sec.fail(k, f"only with reduce: dq_rms (this input has reduce: {values['reduce']})")
    return v if v is not None else default


_PROTECTION_KEYS = ("counter", "crc", "crc_algorithm", "data_id")


def _protection(sec: _Section, k: str, values: dict[str, Any], default: Any) -> dict[str, FrameProtection]:
    """``codec.protection``: frame name -> ``none`` or ``{counter: SIGNAL, crc: SIGNAL, crc_algorithm:
    NAME, data_id: N}`` (each part may be left out)."""
    sub = sec.sub(k)
    out: dict[str, FrameProtection] = {}
    for frame, raw in sub.raw.items():
        if isinstance(raw, str) and raw.strip().lower() == "none":
            out[str(frame)] = FrameProtection()
            continue
        entry = sub.sub(str(frame))  # a mapping, else the error names the key
        if not entry.raw:
            raise entry.fail("", "give counter: and/or crc: (signal names), or none for a frame without protection")
        entry.refuse_unknown(set(_PROTECTION_KEYS))
        counter = entry.string("counter", entry.value("counter"))
        crc = entry.string("crc", entry.value("crc"))
        algorithm = entry.string("crc_algorithm", entry.value("crc_algorithm"), choices=tuple(CRC8_ALGORITHMS))
        data_id = entry.value("data_id")
        if data_id is not None and (isinstance(data_id, bool) or not isinstance(data_id, int) or not 0 <= data_id <= 0xFFFF):
            raise entry.fail("data_id", f"expected a 16-bit integer (0 to 0xFFFF), got {data_id!r}")
        if crc is None and (algorithm is not None or data_id is not None):
            raise entry.fail("crc_algorithm" if algorithm is not None else "data_id", "needs crc: (the CRC signal)")
        if crc is not None and algorithm is None:
            raise entry.fail("crc_algorithm", f"required with crc: one of {', '.join(CRC8_ALGORITHMS)}")
        if counter is None and crc is None:
            raise entry.fail("", "give counter: and/or crc: (signal names), or none for a frame without protection")
        out[str(frame)] = FrameProtection(counter, crc, algorithm or FrameProtection.crc_algorithm, data_id)
    return out


def _reason(sec: _Section, k: str, values: dict[str, Any], default: Any) -> DerateReason:
    v = sec.string(k, sec.value(k), choices=tuple(REASON_NAMES))
    return REASON_NAMES[v] if v is not None else default_reason(values["name"])


def _range_c(sec: _Section, k: str, values: dict[str, Any], default: Any) -> tuple[float, float]:
    rng = sec.value(k)
    if rng is None:
        return default
    if (not isinstance(rng, list) or len(rng) != 2 or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in rng)
            or not rng[0] < rng[1]):
        raise sec.fail(k, f"expected [low, high] in degC with low < high, got {rng!r}")
    lo, hi = float(rng[0]), float(rng[1])
    for v in (lo, hi):
        if (why := TEMPERATURE.problem(v)):
            raise sec.fail(k, why)
    # a valid range must take the readings of a machine at rest: else every cold start is a sensor fault
    if not lo <= ROOM_C <= hi:
        above = TEMPERATURE.whole_above
        kelvin = "; kelvin? (give it in degC)" if above is not None and lo > above else ""
        raise sec.fail(k, f"[{lo:g}, {hi:g}] degC does not contain {ROOM_C:g} degC, a machine at rest{kelvin}")
    return lo, hi


#: The temperature of a machine at rest indoors, degC: every sensor's valid range contains it.
ROOM_C = 20.0


def _bus(sec: _Section, k: str, values: dict[str, Any], default: Any) -> BusConfig:
    """BusConfig checks its own keys (the interface's keyword arguments, or ``options:``)."""
    raw = sec.value(k)
    raw = {} if raw is None else raw
    if not isinstance(raw, Mapping):
        raise sec.fail(k, f"expected a mapping, got {type(raw).__name__}")
    try:
        bus = BusConfig.from_mapping({"node": "TE", **raw})
    except (BusConfigError, TypeError, ValueError) as exc:  # BusConfigError names the key ("bus.chanel: ...")
        msg = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ConfigError(f"{sec.fname}: {msg if msg.startswith('bus') else 'bus: ' + msg}") from None
    lo, hi = CAN_BITRATE_BPS
    if bus.bitrate is not None and not lo <= bus.bitrate <= hi:
        hint = f"; kbit/s typed? {bus.bitrate} kbit/s is {bus.bitrate * 1000}" if lo <= bus.bitrate * 1000 <= hi else ""
        raise sec.fail(k + ".bitrate", f"{bus.bitrate} bit/s is outside the {lo:,} to {hi:,} bit/s of a CAN bus{hint}")
    return bus


#: Bit rates of a CAN bus (the arbitration rate of CAN FD too), bit/s: ISO 11898 from 10 kbit/s
#: (low-speed buses run at 5 kbit/s at the least) to 1 Mbit/s.
CAN_BITRATE_BPS = (5_000, 1_000_000)


#: The longest tick, s (``clock.tick_s``).
MAX_TICK_S = 10.0
#: The longest a frame (``timeouts``) or the whole bus (``transmit.bus_silence_s``) may be missing
#: before the safe limit, s.
MAX_SILENCE_S = 10.0


def _limit_slot(sec: _Section, k: str, values: Mapping[str, Any], default: str | None) -> str | None:
    """A limit that fills one slot of TE_Estimates: the default when left out, none with ``null``
    (the slot then carries the DBC's "no value")."""
    if k in sec.raw and sec.raw[k] is None:
        return None
    v = sec.value(k)
    return default if v is None else sec.string(k, v)


def _within_inverter_timeout(v: float) -> str | None:
    if v > MAX_LIMITS_PERIOD_S:
        return (f"must be at most {MAX_LIMITS_PERIOD_S:g} s (the inverter drops TE_Limits after "
                f"{INVERTER_LIMITS_TIMEOUT_S * 1000:.0f} ms; one lost frame must not trip it), got {v:g}")
    return None


def _ip_address(v: str) -> str | None:
    try:  # an address to bind, not a name: what it binds to must be plain in the file
        ipaddress.ip_address(v)
    except ValueError:
        return (f"not an IP address: {v!r} (127.0.0.1 or ::1 for this host only; "
                "0.0.0.0 or an interface's address to be scraped from the network)")
    return None


# ------------------------------------------------------------------------------------------
# typed sections
@dataclass(frozen=True)
class ModelConfig:
    """``model:`` -- the machine model and its offline (calibrated) parameter values."""

    path: Path
    parameters: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class CodecConfig:
    """``codec:`` -- the DBC, each read frame's end-to-end protection and the alive-counter
    resynchronisation gap (in cycle times)."""

    #: the inverter's frames (null: the shipped CAN matrix); the service's own frames are always the matrix's
    dbc: Path | None = None
    #: per frame of ``dbc`` without the CAN matrix's counter and CRC: ``none`` or ``{counter, crc,
    #: crc_algorithm, data_id}`` (:class:`~thermal_edge.bus.protection.FrameProtection`)
    protection: dict[str, FrameProtection] = setting(default_factory=dict, parse=_protection)
    # the service's own choice, below the codec's 1000: an inverter frame missing for longer than 8
    # cycles is a sender that paused or changed its rate (its input goes stale), not a run of lost frames
    # that time stamps could count (they over-counted a 10 Hz feed of 10 ms frames by a wrap per frame)
    resync_after_cycles: float = setting(8.0, positive=True, max=1000.0)

    def frame_codec(self, fname: str = "<config>", **kwargs: Any) -> FrameCodec:
        """The service's :class:`~thermal_edge.bus.codec.FrameCodec`: the inverter's frames from
        :attr:`dbc` with their :attr:`protection`, the service's own from the shipped DBC.

        Parameters
        ----------
        fname : str
            The configuration's file name, for messages.
        **kwargs
            Passed to the codec (default ``resync_after_cycles`` from this section).

        Raises
        ------
        ConfigError
            A declared protection that does not fit its frame (``codec.protection.<frame>``).
        DbcError
            The DBC cannot be loaded or clashes with the service's own frames.
        """
        from .bus.codec import FrameCodec, ProtectionError

        kwargs.setdefault("resync_after_cycles", self.resync_after_cycles)
        try:
            return FrameCodec(self.dbc or DEFAULT_DBC_PATH, protection=self.protection, service_frames=True, **kwargs)
        except ProtectionError as exc:
            raise ConfigError(f"{fname}: codec.protection.{exc.frame}: {exc}") from None


@dataclass(frozen=True)
class ClockConfig:
    """``clock:`` -- what drives the 1 Hz tick: ``wall`` (hardware) or ``frame`` timestamps."""

    mode: str = setting("wall", choices=CLOCK_MODES)
    # stale inputs are judged once a tick; a tick costs ~5 ms of CPU (observer, look-ahead), so
    # below 0.1 s the loop cannot keep up (0.001 s: every input falsely stale, SIGTERM unanswered)
    tick_s: float = setting(1.0, min=0.1, max=MAX_TICK_S)
    max_catchup_s: float = setting(300.0, positive=True, max=3600.0)


@dataclass(frozen=True, kw_only=True)
class InputSignal:
    """How one model input is formed from CAN signals over a tick."""

    name: str
    frame: str
    reduce: str = setting("mean", choices=REDUCTIONS)
    signals: tuple[str, ...] = setting(aliases=("signal",), parse=_input_signals)
    #: ``dq_rms`` only: the scaling of the d/q transform (:data:`DQ_SQUARE_SHARE`); the CAN matrix's
    #: INV_Id/INV_Iq are peak amplitudes (amplitude-invariant)
    dq: str = setting("amplitude_invariant", parse=_dq)
    status: str | None = None
    resolution: float | None = setting(None, positive=True)


@dataclass(frozen=True)
class SensorSignal:
    """Which CAN signal (and status signal) carries one model sensor."""

    name: str
    frame: str
    signal: str
    status: str | None = None
    required: bool = True


@dataclass(frozen=True)
class LimitConfig:
    """Derating band of one limited model node (the reason by default from its name)."""

    name: str
    warn_c: float | None = None
    max_c: float | None = None
    reason: DerateReason = setting(DerateReason.WINDING, parse=_reason)


@dataclass(frozen=True)
class SignalsConfig:
    """``signals:`` -- CAN signals to model inputs and sensors, and the plausible reading ranges."""

    inputs: dict[str, InputSignal]
    sensors: dict[str, SensorSignal]
    valid_range_c: tuple[float, float] = setting((-40.0, 250.0), parse=_range_c)
    #: the current input ``i_rms`` above this multiple of ``derating.max_current_a`` is implausible (the
    #: input's fault, ``out_of_range``): the inverter obeys TE_CurrentLimit <= max_current_a and a drive's
    #: short-time peak is 2-2.5x its rated current; the d/q signals carry up to 1638 A
    valid_current_factor: float = setting(3.0, min=1.0, max=10.0)  # below 1 the rated current is refused
    #: the speed input ``speed_rpm`` beyond +-this is implausible: about 5x the pm10kw's base speed (its
    #: back-EMF, kt 5.6 Nm/A, reaches the 560 V DC link's phase voltage at ~1170 rpm; field weakening of
    #: a surface PM machine rarely reaches 4x); the signal carries +-16000 rpm
    valid_speed_rpm: float = setting(6000.0, positive=True)
    #: the torque input beyond +-this multiple of ``derating.max_torque_nm`` is implausible (the
    #: inverter obeys TE_TorqueLimit <= max_torque_nm; its estimate overshoots in transients, not by
    #: 3x); the signal carries +-3276.8 Nm
    valid_torque_factor: float = setting(3.0, min=1.0, max=10.0)  # below 1 the rated torque is refused


@dataclass(frozen=True)
class FaultConfig:
    """``derating.faults:`` -- when the model counts as diverged, and when a sensor is stuck.

    Every threshold has an upper bound that keeps its check able to fire: 1e9 would pass ``--check``
    and switch the check off."""

    innovation_k: float = setting(15.0, positive=True, max=100.0)
    innovation_ticks: int = setting(5, min=1)
    prediction_error_k: float = setting(40.0, positive=True, max=200.0)
    #: ... for this many ticks in a row: one glitched reading is not a model fault (a restart from it
    #: would make the next, good, reading disagree by as much and fault again)
    prediction_error_ticks: int = setting(3, min=1, max=60)
    #: readings this far below the **commissioned** model's open-loop prediction (the model file's
    #: parameters, never adapted, never restarted from the readings) for ``prediction_error_ticks``
    #: ticks are not believed: a reference or offset common to every PT100 drifting low looks like a
    #: machine that cools better, and the adaptation would learn it. 20 K is five times the largest
    #: open-loop error of a published 4-node network on its measured machine (3.8 K); the readings
    #: are trusted again within half of it
    commissioned_gap_k: float = setting(20.0, positive=True, max=100.0)
    #: a limited node's upper band is never below the commissioned prediction of it less this
    #: (K): readings a little below the commissioned model (under ``commissioned_gap_k``, believed)
    #: do not take the band sent below what the model file predicts by more than a calibrated
    #: model's own error (3.8 K for the published 4-node network on its machine): without it, both
    #: winding PT100s 19 K low, under the gap, give full current with the hot spot 4.6 K over its max
    commissioned_floor_k: float = setting(5.0, positive=True, max=100.0)
    # at least the longest tick: a hold shorter than a tick never reaches the bus (0 or 1e-9 s
    # would hand a diverged model back at once, and the limit would keep rising after the fault)
    hold_s: float = setting(30.0, min=MAX_TICK_S)
    #: a model fault within this long after the previous hold ended is the same cause recurring: the
    #: hold doubles each time, up to ``hold_max_s`` (with a fixed hold, one cause faulting every 153 s
    #: gives 122 s of each at full power, for as long as it lasts)
    repeat_s: float = setting(300.0, min=0.0)
    hold_max_s: float = setting(960.0, positive=True)
    #: a required sensor is stuck (a sensor fault) when its reading stayed within ``stuck_still_k``
    #: (two steps of a PT100's 0.1 K resolution) while the open-loop prediction, stepped with the measured
    #: losses, heated its node by ``stuck_model_k`` or more, within the last
    #: ``stuck_window_s`` (10 min, against the machine's slowest time constant of about 70 min)
    stuck_window_s: float = setting(600.0, positive=True, max=3600.0)
    stuck_model_k: float = setting(5.0, positive=True, max=50.0)
    stuck_still_k: float = setting(0.2, min=0.0)
    #: ... on the reading averaged over this long (an exponential mean), s: a frozen channel still
    #: carries its ADC's noise (0.1 K sigma flickers over more than 0.2 K within seconds), which
    #: the mean takes out; a healthy reading that rises keeps rising in its mean, this much later
    stuck_smooth_s: float = setting(10.0, min=0.0, max=120.0)
    #: the RMS current must read at least this fraction of ``|torque| / kt`` (where the torque takes
    #: a fifth of ``max_current_a`` or more, 3 ticks in a row); below, the current is not believed
    #: (a sensor fault of the current input, ``current_below_torque``) and the model heats with
    #: ``|torque| / kt``: a DBC scaling 10x low or a second sender diluting the current frame would
    #: otherwise underestimate the copper losses until the model is tens of kelvin off
    current_torque_ratio: float = setting(0.5, positive=True, max=0.95)


@dataclass(frozen=True)
class DeratingConfig:
    """``derating:`` -- limits, bands, safe limit and how limits move."""

    max_current_a: float = setting(positive=True)
    max_torque_nm: float = setting(positive=True)
    safe_current_a: float = setting(positive=True)
    safe_torque_nm: float | None = setting(None, positive=True)
    kt_nm_per_arms: float | None = setting(None, positive=True)
    band_z: float = setting(1.96, min=0.0)
    limits: dict[str, LimitConfig] = field(default_factory=dict)
    rise_rate_a_per_s: float = setting(0.5, positive=True)
    hysteresis_a: float = setting(0.5, min=0.0)
    faults: FaultConfig = field(default_factory=FaultConfig)
    #: how long the present limit must keep every limited node's upper band below its max
    #: (thermal_edge.service.derating explains the choice)
    reaction_time_s: float = setting(10.0, positive=True, max=600.0)
    #: kept below each max by the reaction-time current, K: the model error the band does not cover
    margin_k: float = setting(1.5, min=0.0, max=50.0)
    #: the limit falls linearly over this many K below (max - margin) on the upper band, K
    approach_k: float = setting(3.0, positive=True, max=100.0)


@dataclass(frozen=True)
class LookaheadConfig:
    """``lookahead:`` -- horizon of the look-ahead current and the time to limit."""

    enabled: bool = True
    horizon_s: float = setting(1800.0, positive=True, max=65535)
    steps: int = setting(60, min=1, max=10000)


@dataclass(frozen=True)
class AdaptationConfig:
    """``adaptation:`` -- :class:`AdapterConfig` fields plus how the service runs the adapter."""

    enabled: bool = True
    worker: str = setting("thread", choices=WORKERS)
    apply_delay_ticks: int = setting(5, min=1)
    bands: bool = True
    adapter: AdapterConfig = setting(default_factory=AdapterConfig, inline=True)


@dataclass(frozen=True)
class ObserverConfig:
    """``observer:`` -- Kalman filter noise levels (K)."""

    q_k: float = setting(0.02, positive=True)
    r_k: float = setting(0.15, positive=True)
    p0_k: float = setting(2.0, positive=True)
    restart_p0_k: float = setting(3.0, positive=True)


@dataclass(frozen=True)
class MetricsConfig:
    """``metrics:`` -- the Prometheus endpoint (read only; nothing listens for commands)."""

    enabled: bool = True
    address: str = setting("127.0.0.1", check=_ip_address)
    port: int = setting(9108, min=0, max=65535)


@dataclass(frozen=True)
class StateConfig:
    """``state:`` -- where parameters, decisions and the thermal state persist."""

    dir: Path = setting(env="STATE_DIRECTORY")  # systemd's StateDirectory= sets it
    save_interval_s: float = setting(60.0, positive=True, max=86400.0)  # learned state lost on a crash: at most a day
    max_decisions: int = setting(500, min=0, max=MAX_DECISIONS)
    max_downtime_s: float = setting(7 * 86400.0, positive=True)


@dataclass(frozen=True)
class RecordingConfig:
    """``recording:`` -- optional recording of all RX/TX traffic, a CAN log in its file's format."""

    candump: Path | None = None  # the log (.log candump -L, .asc, .blf, .csv by suffix; the key predates them)
    channel: str = "can0"
    max_bytes: int = setting(DEFAULT_MAX_BYTES, min=0)  # rotate at this size (0: never); closed files gzipped
    keep: int = setting(DEFAULT_KEEP, min=0)  # rotated files kept


@dataclass(frozen=True)
class FluxConfig:
    """``flux:`` -- optional: the magnet temperature from the inverter's dq voltage references, fused
    into the observer (:mod:`thermal_edge.service.flux_input`). Without ``calibration`` nothing of
    it is read and the service is the one without voltages."""

    #: the commissioned flux-linkage model (``thermal-edge flux calibrate --out FILE``); null: off
    calibration: Path | None = None
    frame: str = INV_VOLTAGES
    voltage_d: str = "INV_Ud"
    voltage_q: str = "INV_Uq"
    #: the dq currents the voltages pair with (peak amplitudes, amplitude-invariant)
    currents_frame: str = INV_CURRENTS
    current_d: str = "INV_Id"
    current_q: str = "INV_Iq"
    #: voltages older than this at a tick are stale: that tick's estimate is refused (counted), s
    timeout_s: float = setting(0.5, min=0.02, max=MAX_SILENCE_S)  # 0.02: twice the frame's 10 ms cycle
    #: the model node whose estimate gives the stator resistance its temperature (required with calibration)
    winding_node: str | None = None
    #: the model nodes whose mean the flux linkage sees (default: the node of ``transmit.magnet_limit``)
    magnet_nodes: tuple[str, ...] | None = None
    #: at a current the commissioning did not see (same speeds), use the estimate's changes (its offset
    #: there is unknown) right after an accepted estimate; false: only the commissioned operating points
    extrapolate: bool = True
    #: the derating's margin below the magnet's max while the voltages observe it (an estimate fused
    #: within the error's correlation time), K: the measured band then covers the rotor model's error
    #: that ``derating.margin_k`` is for; ``derating.margin_k`` otherwise
    magnet_margin_k: float = setting(0.5, min=0.0, max=50.0)

    @property
    def enabled(self) -> bool:
        """Whether the voltages are read at all."""
        return self.calibration is not None


@dataclass(frozen=True)
class TransmitConfig:
    """``transmit:`` -- which limit goes into which TE_Estimates slot, cyclic periods, silence."""

    hot_spot_limit: str = "hot_spot"
    #: null: the model has no magnet limit (or it is not sent): TE_T_Magnet and TE_T_MagnetUpper carry "no value"
    magnet_limit: str | None = setting("magnet", parse=_limit_slot)
    # at least 10 ms: faster is a flood (1 µs sent 3,700 TE_Limits/s, most of a 500 kbit/s bus)
    limits_period_s: float = setting(0.1, min=0.01, check=_within_inverter_timeout)
    status_period_s: float = setting(1.0, min=0.1)  # three frames each period
    bus_silence_s: float = setting(1.0, positive=True, max=MAX_SILENCE_S)


@dataclass(frozen=True, kw_only=True)
class EdgeConfig:
    """The validated service configuration: one field per section of the file (and its path)."""

    path: Path | None = None
    bus: BusConfig = setting(default_factory=BusConfig, parse=_bus)
    codec: CodecConfig = field(default_factory=CodecConfig)
    model: ModelConfig
    clock: ClockConfig = field(default_factory=ClockConfig)
    signals: SignalsConfig
    # at most 10 s: beyond it the model runs blind on the last values for longer than protection
    # can allow (1e9 passed --check and switched stale-input protection off: the limit rose with
    # every inverter frame gone)
    timeouts: dict[str, float] = setting(default_factory=dict, positive=True, max=MAX_SILENCE_S)
    derating: DeratingConfig
    lookahead: LookaheadConfig = field(default_factory=LookaheadConfig)
    adaptation: AdaptationConfig = field(default_factory=AdaptationConfig)
    observer: ObserverConfig = field(default_factory=ObserverConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    state: StateConfig
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    transmit: TransmitConfig = field(default_factory=TransmitConfig)
    flux: FluxConfig = field(default_factory=FluxConfig)

    @property
    def inputs(self) -> dict[str, InputSignal]:
        """``signals.inputs``: model input name -> how it is formed from CAN signals."""
        return self.signals.inputs

    @property
    def sensors(self) -> dict[str, SensorSignal]:
        """``signals.sensors``: model sensor name -> its CAN signal."""
        return self.signals.sensors

    @property
    def valid_range_c(self) -> tuple[float, float]:
        """``signals.valid_range_c``: readings outside are implausible, degC."""
        return self.signals.valid_range_c

    @property
    def fname(self) -> str:
        return self.path.name if self.path is not None else "<config>"

    def error(self, key: str, msg: str) -> ConfigError:
        return ConfigError(f"{self.fname}: {key}: {msg}")

    # -- checks that need the model / the DBC -------------------------------------------------
    def check_model(self, model: Any) -> None:
        """Check the mapping against the machine model (inputs, sensors, limits, parameters)."""
        for name in model.inputs:
            if name not in self.inputs:
                raise self.error(f"signals.inputs.{name}", f"model {model.name} needs this input; map it to a CAN signal")
        for name in self.inputs:
            if name not in model.inputs:
                raise self.error(f"signals.inputs.{name}",
                                 f"model {model.name} has no input {name!r} (has: {', '.join(model.inputs)})")
        for name, role in model.input_roles.items():
            reduce = self.inputs[name].reduce
            if role is Role.CURRENT and reduce not in ("rms", "dq_rms"):
                # the copper loss goes with the mean square: a mean or one sample of a current that
                # varies within the tick under-reads it (pulses of 25 % duty: a quarter of the loss)
                raise self.error(f"signals.inputs.{name}.reduce", f"is {reduce!r}; input {name} is the current of model "
                                 f"{model.name}, whose losses need its mean square over the tick: rms (one signal) or "
                                 "dq_rms (the d and q currents)")
            if role in (Role.SPEED, Role.TORQUE) and reduce in ("rms", "dq_rms"):
                raise self.error(f"signals.inputs.{name}.reduce", f"is {reduce!r}; input {name} is the {role.value} of "
                                 f"model {model.name}, signed: mean (or latest)")
        for name in self.sensors:
            if name not in model.sensors:
                raise self.error(f"signals.sensors.{name}",
                                 f"model {model.name} has no sensor {name!r} (has: {', '.join(model.sensors)})")
        limit_names = {lim.name for lim in model.limits}
        for name in self.derating.limits:
            if name not in limit_names:
                have = ", ".join(sorted(limit_names)) or "none"
                raise self.error(f"derating.limits.{name}", f"model {model.name} has no limited node {name!r} (has: {have})")
        lo, hi = self.signals.valid_range_c
        for lim in model.limits:
            warn, mx = self.limit_band(lim)
            if mx > lim.max_c:  # the insulation's or the magnet's limit is the machine's: only its file may raise it
                raise self.error(f"derating.limits.{lim.name}.max_c", f"{mx:g} degC is above the machine's {lim.max_c:g} "
                                 f"degC ({model.where}: limits.{lim.name}.max_c): a configuration may lower a limit, not "
                                 "raise it")
            if not mx > warn:
                raise self.error(f"derating.limits.{lim.name}.max_c", f"must be above warn_c ({warn:g}), got {mx:g}")
            if mx > hi:  # a reading on the way to the limit would be taken for a sensor fault
                raise self.error("signals.valid_range_c", f"the plausible readings ({lo:g} to {hi:g} degC) must reach "
                                 f"every limit's max_c: {lim.name} has {mx:g}")
        if not model.limits:
            raise self.error("model.path", f"model {model.name} declares no limits: nothing to derate on")
        for key in ("hot_spot_limit", "magnet_limit"):
            v = getattr(self.transmit, key)
            if v and v not in limit_names:
                raise self.error(f"transmit.{key}", f"model {model.name} has no limited node {v!r}")
        self.check_parameters(model)
        names = set(model.parameter_names)
        ad = self.adaptation.adapter
        for p in ad.params or ():
            if p not in names:
                raise self.error("adaptation.params", f"model {model.name} has no parameter {p!r}{_did_you_mean(p, names)}")
        for s in ad.sensors or ():
            if s not in model.sensors:
                raise self.error("adaptation.sensors", f"model {model.name} has no sensor {s!r}")
        kt = self.kt(model)
        if kt is None:
            raise self.error("derating.kt_nm_per_arms", f"model {model.name} has no drive.kt_nm_per_arms: give it here")
        d = self.derating
        drive_kt = model.drive.get("kt_nm_per_arms") if getattr(model, "drive", None) else None
        if d.kt_nm_per_arms is not None and drive_kt and not 0.5 <= d.kt_nm_per_arms / float(drive_kt) <= 2.0:
            # a torque constant off by a decade (a typo, Nm/A peak for rms) would scale every torque limit sent
            raise self.error("derating.kt_nm_per_arms", f"{d.kt_nm_per_arms:g} Nm/A is {d.kt_nm_per_arms / float(drive_kt):.3g}"
                             f" x model {model.name}'s drive.kt_nm_per_arms ({float(drive_kt):g} Nm/A): "
                             "give the machine's torque constant (Nm per A rms), within a factor of 2 of the model's")
        if d.safe_torque_nm is None and kt * d.safe_current_a > d.max_torque_nm * (1 + 1e-9):
            # the safe torque derived from kt would be the full torque: no torque derating on a fault
            raise self.error("derating.kt_nm_per_arms", f"kt x safe_current_a = {kt:g} Nm/A x {d.safe_current_a:g} A = "
                             f"{kt * d.safe_current_a:g} Nm exceeds max_torque_nm ({d.max_torque_nm:g}): the safe torque "
                             "would be the full torque; check kt or give derating.safe_torque_nm")
        if d.safe_torque_nm is not None and d.safe_torque_nm > kt * d.safe_current_a * (1 + 1e-9):
            # the torque limit is never above kt x the current limit: a higher safe torque is never sent
            raise self.error("derating.safe_torque_nm", f"must not exceed kt x safe_current_a ({kt:g} Nm/A x "
                             f"{d.safe_current_a:g} A = {kt * d.safe_current_a:g} Nm), got {d.safe_torque_nm:g}")
        self._check_flux_model(model)

    def _check_flux_model(self, model: Any) -> None:
        """``flux:``: its nodes are the model's (only when it is on)."""
        fx = self.flux
        if not fx.enabled:
            return
        if fx.winding_node is None:
            raise self.error("flux.winding_node", "required with flux.calibration: the node whose temperature the "
                             f"stator resistance has (e.g. {next((n for n in model.nodes if 'winding' in n), model.nodes[0])})")
        nodes = set(model.nodes)
        for key, names in (("winding_node", [fx.winding_node]), ("magnet_nodes", list(fx.magnet_nodes or ()))):
            for n in names:
                if n not in nodes:
                    raise self.error(f"flux.{key}", f"model {model.name} has no node {n!r}{_did_you_mean(n, nodes)}")
        if fx.magnet_nodes is not None:
            if not fx.magnet_nodes:
                raise self.error("flux.magnet_nodes", "empty: name the magnet node(s) the flux linkage sees (or leave it "
                                 "out for the node of transmit.magnet_limit)")
            if len(set(fx.magnet_nodes)) != len(fx.magnet_nodes):
                raise self.error("flux.magnet_nodes", f"names a node twice: {list(fx.magnet_nodes)}")
            if fx.winding_node in fx.magnet_nodes:
                raise self.error("flux.magnet_nodes", f"{fx.winding_node!r} is flux.winding_node: the voltages would "
                                 "correct the winding with a magnet temperature")
        # where the model declares roles, a magnet node is a magnet and the winding node a winding
        roles = getattr(model, "node_roles", {}) or {}
        for key, names, role in (("winding_node", [fx.winding_node], NodeRole.WINDING),
                                 ("magnet_nodes", list(fx.magnet_nodes or ()), NodeRole.MAGNET)):
            for n in names:
                if n in roles and roles[n] is not role:
                    raise self.error(f"flux.{key}", f"node {n!r} of model {model.name} has role {roles[n].value}, "
                                     f"not {role.value}")
        if fx.magnet_nodes is None and not any(lim.name == self.transmit.magnet_limit for lim in model.limits):
            why = (f"model {model.name} has no limited node {self.transmit.magnet_limit!r} (transmit.magnet_limit)"
                   if self.transmit.magnet_limit else "transmit.magnet_limit is null")
            raise self.error("flux.magnet_nodes", f"{why}: name the magnet nodes here")

    def check_parameters(self, model: Any) -> None:
        """Check ``model.parameters`` against the model file: known names, values within its bounds.

        Run on the model as loaded from its file, before the values are applied (only the model
        file can widen a bound).

        Raises
        ------
        ConfigError
            ``<file>: model.parameters.<name>: <value> is outside the model's bounds [lo, hi] ...``
            or, for an unknown name, the closest known one.
        """
        # (the model package is only needed once a model is loaded)
        from .lptn import ParameterError

        for name, value in self.model.parameters.items():
            try:
                model.check_parameters({name: value})
            except ParameterError as exc:
                where = f" (bounds of {Path(model.path).name})" if exc.bounds is not None and model.path else ""
                raise self.error(f"model.parameters.{name}", f"{exc.problem}{where}") from None

    def check_state_dir(self, create: bool) -> None:
        """Check that ``state.dir`` is, or can be made, a directory; with ``create`` make it if it can.

        Only a path where no directory can be is an error: the path is a file, or lies under one,
        or the file system refuses any directory there (``/proc``). What the file system's state or
        permissions decide (read-only after an I/O error, full, not this user's) changes without an
        edit of the configuration: the service starts and protects, its state store says it cannot
        save (ERROR, metric ``state_save_failing``) and every save retries.

        Raises
        ------
        ConfigError
            ``<file>: state.dir: ...``.
        """
        self._check_dir("state.dir", self.state.dir, create)

    def state_dir_problem(self) -> str | None:
        """Why ``state.dir`` cannot be written now (a file made and removed there), or None.

        Not a configuration error (:meth:`check_state_dir` says why): ``run --check`` reports it so
        that a service that would protect without saving its state is known before it starts."""
        d = self.state.dir
        if not d.is_dir():  # not there yet: the service makes it (check_state_dir judged where)
            return None
        try:
            fd, name = tempfile.mkstemp(prefix=".thermal-edge-check-", dir=d)
            os.close(fd)
            os.unlink(name)
        except OSError as exc:
            return f"{d} cannot be written now ({exc.strerror or exc})"
        return None

    def check_recording(self) -> None:
        """Check that ``recording.candump`` names a file whose directory is, or can be made, one
        (judged as :meth:`check_state_dir` judges ``state.dir``, without making it): a path that is
        a directory, or lies under a file or where the file system refuses any directory, is a
        configuration error. One the file system's state refuses at start (full, read-only, not
        this user's) only turns the recording off (logged); protection never depends on it.

        Raises
        ------
        ConfigError
            ``<file>: recording.candump: ...``.
        """
        if self.bus.record_path is None:
            return
        path = Path(self.bus.record_path)
        if path.is_dir():
            raise self.error("recording.candump", f"{path} is a directory, not a log file")
        self._check_dir("recording.candump", path.parent, create=False, what=f"the directory of {path.name}")

    def _check_dir(self, key: str, d: Path, create: bool, what: str = "") -> None:
        probe = d
        while not os.path.lexists(probe) and probe != probe.parent:
            probe = probe.parent
        said = f"{d} ({what})" if what else f"{d}"
        if not probe.is_dir():
            msg = f"{said} is not a directory" if probe == d else f"{said} cannot be created: {probe} is not a directory"
            raise self.error(key, msg)
        if not create:
            if probe != d:  # try to make a directory where it would go, then remove it
                try:
                    os.rmdir(tempfile.mkdtemp(prefix=".thermal-edge-check-", dir=probe))
                except OSError as exc:
                    if exc.errno not in _STATE_DIR_CONDITIONS:
                        raise self.error(key, f"{said} cannot be created under {probe}: {exc.strerror or exc}") from None
            return
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            if exc.errno not in _STATE_DIR_CONDITIONS:
                raise self.error(key, f"cannot create {said}: {exc.strerror or exc}") from None

    def check_dbc(self, codec: Any, roles: Mapping[str, Role] | None = None) -> None:
        """Check that every mapped frame and signal exists in the DBC and every read frame has a
        known protection (the CAN matrix's, or declared under ``codec.protection``), and that the
        unit the DBC declares for a mapped signal is the package's (sensors °C; with ``roles``, the
        model's input roles, each input with a role in its role's unit): nothing in ``edge.yaml`` converts units, so a speed
        the DBC gives in rad/s would be read as rpm."""
        for section, items in (("inputs", self.inputs), ("sensors", self.sensors)):
            for name, spec in items.items():
                key = f"signals.{section}.{name}"
                try:
                    signals = set(codec.signal_names(spec.frame))
                except KeyError:
                    why = codec.unsupported(spec.frame)
                    raise self.error(f"{key}.frame", f"frame {spec.frame} of {Path(codec.dbc_path).name} cannot be read: {why}"
                                     if why else f"no frame {spec.frame!r} in {Path(codec.dbc_path).name}") from None
                if codec.protection(spec.frame) is None:
                    raise self.error(f"codec.protection.{spec.frame}",
                                     f"{key} reads {spec.frame}, and {codec.protection_problem(spec.frame)} (counter: "
                                     "and/or crc: with crc_algorithm:, or none)")
                wanted = list(spec.signals) if isinstance(spec, InputSignal) else [spec.signal]
                if spec.status:
                    wanted.append(spec.status)
                for sig in wanted:
                    if sig not in signals:
                        raise self.error(key, f"frame {spec.frame} has no signal {sig!r}")
                if spec.status:
                    self._check_status(f"{key}.status", codec, spec.frame, spec.status)
                role = (roles or {}).get(name) if section == "inputs" else None
                want = TEMPERATURE.unit if section == "sensors" else (role.plausible.unit if role is not None else None)
                if want is not None:
                    for sig in spec.signals if isinstance(spec, InputSignal) else [spec.signal]:
                        self._check_unit(key, codec, spec.frame, sig, want)
        self._check_flux_dbc(codec)
        # a frame the model reads with no timeout never goes stale: its last values would drive the
        # model and the limit however long it is gone (so `timeouts: {}` is refused)
        read = {spec.frame: f"signals.{section}.{name}" for section, items in (("inputs", self.inputs), ("sensors", self.sensors))
                for name, spec in items.items()}
        for frame, key in read.items():
            if frame not in self.timeouts:
                raise self.error(f"timeouts.{frame}", f"missing: {key} reads frame {frame}, which needs a timeout "
                                 f"(at most {MAX_SILENCE_S:g} s) to be judged stale when it stops")
        for frame in self.timeouts:
            try:
                codec.frame_id(frame)
            except KeyError:
                raise self.error(f"timeouts.{frame}", f"no frame {frame!r} in {Path(codec.dbc_path).name}") from None
        # a limit the DBC cannot carry would be sent saturated: not the configured one
        limits = codec.message(TE_LIMITS)
        d = self.derating
        for key, value, signal in (("max_current_a", d.max_current_a, "TE_CurrentLimit"),
                                   ("safe_current_a", d.safe_current_a, "TE_CurrentLimit"),
                                   ("max_torque_nm", d.max_torque_nm, "TE_TorqueLimit"),
                                   ("safe_torque_nm", d.safe_torque_nm, "TE_TorqueLimit")):
            top = limits.get_signal_by_name(signal).maximum
            if value is not None and top is not None and value > top:
                raise self.error(f"derating.{key}", f"must be at most {top:g}, the largest value {signal} carries in "
                                 f"{Path(codec.dbc_path).name}; got {value:g}")

    def _check_status(self, key: str, codec: Any, frame: str, sig: str) -> None:
        """Refuse a status signal that is not a whole-number code (scale 1, offset 0, an integer
        signal): 0 is read as valid, 1-3 as the sensor's faults, any other code as a fault. A
        temperature mapped there by mistake would otherwise be judged as codes."""
        signal = codec.message(frame).get_signal_by_name(sig)
        if signal.is_float or float(signal.scale) != 1.0 or float(signal.offset) != 0.0:
            kind = "a float" if signal.is_float else f"scaled (factor {float(signal.scale):g}, offset {float(signal.offset):g})"
            unit = f", unit {signal.unit!r}" if signal.unit else ""
            raise self.error(key, f"{sig} in {Path(codec.dbc_path).name} is {kind}{unit}: not a status code (a status "
                             "is a whole number, 0 valid, 1 open circuit, 2 short circuit, 3 not fitted)")

    def _check_unit(self, key: str, codec: Any, frame: str, sig: str, want: str) -> None:
        """Refuse a signal whose DBC unit is not ``want``, naming the scaling that would give ``want``
        where the unit is a known one. An empty unit cannot be judged (many DBCs leave it out): a
        WARNING says in which unit the value is read, so a speed in rad/s does not pass unsaid."""
        signal = codec.message(frame).get_signal_by_name(sig)
        unit = (signal.unit or "").strip()
        if not unit:
            log.warning("%s: %s.%s has no unit in %s: read as %s; if the inverter sends another unit, give the "
                        "signal its unit (or scale it to %s) in the DBC", key, frame, sig, Path(codec.dbc_path).name,
                        want, want)
            return
        if is_unit(want, unit):
            return
        dbc = Path(codec.dbc_path).name
        said = f"{dbc} gives {sig} in {unit!r}, and {key.rsplit('.', 1)[-1]} must be in {want} (edge.yaml converts no units)"
        other = foreign_unit(want, unit)
        if other is None:
            raise self.error(key, f"{said}: give the signal in {want} in the DBC (its unit written "
                             f"{' or '.join(repr(u) for u in sorted(UNIT_SPELLINGS[want]))})")
        factor, offset = float(signal.scale) * other.scale, float(signal.offset) * other.scale + other.offset
        raise self.error(key, f"{said}: scale the signal to {want} in the DBC: factor {factor:.7g}, offset {offset:.7g}, "
                         f"unit \"{want}\" (now {float(signal.scale):g}, {float(signal.offset):g})")

    def _check_flux_dbc(self, codec: Any) -> None:
        """``flux:``: its frames and signals are in the DBC with a known protection (only when it is on)."""
        fx = self.flux
        if not fx.enabled:
            return
        dbc = Path(codec.dbc_path).name
        for frame_key, frame, sig_keys in (("frame", fx.frame, ("voltage_d", "voltage_q")),
                                           ("currents_frame", fx.currents_frame, ("current_d", "current_q"))):
            try:
                signals = set(codec.signal_names(frame))
            except KeyError:
                raise self.error(f"flux.{frame_key}", f"no frame {frame!r} in {dbc}") from None
            senders = getattr(codec.message(frame), "senders", None) or []
            if NODE_THERMAL_EDGE in senders:
                raise self.error(f"flux.{frame_key}", f"{frame} is a frame thermal_edge sends (in {dbc}), not one the "
                                 "inverter sends it")
            a, b = (getattr(fx, k) for k in sig_keys)
            if a == b:
                raise self.error(f"flux.{sig_keys[1]}", f"is {b!r}, the same signal as flux.{sig_keys[0]}")
            if codec.protection(frame) is None:
                raise self.error(f"codec.protection.{frame}", f"flux.{frame_key} reads {frame}, and "
                                 f"{codec.protection_problem(frame)} (counter: and/or crc: with crc_algorithm:, or none)")
            prot = codec.protection(frame)
            for k in sig_keys:
                sig = getattr(fx, k)
                for what in ("counter", "crc"):  # in the frame, but its protection: not a value
                    if sig == getattr(prot, what, None):
                        raise self.error(f"flux.{k}", f"{sig} is the {'alive counter' if what == 'counter' else 'CRC'} "
                                         f"of frame {frame} (its protection), not a signal with a value; "
                                         f"its signals: {', '.join(sorted(signals))}")
                if sig not in signals:
                    raise self.error(f"flux.{k}", f"frame {frame} has no signal {sig!r}{_did_you_mean(sig, signals)}")
                self._check_unit(f"flux.{k}", codec, frame, sig, "V" if k.startswith("voltage") else "A")

    # -- derived values -------------------------------------------------------------------------
    def kt(self, model: Any) -> float | None:
        """Torque constant, Nm per A rms (configured, else the model's ``drive``)."""
        if self.derating.kt_nm_per_arms is not None:
            return self.derating.kt_nm_per_arms
        v = model.drive.get("kt_nm_per_arms") if getattr(model, "drive", None) else None
        return float(v) if v is not None else None

    def limit_band(self, limit: Any) -> tuple[float, float]:
        """(warn, max) of a model limit with the configured overrides."""
        over = self.derating.limits.get(limit.name)
        warn = over.warn_c if over is not None and over.warn_c is not None else limit.warn_c
        mx = over.max_c if over is not None and over.max_c is not None else limit.max_c
        return float(warn), float(mx)

    def limit_reason(self, limit: Any) -> DerateReason:
        over = self.derating.limits.get(limit.name)
        if over is not None:
            return over.reason
        return default_reason(limit.name)


# ------------------------------------------------------------------------------------------
# the generic reader
#: the keys of the file that are not read from it (the file's own path; an entry's name is its key)
_NOT_IN_FILE = {EdgeConfig: {"path"}, InputSignal: {"name"}, SensorSignal: {"name"}, LimitConfig: {"name"}}


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def without_none(tp: Any) -> Any:
    """The type of an optional field: ``X | None`` -> ``X`` (anything else as it is)."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        rest = tuple(a for a in args if a is not type(None))
        return rest[0] if len(rest) == 1 else typing.Union[rest]  # noqa: UP007  # built at run time from a tuple of types
    return tp


def file_key(cls: type, key: str) -> tuple[dataclasses.Field[Any], Any] | None:
    """The field (and its type) that the file's ``key`` gives in a section read as ``cls``; an inline
    section's keys included. None for a key the section does not have."""
    for f in fields(cls):
        if f.name in _NOT_IN_FILE.get(cls, ()):
            continue
        tp = _hints(cls)[f.name]
        if spec_of(f).inline:
            found = file_key(tp, key)
            if found is not None:
                return found
        elif key == f.name or key in spec_of(f).aliases:
            return f, tp
    return None


def _file_keys(cls: type) -> set[str]:
    out: set[str] = set()
    for f in fields(cls):
        if f.name in _NOT_IN_FILE.get(cls, ()):
            continue
        spec = spec_of(f)
        out |= _file_keys(_hints(cls)[f.name]) if spec.inline else {f.name, *spec.aliases}
    return out


def field_default(f: dataclasses.Field[Any]) -> Any:
    """The value a field takes when the file leaves its key out (:data:`dataclasses.MISSING`: required)."""
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    return MISSING


def _read(cls: type, sec: _Section, given: Mapping[str, Any] | None = None, *, whole: bool = True) -> Any:
    """A ``cls`` from the section: every field by its declared type, default and :class:`Spec`.

    ``whole``: the section is ``cls`` alone (its unknown keys refused, before any value is read,
    so that a misspelt required key is named as a typo rather than as missing).
    """
    if whole:
        sec.refuse_unknown(_file_keys(cls))
    values: dict[str, Any] = dict(given or {})
    for f in fields(cls):
        if f.name in values:
            continue
        spec, tp = spec_of(f), _hints(cls)[f.name]
        if spec.parse is not None:
            values[f.name] = spec.parse(sec, f.name, values, field_default(f))
        elif spec.inline:
            values[f.name] = _read(tp, sec, whole=False)
        else:
            values[f.name] = _value(sec, f, tp)
    out = cls(**values)
    check = _CHECKS.get(cls)
    if check is not None:
        check(out, sec)
    return out


def _value(sec: _Section, f: dataclasses.Field[Any], tp: Any) -> Any:
    k, spec = f.name, spec_of(f)
    tp = without_none(tp)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return _read(tp, sec.sub(k))
    if typing.get_origin(tp) is dict:
        entry = typing.get_args(tp)[1]
        sub = sec.sub(k)
        if isinstance(entry, type) and dataclasses.is_dataclass(entry):  # named entries: the key is the name
            return {name: _read(entry, sub.sub(name), {"name": name}) for name in list(sub.raw)}
        return {name: sub.number(name, sub.value(name), spec, required=True) for name in list(sub.raw)}
    if typing.get_origin(tp) is tuple:
        return _str_list(sec, k)
    v = sec.value(k)
    if v is None and spec.env:  # e.g. STATE_DIRECTORY: systemd may give several, ':'-separated
        v = os.environ.get(spec.env, "").split(":")[0] or None
    if v is None:
        d = field_default(f)
        if d is MISSING:
            raise sec.fail(k, "is required")
        return d
    if tp is bool:
        out: Any = sec.boolean(k, v)
    elif tp is int:
        out = sec.integer(k, v, spec)
    elif tp is float:
        out = sec.number(k, v, spec)
    elif tp is Path:
        out = sec.path(k, v)
    elif tp is str:
        out = sec.string(k, v, choices=spec.choices)
    else:  # pragma: no cover - a declaration this reader does not know
        raise TypeError(f"{k}: no reader for {tp!r}")
    problem = spec.check(out) if spec.check is not None else None
    if problem:
        raise sec.fail(k, problem)
    return out


# -- rules between fields (not defaults: those are in the declarations) ------------------------
def _check_derating(d: DeratingConfig, sec: _Section) -> None:
    for key, role in (("max_current_a", Role.CURRENT), ("safe_current_a", Role.CURRENT), ("max_torque_nm", Role.TORQUE),
                      ("safe_torque_nm", Role.TORQUE)):
        v = getattr(d, key)
        if v is not None and (why := role.plausible.problem(v)):
            raise sec.fail(key, why)
    if d.safe_current_a > d.max_current_a:
        raise sec.fail("safe_current_a", f"must not exceed max_current_a ({d.max_current_a:g}), got {d.safe_current_a:g}")
    if d.safe_torque_nm is not None and d.safe_torque_nm > d.max_torque_nm:
        raise sec.fail("safe_torque_nm", f"must not exceed max_torque_nm ({d.max_torque_nm:g}), got {d.safe_torque_nm:g}")


def _check_limit(lim: LimitConfig, sec: _Section) -> None:
    for key in ("warn_c", "max_c"):
        v = getattr(lim, key)
        if v is not None and (why := LIMIT.problem(v)):
            raise sec.fail(key, why)
    if lim.warn_c is not None and lim.max_c is not None and not lim.max_c > lim.warn_c:
        raise sec.fail("max_c", f"must be above warn_c ({lim.warn_c:g}), got {lim.max_c:g}")


def _check_signals(s: SignalsConfig, sec: _Section) -> None:
    if not s.inputs:
        raise sec.fail("inputs", "map at least the model's inputs to CAN signals")
    if not s.sensors:
        raise sec.fail("sensors", "map at least one model sensor to a CAN signal")


_CHECKS: dict[type, Any] = {DeratingConfig: _check_derating, LimitConfig: _check_limit, SignalsConfig: _check_signals}


class _Section:
    """One mapping of the file; every error names the file and the dotted key."""

    def __init__(self, fname: str, prefix: str, raw: Any, base: Path) -> None:
        self.fname, self.prefix, self.base = fname, prefix, base
        if raw is None:
            raw = {}
        if not isinstance(raw, Mapping):
            raise self.fail("", f"expected a mapping, got {type(raw).__name__}")
        self.raw: Mapping[str, Any] = raw

    def key(self, k: str) -> str:
        return f"{self.prefix}.{k}" if self.prefix and k else (self.prefix or k or "(top)")

    def fail(self, k: str, msg: str) -> ConfigError:
        return ConfigError(f"{self.fname}: {self.key(k)}: {msg}")

    def has(self, k: str) -> bool:
        return k in self.raw and self.raw[k] is not None

    def value(self, k: str) -> Any:
        """The raw value of ``k`` (None when left out or null)."""
        return self.raw.get(k)

    def sub(self, k: str) -> _Section:
        return _Section(self.fname, self.key(k), self.raw.get(k), self.base)

    def refuse_unknown(self, known: set[str]) -> None:
        extra = sorted(set(self.raw) - known, key=str)
        if extra:
            raise self.fail(str(extra[0]), f"unknown key{_did_you_mean(str(extra[0]), known)}")

    def number(self, k: str, v: Any, spec: Any, *, required: bool = False) -> float:
        if v is None and required:
            raise self.fail(k, "is required")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(k, f"expected a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise self.fail(k, f"must be finite, got {v}")
        if spec.positive and not v > 0:
            raise self.fail(k, f"must be positive, got {v:g}")
        if spec.min is not None and v < spec.min:
            raise self.fail(k, f"must be at least {spec.min:g}, got {v:g}")
        if spec.max is not None and v > spec.max:
            seconds = k.endswith("_s") or self.prefix == "timeouts"  # a duration in s: 500 is 0.5 s typed in ms
            hint = (f"; ms typed? {v:g} ms is {v / 1000:g} s" if seconds and (spec.min or 0) <= v / 1000 <= spec.max
                    else "")
            raise self.fail(k, f"must be at most {spec.max:g}, got {v:g}{hint}")
        return v

    def integer(self, k: str, v: Any, spec: Any) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(k, f"expected an integer, got {v!r}")
        if spec.min is not None and v < spec.min:
            raise self.fail(k, f"must be at least {spec.min}, got {v}")
        if spec.max is not None and v > spec.max:
            raise self.fail(k, f"must be at most {spec.max}, got {v}")
        return int(v)

    def boolean(self, k: str, v: Any) -> bool:
        if not isinstance(v, bool):
            raise self.fail(k, f"expected true or false, got {v!r}")
        return v

    def string(self, k: str, v: Any, *, choices: Iterable[str] | None = None, required: bool = False) -> Any:
        if v is None:
            if required:
                raise self.fail(k, "is required")
            return None
        if not isinstance(v, str) or not v:
            raise self.fail(k, f"expected a non-empty string, got {v!r}")
        if choices is not None and v not in choices:
            raise self.fail(k, f"must be one of {', '.join(choices)}, got {v!r}")
        return v

    def path(self, k: str, v: Any) -> Path:
        p = Path(os.path.expandvars(os.path.expanduser(self.string(k, v))))
        return p if p.is_absolute() else (self.base / p)


def _did_you_mean(name: str, known: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``known``, else empty."""
    close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


# ------------------------------------------------------------------------------------------
def load_config(path: str | os.PathLike[str]) -> EdgeConfig:
    """Read and validate ``edge.yaml`` (structure, types, ranges).

    Raises
    ------
    ConfigError
        Unreadable file, invalid YAML, unknown or invalid key (the message names file and key).
    """
    path = Path(path)
    return config_from_mapping(read_document(path, ConfigError), path)


def config_from_mapping(raw: Any, path: str | os.PathLike[str] | None = None) -> EdgeConfig:
    """Validate an already parsed mapping (``path`` names the file in messages and anchors relative paths)."""
    p = Path(path) if path is not None else None
    fname = p.name if p is not None else "<config>"
    base = p.resolve().parent if p is not None else Path.cwd()
    cfg: EdgeConfig = _read(EdgeConfig, _Section(fname, "", raw, base), {"path": p})
    model_path = cfg.model.path
    if model_path.parent == base and not model_path.exists():  # a bare name: a packaged model of that name
        packaged = find(MACHINES, model_path.name)
        if packaged is not None:
            cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, path=packaged))
    rec = cfg.recording
    if rec.candump is not None and cfg.bus.record_path is None:
        try:
            cfg = dataclasses.replace(cfg, bus=dataclasses.replace(cfg.bus, record_path=rec.candump, record_channel=rec.channel,
                                                                   record_max_bytes=rec.max_bytes, record_keep=rec.keep))
        except BusConfigError as exc:  # the log's format, or a size cap on a format that cannot rotate
            raise ConfigError(f"{fname}: recording.candump: {str(exc).split(': ', 1)[-1]}") from None
    return cfg
