"""The tick pipeline, free of I/O: frames in, estimates and limits out.

Per tick ``t`` (the frames of ``[t - Δt, t)`` accumulated by :class:`.inputs.InputAccumulator`):

1. the previous sample (its inputs are this interval's) goes to the adapter's history;
2. losses -> LPTN step: the **open-loop prediction** (its error against the readings is the
   prediction error that triggers adaptation and tells a diverged model);
3. the **observer** (Kalman filter) predicts with the same step and updates with the readings:
   the best estimate of every node and its σ;
4. accepted parameters of a finished adaptation go to the model, observer and look-ahead (and
   the open-loop state is re-derived with them); a due decision is requested from the worker;
5. **derating** (:mod:`.derating`) from the upper band, the reaction-time current (a short look-ahead
   over ``derating.reaction_time_s``), the readings of the sensors that bound a limited node from
   below, and the health of the inputs and model; the 30 min look-ahead goes to ``TE_Forecast``
   as advice.

Safety events go to the log with their journald priority (:mod:`.journal`): every change of the
state and of the derate reason (NOTICE; WARNING when a fault forces the safe limit), inputs going
stale and coming back, sensor faults and their end, model faults (ERROR), adaptations. Each event
is logged once when it happens; the journal module's rate limit keeps a flapping input from
flooding the journal.

The same engine runs live (:mod:`.service`) and over a recorded log (:mod:`.replay`); given the
same frames in the same order it produces the same estimates. In frame-clock mode a decision's
result is applied exactly ``apply_delay_ticks`` after it was requested (the caller waits for it
if needed); with the wall clock it is applied at the first tick after it is ready.
"""
from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..bus.codec import DecodedFrame
from ..bus.frames import TIME_TO_LIMIT_NOT_WITHIN_HORIZON_S, DerateReason, TeState
from ..config import EdgeConfig
from ..estimation.observer import Observer
from ..lptn import Model, Stepper, initial_state, load_model
from .adaptation import AdaptationResult, AdaptationWorker
from .derating import DeratingPolicy, Limits, NodeBand
from .inputs import InputAccumulator, TickInputs
from .journal import NOTICE, notice
from .lookahead import Lookahead
from .persistence import PersistedState, cool_down

__all__ = ["ThermalEngine", "TickOutput", "bounding_sensors", "load_service_model"]

log = logging.getLogger(__name__)

TEMP_MAX_SIGNAL = 359.4
STEPPER_CACHE = 128  # operating points (speeds) whose transition matrices are kept
#: ticks of bounding-sensor readings averaged for the floor under a limited node's upper band: the
#: PT100 noise (σ 0.1 K, 0.1 K steps) averaged down, so the reaction-time current (very sensitive
#: near the max) does not jump with each reading; at 0.35 K/s (40 A) the mean lags by 0.7 K
FLOOR_TICKS = 5
CURRENT_MAX_SIGNAL = 3276.75


def load_service_model(config: EdgeConfig) -> Model:
    """The machine model of the configuration, with its offline parameter values applied.

    Raises
    ------
    ConfigError
        A configured parameter unknown to the model file or outside its bounds (checked on the
        model as the file defines it: only the model file can widen a bound).
    """
    model = load_model(config.model.path)
    config.check_parameters(model)
    return model.with_parameters(config.model.parameters) if config.model.parameters else model


def bounding_sensors(model: Model, theta: np.ndarray, sensors: dict[str, int], limits: dict[str, int],
                     max_current_a: float, kt_nm_per_arms: float, current_input: str = "i_rms",
                     rated_speed_rpm: float = 1000.0) -> dict[str, list[str]]:
    """Sensors whose reading is a lower bound of a limited node's temperature.

    A sensor bounds a limited node if, in the model's steady states over a grid of operating points
    (speeds 0, ½, 1 and 2 times ``rated_speed_rpm``; currents ¼, ½ and 1 times the maximum; 25 °C),
    its node is never hotter than the limited node: then a reading at or above the node's warning
    temperature means the limited node is at least that hot, whatever the model's state (the
    end-winding PT100 for the end-winding hot spot; not for the magnet, which is cooler than the
    winding at low speed).

    Parameters
    ----------
    model : Model
    theta : ndarray
        Parameters of the steady states.
    sensors, limits : dict of str to int
        Sensor name -> node row, limit name -> node row.
    max_current_a : float
        Maximum current, A rms.
    kt_nm_per_arms : float
        Torque constant (for a ``torque_nm`` input).

    Returns
    -------
    dict of str to list of str
        Limit name -> the sensors that bound it from below (only limits with at least one).
    """
    from ..lptn import steady_state

    bounds = set(model.boundaries.values())
    ok = {(lim, s): True for lim in limits for s in sensors}
    for speed in (0.0, 0.5 * rated_speed_rpm, rated_speed_rpm, 2.0 * rated_speed_rpm):
        for frac in (0.25, 0.5, 1.0):
            i = frac * max_current_a
            u = {k: (25.0 if k in bounds else 0.0) for k in model.inputs}
            u.update({k: v for k, v in (("speed_rpm", speed), ("torque_nm", kt_nm_per_arms * i), (current_input, i))
                      if k in u})
            try:
                T, _ = steady_state(model, u, theta)
            except Exception:  # no steady state at this point: decide on the others
                continue
            for (lim, s) in ok:
                if T[sensors[s]] > T[limits[lim]] + 1e-6:
                    ok[(lim, s)] = False
    out: dict[str, list[str]] = {}
    for (lim, s), v in ok.items():
        if v:
            out.setdefault(lim, []).append(s)
    return out


