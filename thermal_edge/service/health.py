"""Health of the inputs and of the model: which reasons force the safe limit this tick.

- the inputs (:class:`.inputs.TickInputs`): a stale frame forces ``stale_input``, a faulty required
  sensor ``sensor_fault``;
- the model (:class:`ModelHealth`): diverged when its state is not finite, when an innovation
  (reading minus the observer's prediction) stays above ``derating.faults.innovation_k`` for
  ``innovation_ticks`` ticks, or when the open-loop prediction error exceeds
  ``prediction_error_k`` for ``prediction_error_ticks`` ticks; a fault forces ``model_fault`` for
  ``hold_s``, doubled for each fault that recurs within ``repeat_s`` after the previous hold ended
  (up to ``hold_max_s``): a cause that persists does not get full power back after every hold. It also keeps the window of squared
  open-loop prediction errors over the adaptation period, whose RMS is ``TE_PredErrRms``;
- the readings against the commissioned model (:class:`CommissionedCheck`): readings that fall more
  than ``commissioned_gap_k`` below the model file's own open-loop prediction for
  ``prediction_error_ticks`` ticks are not believed (``model_fault``) until they come back within
  half of it;
- the sensors' plausibility over time (:class:`StuckSensors`): a reading that sits still while the
  model, stepped with the measured losses, heats its node by several kelvin is stuck (frozen), a
  sensor fault (kind ``stuck``) until the reading moves again.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Iterable, Mapping

from ..bus.frames import DerateReason
from ..config import FaultConfig
from .inputs import TickInputs
from .journal import notice

__all__ = ["CommissionedCheck", "ModelHealth", "StuckSensors", "input_reasons"]

log = logging.getLogger(__name__)


def input_reasons(ti: TickInputs) -> list[DerateReason]:
    """The reasons the inputs of a tick force (stale frames, then faulty sensors)."""
    out: list[DerateReason] = []
    if ti.stale:
        out.append(DerateReason.STALE_INPUT)
    if ti.faults:
        out.append(DerateReason.SENSOR_FAULT)
    return out


class ModelHealth:
    """Fault detection on the model and the window of its prediction errors.

    Parameters
    ----------
    config : FaultConfig
        ``derating.faults``: thresholds and the hold time.
    window_s : float
        Span of the prediction-error window (the adaptation period), s.
    """

    def __init__(self, config: FaultConfig, window_s: float) -> None:
        self.config = config
        self.window_s = float(window_s)
        self._window: deque[tuple[float, float]] = deque()  # (t, squared error)
        self._sum = 0.0
        self._innovation_ticks = self._prediction_ticks = 0
        self._fault_until = -math.inf
        self._faults = 0
        self._repeats = 0  # faults in a row, each within repeat_s of the previous hold's end

    # -- read-only views -------------------------------------------------------------------------
    @property
    def faults(self) -> int:
        """Times the model was found diverged or a tick failed."""
        return self._faults

    def holding(self, t: float) -> bool:
        """True while a fault's hold (``hold_s``) lasts at ``t``."""
        return t < self._fault_until

    @property
    def rms_error(self) -> float:
        """RMS open-loop prediction error over the window, K (NaN with no reading in it)."""
        n = len(self._window)
        return math.sqrt(self._sum / n) if n > 0 and self._sum >= 0 else math.nan

    # -- updates ----------------------------------------------------------------------------------
    def judge(self, t: float, innovations: Iterable[float], pred_error: Mapping[str, float], finite: bool) -> str | None:
        """Record this tick's errors; returns why the model diverged (None: it did not).

        Parameters
        ----------
        t : float
            Tick time, s.
        innovations : iterable of float
            Absolute innovations of the sensors with a reading, K.
        pred_error : mapping of str to float
            Open-loop prediction minus reading per sensor, K.
        finite : bool
            Whether the observer's state, its covariance and the open-loop state are finite.
        """
        for e in pred_error.values():
            self._window.append((t, e * e))
            self._sum += e * e
        while self._window and self._window[0][0] <= t - self.window_s:
            self._sum -= self._window.popleft()[1]
        fc = self.config
        innov = list(innovations)
        self._innovation_ticks = self._innovation_ticks + 1 if innov and max(innov) > fc.innovation_k else 0
        if not finite:
            return "non-finite state"
        if self._innovation_ticks >= fc.innovation_ticks:
            return f"innovation above {fc.innovation_k:.0f} K for {fc.innovation_ticks} ticks"
        off = any(abs(e) > fc.prediction_error_k for e in pred_error.values())
        self._prediction_ticks = self._prediction_ticks + 1 if off else 0
        if self._prediction_ticks >= fc.prediction_error_ticks:
            return f"open-loop prediction error above {fc.prediction_error_k:.0f} K for {self._prediction_ticks} ticks"
        return None

    @property
    def disagreeing(self) -> bool:
        """The open-loop prediction error is above ``prediction_error_k`` this tick, not yet for
        ``prediction_error_ticks`` in a row: the estimate is not trusted (a glitch or a fault to come)."""
        return self._prediction_ticks > 0

    def fault(self, t: float) -> float:
        """A model fault at ``t``: count it and hold the safe limit; returns the hold, s.

        The hold is ``hold_s``, doubled for each fault in a row that came within ``repeat_s`` after
        the previous hold ended (up to ``hold_max_s``): the state restarts from the readings after
        each fault, so a cause that persists (a reading the model cannot follow) faults again after
        the same time at full power; a longer hold each time keeps the mean current near the safe
        limit instead of handing full power back for most of every cycle.
        """
        fc = self.config
        self._faults += 1
        self._repeats = self._repeats + 1 if t <= self._fault_until + fc.repeat_s else 0
        hold = min(fc.hold_s * 2.0 ** self._repeats, max(fc.hold_max_s, fc.hold_s))
        self._fault_until = t + hold
        return hold

    def restart(self) -> None:
        """The state was re-initialised: the errors of the old one no longer count."""
        self._window.clear()
        self._sum = 0.0
        self._innovation_ticks = self._prediction_ticks = 0

    def new_state(self) -> None:
        """A fresh state (first initialisation): innovations count from zero, the window is kept."""
        self._innovation_ticks = self._prediction_ticks = 0


