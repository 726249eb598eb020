"""``thermal-edge monitor``: a live view of a running service, refreshed in place.

From its metrics endpoint (default ``http://127.0.0.1:9108/metrics``): limits and reason, the
limited nodes' estimates with their 95 % bands, look-ahead, prediction error, adaptation, sensors
and input freshness. With ``--bus`` it listens to the CAN bus instead (read only: it never sends)
and shows what the inverter sees: the ``TE_*`` frames and the age of every frame on the bus.

Examples::

    thermal-edge monitor                                   # the local service's /metrics
    thermal-edge monitor --bus --config /etc/thermal-edge/edge.yaml
    thermal-edge monitor --once > snapshot.txt             # one screen, for a ticket
"""
from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING

from ..errors import UsageError
from .options import http_url, integer, number

if TYPE_CHECKING:
    from ..config import EdgeConfig

DEFAULT_URL = "http://127.0.0.1:9108/metrics"
CLEAR = "\x1b[H\x1b[2J"


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("monitor", help="live view of a running service (metrics or bus)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--metrics", type=http_url, default=DEFAULT_URL, metavar="URL",
                   help=f"metrics endpoint (default {DEFAULT_URL})")
    p.add_argument("--bus", action="store_true", help="listen to the CAN bus instead of the metrics endpoint")
    p.add_argument("--config", help="edge.yaml whose bus: section names the bus (with --bus)")
    p.add_argument("--interface", help="python-can interface (with --bus; default: the config's)")
    p.add_argument("--channel", help="bus channel (with --bus; default: the config's)")
    p.add_argument("--interval", type=number(0.05, 3600, unit="s"), default=1.0, help="seconds between refreshes (default 1)")
    p.add_argument("--once", action="store_true", help="print one screen and exit (bus: after listening one interval)")
    p.add_argument("--count", type=integer(1), default=None, help="stop after this many screens (default: until Ctrl-C)")
    p.set_defaults(func=run)


def _bus_config(args: argparse.Namespace, config: EdgeConfig | None = None) -> dict[str, object]:
    """The bus to listen on: the configuration's (``config``, loaded from ``--config``), with
    ``--interface``/``--channel`` over it."""
    raw: dict[str, object] = {}
    if config is not None:
        bus = config.bus
        raw = {"interface": bus.interface, "channel": bus.channel, **bus.options}
    if args.interface:
        raw["interface"] = args.interface
    if args.channel:
        raw["channel"] = args.channel
    if "interface" not in raw:
        raise UsageError("--bus needs --config or --interface")
    return raw


class _Screen:
    """Writes screens: in place on a terminal, one after another (blank line between) otherwise."""

    def __init__(self, in_place: bool) -> None:
        self.in_place = in_place
        self.shown = 0

    def show(self, text: str) -> None:
        sys.stdout.write((CLEAR if self.in_place else ("\n" if self.shown else "")) + text + "\n")
        sys.stdout.flush()
        self.shown += 1


def run(args: argparse.Namespace) -> int:
    limit = 1 if args.once else args.count
    screen = _Screen(sys.stdout.isatty() and not args.once)
    if args.bus:
        return _run_bus(args, screen, limit)
    from ..monitor.snapshot import fetch_metrics, from_metrics
    from ..monitor.view import render

    while True:
        t0 = time.monotonic()
        try:
            snap = from_metrics(fetch_metrics(args.metrics), args.metrics)
        except OSError as exc:
            if limit == 1:
                print(f"thermal-edge monitor: error: {args.metrics}: {getattr(exc, 'reason', exc)}", file=sys.stderr)
                return 2
            screen.show(f"thermal-edge monitor  {args.metrics}\n\nservice not reachable: {getattr(exc, 'reason', exc)}")
        else:
            screen.show(render(snap))
        if limit and screen.shown >= limit:
            return 0
        time.sleep(max(0.0, args.interval - (time.monotonic() - t0)))


def _run_bus(args: argparse.Namespace, screen: _Screen, limit: int | None) -> int:
    import can

    from ..bus import BusConfig, BusConfigError, FrameCodec, create_bus
    from ..monitor.snapshot import FrameWatch
    from ..monitor.view import render

    config = None
    if args.config:  # its bus, and its CAN matrix: the inverter's own frames are the ones read
        from ..config import load_config

        config = load_config(args.config)
    try:
        cfg = BusConfig.coerce(_bus_config(args, config))
    except BusConfigError as exc:
        raise UsageError(f"--bus: {str(exc).strip().splitlines()[0]}") from None
    codec = config.codec.frame_codec(config.fname) if config is not None else FrameCodec()
    cycles = {codec.frame_name(fid): c for fid in codec.frame_ids() if (c := codec.cycle_time_s(fid))}
    watch = FrameWatch(f"bus {cfg.interface}:{cfg.channel}", cycles)
    try:
        bus = create_bus(cfg)
    except (OSError, can.CanError, ImportError, ValueError) as exc:  # no such interface, no SocketCAN on this host
        why = getattr(exc, "strerror", None) or str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UsageError(f"--bus: cannot open {cfg.interface} bus {cfg.channel!r}: {why}") from None
    try:
        next_t = time.monotonic() + args.interval
        while True:
            msg = bus.recv(timeout=max(0.0, next_t - time.monotonic()))
            if msg is not None:
                frame = codec.decode_message(msg)
                if frame is not None:
                    watch.add(frame)
            if time.monotonic() >= next_t:
                screen.show(render(watch.current()))
                if limit and screen.shown >= limit:
                    return 0
                next_t += args.interval
    finally:
        bus.shutdown()
