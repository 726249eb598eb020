"""The tick pipeline, free of I/O: frames in, estimates and limits out.

Per tick ``t`` (the frames of ``[t - Δt, t)`` accumulated by :class:`.inputs.InputAccumulator`):

1. the previous sample (its inputs are this interval's) goes to the adapter's history
   (:class:`.adaptation.Adaptation`);
2. losses -> LPTN step: the **open-loop prediction** and 3. the **observer** (Kalman filter),
   predicted with the same step and corrected by the readings (:class:`.estimate.StateEstimate`);
4. accepted parameters of a finished adaptation go to the estimate, the look-ahead and the
   reaction-time current (the open-loop state re-derived once, with them); a due decision is
   requested from the worker;
5. the health of the inputs and the model (:mod:`.health`): the reasons that force the safe limit
   (a reading that sits still while the open-loop step heats its node is stuck: a sensor fault);
6. **derating** (:mod:`.derating`) from the upper band, the reaction-time current (a short look-ahead
   over ``derating.reaction_time_s``), the readings of the sensors that bound a limited node from
   below, and the forced reasons; the 30 min look-ahead goes to ``TE_Forecast`` as advice;
7. the output (:class:`.outputs.TickOutput`, the frames' contents) and the safety events in the log
   (:mod:`.events`).

The same engine runs live (:mod:`.service`) and over a recorded log (:mod:`.replay`); given the
same frames in the same order it produces the same estimates. In frame-clock mode a decision's
result is applied exactly ``apply_delay_ticks`` after it was requested (the caller waits for it
if needed); with the wall clock it is applied at the first tick after it is ready.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence

import numpy as np

from ..bus.codec import DecodedFrame
from ..bus.frames import DerateReason, TeState
from ..config import EdgeConfig
from ..estimation.fusion import FluxObserver
from ..estimation.observer import Observer
from ..lptn import Model, Role, load_model
from .adaptation import Adaptation, AdaptationResult
from .clock import FrameClockStats
from .current_torque import CurrentTorqueCheck
from .derating import DeratingPolicy, LimitSpec, MeasuredFloor, NodeBand, bounding_sensors
from .estimate import StateEstimate
from .events import SafetyEvents
from .flux_input import FluxInput, FluxTick, load_flux_model
from .health import CommissionedCheck, ModelHealth, StuckSensors, input_reasons
from .inputs import InputAccumulator, TickInputs
from .journal import notice
from .lookahead import Lookahead
from .outputs import TickOutput
from .persistence import PersistedState

__all__ = ["ThermalEngine", "TickOutput", "load_service_model"]

log = logging.getLogger(__name__)


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


class ThermalEngine:
    """The service's estimate, adaptation, health and derating, one tick at a time.

    Parameters
    ----------
    config : EdgeConfig
    model : Model, optional
        The machine model with the offline parameters (default: from the configuration).
    restored : PersistedState, optional
        State loaded at start (parameters, decisions, thermal state to cool over the downtime).
    worker_mode : {"thread", "sync"}, optional
        Adapter worker (default: the configuration's).

    The parts, each with its own job and a read-only public view: :attr:`adaptation` (parameters,
    decisions), :attr:`estimate` (observer and open-loop prediction), :attr:`health` (model
    faults), :attr:`policy` (derating), :attr:`accumulator` (inputs of the tick).
    """

    def __init__(self, config: EdgeConfig, model: Model | None = None, restored: PersistedState | None = None,
                 worker_mode: str | None = None) -> None:
        self.config = config
        self.model = model if model is not None else load_service_model(config)
        config.check_model(self.model)
        m = self.model
        self.frame_mode = config.clock.mode == "frame"
        self.dt = config.clock.tick_s
        self.adaptation = Adaptation(m, config.adaptation, self.dt, self.frame_mode, config.state.max_decisions,
                                     restored, worker_mode)
        theta = self.adaptation.theta
        self.accumulator = InputAccumulator(config, m.input_roles)
        kt = config.kt(m)
        assert kt is not None  # check_model refuses a model without one
        self.kt = float(kt)
        self.policy = DeratingPolicy(config.derating, self.kt, self.dt, config.transmit.bus_silence_s)
        self.sensor_rows = {s: m.node_index(m.sensors[s]) for s in config.sensors}
        self.limited_nodes = [LimitSpec(lim.name, m.node_index(lim.node), *config.limit_band(lim), config.limit_reason(lim))
                              for lim in m.limits]
        la, dc = config.lookahead, config.derating
        self.lookahead = Lookahead(m, theta, [(n.name, n.row, n.max_c) for n in self.limited_nodes], la.horizon_s,
                                   la.steps) if la.enabled else None
        # the reaction-time current: the same look-ahead over derating.reaction_time_s, one tick a step,
        # against each max less the model margin
        self.reaction = Lookahead(m, theta, [(n.name, n.row, n.max_c - dc.margin_k) for n in self.limited_nodes],
                                  dc.reaction_time_s, max(1, math.ceil(dc.reaction_time_s / self.dt - 1e-9)))
        # the sensors whose readings bound a limited node from below (the band on them is a floor
        # that holds when the model is not trusted)
        rated = float(m.drive.get("rated_speed_rpm", 1000.0)) if getattr(m, "drive", None) else 1000.0
        bound_by = bounding_sensors(m, theta, self.sensor_rows, {n.name: n.row for n in self.limited_nodes},
                                    dc.max_current_a, self.kt, rated)
        self.floor = MeasuredFloor(self.limited_nodes, bound_by)
        self.estimate = StateEstimate(m, self.dt, config.observer, FluxObserver if config.flux.enabled else Observer)
        #: the optional voltage input (None without ``flux.calibration``: the engine as without voltages)
        self.flux: FluxInput | None = None
        if config.flux.enabled:
            speed = m.find_input(Role.SPEED)
            if speed is None:
                raise config.error("flux.calibration", f"model {m.name} has no speed input: the flux estimate needs it")
            self.flux = FluxInput(config, m, load_flux_model(config), speed)
        self.health = ModelHealth(dc.faults, config.adaptation.adapter.period_s)
        self.stuck = StuckSensors(dc.faults, config.sensors)
        self.commissioned = CommissionedCheck(dc.faults)
        self._floored: set[str] = set()  # limited nodes whose band the commissioned floor sets
        #: the current against the torque (None when the model reads either not)
        self.current_check = CurrentTorqueCheck.of(m, dc, self.kt)
        self.events = SafetyEvents()
        self._restored = restored  # used once, at the start of the state
        self._restart_info: dict[str, float] = {}
        self._start_t: float | None = None
        self._last_t: float | None = None
        # (t, measured, observer estimate) at the last tick
        self._prev_sample: tuple[float, dict[str, float], np.ndarray] | None = None
        self._last_inputs: dict[str, float] = dict(restored.inputs) if restored is not None else {}
        self._last: TickOutput | None = None
        self._ticks = 0
        self._gaps = 0
        #: the frame clock's counters (:class:`.clock.FrameClockStats`; set by whoever runs the frame
        #: clock, for the metrics; None with the wall clock)
        self.frame_clock: FrameClockStats | None = None

    # -- read-only views ---------------------------------------------------------------------------
    @property
    def last(self) -> TickOutput | None:
        """The last tick's output (None before the first tick); replaced whole each tick."""
        return self._last

    @property
    def ticks(self) -> int:
        """Ticks run."""
        return self._ticks

    @property
    def gaps(self) -> int:
        """Gaps in the frame clock bridged by cooling the state."""
        return self._gaps

    @property
    def restart_info(self) -> dict[str, float]:
        """How the state was restored at the start (``downtime_s``), empty if not from a saved state."""
        return dict(self._restart_info)

    @property
    def model_faults(self) -> int:
        """Times the model was found diverged or a tick failed."""
        return self.health.faults

    @property
    def adapt_runs(self) -> int:
        """Adaptations run."""
        return self.adaptation.counts.runs

    @property
    def adapt_accepted(self) -> int:
        """Adaptations accepted."""
        return self.adaptation.counts.accepted

    # -- frames -------------------------------------------------------------------------------------
    def add_frame(self, frame: DecodedFrame, t: float, behind_s: float = 0.0) -> None:
        """Accumulate one accepted frame (clock time ``t``; its own time ``behind_s`` s before it,
        :meth:`.clock.Clock.behind`)."""
        if self._start_t is None:
            self._start_t = t
        self.accumulator.add(frame, t)
        if self.flux is not None:
            self.flux.add(frame, t, behind_s)

    def ticks_for(self, boundaries: Sequence[float]) -> Sequence[float]:
        """Frame clock: the ticks to run for the boundaries a frame's timestamp crossed (oldest
        first; :class:`.clock.Boundaries`, constant in memory however many). More than
        ``clock.max_catchup_s`` of them is a gap in the frames: it is bridged (:meth:`bridge_gap`)
        and only the last boundary is ticked. The caller runs the ticks, then adds the frame."""
        if len(boundaries) * self.dt > self.config.clock.max_catchup_s:
            self.bridge_gap(boundaries[-1] - self.dt)
            return boundaries[-1:]
        return boundaries

    def awaiting(self, t: float) -> int | None:
        """In frame-clock mode: the decision that must be applied at the tick ``t`` and is not done yet."""
        return self.adaptation.awaiting(t)

    def bridge_gap(self, t_to: float) -> None:
        """No frames for a long time (more than ``clock.max_catchup_s``): cool the state over the
        gap at standstill, forget the adapter's history, and continue at ``t_to``."""
        self._gaps += 1
        self.accumulator.reset()
        if self.flux is not None:
            self.flux.reset()
        self.stuck.restart()
        gap = t_to - self._last_t if self._last_t is not None else math.nan
        if self.estimate.initialized and self._last_t is not None:
            try:
                self.estimate.bridge(gap, self.adaptation.theta, self._last_inputs)
            except Exception as exc:
                log.warning("cannot bridge a %.0f s gap: %s", gap, exc)
            self._prev_sample = None
            self.adaptation.restart()
        self._last_t = t_to
        log.warning("no frames for %.0f s (frame clock to %.3f): state cooled over the gap, adaptation history restarted",
                    gap, t_to)

    # -- the tick -----------------------------------------------------------------------------------
    def tick(self, t: float) -> TickOutput:
        """Run the tick ending at ``t``; never raises for bad data (a failure forces the safe limit)."""
        # CPU time of this thread: what the tick costs, not how long the host or the adapter's thread
        # kept it from running (that is the wall time, reported beside it)
        c0, w0 = time.thread_time(), time.perf_counter()
        try:
            out = self._tick(t)
        except Exception:
            log.exception("tick at %.3f failed", t)
            self.health.fault(t)
            self.estimate.drop()
            out = self._output(t, None, [DerateReason.MODEL_FAULT], TeState.FAULT)
        out.compute_s = time.thread_time() - c0
        out.wall_s = time.perf_counter() - w0
        self._last = out
        self._last_t = t
        self._ticks += 1
        return out

    def _tick(self, t: float) -> TickOutput:
        cfg = self.config
        ti = self.accumulator.take(t)
        readings = dict(ti.measured)  # as received (the stuck check judges them and their mean)
        means = self.stuck.smooth(t, readings)  # a stuck sensor is released when its mean moves
        self._withhold_stuck(ti, self.stuck.release(readings, means))
        forced = input_reasons(ti)
        for k, v in ti.inputs.items():
            if math.isfinite(v):
                self._last_inputs[k] = v
        est = self.estimate
        if not est.initialized:
            have_sensors = any(math.isfinite(v) for v in ti.measured.values())
            if ti.complete and have_sensors and not self.health.holding(t):
                self._restart_info = est.start(t, ti, self.adaptation.theta, self._restored, cfg.state) or self._restart_info
                self._restored = None
                self.health.new_state()
                obs = est.observer
                assert obs is not None  # started above
                self._prev_sample = (t, dict(ti.measured), obs.T.copy())
                self._fuse_flux(t, None, ti.inputs)  # the state starts: nothing fused into it yet
                return self._finish(t, ti, forced, [])
            grace = max(cfg.timeouts.values(), default=1.0) + self.dt
            waited = t - (self._start_t if self._start_t is not None else t)
            if self.health.holding(t):
                reasons = [DerateReason.MODEL_FAULT]
            elif self._start_t is None or waited > grace:  # still nothing usable: say why
                reasons = forced or [DerateReason.STALE_INPUT]
            else:
                reasons = [DerateReason.STARTING]
            self._fuse_flux(t, None, ti.inputs)  # no state to fuse into: the tick's voltages are dropped
            return self._output(t, ti, reasons, TeState.STARTING)

        u = {k: (v if math.isfinite(v) else self._last_inputs.get(k, math.nan)) for k, v in ti.inputs.items()}
        if self._doubt_current(t, ti, u):
            forced = input_reasons(ti)
        # 1. the previous sample (inputs of this interval) to the adapter
        if self._prev_sample is not None:
            t_prev, y_prev, x_prev = self._prev_sample
            self.adaptation.record(t_prev, u, y_prev, x_prev)
        # 2. open-loop prediction, 3. observer
        y = ti.measured
        assert est.prediction is not None  # initialized
        x_prev = est.prediction.copy()
        innov = est.step(u, y, self.sensor_rows)
        # the stuck-sensor check: how far the measured losses moved each sensor's node in the open-loop
        # prediction's step (the step alone: not a restart or new parameters). Not the observer's step:
        # the readings correct it every tick, so a small steady bias of the model would add up there
        # while a healthy reading sits still; the open loop only moves towards the model's own state.
        x_now = est.prediction
        assert x_now is not None
        moved = {s: float(x_now[r] - x_prev[r]) for s, r in self.sensor_rows.items()}
        newly = self.stuck.observe(t, readings, moved, means)
        if newly:
            for s, stuck_why in sorted(newly.items()):
                log.error("sensor %s stuck at t=%.0f: %s; its reading is withheld%s", s, t, stuck_why,
                          "; safe limit" if self.config.sensors[s].required else "")
                self.accumulator.bad_readings["stuck"] += 1
            self._withhold_stuck(ti, [])
            forced = input_reasons(ti)
        # 4. adaptation results and requests
        new_results = self.adaptation.step(t)
        for res in new_results:
            if res.accepted:
                self._take_parameters(res)
        # 5. health: the open-loop prediction error and the model's
        x_ol = est.prediction
        assert x_ol is not None
        pred_error = {s: float(x_ol[r] - y[s]) for s, r in self.sensor_rows.items() if math.isfinite(y.get(s, math.nan))}
        why = self.health.judge(t, innov, pred_error, est.finite)
        fc = self.config.derating.faults
        if why is not None:
            hold = self.health.fault(t)
            # readings below the prediction would raise the limit if believed: a sensor or
            # calibration fault (every PT100 offset by one bad reference) looks the same as a model
            # that runs hot, so the prediction from before runs on until they agree again
            low = bool(pred_error) and max(pred_error.values()) > fc.prediction_error_k
            log.error("model fault at t=%.0f: %s; safe limit for %.0f s, state re-initialised from the readings%s", t,
                      why, hold, "; the readings lie below the prediction: not trusted until they agree with it, and no estimate "
                      "published below it meanwhile" if low else "")
            est.restart_from_readings(ti, self.adaptation.theta, doubt=low)
            self.health.restart()
        gap = est.doubt_gap(y, self.sensor_rows)
        doubted = gap is not None and gap > fc.prediction_error_k / 2.0
        if gap is not None and not doubted:
            notice(log, "the readings agree again with the prediction from before the model fault (%.1f K below it): "
                   "trusted", gap)
            est.resolve_doubt()
            self.health.restart()
        # readings far below the commissioned model: neither believed nor learnt from
        below = self.commissioned.judge(t, est.commissioned_gap(y, self.sensor_rows))
        if self.health.holding(t) or (why is None and self.health.disagreeing) or doubted or below:
            # a disagreement not yet confirmed is not trusted either: the safe limit (bounded by the
            # band at the readings) for its ticks, without the hold and the restart of a fault
            forced.insert(0, DerateReason.MODEL_FAULT)
        obs = est.observer
        assert obs is not None  # stepped, or restarted from the readings
        flux = self._fuse_flux(t, obs, u)
        # the adapter judges from the observer's state; readings not believed are none to it
        learnt = {s: math.nan for s in y} if below or doubted else dict(y)
        self._prev_sample = (t, learnt, obs.T.copy())
        # nor are the estimates published from them: no node below the prediction they are judged against
        reference = est.doubt_prediction if doubted else est.commissioned_prediction if below else None
        return self._finish(t, ti, forced, new_results, pred_error, flux, reference)

    def _fuse_flux(self, t: float, obs: Observer | None, u: Mapping[str, float]) -> FluxTick | None:
        """The tick's flux estimate of the magnet, fused into ``obs`` (None without the voltage input)."""
        fx = self.flux
        if fx is None:
            return None
        return fx.fuse(t, obs, float(u.get(fx.speed_input, math.nan)))

    def _commissioned_floor(self, t: float, upper: np.ndarray) -> None:
        """Raise each limited node's ``upper`` (°C, by row, in place) to the commissioned prediction
        less ``derating.faults.commissioned_floor_k``: readings that drifted low by less than the
        gap that refuses them do not take the band further below the model file's prediction than a
        calibrated model's error. A WARNING when that starts to set a node's band, a NOTICE when
        it ends."""
        xc = self.estimate.commissioned_prediction
        if xc is None:
            return
        k = self.config.derating.faults.commissioned_floor_k
        for ln in self.limited_nodes:
            floor = float(xc[ln.row]) - k
            binding = floor > upper[ln.row] + 0.5  # K: more than a reading's rounding
            if binding and ln.name not in self._floored:
                log.warning("%s at t=%.0f: the band from the readings (%.1f degC) lies more than %g K below the "
                            "commissioned model's %.1f degC: derated on %.1f degC (a drift of the PT100s, or a "
                            "machine that cools better than its model file: recalibrate)", ln.name, t, upper[ln.row],
                            k, xc[ln.row], floor)
                self._floored.add(ln.name)
            elif not binding and ln.name in self._floored and floor < upper[ln.row] - 1.0:
                notice(log, "%s: the band from the readings is above the commissioned floor again (t=%.0f)", ln.name, t)
                self._floored.discard(ln.name)
            upper[ln.row] = max(upper[ln.row], floor)

    def _doubt_current(self, t: float, ti: TickInputs, u: dict[str, float]) -> bool:
        """Whether the current reads far below what the torque takes (:mod:`.current_torque`): then it
        is a fault of the current input (safe limit) and the model heats with ``|T| / kt`` instead."""
        chk = self.current_check
        if chk is None:
            return False
        v = chk.judge(u)
        name = chk.current_input
        if v.started:
            log.error("current %s at t=%.0f reads %.1f A, below %g of the %.1f A the torque %s of %.1f Nm takes at "
                      "kt %.3g Nm/A: a scaling in the DBC or a second sender of its frame? Not believed: safe limit, "
                      "the model heats with %.1f A", name, t, u[name], chk.ratio, v.needed, chk.torque_input,
                      u[chk.torque_input], chk.kt, v.needed)
            self.accumulator.bad_readings["current_below_torque"] += 1
        elif v.ended:
            notice(log, "current %s agrees again with the torque %s (at t=%.0f)", name, chk.torque_input, t)
        if not v.doubted:
            return False
        ti.faults.setdefault(name, "current_below_torque")
        u[name] = max(u[name], v.needed) if math.isfinite(u[name]) else v.needed
        return True

    def _withhold_stuck(self, ti: TickInputs, released: list[str]) -> None:
        """The stuck sensors' readings are not used; a required one is a sensor fault (``stuck``)."""
        for s in released:
            notice(log, "sensor %s no longer stuck: its reading moved", s)
        for s in self.stuck.stuck:
            ti.measured[s] = math.nan
            if self.config.sensors[s].required:
                ti.faults.setdefault(s, "stuck")

    def _take_parameters(self, res: AdaptationResult) -> None:
        """Accepted parameters to the estimate, the look-ahead and the reaction-time current; the
        open-loop state re-derived with them, the observer's estimate the one they were judged from."""
        theta = self.adaptation.theta
        self.estimate.set_parameters(theta)
        if self.lookahead is not None:
            self.lookahead.set_parameters(theta)
        self.reaction.set_parameters(theta)
        self.estimate.replace_prediction(self.adaptation.state_now(res, self.estimate.stepper))
        # the observer continues from the estimate the promoted parameters were judged from: its own,
        # not the one the parameters before them left in the nodes no sensor reads
        self.estimate.replace_estimate(self.adaptation.state_now(res, self.estimate.stepper, "estimate"))

    # -- outputs ------------------------------------------------------------------------------------
    def _finish(self, t: float, ti: TickInputs, forced: list[DerateReason], new_results: list[AdaptationResult],
                pred_error: dict[str, float] | None = None, flux: FluxTick | None = None,
                reference: np.ndarray | None = None) -> TickOutput:
        state = TeState.NOMINAL
        if DerateReason.MODEL_FAULT in forced:
            state = TeState.FAULT
        elif forced:
            state = TeState.DEGRADED
        elif self.adaptation.deciding:
            state = TeState.ADAPTING
        return self._output(t, ti, forced, state, new_results, pred_error, flux, reference)

    def _output(self, t: float, ti: TickInputs | None, forced: list[DerateReason], state: TeState,
                new_results: list[AdaptationResult] | None = None, pred_error: dict[str, float] | None = None,
                flux: FluxTick | None = None, reference: np.ndarray | None = None) -> TickOutput:
        """The tick's output. ``pred_error`` is the open-loop prediction error the tick measured
        (before a model fault re-initialised the state); without it, the error of the state now.
        ``reference`` (°C per node), while the readings are not believed: the prediction they are
        judged against; the estimate published and its band are not below it."""
        n = len(self.model.nodes)
        la_a, ttl, react_a = math.inf, math.inf, math.inf
        react_reason = DerateReason.NONE
        measured = dict(ti.measured) if ti is not None else {}
        stale, faults = (list(ti.stale), dict(ti.faults)) if ti is not None else ([], {})
        floor = self.floor.bands(measured)
        obs, x_ol = self.estimate.observer, self.estimate.prediction
        if obs is not None:
            est = obs.T.copy()
            sigma = obs.std()
            if reference is not None:  # a state rebuilt from readings not believed is not published as such
                np.maximum(est, reference, out=est)
            pred = x_ol.copy() if x_ol is not None else np.full(n, math.nan)
            observer_upper = est + self.config.derating.band_z * sigma
            upper = observer_upper.copy()
            # a limited node is at least as hot as a sensor that bounds it from below: an estimate
            # the readings have outrun (a model that runs cold) does not hide that
            self.floor.raise_upper(upper, measured)
            self._commissioned_floor(t, upper)
            # the one definition of the band derated on and sent (TE_Estimates); the replay's
            # per-tick table reads these, never a band of its own. While the voltages observe the
            # magnet its band is a measured one: the smaller margin
            observed = self.flux is not None and self.flux.observing(t)
            bands = [NodeBand(ln.name, float(est[ln.row]), float(upper[ln.row]), ln.warn_c, ln.max_c, ln.reason,
                              float(observer_upper[ln.row]),
                              margin_k=(self.config.flux.magnet_margin_k
                                        if observed and ln.name == self.config.transmit.magnet_limit else None))
                     for ln in self.limited_nodes]
            u = {k: (v if math.isfinite(v) else self._last_inputs.get(k, 0.0))
                 for k, v in (ti.inputs if ti else self._last_inputs).items()}
            try:
                rr = self.reaction.compute(upper, u)
                react_a, react_reason = rr.current_a, self.limited_nodes[rr.binding].reason
            except Exception as exc:
                log.error("reaction-time look-ahead failed: %s", exc)
                react_a = math.nan  # the policy treats it as a model fault
            if self.lookahead is not None and ti is not None:
                try:
                    ahead = self.lookahead.compute(upper, u)
                    la_a, ttl = ahead.current_a, ahead.time_to_limit_s
                except Exception as exc:
                    log.warning("look-ahead failed: %s", exc)
                    la_a = math.nan
            limits = self.policy.update(bands, (react_a, react_reason), forced, floor)
            if forced and math.isfinite(la_a):  # the estimate is not trusted: no advice above the limit sent
                la_a = min(la_a, limits.current_a)
        else:
            est = np.full(n, math.nan)
            sigma = np.full(n, math.nan)
            pred = np.full(n, math.nan)
            bands = []
            limits = self.policy.update([], None, forced or [DerateReason.STARTING], floor)
        self.events.record(state, limits, stale, faults, self.accumulator.refusal)
        if pred_error is None:
            pred_error = {}
            if obs is not None and x_ol is not None:
                for s, r in self.sensor_rows.items():
                    v = measured.get(s, math.nan)
                    if math.isfinite(v):
                        pred_error[s] = float(pred[r] - v)
        by_name = {b.name: b for b in bands}
        tr = self.config.transmit
        ad = self.adaptation.counts
        refusal = self.adaptation.last_refusal
        return TickOutput(
            t=t, state=state, limits=limits, initialized=obs is not None,
            estimate=est, sigma=sigma, prediction=pred, measured=measured,
            inputs=dict(ti.inputs) if ti is not None else {}, pred_error=pred_error,
            pred_err_rms=self.health.rms_error, bands=bands, lookahead_a=la_a, time_to_limit_s=ttl,
            horizon_s=self.config.lookahead.horizon_s, adapt_runs=ad.runs, adapt_accepted=ad.accepted,
            adapt_rejected=ad.rejected, param_version=ad.version, forced=list(forced),
            stale=stale, faults=faults, new_results=list(new_results or []),
            hot_spot=by_name.get(tr.hot_spot_limit), magnet=by_name.get(tr.magnet_limit) if tr.magnet_limit else None,
            reaction_a=react_a,
            adapt_status=self.adaptation.status, adapt_refusal=refusal[1] if refusal is not None else "",
            ages=dict(ti.ages) if ti is not None else {}, flux=flux,
        )

    def placeholder(self, t: float) -> TickOutput:
        """An output for before the first tick (starting, safe limit, no estimates)."""
        nan = np.full(len(self.model.nodes), math.nan)
        ad = self.adaptation.counts
        return TickOutput(
            t=t, state=TeState.STARTING, limits=self.policy.safe(DerateReason.STARTING), initialized=False, estimate=nan,
            sigma=nan, prediction=nan, measured={}, inputs={}, pred_error={}, pred_err_rms=math.nan, bands=[],
            lookahead_a=math.inf, time_to_limit_s=math.inf, horizon_s=self.config.lookahead.horizon_s,
            adapt_runs=ad.runs, adapt_accepted=ad.accepted, adapt_rejected=ad.rejected,
            param_version=ad.version, forced=[DerateReason.STARTING], stale=[], faults={},
        )

    # -- persistence --------------------------------------------------------------------------------
    def persisted(self, t: float) -> PersistedState:
        """What to save now (parameters, decisions and, once running, the thermal state)."""
        ad, counts = self.adaptation, self.adaptation.counts
        learned = ad.changed()
        start = dict(zip(self.model.parameter_names, self.model.nominal()))
        st = PersistedState(model=self.model.name, saved_at=float(t), parameters=learned, param_version=counts.version,
                            adapt_runs=counts.runs, decisions=ad.decisions, saved_wall=time.time(),
                            inputs={k: float(v) for k, v in self._last_inputs.items() if math.isfinite(v)},
                            nominal={k: float(start[k]) for k in learned})
        saved = self.estimate.saved()
        if saved is not None:
            st.nodes, st.T, st.sigma, st.P, st.T_pred = saved["nodes"], saved["T"], saved["sigma"], saved["P"], saved["T_pred"]
            st.T_commissioned = saved["T_commissioned"]
        elif self._restored is not None and self._restored.T:  # not yet running: keep what was loaded
            rs = self._restored
            st.nodes, st.T, st.sigma, st.P, st.T_pred = rs.nodes, rs.T, rs.sigma, rs.P, rs.T_pred
            st.T_commissioned = rs.T_commissioned
            st.saved_at = rs.saved_at
        return st

    def close(self) -> None:
        self.adaptation.close()
