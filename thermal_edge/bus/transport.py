"""asyncio CAN transport: one bus, decoded reception, transmission, recording, reconnection.

:class:`CanTransport` opens the bus of a :class:`~thermal_edge.bus.busconfig.BusConfig` and
reads it in batches: from the event loop when the bus has a file descriptor (SocketCAN,
``udp_multicast``: every readiness drains what is waiting), else from a reader thread that
hands whole batches to the loop (``virtual``). Every message is checked and decoded with a
:class:`~thermal_edge.bus.codec.FrameCodec`; accepted frames go to a callback and/or an
``asyncio.Queue``.

A receive error on one message (a datagram python-can cannot unpack, a malformed frame) is
counted in ``stats.rx_undecodable``, logged at most every few seconds, and reading goes on.
Only a bus that is really gone (shut down, a socket error, :data:`RX_ERROR_RUN_LIMIT` errors in
a row) is torn down and reopened with exponential backoff. Sends never raise; cyclic senders
keep their cadence meanwhile, and can run in their own thread (``start_cyclic(thread=True)``),
independent of the event loop.

On interfaces that filter in the kernel (SocketCAN) only the identifiers this node receives are
let in (``can_filters``), so a full bus of foreign traffic costs no CPU. Elsewhere the filtering
happens in Python either way, and the codec's identifier lookup is that filter: it also counts
what it rejects (``unknown_id``), which python-can's software filter would drop uncounted.
"""

from __future__ import annotations

import asyncio
import collections
import inspect
import logging
import threading
import time
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

import can

from .busconfig import BusConfig, BusConfigError, create_bus
from .codec import DecodedFrame, FrameCodec
from .cyclic import CyclicSender, Fallback, SignalProvider
from .logs import LogRecorder
from .stats import TransportStats
from .udp import UndecodableDatagram

__all__ = ["RX_ERROR_RUN_LIMIT", "CanTransport", "FrameCallback"]

log = logging.getLogger(__name__)

#: Called with every accepted frame; may return an awaitable, which is awaited.
FrameCallback = Callable[[DecodedFrame], Any]

#: Receive errors in a row (no good message between them) after which the bus counts as dead.
RX_ERROR_RUN_LIMIT = 50
#: Messages read per readiness of the bus before the loop gets control back.
RX_BATCH_MAX = 512
#: Messages handled in a row before the consumer yields to the loop (cyclic senders, ticks).
RX_HANDLE_SLICE = 256
#: Received messages waiting to be handled above which reading pauses (the kernel queue waits).
RX_PENDING_MAX = 20_000
#: Least time between two warnings about undecodable messages, s (the count is exact).
RX_WARN_INTERVAL_S = 10.0
#: sends remembered per own identifier to tell our echoes from another node's frames. An echo comes
#: back within milliseconds, but the frame clock ticking through a gap sends a frame per tick at
#: once (up to ``clock.max_catchup_s`` = 3600 ticks) before the loop reads any echo; 4096 covers
#: that burst (a few MB at most, answered sends make room as they are read)
ECHO_MEMORY = 4096
#: Time a reader thread blocks in one receive, s (how fast it notices a stop).
RX_THREAD_POLL_S = 0.1


class EchoMemory:
    """The data of the last ``size`` sends of one identifier, each answering one echo, the oldest
    first; O(1) per send and per echo (a burst of thousands of sends is matched as fast as one).

    >>> m = EchoMemory(2)
    >>> m.add(b"a"); m.add(b"a"); m.add(b"b")  # the first "a" forgotten
    >>> m.take(b"a"), m.take(b"a"), m.take(b"b"), m.take(b"b")
    (True, False, True, False)
    """

    def __init__(self, size: int) -> None:
        self._size = size
        self._order: collections.deque[list[Any]] = collections.deque()  # [data, answered] in send order
        self._pending: dict[bytes, collections.deque[list[Any]]] = {}  # data -> its unanswered sends, oldest first

    def add(self, data: bytes) -> None:
        """Remember a send of ``data``."""
        entry = [data, False]
        self._order.append(entry)
        self._pending.setdefault(data, collections.deque()).append(entry)
        if len(self._order) > self._size:
            old = self._order.popleft()
            if not old[1]:  # unanswered: the oldest pending send of its data, forgotten
                self._drop(old[0])

    def take(self, data: bytes) -> bool:
        """Whether a remembered send of ``data`` is unanswered; it is answered by this echo."""
        if data not in self._pending:
            return False
        self._drop(data)[1] = True
        return True

    def _drop(self, data: bytes) -> list[Any]:
        queue = self._pending[data]
        entry = queue.popleft()
        if not queue:
            del self._pending[data]
        return entry


