"""The online adapter (paper Fig. 7): every ``period_s`` compare prediction and measurement over the
last period; above a threshold, screen and optimise the adaptable parameters on the history
window. The optimised candidate does not replace the parameters in use (the *champion*) at once:
it becomes a *challenger*, judged only on data it was not fitted to. At the following decisions
both predict every sample recorded since, period by period open loop from the recorded state at
each period's start (as the online trace is scored); the challenger is promoted when its squared
error over the seen sensors is lower by more than a margin that accounts for the sensor noise and
the length of the evidence (:func:`judge`), dropped when it is worse by that margin or when
``validate_s`` of evidence has not decided it. A candidate judged on its own window would pass by
fitting noise and the present operating point. Every decision is recorded with its evidence.
The evidence is counted in periods, not samples: one period never decides, either way.

A fit is triggered when the last period's error or the open-loop error over the last
``validate_s`` (from the recorded state then) exceeds ``threshold_k``: a period of a few minutes
predicted from corrected temperatures does not show the slow modes (the housing's time constant
is hours), and the service predicts open loop over its look-ahead (30 min). With only the
period's error a model whose short-term prediction is within the noise stopped adapting while
its open-loop prediction drifted by 1 K over a cold light duty. The challenger is still judged
period by period: judged open loop over all its evidence, it promoted candidates on the real
machine that made the online trace worse from every wrong start.

Below the threshold a *refinement* is fitted when the window alone pins an adaptable parameter
away from its value (:func:`.pinned.pinned_step`: more than 5 % and 3σ, pinned to 2 %): the
pinned Gauss-Newton step, then SLSQP (:func:`.pinned.fit_refine`). Once the model predicts within
the threshold the error triggers nothing, while the window goes on pinning such a parameter ever
tighter. Its challenger and the champion are each judged from their own shadow observer
(:class:`.shadow.ShadowObserver`): the recorded state is the estimate of an observer running with
the parameters in use, which in the nodes no sensor reads compensates their errors and favours
them. On a promotion :attr:`OnlineAdapter.promoted_state` holds the promoted parameters' estimate.

The optimiser resumes from its last candidate (unless the data refuted it), so that fits capped
at ``max_iter`` iterations add up across decisions as in the paper, while the parameters in use
change only on out-of-sample evidence.

Optimisation starts when the window can identify something: at least one adaptable parameter
pinned down to ``max_rel_std`` by the window's Fisher information, and no less than
``min_window_s`` of history (a floor: the Fisher information of a few minutes at one operating
point is computed from residuals correlated in time and overstates what they separate).

Only data up to the decision time is used: the history holds samples recorded so far, and a
decision at time ``t`` reads nothing newer than ``t``.

The history is bounded: ``window_s`` of samples in ring buffers (inputs, readings, and the state
estimate at each sample, which gives the window its initial state). For the optimiser the window
is decimated by ``decimate`` (inputs averaged per step, currents as RMS), which is exact for
inputs held over each coarse step.
"""
from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.special import ndtr, stdtrit  # not scipy.stats: 0.7 s more at the service's import

from ..lptn import Model
from ..lptn.reduced import simulator_for
from ..settings import METHODS, AdapterConfig  # plain settings (edge.yaml adaptation:), read here
from .common import ParamSpace, Window, decimate, rms_inputs
from .gauss_newton import fit_gauss_newton
from .objective import Objective
from .pinned import fit_refine, pinned_step
from .screening import screen
from .shadow import ShadowObserver
from .sqp import fit_sqp
from .uncertainty import Uncertainty, estimate_uncertainty

