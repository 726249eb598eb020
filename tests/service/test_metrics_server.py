"""The /metrics endpoint: one thread, connections bounded in time and number, scrapes answered under abuse."""
from __future__ import annotations

import resource
import socket
import threading
import time
import urllib.error
import urllib.request

import pytest
from prometheus_client import CollectorRegistry, Counter

from benchmarks.faults.bus import open_connections
from thermal_edge.service.metrics_server import IDLE_TIMEOUT_S, MAX_CONNECTIONS, MetricsServer

#: generous upper bound of a wait (a hang guard, not a performance bound), s
HANG_S = 300.0


def _scrape(port: int) -> str:
    return urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=HANG_S / 5).read().decode()


def _ended(s: socket.socket) -> bool:
    """The server closed this (non-blocking, idle) connection: end of stream, or a reset."""
    try:
        return s.recv(1) == b""
    except (BlockingIOError, OSError) as exc:
        return isinstance(exc, ConnectionResetError)


def test_idle_connections_held_do_not_keep_a_scrape_out_nor_add_threads():
    """2,000 idle connections held by one client must not leave a scrape unanswered."""
    reg = CollectorRegistry()
    Counter("probe", "a probe", registry=reg).inc(3)
    server = MetricsServer(reg, "127.0.0.1", 0)
    port = server.address[1]
    try:
        assert "probe_total 3.0" in _scrape(port)
        base = threading.active_count()
        n = min(2000, resource.getrlimit(resource.RLIMIT_NOFILE)[0] - 200)  # as many as this process may open
        held = open_connections(port, n)
        try:
            time.sleep(0.5)
            # scrapes while the connections are held, each answered
            for _ in range(5):
                assert "probe_total 3.0" in _scrape(port)
            # counted another way: no thread per connection
            assert threading.active_count() == base
            # the idle ones the server took were closed unanswered (dropped for newer ones, or at their
            # deadline), each counted by the server, and more of them than the bound: counted again on
            # the client's side as the end of stream each sees. (A busy host's server may take its
            # connections late; the ones its kernel never completed are nobody's to count.)
            deadline = time.monotonic() + HANG_S
            while time.monotonic() < deadline:
                ended = sum(1 for s in held if _ended(s))
                if server.rejected == ended > MAX_CONNECTIONS:
                    break
                time.sleep(0.1)
            assert server.rejected == ended > MAX_CONNECTIONS, (server.rejected, ended)
        finally:
            for s in held:
                s.close()
    finally:
        server.close()


def test_slow_senders_are_cut_at_their_deadline_and_a_scrape_gets_through():
    """A client dribbling its request a byte at a time gains nothing: the deadline counts from its
    arrival (300 slow senders held kept every scrape out before)."""
    server = MetricsServer(CollectorRegistry(), "127.0.0.1", 0)
    port = server.address[1]
    t0 = time.monotonic()
    slow = open_connections(port, 300)
    try:
        request = b"GET /metrics HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * 200
        for s in slow:  # each has started its request
            try:
                s.send(request[:1])
            except OSError:
                pass
        scraped = [_scrape(port) for _ in range(3)]  # while they are held
        closed: dict[int, float] = {}
        k = 1
        # a generous window: without a deadline from arrival a dribbling sender is never cut off, with
        # it every one is closed; how soon depends on when the server accepted it (late on a busy host)
        while time.monotonic() - t0 < IDLE_TIMEOUT_S + 60 and len(closed) < len(slow):
            for i, s in enumerate(slow):
                if i in closed:
                    continue
                try:
                    s.send(request[k:k + 1])
                    if s.recv(1) == b"":
                        closed[i] = time.monotonic() - t0
                except BlockingIOError:
                    pass
                except OSError:
                    closed[i] = time.monotonic() - t0
            k = min(k + 1, len(request) - 1)
            time.sleep(0.1)
        assert scraped == ["", "", ""]  # an empty registry, answered each time
        # every slow sender cut off although it kept sending: activity never extends a deadline
        assert len(closed) == len(slow)
    finally:
        for s in slow:
            s.close()
        server.close()


