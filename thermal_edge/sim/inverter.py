"""The inverter emulator: a simulated machine ("plant") behind the inverter's CAN frames.

It sends ``INV_Currents`` and ``INV_Mechanics`` (every ``current_period_s``, the DBC's 10 ms by
default) and ``INV_StatorTemps`` / ``INV_AmbientTemps`` (every ``temperature_period_s``, 100 ms)
from a plant -- the machine model with its own parameters (e.g. the paper's Table 4 variations,
or aging over time) -- with PT100 noise and quantisation and a drifting ambient, driven by a drive
cycle (a file, or one shipped with the package: :mod:`thermal_edge.shipped`).

Closed loop, it **obeys** the ``TE_Limits`` it receives: the torque demand of the cycle is clamped
to the torque limit and to the current limit times the torque constant (i_d = 0 control; with an
electrical model the field-weakening i_d at high speed, and the current magnitude within the limit). Without
a valid ``TE_Limits`` for ``limits_timeout_s`` (wall clock, 300 ms like the real inverter) it falls
back to its own protection: ``fallback_current_a`` (None: no limit); accelerated, a limit also
counts as absent after ``limits_timeout_sim_s`` of simulated time (300 ms of wall time would be
minutes of machine time). Open loop it ignores them.

Time: simulated time advances ``speed`` times faster than the wall clock (1: real time) and every
frame's timestamp is its simulated time (an absolute epoch time starting at ``t0``). Each frame
is sent at its own time (scaled by ``speed``; frames due within 1 ms go at once), so in real time
``INV_Currents`` comes every 10 ms as from the inverter, not a plant step's frames in a burst.
With ``flow_control`` the emulator also stays at most ``max_lead_s`` of simulated time ahead of
the service's ticks: it counts the service's ``TE_Status`` frames (one per tick with the frame
clock) against the tick boundaries its own frames cross since its run began, so the service
must be listening by then. A receiver that falls behind (e.g. while adapting) is thus waited for
instead of having its ``udp_multicast`` socket overflow. If no ``TE_Status`` arrives while it has
waited ``flow_timeout_s`` (its own pauses on a busy host not counted) the emulator runs on at
``speed`` and counts again from the next ``TE_Status``. With ``max_free_s`` it runs on for at most
that much simulated time and then waits for a service's ``TE_Limits`` (up to ``FREE_WAIT_MAX_S``
of wall time): a test that restarts its service gets a downtime of known length however long the new
process takes to start on a busy host.

With an electrical model (``EmulatorConfig.pmsm``, :class:`.pmsm.Pmsm`) the currents have the
field-weakening ``i_d`` above the machine's base speed (it heats the winding like ``i_q``), and with
``EmulatorConfig.voltages`` it also sends the optional ``INV_Voltages`` with every
``INV_Currents``: the dq voltage references the current controller would command for those
currents at that speed, from the plant's *true* winding and magnet temperatures (plus the model's
voltage noise, from a random stream of its own, so that the PT100 readings are the same with and
without the voltage frame).

The plant's true node temperatures now are :attr:`InverterEmulator.T`. A trace of them (a row
every ``trace_every_s``) and a log of the ``TE_Estimates`` and ``TE_Limits`` changes received
(``record_estimates``) are kept only when asked (tests, ``--trace``): they grow with the run, and
a demo or a bench runs for days.

Run as a process: ``python -m thermal_edge.sim.inverter --help``.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..bus.busconfig import BusConfig, create_bus, interface_keywords
from ..bus.codec import DecodedFrame, FrameCodec
from ..bus.frames import (
    DEFAULT_DBC_PATH,
    INV_AMBIENT_TEMPS,
    INV_CURRENTS,
    INV_MECHANICS,
    INV_STATOR_TEMPS,
    INV_VOLTAGES,
    TE_ESTIMATES,
    TE_LIMITS,
    TE_STATUS,
    SensorStatus,
)
from ..bus.logs import LogRecorder
from ..errors import UsageError
from ..lptn import Model, Role, load_model
from ..shipped import CYCLES, MACHINES, config_path, cycle_file, model_file
from .cycles import AMBIENT, COOLANT, SPEED, TORQUE, cycle_run, load_cycle
from .plant import Plant
from .pmsm import Pmsm
from .sensors import pt100

__all__ = ["DEFAULT_SENSOR_SIGNALS", "STATOR_FRAME", "EmulatorConfig", "InverterEmulator", "TABLE4_VARIATIONS", "main",
           "mapped_sensor_signals", "write_log"]

log = logging.getLogger(__name__)

#: frames due sooner than this are sent at once (accelerated runs: a sleep per frame would only add
#: event-loop turns); later ones are slept for, so a real-time run sends at the DBC's cycle
PACE_MIN_SLEEP_S = 0.001
#: longest gap between two polls of the flow-control wait that counts fully as the service's
#: silence (wall s); a longer one is the emulator's own pause
FLOW_POLL_MAX_S = 0.1
#: longest wall time the emulator waits for a service after running on for ``max_free_s``
FREE_WAIT_MAX_S = 120.0

#: The paper's Table 4 parameter variations (additive, in the parameters' units).
TABLE4_VARIATIONS: dict[str, float] = {"k_r_sw": 4.0, "k_c_sw": 1.5, "c_p_sw": -50.0, "R_e_hous": -4.0}

#: the frame of the stator PT100s the emulator sends
STATOR_FRAME = "INV_StatorTemps"
#: Default PT100 signals -> model sensors (the pm10kw model's production sensor set).
DEFAULT_SENSOR_SIGNALS: dict[str, str] = {
    "INV_T_WindingSlot": "slot_winding",
    "INV_T_EndWinding": "end_winding",
    "INV_T_Housing": "housing",
}
_STATUS_OF = {"INV_T_WindingSlot": "INV_S_WindingSlot", "INV_T_EndWinding": "INV_S_EndWinding",
              "INV_T_Housing": "INV_S_Housing"}


def mapped_sensor_signals(sensors: Mapping[str, Any]) -> dict[str, str]:
    """The PT100 signals of the emulator's :data:`STATOR_FRAME` -> the sensor each carries, as a
    service configuration's ``signals.sensors`` (sensor -> frame and signal) maps them; a sensor
    mapped elsewhere is not sent."""
    return {spec.signal: name for name, spec in sensors.items()
            if spec.frame == STATOR_FRAME and spec.signal in DEFAULT_SENSOR_SIGNALS}


def table4_parameters(model: Model, sign: float = 1.0) -> dict[str, float]:
    """The model's nominal values moved by the Table 4 variations (``sign`` -1: the other way)."""
    nominal = dict(zip(model.parameter_names, model.nominal()))
    return {k: float(nominal[k] + sign * v) for k, v in TABLE4_VARIATIONS.items()}


