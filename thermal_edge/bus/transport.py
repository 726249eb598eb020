"""asyncio CAN transport: one bus, decoded reception, transmission, recording, reconnection.

:class:`CanTransport` opens the bus of a :class:`~thermal_edge.bus.busconfig.BusConfig`,
receives through ``can.Notifier`` + ``can.AsyncBufferedReader`` on the running
event loop, checks and decodes every frame with a
:class:`~thermal_edge.bus.codec.FrameCodec`, and hands accepted frames to a
callback and/or an ``asyncio.Queue``. Sends never raise: a bus that fails (closed,
down, send error) is logged, counted in ``stats.bus_errors``, torn down and
reopened with exponential backoff, while cyclic senders keep their cadence.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import can

from .busconfig import BusConfig, BusConfigError, create_bus
from .candump import CandumpRecorder
from .codec import DecodedFrame, FrameCodec
from .cyclic import CyclicSender, Fallback, SignalProvider
from .stats import TransportStats

__all__ = ["CanTransport", "FrameCallback"]

log = logging.getLogger(__name__)

#: Called with every accepted frame; may return an awaitable, which is awaited.
FrameCallback = Callable[[DecodedFrame], Any]


class _GuardedNotifier(can.Notifier):
    """``can.Notifier`` whose receive errors always reach the listeners' ``on_error``.

    python-can reports errors of its reader thread through ``on_error`` (on the
    loop) but then lets the thread die with a traceback, and errors of the
    file-descriptor path (``loop.add_reader``) go to the loop's exception
    handler only. Both are routed to ``on_error`` here, quietly.
    """

    def _rx_thread(self, bus: can.BusABC) -> None:
        try:
            super()._rx_thread(bus)
        except Exception:  # already handed to on_error via the loop
            pass

    def _on_message_available(self, bus: can.BusABC) -> None:
        try:
            super()._on_message_available(bus)
        except Exception as exc:
            self.exception = exc
            if self._loop is not None:
                for reader in list(self._readers):
                    if isinstance(reader, int):
                        try:
                            self._loop.remove_reader(reader)
                        except Exception:
                            pass
            self._on_error(exc)


class _ErrorWatch(can.Listener):
    """Listener that forwards bus errors to a callback."""

    def __init__(self, callback: Callable[[BaseException], None]) -> None:
        self._callback = callback

    def on_message_received(self, msg: can.Message) -> None:
        pass

    def on_error(self, exc: Exception) -> None:
        self._callback(exc)

    def stop(self) -> None:
        pass


class CanTransport:
    """Receive, transmit and record the thermal_edge frames on one CAN bus.

    Parameters
    ----------
    config : BusConfig or mapping
        Bus configuration (interface, channel, bitrate, node, recording, backoff).
    codec : FrameCodec, optional
        Codec for the DBC; a new one on the project DBC by default. Its
        ``stats`` hold the frame integrity counters.
    on_frame : callable, optional
        Called with every accepted :class:`DecodedFrame`, in order; if it returns
        an awaitable, that is awaited before the next frame. Exceptions are
        logged and counted (``stats.callback_errors``).
    queue : asyncio.Queue, optional
        Accepted frames are also put here (``put_nowait``; a full queue drops and
        counts ``stats.queue_overflow``).
    bus_factory : callable, optional
        Opens the bus from the configuration (default :func:`create_bus`); tests
        inject failing buses here.
    timestamp_fn : callable, optional
        Time stamp (s) of sent frames in the recording and on buses that carry it
        (default wall time; replays and accelerated runs pass their own clock).

    Examples
    --------
    >>> async def main():                                      # doctest: +SKIP
    ...     async with CanTransport({"interface": "virtual", "channel": "demo"},
    ...                             on_frame=print) as bus:
    ...         bus.start_cyclic("TE_Limits", current_limits, fallback=SAFE_LIMITS)
    ...         await asyncio.sleep(10)
    """

    def __init__(
        self,
        config: BusConfig | Mapping[str, Any],
        codec: FrameCodec | None = None,
        *,
        on_frame: FrameCallback | None = None,
        queue: asyncio.Queue[DecodedFrame] | None = None,
        bus_factory: Callable[[BusConfig], can.BusABC] = create_bus,
        timestamp_fn: Callable[[], float] = time.time,
    ) -> None:
        self.config = BusConfig.coerce(config)
        self.timestamp_fn = timestamp_fn
        self.codec = codec if codec is not None else FrameCodec()
        self.stats = TransportStats()
        self.on_frame = on_frame
        self.queue = queue
        self._bus_factory = bus_factory
        self._own_ids = self.codec.frames_sent_by(self.config.node) if self.config.node else frozenset()
        self._bus: can.BusABC | None = None
        self._notifier: _GuardedNotifier | None = None
        self._reader: can.AsyncBufferedReader | None = None
        self._consumer: asyncio.Task[None] | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._failed: asyncio.Event | None = None
        self._connected: asyncio.Event | None = None
        self._failed_flag = False
        self._stopping = False
        self._opened_once = False
        self._generation = 0  # bumped per open; errors of an older bus are ignored
        self._opened_at = 0.0
        self._cyclic: list[CyclicSender] = []
        self._recorder: CandumpRecorder | None = None
        self._thread_lock = threading.Lock()

    # ----------------------------------------------------------------- status
    @property
    def bus(self) -> can.BusABC | None:
        """The open python-can bus, None while down."""
        return self._bus

    @property
    def connected(self) -> bool:
        """True while the bus is open and has not failed."""
        return self._bus is not None and not self._failed_flag

    @property
    def recorder(self) -> CandumpRecorder | None:
        """The candump recorder, if recording."""
        return self._recorder

    async def wait_connected(self, timeout: float | None = None) -> bool:
        """Wait until the bus is open; False on timeout (in s)."""
        if self._connected is None:
            raise RuntimeError("transport not started")
        try:
            await asyncio.wait_for(self._connected.wait(), timeout)
        except asyncio.TimeoutError:
            return False
        return True

    # ------------------------------------------------------------- lifecycle
    async def start(self) -> None:
        """Open the bus and start receiving (must run inside the event loop).

        If the bus cannot be opened yet, this logs, counts a bus error and keeps
        retrying in the background; it does not raise for that.

        Raises
        ------
        BusConfigError
            Invalid configuration.
        can.CanInterfaceNotImplementedError
            Unknown or unavailable python-can interface (retrying cannot help).
        """
        if self._supervisor is not None:
            return
        self._loop = asyncio.get_running_loop()
        self._failed = asyncio.Event()
        self._connected = asyncio.Event()
        self._stopping = False
        if self.config.record_path is not None and self._recorder is None:
            self._recorder = CandumpRecorder(self.config.record_path, channel=self.config.record_channel)
        try:
            self._open()
        except (BusConfigError, can.CanInterfaceNotImplementedError, TypeError):
            if self._recorder is not None:
                self._recorder.close()
                self._recorder = None
            raise
        except Exception as exc:
            self._note_bus_error(exc, "open")
        self._supervisor = self._loop.create_task(self._supervise(), name="can supervisor")

    async def stop(self) -> None:
        """Stop cyclic senders, receive the frames already queued, close bus and recorder."""
        self._stopping = True
        for sender in self._cyclic:
            await sender.stop()
        self._cyclic.clear()
        if self._supervisor is not None:
            self._supervisor.cancel()
            try:
                await self._supervisor
            except asyncio.CancelledError:
                pass
            self._supervisor = None
        await self._teardown()
        if self._recorder is not None:
            self._recorder.close()
            self._recorder = None

    async def __aenter__(self) -> CanTransport:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # ------------------------------------------------------------ bus handling
    def _open(self) -> None:
        assert self._loop is not None and self._connected is not None
        bus = self._bus_factory(self.config)
        generation = self._generation + 1

        def on_error(exc: BaseException) -> None:
            if generation == self._generation:
                self._on_bus_error(exc, "receive")

        try:
            reader = can.AsyncBufferedReader()
            notifier = _GuardedNotifier(bus, [reader, _ErrorWatch(on_error)], timeout=0.1, loop=self._loop)
        except Exception:
            bus.shutdown()
            raise
        self._generation = generation
        self._opened_at = self._loop.time()
        self._bus, self._reader, self._notifier = bus, reader, notifier
        self._failed_flag = False
        self._consumer = self._loop.create_task(self._consume(reader), name="can receiver")
        if self._opened_once:
            self.stats.reconnects += 1
            log.warning("CAN bus %s reconnected", self._describe())
        else:
            log.info("CAN bus %s open", self._describe())
        self._opened_once = True
        self._connected.set()

    def _describe(self) -> str:
        return f"{self.config.interface}:{self.config.channel if self.config.channel is not None else 'default'}"

    async def _teardown(self) -> None:
        if self._connected is not None:
            self._connected.clear()
        notifier, self._notifier = self._notifier, None
        reader, self._reader = self._reader, None
        consumer, self._consumer = self._consumer, None
        bus, self._bus = self._bus, None
        # synchronous part first: even if this coroutine is cancelled later, the bus is closed
        if notifier is not None:
            try:
                notifier.stop(timeout=1.0)
            except Exception as exc:
                log.debug("notifier stop: %s", exc)
        if bus is not None:
            try:
                bus.shutdown()
            except Exception as exc:
                log.debug("bus shutdown: %s", exc)
        if consumer is not None:
            consumer.cancel()
            try:
                await consumer
            except asyncio.CancelledError:
                pass
            except Exception:
                log.exception("CAN receiver ended with an error")
        if reader is not None:  # frames that arrived before the stop
            while not reader.buffer.empty():
                await self._handle(reader.buffer.get_nowait())

    def _note_bus_error(self, exc: BaseException, where: str) -> None:
        self.stats.bus_errors += 1
        log.warning("CAN bus %s error (%s): %s: %s", self._describe(), where, type(exc).__name__, exc)

    def _on_bus_error(self, exc: BaseException, where: str = "receive") -> None:
        """Mark the bus failed (any thread); the supervisor reconnects."""
        with self._thread_lock:
            if self._failed_flag or self._stopping:
                return
            self._failed_flag = True
        self._note_bus_error(exc, where)
        loop, failed = self._loop, self._failed
        if loop is None or failed is None:
            return
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if running is loop:
            failed.set()
        else:
            loop.call_soon_threadsafe(failed.set)

    async def _supervise(self) -> None:
        assert self._failed is not None
        delay = self.config.reconnect_min_s
        while not self._stopping:
            if self._bus is None:
                try:
                    self._open()
                except Exception as exc:
                    self._note_bus_error(exc, "open")
                    log.warning("CAN bus %s: retrying in %.2f s", self._describe(), delay)
                    await asyncio.sleep(delay)
                    delay = min(delay * 2, self.config.reconnect_max_s)
                    continue
            if self._failed_flag:
                self._failed.set()
            await self._failed.wait()
            self._failed.clear()
            if self._stopping:
                break
            # a connection that held for a while starts the backoff afresh; one that
            # fails right after opening keeps growing it
            if asyncio.get_running_loop().time() - self._opened_at > 2 * self.config.reconnect_max_s:
                delay = self.config.reconnect_min_s
            await self._teardown()
            log.warning("CAN bus %s down; reopening in %.2f s", self._describe(), delay)
            await asyncio.sleep(delay)
            delay = min(delay * 2, self.config.reconnect_max_s)

    # --------------------------------------------------------------- receive
    async def _consume(self, reader: can.AsyncBufferedReader) -> None:
        while True:
            msg = await reader.get_message()
            await self._handle(msg)

    async def _handle(self, msg: can.Message) -> None:
        if not msg.is_extended_id and msg.arbitration_id in self._own_ids:
            self.stats.own_echo += 1
            return
        self.stats.rx_messages += 1
        if self._recorder is not None:
            # received by us, whatever the interface says: SocketCAN reports frames from another
            # local socket (vcan) as looped back, not received, and the log must mark them R
            msg.is_rx = True
            self._recorder.write(msg)
        frame = self.codec.decode_message(msg)
        if frame is None:
            return
        if self.queue is not None:
            try:
                self.queue.put_nowait(frame)
            except asyncio.QueueFull:
                self.stats.queue_overflow += 1
        if self.on_frame is not None:
            try:
                result = self.on_frame(frame)
                if inspect.isawaitable(result):
                    await result
            except asyncio.CancelledError:
                raise
            except Exception:
                self.stats.callback_errors += 1
                log.exception("frame callback failed on %s", frame.name)

    # -------------------------------------------------------------- transmit
    def send_raw(self, arbitration_id: int, data: bytes) -> bool:
        """Put one already encoded frame on the bus; never raises.

        Parameters
        ----------
        arbitration_id : int
            11-bit CAN identifier.
        data : bytes
            Frame data (8 bytes for the DBC frames).

        Returns
        -------
        bool
            True if the bus accepted the frame; False if the bus is down or the
            send failed (counted in ``stats.tx_failed``; a bus error also
            triggers a reconnect, a send timeout does not).
        """
        bus = self._bus
        if bus is None or self._failed_flag:
            self.stats.tx_failed += 1
            return False
        try:
            ts = float(self.timestamp_fn())
        except Exception:  # a broken clock must not stop TE_Limits
            ts = time.time()
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False, is_rx=False, timestamp=ts)
        try:
            bus.send(msg, timeout=self.config.send_timeout_s)
        except can.CanTimeoutError as exc:
            self.stats.tx_failed += 1
            log.debug("send 0x%03X timed out: %s", arbitration_id, exc)
            return False
        except Exception as exc:  # CanError, OSError, closed bus ...
            self.stats.tx_failed += 1
            self._on_bus_error(exc, "send")
            return False
        self.stats.tx_frames += 1
        if self._recorder is not None:
            self._recorder.write(msg)
        return True

    def send(self, frame: str | int, signals: Mapping[str, Any], *, counter: int | None = None) -> bool:
        """Encode (counter and CRC filled) and send one frame.

        Parameters
        ----------
        frame : str or int
            Frame name or identifier.
        signals : mapping
            Physical signal values in DBC units (see :meth:`FrameCodec.encode`).
        counter : int, optional
            Force the alive counter (tests, emulators).

        Returns
        -------
        bool
            See :meth:`send_raw`.

        Raises
        ------
        KeyError, FrameEncodeError
            Unknown frame or signals that do not fit it (programming errors);
            bus problems never raise.
        """
        data = self.codec.encode(frame, signals, counter=counter)
        return self.send_raw(self.codec.frame_id(frame), data)

    def start_cyclic(
        self,
        frame: str | int,
        provider: SignalProvider,
        *,
        period_s: float | None = None,
        fallback: Fallback | None = None,
    ) -> CyclicSender:
        """Send ``frame`` every period from ``provider`` until :meth:`stop`.

        Parameters
        ----------
        frame : str or int
            Frame name or identifier.
        provider : callable
            Returns the current signal values (see :class:`CyclicSender`).
        period_s : float, optional
            Period in s, default the DBC cycle time.
        fallback : mapping or callable, optional
            Values sent when the provider fails.

        Returns
        -------
        CyclicSender
            The running sender (``stop()`` it to end early).
        """
        sender = CyclicSender(
            self.codec, self.send_raw, frame, provider, period_s=period_s, fallback=fallback, stats=self.stats
        )
        self._cyclic.append(sender)
        return sender.start()

