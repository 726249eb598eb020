"""Periodic transmission of one frame from a provider of current signal values.

The sender keeps its cadence whatever happens around it: a provider that raises
(or returns nothing usable) is replaced by the fallback values, a bus that is
down only makes single sends fail, and a late schedule skips missed periods
instead of bursting. This is what keeps ``TE_Limits`` on the bus.

It runs as an asyncio task, or (``thread=True``) in a daemon thread of its own on a
``time.monotonic`` fixed-rate schedule, which a blocked or busy event loop cannot delay.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from .codec import FrameCodec
from .stats import TransportStats

__all__ = ["CyclicSender", "Fallback", "SignalProvider"]

log = logging.getLogger(__name__)

#: Returns the frame's current physical signal values (may be a coroutine function).
SignalProvider = Callable[[], Mapping[str, Any] | Any]
#: Fixed signal values, or a callable returning them, sent when the provider fails.
Fallback = Mapping[str, Any] | Callable[[], Mapping[str, Any]]


class CyclicSender:
    """Send one frame every period from a provider callback.

    Parameters
    ----------
    codec : FrameCodec
        Encodes the frame (fills counter and CRC).
    sink : callable(int, bytes) -> bool
        Puts an encoded frame on the bus; must not raise (``CanTransport.send_raw``).
    frame : str or int
        Frame name or identifier.
    provider : callable
        Returns the current physical signal values of the frame (mapping of
        signal name to value in DBC units). Called once per period; should be
        fast. A coroutine function is awaited for at most half a period.
    period_s : float, optional
        Cycle time in s; defaults to the frame's ``GenMsgCycleTime``.
    fallback : mapping or callable, optional
        Signal values sent when the provider raises, times out, returns None or
        values that cannot be encoded (e.g. safe derating limits with reason
        "model fault"). Without a fallback such a period sends nothing.
    stats : TransportStats, optional
        Where ``provider_errors``, ``fallback_sent`` and ``cyclic_overruns`` are counted.
    thread : bool, optional
        Run in a daemon thread of its own instead of an asyncio task. The provider (and a
        callable fallback) is then called in that thread: a plain function, thread-safe,
        returning at once (e.g. reading values the model published). The sink must be
        thread-safe (``CanTransport.send_raw`` is).
    send_lock : threading.Lock, optional
        Held while a frame is encoded and handed to the sink, so that frames of one identifier
        leave in counter order whoever sends them (``CanTransport`` shares one with its
        :meth:`~thermal_edge.bus.transport.CanTransport.send`).
    on_sent : callable(float), optional
        Given, after each frame the sink accepted, the time since the one before (s, monotonic
        clock): the cadence as the bus saw it (a metric). Must be quick and must not raise.
    """

    def __init__(
        self,
        codec: FrameCodec,
        sink: Callable[[int, bytes], bool],
        frame: str | int,
        provider: SignalProvider,
        *,
        period_s: float | None = None,
        fallback: Fallback | None = None,
        stats: TransportStats | None = None,
        thread: bool = False,
        send_lock: threading.Lock | None = None,
        on_sent: Callable[[float], None] | None = None,
    ) -> None:
        if thread and inspect.iscoroutinefunction(provider):
            raise TypeError(f"{frame}: a threaded cyclic sender needs a plain provider function, not a coroutine")
        self.codec = codec
        self.frame_name = codec.frame_name(frame)
        self.frame_id = codec.frame_id(frame)
        period = period_s if period_s is not None else codec.cycle_time_s(frame)
        if period is None or period <= 0:
            raise ValueError(f"{self.frame_name}: no cycle time in the DBC, give period_s")
        self.period_s = float(period)
        self._sink = sink
        self._provider = provider
        self._fallback = fallback
        self.stats = stats if stats is not None else TransportStats()
        #: Frames handed to the sink (sent or not) and frames the sink accepted.
        self.attempts = 0
        self.sent = 0
        self._failing = False
        self.threaded = bool(thread)
        self._task: asyncio.Task[None] | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._send_lock = send_lock if send_lock is not None else threading.Lock()
        self._on_sent = on_sent
        self._last_sent: float | None = None  # monotonic time of the last frame the sink accepted

    @property
    def running(self) -> bool:
        """True while the periodic task or thread runs."""
        if self._thread is not None:
            return self._thread.is_alive()
        return self._task is not None and not self._task.done()

    def start(self) -> CyclicSender:
        """Start sending (first frame immediately): a task on the running event loop, or the thread."""
        if self.running:
            return self
        if self.threaded:
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._run_thread, name=f"cyclic {self.frame_name}", daemon=True)
            self._thread.start()
        else:
            self._task = asyncio.get_running_loop().create_task(self._run(), name=f"cyclic {self.frame_name}")
        return self

    async def stop(self) -> None:
        """Stop sending and wait for the task or thread to end."""
        task, self._task = self._task, None
        thread, self._thread = self._thread, None
        self._stop.set()
        if thread is not None:
            await asyncio.to_thread(thread.join, 2.0 + self.period_s)
        if task is not None:
            task.cancel()
            try:
                await task
            except asyncio.CancelledError:
                pass

    async def _values(self) -> Mapping[str, Any]:
        values = self._provider()
        if inspect.isawaitable(values):
            values = await asyncio.wait_for(values, timeout=self.period_s / 2)
        return values

    async def send_once(self) -> bool:
        """Build and send one frame now (asyncio mode); True if the sink accepted it."""
        try:
            values: Any = await self._values()
            error: Exception | None = None
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            values, error = None, exc
        return self._send(values, error)

    def send_once_sync(self) -> bool:
        """Build and send one frame now from a plain provider (thread mode); True if sent."""
        try:
            values: Any = self._provider()
            error: Exception | None = None
        except Exception as exc:
            values, error = None, exc
        return self._send(values, error)

    def _send(self, values: Any, error: Exception | None) -> bool:
        # encode (which takes the next alive counter) and hand over in one step: another sender
        # of this frame in another thread (an immediate send from the loop) cannot overtake it
        with self._send_lock:
            data = self._encode(values, error)
            if data is None:
                return False
            self.attempts += 1
            ok = bool(self._sink(self.frame_id, data))
        self.sent += ok
        if ok:
            now = time.monotonic()
            if self._on_sent is not None and self._last_sent is not None:
                self._on_sent(now - self._last_sent)
            self._last_sent = now
        return ok

    def _encode(self, values: Any, error: Exception | None) -> bytes | None:
        data: bytes | None = None
        try:
            if error is not None:
                raise error
            if values is None:
                raise ValueError("provider returned None")
            data = self.codec.encode(self.frame_name, values)
            if self._failing:
                self._failing = False
                log.info("%s provider recovered", self.frame_name)
        except Exception as exc:
            self.stats.provider_errors += 1
            if not self._failing:
                self._failing = True
                log.error("%s provider failed (%s: %s); %s", self.frame_name, type(exc).__name__, exc,
                          "sending fallback values" if self._fallback is not None else "frame not sent")
            if self._fallback is not None:
                try:
                    values = self._fallback() if callable(self._fallback) else self._fallback
                    data = self.codec.encode(self.frame_name, values)
                    self.stats.fallback_sent += 1
                except Exception:
                    log.exception("%s fallback values cannot be encoded", self.frame_name)
        return data

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            try:
                await self.send_once()
            except asyncio.CancelledError:
                raise
            except Exception:  # belt and braces: the cadence must survive anything
                log.exception("%s cyclic send failed", self.frame_name)
            next_t, delay = self._next(next_t, loop.time())
            await asyncio.sleep(delay)

    def _next(self, next_t: float, now: float) -> tuple[float, float]:
        """The next send time after ``next_t`` and the wait until it (s), from ``now``: fixed rate,
        periods already missed skipped (counted in ``cyclic_overruns``), never a burst."""
        next_t += self.period_s
        if now - next_t > self.period_s:
            missed = int((now - next_t) // self.period_s)
            self.stats.cyclic_overruns += missed
            next_t += missed * self.period_s
        return next_t, max(0.0, next_t - now)

    def _run_thread(self) -> None:
        next_t = time.monotonic()
        stop = self._stop
        while not stop.is_set():
            try:
                self.send_once_sync()
            except Exception:  # belt and braces: the cadence must survive anything
                log.exception("%s cyclic send failed", self.frame_name)
            next_t, delay = self._next(next_t, time.monotonic())
            stop.wait(delay)