class CommissionedCheck:
    """Readings far below the commissioned model's prediction: not believed until they agree again.

    The adaptation follows the readings, and a restart after a model fault starts from them: a drift
    common to every PT100 (one excitation current or ADC reference in the inverter, an offset
    flashed into it) that reads low slowly enough passes every check made against them, and the
    machine gets full current while it runs hot. The commissioned prediction (the model file's
    parameters on open loop, :meth:`.estimate.StateEstimate.commissioned_gap`) follows neither.
    Only readings *below* it count: above it, believing them costs headroom, not safety.

    Parameters
    ----------
    config : FaultConfig
        ``derating.faults``: ``commissioned_gap_k`` (K) and ``prediction_error_ticks``.
    """

    def __init__(self, config: FaultConfig) -> None:
        self.config = config
        self._ticks = 0
        self._active = False
        self._count = 0
        #: the last gap measured: (sensor, K below the commissioned prediction)
        self.gap: tuple[str, float] | None = None

    @property
    def active(self) -> bool:
        """The readings are not believed now."""
        return self._active

    @property
    def count(self) -> int:
        """Times the readings fell below the commissioned prediction and were not believed."""
        return self._count

    def judge(self, t: float, gap: tuple[str, float] | None) -> bool:
        """Record this tick's gap (sensor and K below the commissioned prediction; None: no
        reading); returns whether the readings are not believed. Logs the start at ERROR and the
        end at NOTICE."""
        fc = self.config
        if gap is None:  # no reading: nothing changes
            return self._active
        self.gap = gap
        sensor, k = gap
        if self._active:
            if k <= fc.commissioned_gap_k / 2.0:
                self._active = False
                self._ticks = 0
                notice(log, "the readings agree again with the commissioned model (%s %.1f K below its "
                       "prediction): trusted", sensor, k)
            return self._active
        self._ticks = self._ticks + 1 if k > fc.commissioned_gap_k else 0
        if self._ticks >= fc.prediction_error_ticks:
            self._active = True
            self._count += 1
            log.error("readings not believed at t=%.0f: %s reads %.1f K below the commissioned model's prediction "
                      "(more than %.0f K for %d ticks): a drift common to the PT100s, or a machine that cools far "
                      "better than its model file says (recalibrate it); safe limit, and no estimate published below that "
                      "prediction, until within %.0f K",
                      t, sensor, k, fc.commissioned_gap_k, self._ticks, fc.commissioned_gap_k / 2.0)
        return self._active


