"""The asyncio edge service: CAN in, tick, derating out, metrics, persistence, systemd.

:class:`EdgeService` wires the parts together:

- a :class:`~thermal_edge.bus.CanTransport` (sent frames stamped by the service clock) receives
  and checks the inverter's frames; each accepted frame goes to the :class:`~.engine.ThermalEngine`'s input accumulator;
- the tick runs at 1 Hz of the configured clock: with the wall clock from a timer task, with the
  frame clock whenever a frame's timestamp crosses a tick boundary (replays, accelerated
  simulation);
- ``TE_Limits`` is sent every 100 ms by the transport's cyclic sender, in a thread of its own, from the
  last tick's limits;
  if that fails, the fallback is the safe limit (reason "model fault"); if the inverter goes silent
  the limit drops to the safe limit with reason "stale input" even between ticks (and with the
  frame clock, where ticks stop with the frames). The 1 s frames (estimates, forecast, status) go
  out with every tick (frame clock) or from cyclic senders (wall clock);
- the state is saved every ``state.save_interval_s``, after every accepted adaptation, and on stop;
- systemd gets ``READY=1`` once the bus is up, ``WATCHDOG=1`` at half ``WatchdogSec`` while ticks
  are on time, ``STATUS=`` lines, and ``STOPPING=1``.

Signals: :mod:`thermal_edge.process_signals` (stop: SIGTERM, SIGINT, SIGQUIT; logged and ignored: SIGHUP,
SIGUSR1, SIGUSR2, SIGALRM).
"""
from __future__ import annotations

import asyncio
import logging
import math
import signal
import time
from collections.abc import Callable, Sequence
from typing import Any

from prometheus_client import CollectorRegistry

from ..bus.busconfig import create_bus as bus_factory
from ..bus.codec import DecodedFrame
from ..bus.frames import TE_ESTIMATES, TE_FORECAST, TE_LIMITS, TE_STATUS, DerateReason, TeState
from ..bus.stats import DropReport
from ..bus.transport import CanTransport
from ..config import EdgeConfig
from ..lptn import Model
from ..process_signals import EXIT_STATE_NOT_SAVED, IGNORED_SIGNALS, STOP_SIGNALS, stop_requested_while_starting
from .clock import FrameClock, WallClock
from .derating import Limits
from .engine import ThermalEngine, load_service_model
from .journal import notice
from .memory import limit_heap_retention
from .metrics import ServiceMetrics
from .outputs import TickOutput
from .persistence import StateLock, StateStore
from .systemd import SystemdNotifier

__all__ = ["EdgeService", "status_line"]

log = logging.getLogger(__name__)

ADAPT_WAIT_TIMEOUT_S = 300.0


def status_line(out: TickOutput | None) -> str:
    """One line: time, state, hot spot estimate/upper band, magnet, limit, reason, error, adaptations."""
    if out is None:
        return "starting: no tick yet"
    hs, mg = out.hot_spot, out.magnet

    def t(x: float | None) -> str:
        return f"{x:6.1f}" if x is not None and math.isfinite(x) else "   -- "

    stamp = time.strftime("%H:%M:%S", time.gmtime(out.t)) if out.t > 1e6 else f"{out.t:9.0f}s"
    err = f"{out.pred_err_rms:5.2f}" if math.isfinite(out.pred_err_rms) else "  -- "
    return (f"{stamp} {out.state.name.lower():9s} hot spot {t(hs.estimate_c if hs else None)}/{t(hs.upper_c if hs else None)} °C"
            f"  magnet {t(mg.estimate_c if mg else None)} °C  limit {out.limits.current_a:5.1f} A {out.limits.torque_nm:6.1f} Nm"
            f"  reason {out.limits.reason.name.lower():10s} pred err {err} K  adapted {out.adapt_accepted}/{out.adapt_runs}"
            + (f"  model {adapt_phrase(out.adapt_status, out.adapt_refusal)}" if out.adapt_status else ""))


