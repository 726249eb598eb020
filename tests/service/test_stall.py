"""The process standing still (a paused VM, SIGSTOP, no CPU) is told apart from a silent bus: the
TE_Limits sender, which runs every cycle whatever the bus does, notices the gap in its own calls."""
from __future__ import annotations

import logging

import pytest
from svc_testlib import edge_raw

from thermal_edge.config import config_from_mapping
from thermal_edge.service import service as service_module
from thermal_edge.service.service import EdgeService


class _Clock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def svc(tmp_path, monkeypatch):
    raw = edge_raw(tmp_path / "state", {"interface": "virtual", "channel": "stall"}, table4=False, adapt=False)
    raw["clock"]["mode"] = "wall"
    s = EdgeService(config_from_mapping(raw, path=tmp_path / "edge.yaml"), serve_metrics=False, worker_mode="sync")
    clock = _Clock(1000.0)
    monkeypatch.setattr(service_module.time, "monotonic", clock)
    s._started_mono = s._last_frame_mono = clock.t
    yield s, clock
    s.state_lock.release()


def _said(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING or "frames accepted" in r.getMessage()]


def test_a_stall_of_the_process_is_named_and_not_blamed_on_the_bus(svc, caplog):
    s, clock = svc
    with caplog.at_level(logging.INFO):
        for _ in range(5):  # the sender every 100 ms, frames arriving
            clock.t += 0.1
            s._last_frame_mono = clock.t - 0.05
            s._limits_signals()
        clock.t += 7.0  # SIGSTOP for 7 s: neither the sender nor the reader ran
        s._limits_signals()
        for _ in range(5):  # the frames that waited in the socket are read
            clock.t += 0.1
            s._last_frame_mono = clock.t - 0.01
            s._limits_signals()
    assert _said(caplog) == ["this process stood still for 7.0 s (no TE_Limits sent meanwhile; a paused VM, a swap "
                             "storm, a stop signal or no CPU for it): not the bus"]


def test_a_silent_bus_is_still_a_silent_bus(svc, caplog):
    s, clock = svc
    with caplog.at_level(logging.INFO):
        for _ in range(30):  # the sender runs on; no frame for 3 s (transmit.bus_silence_s is 2 s here)
            clock.t += 0.1
            s._limits_signals()
        s._last_frame_mono = clock.t
        clock.t += 0.1
        s._limits_signals()
    said = _said(caplog)
    assert len(said) == 2 and said[0].startswith("no frame accepted for ") and "the bus is silent" in said[0]
    assert said[1].startswith("frames accepted again after the bus was silent")


def test_a_bus_that_goes_silent_during_a_stall_is_said_once_the_process_runs_again(svc, caplog):
    s, clock = svc
    with caplog.at_level(logging.INFO):
        clock.t += 0.1
        s._limits_signals()
        clock.t += 5.0
        s._limits_signals()
        for _ in range(20):  # running again, and still no frame
            clock.t += 0.1
            s._limits_signals()
    said = _said(caplog)
    assert said[0].startswith("this process stood still for 5.0 s")
    assert len(said) == 2 and "the bus is silent" in said[1]
