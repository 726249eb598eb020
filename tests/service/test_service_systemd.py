"""sd_notify written by hand: path and abstract sockets, watchdog interval, no-op outside systemd."""
from __future__ import annotations

import os

from svc_testlib import NotifySocket

from thermal_edge.service.systemd import SystemdNotifier


def test_path_socket_ready_status_watchdog_stopping(tmp_path):
    sock = NotifySocket(tmp_path / "notify")
    try:
        n = SystemdNotifier({"NOTIFY_SOCKET": sock.address, "WATCHDOG_USEC": "4000000"})
        assert n.enabled and n.watchdog_interval_s == 2.0
        assert n.ready("running") and n.watchdog() and n.status("hot spot 80 degC") and n.stopping()
        assert sock.wait_for("STOPPING=1", 2.0)
        assert sock.messages == ["READY=1\nSTATUS=running", "WATCHDOG=1", "STATUS=hot spot 80 degC", "STOPPING=1"]
    finally:
        sock.close()


def test_abstract_socket(tmp_path):
    name = f"thermal-edge-test-{os.getpid()}"
    sock = NotifySocket(abstract=name)
    try:
        n = SystemdNotifier({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert sock.wait_for("READY=1", 2.0)
        assert n.watchdog_interval_s is None  # no WATCHDOG_USEC
    finally:
        sock.close()


def test_no_op_outside_systemd_and_foreign_watchdog_pid():
    n = SystemdNotifier({})
    assert not n.enabled and n.ready() is False and n.watchdog_interval_s is None
    n = SystemdNotifier({"NOTIFY_SOCKET": "/nonexistent/notify", "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"})
    assert n.watchdog_interval_s is None  # the watchdog is for another process
    assert n.ready() is False and n.errors == 1  # the socket is missing: counted, not raised
