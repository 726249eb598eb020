"""What a running service shows an operator, read from its ``/metrics`` or from its CAN frames.

Both sources fill one :class:`Snapshot`, so the view does not care where the figures came from.
The metrics give everything (estimates with bands, sensors, adaptation, input freshness); the bus
gives what the inverter sees (the four ``TE_*`` frames and the age of every frame on the bus),
which works on a drive without network access to the edge computer.
"""
from __future__ import annotations

import math
import time
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field

from ..bus.codec import DecodedFrame
from ..bus.frames import (
    TE_ESTIMATES,
    TE_FORECAST,
    TE_LIMITS,
    TE_STATUS,
    TIME_TO_LIMIT_NOT_WITHIN_HORIZON_S,
    DerateReason,
    TeState,
)

__all__ = ["FrameWatch", "NodeView", "SensorView", "Snapshot", "fetch_metrics", "from_metrics"]

P = "thermal_edge_"


@dataclass
class NodeView:
    """A limited node: estimate and 95 % upper band (°C), its warn and max (°C) when known."""

    name: str
    estimate_c: float
    upper_c: float
    warn_c: float = math.nan
    max_c: float = math.nan


@dataclass
class SensorView:
    """One sensor: latest usable reading (°C), prediction error (K), seconds since its last reading, fault kind."""

    name: str
    measured_c: float = math.nan
    error_k: float = math.nan
    age_s: float = math.nan
    fault: str = ""


@dataclass
class Snapshot:
    """The service as one screen shows it.

    Attributes
    ----------
    source : str
        Where it was read ("http://…/metrics" or "bus udp_multicast:…").
    current_limit_a, torque_limit_nm : float
        The limits in force (A rms, Nm).
    reason : str
        Derate reason (lower case enumeration name; "none" at full limits).
    state : str
        Service state (lower case).
    nodes : list of NodeView
        Limited nodes with their bands.
    lookahead_a, time_to_limit_s, horizon_s : float
        Look-ahead advice: the current that could be held over the horizon (A), the time to the first
        limit at the present load (s; inf: not within the horizon), the horizon (s).
    pred_err_rms_k : float
        RMS open-loop prediction error of the last period (K).
    adapt_runs, adapt_accepted, adapt_rejected, param_version : int
        Adaptation counts (bus: runs and version only).
    adapt_status : str
        What the adaptation is doing ("fits", "waiting_for_evidence", "learning", "refusing", ...;
        metrics only, "" when unknown).
    adapt_refusal : str
        Why the last challenger was dropped ("" if none was; metrics only).
    adapt_refusal_t, tick_t : float
        When it was dropped and the time of the last tick (s, the service's clock).
    sensors : list of SensorView
    stale : list of str
        Frames missing longer than their timeout (metrics), or not seen for 3 cycle times (bus).
    frame_ages : dict
        Frame name -> seconds since last seen (bus).
    unheard : list
        Frames with a cycle time in the CAN matrix never heard on the bus (bus view).
    dropped : int
        Frames dropped by the integrity checks (metrics).
    bus_silent_s : float
        Seconds without an accepted frame once beyond ``transmit.bus_silence_s`` (0: frames come; metrics).
    flux_used : int
        Ticks whose magnet estimate from the inverter's voltages was fused (None: no voltage input; metrics).
    flux_refused : dict
        Reason -> ticks whose estimate was refused (metrics).
    flux_magnet_c, flux_magnet_sigma_k : float
        The last fused magnet estimate from the voltages and its standard deviation (°C, K; metrics).
    """

    source: str
    current_limit_a: float = math.nan
    torque_limit_nm: float = math.nan
    reason: str = "?"
    state: str = "?"
    nodes: list[NodeView] = field(default_factory=list)
    lookahead_a: float = math.nan
    time_to_limit_s: float = math.nan
    horizon_s: float = math.nan
    pred_err_rms_k: float = math.nan
    adapt_runs: int | None = None
    adapt_accepted: int | None = None
    adapt_rejected: int | None = None
    param_version: int | None = None
    adapt_status: str = ""
    adapt_refusal: str = ""
    adapt_refusal_t: float = math.nan
    tick_t: float = math.nan
    sensors: list[SensorView] = field(default_factory=list)
    stale: list[str] = field(default_factory=list)
    frame_ages: dict[str, float] = field(default_factory=dict)
    unheard: list[str] = field(default_factory=list)
    dropped: int | None = None
    bus_silent_s: float = 0.0
    flux_used: int | None = None
    flux_refused: dict[str, int] = field(default_factory=dict)
    flux_magnet_c: float = math.nan
    flux_magnet_sigma_k: float = math.nan


def _enum_name(enum_cls: type[DerateReason] | type[TeState], code: float) -> str:
    try:
        return enum_cls(int(code)).name.lower()
    except ValueError:
        return f"unknown ({int(code)})"


def fetch_metrics(url: str, timeout_s: float = 3.0) -> str:
    """The exposition text at ``url``; raises OSError when the service cannot be reached."""
    with urllib.request.urlopen(url, timeout=timeout_s) as resp:  # a URL the user gave
        return resp.read().decode()