class StuckSensors:
    """A sensor whose reading sits still while the model says its node moved: stuck (frozen).

    A healthy PT100 at a steady state sits still too, but then the model predicts no change either.
    Per sensor with a reading: the latest stretch (within the last ``stuck_window_s``) over which the
    readings stayed within ``stuck_still_k``, and the model's path of the sensor's node over it (the
    sum of the open-loop prediction's one-step changes with the tick's measured losses: a change the
    losses drive, not a restart or new parameters). A path that *rose* ``stuck_model_k`` or more
    over such a stretch latches the sensor as stuck; it stays stuck (its reading withheld, a sensor
    fault if it is required) until the reading leaves the value it froze at by more than
    ``stuck_still_k``.

    Only a rise is evidence. A reading that stands still while its node heats reads cold, which is
    the danger; one that stands still while the model's node cools reads hot, which costs headroom
    and nothing else, and withholding it would hide a hot machine: a winding PT100 stepping to
    170 °C restarts the model from that reading, the model's node relaxes 8 K towards its cooler
    neighbours in a second, and were the reading then withheld as stuck, the hot spot's band would
    sit at 54 °C and the limit at 9.5 A.

    Parameters
    ----------
    config : FaultConfig
        ``derating.faults``: ``stuck_window_s`` (s), ``stuck_model_k`` and ``stuck_still_k`` (K).
        ``stuck_still_k`` is two steps of the reading's resolution, judged on the reading's mean over
        ``stuck_smooth_s`` (:meth:`smooth`): a frozen reading may flicker by a
        step; a reading with a coarser resolution needs a larger one.
    sensors : iterable of str
        The sensors to watch.
    """

    def __init__(self, config: FaultConfig, sensors: Iterable[str]) -> None:
        self.config = config
        #: per sensor: the still stretch of its readings and of their mean
        self._runs: dict[str, tuple[_StillRun, _StillRun]] = {s: (_StillRun(), _StillRun()) for s in sensors}
        self._frozen: dict[str, float] = {}  # stuck sensor -> the reading (or mean) it froze at, degC
        self._on_mean: dict[str, bool] = {}  # stuck sensor -> found on its mean (else on its readings)
        self._mean: dict[str, tuple[float, float]] = {}  # sensor -> (time, exponential mean of its readings)

    def smooth(self, t: float, readings: Mapping[str, float]) -> dict[str, float]:
        """The readings of the tick at ``t`` averaged over ``stuck_smooth_s`` (an exponential mean,
        degC; NaN where a sensor has no reading, which restarts its mean): what :meth:`release` and
        :meth:`observe` judge. A frozen channel still carries its converter's noise; the mean of a
        healthy reading that rises keeps rising."""
        tau = self.config.stuck_smooth_s
        out: dict[str, float] = {}
        for s, v in readings.items():
            prev = self._mean.get(s)
            if not math.isfinite(v) or tau <= 0.0:
                self._mean.pop(s, None)
                out[s] = v
                continue
            m = v if prev is None else prev[1] + (1.0 - math.exp(-max(t - prev[0], 0.0) / tau)) * (v - prev[1])
            self._mean[s] = (t, m)
            out[s] = m
        return out

    @property
    def stuck(self) -> dict[str, float]:
        """The sensors found stuck, with the reading each froze at (degC)."""
        return dict(self._frozen)

    def release(self, readings: Mapping[str, float], means: Mapping[str, float] | None = None) -> list[str]:
        """Release the stuck sensors whose reading (or, found stuck on it, whose mean, :meth:`smooth`)
        moved by more than ``stuck_still_k`` (or has none now: the input's own fault or staleness
        speaks for it); returns them."""
        out = []
        for s, v0 in list(self._frozen.items()):
            v = (means if means is not None and self._on_mean.get(s) else readings).get(s, math.nan)
            if not math.isfinite(v) or abs(v - v0) > self.config.stuck_still_k:
                del self._frozen[s]
                self._on_mean.pop(s, None)
                for run in self._runs[s]:
                    run.clear()
                out.append(s)
        return out

    def observe(self, t: float, readings: Mapping[str, float], moved: Mapping[str, float],
                means: Mapping[str, float] | None = None) -> dict[str, str]:
        """Record a tick; returns the sensors newly found stuck, each with the evidence (a sentence).

        Parameters
        ----------
        t : float
            Tick time, s.
        readings : mapping of str to float
            Sensor -> reading of the tick, degC (NaN: none; the sensor's history restarts).
        moved : mapping of str to float
            Sensor -> the open-loop prediction's one-step change of its node this tick, K.
        means : mapping of str to float, optional
            Sensor -> the readings' mean (:meth:`smooth`), degC: judged beside the readings, so that
            a frozen channel with noise is found as well as an exactly frozen one, which the
            readings themselves show without the mean's lag. Default: the readings.
        """
        fc = self.config
        new: dict[str, str] = {}
        means = readings if means is None else means
        for s, runs in self._runs.items():
            if s in self._frozen:
                continue
            d = moved.get(s, math.nan)
            for on_mean, run, v in zip((False, True), runs, (readings.get(s, math.nan), means.get(s, math.nan))):
                if not (math.isfinite(v) and math.isfinite(d)):
                    run.clear()
                    continue
                run.add(t, v, d, fc.stuck_still_k, t - fc.stuck_window_s)
                rise_k = run.path - run.p_min.value
                if rise_k >= fc.stuck_model_k and s not in self._frozen:
                    self._frozen[s], self._on_mean[s] = v, on_mean
                    what = "mean reading" if on_mean else "reading"
                    new[s] = (f"{what} within {run.v_max.value - run.v_min.value:.1f} K at {v:.1f} degC for "
                              f"{t - run.since:.0f} s while the model heated its node {rise_k:.1f} K with the measured losses")
        return new

    def restart(self) -> None:
        """A gap in the data: the histories no longer describe one stretch of time."""
        for runs in self._runs.values():
            for run in runs:
                run.clear()
        self._mean.clear()


