"""The /metrics endpoint: bounded threads, idle connections closed, scrapes still answered."""
from __future__ import annotations

import socket
import threading
import time
import urllib.request

from prometheus_client import CollectorRegistry, Counter

from thermal_edge.service.metrics_server import IDLE_TIMEOUT_S, MAX_CONNECTIONS, MetricsServer


def _scrape(port: int) -> str:
    return urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()


def test_idle_connections_do_not_pile_up_threads_and_scrapes_come_back():
    reg = CollectorRegistry()
    Counter("probe", "a probe", registry=reg).inc(3)
    server = MetricsServer(reg, "127.0.0.1", 0)
    port = server.address[1]
    try:
        assert "probe_total 3.0" in _scrape(port)
        base = threading.active_count()
        idle = [socket.create_connection(("127.0.0.1", port)) for _ in range(200)]
        deadline = time.monotonic() + 10
        while server.rejected < 200 - MAX_CONNECTIONS and time.monotonic() < deadline:
            # counted another way: the threads that exist, against the bound, all along
            assert threading.active_count() - base <= MAX_CONNECTIONS
            time.sleep(0.05)
        assert threading.active_count() - base <= MAX_CONNECTIONS
        # all but the served ones closed on arrival (a slow host may free a slot by the idle timeout meanwhile)
        assert 200 - 4 * MAX_CONNECTIONS <= server.rejected <= 200 - MAX_CONNECTIONS
        for s in idle:
            s.close()
        # the idle ones that held a slot are closed by the server within its idle timeout
        deadline = time.monotonic() + IDLE_TIMEOUT_S + 5
        text = ""
        while time.monotonic() < deadline:
            try:
                text = _scrape(port)
                break
            except OSError:
                time.sleep(0.2)
        assert "probe_total 3.0" in text
        time.sleep(IDLE_TIMEOUT_S + 0.5)
        assert threading.active_count() <= base
    finally:
        server.close()


def test_a_client_that_never_finishes_its_request_is_cut_off():
    server = MetricsServer(CollectorRegistry(), "127.0.0.1", 0)
    try:
        s = socket.create_connection(("127.0.0.1", server.address[1]))
        s.sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\n")  # no blank line: the request never ends
        s.settimeout(IDLE_TIMEOUT_S + 5)
        t0 = time.monotonic()
        assert s.recv(100) == b""  # closed by the server
        assert time.monotonic() - t0 < IDLE_TIMEOUT_S + 4
        s.close()
    finally:
        server.close()


def test_the_default_endpoint_cannot_be_reached_from_beyond_the_host():
    """Bound to 127.0.0.1 as configured by default: a connection to the host's own network address
    (as a client on the network would make) is refused, one to loopback is served."""
    import pytest

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("198.51.100.1", 9))  # route lookup only, nothing is sent
            own = s.getsockname()[0]
        except OSError:
            own = "127.0.0.1"
    if own.startswith("127."):
        pytest.skip("this host has no non-loopback IPv4 address to connect to")
    from thermal_edge.config import load_config
    from svc_testlib import EDGE_YAML

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
