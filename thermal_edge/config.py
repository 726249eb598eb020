"""The service configuration (``config/edge.yaml``): YAML -> validated, typed dataclasses.

:func:`load_config` checks the file's structure, types and ranges; :meth:`EdgeConfig.check_model`
and :meth:`EdgeConfig.check_dbc` then check what needs the machine model and the DBC (model
inputs and sensors mapped, signal names present). Every error is a :class:`ConfigError` whose
message starts with the file name and the key, e.g.
``edge.yaml: derating.safe_current_a: must be positive, got -3``.

Relative paths in the file (model, state directory, recording) are relative to the directory of
the configuration file.
"""
from __future__ import annotations

import difflib
import ipaddress
import math
import os
import tempfile
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Iterable, Mapping

import yaml

from .bus.busconfig import BusConfig, BusConfigError
from .bus.frames import DerateReason
from .estimation.adapter import METHODS, AdapterConfig

__all__ = [
    "AdaptationConfig",
    "ClockConfig",
    "CodecConfig",
    "ConfigError",
    "DeratingConfig",
    "EdgeConfig",
    "FaultConfig",
    "InputSignal",
    "LimitConfig",
    "LookaheadConfig",
    "MetricsConfig",
    "ModelConfig",
    "ObserverConfig",
    "RecordingConfig",
    "SensorSignal",
    "StateConfig",
    "TransmitConfig",
    "config_from_mapping",
    "load_config",
]

REDUCTIONS = ("mean", "rms", "dq_rms", "latest")
CLOCK_MODES = ("wall", "frame")
WORKERS = ("thread", "sync")
REASON_NAMES = {"winding": DerateReason.WINDING, "magnet": DerateReason.MAGNET}
WEIGHTINGS = ("paper", "forgetting", "uniform")
#: The inverter treats TE_Limits as absent after this long without a valid frame, s (can-matrix.md).
INVERTER_LIMITS_TIMEOUT_S = 0.3
#: Longest TE_Limits period accepted, s: half the timeout, so that one lost or late frame still
#: leaves the next one inside it.
MAX_LIMITS_PERIOD_S = INVERTER_LIMITS_TIMEOUT_S / 2
#: Most adapter decisions kept in the state file (bounds its size below persistence.MAX_BYTES).
MAX_DECISIONS = 5000


class ConfigError(ValueError):
    """An invalid service configuration; the message names the file and the key."""


# ------------------------------------------------------------------------------------------
# typed sections
@dataclass(frozen=True)
class ModelConfig:
    """``model:`` -- the machine model and its offline (calibrated) parameter values."""

    path: Path
    parameters: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class CodecConfig:
    """``codec:`` -- the DBC and the alive-counter resynchronisation gap (in cycle times)."""

    dbc: Path | None = None
    # the service's own choice, below the codec's 1000: an inverter frame missing for longer than 8
    # cycles is a sender that paused or changed its rate (its input goes stale), not a run of lost frames
    # that time stamps could count (they over-counted a 10 Hz feed of 10 ms frames by a wrap per frame)
    resync_after_cycles: float = 8.0


@dataclass(frozen=True)
class ClockConfig:
    """``clock:`` -- what drives the 1 Hz tick: ``wall`` (hardware) or ``frame`` timestamps."""

    mode: str = "wall"
    tick_s: float = 1.0
    max_catchup_s: float = 300.0


@dataclass(frozen=True)
class InputSignal:
    """How one model input is formed from CAN signals over a tick."""

    name: str
    frame: str
    reduce: str
    signals: tuple[str, ...]
    status: str | None = None
    resolution: float | None = None


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
    """Derating band of one limited model node."""

    name: str
    warn_c: float | None = None
    max_c: float | None = None
    reason: DerateReason = DerateReason.WINDING


@dataclass(frozen=True)
class FaultConfig:
    """``derating.faults:`` -- when the model counts as diverged."""

    innovation_k: float = 15.0
    innovation_ticks: int = 5
    prediction_error_k: float = 40.0
    hold_s: float = 30.0


