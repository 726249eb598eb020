"""The ``/metrics`` HTTP endpoint: one thread, every connection bounded in time, the newest served.

prometheus_client's ``start_http_server`` starts one thread per connection and waits forever for
a request on each: 200 idle connections are 200 threads (the unit allows ``TasksMax=64``), and
creating them contends with ``TE_Limits`` for the interpreter. Serving a fixed number of
connections on threads and closing any further one on arrival is no better: a client holding 300
slow or 2,000 idle connections keeps every scrape out (Prometheus gets an empty reply and the
dashboards go blank).

Here one thread multiplexes every connection (:mod:`selectors`):

* a connection must deliver its complete request **and** take its response within
  :data:`IDLE_TIMEOUT_S` of its arrival: an absolute deadline, so a sender that dribbles a byte at
  a time gains nothing;
* at most :data:`MAX_CONNECTIONS` are open; a new one closes the one that has waited longest
  without an answer. A scrape sends its request within milliseconds of connecting, so the oldest
  waiting connection is an idle or slow one, and a client holding any number of connections cannot
  keep a scrape out: it would have to open :data:`MAX_CONNECTIONS` new ones within those
  milliseconds;
* a request head longer than :data:`MAX_REQUEST_BYTES` is answered ``431`` and closed.

The answer is prometheus_client's own WSGI application (content negotiation, gzip, ``name[]``)
called with the request's environment, one request per connection (``Connection: close``).
"""
from __future__ import annotations

import logging
import selectors
import socket
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any
from urllib.parse import unquote

from prometheus_client import CollectorRegistry, make_wsgi_app

__all__ = ["IDLE_TIMEOUT_S", "MAX_CONNECTIONS", "MAX_REQUEST_BYTES", "MetricsServer"]

log = logging.getLogger(__name__)

#: Connections open at once; a new one closes the one waiting longest without an answer.
MAX_CONNECTIONS = 64
#: Seconds from a connection's arrival within which its request must be complete and its answer sent.
IDLE_TIMEOUT_S = 3.0
#: Longest request head accepted (request line and headers), bytes.
MAX_REQUEST_BYTES = 8192
#: Listening backlog: a burst of connections waits in the kernel, not in SYN retries.
BACKLOG = 128


class _Connection:
    """One client connection: what it sent, what it is owed, and by when."""

    __slots__ = ("sock", "deadline", "inbuf", "outbuf", "answered")

    def __init__(self, sock: socket.socket, deadline: float) -> None:
        self.sock = sock
        self.deadline = deadline
        self.inbuf = b""
        self.outbuf = b""
        self.answered = False  # a response was queued (the connection is no longer waiting)


def _head_end(buf: bytes) -> int:
    """Where the request head in ``buf`` ends (before its blank line), or -1: lines end in CRLF, or
    in a bare LF, which RFC 9112 lets a server accept (a hand-typed ``printf`` or ``nc`` request)."""
    ends = [i for i in (buf.find(b"\r\n\r\n"), buf.find(b"\n\n")) if i >= 0]
    return min(ends, default=-1)


def _environ(head: bytes) -> dict[str, Any] | None:
    """The WSGI environment of a request head (request line and headers), or None if malformed."""
    lines = [line.rstrip("\r") for line in head.decode("latin-1").split("\n")]
    parts = lines[0].split()
    if len(parts) != 3 or not parts[2].startswith("HTTP/"):
        return None
    method, target, version = parts
    path, _, query = target.partition("?")
    env: dict[str, Any] = {"REQUEST_METHOD": method, "PATH_INFO": unquote(path), "QUERY_STRING": query,
                           "SERVER_PROTOCOL": version, "wsgi.url_scheme": "http"}
    for line in lines[1:]:
        name, sep, value = line.partition(":")
        if sep and name.strip():
            env["HTTP_" + name.strip().upper().replace("-", "_")] = value.strip()
    return env


def _response(status: str, headers: Iterable[tuple[str, str]], body: bytes, head_only: bool = False) -> bytes:
    lines = [f"HTTP/1.1 {status}", *(f"{k}: {v}" for k, v in headers), f"Content-Length: {len(body)}", "Connection: close"]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + (b"" if head_only else body)