@dataclass
class TickOutput:
    """Everything one tick produced (for the bus, the metrics and the tests)."""

    t: float
    state: TeState
    limits: Limits
    initialized: bool
    estimate: np.ndarray
    sigma: np.ndarray
    prediction: np.ndarray
    measured: dict[str, float]
    inputs: dict[str, float]
    pred_error: dict[str, float]
    pred_err_rms: float
    bands: list[NodeBand]
    lookahead_a: float  # 30 min look-ahead current (advice, TE_Forecast)
    time_to_limit_s: float
    horizon_s: float
    adapt_runs: int
    adapt_accepted: int
    adapt_rejected: int
    param_version: int
    forced: list[DerateReason]
    stale: list[str]
    faults: dict[str, str]
    new_results: list[AdaptationResult] = field(default_factory=list)
    compute_s: float = 0.0  # CPU time of the tick's thread, s
    wall_s: float = 0.0  # wall time of the tick, s
    hot_spot: NodeBand | None = None
    magnet: NodeBand | None = None
    reaction_a: float = math.inf  # largest current keeping every upper band below max over the reaction time

    # -- frame contents ---------------------------------------------------------------------------
    def estimates_signals(self) -> dict[str, float]:
        def clip(x: float) -> float:
            return min(x, TEMP_MAX_SIGNAL) if math.isfinite(x) else math.nan

        hs, mg = self.hot_spot, self.magnet
        return {
            "TE_T_HotSpot": clip(hs.estimate_c) if hs and self.initialized else math.nan,
            "TE_T_HotSpotUpper": clip(hs.upper_c) if hs and self.initialized else math.nan,
            "TE_T_Magnet": clip(mg.estimate_c) if mg and self.initialized else math.nan,
            "TE_T_MagnetUpper": clip(mg.upper_c) if mg and self.initialized else math.nan,
        }

    def forecast_signals(self) -> dict[str, float]:
        ttl = self.time_to_limit_s
        ttl_sig = float(TIME_TO_LIMIT_NOT_WITHIN_HORIZON_S) if not math.isfinite(ttl) or ttl >= TIME_TO_LIMIT_NOT_WITHIN_HORIZON_S else max(0.0, ttl)
        la = self.lookahead_a
        la_sig = CURRENT_MAX_SIGNAL if not math.isfinite(la) else min(max(la, 0.0), CURRENT_MAX_SIGNAL)
        return {"TE_TimeToLimit": ttl_sig, "TE_LookaheadCurrent": la_sig, "TE_Horizon": self.horizon_s}

    def status_signals(self) -> dict[str, float]:
        e = self.pred_err_rms
        e_sig = 0.0 if not self.initialized or (isinstance(e, float) and math.isnan(e) and self.state != TeState.FAULT) else (
            min(e, 655.35) if math.isfinite(e) else 655.35)
        return {
            "TE_State": int(self.state),
            "TE_PredErrRms": e_sig,
            "TE_AdaptCount": self.adapt_runs % 65536,
            "TE_ParamVersion": self.param_version % 256,
        }