@dataclass(frozen=True)
class DeratingConfig:
    """``derating:`` -- limits, bands, safe limit and how limits move."""

    max_current_a: float
    max_torque_nm: float
    safe_current_a: float
    safe_torque_nm: float | None = None
    kt_nm_per_arms: float | None = None
    band_z: float = 1.96
    limits: dict[str, LimitConfig] = field(default_factory=dict)
    rise_rate_a_per_s: float = 0.5
    hysteresis_a: float = 0.5
    faults: FaultConfig = field(default_factory=FaultConfig)
    #: how long the present limit must keep every limited node's upper band below its max
    #: (thermal_edge.service.derating explains the choice)
    reaction_time_s: float = 10.0
    #: kept below each max by the reaction-time current, K: the model error the band does not cover
    margin_k: float = 1.5
    #: the limit falls linearly over this many K below (max - margin) on the upper band, K
    approach_k: float = 3.0


@dataclass(frozen=True)
class LookaheadConfig:
    """``lookahead:`` -- horizon of the look-ahead current and the time to limit."""

    enabled: bool = True
    horizon_s: float = 1800.0
    steps: int = 60


@dataclass(frozen=True)
class AdaptationConfig:
    """``adaptation:`` -- :class:`AdapterConfig` fields plus how the service runs the adapter."""

    enabled: bool = True
    worker: str = "thread"
    apply_delay_ticks: int = 5
    bands: bool = True
    adapter: AdapterConfig = field(default_factory=AdapterConfig)


@dataclass(frozen=True)
class ObserverConfig:
    """``observer:`` -- Kalman filter noise levels (K)."""

    q_k: float = 0.02
    r_k: float = 0.15
    p0_k: float = 2.0
    restart_p0_k: float = 3.0


@dataclass(frozen=True)
class MetricsConfig:
    """``metrics:`` -- the Prometheus endpoint (read only; nothing listens for commands)."""

    enabled: bool = True
    address: str = "127.0.0.1"
    port: int = 9108


@dataclass(frozen=True)
class StateConfig:
    """``state:`` -- where parameters, decisions and the thermal state persist."""

    dir: Path
    save_interval_s: float = 60.0
    max_decisions: int = 500
    max_downtime_s: float = 7 * 86400.0


@dataclass(frozen=True)
class RecordingConfig:
    """``recording:`` -- optional candump -L recording of all RX/TX traffic."""

    candump: Path | None = None
    channel: str = "can0"


@dataclass(frozen=True)
class TransmitConfig:
    """``transmit:`` -- which limit goes into which TE_Estimates slot, cyclic periods, silence."""

    hot_spot_limit: str = "hot_spot"
    magnet_limit: str = "magnet"
    limits_period_s: float = 0.1
    status_period_s: float = 1.0
    bus_silence_s: float = 1.0


