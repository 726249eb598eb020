"""The online adapter, run beside the tick so that ticks stay on time.

:class:`AdaptationWorker` owns one :class:`~thermal_edge.estimation.adapter.OnlineAdapter` and
serialises everything done to it: samples recorded and decisions requested are commands in one
FIFO, executed in order by a worker thread (``mode="thread"``) or at once (``mode="sync"``, for
replays and tests). A decision therefore sees exactly the samples recorded before it was
requested, wherever and however long it runs, and the same log replayed gives the same decisions.

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
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from ..estimation.adapter import AdapterConfig, Decision, OnlineAdapter
from ..estimation.uncertainty import Z95
from ..lptn import Model

__all__ = ["AdaptationResult", "AdaptationWorker"]

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
    bands: dict[str, tuple[float, float]] = field(default_factory=dict)
    identifiable: dict[str, bool] = field(default_factory=dict)
    error: str | None = None
    wall_s: float = 0.0

    @property
    def accepted(self) -> bool:
        return self.decision is not None and self.decision.accepted


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
        self._done: list[AdaptationResult] = []
        self._cond = threading.Condition()
        self._pending: set[int] = set()
        self._queue: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self.failures = 0
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
    def poll(self) -> list[AdaptationResult]:
        """Completed results not yet returned (oldest first)."""
        with self._cond:
            out, self._done = self._done, []
        return out

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
        except Exception as exc:  # a failed command must never kill the worker
            self.failures += 1
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
            win = ad._window(t - self.config.window_s)
            traj = ad.sim.simulate(ad.theta, win.inputs, win.dt, win.T0)
            x = traj.T[-1]
            if np.all(np.isfinite(x)):
                res.state, res.state_t = x.copy(), float(win.t[-1])
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
            self._done.append(res)
            self._pending.discard(res.request_id)
            self._cond.notify_all()
