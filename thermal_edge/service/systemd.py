"""systemd readiness, status and watchdog notification (``sd_notify`` written by hand).

Messages go as one datagram to the unix socket named by ``NOTIFY_SOCKET`` (a path, or an
abstract address starting with ``@``). Without ``NOTIFY_SOCKET`` (not run by systemd) every call
is a no-op. The watchdog interval is half of ``WATCHDOG_USEC`` (only when ``WATCHDOG_PID`` is
unset or ours), as ``sd_watchdog_enabled`` recommends.
"""
from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

__all__ = ["SystemdNotifier"]

log = logging.getLogger(__name__)


class SystemdNotifier:
    """Send ``READY=1``, ``STATUS=…``, ``WATCHDOG=1``, ``STOPPING=1`` to systemd.

    Parameters
    ----------
    environ : mapping, optional
        Where to read ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` (default
        ``os.environ``).
    """

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        addr = env.get("NOTIFY_SOCKET") or None
        self.address: str | bytes | None = None
        if addr:
            if addr.startswith("@"):
                self.address = b"\0" + addr[1:].encode()
            elif addr.startswith("/"):
                self.address = addr
            else:
                log.warning("NOTIFY_SOCKET=%r is neither a path nor an abstract address: not notifying", addr)
        self.watchdog_interval_s: float | None = None
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        if usec and (not pid or pid == str(os.getpid())):
            try:
                value = int(usec)
                if value > 0:
                    self.watchdog_interval_s = value / 2e6
            except ValueError:
                log.warning("WATCHDOG_USEC=%r is not an integer: watchdog disabled", usec)
        self._sock: socket.socket | None = None
        self.sent = 0
        self.errors = 0

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, message: str) -> bool:
        """Send one notification (``KEY=VALUE`` lines); False if not under systemd or it failed."""
        if self.address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                self._sock.setblocking(False)
            self._sock.sendto(message.encode(), self.address)
        except OSError as exc:
            self.errors += 1
            if self.errors == 1:
                log.warning("cannot notify systemd at %r: %s", self.address, exc)
            return False
        self.sent += 1
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        return self.notify("STOPPING=1" + (f"\nSTATUS={status}" if status else ""))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
