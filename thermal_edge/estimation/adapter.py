"""The online adapter (paper Fig. 7): every ``period_s`` compare prediction and measurement over the
last period; above a threshold, screen and optimise the adaptable parameters on the history
window, then accept the candidate only if it predicts recent data no worse than the current
parameters (else roll back). Every decision is recorded.

Only data up to the decision time is used: the history holds samples recorded so far, and a
decision at time ``t`` reads nothing newer than ``t``.

The history is bounded: ``window_s`` of samples in ring buffers (inputs, readings, and the state
estimate at each sample, which gives the window its initial state). For the optimiser the window
is decimated by ``decimate`` (inputs averaged per step, currents as RMS), which is exact for
inputs held over each coarse step.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from ..lptn import Model, Simulator
from .common import ParamSpace, Window, decimate
from .gauss_newton import fit_gauss_newton
from .objective import Objective
from .screening import screen
from .sqp import fit_sqp
from .uncertainty import estimate_uncertainty

METHODS = ("sqp", "gauss_newton", "numerical")


@dataclass
class AdapterConfig:
    """Settings of the online adapter (``adaptation:`` in ``config/edge.yaml``).

    Attributes
    ----------
    period_s : float
        Decision period ``Ts``, s (the paper: 180 s).
    threshold_k : float
        RMS prediction error over the last period above which the adapter optimises, K.
    window_s : float
        History window used for estimation, s.
    min_window_s : float
        No optimisation before this much history (s): minutes of data from one operating point
        cannot separate capacities from resistances, and a fit on them extrapolates badly.
    decimate : int
        Samples per optimiser step (20 at 1 Hz: 20 s steps, short against the machine's thermal
        time constants; ZOH on the coarse grid is exact for inputs held over each step).
    max_iter : int
        SQP iteration cap per decision.
    coverage : float
        Screening keeps parameters covering this share of the optimisation potential.
    weighting : {"paper", "forgetting", "uniform"}
    tau_s : float
        Forgetting time constant for ``weighting: forgetting``, s.
    prior_weight : float
        MAP weight toward the offline values (0 = least squares), K².
    validate_s : float
        Recent data (s) on which candidate and current parameters are compared: a candidate is
        accepted only if its RMS error over all sensors is no worse and no single sensor's RMS
        error grows by more than ``sensor_tolerance_k`` (K).
    method : {"sqp", "gauss_newton", "numerical"}
    params : tuple of str, optional
        Adaptable parameters; default: the model's ``adaptable: true`` ones.
    sensors : tuple of str, optional
        Sensors the adapter learns from; default: all the model's sensors present.
    max_rel_std : float
        A parameter is offered to the optimiser only if the window pins it down to this relative
        standard deviation (Fisher information, all adaptable parameters free).
    """

    period_s: float = 180.0
    threshold_k: float = 0.25
    window_s: float = 10800.0
    min_window_s: float = 1800.0
    decimate: int = 20
    max_iter: int = 3
    coverage: float = 0.98
    weighting: str = "paper"
    tau_s: float = 3600.0
    prior_weight: float = 1e-4
    validate_s: float = 1800.0
    sensor_tolerance_k: float = 0.02
    method: str = "sqp"
    params: tuple[str, ...] | None = None
    sensors: tuple[str, ...] | None = None
    max_rel_std: float = 0.5


@dataclass
class Decision:
    """One adapter decision."""

    t: float
    error_before_k: float  # RMS over the last period with the current parameters
    triggered: bool
    accepted: bool = False
    candidate_error_k: float = float("nan")  # validation RMS of the candidate
    current_error_k: float = float("nan")  # validation RMS of the current parameters
    selected: tuple[str, ...] = ()
    unidentifiable: tuple[str, ...] = ()
    params: dict[str, float] = field(default_factory=dict)
    iterations: int = 0
    evaluations: int = 0
    duration_s: float = 0.0
    reason: str = ""

    def as_dict(self) -> dict[str, object]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


class _Ring:
    """Fixed-capacity ring buffer of rows (samples) of a given width."""

    def __init__(self, capacity: int, width: int) -> None:
        self.buf = np.full((capacity, width), np.nan)
        self.n = 0
        self.head = 0

    def push(self, row: np.ndarray) -> None:
        self.buf[self.head] = row
        self.head = (self.head + 1) % len(self.buf)
        self.n = min(self.n + 1, len(self.buf))

    def array(self) -> np.ndarray:
        if self.n < len(self.buf):
            return self.buf[: self.n]
        return np.concatenate([self.buf[self.head:], self.buf[: self.head]])


class History:
    """Bounded history of samples: time, inputs, readings and state estimates."""

    def __init__(self, model: Model, sensors: Sequence[str], capacity: int) -> None:
        self.inputs = list(model.inputs)
        self.sensors = list(sensors)
        self.ring = _Ring(capacity, 1 + len(self.inputs) + len(self.sensors) + len(model.nodes))

    def push(self, t: float, inputs: Mapping[str, float], measured: Mapping[str, float], state: np.ndarray) -> None:
        row = np.concatenate([
            [t],
            [float(inputs[c]) for c in self.inputs],
            [float(measured.get(s, np.nan)) for s in self.sensors],
            np.asarray(state, dtype=float),
        ])
        self.ring.push(row)

    def __len__(self) -> int:
        return self.ring.n

    def arrays(self, since: float = -np.inf) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray], np.ndarray]:
        """Time, inputs, readings and states of the samples at ``t >= since``."""
        a = self.ring.array()
        a = a[a[:, 0] >= since]
        ni, ns = len(self.inputs), len(self.sensors)
        t = a[:, 0]
        inputs = {c: a[:, 1 + i] for i, c in enumerate(self.inputs)}
        meas = {s: a[:, 1 + ni + i] for i, s in enumerate(self.sensors)}
        return t, inputs, meas, a[:, 1 + ni + ns:]


class OnlineAdapter:
    """Adapts a model's parameters to the readings, one decision every ``period_s``.

    Parameters
    ----------
    model : Model
    config : AdapterConfig
    dt : float
        Sample period of the recorded samples, s.
    theta : ndarray, optional
        Starting parameters (default nominal: the offline values, also the prior).
    """

    def __init__(self, model: Model, config: AdapterConfig, dt: float, theta: np.ndarray | None = None) -> None:
        if config.method not in METHODS:
            raise ValueError(f"adaptation.method must be one of {', '.join(METHODS)}, got {config.method!r}")
        self.model, self.config, self.dt = model, config, float(dt)
        self.theta = model.nominal() if theta is None else np.asarray(theta, dtype=float).copy()
        self.prior = self.theta.copy()
        self.params = tuple(config.params or model.adaptable)
        self.sensors = tuple(config.sensors or model.sensors)
        self.sim = Simulator(model)
        self.history = History(model, self.sensors, int(round(config.window_s / dt)) + 1)
        self.decisions: list[Decision] = []
        self.version = 0
        self.last_decision_t: float | None = None

    # -- data --------------------------------------------------------------------------------
    def record(self, t: float, inputs: Mapping[str, float], measured: Mapping[str, float], state: np.ndarray) -> None:
        """Append one sample: inputs, readings of the adapter's sensors, and the model's open-loop
        prediction of every node at that sample (its error triggers adaptation; it also gives a
        window its initial state, with measured nodes set to their readings)."""
        if self.last_decision_t is None:
            self.last_decision_t = t
        self.history.push(t, inputs, measured, state)

    def due(self, t: float) -> bool:
        """Whether a decision is due at time ``t`` (s)."""
        return self.last_decision_t is not None and t - self.last_decision_t >= self.config.period_s - 1e-9

    # -- helpers -----------------------------------------------------------------------------
    def _window(self, since: float) -> Window:
        t, inputs, meas, states = self.history.arrays(since)
        T0 = states[0].copy()
        for s in self.sensors:  # a measured node starts at its reading
            y = meas[s][0]
            if np.isfinite(y):
                T0[self.model.node_index(self.model.sensors[s])] = y
        return Window(inputs, meas, T0, self.dt, t)

    def _rms(self, theta: np.ndarray, window: Window, since: float = -np.inf) -> tuple[float, dict[str, float]]:
        """RMS error of the open-loop prediction over the window, scored from ``since`` on: all
        sensors together, and per sensor (K). The prediction runs from the window's start, as
        the model's state is derived after a decision."""
        traj = self.sim.simulate(theta, window.inputs, window.dt, window.T0)
        scored = window.t >= since
        errs = {}
        for s in self.sensors:
            e = (traj.node(self.model.sensors[s]) - window.measured[s])[scored]
            errs[s] = e[np.isfinite(e)]
        e = np.concatenate(list(errs.values())) if errs else np.zeros(0)
        per = {s: float(np.sqrt(np.mean(v**2))) if len(v) else float("nan") for s, v in errs.items()}
        return (float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")), per

    def recent_error(self, since: float) -> float:
        """RMS (K) of the recorded predictions against the readings since ``since``."""
        _, _, meas, states = self.history.arrays(since)
        errs = []
        for s in self.sensors:
            e = states[:, self.model.node_index(self.model.sensors[s])] - meas[s]
            errs.append(e[np.isfinite(e)])
        e = np.concatenate(errs) if errs else np.zeros(0)
        return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")

    def objective(self, window: Window, names: Sequence[str] | None = None) -> Objective:
        """The estimation objective over a window for the given parameters (default: all adaptable)."""
        space = ParamSpace(self.model, tuple(names or self.params), self.theta, self.prior[self.model.parameter_index(tuple(names or self.params))])
        cfg = self.config
        return Objective(self.sim, space, window, list(self.sensors), cfg.weighting, cfg.prior_weight, cfg.tau_s)

    # -- the decision ------------------------------------------------------------------------
    def decide(self, t: float) -> Decision:
        """Check the last period at time ``t`` and adapt if the error is above the threshold."""
        cfg = self.config
        t0 = time.perf_counter()
        self.last_decision_t = t
        err = self.recent_error(t - cfg.period_s)
        d = Decision(t=t, error_before_k=err, triggered=bool(err > cfg.threshold_k))
        if not d.triggered:
            d.reason = "error below threshold" if np.isfinite(err) else "no readings in the last period"
            return self._done(d, t0)
        t_hist = self.history.arrays()[0]
        if t - t_hist[0] < cfg.min_window_s:
            d.reason = f"waiting for {cfg.min_window_s:g} s of history before adapting"
            return self._done(d, t0)
        full = self._window(t - cfg.window_s)
        coarse = decimate(full, cfg.decimate)
        obj = self.objective(coarse)
        phi = np.log(self.theta[obj.space.index])
        ev = obj.evaluate(phi)
        unc = estimate_uncertainty(obj, ev, cfg.max_rel_std)
        sc = screen(obj.space.names, ev.grad, ev.hess, phi, obj.space.lower, obj.space.upper, cfg.coverage,
                    unc.identifiable)
        d.selected = sc.selected
        d.unidentifiable = tuple(n for n, ok in zip(obj.space.names, unc.identifiable) if not ok)
        if not sc.selected:
            d.reason = "no identifiable parameter can reduce the error within its bounds"
            return self._done(d, t0)
        sub = self.objective(coarse, sc.selected)
        if cfg.method == "gauss_newton":
            res = fit_gauss_newton(sub, max_iter=cfg.max_iter + 1)
        else:
            res = fit_sqp(sub, max_iter=cfg.max_iter, gradient="numerical" if cfg.method == "numerical" else "analytic")
        cand = self.theta.copy()
        cand[sub.space.index] = np.clip(res.values, sub.space.lower, sub.space.upper)  # exp(log(bound)) rounds past it
        d.iterations, d.evaluations = res.iterations, res.evaluations
        d.params = dict(zip(sc.selected, map(float, res.values)))
        d.current_error_k, cur = self._rms(self.theta, coarse, t - cfg.validate_s)
        d.candidate_error_k, new = self._rms(cand, coarse, t - cfg.validate_s)
        worse = [s for s in self.sensors if new[s] > cur[s] + cfg.sensor_tolerance_k]
        if d.candidate_error_k <= d.current_error_k and not worse:
            d.accepted = True
            d.reason = "candidate predicts recent data better"
            self.theta = cand
            self.version += 1
        elif worse:
            d.reason = f"rolled back: candidate predicts {', '.join(worse)} worse"
        else:
            d.reason = "rolled back: candidate predicts recent data worse"
        return self._done(d, t0)

    def _done(self, d: Decision, t0: float) -> Decision:
        d.duration_s = time.perf_counter() - t0
        self.decisions.append(d)
        return d

    def current_uncertainty(self, since: float | None = None):  # type: ignore[no-untyped-def]
        """Parameter covariance and identifiability at the current parameters over the history."""
        cfg = self.config
        win = decimate(self._window(-np.inf if since is None else since), cfg.decimate)
        obj = self.objective(win)
        ev = obj.evaluate(np.log(self.theta[obj.space.index]))
        return estimate_uncertainty(obj, ev)

    def params_dict(self) -> dict[str, float]:
        """Current values of the adaptable parameters."""
        return {n: float(self.theta[i]) for n, i in zip(self.params, self.model.parameter_index(self.params))}