class ThermalEngine:
    """The service's model, observer, adapter and derating policy, one tick at a time.

    Parameters
    ----------
    config : EdgeConfig
    model : Model, optional
        The machine model with the offline parameters (default: from the configuration).
    restored : PersistedState, optional
        State loaded at start (parameters, decisions, thermal state to cool over the downtime).
    worker_mode : {"thread", "sync"}, optional
        Adapter worker (default: the configuration's).
    """

    def __init__(self, config: EdgeConfig, model: Model | None = None, restored: PersistedState | None = None,
                 worker_mode: str | None = None) -> None:
        self.config = config
        self.model = model if model is not None else load_service_model(config)
        config.check_model(self.model)
        m = self.model
        self.frame_mode = config.clock.mode == "frame"
        self.dt = config.clock.tick_s
        self.offline_theta = m.nominal()
        self.theta = self.offline_theta.copy()
        self.restored = restored
        self.param_version = 0
        self.adapt_runs = self.adapt_accepted = self.adapt_rejected = self.adapt_failures = self.adapt_skipped = 0
        self.decisions: list[dict[str, Any]] = []
        if restored is not None:
            idx = {n: i for i, n in enumerate(m.parameter_names)}
            for k, v in restored.parameters.items():
                self.theta[idx[k]] = v
            self.param_version = restored.param_version
            self.adapt_runs = restored.adapt_runs
            self.decisions = list(restored.decisions)
        self.accumulator = InputAccumulator(config)
        self.kt = float(config.kt(m))  # type: ignore[arg-type]
        self.policy = DeratingPolicy(config.derating, self.kt, self.dt)
        self.sensor_rows = {s: m.node_index(m.sensors[s]) for s in config.sensors}
        self.limit_specs = []
        for lim in m.limits:
            warn, mx = config.limit_band(lim)
            self.limit_specs.append((lim.name, m.node_index(lim.node), warn, mx, config.limit_reason(lim)))
        self.current_input = next((k for k, s in config.inputs.items() if s.reduce in ("dq_rms", "rms")), "i_rms")
        la = config.lookahead
        self.lookahead = Lookahead(m, self.theta, [(n, i, mx) for n, i, _, mx, _ in self.limit_specs], la.horizon_s,
                                   la.steps, self.current_input) if la.enabled else None
        # the reaction-time current: the same look-ahead over derating.reaction_time_s, one tick a step,
        # against each max less the model margin
        dc = config.derating
        self.reaction = Lookahead(m, self.theta, [(n, i, mx - dc.margin_k) for n, i, _, mx, _ in self.limit_specs],
                                  dc.reaction_time_s, max(1, math.ceil(dc.reaction_time_s / self.dt - 1e-9)), self.current_input)
        # the sensors whose readings bound a limited node from below (the band on them is a floor
        # that holds when the model is not trusted)
        rated = float(m.drive.get("rated_speed_rpm", 1000.0)) if getattr(m, "drive", None) else 1000.0
        bound_by = bounding_sensors(m, self.theta, self.sensor_rows, {n: i for n, i, *_ in self.limit_specs},
                                    config.derating.max_current_a, self.kt, self.current_input, rated)
        self.measured_specs = [(s, name, row, warn, mx, reason) for name, row, warn, mx, reason in self.limit_specs
                               for s in bound_by.get(name, [])]
        self.floor_readings: dict[str, deque[float]] = {s: deque(maxlen=FLOOR_TICKS) for s, *_ in self.measured_specs}
        ad = config.adaptation
        self.worker = AdaptationWorker(m, ad.adapter, self.dt, self.theta, self.offline_theta,
                                       worker_mode or ad.worker, ad.bands) if ad.enabled else None
        self.param_bands: dict[str, tuple[float, float]] = {}
        self.identifiable: dict[str, bool] = {}
        # dynamic state
        self.observer: Observer | None = None
        self.x_ol: np.ndarray | None = None
        self.initialized = False
        self.start_t: float | None = None
        self.last_t: float | None = None
        self.prev_sample: tuple[float, dict[str, float], np.ndarray] | None = None  # (t, measured, observer estimate) at last tick
        self.last_inputs: dict[str, float] = dict(restored.inputs) if restored is not None else {}
        self.recent_inputs: deque[tuple[float, dict[str, float]]] = deque(maxlen=1024)
        self.err_window: deque[tuple[float, float, int]] = deque()
        self.err_sum = 0.0
        self.err_n = 0
        self.innovation_count = 0
        self.fault_until = -math.inf
        self.model_faults = 0
        self.next_decision_t: float | None = None
        self.pending: tuple[int, float] | None = None  # (request id, apply at)
        self.restart_info: dict[str, float] = {}
        self.last: TickOutput | None = None
        self.ticks = 0
        self.gaps = 0
        # what was last logged (safety events are logged when they change)
        self._logged_reason: DerateReason | None = None
        self._logged_state: TeState | None = None
        self._logged_stale: frozenset[str] = frozenset()
        self._logged_faults: dict[str, str] = {}

    # ------------------------------------------------------------------------------------------
    def add_frame(self, frame: DecodedFrame, t: float) -> None:
        """Accumulate one accepted frame (clock time ``t``)."""
        if self.start_t is None:
            self.start_t = t
        self.accumulator.add(frame, t)

    def awaiting(self, t: float) -> int | None:
        """In frame-clock mode: the decision that must be applied at the tick ``t`` and is not done yet."""
        if self.worker is None or self.pending is None or not self.frame_mode:
            return None
        rid, apply_at = self.pending
        if t + 1e-9 >= apply_at and self.worker.result(rid) is None:
            return rid
        return None

    # ------------------------------------------------------------------------------------------
    def _init_state(self, t: float, ti: TickInputs) -> None:
        m, cfg = self.model, self.config
        inputs = ti.inputs
        measured = ti.measured
        obs_cfg = cfg.observer
        T0 = None
        P0 = None
        rs = self.restored
        if rs is not None and rs.T:
            downtime = t - rs.saved_at
            self.restart_info = {"downtime_s": downtime}
            last = {**inputs, **{k: v for k, v in rs.inputs.items() if math.isfinite(v)}}
            if 0 <= downtime <= cfg.state.max_downtime_s:
                try:
                    T0, Phi = cool_down(m, self.theta, np.array(rs.T), downtime, last)
                    P = np.array(rs.P) if rs.P else np.diag(np.square(np.array(rs.sigma))) if rs.sigma else np.eye(len(T0)) * obs_cfg.restart_p0_k**2
                    P = P + self._run_on_covariance(np.array(rs.T), rs.inputs, min(downtime, cfg.state.save_interval_s))
                    grow = min(obs_cfg.q_k**2 * downtime / self.dt, obs_cfg.restart_p0_k**2)
                    P0 = Phi @ P @ Phi.T + np.eye(len(T0)) * grow
                    log.info("restored thermal state from %.0f s ago (cooled over the downtime at %.1f degC ambient)",
                             downtime, float(np.mean(m_bound(m, last))))
                except Exception as exc:
                    log.warning("cannot cool the saved state over the downtime (%s): starting from the readings", exc)
                    T0 = None
            elif downtime < 0:
                log.warning("saved state is %.0f s in the future (clock changed?): using it as it is", -downtime)
                T0 = np.array(rs.T)
            else:
                log.info("saved state is %.0f s old (more than %.0f s): starting from the readings", downtime,
                         cfg.state.max_downtime_s)
        if T0 is None:
            T0 = initial_state(m, inputs, measured, self.theta)
        self.observer = Observer(m, T0, self.theta, self.dt, obs_cfg.q_k, obs_cfg.r_k, obs_cfg.p0_k)
        self.observer.stepper.cache_size = STEPPER_CACHE
        if P0 is not None:
            self.observer.P = 0.5 * (P0 + P0.T)
        self.observer.update(measured)  # corrected by the first measurements
        self.x_ol = self.observer.T.copy()
        self.initialized = True
        self.innovation_count = 0
        self.restored = None  # used once

    def _run_on_covariance(self, T: np.ndarray, last: dict[str, float], run_on_s: float) -> np.ndarray:
        """Uncertainty of the saved state about what happened after it was saved: the machine may have
        run on at its last load for up to one save interval before it stopped. Rank one, along the
        difference between running on and standing still, so that the first readings of the measured
        nodes correct the unmeasured ones consistently (they were all heated by the same losses)."""
        m = self.model
        n = len(m.nodes)
        if run_on_s <= 0 or not all(math.isfinite(last.get(k, math.nan)) for k in m.inputs):
            return np.zeros((n, n))
        try:
            run, _ = Stepper(m, self.theta, run_on_s).step(T, {k: float(last[k]) for k in m.inputs})
            stop, _ = cool_down(m, self.theta, T, run_on_s, last)
        except Exception:
            return np.zeros((n, n))
        v = run - stop
        return np.outer(v, v) if np.all(np.isfinite(v)) else np.zeros((n, n))

    def _reinit_after_fault(self, ti: TickInputs) -> None:
        m, obs_cfg = self.model, self.config.observer
        ok = {k: v for k, v in ti.measured.items() if math.isfinite(v)}
        try:
            T0 = initial_state(m, ti.inputs, ok, self.theta)
        except Exception:
            T0 = np.full(len(m.nodes), float(np.nanmean(list(ok.values()))) if ok else 25.0)
        if not np.all(np.isfinite(T0)):
            T0 = np.full(len(m.nodes), 25.0)
        self.observer = Observer(m, T0, self.theta, self.dt, obs_cfg.q_k, obs_cfg.r_k, obs_cfg.p0_k)
        self.observer.stepper.cache_size = STEPPER_CACHE
        self.observer.update(ok)
        self.x_ol = self.observer.T.copy()
        self.innovation_count = 0
        self.err_window.clear()
        self.err_sum, self.err_n = 0.0, 0

    # ------------------------------------------------------------------------------------------
    def bridge_gap(self, t_to: float) -> None:
        """No frames for a long time (more than ``clock.max_catchup_s``): cool the state over the
        gap at standstill, forget the adapter's history, and continue at ``t_to``."""
        self.gaps += 1
        self.accumulator.reset()
        if self.initialized and self.observer is not None and self.last_t is not None:
            gap = t_to - self.last_t
            try:
                T1, Phi = cool_down(self.model, self.theta, self.observer.T, gap, self.last_inputs)
                grow = min(self.config.observer.q_k**2 * gap / self.dt, self.config.observer.restart_p0_k**2)
                self.observer.T = T1
                self.observer.P = Phi @ self.observer.P @ Phi.T + np.eye(len(T1)) * grow
                self.x_ol = T1.copy()
            except Exception as exc:
                log.warning("cannot bridge a %.0f s gap: %s", gap, exc)
            self.prev_sample = None
            if self.worker is not None:
                self.worker.reset(self.theta)
            self.next_decision_t = None
        self.last_t = t_to
        log.warning("no frames for %.0f s: state cooled over the gap, adaptation history restarted", t_to)

    # ------------------------------------------------------------------------------------------
    def tick(self, t: float) -> TickOutput:
        """Run the tick ending at ``t``; never raises for bad data (a failure forces the safe limit)."""
        # CPU time of this thread: what the tick costs, not how long the host or the adapter's thread
        # kept it from running (that is the wall time, reported beside it)
        c0, w0 = time.thread_time(), time.perf_counter()
        try:
            out = self._tick(t)
        except Exception as exc:
            log.exception("tick at %.3f failed", t)
            self.model_faults += 1
            self.fault_until = t + self.config.derating.faults.hold_s
            self.initialized = False
            self.observer = None
            out = self._output(t, None, [DerateReason.MODEL_FAULT], [], {}, TeState.FAULT, error=str(exc))
        out.compute_s = time.thread_time() - c0
        out.wall_s = time.perf_counter() - w0
        self.last = out
        self.last_t = t
        self.ticks += 1
        return out

    def _tick(self, t: float) -> TickOutput:
        cfg = self.config
        ti = self.accumulator.take(t)
        forced: list[DerateReason] = []
        if ti.stale:
            forced.append(DerateReason.STALE_INPUT)
        if ti.faults:
            forced.append(DerateReason.SENSOR_FAULT)
        for k, v in ti.inputs.items():
            if math.isfinite(v):
                self.last_inputs[k] = v
        if not self.initialized:
            have_inputs = ti.complete
            have_sensors = any(math.isfinite(v) for v in ti.measured.values())
            if have_inputs and have_sensors and t >= self.fault_until:
                self._init_state(t, ti)
                self.prev_sample = (t, dict(ti.measured), self.observer.T.copy())  # type: ignore[union-attr]
            else:
                grace = max(cfg.timeouts.values(), default=1.0) + self.dt
                waited = t - (self.start_t if self.start_t is not None else t)
                if t < self.fault_until:
                    reasons = [DerateReason.MODEL_FAULT]
                elif self.start_t is None or waited > grace:  # still nothing usable: say why
                    reasons = forced or [DerateReason.STALE_INPUT]
                else:
                    reasons = [DerateReason.STARTING]
                return self._output(t, ti, reasons, ti.stale, ti.faults, TeState.STARTING)
            return self._finish(t, ti, forced, new_results=[])

        obs = self.observer
        assert obs is not None and self.x_ol is not None
        u = {k: (v if math.isfinite(v) else self.last_inputs.get(k, math.nan)) for k, v in ti.inputs.items()}
        # 1. the previous sample (inputs of this interval) to the adapter
        if self.prev_sample is not None:
            t_prev, y_prev, x_prev = self.prev_sample
            self.recent_inputs.append((t_prev, u))
            if self.worker is not None:
                self.worker.record(t_prev, u, y_prev, x_prev)
                if self.next_decision_t is None:
                    self.next_decision_t = t_prev + cfg.adaptation.adapter.period_s
        # 2. open-loop prediction, 3. observer
        self.x_ol, _ = obs.stepper.step(self.x_ol, u)
        obs.predict(u)
        prior = obs.T.copy()
        y = ti.measured
        innov = [abs(y[s] - prior[r]) for s, r in self.sensor_rows.items() if math.isfinite(y.get(s, math.nan))]
        obs.update(y)
        # 4. adaptation results and requests
        new_results = self._adaptation(t)
        # prediction error of the open loop
        pred_error: dict[str, float] = {}
        for s, r in self.sensor_rows.items():
            v = y.get(s, math.nan)
            if math.isfinite(v):
                e = float(self.x_ol[r] - v)
                pred_error[s] = e
                self.err_window.append((t, e * e, 1))
                self.err_sum += e * e
                self.err_n += 1
        horizon = cfg.adaptation.adapter.period_s
        while self.err_window and self.err_window[0][0] <= t - horizon:
            _, e2, n = self.err_window.popleft()
            self.err_sum -= e2
            self.err_n -= n
        # model health
        fc = cfg.derating.faults
        finite = bool(np.all(np.isfinite(obs.T)) and np.all(np.isfinite(obs.P)) and np.all(np.isfinite(self.x_ol)))
        if innov and max(innov) > fc.innovation_k:
            self.innovation_count += 1
        else:
            self.innovation_count = 0
        diverged = (not finite or self.innovation_count >= fc.innovation_ticks
                    or any(abs(e) > fc.prediction_error_k for e in pred_error.values()))
        if diverged:
            self.model_faults += 1
            why = ("non-finite state" if not finite else "innovation above %.0f K for %d ticks" % (fc.innovation_k, fc.innovation_ticks)
                   if self.innovation_count >= fc.innovation_ticks else "open-loop prediction error above %.0f K" % fc.prediction_error_k)
            log.error("model fault at t=%.0f: %s; safe limit for %.0f s, state re-initialised from the readings", t, why, fc.hold_s)
            self.fault_until = t + fc.hold_s
            self._reinit_after_fault(ti)
        if t < self.fault_until:
            forced.insert(0, DerateReason.MODEL_FAULT)
        self.prev_sample = (t, dict(y), obs.T.copy())  # the adapter judges from the observer's state
        return self._finish(t, ti, forced, new_results, pred_error)

    def _adaptation(self, t: float) -> list[AdaptationResult]:
        w = self.worker
        if w is None:
            return []
        applied: list[AdaptationResult] = []
        if self.pending is not None:
            rid, apply_at = self.pending
            res = w.result(rid)
            if res is not None and (not self.frame_mode or t + 1e-9 >= apply_at):
                self.pending = None
                w.forget(rid)
                w.poll()
                self._apply(res)
                applied.append(res)
        if self.pending is None and self.next_decision_t is not None and self.prev_sample is not None:
            t_rec = self.recent_inputs[-1][0] if self.recent_inputs else None
            if t_rec is not None and t_rec + 1e-9 >= self.next_decision_t:
                rid = w.request(t_rec)
                self.pending = (rid, t + self.config.adaptation.apply_delay_ticks * self.dt)
                self.next_decision_t = t_rec + self.config.adaptation.adapter.period_s
        return applied

    def _apply(self, res: AdaptationResult) -> None:
        if res.error is not None or res.decision is None:
            if res.error != "no history yet":
                self.adapt_failures += 1
                log.warning("adaptation at t=%.0f failed: %s", res.t, res.error)
            return
        d = res.decision
        rec = _json_safe(d.as_dict())
        rec["wall_s"] = res.wall_s
        self.decisions.append(rec)
        limit = self.config.state.max_decisions
        if len(self.decisions) > limit:
            del self.decisions[: len(self.decisions) - limit]
        if not d.triggered:
            return
        if d.evaluations == 0 and not d.accepted:  # triggered, but the adapter did not optimise (too little history, ...)
            self.adapt_skipped += 1
            log.debug("adaptation at t=%.0f skipped: %s", d.t, d.reason)
            return
        self.adapt_runs += 1
        if not d.accepted:
            self.adapt_rejected += 1
            log.info("adaptation at t=%.0f rolled back (%s)", d.t, d.reason)
            return
        self.adapt_accepted += 1
        self.param_version += 1
        self.theta = np.array(res.theta, dtype=float)
        if res.bands:
            self.param_bands.update(res.bands)
            self.identifiable.update(res.identifiable)
        assert self.observer is not None
        self.observer.set_parameters(self.theta)
        if self.lookahead is not None:
            self.lookahead.set_parameters(self.theta)
        self.reaction.set_parameters(self.theta)
        if res.state is not None and res.state_t is not None:
            x = res.state.copy()
            for ts, u in self.recent_inputs:
                if ts + 1e-9 >= res.state_t:
                    x, _ = self.observer.stepper.step(x, u)
            if np.all(np.isfinite(x)):
                self.x_ol = x
        log.info("adaptation at t=%.0f accepted (version %d): %s", d.t, self.param_version,
                 ", ".join(f"{k}={v:.4g}" for k, v in d.params.items()))

    # ------------------------------------------------------------------------------------------
    def _finish(self, t: float, ti: TickInputs, forced: list[DerateReason], new_results: list[AdaptationResult],
                pred_error: dict[str, float] | None = None) -> TickOutput:
        state = TeState.NOMINAL
        if DerateReason.MODEL_FAULT in forced:
            state = TeState.FAULT
        elif forced:
            state = TeState.DEGRADED
        elif self.worker is not None and self.pending is not None:
            state = TeState.ADAPTING
        return self._output(t, ti, forced, ti.stale, ti.faults, state, new_results=new_results, pred_error=pred_error)

    def _output(self, t: float, ti: TickInputs | None, forced: list[DerateReason], stale: list[str],
                faults: dict[str, str], state: TeState, new_results: list[AdaptationResult] | None = None,
                error: str | None = None, pred_error: dict[str, float] | None = None) -> TickOutput:
        """The tick's output. ``pred_error`` is the open-loop prediction error the tick measured
        (before a model fault re-initialised the state); without it, the error of the state now."""
        n = len(self.model.nodes)
        la_a, ttl, react_a = math.inf, math.inf, math.inf
        react_reason = DerateReason.NONE
        measured = dict(ti.measured) if ti is not None else {}
        floor = [NodeBand(name, measured[s], measured[s], warn, mx, reason) for s, name, _, warn, mx, reason in self.measured_specs
                 if math.isfinite(measured.get(s, math.nan))]
        if self.initialized and self.observer is not None:
            est = self.observer.T.copy()
            sigma = self.observer.std()
            pred = self.x_ol.copy() if self.x_ol is not None else np.full(n, math.nan)
            upper = est + self.config.derating.band_z * sigma
            # a limited node is at least as hot as a sensor that bounds it from below (its readings
            # averaged over FLOOR_TICKS): an estimate the readings have outrun (a model that runs
            # cold) does not hide that
            for s, _, row, *_ in self.measured_specs:
                v = measured.get(s, math.nan)
                hist = self.floor_readings[s]
                if math.isfinite(v):
                    hist.append(v)
                if hist:
                    upper[row] = max(upper[row], sum(hist) / len(hist))
            bands = [NodeBand(name, float(est[i]), float(upper[i]), warn, mx, reason)
                     for name, i, warn, mx, reason in self.limit_specs]
            u = {k: (v if math.isfinite(v) else self.last_inputs.get(k, 0.0)) for k, v in (ti.inputs if ti else self.last_inputs).items()}
            try:
                rr = self.reaction.compute(upper, u)
                react_a, react_reason = rr.current_a, self.limit_specs[rr.binding][4]
            except Exception as exc:
                log.error("reaction-time look-ahead failed: %s", exc)
                react_a = math.nan  # the policy treats it as a model fault
            if self.lookahead is not None and ti is not None:
                try:
                    r = self.lookahead.compute(upper, u)
                    la_a, ttl = r.current_a, r.time_to_limit_s
                except Exception as exc:
                    log.warning("look-ahead failed: %s", exc)
                    la_a = math.nan
            limits = self.policy.update(bands, (react_a, react_reason), forced, floor)
        else:
            est = np.full(n, math.nan)
            sigma = np.full(n, math.nan)
            pred = np.full(n, math.nan)
            bands = []
            limits = self.policy.update([], None, forced or [DerateReason.STARTING], floor)
        self._log_events(t, state, limits, stale, faults)
        inputs = dict(ti.inputs) if ti is not None else {}
        if pred_error is None:
            pred_error = {}
            if self.initialized and self.x_ol is not None:
                for s, r in self.sensor_rows.items():
                    v = measured.get(s, math.nan)
                    if math.isfinite(v):
                        pred_error[s] = float(pred[r] - v)
        rms = math.sqrt(self.err_sum / self.err_n) if self.err_n > 0 and self.err_sum >= 0 else math.nan
        by_name = {b.name: b for b in bands}
        tr = self.config.transmit
        return TickOutput(
            t=t, state=state, limits=limits, initialized=self.initialized and self.observer is not None,
            estimate=est, sigma=sigma, prediction=pred, measured=measured, inputs=inputs, pred_error=pred_error,
            pred_err_rms=rms, bands=bands, lookahead_a=la_a, time_to_limit_s=ttl,
            horizon_s=self.config.lookahead.horizon_s, adapt_runs=self.adapt_runs, adapt_accepted=self.adapt_accepted,
            adapt_rejected=self.adapt_rejected, param_version=self.param_version, forced=list(forced),
            stale=list(stale), faults=dict(faults), new_results=list(new_results or []),
            hot_spot=by_name.get(tr.hot_spot_limit), magnet=by_name.get(tr.magnet_limit), reaction_a=react_a,
        )

    def _log_events(self, t: float, state: TeState, limits: Limits, stale: list[str], faults: dict[str, str]) -> None:
        """Log the safety events of this tick: changes of stale inputs, sensor faults, state and reason."""
        now_stale = frozenset(stale)
        if now_stale - self._logged_stale:
            log.warning("input(s) stale: %s (no valid frame within the timeout); safe limit",
                        ", ".join(sorted(now_stale - self._logged_stale)))
        if self._logged_stale - now_stale:
            notice(log, "input(s) back: %s", ", ".join(sorted(self._logged_stale - now_stale)))
        self._logged_stale = now_stale
        new = {k: v for k, v in faults.items() if self._logged_faults.get(k) != v}
        if new:
            log.warning("sensor fault: %s; safe limit", ", ".join(f"{k} ({v})" for k, v in sorted(new.items())))
        gone = sorted(set(self._logged_faults) - set(faults))
        if gone:
            notice(log, "sensor fault cleared: %s", ", ".join(gone))
        self._logged_faults = dict(faults)
        if state != self._logged_state:
            level = logging.WARNING if state in (TeState.DEGRADED, TeState.FAULT) else (
                logging.INFO if state == TeState.ADAPTING or self._logged_state == TeState.ADAPTING else NOTICE)
            log.log(level, "state %s -> %s", self._logged_state.name.lower() if self._logged_state is not None else "-",
                    state.name.lower())
            self._logged_state = state
        if limits.reason != self._logged_reason:
            r = limits.reason
            level = (logging.WARNING if r in (DerateReason.MODEL_FAULT, DerateReason.STALE_INPUT, DerateReason.SENSOR_FAULT)
                     else logging.INFO if r == DerateReason.STARTING else NOTICE)
            log.log(level, "derate reason %s -> %s: current limit %.1f A, torque limit %.1f Nm",
                    self._logged_reason.name.lower() if self._logged_reason is not None else "-", r.name.lower(),
                    limits.current_a, limits.torque_nm)
            self._logged_reason = r

    def placeholder(self, t: float) -> TickOutput:
        """An output for before the first tick (starting, safe limit, no estimates)."""
        n = len(self.model.nodes)
        nan = np.full(n, math.nan)
        return TickOutput(
            t=t, state=TeState.STARTING, limits=self.policy.safe(DerateReason.STARTING), initialized=False, estimate=nan,
            sigma=nan, prediction=nan, measured={}, inputs={}, pred_error={}, pred_err_rms=math.nan, bands=[],
            lookahead_a=math.inf, time_to_limit_s=math.inf, horizon_s=self.config.lookahead.horizon_s,
            adapt_runs=self.adapt_runs, adapt_accepted=self.adapt_accepted, adapt_rejected=self.adapt_rejected,
            param_version=self.param_version, forced=[DerateReason.STARTING], stale=[], faults={},
        )

    # ------------------------------------------------------------------------------------------
    def adaptable_values(self) -> dict[str, float]:
        names = self.worker.params if self.worker is not None else self.model.adaptable
        idx = self.model.parameter_index(names)
        return {n: float(self.theta[i]) for n, i in zip(names, idx)}

    def persisted(self, t: float) -> PersistedState:
        """What to save now (parameters, decisions and, once running, the thermal state)."""
        m = self.model
        params = {n: float(v) for n, v, v0 in zip(m.parameter_names, self.theta, self.offline_theta) if v != v0}
        st = PersistedState(model=m.name, saved_at=float(t), parameters=params, param_version=self.param_version,
                            adapt_runs=self.adapt_runs, decisions=list(self.decisions), saved_wall=time.time(),
                            inputs={k: float(v) for k, v in self.last_inputs.items() if math.isfinite(v)})
        obs = self.observer
        if self.initialized and obs is not None and np.all(np.isfinite(obs.T)) and np.all(np.isfinite(obs.P)):
            st.nodes = list(m.nodes)
            st.T = [float(x) for x in obs.T]
            st.sigma = [float(x) for x in obs.std()]
            st.P = [[float(x) for x in row] for row in obs.P]
            if self.x_ol is not None and np.all(np.isfinite(self.x_ol)):
                st.T_pred = [float(x) for x in self.x_ol]
        elif self.restored is not None and self.restored.T:  # not yet running: keep what was loaded
            rs = self.restored
            st.nodes, st.T, st.sigma, st.P, st.T_pred = rs.nodes, rs.T, rs.sigma, rs.P, rs.T_pred
            st.saved_at = rs.saved_at
        return st

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()


def _json_safe(x: Any) -> Any:
    """Non-finite floats -> None, numpy scalars -> Python, recursively (for the JSON state file)."""
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x


def m_bound(model: Model, inputs: dict[str, float]) -> list[float]:
    return [float(inputs.get(c, math.nan)) for c in model.boundaries.values()]
