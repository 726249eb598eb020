"""The thermal state estimate: the observer's best estimate and the open-loop prediction beside it.

:class:`StateEstimate` owns the :class:`~thermal_edge.estimation.observer.Observer` (Kalman filter,
corrected by the readings) and the **open-loop prediction** (the same model step, never corrected:
its error against the readings is what tells a model gone wrong and triggers adaptation). It starts
them (from the readings, or from a saved state cooled over the downtime), steps them once a tick,
restarts them from the readings after a model fault, cools them over a gap in the frames, and takes
new parameters.

Beside them runs the **commissioned prediction**: the model file's parameters (never adapted) on
open loop from the first state, never restarted from the readings. What the adaptation learns and
what a restart takes from the readings both follow readings that drift; this prediction does not,
so readings that fall far below it are evidence against the readings (:meth:`commissioned_gap`).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Mapping

import numpy as np

from ..config import ObserverConfig, StateConfig
from ..estimation.observer import Observer
from ..lptn import Model, Role, Stepper, cool_down, initial_state
from .inputs import TickInputs
from .persistence import PersistedState

__all__ = ["StateEstimate"]

log = logging.getLogger(__name__)

#: operating points (exact speeds) whose transition matrices are kept (18 kB each for pm10kw): a
#: drive dwells at a few and ramps through others it will not meet again to the rpm
STEPPER_CACHE = 32
#: the commissioned prediction steps once per this many ticks, with the block's mean inputs (the
#: current as RMS, so that the copper losses are kept): it is judged against a 20 K gap on drifts
#: of minutes, and a step (the losses at the operating point) costs as much as the open loop's
COMMISSIONED_BLOCK = 10


class StateEstimate:
    """Observer and open-loop prediction of the model's node temperatures (°C).

    Parameters
    ----------
    model : Model
    dt : float
        Tick period, s.
    config : ObserverConfig
        Noise levels (K).
    """

    def __init__(self, model: Model, dt: float, config: ObserverConfig, observer_type: type[Observer] = Observer) -> None:
        self.model = model
        self.dt = float(dt)
        self.config = config
        #: the observer's class (a FluxObserver where the voltages are fused: the same filter with room for
        #: the flux estimate's error states)
        self.observer_type = observer_type
        self._observer: Observer | None = None
        self._prediction: np.ndarray | None = None
        #: after a model fault whose readings lay below the open-loop prediction (the direction that
        #: would raise the limit): that prediction, run on open loop with the parameters of the
        #: fault (:meth:`doubt_gap`); None when no such fault is unresolved
        self._doubt: tuple[Stepper, np.ndarray] | None = None
        #: the commissioned prediction: the model file's parameters on open loop, °C (None before the start)
        self._commissioned = Stepper(model, model.nominal(), self.dt * COMMISSIONED_BLOCK)
        self._commissioned.cache_size = STEPPER_CACHE
        self._commissioned_x: np.ndarray | None = None
        self._block: list[Mapping[str, float]] = []  # the inputs of the ticks since its last step
        self._current = model.find_input(Role.CURRENT)

    # -- read-only views -------------------------------------------------------------------------
    @property
    def initialized(self) -> bool:
        """True once the state is started (and until a failed tick drops it)."""
        return self._observer is not None

    @property
    def observer(self) -> Observer | None:
        """The observer (None before the start)."""
        return self._observer

    @property
    def prediction(self) -> np.ndarray | None:
        """The open-loop prediction, °C (None before the start)."""
        return self._prediction

    @property
    def finite(self) -> bool:
        """Whether the estimate, its covariance and the prediction are all finite."""
        obs, x = self._observer, self._prediction
        return bool(obs is not None and x is not None and np.all(np.isfinite(obs.T)) and np.all(np.isfinite(obs.P))
                    and np.all(np.isfinite(x)))

    # -- start and restart ------------------------------------------------------------------------
    def start(self, t: float, ti: TickInputs, theta: np.ndarray, restored: PersistedState | None,
              state: StateConfig) -> dict[str, float]:
        """Start from a saved state cooled over the downtime (if usable) or from the readings, then
        correct by the first readings; returns what the restart was (``downtime_s``, or empty)."""
        m, cfg = self.model, self.config
        T0 = P0 = None
        info: dict[str, float] = {}
        rs = restored
        if rs is not None and rs.T:
            downtime = t - rs.saved_at
            info = {"downtime_s": downtime}
            last = {**ti.inputs, **{k: v for k, v in rs.inputs.items() if math.isfinite(v)}}
            if 0 <= downtime <= state.max_downtime_s:
                try:
                    T0, Phi = cool_down(m, theta, np.array(rs.T), downtime, last)
                    P = (np.array(rs.P) if rs.P else np.diag(np.square(np.array(rs.sigma))) if rs.sigma
                         else np.eye(len(T0)) * cfg.restart_p0_k**2)
                    P = P + self._run_on_covariance(theta, np.array(rs.T), rs.inputs, min(downtime, state.save_interval_s))
                    grow = min(cfg.q_k**2 * downtime / self.dt, cfg.restart_p0_k**2)
                    P0 = Phi @ P @ Phi.T + np.eye(len(T0)) * grow
                    log.info("restored thermal state from %.0f s ago (cooled over the downtime at %.1f degC ambient)",
                             downtime, float(np.mean([float(last.get(c, math.nan)) for c in m.boundaries.values()])))
                except Exception as exc:
                    log.warning("cannot cool the saved state over the downtime (%s): starting from the readings", exc)
                    T0 = None
            elif downtime < 0:  # a clock set back (an RTC reset, a replay of an earlier log): its age is unknown
                log.warning("saved state is %.0f s in the future (clock changed?): its age is unknown, the temperatures "
                            "start from the readings (the learned parameters are kept)", -downtime)
            else:
                log.info("saved state is %.0f s old (more than %.0f s): starting from the readings", downtime,
                         state.max_downtime_s)
        if T0 is None:
            T0 = initial_state(m, ti.inputs, ti.measured, theta)
        self._begin(T0, theta, ti.measured, P0)
        self._start_commissioned(rs, t, state)
        return info

    def _start_commissioned(self, rs: PersistedState | None, t: float, state: StateConfig) -> None:
        """The commissioned prediction: kept through a failed tick, restored from the saved one
        cooled over the downtime, else from the started state."""
        if self._commissioned_x is not None:
            return
        assert self._prediction is not None
        x = self._prediction.copy()
        if rs is not None and rs.T_commissioned and len(rs.T_commissioned) == len(x):
            downtime = t - rs.saved_at
            last = {k: v for k, v in rs.inputs.items() if math.isfinite(v)}
            try:
                if 0 <= downtime <= state.max_downtime_s:
                    x = cool_down(self.model, self._commissioned.theta, np.array(rs.T_commissioned), downtime, last)[0]
            except Exception as exc:  # the inputs saved do not cover the model's: from the started state
                log.warning("cannot cool the saved commissioned prediction over the downtime (%s): "
                            "starting it from the state", exc)
        self._commissioned_x = x if np.all(np.isfinite(x)) else self._prediction.copy()

    def restart_from_readings(self, ti: TickInputs, theta: np.ndarray, doubt: bool = False) -> None:
        """After a model fault: start again from the usable readings alone. With ``doubt`` (the
        readings lay below the prediction) the prediction from before the fault runs on beside
        the new state until the readings agree with it again (:meth:`doubt_gap`)."""
        m = self.model
        if doubt and self._prediction is not None and np.all(np.isfinite(self._prediction)):
            self._doubt = (Stepper(m, theta, self.dt), self._prediction.copy())
        ok = {k: v for k, v in ti.measured.items() if math.isfinite(v)}
        try:
            T0 = initial_state(m, ti.inputs, ok, theta)
        except Exception:
            T0 = np.full(len(m.nodes), float(np.nanmean(list(ok.values()))) if ok else 25.0)
        if not np.all(np.isfinite(T0)):
            T0 = np.full(len(m.nodes), 25.0)
        self._begin(T0, theta, ok, None)

    def doubt_gap(self, measured: Mapping[str, float], sensor_rows: Mapping[str, int]) -> float | None:
        """By how much (K) the readings lie below the prediction from before an unresolved model
        fault, at the sensor where most (None without such a fault, or without a reading)."""
        if self._doubt is None:
            return None
        x = self._doubt[1]
        gaps = [x[r] - measured[s] for s, r in sensor_rows.items() if math.isfinite(measured.get(s, math.nan))]
        return max(gaps) if gaps and math.isfinite(max(gaps)) else None

    @property
    def doubt_prediction(self) -> np.ndarray | None:
        """The prediction from before an unresolved model fault whose readings lay below it, run on
        with the inputs (°C per node; None without such a fault)."""
        return None if self._doubt is None else self._doubt[1]

    @property
    def commissioned_prediction(self) -> np.ndarray | None:
        """The commissioned prediction (°C per node; None before the start)."""
        return self._commissioned_x

    def commissioned_gap(self, measured: Mapping[str, float], sensor_rows: Mapping[str, int]) -> tuple[str, float] | None:
        """The sensor whose reading lies furthest below the commissioned prediction, and by how much
        (K; negative: every reading above it); None before the start or without a reading."""
        x = self._commissioned_x
        if x is None:
            return None
        gaps = [(float(x[r] - measured[s]), s) for s, r in sensor_rows.items() if math.isfinite(measured.get(s, math.nan))]
        if not gaps:
            return None
        gap, s = max(gaps)
        return (s, gap) if math.isfinite(gap) else None

    def resolve_doubt(self) -> None:
        """The readings agree with the prediction from before the fault again: the state and the
        open-loop prediction continue from it (the state restarted from the doubted readings
        would disagree with the good ones as much as they did), and it is forgotten."""
        if self._doubt is not None:
            x = self._doubt[1]
            self.replace_estimate(x.copy())
            self.replace_prediction(x.copy())
        self._doubt = None

    def drop(self) -> None:
        """Forget the state (a tick failed): the next usable tick starts it again."""
        self._observer = None

    def _begin(self, T0: np.ndarray, theta: np.ndarray, measured: Mapping[str, float], P0: np.ndarray | None) -> None:
        c = self.config
        obs = self.observer_type(self.model, T0, theta, self.dt, c.q_k, c.r_k, c.p0_k)
        obs.stepper.cache_size = STEPPER_CACHE
        if P0 is not None:
            obs.P = 0.5 * (P0 + P0.T)
        obs.update(dict(measured))  # corrected by the first measurements
        self._observer = obs
        self._prediction = obs.T.copy()

    def _run_on_covariance(self, theta: np.ndarray, T: np.ndarray, last: dict[str, float], run_on_s: float) -> np.ndarray:
        """Uncertainty of the saved state about what happened after it was saved: the machine may have
        run on at its last load for up to one save interval before it stopped. Rank one, along the
        difference between running on and standing still, so that the first readings of the measured
        nodes correct the unmeasured ones consistently (they were all heated by the same losses)."""
        m = self.model
        n = len(m.nodes)
        if run_on_s <= 0 or not all(math.isfinite(last.get(k, math.nan)) for k in m.inputs):
            return np.zeros((n, n))
        try:
            run, _ = Stepper(m, theta, run_on_s).step(T, {k: float(last[k]) for k in m.inputs})
            stop, _ = cool_down(m, theta, T, run_on_s, last)
        except Exception:
            return np.zeros((n, n))
        v = run - stop
        return np.outer(v, v) if np.all(np.isfinite(v)) else np.zeros((n, n))

    # -- per tick -----------------------------------------------------------------------------------
    def step(self, u: Mapping[str, float], measured: Mapping[str, float], sensor_rows: Mapping[str, int]) -> list[float]:
        """One tick: the prediction and the observer step with the interval's inputs ``u``, the
        observer is corrected by ``measured``; returns the absolute innovations (K) of the sensors
        with a reading."""
        obs, x = self._observer, self._prediction
        assert obs is not None and x is not None
        self._prediction, _ = obs.stepper.step(x, dict(u))
        if self._doubt is not None:
            st, xd = self._doubt
            self._doubt = (st, st.step(xd, dict(u))[0])
        self._step_commissioned(u)
        obs.predict(dict(u))
        prior = obs.T.copy()
        innov = [abs(measured[s] - prior[r]) for s, r in sensor_rows.items() if math.isfinite(measured.get(s, math.nan))]
        obs.update(dict(measured))
        return innov

    def _step_commissioned(self, u: Mapping[str, float]) -> None:
        """Collect the tick's inputs; every :data:`COMMISSIONED_BLOCK` ticks step the commissioned
        prediction over the block with their mean (the current's RMS)."""
        if self._commissioned_x is None:
            return
        self._block.append(u)
        if len(self._block) < COMMISSIONED_BLOCK:
            return
        mean = {k: float(np.sqrt(np.mean([b[k] ** 2 for b in self._block])) if k == self._current
                         else np.mean([b[k] for b in self._block])) for k in u}
        self._block = []
        xc = self._commissioned.step(self._commissioned_x, mean)[0]
        if np.all(np.isfinite(xc)):  # inputs the model cannot step: it waits for usable ones
            self._commissioned_x = xc

    def bridge(self, gap_s: float, theta: np.ndarray, last_inputs: Mapping[str, float]) -> None:
        """Cool the state at standstill over a gap of ``gap_s`` in the frames (the uncertainty grows)."""
        obs = self._observer
        if obs is None:
            return
        T1, Phi = cool_down(self.model, theta, obs.T, gap_s, dict(last_inputs))
        grow = min(self.config.q_k**2 * gap_s / self.dt, self.config.restart_p0_k**2)
        obs.T = T1
        obs.P = Phi @ obs.P @ Phi.T + np.eye(len(T1)) * grow
        self._prediction = T1.copy()
        if self._commissioned_x is not None:
            self._commissioned_x = cool_down(self.model, self._commissioned.theta, self._commissioned_x, gap_s,
                                             dict(last_inputs))[0]
            self._block = []

    @property
    def stepper(self) -> Stepper:
        """The model step with the parameters in use (the observer's)."""
        assert self._observer is not None
        return self._observer.stepper

    def set_parameters(self, theta: np.ndarray) -> None:
        """New parameters for the observer (and so for the prediction's next steps)."""
        assert self._observer is not None
        self._observer.set_parameters(theta)

    def replace_prediction(self, prediction: np.ndarray | None) -> None:
        """The open-loop state consistent with new parameters, °C (ignored if None or not finite)."""
        if prediction is not None and np.all(np.isfinite(prediction)):
            self._prediction = prediction

    def replace_estimate(self, estimate: np.ndarray | None) -> None:
        """The observer's estimate consistent with new parameters, °C (ignored if None or not
        finite; its covariance is kept)."""
        if self._observer is not None and estimate is not None and np.all(np.isfinite(estimate)):
            self._observer.T = np.asarray(estimate, dtype=float).copy()

    def saved(self) -> dict[str, list] | None:
        """The state to persist (nodes, T, sigma, P, T_pred, T_commissioned), or None if not started or
        not finite."""
        obs = self._observer
        if obs is None or not (np.all(np.isfinite(obs.T)) and np.all(np.isfinite(obs.P))):
            return None
        out: dict[str, list] = {"nodes": list(self.model.nodes), "T": [float(x) for x in obs.T],
                                "sigma": [float(x) for x in obs.std()],
                                # with the parameters' part of the bands (the rotor-side model error), which a
                                # restart must not forget
                                "P": [[float(x) for x in row] for row in obs.covariance()],
                                "T_pred": []}
        x = self._prediction
        if x is not None and np.all(np.isfinite(x)):
            out["T_pred"] = [float(v) for v in x]
        xc = self._commissioned_x
        out["T_commissioned"] = [float(v) for v in xc] if xc is not None and np.all(np.isfinite(xc)) else []
        return out
