"""The online adapter, run beside the tick so that ticks stay on time.

:class:`AdaptationWorker` owns one :class:`~thermal_edge.estimation.adapter.OnlineAdapter` and
serialises everything done to it: samples recorded and decisions requested are commands in one
FIFO, executed in order by a worker thread (``mode="thread"``) or at once (``mode="sync"``, for
replays and tests). A decision therefore sees exactly the samples recorded before it was
requested, wherever and however long it runs, and the same log replayed gives the same decisions.

:class:`Adaptation` is the service's side: the parameters in use, when a decision is due and when
its result is applied, the counters and the bounded list of decisions.

For an accepted decision the worker also re-derives the open-loop state at the last recorded
sample with the new parameters (simulating the history window, as the paper's §5.1 and
:func:`thermal_edge.estimation.online.run_online` do) and, if asked, the parameters' 95 % bands
from the Fisher information.
"""
from __future__ import annotations

import asyncio
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..config import AdaptationConfig
from ..estimation.adapter import AdapterConfig, Decision, OnlineAdapter
from ..estimation.uncertainty import Z95
from ..lptn import Model, Stepper
from .memory import release_free_heap

__all__ = ["ADAPT_STATUSES", "Adaptation", "AdaptationCounts", "AdaptationResult", "AdaptationWorker", "decision_status"]

#: what the adaptation is doing, after its last decision (the operator's view: /metrics, monitor, demo):
#: ``off`` adaptation disabled; ``starting`` no decision yet; ``fits`` the model predicts the last
#: period within the threshold; ``waiting_for_data`` the history cannot identify anything yet;
#: ``waiting_for_evidence`` a challenger is being judged on the data after its fit; ``learning`` a
#: challenger was just promoted; ``refusing`` the last judged challenger was dropped
ADAPT_STATUSES = ("off", "starting", "fits", "waiting_for_data", "waiting_for_evidence", "learning", "refusing")


def decision_status(decision: Mapping[str, Any]) -> str:
    """The :data:`ADAPT_STATUSES` value a decision (as recorded: :meth:`Decision.as_dict`) leaves."""
    verdict = decision.get("verdict") or ""
    if verdict == "promoted" or decision.get("accepted"):
        return "learning"
    if verdict == "dropped":
        return "refusing"
    if verdict == "undecided" or decision.get("challenger"):
        return "waiting_for_evidence"
    if not decision.get("triggered"):
        return "fits"
    return "waiting_for_data"

log = logging.getLogger(__name__)


@dataclass
class AdaptationResult:
    """Outcome of one requested decision."""

    request_id: int
    t: float
    decision: Decision | None = None
    theta: np.ndarray | None = None  # full parameter vector after the decision
    version: int = 0
    state_t: float | None = None  # time of the last recorded sample
    state: np.ndarray | None = None  # open-loop state at state_t with the new parameters (accepted only)
    #: the observer's estimate at state_t with the new parameters (accepted only): the shadow
    #: observer's the challenger was judged from
    estimate: np.ndarray | None = None
    bands: dict[str, tuple[float, float]] = field(default_factory=dict)
    identifiable: dict[str, bool] = field(default_factory=dict)
    error: str | None = None
    wall_s: float = 0.0

    @property
    def accepted(self) -> bool:
        return self.decision is not None and self.decision.accepted

    def state_now(self, stepper: Stepper, recent: Iterable[tuple[float, Mapping[str, float]]],
                  which: str = "state") -> np.ndarray | None:
        """The open-loop state with the new parameters now (°C), derived once: the state at the end
        of the decision's window (``state_t``, simulated by the worker), stepped by ``stepper`` (the
        new parameters) over the inputs of the samples recorded since. None without a state or if
        it is not finite. ``which="estimate"``: the same for :attr:`estimate`."""
        x0 = self.estimate if which == "estimate" else self.state
        if x0 is None or self.state_t is None:
            return None
        x = x0.copy()
        for ts, u in recent:
            if ts + 1e-9 >= self.state_t:
                x, _ = stepper.step(x, dict(u))
        return x if np.all(np.isfinite(x)) else None