def _bus_gone(bus: can.BusABC, exc: BaseException) -> bool:
    """True if a receive error means the bus itself is gone, not one bad message."""
    return bool(getattr(bus, "_is_shutdown", False)) or isinstance(exc, OSError) or isinstance(exc.__cause__, OSError)


def _fileno(bus: can.BusABC) -> int:
    try:
        return int(bus.fileno())
    except (NotImplementedError, AttributeError, ValueError, OSError):
        return -1


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
    ...         bus.start_cyclic("TE_Limits", current_limits, fallback=SAFE_LIMITS, thread=True)
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
        #: identifiers let in by kernel filters (frames of the DBC this node does not send)
        self._rx_ids = (
            frozenset(self.codec.frame_ids()) - self._own_ids if self.config.node else frozenset()
        )
        self._bus: can.BusABC | None = None
        self._bus_lock = threading.Lock()  # bus and generation read together by sending threads
        self._send_lock = threading.Lock()  # encode + send of one frame, whichever thread sends
        self._pending: collections.deque[can.Message] = collections.deque()
        self._wake: asyncio.Event | None = None
        self._rx_fd = -1
        self._rx_paused = False
        self._rx_thread: threading.Thread | None = None
        self._rx_stop = threading.Event()
        self._rx_error_run = 0
        self._rx_warned_at = -float("inf")
        self._rx_unreported = 0
        # the data of the last frames sent per own identifier: a frame received with one of them
        # is our echo only if it carries data we sent (udp_multicast loops every send back);
        # anything else is another node sending this node's frames
        self._sent: dict[int, EchoMemory] = {i: EchoMemory(ECHO_MEMORY) for i in self._own_ids}
        self._sent_lock = threading.Lock()  # senders' threads append, the loop matches
        self._foreign_warned_at = -float("inf")
        self._foreign_unreported = 0
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
        self._recorder: LogRecorder | None = None

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
    def recorder(self) -> LogRecorder | None:
        """The recorder of the traffic, if recording."""
        return self._recorder

    async def wait_connected(self, timeout: float | None = None) -> bool:
        """Wait until the bus is open; False on timeout (in s)."""
        if self._connected is None:
            raise RuntimeError("transport not started")
        try:
            await asyncio.wait_for(self._connected.wait(), timeout)
        except TimeoutError:
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
        self._wake = asyncio.Event()
        self._failed = asyncio.Event()
        self._connected = asyncio.Event()
        self._stopping = False
        if self.config.record_path is not None and self._recorder is None:
            try:
                self._recorder = LogRecorder(self.config.record_path, channel=self.config.record_channel,
                                             max_bytes=self.config.record_max_bytes, keep=self.config.record_keep)
            except OSError as exc:  # a diagnostic recording is never worth the protection: without it
                log.error("CAN recording %s cannot be written (%s): recording off, the bus runs without it",
                          self.config.record_path, exc.strerror or exc)
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
        try:
            self._apply_filters(bus)
            fd = _fileno(bus)
            if fd >= 0:
                self._loop.add_reader(fd, self._read_ready, bus, generation)
        except Exception:
            bus.shutdown()
            raise
        self._rx_fd = fd
        self._rx_paused = False
        self._rx_error_run = 0
        if fd < 0:
            self._rx_stop = threading.Event()
            self._rx_thread = threading.Thread(
                target=self._read_thread, args=(bus, generation, self._rx_stop), name="can reader", daemon=True
            )
            self._rx_thread.start()
        with self._bus_lock:
            self._generation = generation
            self._bus = bus
            self._failed_flag = False
        self._opened_at = self._loop.time()
        self._consumer = self._loop.create_task(self._consume(), name="can receiver")
        if self._opened_once:
            self.stats.reconnects += 1
            log.warning("CAN bus %s reconnected", self._describe())
        else:
            log.info("CAN bus %s open", self._describe())
        self._opened_once = True
        self._connected.set()

    def _apply_filters(self, bus: can.BusABC) -> None:
        """Kernel filters for the identifiers this node receives, where the interface has them.

        python-can's software filtering (every other interface) is not kept: it would drop
        foreign identifiers before the codec counts them as ``unknown_id``, and saves nothing
        over the codec's own lookup.
        """
        if not self._rx_ids:
            return
        bus.set_filters([{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in sorted(self._rx_ids)])
        if not getattr(bus, "_is_filtered", False):
            bus.set_filters(None)

    def _describe(self) -> str:
        return f"{self.config.interface}:{self.config.channel if self.config.channel is not None else 'default'}"

    async def _teardown(self) -> None:
        if self._connected is not None:
            self._connected.clear()
        with self._bus_lock:
            bus, self._bus = self._bus, None
        consumer, self._consumer = self._consumer, None
        thread, self._rx_thread = self._rx_thread, None
        # synchronous part first: even if this coroutine is cancelled later, the bus is closed
        self._stop_reading()
        self._rx_stop.set()
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
        if thread is not None:
            await asyncio.to_thread(thread.join, 2 * RX_THREAD_POLL_S + 1.0)
        await self._handle_pending(slice_=None)  # frames that arrived before the stop

    def _note_bus_error(self, exc: BaseException, where: str) -> None:
        self.stats.bus_errors += 1
        log.warning("CAN bus %s error (%s): %s: %s", self._describe(), where, type(exc).__name__, exc)

    def _on_bus_error(self, exc: BaseException, where: str = "receive") -> None:
        """Mark the bus failed (any thread); the supervisor reconnects."""
        with self._bus_lock:
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
    def _stop_reading(self) -> None:
        if self._rx_fd >= 0 and self._loop is not None:
            try:
                self._loop.remove_reader(self._rx_fd)
            except Exception as exc:  # loop closing
                log.debug("remove_reader: %s", exc)
        self._rx_fd = -1

    def _read_ready(self, bus: can.BusABC, generation: int) -> None:
        """The bus's descriptor is readable: read what is waiting, up to a batch (on the loop)."""
        pending = self._pending
        n = 0
        while n < RX_BATCH_MAX:
            try:
                msg = bus.recv(0)
            except Exception as exc:
                if self._receive_error(bus, generation, exc):
                    self._stop_reading()
                    break
                continue
            if msg is None:
                break
            pending.append(msg)
            n += 1
        if n:
            self._rx_error_run = 0
            assert self._wake is not None
            self._wake.set()
        if len(pending) > RX_PENDING_MAX and self._rx_fd >= 0 and self._loop is not None:
            self._loop.remove_reader(self._rx_fd)  # the kernel queue holds the rest meanwhile
            self._rx_paused = True

    def _read_thread(self, bus: can.BusABC, generation: int, stop: threading.Event) -> None:
        """Reader of a bus without a descriptor: blocks in ``recv``, hands batches to the loop."""
        loop = self._loop
        assert loop is not None
        while not stop.is_set():
            batch: list[can.Message] = []
            try:
                msg = bus.recv(RX_THREAD_POLL_S)
                while msg is not None:
                    batch.append(msg)
                    if len(batch) >= RX_BATCH_MAX:
                        break
                    msg = bus.recv(0)
                error: Exception | None = None
            except Exception as exc:
                error = exc
            if batch:
                self._rx_error_run = 0
                try:
                    loop.call_soon_threadsafe(self._deliver, batch)
                except RuntimeError:  # loop closed
                    return
            if error is not None and self._receive_error(bus, generation, error):
                return

    def _deliver(self, batch: list[can.Message]) -> None:
        self._pending.extend(batch)
        if self._wake is not None:
            self._wake.set()

    def _receive_error(self, bus: can.BusABC, generation: int, exc: BaseException) -> bool:
        """Count one receive error; True (and a reconnect) if the bus is gone (any thread)."""
        if generation != self._generation or self._stopping:
            return True
        # a datagram that arrived but is no CAN message proves the socket works: never a reason to reopen,
        # however many come (a flood of them must not silence TE_Limits through reconnects)
        self._rx_error_run = 0 if isinstance(exc, UndecodableDatagram) else self._rx_error_run + 1
        if _bus_gone(bus, exc) or self._rx_error_run >= RX_ERROR_RUN_LIMIT:
            if self._rx_error_run >= RX_ERROR_RUN_LIMIT:
                log.warning("CAN bus %s: %d receive errors in a row", self._describe(), self._rx_error_run)
            self._on_bus_error(exc, "receive")
            return True
        self.stats.rx_undecodable += 1
        self._rx_unreported += 1
        now = time.monotonic()
        if now - self._rx_warned_at >= RX_WARN_INTERVAL_S:
            log.warning("CAN bus %s: %d undecodable message(s) ignored, bus kept open (last: %s: %s)",
                        self._describe(), self._rx_unreported, type(exc).__name__, exc)
            self._rx_warned_at, self._rx_unreported = now, 0
        return False

    async def _consume(self) -> None:
        assert self._wake is not None
        while True:
            await self._wake.wait()
            self._wake.clear()
            await self._handle_pending(slice_=RX_HANDLE_SLICE)
            if self._rx_paused and self._rx_fd >= 0 and self._bus is not None and self._loop is not None:
                self._rx_paused = False
                self._loop.add_reader(self._rx_fd, self._read_ready, self._bus, self._generation)

    async def _handle_pending(self, slice_: int | None) -> None:
        """Handle the waiting messages in order, yielding to the loop every ``slice_`` of them."""
        pending, n = self._pending, 0
        while pending:
            result = self._handle(pending.popleft())
            if result is not None:
                try:
                    await result
                except asyncio.CancelledError:
                    raise
                except Exception:
                    self.stats.callback_errors += 1
                    log.exception("frame callback failed")
            n += 1
            if slice_ is not None and n % slice_ == 0:
                await asyncio.sleep(0)

    def _handle(self, msg: can.Message) -> Awaitable[Any] | None:
        """Check, record and decode one message; the callback's awaitable, if it returned one."""
        if msg.arbitration_id in self._own_ids and not msg.is_extended_id:
            if self._is_echo(msg):
                self.stats.own_echo += 1
            else:
                self._foreign(msg)
            return None
        self.stats.rx_messages += 1
        if self._recorder is not None:
            # received by us, whatever the interface says: SocketCAN reports frames from another
            # local socket (vcan) as looped back, not received, and the log must mark them R
            msg.is_rx = True
            self._recorder.write(msg)
        frame = self.codec.decode_message(msg)
        if frame is None:
            return None
        if self.queue is not None:
            try:
                self.queue.put_nowait(frame)
            except asyncio.QueueFull:
                self.stats.queue_overflow += 1
        if self.on_frame is not None:
            try:
                result = self.on_frame(frame)
            except Exception:
                self.stats.callback_errors += 1
                log.exception("frame callback failed on %s", frame.name)
                return None
            if inspect.isawaitable(result):
                return result
        return None

    def _is_echo(self, msg: can.Message) -> bool:
        """Whether ``msg`` (one of this node's identifiers) carries data this node sent; each send
        answers one echo."""
        with self._sent_lock:
            sent = self._sent.get(msg.arbitration_id)
            return sent is not None and sent.take(bytes(msg.data))

    def _foreign(self, msg: can.Message) -> None:
        """Another node sends a frame of this node (two sources of ``TE_Limits`` on one bus: the
        inverter may obey either): counted, recorded as received, logged at ERROR at most every
        ``RX_WARN_INTERVAL_S``. Never obeyed: nothing here listens for commands."""
        self.stats.foreign_own_id += 1
        self._foreign_unreported += 1
        if self._recorder is not None:
            msg.is_rx = True
            self._recorder.write(msg)
        now = time.monotonic()
        if now - self._foreign_warned_at >= RX_WARN_INTERVAL_S:
            name = self.codec.frame_name(msg.arbitration_id)  # an own identifier: in the DBC
            log.error("CAN bus %s: %d frame(s) 0x%03X (%s) sent by another node, though this node sends them "
                      "(last data %s): two senders of %s on one bus", self._describe(), self._foreign_unreported,
                      msg.arbitration_id, name, bytes(msg.data).hex(" "), name)
            self._foreign_warned_at, self._foreign_unreported = now, 0

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
        with self._bus_lock:  # a sender thread may run while the loop reconnects
            bus, generation, failed = self._bus, self._generation, self._failed_flag
        if bus is None or failed:
            self.stats.tx_failed += 1
            return False
        try:
            ts = float(self.timestamp_fn())
        except Exception:  # a broken clock must not stop TE_Limits
            ts = time.time()
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False, is_rx=False, timestamp=ts)
        sent = self._sent.get(arbitration_id)
        if sent is not None:  # before the send: its echo may be read before send() returns
            with self._sent_lock:
                sent.add(bytes(data))
        try:
            bus.send(msg, timeout=self.config.send_timeout_s)
        except can.CanTimeoutError as exc:
            self.stats.tx_failed += 1
            log.debug("send 0x%03X timed out: %s", arbitration_id, exc)
            return False
        except Exception as exc:  # CanError, OSError, closed bus ...
            self.stats.tx_failed += 1
            if generation == self._generation:  # not a bus already replaced by a reconnect
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
        with self._send_lock:  # counter order on the bus, with a cyclic sender in its own thread
            data = self.codec.encode(frame, signals, counter=counter)
            return self.send_raw(self.codec.frame_id(frame), data)

    def start_cyclic(
        self,
        frame: str | int,
        provider: SignalProvider,
        *,
        period_s: float | None = None,
        fallback: Fallback | None = None,
        thread: bool = False,
        on_sent: Callable[[float], None] | None = None,
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
        thread : bool, optional
            Send from a daemon thread of its own on a monotonic fixed-rate schedule, so that
            nothing on the event loop can delay the frame (``TE_Limits``); the provider is
            then called in that thread and must be a plain, thread-safe function.
        on_sent : callable(float), optional
            Given the interval since the previous frame sent, after each (s; see :class:`CyclicSender`).

        Returns
        -------
        CyclicSender
            The running sender (``stop()`` it to end early).
        """
        sender = CyclicSender(
            self.codec, self.send_raw, frame, provider, period_s=period_s, fallback=fallback, stats=self.stats,
            thread=thread, send_lock=self._send_lock, on_sent=on_sent,
        )
        self._cyclic.append(sender)
        return sender.start()