@dataclass(frozen=True)
class EdgeConfig:
    """The validated service configuration."""

    path: Path | None
    bus: BusConfig
    codec: CodecConfig
    model: ModelConfig
    clock: ClockConfig
    inputs: dict[str, InputSignal]
    sensors: dict[str, SensorSignal]
    valid_range_c: tuple[float, float]
    timeouts: dict[str, float]
    derating: DeratingConfig
    lookahead: LookaheadConfig
    adaptation: AdaptationConfig
    observer: ObserverConfig
    metrics: MetricsConfig
    state: StateConfig
    recording: RecordingConfig
    transmit: TransmitConfig

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
        for name in self.sensors:
            if name not in model.sensors:
                raise self.error(f"signals.sensors.{name}",
                                 f"model {model.name} has no sensor {name!r} (has: {', '.join(model.sensors)})")
        limit_names = {lim.name for lim in model.limits}
        for name, lim in self.derating.limits.items():
            if name not in limit_names:
                raise self.error(f"derating.limits.{name}",
                                 f"model {model.name} has no limited node {name!r} (has: {', '.join(sorted(limit_names)) or 'none'})")
        for lim in model.limits:
            warn, mx = self.limit_band(lim)
            if not mx > warn:
                raise self.error(f"derating.limits.{lim.name}.max_c", f"must be above warn_c ({warn:g}), got {mx:g}")
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
        if self.kt(model) is None:
            raise self.error("derating.kt_nm_per_arms", f"model {model.name} has no drive.kt_nm_per_arms: give it here")

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
        from .lptn import ParameterError  # (the model package is only needed once a model is loaded)

        for name, value in self.model.parameters.items():
            try:
                model.check_parameters({name: value})
            except ParameterError as exc:
                where = f" (bounds of {Path(model.path).name})" if exc.bounds is not None and model.path else ""
                raise self.error(f"model.parameters.{name}", f"{exc.problem}{where}") from None

    def check_state_dir(self, create: bool) -> None:
        """Check that ``state.dir`` is, or can be made, a directory; with ``create`` make it and
        check that this user can write it.

        Without ``create`` (``run --check``, perhaps as another user than the service's) only what
        no user could fix is an error: the path is a file, or lies under one.

        Raises
        ------
        ConfigError
            ``<file>: state.dir: ...``.
        """
        d = self.state.dir
        probe = d
        while not os.path.lexists(probe) and probe != probe.parent:
            probe = probe.parent
        if not probe.is_dir():
            msg = f"{d} is not a directory" if probe == d else f"{d} cannot be created: {probe} is not a directory"
            raise self.error("state.dir", msg)
        if not create:
            if probe != d:  # try to make a directory where it would go, then remove it
                try:
                    os.rmdir(tempfile.mkdtemp(prefix=".thermal-edge-check-", dir=probe))
                except PermissionError:
                    pass  # perhaps only for this user: the service's user may be allowed
                except OSError as exc:
                    raise self.error("state.dir", f"{d} cannot be created under {probe}: {exc.strerror or exc}") from None
            return
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise self.error("state.dir", f"cannot create {d}: {exc.strerror or exc}") from None
        if not os.access(d, os.W_OK | os.X_OK):
            raise self.error("state.dir", f"{d} is not writable by this user")

    def check_dbc(self, codec: Any) -> None:
        """Check that every mapped frame and signal exists in the DBC."""
        for section, items in (("inputs", self.inputs), ("sensors", self.sensors)):
            for name, spec in items.items():
                key = f"signals.{section}.{name}"
                try:
                    signals = set(codec.signal_names(spec.frame))
                except KeyError:
                    raise self.error(f"{key}.frame", f"no frame {spec.frame!r} in {Path(codec.dbc_path).name}") from None
                wanted = list(spec.signals) if isinstance(spec, InputSignal) else [spec.signal]
                if spec.status:
                    wanted.append(spec.status)
                for sig in wanted:
                    if sig not in signals:
                        raise self.error(key, f"frame {spec.frame} has no signal {sig!r}")
        for frame in self.timeouts:
            try:
                codec.frame_id(frame)
            except KeyError:
                raise self.error(f"timeouts.{frame}", f"no frame {frame!r} in {Path(codec.dbc_path).name}") from None

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
        return DerateReason.MAGNET if "magnet" in limit.name.lower() else DerateReason.WINDING