class MetricsServer:
    """Serves a registry on ``http://address:port/metrics`` from a daemon thread.

    Parameters
    ----------
    registry : CollectorRegistry
        What is served.
    address : str
        Address to bind (``127.0.0.1`` by default in the configuration; an IPv6 address works).
    port : int
        TCP port; 0 picks a free one.
    """

    def __init__(self, registry: CollectorRegistry, address: str, port: int) -> None:
        self._app: Callable[..., Iterable[bytes]] = make_wsgi_app(registry)
        family = socket.AF_INET6 if ":" in address else socket.AF_INET
        self._listener = socket.socket(family, socket.SOCK_STREAM)
        try:
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind((address, port))
            self._listener.listen(BACKLOG)
        except OSError:
            self._listener.close()
            raise
        self._listener.setblocking(False)
        self._wake_r, self._wake_w = socket.socketpair()
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ)
        self._selector.register(self._wake_r, selectors.EVENT_READ)
        # by file number, in order of arrival, hence of deadline (arrival + IDLE_TIMEOUT_S)
        self._open: dict[int, _Connection] = {}
        self._stopping = False
        #: connections closed without an answer (dropped for a newer one, or too slow)
        self.rejected = 0
        self._thread = threading.Thread(target=self._serve, name="metrics http", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        """The bound (address, port)."""
        host, port = self._listener.getsockname()[:2]
        return str(host), int(port)

    def close(self) -> None:
        """Stop serving and close the listening socket and every connection."""
        self._stopping = True
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass
        self._thread.join(timeout=2.0)
        for conn in list(self._open.values()):
            self._close(conn)
        self._selector.close()
        for s in (self._listener, self._wake_r, self._wake_w):
            s.close()

    # -- the serving thread ---------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stopping:
            now = time.monotonic()
            oldest = next(iter(self._open.values()), None)  # the earliest deadline: they follow arrival
            wait = (oldest.deadline if oldest is not None else now + 1.0) - now
            try:
                events = self._selector.select(min(1.0, max(0.0, wait)))
                for key, mask in events:
                    if key.fileobj is self._listener:
                        self._accept()
                    elif key.fileobj is self._wake_r:
                        return
                    elif mask & selectors.EVENT_WRITE:
                        self._send(key.data)
                    else:
                        self._receive(key.data)
                self._expire(time.monotonic())
            except Exception:  # the endpoint must outlive anything a client does
                log.warning("metrics endpoint: unexpected error, connections reset", exc_info=True)
                for conn in list(self._open.values()):
                    self._close(conn)

    def _accept(self) -> None:
        while True:
            try:
                sock, _ = self._listener.accept()
            except BlockingIOError:
                return
            except OSError:  # out of file descriptors: free the oldest waiting connection's
                self._drop_oldest()
                return
            sock.setblocking(False)
            if len(self._open) >= MAX_CONNECTIONS:
                self._drop_oldest()
            conn = _Connection(sock, time.monotonic() + IDLE_TIMEOUT_S)
            self._open[sock.fileno()] = conn
            self._selector.register(sock, selectors.EVENT_READ, conn)

    def _drop_oldest(self) -> None:
        """Close the connection that has waited longest without an answer (else the oldest)."""
        if not self._open:
            return
        waiting = (c for c in self._open.values() if not c.answered)
        self._close(next(waiting, next(iter(self._open.values()))))

    def _receive(self, conn: _Connection) -> None:
        try:
            data = conn.sock.recv(4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # the client closed (or reset)
            self._close(conn)
            return
        if conn.answered:  # after the answer: read and discard until the client closes
            return
        conn.inbuf += data
        end = _head_end(conn.inbuf)
        if end < 0:
            if len(conn.inbuf) > MAX_REQUEST_BYTES:
                self._answer(conn, _response("431 Request Header Fields Too Large", [], b""))
            return
        env = _environ(conn.inbuf[:end])
        if env is None:
            self._answer(conn, _response("400 Bad Request", [], b""))
            return
        captured: list[Any] = []
        try:
            body = b"".join(self._app(env, lambda status, headers, exc_info=None: captured.extend((status, headers))))
            status, headers = captured[0], captured[1]
        except Exception:  # a collector that fails: this request gets a 500, the others are untouched
            log.warning("metrics endpoint: collecting the metrics failed", exc_info=True)
            status, headers, body = "500 Internal Server Error", [], b""
        self._answer(conn, _response(status, headers, body, head_only=env["REQUEST_METHOD"] == "HEAD"))

    def _answer(self, conn: _Connection, payload: bytes) -> None:
        conn.answered = True
        conn.outbuf = payload
        conn.inbuf = b""
        self._selector.modify(conn.sock, selectors.EVENT_WRITE, conn)
        self._send(conn)

    def _send(self, conn: _Connection) -> None:
        try:
            sent = conn.sock.send(conn.outbuf)
        except BlockingIOError:
            return
        except OSError:
            self._close(conn)
            return
        conn.outbuf = conn.outbuf[sent:]
        if not conn.outbuf:
            # lingering close: stop sending, read until the client closes (closing with unread
            # bytes would reset the connection and could lose the answer in the client's kernel)
            try:
                conn.sock.shutdown(socket.SHUT_WR)
            except OSError:
                self._close(conn)
                return
            self._selector.modify(conn.sock, selectors.EVENT_READ, conn)

    def _expire(self, now: float) -> None:
        """Close the connections past their deadline: the oldest ones, as ``_open`` keeps arrival order."""
        while self._open:
            conn = next(iter(self._open.values()))
            if conn.deadline > now:
                return
            self._close(conn)

    def _close(self, conn: _Connection) -> None:
        if self._open.pop(conn.sock.fileno(), None) is None:
            return
        if not conn.answered:
            self.rejected += 1
        try:
            self._selector.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        conn.sock.close()