class AdaptationWorker:
    """Serialised access to the online adapter.

    Parameters
    ----------
    model : Model
    config : AdapterConfig
    dt : float
        Sample period (the tick), s.
    theta : ndarray
        Starting parameters (e.g. restored from the state file).
    prior : ndarray
        Offline parameter values (the MAP prior), normally the model file's.
    mode : {"thread", "sync"}
    bands : bool
        Compute parameter bands after accepted decisions.
    """

    def __init__(self, model: Model, config: AdapterConfig, dt: float, theta: np.ndarray, prior: np.ndarray,
                 mode: str = "thread", bands: bool = True) -> None:
        if mode not in ("thread", "sync"):
            raise ValueError(f"adaptation worker mode must be thread or sync, got {mode!r}")
        self.model, self.config, self.dt = model, config, float(dt)
        self.mode = mode
        self.bands = bands
        self.prior = np.asarray(prior, dtype=float).copy()
        self.adapter = self._new_adapter(np.asarray(theta, dtype=float))
        self.params = self.adapter.params
        self._ids = 0
        self._results: dict[int, AdaptationResult] = {}
        self._cond = threading.Condition()
        self._pending: set[int] = set()
        self._queue: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        if mode == "thread":
            self._thread = threading.Thread(target=self._loop, name="thermal-edge adapter", daemon=True)
            self._thread.start()

    def _new_adapter(self, theta: np.ndarray) -> OnlineAdapter:
        ad = OnlineAdapter(self.model, self.config, self.dt, theta)
        ad.prior = self.prior.copy()
        return ad

    # -- commands (called from the tick) ----------------------------------------------------------
    def record(self, t: float, inputs: Mapping[str, float], measured: Mapping[str, float], state: np.ndarray) -> None:
        cmd = ("record", float(t), dict(inputs), dict(measured), np.array(state, dtype=float))
        self._submit(cmd)

    def reset(self, theta: np.ndarray) -> None:
        """Forget the history (after a gap in the data); keep the parameters."""
        self._submit(("reset", np.array(theta, dtype=float)))

    def request(self, t: float) -> int:
        """Ask for a decision at time ``t`` (over the samples recorded so far); returns its id."""
        self._ids += 1
        rid = self._ids
        with self._cond:
            self._pending.add(rid)
        self._submit(("decide", float(t), rid))
        return rid

    @property
    def busy(self) -> bool:
        with self._cond:
            return bool(self._pending)

    def _submit(self, cmd: tuple[Any, ...]) -> None:
        if self.mode == "sync":
            self._execute(cmd)
        else:
            self._queue.put(cmd)

    # -- results --------------------------------------------------------------------------------
    def result(self, rid: int) -> AdaptationResult | None:
        with self._cond:
            return self._results.get(rid)

    def wait(self, rid: int, timeout: float | None = None) -> AdaptationResult | None:
        """Block until decision ``rid`` is done (None on timeout)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while rid not in self._results:
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._results[rid]

    async def wait_async(self, rid: int, timeout: float | None = None) -> AdaptationResult | None:
        """Await decision ``rid`` without blocking the event loop."""
        res = self.result(rid)
        if res is not None:
            return res
        return await asyncio.get_running_loop().run_in_executor(None, self.wait, rid, timeout)

    def forget(self, rid: int) -> None:
        with self._cond:
            self._results.pop(rid, None)

    def close(self, timeout: float = 5.0) -> None:
        """Stop the worker thread (a decision in progress is abandoned after ``timeout``)."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout)
            self._thread = None

    # -- worker side ----------------------------------------------------------------------------
    def _loop(self) -> None:
        while True:
            cmd = self._queue.get()
            if cmd is None:
                return
            self._execute(cmd)

    def _execute(self, cmd: tuple[Any, ...]) -> None:
        kind = cmd[0]
        try:
            if kind == "record":
                _, t, inputs, measured, state = cmd
                self.adapter.record(t, inputs, measured, state)
            elif kind == "reset":
                self.adapter = self._new_adapter(cmd[1])
            elif kind == "decide":
                _, t, rid = cmd
                self._finish(self._decide(t, rid))
                release_free_heap()  # the decision's temporaries (thermal_edge.service.memory)
        except Exception as exc:  # a failed command must never kill the worker
            log.exception("adaptation %s failed", kind)
            if kind == "decide":
                self._finish(AdaptationResult(cmd[2], cmd[1], theta=self.adapter.theta.copy(),
                                              version=self.adapter.version, error=f"{type(exc).__name__}: {exc}"))

    def _decide(self, t: float, rid: int) -> AdaptationResult:
        ad = self.adapter
        t0 = time.perf_counter()
        if len(ad.history) < 2:
            return AdaptationResult(rid, t, theta=ad.theta.copy(), version=ad.version, error="no history yet")
        theta_before = ad.theta.copy()
        try:
            d = ad.decide(t)
        except Exception:
            ad.theta = theta_before  # never keep a half-applied candidate
            raise
        if len(ad.decisions) > 100:  # the service keeps its own bounded history of decisions
            del ad.decisions[:-100]
        res = AdaptationResult(rid, t, decision=d, theta=ad.theta.copy(), version=ad.version)
        if d.accepted:
            x, x_t = ad.replayed_state(t - self.config.window_s)
            if np.all(np.isfinite(x)):
                res.state, res.state_t = x, x_t
                shadow = ad.promoted_state
                if shadow is not None and shadow[0] == x_t and np.all(np.isfinite(shadow[1])):
                    res.estimate = shadow[1].copy()
            if self.bands:
                try:
                    unc = ad.current_uncertainty(t - self.config.window_s)
                    vals = ad.params_dict()
                    for name, rel, ok in zip(unc.names, unc.rel_std, unc.identifiable):
                        v = vals.get(name, math.nan)
                        res.bands[name] = (v * math.exp(-Z95 * rel), v * math.exp(Z95 * rel))
                        res.identifiable[name] = bool(ok)
                except Exception as exc:  # bands are informative only
                    log.warning("parameter bands not computed: %s", exc)
        res.wall_s = time.perf_counter() - t0
        return res

    def _finish(self, res: AdaptationResult) -> None:
        with self._cond:
            self._results[res.request_id] = res
            self._pending.discard(res.request_id)
            self._cond.notify_all()


