"""The service's buses: ones that keep frame timestamps.

(Sent frames carry the service's clock through ``CanTransport(timestamp_fn=...)``, so a candump
log of a replay or an accelerated run is in one time base.)

- :func:`bus_factory` -- opens the configured bus; with ``preserve_timestamps: true`` in the bus
  options the receiver keeps the sender's timestamps (``virtual`` supports this natively;
  ``udp_multicast`` through :class:`TimestampedUdpMulticastBus`), which is how simulated time
  travels with the frames. ``udp_multicast`` sockets also get a larger receive buffer
  (``rcvbuf_bytes``, default 4 MiB) so that short stalls of the receiver do not drop datagrams.
"""
from __future__ import annotations

import logging
from typing import Any

import can
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.utils import unpack_message

from ..bus.busconfig import RECEIVE_QUEUE_BYTES, BusConfig, _assert_hop_limit_zero, bus_kwargs, create_bus, enlarge_receive_queue

__all__ = ["TimestampedUdpMulticastBus", "bus_factory"]

log = logging.getLogger(__name__)

class TimestampedUdpMulticastBus(UdpMulticastBus):
    """``udp_multicast`` bus that can keep the sender's message timestamps on reception."""

    def __init__(self, *args: Any, preserve_timestamps: bool = False, rcvbuf_bytes: int = RECEIVE_QUEUE_BYTES,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.preserve_timestamps = bool(preserve_timestamps)
        sock = getattr(getattr(self, "_multicast", None), "_socket", None)
        if sock is not None and rcvbuf_bytes:
            enlarge_receive_queue(sock, rcvbuf_bytes)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self.preserve_timestamps:
            return super()._recv_internal(timeout)
        result = self._multicast.recv(timeout)
        if not result:
            return None, False
        data, _, kernel_ts = result
        try:
            msg = unpack_message(data, check=True)
        except Exception as exc:
            raise can.CanOperationError("could not unpack received message") from exc
        if not msg.timestamp:
            msg.timestamp = kernel_ts
        return msg, False


def bus_factory(config: BusConfig) -> can.BusABC:
    """Open the bus of a configuration (see the module docstring for the extras)."""
    if config.interface != "udp_multicast":
        return create_bus(config)
    kwargs = bus_kwargs(config)
    kwargs.pop("interface")
    preserve = bool(kwargs.pop("preserve_timestamps", False))
    rcvbuf = int(kwargs.pop("rcvbuf_bytes", RECEIVE_QUEUE_BYTES))
    bus = TimestampedUdpMulticastBus(preserve_timestamps=preserve, rcvbuf_bytes=rcvbuf, **kwargs)
    _assert_hop_limit_zero(bus)
    return bus