#: how long before a challenger's fit its shadow observer and the champion's start (from the
#: recorded state), s: long enough for the filter to forget the state it starts from
SHADOW_LEAD_S = 1800.0
#: below the error threshold a refinement fit is triggered when the window alone (no prior) pins a
#: parameter down to PINNED_REL_STD (relative 1σ, residuals independent, all others free) and its
#: Gauss-Newton step in the pinned directions moves it by more than PINNED_OFFSET and PINNED_Z σ
PINNED_REL_STD = 0.02
PINNED_OFFSET = 0.05
PINNED_Z = 3.0
#: the refinement's Gauss-Newton step is taken in the directions pinned down to this relative 1σ
REFINE_STEP_REL_STD = 0.03
#: SQP iterations of a refinement fit (rare: only when the window says the optimum is far)
REFINE_MAX_ITER = 10
#: whole periods whose errors are kept for the judging of a challenger (a few kB each): as many as
#: two sets of parameters judged over the longest evidence
PERIOD_CACHE = 64
#: the pinned check runs again once this share of the window is new since the last check (or the
#: parameters in use changed): what a 3 h window pins moves little in one 3 min period, and each
#: check costs a window's sensitivities (at 1.7 % new data a decision, every sixth decision)
PINNED_RECHECK_SHARE = 0.1


@dataclass
class Decision:
    """One adapter decision, with its evidence.

    ``candidate_error_k`` and ``current_error_k`` are the RMS errors (K, seen sensors) of the
    challenger and the champion over the evidence recorded after the challenger's fit (NaN when
    no challenger was judged). ``params`` holds the promoted values when ``accepted``;
    ``challenger`` the values of a candidate fitted at this decision, to be judged later.
    """

    t: float
    error_before_k: float  # RMS over the last period with the current parameters, K
    triggered: bool = False
    horizon_error_k: float = float("nan")  # RMS open loop over the last validate_s with them, K
    accepted: bool = False
    candidate_error_k: float = float("nan")
    current_error_k: float = float("nan")
    selected: tuple[str, ...] = ()
    unidentifiable: tuple[str, ...] = ()
    params: dict[str, float] = field(default_factory=dict)
    iterations: int = 0
    evaluations: int = 0
    duration_s: float = 0.0
    reason: str = ""
    challenger: dict[str, float] = field(default_factory=dict)
    challenger_t: float = float("nan")  # when the judged challenger was fitted, s
    evidence_s: float = 0.0  # length of the evidence it was judged on, s
    improvement_k2: float = float("nan")  # champion MSE − challenger MSE over the evidence, K²
    margin_k2: float = float("nan")  # what the improvement had to exceed, K²
    #: what became of the judged challenger: "promoted", "dropped", "undecided" ("" if none was judged)
    verdict: str = ""
    #: why a judged challenger was dropped ("not better", "predicts housing worse", ...; "" otherwise)
    refusal: str = ""

    def as_dict(self) -> dict[str, object]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass
class Verdict:
    """A challenger judged against the champion on evidence neither was fitted to."""

    outcome: str  # "promote", "drop" or "wait"
    improvement_k2: float
    margin_k2: float
    champion_rms: dict[str, float]
    challenger_rms: dict[str, float]
    samples: int
    vetoed_by: tuple[str, ...] = ()  # the sensors that veto a promotion (see :func:`judge`)


def drop_cause(v: Verdict) -> str:
    """Why a dropped challenger was dropped, in a few words."""
    if v.vetoed_by:
        return f"predicts {', '.join(v.vetoed_by)} worse"
    return "not better" if np.isfinite(v.improvement_k2) else "never scored"


def verdict_reason(v: Verdict, evidence_s: float) -> str:
    """The log's words for a verdict on the ``evidence_s`` (s) recorded after the challenger's fit.
    Too few samples scored (both predictions finite: a state re-initialised after a model fault,
    readings missing) is said so, not as a NaN score.

    >>> verdict_reason(Verdict("wait", float("nan"), float("nan"), {}, {}, 1), 180.0)[:74]
    'challenger undecided on the 180 s after its fit: too few of them scored (1'
    """
    if np.isfinite(v.improvement_k2):
        ev = f"{evidence_s:g} s after its fit: MSE {v.improvement_k2:+.4g} K² vs margin {v.margin_k2:.3g} K²"
    else:
        ev = (f"{evidence_s:g} s after its fit: too few of them scored ({v.samples} with both predictions finite, 3 "
              "needed; a state re-initialised or readings missing)")
    if v.outcome == "promote":
        return f"challenger promoted: better on the {ev}"
    if v.outcome == "drop":
        return f"challenger dropped ({drop_cause(v)}) on the {ev}"
    if not np.isfinite(v.improvement_k2):
        return f"challenger undecided on the {ev}; waiting for the next period"
    wait = "one period: waiting for the next" if not np.isfinite(v.margin_k2) else f"margin {v.margin_k2:.3g} K²"
    return f"challenger undecided on the {evidence_s:g} s after its fit: MSE {v.improvement_k2:+.4g} K² vs {wait}"