def test_a_client_that_never_finishes_its_request_is_cut_off():
    server = MetricsServer(CollectorRegistry(), "127.0.0.1", 0)
    try:
        s = socket.create_connection(("127.0.0.1", server.address[1]))
        s.sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\n")  # no blank line: the request never ends
        s.settimeout(IDLE_TIMEOUT_S + 60)  # a generous upper bound: the server's deadline is 3 s
        assert s.recv(100) == b""  # closed by the server, not by the client's time-out
        s.close()
    finally:
        server.close()


def test_the_default_endpoint_cannot_be_reached_from_beyond_the_host():
    """Bound to 127.0.0.1 as configured by default: a connection to the host's own network address
    (as a client on the network would make) is refused, one to loopback is served."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("198.51.100.1", 9))  # route lookup only, nothing is sent
            own = s.getsockname()[0]
        except OSError:
            own = "127.0.0.1"
    if own.startswith("127."):
        pytest.skip("this host has no non-loopback IPv4 address to connect to")
    from svc_testlib import EDGE_YAML

    from thermal_edge.config import load_config

    address = load_config(EDGE_YAML).metrics.address
    assert address == "127.0.0.1"
    server = MetricsServer(CollectorRegistry(), address, 0)
    try:
        port = server.address[1]
        try:
            socket.create_connection((own, port), timeout=3).close()
            reached = True
        except OSError:  # ConnectionRefusedError
            reached = False
        assert not reached, f"{own}:{port} accepted a connection"
        assert _scrape(port) == ""  # an empty registry, but served on loopback
    finally:
        server.close()


@pytest.mark.parametrize("request_bytes", [b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n", b"GET /metrics HTTP/1.0\n\n",
                                           b"GET /metrics?name[]=probe_total HTTP/1.1\r\nAccept-Encoding: gzip\r\n\r\n"],
                         ids=["crlf", "bare-lf", "gzip-and-filter"])
def test_a_request_typed_by_hand_is_answered_as_prometheus_client_answers_it(request_bytes):
    """The answer is prometheus_client's own (content, encoding, ``name[]``), read back with the
    standard library; a request with bare LF line ends (``printf ... | nc``) is answered too."""
    import gzip

    reg = CollectorRegistry()
    Counter("probe", "a probe", registry=reg).inc(3)
    Counter("other", "another", registry=reg).inc(1)
    server = MetricsServer(reg, "127.0.0.1", 0)
    try:
        with socket.create_connection(("127.0.0.1", server.address[1]), timeout=5) as s:
            s.sendall(request_bytes)
            data = b""
            while chunk := s.recv(65536):
                data += chunk
        head, _, body = data.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 200 OK")
        headers = dict(line.split(": ", 1) for line in head.decode().split("\r\n")[1:])
        assert int(headers["Content-Length"]) == len(body)
        if headers.get("Content-Encoding") == "gzip":
            body = gzip.decompress(body)
        text = body.decode()
        assert "probe_total 3.0" in text
        assert ("other_total" in text) == (b"name[]" not in request_bytes)
    finally:
        server.close()


def test_a_failing_collector_costs_its_request_a_500_and_the_endpoint_serves_on():
    class Flaky:
        fail = True

        def collect(self):
            if Flaky.fail:
                raise RuntimeError("collector broke")
            yield from Counter("probe", "a probe", registry=None).collect()

    reg = CollectorRegistry()
    reg.register(Flaky())
    server = MetricsServer(reg, "127.0.0.1", 0)
    try:
        idle = open_connections(server.address[1], 3)  # other connections, open meanwhile
        time.sleep(0.2)
        with pytest.raises(urllib.error.HTTPError) as err:
            _scrape(server.address[1])
        assert err.value.code == 500
        Flaky.fail = False
        assert "probe_total 0.0" in _scrape(server.address[1])
        for s in idle:  # still open: nothing to read, no end of stream (the failure closed no other connection)
            with pytest.raises(BlockingIOError):
                s.recv(1)
        for s in idle:
            s.close()
    finally:
        server.close()