@dataclass
class EmulatorConfig:
    """Settings of the emulator (all times in simulated seconds unless marked wall)."""

    model_path: str | Path = field(default_factory=lambda: config_path(MACHINES, "pm10kw.yaml"))
    cycle_path: str | Path = field(default_factory=lambda: config_path(CYCLES, "overload.yaml"))
    params: dict[str, float] = field(default_factory=dict)  # the plant's parameters (absolute values)
    aging: dict[str, float] = field(default_factory=dict)  # relative change per simulated hour
    aging_update_s: float = 60.0
    duration_s: float | None = None  # default: the cycle's duration
    speed: float = 1.0  # simulated s per wall s; 0: as fast as flow control allows
    t0: float | None = None  # simulated epoch of the start (default: wall time at start)
    current_period_s: float = 0.01
    temperature_period_s: float = 0.1
    plant_dt_s: float = 0.1
    noise_k: float = 0.1
    resolution_k: float = 0.1
    ambient_drift_k: float = 0.0  # amplitude of a sinusoidal ambient drift, K
    ambient_offset_k: float = 0.0  # added to the cycle's ambient (and coolant), K (e.g. a hot day)
    ambient_drift_period_s: float = 7200.0
    current_ripple: float = 0.0  # relative ripple of the current over successive frames
    udc_v: float = 560.0
    closed_loop: bool = True
    limits_timeout_s: float = 0.3  # wall
    limits_timeout_sim_s: float | None = None  # simulated; default: max_lead_s + 3 service ticks
    fallback_current_a: float | None = None
    flow_control: bool = True
    max_lead_s: float = 10.0
    flow_timeout_s: float = 2.0  # wall
    max_free_s: float | None = None  # simulated s run on without a service before waiting for one again
    service_tick_s: float = 1.0
    #: simulated s between rows of the trace (:meth:`InverterEmulator.trace`); inf: no trace (a row a
    #: second of a 39-node model is 2 MB per simulated hour, kept for the whole run)
    trace_every_s: float = math.inf
    #: keep every TE_Estimates and TE_Limits change received (the trace's ``est_*``, ``limit_*``; about
    #: 1.5 MB per simulated hour of a closed loop)
    record_estimates: bool = False
    seed: int = 0
    sensor_signals: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_SENSOR_SIGNALS))
    #: the machine's electrical side: with it the currents have the field-weakening ``i_d`` at high speed
    #: (:meth:`.pmsm.Pmsm.currents`; None: ``i_d = 0``) and, with ``voltages``, INV_Voltages goes out with
    #: every INV_Currents
    pmsm: Pmsm | None = None
    #: send INV_Voltages (with ``pmsm``)
    voltages: bool = True
    #: the plant node whose temperature the stator resistance has ...
    pmsm_winding_node: str = "slot_winding_1"
    #: ... and the nodes whose mean temperature the flux linkage has
    pmsm_magnet_nodes: tuple[str, ...] = ("magnet_1", "magnet_2")


@dataclass
class EmulatorSummary:
    """What happened in a run (JSON-serialisable)."""

    sim_start: float = 0.0
    sim_end: float = 0.0
    sim_seconds: float = 0.0
    wall_seconds: float = 0.0
    frames_sent: dict[str, int] = field(default_factory=dict)
    send_failures: int = 0
    frames_received: dict[str, int] = field(default_factory=dict)
    rx_lost: int = 0
    rx_dropped: dict[str, int] = field(default_factory=dict)
    limits_received: int = 0
    limits_applied_s: float = 0.0  # simulated time with a valid TE_Limits in force
    limited_s: float = 0.0  # simulated time the demand was clamped
    flow_waits: int = 0
    flow_wait_wall_s: float = 0.0
    #: waits given up after ``flow_timeout_s`` of the service's silence (the emulator then runs on)
    flow_timeouts: int = 0
    #: received datagrams that were no CAN message (garbage on a udp_multicast group): skipped
    rx_undecodable: int = 0
    true_max_c: dict[str, float] = field(default_factory=dict)  # per limited node of the model
    true_max_t: dict[str, float] = field(default_factory=dict)
    closed_loop: bool = True
    params: dict[str, float] = field(default_factory=dict)


