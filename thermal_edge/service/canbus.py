"""The service's buses: ones that keep frame timestamps.

(Sent frames carry the service's clock through ``CanTransport(timestamp_fn=...)``, so a candump
log of a replay or an accelerated run is in one time base.)

- :func:`bus_factory` -- opens the configured bus with :func:`thermal_edge.bus.create_bus`; with
  ``preserve_timestamps: true`` the receiver keeps the sender's timestamps (``virtual`` supports
  this natively; ``udp_multicast`` through :class:`~thermal_edge.bus.udp.LocalUdpMulticastBus`),
  which is how simulated time travels with the frames. ``udp_multicast`` sockets also get a
  larger receive buffer (``rcvbuf_bytes``, default 4 MiB) so that short stalls of the receiver
  do not drop datagrams, and take frames from this host only.
"""
from __future__ import annotations

import can

from ..bus.busconfig import BusConfig, create_bus

__all__ = ["bus_factory"]


def bus_factory(config: BusConfig) -> can.BusABC:
    """Open the bus of a configuration (see the module docstring for the extras)."""
    return create_bus(config)
