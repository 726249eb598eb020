"""Periodic transmission of one frame from a provider of current signal values.

The sender keeps its cadence whatever happens around it: a provider that raises
(or returns nothing usable) is replaced by the fallback values, a bus that is
down only makes single sends fail, and a late event loop skips missed periods
instead of bursting. This is what keeps ``TE_Limits`` on the bus.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
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
    ) -> None:
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
        self._task: asyncio.Task[None] | None = None

    @property
    def running(self) -> bool:
        """True while the periodic task runs."""
        return self._task is not None and not self._task.done()

    def start(self) -> CyclicSender:
        """Start the periodic task on the running event loop (first frame immediately)."""
        if not self.running:
            self._task = asyncio.get_running_loop().create_task(self._run(), name=f"cyclic {self.frame_name}")
        return self

    async def stop(self) -> None:
        """Stop the periodic task and wait for it to end."""
        task, self._task = self._task, None
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
        if values is None:
            raise ValueError("provider returned None")
        return values

    async def send_once(self) -> bool:
        """Build and send one frame now; True if the sink accepted it."""
        data: bytes | None = None
        try:
            data = self.codec.encode(self.frame_name, await self._values())
            if self._failing:
                self._failing = False
                log.info("%s provider recovered", self.frame_name)
        except asyncio.CancelledError:
            raise
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
        if data is None:
            return False
        self.attempts += 1
        ok = bool(self._sink(self.frame_id, data))
        self.sent += ok
        return ok

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
            next_t += self.period_s
            delay = next_t - loop.time()
            if delay < -self.period_s:
                missed = int(-delay // self.period_s)
                self.stats.cyclic_overruns += missed
                next_t += missed * self.period_s
                delay = next_t - loop.time()
            await asyncio.sleep(max(0.0, delay))