def from_metrics(text: str, source: str = "metrics") -> Snapshot:
    """A :class:`Snapshot` from the service's Prometheus exposition text."""
    from prometheus_client.parser import text_string_to_metric_families

    snap = Snapshot(source)
    nodes: dict[str, NodeView] = {}
    sensors: dict[str, SensorView] = {}

    def sensor(name: str) -> SensorView:
        return sensors.setdefault(name, SensorView(name))

    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            name, lab, v = s.name, s.labels, float(s.value)
            if not name.startswith(P):
                continue
            key = name[len(P):]
            if key == "current_limit_amperes":
                snap.current_limit_a = v
            elif key == "torque_limit_newton_meters":
                snap.torque_limit_nm = v
            elif key == "derate_reason_code":
                snap.reason = _enum_name(DerateReason, v)
            elif key == "state_code":
                snap.state = _enum_name(TeState, v)
            elif key == "limited_node_celsius":
                n = nodes.setdefault(lab["limit"], NodeView(lab["limit"], math.nan, math.nan))
                setattr(n, {"estimate": "estimate_c", "upper": "upper_c", "warn": "warn_c", "max": "max_c"}[lab["band"]], v)
            elif key == "lookahead_current_amperes":
                snap.lookahead_a = v
            elif key == "time_to_limit_seconds":
                snap.time_to_limit_s = v
            elif key == "lookahead_horizon_seconds":
                snap.horizon_s = v
            elif key == "prediction_error_rms_celsius":
                snap.pred_err_rms_k = v
            elif key == "adaptation_runs_total":
                snap.adapt_runs = int(v)
            elif key == "adaptation_accepted_total":
                snap.adapt_accepted = int(v)
            elif key == "adaptation_rejected_total":
                snap.adapt_rejected = int(v)
            elif key == "parameter_version":
                snap.param_version = int(v)
            elif key == "adaptation_status" and v:
                snap.adapt_status = lab.get(name, "")
            elif key == "adaptation_last_refusal_timestamp_seconds":
                snap.adapt_refusal, snap.adapt_refusal_t = lab.get("reason", ""), v
            elif key == "last_tick_timestamp_seconds":
                snap.tick_t = v
            elif key == "sensor_measurement_celsius":
                sensor(lab["sensor"]).measured_c = v
            elif key == "prediction_error_celsius":
                sensor(lab["sensor"]).error_k = v
            elif key == "sensor_age_seconds":
                sensor(lab["sensor"]).age_s = v
            elif key == "sensor_fault" and v:
                sensor(lab["sensor"]).fault = lab["kind"]
            elif key == "input_stale" and v:
                snap.stale.append(lab["frame"])
            elif key == "frames_dropped_total":
                snap.dropped = (snap.dropped or 0) + int(v)
            elif key == "bus_silent_seconds":
                snap.bus_silent_s = v
            elif key == "flux_used_total":
                snap.flux_used = int(v)
            elif key == "flux_refused_total":
                snap.flux_refused[lab.get("reason", "?")] = int(v)
            elif key == "flux_magnet_celsius":
                snap.flux_magnet_c = v
            elif key == "flux_magnet_stddev_celsius":
                snap.flux_magnet_sigma_k = v
    snap.nodes = list(nodes.values())
    snap.sensors = sorted(sensors.values(), key=lambda x: x.name)
    return snap


class FrameWatch:
    """Collects the ``TE_*`` frames and the age of every frame seen on a bus into a :class:`Snapshot`.

    Parameters
    ----------
    source : str
        Description of the bus, shown in the view.
    cycle_s : dict, optional
        Frame name -> cycle time (s): a frame not seen for 3 cycles is listed as stale.
    clock : callable, optional
        Monotonic time in s (tests).
    """

    def __init__(self, source: str, cycle_s: dict[str, float] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.snapshot = Snapshot(source)
        self.cycle_s = dict(cycle_s or {})
        self._clock = clock
        self._seen: dict[str, float] = {}

    def add(self, frame: DecodedFrame) -> None:
        """Take one decoded frame."""
        self._seen[frame.name] = self._clock()
        s, snap = frame.signals, self.snapshot
        if frame.name == TE_LIMITS:
            snap.current_limit_a = float(s["TE_CurrentLimit"])
            snap.torque_limit_nm = float(s["TE_TorqueLimit"])
            snap.reason = _enum_name(DerateReason, s["TE_DerateReason"])
        elif frame.name == TE_ESTIMATES:
            snap.nodes = [NodeView("hot_spot", float(s["TE_T_HotSpot"]), float(s["TE_T_HotSpotUpper"])),
                          NodeView("magnet", float(s["TE_T_Magnet"]), float(s["TE_T_MagnetUpper"]))]
        elif frame.name == TE_FORECAST:
            ttl = float(s["TE_TimeToLimit"])
            snap.time_to_limit_s = math.inf if ttl >= TIME_TO_LIMIT_NOT_WITHIN_HORIZON_S else ttl
            snap.lookahead_a = float(s["TE_LookaheadCurrent"])
            snap.horizon_s = float(s["TE_Horizon"])
        elif frame.name == TE_STATUS:
            snap.state = _enum_name(TeState, s["TE_State"])
            snap.pred_err_rms_k = float(s["TE_PredErrRms"])
            snap.adapt_accepted = int(s["TE_AdaptCount"])
            snap.param_version = int(s["TE_ParamVersion"])

    def current(self) -> Snapshot:
        """The snapshot with the frame ages and stale frames as of now."""
        now = self._clock()
        snap = self.snapshot
        snap.frame_ages = {k: now - t for k, t in sorted(self._seen.items())}
        snap.stale = [k for k, age in snap.frame_ages.items() if k in self.cycle_s and age > 3 * self.cycle_s[k]]
        snap.unheard = sorted(k for k in self.cycle_s if k not in self._seen)
        return snap
