"""The ``/metrics`` HTTP endpoint with bounded threads and an idle timeout.

prometheus_client's ``start_http_server`` starts one thread per connection and waits forever for
a request on each: 200 idle connections are 200 threads (the unit allows ``TasksMax=64``), and
creating them contends with ``TE_Limits`` for the interpreter. Here at most
:data:`MAX_CONNECTIONS` connections are served at once, a connection that sends no complete
request within :data:`IDLE_TIMEOUT_S` is closed, and a connection beyond the bound is closed at
once and counted. A Prometheus scrape needs one connection for milliseconds.
"""
from __future__ import annotations

import logging
import socket
import threading
from socketserver import ThreadingMixIn
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, make_wsgi_app

__all__ = ["IDLE_TIMEOUT_S", "MAX_CONNECTIONS", "MetricsServer"]

log = logging.getLogger(__name__)

#: Connections served at once; more are closed on arrival.
MAX_CONNECTIONS = 8
#: Seconds a connection may take to send its request (socket timeout of the handler).
IDLE_TIMEOUT_S = 3.0


class _Handler(WSGIRequestHandler):
    timeout = IDLE_TIMEOUT_S

    def log_message(self, format: str, *args: Any) -> None:
        pass  # a scrape is not an event

    def handle(self) -> None:
        try:
            super().handle()
        except (TimeoutError, ConnectionError):
            pass  # idle or vanished client: the connection closes, the slot frees


class _BoundedServer(ThreadingMixIn, WSGIServer):
    daemon_threads = True
    block_on_close = False
    request_queue_size = 128  # a burst of connections waits in the kernel, not in SYN retries

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self.rejected = 0
        super().__init__(*args, **kwargs)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self.slots.acquire(blocking=False):
            self.rejected += 1
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except Exception:  # no thread could be started: free the slot, drop the connection
            self.slots.release()
            self.shutdown_request(request)
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()

    def handle_error(self, request: Any, client_address: Any) -> None:
        log.debug("metrics request from %s failed", client_address, exc_info=True)


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
        family = socket.AF_INET6 if ":" in address else socket.AF_INET

        class Server(_BoundedServer):
            address_family = family

        self._httpd = make_server(address, port, make_wsgi_app(registry), Server, handler_class=_Handler)
        self._thread = threading.Thread(target=self._httpd.serve_forever, name="metrics http", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        """The bound (address, port)."""
        host, port = self._httpd.server_address[:2]
        return str(host), int(port)

    @property
    def rejected(self) -> int:
        """Connections closed on arrival because :data:`MAX_CONNECTIONS` were being served."""
        return self._httpd.rejected

    def close(self) -> None:
        """Stop serving and close the listening socket."""
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(timeout=2.0)