# ------------------------------------------------------------------------------------------
# parsing helpers
class _Section:
    """Reads one mapping of the file; every error names the file and the dotted key."""

    def __init__(self, fname: str, prefix: str, raw: Any) -> None:
        self.fname, self.prefix = fname, prefix
        if raw is None:
            raw = {}
        if not isinstance(raw, Mapping):
            raise self.fail("", f"expected a mapping, got {type(raw).__name__}")
        self.raw: Mapping[str, Any] = raw
        self.used: set[str] = set()

    def key(self, k: str) -> str:
        return f"{self.prefix}.{k}" if self.prefix and k else (self.prefix or k or "(top)")

    def fail(self, k: str, msg: str) -> ConfigError:
        return ConfigError(f"{self.fname}: {self.key(k)}: {msg}")

    def has(self, k: str) -> bool:
        return k in self.raw and self.raw[k] is not None

    def get(self, k: str, default: Any = None) -> Any:
        self.used.add(k)
        v = self.raw.get(k, default)
        return default if v is None else v

    def required(self, k: str) -> Any:
        self.used.add(k)
        if k not in self.raw or self.raw[k] is None:
            raise self.fail(k, "is required")
        return self.raw[k]

    def number(self, k: str, default: float | None = None, *, positive: bool = False, min_: float | None = None,
               max_: float | None = None, required: bool = False, allow_none: bool = False) -> Any:
        v = self.required(k) if required else self.get(k, default)
        if v is None:
            if allow_none:
                return None
            raise self.fail(k, "is required")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(k, f"expected a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise self.fail(k, f"must be finite, got {v}")
        if positive and not v > 0:
            raise self.fail(k, f"must be positive, got {v:g}")
        if min_ is not None and v < min_:
            raise self.fail(k, f"must be at least {min_:g}, got {v:g}")
        if max_ is not None and v > max_:
            raise self.fail(k, f"must be at most {max_:g}, got {v:g}")
        return v

    def integer(self, k: str, default: int, *, min_: int | None = None, max_: int | None = None) -> int:
        v = self.get(k, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(k, f"expected an integer, got {v!r}")
        if min_ is not None and v < min_:
            raise self.fail(k, f"must be at least {min_}, got {v}")
        if max_ is not None and v > max_:
            raise self.fail(k, f"must be at most {max_}, got {v}")
        return int(v)

    def boolean(self, k: str, default: bool) -> bool:
        v = self.get(k, default)
        if not isinstance(v, bool):
            raise self.fail(k, f"expected true or false, got {v!r}")
        return v

    def string(self, k: str, default: str | None = None, *, choices: Iterable[str] | None = None,
               required: bool = False) -> Any:
        v = self.required(k) if required else self.get(k, default)
        if v is None:
            return None
        if not isinstance(v, str) or not v:
            raise self.fail(k, f"expected a non-empty string, got {v!r}")
        if choices is not None and v not in choices:
            raise self.fail(k, f"must be one of {', '.join(choices)}, got {v!r}")
        return v

    def path(self, k: str, base: Path, default: str | None = None, *, required: bool = False) -> Path | None:
        v = self.string(k, default, required=required)
        if v is None:
            return None
        p = Path(os.path.expandvars(os.path.expanduser(v)))
        return p if p.is_absolute() else (base / p)

    def sub(self, k: str) -> "_Section":
        self.used.add(k)
        return _Section(self.fname, self.key(k), self.raw.get(k))

    def done(self, allow_extra: bool = False) -> None:
        if allow_extra:
            return
        extra = sorted(set(self.raw) - self.used, key=str)
        if extra:
            raise self.fail(str(extra[0]), f"unknown key{_did_you_mean(str(extra[0]), self.used)}")


def _did_you_mean(name: str, known: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``known``, else empty."""
    close = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _limits_period(sec: _Section) -> float:
    v = sec.number("limits_period_s", 0.1, positive=True)
    if v > MAX_LIMITS_PERIOD_S:
        raise sec.fail("limits_period_s", f"must be at most {MAX_LIMITS_PERIOD_S:g} s (the inverter drops TE_Limits after "
                                          f"{INVERTER_LIMITS_TIMEOUT_S * 1000:.0f} ms; one lost frame must not trip it), "
                                          f"got {v:g}")
    return v


def _str_list(sec: _Section, k: str) -> tuple[str, ...] | None:
    v = sec.get(k)
    if v is None:
        return None
    if isinstance(v, str):
        v = [v]
    if not isinstance(v, list) or not all(isinstance(x, str) and x for x in v):
        raise sec.fail(k, f"expected a list of names, got {v!r}")
    return tuple(v)


def _input_signal(sec: _Section, name: str) -> InputSignal:
    s = sec.sub(name)
    frame = s.string("frame", required=True)
    reduce = s.string("reduce", "mean", choices=REDUCTIONS)
    if reduce == "dq_rms":
        sigs = _str_list(s, "signals")
        if sigs is None or len(sigs) != 2:
            raise s.fail("signals", "dq_rms needs the two signals [d axis, q axis] (peak amplitudes)")
        if s.has("signal"):
            raise s.fail("signal", "use signals: [d, q] with reduce: dq_rms")
    else:
        sigs = (s.string("signal", required=True),)
        s.used.add("signals")
        if s.has("signals"):
            raise s.fail("signals", f"reduce: {reduce} takes one signal (signal: NAME)")
    status = s.string("status")
    resolution = s.number("resolution", None, positive=True, allow_none=True)
    s.done()
    return InputSignal(name, frame, reduce, tuple(sigs), status, resolution)


def _sensor_signal(sec: _Section, name: str) -> SensorSignal:
    s = sec.sub(name)
    out = SensorSignal(name, s.string("frame", required=True), s.string("signal", required=True), s.string("status"),
                       s.boolean("required", True))
    s.done()
    return out


def _adapter_config(sec: _Section) -> AdapterConfig:
    d = AdapterConfig()
    kwargs: dict[str, Any] = {}
    for f in fields(AdapterConfig):
        k = f.name
        if k in ("params", "sensors"):
            kwargs[k] = _str_list(sec, k)
        elif k == "method":
            kwargs[k] = sec.string(k, d.method, choices=METHODS)
        elif k == "weighting":
            kwargs[k] = sec.string(k, d.weighting, choices=WEIGHTINGS)
        elif k in ("decimate", "max_iter"):
            kwargs[k] = sec.integer(k, getattr(d, k), min_=1)
        elif k == "coverage":
            kwargs[k] = sec.number(k, d.coverage, positive=True, max_=1.0)
        elif k in ("period_s", "window_s", "tau_s", "validate_s"):
            kwargs[k] = sec.number(k, getattr(d, k), positive=True)
        else:  # thresholds, weights, tolerances (new numeric fields of AdapterConfig are read alike)
            kwargs[k] = sec.number(k, getattr(d, k), min_=0.0)
    return AdapterConfig(**kwargs)


# ------------------------------------------------------------------------------------------
def load_config(path: str | os.PathLike[str]) -> EdgeConfig:
    """Read and validate ``edge.yaml`` (structure, types, ranges).

    Raises
    ------
    ConfigError
        Unreadable file, invalid YAML, unknown or invalid key (the message names file and key).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path.name}: not a UTF-8 text file") from None
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1})" if mark is not None else ""
        raise ConfigError(f"{path.name}: not valid YAML{where}: {getattr(exc, 'problem', None) or exc}") from None
    return config_from_mapping(raw, path)