@dataclass
class AdaptationCounts:
    """What the adaptation has done so far (read as a copy, :attr:`Adaptation.counts`)."""

    version: int = 0  #: accepted parameter sets (TE_ParamVersion)
    runs: int = 0  #: adaptations run (triggered and optimised)
    accepted: int = 0
    rejected: int = 0  #: rolled back
    failures: int = 0  #: decisions that failed with an error
    skipped: int = 0  #: triggered decisions that could not optimise yet


class Adaptation:
    """The parameters in use and the decisions that change them, one tick at a time.

    A decision is requested every ``adapter.period_s`` of recorded samples; with the frame clock
    its result is applied exactly ``apply_delay_ticks`` after the request (the caller waits for it,
    see :meth:`awaiting`), with the wall clock at the first tick after it is ready.

    Parameters
    ----------
    model : Model
    config : AdaptationConfig
    dt : float
        Tick period, s.
    frame_mode : bool
        Frame clock (results applied at a fixed tick) or wall clock.
    max_decisions : int
        Decisions kept (``state.max_decisions``).
    restored : PersistedState, optional
        Parameters, version, run count and decisions saved before.
    worker_mode : {"thread", "sync"}, optional
        Default: the configuration's.
    """

    def __init__(self, model: Model, config: AdaptationConfig, dt: float, frame_mode: bool, max_decisions: int,
                 restored: Any = None, worker_mode: str | None = None) -> None:
        self.model = model
        self.config = config
        self.dt = float(dt)
        self.frame_mode = frame_mode
        self.max_decisions = int(max_decisions)
        self.offline_theta = model.nominal()
        self._theta = self.offline_theta.copy()
        self._counts = AdaptationCounts()
        self._decisions: list[dict[str, Any]] = []
        if restored is not None:
            idx = {n: i for i, n in enumerate(model.parameter_names)}
            for k, v in restored.parameters.items():
                self._theta[idx[k]] = v
            self._counts.version = restored.param_version
            self._counts.runs = restored.adapt_runs
            self._decisions = list(restored.decisions)
        self.worker = AdaptationWorker(model, config.adapter, self.dt, self._theta, self.offline_theta,
                                       worker_mode or config.worker, config.bands) if config.enabled else None
        self._bands: dict[str, tuple[float, float]] = {}
        self._identifiable: dict[str, bool] = {}
        self._recent: deque[tuple[float, dict[str, float]]] = deque(maxlen=1024)
        self._next_t: float | None = None
        self._pending: tuple[int, float] | None = None  # (request id, apply at)
        self._status = "starting" if config.enabled else "off"
        self._last_refusal: tuple[float, str, str] | None = None  # (t, why, the decision's reason)
        if config.enabled and self._decisions:  # restored: what the saved decisions left
            self._status = decision_status(self._decisions[-1])
            for rec in reversed(self._decisions):
                if rec.get("verdict") == "dropped":
                    self._last_refusal = (float(rec.get("t") or 0.0), str(rec.get("refusal") or ""),
                                          str(rec.get("reason") or "").split(";")[0])
                    break

    # -- read-only views -------------------------------------------------------------------------
    @property
    def theta(self) -> np.ndarray:
        """The full parameter vector in use (a copy)."""
        return self._theta.copy()

    @property
    def counts(self) -> AdaptationCounts:
        """The counters (a copy)."""
        return replace(self._counts)

    @property
    def decisions(self) -> list[dict[str, Any]]:
        """The kept decisions, oldest first (a copy)."""
        return list(self._decisions)

    def parameter_bands(self) -> tuple[dict[str, tuple[float, float]], dict[str, bool]]:
        """After the last accepted decision: the 95 % band of each adaptable parameter, and whether
        the sensors pin it down (copies)."""
        return dict(self._bands), dict(self._identifiable)

    @property
    def status(self) -> str:
        """What the adaptation is doing after its last decision (one of :data:`ADAPT_STATUSES`)."""
        return self._status

    @property
    def last_refusal(self) -> tuple[float, str, str] | None:
        """The last challenger dropped: its decision's time (s), why in short ("not better",
        "predicts housing worse", ...) and the decision's whole reason, with its evidence."""
        return self._last_refusal

    @property
    def deciding(self) -> bool:
        """A decision was requested and its result not applied yet."""
        return self.worker is not None and self._pending is not None

    def values(self) -> dict[str, float]:
        """The adaptable parameters' values in use."""
        names = self.worker.params if self.worker is not None else self.model.adaptable
        idx = self.model.parameter_index(names)
        return {n: float(self._theta[i]) for n, i in zip(names, idx)}

    def changed(self) -> dict[str, float]:
        """Every parameter whose value differs from the model file's (what is saved)."""
        m = self.model
        return {n: float(v) for n, v, v0 in zip(m.parameter_names, self._theta, self.offline_theta) if v != v0}

    # -- per tick -----------------------------------------------------------------------------------
    def record(self, t: float, inputs: dict[str, float], measured: Mapping[str, float], state: np.ndarray) -> None:
        """A finished sample: time ``t`` (s), the inputs of the interval after it, its readings and
        the observer's state then."""
        self._recent.append((t, inputs))
        if self.worker is not None:
            self.worker.record(t, inputs, measured, state)
            if self._next_t is None:
                self._next_t = t + self.config.adapter.period_s

    def awaiting(self, t: float) -> int | None:
        """With the frame clock: the decision that must be applied at the tick ``t`` and is not done yet."""
        if self.worker is None or self._pending is None or not self.frame_mode:
            return None
        rid, apply_at = self._pending
        if t + 1e-9 >= apply_at and self.worker.result(rid) is None:
            return rid
        return None

    async def wait_async(self, rid: int, timeout_s: float) -> AdaptationResult | None:
        """Await decision ``rid`` (None after ``timeout_s``: it is then dropped)."""
        assert self.worker is not None
        res = await self.worker.wait_async(rid, timeout_s)
        if res is None:
            self._pending = None
        return res

    def step(self, t: float) -> list[AdaptationResult]:
        """Apply a finished decision (when due), request the next one when due; returns the results applied."""
        w = self.worker
        if w is None:
            return []
        applied: list[AdaptationResult] = []
        if self._pending is not None:
            rid, apply_at = self._pending
            res = w.result(rid)
            if res is not None and (not self.frame_mode or t + 1e-9 >= apply_at):
                self._pending = None
                w.forget(rid)
                self._apply(res)
                applied.append(res)
        if self._pending is None and self._next_t is not None and self._recent:
            t_rec = self._recent[-1][0]
            if t_rec + 1e-9 >= self._next_t:
                rid = w.request(t_rec)
                self._pending = (rid, t + self.config.apply_delay_ticks * self.dt)
                self._next_t = t_rec + self.config.adapter.period_s
        return applied

    def state_now(self, res: AdaptationResult, stepper: Stepper, which: str = "state") -> np.ndarray | None:
        """The open-loop state (or, ``which="estimate"``, the observer's estimate) after the
        accepted ``res`` (see :meth:`AdaptationResult.state_now`)."""
        return res.state_now(stepper, self._recent, which)

    def restart(self) -> None:
        """A gap in the data: the worker forgets its history, the next decision is a period away."""
        if self.worker is not None:
            self.worker.reset(self._theta)
        self._next_t = None

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()

    def _apply(self, res: AdaptationResult) -> None:
        if res.error is not None or res.decision is None:
            if res.error != "no history yet":
                self._counts.failures += 1
                log.warning("adaptation at t=%.0f failed: %s", res.t, res.error)
            return
        d = res.decision
        rec = json_safe(d.as_dict())
        rec["wall_s"] = res.wall_s
        self._decisions.append(rec)
        if len(self._decisions) > self.max_decisions:
            del self._decisions[: len(self._decisions) - self.max_decisions]
        self._status = decision_status(rec)
        if d.verdict == "dropped":
            self._last_refusal = (d.t, d.refusal, d.reason.split(";")[0])
        if not d.triggered:
            return
        if d.evaluations == 0 and not d.accepted:  # triggered, but the adapter did not optimise (too little history, ...)
            self._counts.skipped += 1
            log.debug("adaptation at t=%.0f skipped: %s", d.t, d.reason)
            return
        c = self._counts
        c.runs += 1
        if not d.accepted:
            c.rejected += 1
            log.info("adaptation at t=%.0f rolled back (%s)", d.t, d.reason)
            return
        c.accepted += 1
        c.version += 1
        self._theta = np.array(res.theta, dtype=float)
        if res.bands:
            self._bands.update(res.bands)
            self._identifiable.update(res.identifiable)
        log.info("adaptation at t=%.0f accepted (version %d): %s", d.t, c.version,
                 ", ".join(f"{k}={v:.4g}" for k, v in d.params.items()))


def json_safe(x: Any) -> Any:
    """Non-finite floats -> None, numpy scalars -> Python, recursively (for the JSON state file)."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x