class _Extreme:
    """Running min or max over a sliding stretch (monotonic deque of (sequence number, value))."""

    __slots__ = ("q", "sign")

    def __init__(self, sign: float) -> None:
        self.q: deque[tuple[int, float]] = deque()
        self.sign = sign  # +1: max, -1: min

    @property
    def value(self) -> float:
        return self.q[0][1]

    def push(self, n: int, x: float) -> None:
        while self.q and self.sign * self.q[-1][1] <= self.sign * x:
            self.q.pop()
        self.q.append((n, x))

    def drop_before(self, n: int) -> None:
        while self.q and self.q[0][0] < n:
            self.q.popleft()


class _StillRun:
    """The latest stretch of one sensor's ticks over which its reading stayed within a band, with the
    extremes of the reading and the lowest point of the model's path (cumulative one-step change)
    over it: amortised O(1) a tick (the stretch that ends at the next tick starts no earlier than
    this one)."""

    def __init__(self) -> None:
        self.ts: deque[float] = deque()
        self.v_min, self.v_max, self.p_min = _Extreme(-1), _Extreme(1), _Extreme(-1)
        self.path = 0.0
        self.n = 0  # sequence number of the next tick
        self.first = 0  # sequence number of the stretch's first tick

    @property
    def since(self) -> float:
        """Time of the stretch's first tick, s."""
        return self.ts[0]

    def add(self, t: float, v: float, d: float, band: float, not_before: float) -> None:
        """A tick at ``t`` with reading ``v`` and the model's one-step change ``d``; the stretch keeps
        its ticks after ``not_before`` over which the reading stays within ``band``."""
        self.path += d
        for e, x in ((self.v_min, v), (self.v_max, v), (self.p_min, self.path)):
            e.push(self.n, x)
        self.ts.append(t)
        self.n += 1
        while self.ts[0] <= not_before or self.v_max.value - self.v_min.value > band:
            self.ts.popleft()
            self.first += 1
            for e in (self.v_min, self.v_max, self.p_min):
                e.drop_before(self.first)

    def clear(self) -> None:
        self.ts.clear()
        for e in (self.v_min, self.v_max, self.p_min):
            e.q.clear()
        self.path = 0.0
        self.first = self.n