def adapt_phrase(status: str, refusal: str = "") -> str:
    """What the adaptation is doing, in words: "learning", "waiting for evidence", "refusing (not
    better)", ... (``status`` one of :data:`.adaptation.ADAPT_STATUSES`)."""
    if status == "refusing":
        return f"refusing ({refusal})" if refusal else "refusing"
    return status.replace("_", " ")


class EdgeService:
    """The service.

    Parameters
    ----------
    config : EdgeConfig
    model : Model, optional
        Machine model with the offline parameters (default: loaded from the configuration).
    registry : CollectorRegistry, optional
        Metrics registry (default: a private one).
    notifier : SystemdNotifier, optional
        Default: from the environment (a no-op outside systemd).
    serve_metrics : bool, optional
        Start the HTTP endpoint if the configuration enables it (default True).
    worker_mode : {"thread", "sync"}, optional
        Adapter worker (default: the configuration's).
    """

    def __init__(self, config: EdgeConfig, *, model: Model | None = None, registry: CollectorRegistry | None = None,
                 notifier: SystemdNotifier | None = None, serve_metrics: bool = True,
                 worker_mode: str | None = None, bus_factory_fn: Callable[..., Any] = bus_factory) -> None:
        limit_heap_retention()  # before the model and the adapter allocate (thermal_edge.service.memory)
        self.config = config
        self.model = model if model is not None else load_service_model(config)
        self.codec = config.codec.frame_codec(config.fname)
        config.check_dbc(self.codec, self.model.input_roles)
        self.state_lock = StateLock(config.state.dir)
        self.state_lock.acquire()  # before anything is read: a second service on the directory stops here
        self.store = StateStore(config.state.dir, self.model)
        # a state file this model cannot use is moved aside only once the configuration is accepted
        # (the end of this constructor): a refused configuration leaves the directory as it was
        restored = self.store.load(defer=True)
        self.store.probe()  # an unwritable state directory: ERROR, counted; the service protects on and retries
        self.engine = ThermalEngine(config, self.model, restored, worker_mode)
        self.frame_mode = config.clock.mode == "frame"
        self.clock: FrameClock | WallClock = (FrameClock(config.clock.tick_s, config.clock.max_catchup_s) if self.frame_mode
                                              else WallClock(config.clock.tick_s))
        if isinstance(self.clock, FrameClock):
            self.engine.frame_clock = self.clock.stats
        self.metrics = ServiceMetrics(registry)
        self.notifier = notifier if notifier is not None else SystemdNotifier()
        self.transport = CanTransport(config.bus, self.codec, on_frame=self._on_frame, timestamp_fn=self._tx_time,
                                      bus_factory=bus_factory_fn)
        self.metrics.attach(self.engine, self.codec, self.transport.stats, self.store)
        self.metrics.limits_now = self._limits_now
        self.metrics.silent_s = self._silent_for
        self._silent = False  # the bus silent longer than transmit.bus_silence_s (said once in the log)
        self._limits_called: float | None = None  # monotonic time of the TE_Limits sender's last call
        self._stalled_s = 0.0  # how long the process stood still before that call (0: it did not)
        self._drop_report = DropReport(self.codec.stats)
        self.metrics.extra.append(("frame_clock_lag_seconds", self._clock_lag,
                                   "Wall time minus clock time of the last frame (frame clock; large = behind)"))
        self.serve_metrics = serve_metrics
        self.metrics_address: tuple[str, int] | None = None
        self._tasks: list[asyncio.Task[Any]] = []
        self._last_frame_mono: float | None = None
        self._started_mono: float | None = None
        self._last_tick_mono: float | None = None
        self._last_save_t: float | None = None
        self._tick_lock = asyncio.Lock()
        self._waiting = False
        self._saved_running = False
        self._stopped = False
        self._final_saved = True
        #: Signals received and ignored, by name.
        self.signals_ignored: dict[str, int] = {}
        self.on_tick: list[Callable[[TickOutput], Any]] = []
        self.max_lateness_s = 0.0
        self.store.settle()

    # ------------------------------------------------------------------------------------------
    async def start(self) -> None:
        """Open the bus, start the cyclic frames, the tick, the metrics endpoint and the watchdog."""
        self._started_mono = time.monotonic()
        await self.transport.start()
        cfg = self.config
        if self.serve_metrics and cfg.metrics.enabled:
            try:
                self.metrics_address = self.metrics.serve(cfg.metrics.address, cfg.metrics.port)
            except OSError as exc:  # the service runs on without the endpoint
                log.error("cannot serve metrics on %s:%d: %s", cfg.metrics.address, cfg.metrics.port, exc)
        tr = self.transport
        # TE_Limits from a thread of its own: a slow tick, a burst of frames or of metrics connections on the
        # event loop must not delay it past the inverter's 300 ms timeout
        tr.start_cyclic(TE_LIMITS, self._limits_signals, period_s=cfg.transmit.limits_period_s,
                        fallback=lambda: self.engine.policy.safe(DerateReason.MODEL_FAULT).signals(), thread=True,
                        on_sent=self.metrics.limits_interval.observe)
        loop = asyncio.get_running_loop()
        if not self.frame_mode:
            tr.start_cyclic(TE_ESTIMATES, lambda: self._last_or_start().estimates_signals(),
                            period_s=cfg.transmit.status_period_s)
            tr.start_cyclic(TE_FORECAST, lambda: self._last_or_start().forecast_signals(), period_s=cfg.transmit.status_period_s)
            tr.start_cyclic(TE_STATUS, lambda: self._last_or_start().status_signals(), period_s=cfg.transmit.status_period_s)
            self._tasks.append(loop.create_task(self._wall_ticks(), name="thermal-edge tick"))
        if self.notifier.watchdog_interval_s:
            self._tasks.append(loop.create_task(self._watchdog(), name="systemd watchdog"))
        self.metrics.up.set(1)
        self.notifier.ready(f"running: {self.model.name}, {cfg.clock.mode} clock")
        log.info("thermal_edge service up: model %s, %s clock, bus %s:%s", self.model.name, cfg.clock.mode,
                 cfg.bus.interface, cfg.bus.channel if cfg.bus.channel is not None else "default")

    async def stop(self) -> None:
        """Persist the state and stop (idempotent)."""
        if self._stopped:
            return
        self._stopped = True
        self.notifier.stopping("stopping: saving state")
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks.clear()
        try:
            await self.transport.stop()
        except Exception as exc:
            log.warning("bus stop: %s", exc)
        self._final_saved = self.save()
        self.state_lock.release()
        self.engine.close()
        self.metrics.up.set(0)
        self.metrics.close()
        self.notifier.close()
        store = self.store
        if self._final_saved:
            log.info("thermal_edge service stopped, state saved to %s", store.path)
        else:
            kept = ("the file there holds the state saved at " + time.strftime("%H:%M:%S UTC", time.gmtime(store.last_saved_wall))
                    if store.last_saved_wall is not None else "no state was saved by this run")
            log.error("thermal_edge service stopped WITHOUT saving its state to %s (%s): the parameters, decisions and "
                      "thermal state since the last good save are lost; %s", store.path, store.last_error, kept)

    async def run(self, stop: asyncio.Event | None = None, *, handle_signals: bool = True) -> int:
        """Run until ``stop`` is set or a stop signal (:data:`STOP_SIGNALS`) arrives.

        Returns
        -------
        int
            The exit status: 0, or :data:`EXIT_STATE_NOT_SAVED` if the final save failed.
        """
        stop = stop or asyncio.Event()
        loop = asyncio.get_running_loop()
        installed = []
        if handle_signals:
            def stopping(sig: signal.Signals) -> None:
                log.info("received %s: stopping", sig.name)
                stop.set()

            for sig in STOP_SIGNALS + IGNORED_SIGNALS:
                try:
                    loop.add_signal_handler(sig, stopping if sig in STOP_SIGNALS else self._ignore_signal, sig)
                    installed.append(sig)
                except (NotImplementedError, RuntimeError, ValueError):
                    pass
            early = stop_requested_while_starting()
            if early is not None:
                log.info("received %s while starting: stopping", early.name)
                stop.set()
        try:
            await self.start()
            await stop.wait()
        finally:
            await self.stop()
            for sig in installed:
                loop.remove_signal_handler(sig)
        return 0 if self._final_saved else EXIT_STATE_NOT_SAVED

    def _ignore_signal(self, sig: signal.Signals) -> None:
        n = self.signals_ignored[sig.name] = self.signals_ignored.get(sig.name, 0) + 1
        # every one logged: the journal's rate limit (.journal) keeps a signal storm from flooding it
        log.warning("received %s: ignored (thermal-edge has no reload and takes no command by signal; "
                    "TE_Limits continues; %d so far)", sig.name, n)

    # ------------------------------------------------------------------------------------------
    def _on_frame(self, frame: DecodedFrame) -> Any:
        self._last_frame_mono = time.monotonic()
        if self.frame_mode:
            clock = self.clock
            assert isinstance(clock, FrameClock)
            boundaries = clock.observe(frame.timestamp)
            if boundaries:
                return self._frame_ticks(boundaries, frame)
            self.engine.add_frame(frame, clock.now(), clock.behind(frame.timestamp))
            return None
        self.engine.add_frame(frame, time.time())
        return None

    async def _frame_ticks(self, boundaries: Sequence[float], frame: DecodedFrame) -> None:
        for b in self.engine.ticks_for(boundaries):
            await self._run_tick(b, None)
        self.engine.add_frame(frame, self.clock.now(), self.clock.behind(frame.timestamp))

    async def _wall_ticks(self) -> None:
        clock = self.clock
        assert isinstance(clock, WallClock)
        while True:
            t, late = await clock.wait_next_tick()
            try:
                await self._run_tick(t, late)
            except asyncio.CancelledError:
                raise
            except Exception:  # the tick task must survive anything
                log.exception("tick at %.3f failed", t)

    async def _run_tick(self, t: float, lateness: float | None) -> TickOutput:
        async with self._tick_lock:
            rid = self.engine.awaiting(t)
            if rid is not None:
                # frame clock: the decision is applied at a fixed tick; the sender waits for us meanwhile,
                # which is not the inverter going silent
                self._waiting = True
                try:
                    res = await self.engine.adaptation.wait_async(rid, ADAPT_WAIT_TIMEOUT_S)
                finally:
                    self._waiting = False
                    self._last_frame_mono = time.monotonic()
                if res is None:
                    log.error("adaptation %d did not finish within %.0f s: dropped", rid, ADAPT_WAIT_TIMEOUT_S)
            out = self.engine.tick(t)
            self._last_tick_mono = time.monotonic()
            dropped = self._drop_report.due(self._last_tick_mono)
            if dropped is not None:  # bad frames are seen in the journal too, not only in the metrics
                log.warning("%s", dropped)
            self.metrics.observe_tick(out, lateness)
            if lateness is not None:
                self.max_lateness_s = max(self.max_lateness_s, lateness)
            if self.frame_mode:
                tr = self.transport
                tr.send(TE_LIMITS, self._limits_signals())
                tr.send(TE_ESTIMATES, out.estimates_signals())
                tr.send(TE_FORECAST, out.forecast_signals())
                tr.send(TE_STATUS, out.status_signals())
            accepted = any(r.accepted for r in out.new_results)
            first = out.initialized and not self._saved_running  # the (re)started state, corrected by the readings
            if accepted or first or self._last_save_t is None or t - self._last_save_t >= self.config.state.save_interval_s:
                self.save(t)
                self._saved_running = self._saved_running or out.initialized
            for cb in self.on_tick:
                try:
                    cb(out)
                except Exception:
                    log.exception("tick callback failed")
            return out

    # ------------------------------------------------------------------------------------------
    def _last_or_start(self) -> TickOutput:
        out = self.engine.last
        return out if out is not None else self.engine.placeholder(self.clock.now())

    def _limits_now(self) -> Limits:
        """The limits TE_Limits carries now (any thread: reads only references and numbers the loop
        replaces whole); the rule (silence, stalled ticks) is the derating policy's."""
        out = self.engine.last
        return self.engine.policy.between_ticks(out.limits if out is not None else None, self._frame_age(),
                                                self._tick_age())

    def _silent_for(self) -> float | None:
        """Seconds the bus has been silent beyond ``transmit.bus_silence_s`` began (None: not silent)."""
        age = self._frame_age()
        return age if age is not None and age > self.engine.policy.bus_silence_s else None

    def _limits_signals(self) -> dict[str, float | int]:
        # called in the TE_Limits sender thread
        self._note_stall()
        silent = self._silent_for()
        if silent is not None and silent <= self._stalled_s + self.engine.policy.bus_silence_s:
            silent = None  # the frames of the stall wait in the socket: the process stood still, not the bus
        if (silent is not None) != self._silent:  # said once when it begins and once when it ends
            self._silent = silent is not None
            if self._silent:
                log.warning("no frame accepted for %.1f s (transmit.bus_silence_s %.1f s): the bus is silent, "
                            "TE_Limits carries the safe limit until frames come again", silent,
                            self.engine.policy.bus_silence_s)
            else:
                notice(log, "frames accepted again after the bus was silent: TE_Limits follows the ticks again")
        return self._limits_now().signals()

    def _note_stall(self) -> None:
        """Say when the TE_Limits sender itself could not run for longer than
        ``transmit.bus_silence_s``: the whole process stood still (a paused VM, a swap storm,
        SIGSTOP, no CPU for it), which the inverter sees as missing TE_Limits; what was on the bus
        meanwhile waits in the socket and is not a silent bus."""
        now = time.monotonic()
        last, self._limits_called = self._limits_called, now
        gap = 0.0 if last is None else now - last
        if gap > self.engine.policy.bus_silence_s:
            self._stalled_s = gap
            log.warning("this process stood still for %.1f s (no TE_Limits sent meanwhile; a paused VM, a swap "
                        "storm, a stop signal or no CPU for it): not the bus", gap)
        elif self._stalled_s and gap > 0.0:
            self._stalled_s = max(self._stalled_s - gap, 0.0)  # forgotten as the sender runs on

    def _frame_age(self) -> float | None:
        """Seconds since the last accepted frame (or the start); None while silence is expected (the
        frame clock waits for an adaptation's result)."""
        ref = self._last_frame_mono if self._last_frame_mono is not None else self._started_mono
        return None if ref is None or self._waiting else time.monotonic() - ref

    def _tick_age(self) -> float | None:
        """Seconds since the last tick of the wall clock (None with the frame clock or before the first tick)."""
        last = self._last_tick_mono
        return None if self.frame_mode or last is None else time.monotonic() - last

    def _tx_time(self) -> float:
        """Timestamp of sent (and recorded) frames: the clock's time. With the frame clock, frames
        sent before the first frame arrived carry 0, python-can's "no time" (not known yet): the
        recorder writes them at the first known time, so that a recording neither starts in 1970
        nor has a wall-clock stamp ahead of the simulated times that follow."""
        clock = self.clock
        if isinstance(clock, FrameClock) and not clock.started:
            return 0.0
        return clock.now()

    def _clock_lag(self) -> float:
        if not self.frame_mode:
            return 0.0
        return time.time() - self.clock.now()

    def save(self, t: float | None = None) -> bool:
        """Persist parameters, decisions and the thermal state now."""
        t = t if t is not None else (self.engine.last.t if self.engine.last is not None else self.clock.now())
        ok = self.store.save(self.engine.persisted(t))
        self._last_save_t = t
        return ok

    async def _watchdog(self) -> None:
        interval = self.notifier.watchdog_interval_s
        assert interval
        next_t = time.monotonic()
        while True:
            now = time.monotonic()
            # a stalled tick loop stops the pings: systemd restarts the service
            if not self.engine.policy.stalled(self._tick_age()):
                self.notifier.watchdog()
                self.metrics.watchdog_pings.inc()
            out = self.engine.last
            if out is not None:
                self.notifier.status(status_line(out))
            next_t += interval  # fixed rate, no drift
            if next_t < now:
                next_t = now + interval
            await asyncio.sleep(next_t - time.monotonic())

    # ------------------------------------------------------------------------------------------
    @property
    def state(self) -> TeState:
        return self.engine.last.state if self.engine.last is not None else TeState.STARTING