class InverterEmulator:
    """Emulate the inverter and its machine on a CAN bus (or into a candump log).

    Parameters
    ----------
    config : EmulatorConfig
    bus : BusConfig or mapping, optional
        The bus (its ``node`` is forced to ``INV``); not needed for :meth:`write_log`.
    codec : FrameCodec, optional
    model : Model, optional
        The machine model (default: ``config.model_path``); the plant applies ``config.params``.
    """

    def __init__(self, config: EmulatorConfig, bus: BusConfig | Mapping[str, Any] | None = None,
                 codec: FrameCodec | None = None, model: Model | None = None) -> None:
        self.config = cfg = config
        self.model = model if model is not None else load_model(cfg.model_path)
        # the service's frames pause while it bridges ticks in simulated time: counter alone
        self.codec = codec if codec is not None else FrameCodec(DEFAULT_DBC_PATH, resync_after_cycles=1e9,
                                                                wraps_from_time=False)
        if bus is not None:
            b = dict(bus.__dict__) if isinstance(bus, BusConfig) else dict(bus)
            if isinstance(bus, BusConfig):
                opts = b.pop("options", {})
                b.update(opts)
            b["node"] = "INV"
            self.bus_config: BusConfig | None = BusConfig.from_mapping(b)
        else:
            self.bus_config = None
        kt = self.model.drive.get("kt_nm_per_arms")
        if kt is None:
            raise ValueError(f"model {self.model.name} has no drive.kt_nm_per_arms: cannot turn torque into current")
        self.kt = float(kt)
        cycle = load_cycle(cfg.cycle_path)
        self.cycle = cycle
        self.duration = float(cfg.duration_s if cfg.duration_s is not None else cycle.duration_s)
        self.run_inputs = cycle_run(cycle, self.kt, self.duration)
        if cfg.ambient_offset_k:
            for c in (AMBIENT, COOLANT):
                self.run_inputs.columns[c] = self.run_inputs.columns[c] + cfg.ambient_offset_k
        self.cycle_dt = cycle.dt_s
        amb0 = float(self.run_inputs.columns[AMBIENT][0])
        self.plant = Plant(self.model, cfg.params, cfg.plant_dt_s, cfg.aging,
                           rest_inputs={c: amb0 for c in self.model.temperature_inputs})
        # the model's inputs the emulator drives (a model may lack torque), by role
        self._input_of = {r: self.model.find_input(r) for r in (Role.SPEED, Role.TORQUE, Role.CURRENT, Role.AMBIENT)}
        self.rng = np.random.default_rng(cfg.seed)
        #: rows of the winding node (the stator resistance's temperature) and of the magnet nodes (the
        #: flux linkage's) that the electrical model reads; the voltage frame's rows where it is sent
        self._electrical_rows: tuple[int, list[int]] | None = None
        if cfg.pmsm is not None:
            missing = [n for n in (cfg.pmsm_winding_node, *cfg.pmsm_magnet_nodes) if n not in self.model.nodes]
            if missing or not cfg.pmsm_magnet_nodes:
                raise UsageError(f"inverter voltages: model {self.model.name} has no node(s) "
                                 f"{', '.join(missing) or '(none given)'} (has: {', '.join(self.model.nodes)})")
            self._electrical_rows = (self.model.node_index(cfg.pmsm_winding_node),
                                     [self.model.node_index(n) for n in cfg.pmsm_magnet_nodes])
        self._voltage_rows = self._electrical_rows if cfg.voltages else None
        # the voltage noise from a stream of its own: the PT100 readings stay those of a run without voltages
        self._u_rng = np.random.default_rng([cfg.seed, 0x2D0])
        self.t0 = float(cfg.t0) if cfg.t0 is not None else time.time()
        self.elapsed = 0.0  # simulated seconds since t0
        self._ts = self.t0
        self._frame_k = 0
        self._temp_k = 0
        self._next_trace = 0.0 if math.isfinite(cfg.trace_every_s) else math.inf
        self._next_aging = 0.0
        # fault injection (tests)
        self.sensor_status: dict[str, int] = {}
        self.sensor_offset: dict[str, float] = {}
        self.paused: set[str] = set()
        # limits and service progress
        self.current_limit: float | None = None
        self.torque_limit: float | None = None
        self.limits_wall: float | None = None
        self.limits_sim = -math.inf
        self.last_reason: int | None = None
        self.status_count = 0
        self._status_event: asyncio.Event | None = None
        self.estimates: list[tuple[float, float, float, float, float, float]] = []  # (sim t, rx ts, hs, hsU, mg, mgU)
        self.limit_log: list[tuple[float, float, float, int]] = []  # (sim t, current, torque, reason)
        # traces
        self.trace_t: list[float] = []
        self.trace_T: list[np.ndarray] = []
        self.trace_i: list[tuple[float, float, float]] = []  # (demand i_rms, applied i_rms, ambient)
        self.summary = EmulatorSummary(closed_loop=cfg.closed_loop, params=dict(cfg.params))
        self._limit_nodes = {lim.name: self.model.node_index(lim.node) for lim in self.model.limits}
        self._true_max = {n: -math.inf for n in self._limit_nodes}
        self._true_max_t = {n: 0.0 for n in self._limit_nodes}
        self.bus: Any = None
        self._stop = False

    # ------------------------------------------------------------------------------------------
    @property
    def T(self) -> np.ndarray:
        """The plant's true node temperatures now, °C."""
        return self.plant.T.copy()

    @property
    def sim_time(self) -> float:
        """Simulated time now (absolute, s since the epoch)."""
        return self.t0 + self.elapsed

    def true(self, node: str) -> float:
        return self.plant.node(node)

    def trace(self) -> dict[str, np.ndarray]:
        """Arrays of the trace: ``t`` (absolute simulated time), ``T`` (t, nodes), ``i_demand``,
        ``i_applied``, ``ambient``, and the estimates received (``est_*``)."""
        i = np.array(self.trace_i) if self.trace_i else np.zeros((0, 3))
        e = np.array(self.estimates) if self.estimates else np.zeros((0, 6))
        lg = np.array(self.limit_log) if self.limit_log else np.zeros((0, 4))
        return {
            "t": np.array(self.trace_t), "T": np.array(self.trace_T) if self.trace_T else np.zeros((0, len(self.model.nodes))),
            "i_demand": i[:, 0], "i_applied": i[:, 1], "ambient": i[:, 2],
            "est_t": e[:, 0], "est_ts": e[:, 1], "est_hot_spot": e[:, 2], "est_hot_spot_upper": e[:, 3],
            "est_magnet": e[:, 4], "est_magnet_upper": e[:, 5],
            "limit_t": lg[:, 0], "limit_current": lg[:, 1], "limit_torque": lg[:, 2], "limit_reason": lg[:, 3],
        }

    def stop(self) -> None:
        self._stop = True

    # -- one plant step -------------------------------------------------------------------------
    def demand(self, tau: float) -> tuple[float, float, float]:
        """What the cycle demands at ``tau`` (simulated s since the start): speed (rpm), torque
        (Nm, before any limit clips it) and ambient (°C)."""
        cols = self.run_inputs.columns
        k = min(int(tau // self.cycle_dt), len(self.run_inputs) - 1)
        amb = float(cols[AMBIENT][k])
        cfg = self.config
        if cfg.ambient_drift_k:
            amb += cfg.ambient_drift_k * math.sin(2 * math.pi * tau / cfg.ambient_drift_period_s)
        return float(cols[SPEED][k]), float(cols[TORQUE][k]), amb

    def _limits_in_force(self, now_wall: float | None) -> tuple[float | None, float | None, bool]:
        """(current limit, torque limit, from a fresh TE_Limits)."""
        cfg = self.config
        if not cfg.closed_loop:
            return None, None, False
        sim_timeout = (cfg.limits_timeout_sim_s if cfg.limits_timeout_sim_s is not None
                       else cfg.max_lead_s + 3 * cfg.service_tick_s)
        # an infinite wall-clock time-out leaves the simulated one alone in force (an accelerated run on a
        # busy host: a pause of this process is no time of the plant's)
        wall_s = cfg.limits_timeout_s if math.isfinite(cfg.limits_timeout_s) else 0.0
        fresh = (self.limits_wall is not None and (now_wall is None or now_wall - self.limits_wall <= cfg.limits_timeout_s)
                 and self.sim_time - self.limits_sim <= max(sim_timeout, wall_s))
        if fresh:
            return self.current_limit, self.torque_limit, True
        if cfg.fallback_current_a is not None:
            return cfg.fallback_current_a, cfg.fallback_current_a * self.kt, False
        return None, None, False

    def step(self, now_wall: float | None) -> list[tuple[float, str, dict[str, float]]]:
        """Advance the plant by one step (``plant_dt_s``) under the limits in force at ``now_wall``
        (monotonic s; None: the last limits, as a bench that drives the emulator directly sets
        them); return the frames of that step as (simulated timestamp, frame name, signals)."""
        cfg = self.config
        tau = self.elapsed
        dt = cfg.plant_dt_s
        if self.plant.aging and tau >= self._next_aging:
            self.plant.age(tau / 3600.0)
            self._next_aging = tau + cfg.aging_update_s
        speed, torque_d, amb = self.demand(tau)
        i_lim, t_lim, fresh = self._limits_in_force(now_wall)
        if not fresh and i_lim == 0.0:  # its own protection tripped the drive: the machine stands still
            speed = 0.0
        torque = torque_d
        limited = False
        if i_lim is not None:
            cap = min(t_lim if t_lim is not None else math.inf, i_lim * self.kt)
            if abs(torque) > cap:
                torque = math.copysign(cap, torque)
                limited = True
        if fresh:
            self.summary.limits_applied_s += dt
        if limited:
            self.summary.limited_s += dt
        i_d = 0.0
        if cfg.pmsm is not None:  # field weakening: i_d at high speed, the current magnitude within the limit
            T = self.plant.T
            assert self._electrical_rows is not None  # set with pmsm
            w_row, m_rows = self._electrical_rows
            d, q = cfg.pmsm.currents(np.array(torque), self.kt, np.array(speed), np.array(T[w_row]),
                                     np.array(float(np.mean(T[m_rows]))), i_lim)
            i_d, i_q_peak = float(d), float(q)
            if abs(i_q_peak) < math.sqrt(2.0) * abs(torque) / self.kt - 1e-9:  # the current limit took torque
                torque = i_q_peak / math.sqrt(2.0) * self.kt
                limited = True
            i_rms = math.hypot(i_d, i_q_peak) / math.sqrt(2.0)
            iq_rms = abs(i_q_peak) / math.sqrt(2.0)
        else:
            i_rms = iq_rms = abs(torque) / self.kt
        frames: list[tuple[float, str, dict[str, float]]] = []
        # current/mechanics frames in [tau, tau + dt)
        i2 = []
        while self._frame_k * cfg.current_period_s < tau + dt - 1e-9:
            ft = self._frame_k * cfg.current_period_s
            ripple = 1.0
            if cfg.current_ripple:
                ripple = (1.0 + cfg.current_ripple * math.sin(2 * math.pi * self._frame_k / 7.0)) / math.sqrt(
                    1.0 + cfg.current_ripple**2 / 2)
            iq = math.sqrt(2.0) * iq_rms * ripple * (1.0 if torque >= 0 else -1.0)
            idr = i_d * ripple
            i2.append((iq * iq + idr * idr) / 2.0)
            frames.append((ft, INV_CURRENTS, {"INV_Id": idr, "INV_Iq": iq, "INV_IphRms": i_rms * ripple}))
            if self._voltage_rows is not None:
                frames.append((ft, INV_VOLTAGES, self._voltage_signals(idr, iq, speed)))
            frames.append((ft, INV_MECHANICS, {"INV_Speed": speed, "INV_Torque": torque, "INV_Udc": cfg.udc_v}))
            self._frame_k += 1
        while self._temp_k * cfg.temperature_period_s < tau + dt - 1e-9:
            ft = self._temp_k * cfg.temperature_period_s
            frames.append((ft, INV_STATOR_TEMPS, self._stator_signals()))
            frames.append((ft, INV_AMBIENT_TEMPS, self._ambient_signals(amb)))
            self._temp_k += 1
        frames.sort(key=lambda f: f[0])
        i_eff = math.sqrt(sum(i2) / len(i2)) if i2 else i_rms
        inputs = {c: 0.0 for c in self.model.inputs}
        for role, value in ((Role.SPEED, speed), (Role.TORQUE, torque), (Role.CURRENT, i_eff), (Role.AMBIENT, amb)):
            name = self._input_of[role]
            if name is not None:
                inputs[name] = value
        if tau >= self._next_trace:
            self.trace_t.append(self.t0 + tau)
            self.trace_T.append(self.plant.T.copy())
            self.trace_i.append((abs(torque_d) / self.kt, i_eff, amb))
            self._next_trace += cfg.trace_every_s
        self.plant.step(inputs)
        self.elapsed = tau + dt
        for name, i in self._limit_nodes.items():
            v = float(self.plant.T[i])
            if v > self._true_max[name]:
                self._true_max[name] = v
                self._true_max_t[name] = self.t0 + self.elapsed
        return [(self.t0 + ft, name, sig) for ft, name, sig in frames]

    def _voltage_signals(self, i_d: float, i_q: float, speed_rpm: float) -> dict[str, float]:
        """``INV_Voltages``: the voltage references for these currents (A peak) at this speed, from the
        plant's true winding and magnet temperatures now (V)."""
        pm = self.config.pmsm
        assert pm is not None and self._voltage_rows is not None
        w_row, m_rows = self._voltage_rows
        T = self.plant.T
        u_d, u_q = pm.voltages(np.array(i_d), np.array(i_q), np.array(speed_rpm), np.array(T[w_row]),
                               np.array(float(np.mean(T[m_rows]))), seed=None)
        noise = self._u_rng.normal(0.0, pm.noise_v, 2) if pm.noise_v > 0 else np.zeros(2)
        return {"INV_Ud": float(u_d) + float(noise[0]), "INV_Uq": float(u_q) + float(noise[1])}

    def _reading(self, true_c: float) -> float:
        """One PT100 reading of a true temperature, °C."""
        return float(pt100(true_c, self.rng, self.config.noise_k, self.config.resolution_k))

    def _stator_signals(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for sig, status_sig in _STATUS_OF.items():
            sensor = self.config.sensor_signals.get(sig)
            if sensor is None or sensor not in self.model.sensors:
                out[sig], out[status_sig] = math.nan, int(SensorStatus.NOT_FITTED)
                continue
            status = self.sensor_status.get(sensor, int(SensorStatus.VALID))
            if status == int(SensorStatus.VALID):
                v = self._reading(self.plant.node(self.model.sensors[sensor])) + self.sensor_offset.get(sensor, 0.0)
                out[sig] = min(max(v, -50.0), 359.4)
            else:
                out[sig] = math.nan
            out[status_sig] = status
        return out

    def _ambient_signals(self, amb: float) -> dict[str, float]:
        status = self.sensor_status.get("ambient", int(SensorStatus.VALID))
        v = self._reading(amb) + self.sensor_offset.get("ambient", 0.0) if status == int(SensorStatus.VALID) else math.nan
        return {"INV_T_Ambient": v, "INV_T_Coolant": math.nan, "INV_S_Ambient": status,
                "INV_S_Coolant": int(SensorStatus.NOT_FITTED)}

    # -- reception --------------------------------------------------------------------------------
    def _on_frame(self, frame: DecodedFrame) -> None:
        name = frame.name
        self.summary.frames_received[name] = self.summary.frames_received.get(name, 0) + 1
        now = time.monotonic()
        if name == TE_LIMITS:
            s = frame.signals
            self.current_limit = float(s["TE_CurrentLimit"])
            self.torque_limit = float(s["TE_TorqueLimit"])
            self.last_reason = int(s["TE_DerateReason"])
            self.limits_wall = now
            self.limits_sim = self.sim_time
            self.summary.limits_received += 1
            if self.config.record_estimates and (
                    not self.limit_log or self.limit_log[-1][1:] != (self.current_limit, self.torque_limit, self.last_reason)):
                self.limit_log.append((self.sim_time, self.current_limit, self.torque_limit, self.last_reason))
        elif name == TE_STATUS:
            self.status_count += 1
            if self._status_event is not None:
                self._status_event.set()
        elif name == TE_ESTIMATES and self.config.record_estimates:
            s = frame.signals
            self.estimates.append((self.sim_time, float(frame.timestamp or math.nan), float(s["TE_T_HotSpot"]),
                                   float(s["TE_T_HotSpotUpper"]), float(s["TE_T_Magnet"]), float(s["TE_T_MagnetUpper"])))

    # -- live -------------------------------------------------------------------------------------
    async def run(self, stop: asyncio.Event | None = None, started: asyncio.Event | None = None) -> EmulatorSummary:
        """Run the cycle on the bus (until its end, :meth:`stop`, or ``stop`` is set).

        The emulator owns its python-can bus and drains it after every plant step (and while it
        waits): ``udp_multicast`` loops every sent frame back to the sender, and a reader that took
        one message per event-loop turn would fall behind its own echoes.
        """
        import can

        from ..bus.udp import UndecodableDatagram

        if self.bus_config is None:
            raise ValueError("no bus configured")
        cfg = self.config
        self.bus = bus = create_bus(self.bus_config)
        own = self.codec.frames_sent_by("INV")
        ids = {name: self.codec.frame_id(name)
               for name in (INV_CURRENTS, INV_MECHANICS, INV_STATOR_TEMPS, INV_AMBIENT_TEMPS, INV_VOLTAGES)}

        def drain() -> int:
            n = 0
            while True:
                try:
                    msg = bus.recv(0)
                except UndecodableDatagram as exc:  # one bad datagram is not a dead bus: skipped, counted
                    self.summary.rx_undecodable += 1
                    if self.summary.rx_undecodable == 1:
                        log.warning("emulator: undecodable datagram(s) on the bus skipped (first: %s)", exc)
                    continue
                except Exception as exc:  # a broken bus ends the run
                    raise RuntimeError(f"emulator bus receive failed: {exc}") from exc
                if msg is None:
                    return n
                if msg.arbitration_id in own and not msg.is_extended_id:
                    continue
                frame = self.codec.decode_message(msg)
                if frame is not None:
                    self._on_frame(frame)
                    n += 1

        if started is not None:
            started.set()
        wall0 = time.monotonic()
        t_start = wall0
        sim0 = self.elapsed
        self.summary.sim_start = self.sim_time
        # the service is expected to listen from the start: its ticks are counted from ours at once.
        # Syncing at its first TE_Status instead took the lead at that moment as zero, and a
        # service slow to tick first (busy process) then lagged by hundreds of ticks for the run
        synced = cfg.flow_control
        base_ticks, base_status = 0, self.status_count
        status_at_timeout = self.status_count
        free_until = math.inf  # simulated elapsed time up to which the emulator runs on without a service
        tick = cfg.service_tick_s
        ticks_sent = 0
        max_lead = max(1, int(round(cfg.max_lead_s / tick)))
        step_i = 0
        try:
            while self.elapsed < self.duration - 1e-9 and not self._stop and not (stop is not None and stop.is_set()):
                drain()
                # flow control: stay at most max_lead ticks ahead of the service
                if cfg.flow_control:
                    if not synced and self.elapsed >= free_until and self.status_count == status_at_timeout:
                        # ran on long enough: wait for a service to be there again. Its cyclic
                        # TE_Limits says so (its TE_Status needs ticks, and ticks need our frames)
                        w0, heard = time.monotonic(), self.summary.limits_received
                        while self.summary.limits_received == heard and time.monotonic() - w0 < FREE_WAIT_MAX_S:
                            if drain() == 0:
                                await asyncio.sleep(0.005)
                        self.summary.flow_wait_wall_s += time.monotonic() - w0
                        free_until = math.inf
                        wall0, sim0 = time.monotonic(), self.elapsed
                    if not synced and self.status_count > status_at_timeout:  # TE_Status again after a timeout
                        synced, base_ticks, base_status = True, ticks_sent, self.status_count
                    if synced and (ticks_sent - base_ticks) - (self.status_count - base_status) > max_lead:
                        self.summary.flow_waits += 1
                        w0 = prev = time.monotonic()
                        heard, silent = self.status_count, 0.0
                        while (ticks_sent - base_ticks) - (self.status_count - base_status) > max_lead:
                            if drain() == 0:
                                await asyncio.sleep(0.0005)
                            now = time.monotonic()
                            # the service's silence counts only while the emulator itself runs: a
                            # pause of this whole process (a busy host) gave the service no chance
                            # to answer either, so a longer gap between two polls counts as one poll
                            if self.status_count != heard:
                                heard, silent = self.status_count, 0.0
                            else:
                                silent += min(now - prev, FLOW_POLL_MAX_S)
                            prev = now
                            if silent >= cfg.flow_timeout_s:
                                synced = False  # the service is gone or lost frames: resync later
                                status_at_timeout = self.status_count
                                self.summary.flow_timeouts += 1
                                if cfg.max_free_s is not None:
                                    free_until = self.elapsed + cfg.max_free_s
                                break
                        self.summary.flow_wait_wall_s += time.monotonic() - w0
                        if not synced:
                            wall0, sim0 = time.monotonic(), self.elapsed  # do not burst to catch up
                frames = self.step(time.monotonic())
                for ts, name, signals in frames:
                    if name in self.paused:
                        continue
                    if cfg.speed > 0:  # each frame at its own time, not the step's frames in a burst
                        delay = wall0 + (ts - self.t0 - sim0) / cfg.speed - time.monotonic()
                        if delay > PACE_MIN_SLEEP_S:
                            await asyncio.sleep(delay)
                            drain()
                    if math.floor(ts / tick) != math.floor(self._ts / tick):
                        ticks_sent += 1
                    self._ts = ts
                    data = self.codec.encode(name, signals)
                    try:
                        bus.send(can.Message(timestamp=ts, arbitration_id=ids[name], data=data, is_extended_id=False),
                                 timeout=0.05)
                        self.summary.frames_sent[name] = self.summary.frames_sent.get(name, 0) + 1
                    except Exception as exc:
                        self.summary.send_failures += 1
                        if self.summary.send_failures == 1:
                            log.warning("emulator send failed: %s", exc)
                step_i += 1
                if cfg.speed > 0:
                    target = wall0 + (self.elapsed - sim0) / cfg.speed
                    delay = target - time.monotonic()
                    if delay > 0:
                        await asyncio.sleep(delay)
                    else:
                        await asyncio.sleep(0)
                else:
                    await asyncio.sleep(0)
            t_end = time.monotonic() + 0.05  # the last replies
            while time.monotonic() < t_end:
                if drain() == 0:
                    await asyncio.sleep(0.002)
        finally:
            self.summary.wall_seconds = time.monotonic() - t_start
            try:
                bus.shutdown()
            except Exception:
                pass
            self._finish()
        return self.summary

    def inject(self, arbitration_id: int, data: bytes, *, extended: bool = False, remote: bool = False,
               timestamp: float | None = None) -> None:
        """Put a raw (possibly malformed) frame on the bus (tests)."""
        import can

        self.bus.send(can.Message(timestamp=self._ts if timestamp is None else timestamp, arbitration_id=arbitration_id,
                                  data=data, is_extended_id=extended, is_remote_frame=remote, check=False))

    def _finish(self) -> None:
        s = self.summary
        s.sim_end = self.sim_time
        s.sim_seconds = self.elapsed
        s.true_max_c = {k: float(v) for k, v in self._true_max.items()}
        s.true_max_t = dict(self._true_max_t)
        st = self.codec.stats
        s.rx_lost = st.lost
        s.rx_dropped = {k: int(v) for k, v in st.dropped.items()}

    # -- offline ----------------------------------------------------------------------------------
    def write_log(self, path: str | os.PathLike[str], channel: str = "can0",
                  progress: Callable[[float], object] | None = None) -> EmulatorSummary:
        """Write the inverter frames of the whole (open-loop) run as a CAN log, no bus (format by
        the file's suffix: ``.log`` candump -L, ``.asc``, ``.blf``, ... see :mod:`thermal_edge.bus.logs`);
        ``progress(elapsed_s)`` after every plant step."""
        import can

        self.summary.sim_start = self.sim_time
        with LogRecorder(path, channel=channel, flush_interval_s=60.0) as rec:
            while self.elapsed < self.duration - 1e-9:
                for ts, name, signals in self.step(None):
                    data = self.codec.encode(name, signals)
                    rec.write(can.Message(timestamp=ts, arbitration_id=self.codec.frame_id(name), data=data,
                                          is_extended_id=False, is_rx=True))
                    self.summary.frames_sent[name] = self.summary.frames_sent.get(name, 0) + 1
                if progress is not None:
                    progress(self.elapsed)
        if rec.write_errors:
            raise OSError(f"{path}: {rec.write_errors} frames could not be written (see the log)")
        self._finish()
        return self.summary


def write_log(model_path: str | os.PathLike[str], cycle_path: str | os.PathLike[str], out: str | os.PathLike[str], *,
              params: Mapping[str, float] | None = None, duration_s: float | None = None, noise_k: float = 0.1,
              resolution_k: float = 0.1, seed: int = 0, t0: float | None = None, current_period_s: float = 0.01,
              temperature_period_s: float = 0.1, channel: str = "can0",
              progress: Callable[[float], object] | None = None, pmsm: Pmsm | None = None,
              sensor_signals: Mapping[str, str] | None = None) -> EmulatorSummary:
    """The inverter frames of a simulated open-loop run as a CAN log in the format of ``out``'s
    suffix (``thermal-edge simulate --format can``); ``progress(elapsed_s)`` as it goes; with
    ``pmsm`` ``INV_Voltages`` too; ``sensor_signals``: which model sensor each PT100 signal carries
    (default :data:`DEFAULT_SENSOR_SIGNALS`)."""
    cfg = EmulatorConfig(model_path=Path(model_path), cycle_path=Path(cycle_path), params=dict(params or {}),
                         duration_s=duration_s, pmsm=pmsm,
                         sensor_signals=dict(sensor_signals if sensor_signals is not None else DEFAULT_SENSOR_SIGNALS),
                         noise_k=noise_k, resolution_k=resolution_k, seed=seed, t0=t0 if t0 is not None else 1.7e9,
                         current_period_s=current_period_s, temperature_period_s=temperature_period_s,
                         closed_loop=False, plant_dt_s=max(current_period_s, min(1.0, temperature_period_s)))
    return InverterEmulator(cfg).write_log(out, channel, progress)


# ----------------------------------------------------------------------------------------------
def _parse_params(items: list[str]) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"inverter: --param {item!r}: expected NAME=VALUE")
        out[name.strip()] = float(value)
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m thermal_edge.sim.inverter``: run the emulator on a bus, as its own process."""
    p = argparse.ArgumentParser(prog="python -m thermal_edge.sim.inverter", description=__doc__.split("\n\n")[0])
    p.add_argument("--interface", default="udp_multicast", help="python-can interface (default udp_multicast)")
    p.add_argument("--channel", default=None, help="bus channel (multicast group, virtual bus name, can0)")
    p.add_argument("--port", type=int, default=None, help="udp_multicast port")
    p.add_argument("--model", default="pm10kw", help="machine model: a file or a packaged name (default pm10kw)")
    p.add_argument("--cycle", default="overload", help="drive cycle: a file or a packaged name (default overload)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="plant parameter (repeatable)")
    p.add_argument("--table4", choices=("none", "plus", "minus"), default="none",
                   help="plant parameters = model nominal +/- the paper's Table 4 variations")
    p.add_argument("--aging", action="append", default=[], metavar="NAME=RATE", help="relative change per hour")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds (default: the cycle)")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second (0: flow control only)")
    p.add_argument("--t0", type=float, default=None, help="simulated epoch of the start (default: now)")
    p.add_argument("--current-period", type=float, default=0.01)
    p.add_argument("--temperature-period", type=float, default=0.1)
    p.add_argument("--plant-dt", type=float, default=0.1)
    p.add_argument("--ambient-drift", type=float, default=0.0)
    p.add_argument("--open-loop", action="store_true", help="ignore TE_Limits")
    p.add_argument("--fallback-current", type=float, default=None, help="A rms when TE_Limits is absent")
    p.add_argument("--no-flow-control", action="store_true")
    p.add_argument("--max-lead", type=float, default=10.0, help="simulated s the emulator may run ahead of the service")
    p.add_argument("--flow-timeout", type=float, default=2.0, help="wall s without TE_Status before running on")
    p.add_argument("--max-free", type=float, default=None,
                   help="simulated s to run on without a service before waiting for one again (default: run on)")
    p.add_argument("--limits-timeout", type=float, default=0.3,
                   help="wall s after which TE_Limits counts as absent (inf: only the simulated time-out)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--voltages", action="store_true",
                   help="also send INV_Voltages (the dq voltage references of the simulated machine, sim.pmsm)")
    p.add_argument("--summary", default=None, help="write the summary JSON here")
    p.add_argument("--trace", default=None, help="write the trace (npz) here")
    p.add_argument("--ready-file", default=None, help="touch this file once the bus is open")
    args = p.parse_args(argv)
    try:
        args.model, args.cycle = model_file(args.model), cycle_file(args.cycle)
    except UsageError as exc:
        p.error(str(exc))
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s inverter: %(message)s")
    model = load_model(args.model)
    params = {}
    if args.table4 != "none":
        params.update(table4_parameters(model, 1.0 if args.table4 == "plus" else -1.0))
    params.update(_parse_params(args.param))
    cfg = EmulatorConfig(
        model_path=args.model, cycle_path=args.cycle, params=params, aging=_parse_params(args.aging),
        duration_s=args.duration, speed=args.speed, t0=args.t0, current_period_s=args.current_period,
        temperature_period_s=args.temperature_period, plant_dt_s=args.plant_dt, ambient_drift_k=args.ambient_drift,
        closed_loop=not args.open_loop, fallback_current_a=args.fallback_current, flow_control=not args.no_flow_control,
        max_lead_s=args.max_lead, seed=args.seed, flow_timeout_s=args.flow_timeout, limits_timeout_s=args.limits_timeout,
        max_free_s=args.max_free, pmsm=Pmsm() if args.voltages else None,
        trace_every_s=1.0 if args.trace else math.inf, record_estimates=bool(args.trace),
    )
    bus: dict[str, Any] = {"interface": args.interface}
    if "preserve_timestamps" in interface_keywords(args.interface):  # simulated time on virtual/udp buses
        bus["preserve_timestamps"] = True
    if args.channel is not None:
        bus["channel"] = args.channel
    if args.port is not None:
        bus["port"] = args.port
    emu = InverterEmulator(cfg, bus, model=model)

    async def go() -> EmulatorSummary:
        started = asyncio.Event()
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        import signal as _signal

        for sig in (_signal.SIGTERM, _signal.SIGINT):
            try:
                loop.add_signal_handler(sig, stop.set)
            except (NotImplementedError, RuntimeError):
                pass
        task = loop.create_task(emu.run(stop, started))
        await started.wait()
        if args.ready_file:
            Path(args.ready_file).touch()
        return await task

    summary = asyncio.run(go())
    if args.summary:
        Path(args.summary).write_text(json.dumps(asdict(summary), indent=2))
    if args.trace:
        np.savez_compressed(args.trace, **emu.trace())  # type: ignore[arg-type]  # mypy matches **kwargs to allow_pickle too
    print(json.dumps({"sim_seconds": summary.sim_seconds, "wall_seconds": round(summary.wall_seconds, 2),
                      "true_max_c": summary.true_max_c, "rx_lost": summary.rx_lost}))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