def judge(champion: Mapping[str, np.ndarray], challenger: Mapping[str, np.ndarray], noise_k: float, z: float,
          min_gain: float, tolerance_k: float, share: float, blocks: np.ndarray | None = None) -> Verdict:
    """Compare two open-loop predictions' errors (K) per sensor over the same evidence samples.

    The statistic is the mean over the evidence of ``d_k``, the champion's minus the challenger's
    squared error averaged over the sensors reporting at sample ``k`` (K²). ``blocks`` labels the
    samples by the period they were predicted in (each period open loop from its own start);
    without it every sample is its own block. Three margins:

    * sensor noise: white noise of σ ``noise_k`` alone moves the mean by a standard error of
      ``2 σ rms(Δp) / √n`` (``d_k = Δp_k (p_k + p'_k − 2 y_k)`` with ``Δp`` the difference of the
      predictions, over all ``n`` readings); the improvement must exceed ``z`` of them;
    * consistency: the errors of a model that is not the machine are correlated in time, so the
      samples of one period are not independent evidence: the periods are. The improvement must
      exceed the standard error of the per-period means ``D_j`` (``std(D)/√m`` over ``m``
      periods) times Student's t quantile with ``m − 1`` degrees of freedom at the one-sided
      level of ``z`` (one period never promotes; two need a huge, three a large margin);
    * structure: the improvement must remove a share of the champion's mean squared error in
      excess of the sensor noise (``noise_k²``) that falls linearly from all of it, with no
      evidence, to ``min_gain`` when the full evidence is in (``share`` = evidence / full
      evidence = 1): a model that is not the machine has parameters that suit one operating point
      better than another, and gains on the next minutes are undone later unless they are
      overwhelming or persist. (Noise cannot be removed: a share of it would stop a model that
      is already the machine from ever being improved.)

    Promoted when all margins are met and no sensor vetoes it. A sensor vetoes when its RMS error
    grows by more than ``tolerance_k`` *and* ends above the champion's RMS error over all sensors:
    a model that is not yet the machine balances its errors over the sensors, so a challenger
    that removes most of the error of the windings may leave the housing, which the champion
    happened to predict better than the rest, a little worse; refusing that (a Pareto test)
    keeps every sensor at the champion's larger error. What is never accepted is a sensor left
    worse than the model in use predicts on average. Dropped as soon as the challenger is worse
    by the noise and consistency margins (or by the noise margin alone over a single period), or
    when the full evidence is in and it is not promoted; otherwise the verdict waits for more
    evidence.
    """
    final = share >= 1.0
    names = [s for s in champion if s in challenger]
    a = np.column_stack([champion[s] for s in names]) if names else np.zeros((0, 0))
    b = np.column_stack([challenger[s] for s in names]) if names else np.zeros((0, 0))
    ok = np.isfinite(a) & np.isfinite(b)
    a2, b2 = np.where(ok, a, 0.0) ** 2, np.where(ok, b, 0.0) ** 2
    rms = {}
    for j, s in enumerate(names):
        m = ok[:, j]
        rms[s] = (float(np.sqrt(np.mean(a2[m, j]))) if m.any() else float("nan"),
                  float(np.sqrt(np.mean(b2[m, j]))) if m.any() else float("nan"))
    cnt = ok.sum(axis=1) if a.size else np.zeros(0, dtype=int)
    rows = cnt > 0
    n = int(ok.sum())
    champ = {s: v[0] for s, v in rms.items()}
    chal = {s: v[1] for s, v in rms.items()}
    if rows.sum() < 3:
        return Verdict("drop" if final else "wait", float("nan"), float("nan"), champ, chal, int(rows.sum()))
    d = (a2 - b2).sum(axis=1)[rows] / cnt[rows]
    mean = float(d.mean())
    mse = float(np.mean(a2[ok]))
    dp = (a - b)[ok]
    noise = z * 2.0 * noise_k * float(np.sqrt(np.mean(dp**2) / n))
    labels = np.arange(len(d)) if blocks is None else np.asarray(blocks)[rows]
    per = np.array([d[labels == j].mean() for j in np.unique(labels)])
    if len(per) > 1:
        level = float(ndtr(z))  # the one-sided level of z, as Student's t quantile with m - 1 degrees of freedom
        spread = float(stdtrit(len(per) - 1, level) * per.std(ddof=1) / np.sqrt(len(per)))
    else:
        spread = np.inf
    gain = 1.0 - (1.0 - min_gain) * min(share, 1.0)
    margin = max(noise, spread, gain * max(mse - noise_k**2, 0.0))
    overall = float(np.sqrt(mse))
    vetoed = tuple(s for s, v in rms.items() if v[1] > v[0] + tolerance_k and v[1] > overall)
    if mean > margin and not vetoed:
        outcome = "promote"
    elif (len(per) > 1 and mean < -max(noise, spread)) or final:
        outcome = "drop"
    else:
        outcome = "wait"
    return Verdict(outcome, mean, margin, champ, chal, int(rows.sum()), vetoed)


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
        #: a whole period's errors by (parameters, start) (:meth:`_period_errors`)
        self._period_cache: dict[tuple[bytes, float], dict[str, np.ndarray]] = {}
        #: when the pinned check last ran, and with which parameters (:meth:`_pinned_due`)
        self._pinned_checked: tuple[float, bytes] | None = None
        self.prior = self.theta.copy()
        self.params = tuple(config.params or model.adaptable)
        self.sensors = tuple(config.sensors or model.sensors)
        self.sim = simulator_for(model)  # the reduced model above a node count, the exact dense one below
        self.history = History(model, self.sensors, int(round(config.window_s / dt)) + 1)
        self.decisions: list[Decision] = []
        self.version = 0
        self.last_decision_t: float | None = None
        self.challenger: tuple[float, np.ndarray] | None = None  # (fitted at, full parameters)
        #: where the optimiser resumes (values of ``params``; None: from the parameters in use)
        self.iterate: np.ndarray | None = None
        #: the champion's and the challenger's shadow observers while a challenger is judged
        self.shadows: tuple[ShadowObserver, ShadowObserver] | None = None
        #: after a promotion: the time of the last sample and the promoted parameters' observer
        #: estimate then (the state the service's observer continues from), °C
        self.promoted_state: tuple[float, np.ndarray] | None = None

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
        return Window(inputs, meas, T0, self.dt, t, rms_inputs(self.model))

    def _errors(self, theta: np.ndarray, since: float, until: float = np.inf,
                shadow: ShadowObserver | None = None) -> dict[str, np.ndarray]:
        """Per-sensor errors (K, NaN where not read) of the open-loop prediction from the recorded
        state at ``since`` (or ``shadow``'s estimate then; measured nodes at their readings) at the
        samples in ``(since, until]``."""
        win = self._window(since)
        T0 = win.T0
        if shadow is not None:
            T0 = shadow.state_at(win.t[0])
            for s in self.sensors:
                y = win.measured[s][0]
                if np.isfinite(y):
                    T0[self.model.node_index(self.model.sensors[s])] = y
        keep = win.t <= until
        traj = self.sim.simulate(theta, {c: v[keep] for c, v in win.inputs.items()}, win.dt, T0)
        t = win.t[keep]
        scored = t > t[0]
        return {s: (traj.node(self.model.sensors[s]) - win.measured[s][keep])[scored] for s in self.sensors}

    def _period_errors(self, theta: np.ndarray, since: float, until: float,
                       shadow: ShadowObserver | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """:meth:`_errors` period by period over ``(since, until]``: each ``period_s`` predicted
        open loop from the state at its start (``shadow``'s estimate, else the recorded one), as
        the online trace is scored. Also the period (0, 1, …) of every sample."""
        parts: list[dict[str, np.ndarray]] = []
        a = since
        key = theta.tobytes()
        while a < until - 1e-9:
            b = min(a + self.config.period_s, until)
            # a whole period's errors never change once recorded: a challenger judged at every
            # decision against the same parameters predicts only the new period
            whole = shadow is None and b == a + self.config.period_s
            part = self._period_cache.get((key, a)) if whole else None
            if part is None:
                part = self._errors(theta, a, b, shadow)
                if whole:
                    self._period_cache[(key, a)] = part
            parts.append(part)
            a = b
        while len(self._period_cache) > PERIOD_CACHE:
            self._period_cache.pop(next(iter(self._period_cache)))
        errors = {s: np.concatenate([p[s] for p in parts]) if parts else np.zeros(0) for s in self.sensors}
        blocks = np.concatenate([np.full(len(p[self.sensors[0]]), j) for j, p in enumerate(parts)]) if parts else np.zeros(0)
        return errors, blocks

    def recent_error(self, since: float) -> float:
        """RMS (K) over the seen sensors of the current parameters' open-loop prediction from the
        recorded state at ``since`` (measured nodes at their readings) against the readings after it."""
        e = np.concatenate([v[np.isfinite(v)] for v in self._errors(self.theta, since).values()])
        return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")

    def objective(self, window: Window, names: Sequence[str] | None = None, theta: np.ndarray | None = None) -> Objective:
        """The estimation objective over a window for the given parameters (default: all adaptable),
        the others held at ``theta`` (default: the parameters in use)."""
        names = tuple(names or self.params)
        space = ParamSpace(self.model, names, self.theta if theta is None else theta,
                           self.prior[self.model.parameter_index(names)])
        cfg = self.config
        return Objective(self.sim, space, window, list(self.sensors), cfg.weighting, cfg.prior_weight, cfg.tau_s)

    # -- the decision ------------------------------------------------------------------------
    def decide(self, t: float) -> Decision:
        """Judge a pending challenger on the data recorded since its fit, then, if none is
        pending and the last period's error or the open-loop error over the last ``validate_s``
        is above the threshold, fit a new challenger."""
        cfg = self.config
        t0 = time.perf_counter()
        self.last_decision_t = t
        err = self.recent_error(t - cfg.period_s)
        t_hist0 = float(self.history.arrays()[0][0]) if len(self.history) else t
        d = Decision(t=t, error_before_k=err, horizon_error_k=self.recent_error(max(t_hist0, t - cfg.validate_s)))
        above = bool(err > cfg.threshold_k or d.horizon_error_k > cfg.threshold_k)
        refine = False
        # (an infinite threshold means never adapt: the fixed baseline of a replay)
        if (not above and self.challenger is None and cfg.method == "sqp" and np.isfinite(cfg.threshold_k)
                and np.isfinite(err) and t - t_hist0 >= cfg.min_window_s and self._pinned_due(t, t - t_hist0)):
            self._pinned_checked = (t, self.theta.tobytes())
            name, off = self._pinned_offset(t)
            if name:
                above = refine = True
                d.reason = f"the window pins {name} {100 * off:+.1f} % from its value in use"
        d.triggered = above
        if self.challenger is not None:
            d.triggered = True
            self._judge(d, t)
            if self.challenger is not None:
                return self._done(d, t0)
        if not above:
            if not d.reason:
                d.reason = "error below threshold" if np.isfinite(err) else "no readings in the last period"
            return self._done(d, t0)
        t_hist = self.history.arrays()[0]
        if t - t_hist[0] < cfg.min_window_s:
            d.reason = self._also(d, f"waiting for {cfg.min_window_s:g} s of history before adapting")
            return self._done(d, t0)
        coarse = decimate(self._window(t - cfg.window_s), cfg.decimate)
        # The optimiser resumes from its last candidate unless that one was refuted: a fit capped
        # at max_iter iterations stops short of the window's optimum, and the next one would stop
        # at the same point if each restarted from the parameters in use, which change only on
        # out-of-sample evidence.
        start = self.theta.copy()
        if self.iterate is not None and not refine:
            start[self.model.parameter_index(self.params)] = self.iterate
        obj = self.objective(coarse, theta=start)
        phi = np.log(start[obj.space.index])
        ev = obj.evaluate(phi)
        unc = estimate_uncertainty(obj, ev, cfg.max_rel_std)
        d.unidentifiable = tuple(n for n, ok in zip(obj.space.names, unc.identifiable) if not ok)
        if not unc.identifiable.any():
            d.reason = self._also(d, "the window identifies no adaptable parameter yet (Fisher information)")
            return self._done(d, t0)
        sc = screen(obj.space.names, ev.grad, ev.hess, phi, obj.space.lower, obj.space.upper, cfg.coverage,
                    unc.identifiable)
        d.selected = sc.selected
        if not sc.selected:
            d.reason = self._also(d, "no identifiable parameter can reduce the error within its bounds")
            return self._done(d, t0)
        sub = self.objective(coarse, sc.selected, theta=start)
        if refine:
            res = fit_refine(sub, max(cfg.max_iter, REFINE_MAX_ITER), REFINE_STEP_REL_STD)
        elif cfg.method == "gauss_newton":
            res = fit_gauss_newton(sub, max_iter=cfg.max_iter + 1)
        else:
            res = fit_sqp(sub, max_iter=cfg.max_iter, gradient="numerical" if cfg.method == "numerical" else "analytic")
        d.iterations, d.evaluations = res.iterations, d.evaluations + res.evaluations
        cand = start.copy()
        cand[sub.space.index] = np.clip(res.values, sub.space.lower, sub.space.upper)  # exp(log(bound)) rounds past it
        if np.array_equal(cand, start) or np.array_equal(cand, self.theta):
            d.reason = self._also(d, "the optimiser found no better parameters on the window")
            self.iterate = None
            return self._done(d, t0)
        d.challenger = dict(zip(sc.selected, map(float, res.values)))
        self.challenger = (t, cand)
        self.shadows = self._start_shadows(t, cand) if refine else None
        self.iterate = cand[self.model.parameter_index(self.params)].copy()
        d.reason = self._also(d, "challenger fitted; it is judged on the data that follows")
        return self._done(d, t0)

    def _pinned_due(self, t: float, history_s: float) -> bool:
        """Whether the pinned check runs at ``t``: never run, other parameters in use since, or
        :data:`PINNED_RECHECK_SHARE` of the window (``history_s`` of history, s) new since."""
        if self._pinned_checked is None:
            return True
        t_last, theta = self._pinned_checked
        new = min(self.config.window_s, history_s) * PINNED_RECHECK_SHARE
        return theta != self.theta.tobytes() or t - t_last >= new - 1e-9

    def _pinned_offset(self, t: float) -> tuple[str, float]:
        """The adaptable parameter that the history window alone (no prior) pins down (see
        :data:`PINNED_REL_STD`) and its pinned Gauss-Newton step moves most by more than
        :data:`PINNED_OFFSET` and :data:`PINNED_Z` of its 1σ, and by how much (relative, log);
        ``("", 0.0)`` if none."""
        cfg = self.config
        obj = self.objective(decimate(self._window(t - cfg.window_s), cfg.decimate))
        obj.prior_weight = 0.0  # what the window says, not the prior (which pins every parameter a little)
        ev = obj.evaluate(np.log(self.theta[obj.space.index]))
        step, sigma = pinned_step(obj, ev, PINNED_REL_STD)
        off = np.where((sigma <= PINNED_REL_STD) & (np.abs(step) > np.maximum(PINNED_OFFSET, PINNED_Z * sigma)), step, 0.0)
        j = int(np.argmax(np.abs(off)))
        return (obj.space.names[j], float(off[j])) if off[j] else ("", 0.0)

    @staticmethod
    def _also(d: Decision, why: str) -> str:
        return f"{d.reason}; {why}" if d.reason else why

    def _start_shadows(self, t: float, cand: np.ndarray) -> tuple[ShadowObserver, ShadowObserver]:
        """The champion's and the challenger's shadow observers, started :data:`SHADOW_LEAD_S`
        before ``t`` (or at the oldest sample) from the recorded state there and followed to ``t``."""
        th, inputs, meas, states = self.history.arrays(t - SHADOW_LEAD_S)
        out = []
        for theta in (self.theta, cand):
            sh = ShadowObserver(self.model, theta, self.dt, float(th[0]), states[0],
                                {c: float(v[0]) for c, v in inputs.items()})
            sh.follow(th, inputs, meas)
            out.append(sh)
        return out[0], out[1]

    def _judge(self, d: Decision, t: float) -> None:
        """Judge the pending challenger on the samples recorded after its fit, period by period open
        loop: a refinement's challenger and the champion each from the estimate of their own
        shadow observer at the period's start, any other from the recorded state."""
        cfg = self.config
        assert self.challenger is not None
        t_fit, cand = self.challenger
        shadows = self.shadows
        if shadows is not None:
            th, inputs, meas, _ = self.history.arrays(shadows[0].t)
            for sh in shadows:
                sh.follow(th, inputs, meas)
        t_last = float(self.history.arrays(t_fit)[0][-1])
        d.challenger_t, d.evidence_s = t_fit, t_last - t_fit
        sh_champ, sh_chal = shadows if shadows is not None else (None, None)
        (champ, blocks), (chal, _) = (self._period_errors(self.theta, t_fit, t_last, sh_champ),
                                      self._period_errors(cand, t_fit, t_last, sh_chal))
        d.evaluations += 2
        v = judge(champ, chal, cfg.noise_k, cfg.promote_z, cfg.min_gain, cfg.sensor_tolerance_k,
                  share=d.evidence_s / cfg.validate_s + 1e-9, blocks=blocks)
        d.improvement_k2, d.margin_k2 = v.improvement_k2, v.margin_k2
        e_cur = np.concatenate([e[np.isfinite(e)] for e in champ.values()]) if champ else np.zeros(0)
        e_new = np.concatenate([e[np.isfinite(e)] for e in chal.values()]) if chal else np.zeros(0)
        d.current_error_k = float(np.sqrt(np.mean(e_cur**2))) if len(e_cur) else float("nan")
        d.candidate_error_k = float(np.sqrt(np.mean(e_new**2))) if len(e_new) else float("nan")
        names = self.params
        vals = dict(zip(names, map(float, cand[self.model.parameter_index(names)])))
        if v.outcome == "promote":
            self.promoted_state = (t_last, sh_chal.state_at(t_last)) if sh_chal is not None else None
            self.theta = cand
            self.version += 1
            self.challenger = None
            self.shadows = None
            self.iterate = None
            d.accepted = True
            d.params = vals
            d.verdict = "promoted"
            d.reason = verdict_reason(v, d.evidence_s)
        elif v.outcome == "drop":
            self.challenger = None
            self.shadows = None
            if v.improvement_k2 < 0:  # refuted: the search restarts from the parameters in use
                self.iterate = None
            d.verdict, d.refusal = "dropped", drop_cause(v)
            d.reason = verdict_reason(v, d.evidence_s)
        else:
            d.verdict = "undecided"
            d.reason = verdict_reason(v, d.evidence_s)

    def _done(self, d: Decision, t0: float) -> Decision:
        d.duration_s = time.perf_counter() - t0
        self.decisions.append(d)
        return d

    def replayed_state(self, since: float) -> tuple[np.ndarray, float]:
        """The node temperatures the present parameters give at the last recorded sample.

        Parameters
        ----------
        since : float
            Start of the replay, s: the recorded state there (measured nodes at their readings)
            is simulated open loop over the recorded inputs.

        Returns
        -------
        T : ndarray
            Node temperatures, °C, at the last sample (what a service restarts its state from
            once it accepts these parameters).
        t : float
            Time of that sample, s.
        """
        win = self._window(since)
        traj = self.sim.simulate(self.theta, win.inputs, win.dt, win.T0)
        return traj.T[-1].copy(), float(win.t[-1])

    def current_uncertainty(self, since: float | None = None) -> Uncertainty:
        """Parameter covariance and identifiability at the current parameters over the history
        since ``since`` (s; default all of it), judged by the same ``max_rel_std`` as the gate of
        :meth:`decide`: what is reported as identifiable is what the adapter may adapt."""
        cfg = self.config
        win = decimate(self._window(-np.inf if since is None else since), cfg.decimate)
        obj = self.objective(win)
        ev = obj.evaluate(np.log(self.theta[obj.space.index]))
        return estimate_uncertainty(obj, ev, cfg.max_rel_std)

    def params_dict(self) -> dict[str, float]:
        """Current values of the adaptable parameters."""
        return {n: float(self.theta[i]) for n, i in zip(self.params, self.model.parameter_index(self.params))}