def config_from_mapping(raw: Any, path: str | os.PathLike[str] | None = None) -> EdgeConfig:
    """Validate an already parsed mapping (``path`` names the file in messages and anchors relative paths)."""
    p = Path(path) if path is not None else None
    fname = p.name if p is not None else "<config>"
    base = p.resolve().parent if p is not None else Path.cwd()
    top = _Section(fname, "", raw)

    # bus (python-can): BusConfig checks its keys (the interface's own keyword arguments, or options:)
    bus_raw = top.get("bus", {})
    if not isinstance(bus_raw, Mapping):
        raise ConfigError(f"{fname}: bus: expected a mapping, got {type(bus_raw).__name__}")
    try:
        bus = BusConfig.from_mapping({"node": "TE", **bus_raw})
    except (BusConfigError, TypeError, ValueError) as exc:  # BusConfigError names the key ("bus.chanel: ...")
        msg = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ConfigError(f"{fname}: {msg if msg.startswith('bus') else 'bus: ' + msg}") from None

    s = top.sub("codec")
    codec = CodecConfig(s.path("dbc", base), s.number("resync_after_cycles", CodecConfig.resync_after_cycles, positive=True))
    s.done()

    s = top.sub("model")
    mpath = s.path("path", base, required=True)
    ps = s.sub("parameters")
    params = {k: ps.number(k) for k in list(ps.raw)}
    ps.done()
    s.done()
    model = ModelConfig(mpath, params)  # type: ignore[arg-type]

    s = top.sub("clock")
    clock = ClockConfig(s.string("mode", "wall", choices=CLOCK_MODES), s.number("tick_s", 1.0, positive=True),
                        s.number("max_catchup_s", 300.0, positive=True))
    s.done()

    s = top.sub("signals")
    si = s.sub("inputs")
    inputs = {k: _input_signal(si, k) for k in list(si.raw)}
    if not inputs:
        raise si.fail("", "map at least the model's inputs to CAN signals")
    ss = s.sub("sensors")
    sensors = {k: _sensor_signal(ss, k) for k in list(ss.raw)}
    if not sensors:
        raise ss.fail("", "map at least one model sensor to a CAN signal")
    rng = s.get("valid_range_c", [-40.0, 250.0])
    if (not isinstance(rng, list) or len(rng) != 2 or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in rng)
            or not rng[0] < rng[1]):
        raise s.fail("valid_range_c", f"expected [low, high] in degC with low < high, got {rng!r}")
    s.done()

    s = top.sub("timeouts")
    timeouts = {k: s.number(k, positive=True) for k in list(s.raw)}
    s.done()

    s = top.sub("derating")
    max_i = s.number("max_current_a", required=True, positive=True)
    safe_i = s.number("safe_current_a", required=True, positive=True)
    if safe_i > max_i:
        raise s.fail("safe_current_a", f"must not exceed max_current_a ({max_i:g}), got {safe_i:g}")
    ls = s.sub("limits")
    limits: dict[str, LimitConfig] = {}
    for name in list(ls.raw):
        e = ls.sub(name)
        reason = e.string("reason", "magnet" if "magnet" in name.lower() else "winding", choices=tuple(REASON_NAMES))
        limits[name] = LimitConfig(name, e.number("warn_c", None, allow_none=True), e.number("max_c", None, allow_none=True),
                                   REASON_NAMES[reason])
        if limits[name].warn_c is not None and limits[name].max_c is not None and not limits[name].max_c > limits[name].warn_c:
            raise e.fail("max_c", f"must be above warn_c ({limits[name].warn_c:g}), got {limits[name].max_c:g}")
        e.done()
    ls.done()
    fs = s.sub("faults")
    faults = FaultConfig(fs.number("innovation_k", 15.0, positive=True), fs.integer("innovation_ticks", 5, min_=1),
                         fs.number("prediction_error_k", 40.0, positive=True), fs.number("hold_s", 30.0, min_=0.0))
    fs.done()
    derating = DeratingConfig(
        max_current_a=max_i,
        max_torque_nm=s.number("max_torque_nm", required=True, positive=True),
        safe_current_a=safe_i,
        safe_torque_nm=s.number("safe_torque_nm", None, positive=True, allow_none=True),
        kt_nm_per_arms=s.number("kt_nm_per_arms", None, positive=True, allow_none=True),
        band_z=s.number("band_z", 1.96, min_=0.0),
        limits=limits,
        rise_rate_a_per_s=s.number("rise_rate_a_per_s", 0.5, positive=True),
        hysteresis_a=s.number("hysteresis_a", 0.5, min_=0.0),
        faults=faults,
        reaction_time_s=s.number("reaction_time_s", DeratingConfig.reaction_time_s, positive=True, max_=600.0),
        margin_k=s.number("margin_k", DeratingConfig.margin_k, min_=0.0, max_=50.0),
        approach_k=s.number("approach_k", DeratingConfig.approach_k, positive=True, max_=100.0),
    )
    s.done()

    s = top.sub("lookahead")
    lookahead = LookaheadConfig(s.boolean("enabled", True), s.number("horizon_s", 1800.0, positive=True, max_=65535),
                                s.integer("steps", 60, min_=1, max_=10000))
    s.done()

    s = top.sub("adaptation")
    enabled = s.boolean("enabled", True)
    worker = s.string("worker", "thread", choices=WORKERS)
    delay = s.integer("apply_delay_ticks", 5, min_=1)
    bands = s.boolean("bands", True)
    adapter = _adapter_config(s)
    s.done()
    adaptation = AdaptationConfig(enabled, worker, delay, bands, adapter)

    s = top.sub("observer")
    observer = ObserverConfig(s.number("q_k", 0.02, positive=True), s.number("r_k", 0.15, positive=True),
                              s.number("p0_k", 2.0, positive=True), s.number("restart_p0_k", 3.0, positive=True))
    s.done()

    s = top.sub("metrics")
    address = s.string("address", MetricsConfig.address)
    try:  # an address to bind, not a name: what it binds to must be plain in the file
        ipaddress.ip_address(address)
    except ValueError:
        raise s.fail("address", f"not an IP address: {address!r} (127.0.0.1 or ::1 for this host only; "
                                "0.0.0.0 or an interface's address to be scraped from the network)") from None
    metrics = MetricsConfig(s.boolean("enabled", MetricsConfig.enabled), address,
                            s.integer("port", MetricsConfig.port, min_=0, max_=65535))
    s.done()

    s = top.sub("state")
    default_dir = os.environ.get("STATE_DIRECTORY", "").split(":")[0] or None
    sdir = s.path("dir", base, default_dir, required=default_dir is None)
    state = StateConfig(sdir, s.number("save_interval_s", 60.0, positive=True),  # type: ignore[arg-type]
                        s.integer("max_decisions", 500, min_=0, max_=MAX_DECISIONS), s.number("max_downtime_s", 7 * 86400.0, positive=True))
    s.done()

    s = top.sub("recording")
    recording = RecordingConfig(s.path("candump", base), s.string("channel", "can0"))
    s.done()

    s = top.sub("transmit")
    transmit = TransmitConfig(s.string("hot_spot_limit", "hot_spot"), s.string("magnet_limit", "magnet"),
                              _limits_period(s), s.number("status_period_s", 1.0, positive=True),
                              s.number("bus_silence_s", 1.0, positive=True))
    s.done()
    top.used.add("bus")
    top.done()

    if recording.candump is not None and bus.record_path is None:
        bus = BusConfig(**{**{f.name: getattr(bus, f.name) for f in fields(BusConfig)},
                           "record_path": recording.candump, "record_channel": recording.channel})
    return EdgeConfig(
        path=p, bus=bus, codec=codec, model=model, clock=clock, inputs=inputs, sensors=sensors,
        valid_range_c=(float(rng[0]), float(rng[1])), timeouts=timeouts, derating=derating, lookahead=lookahead,
        adaptation=adaptation, observer=observer, metrics=metrics, state=state, recording=recording, transmit=transmit,
    )
