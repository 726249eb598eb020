"""Suite-wide collection order: the files with the longest set-up first.

``make test`` runs on two xdist workers that take whole files (``--dist loadfile``) in collection
order; a long file handed out last would leave one worker idle while the other finishes it (the
SocketCAN VM's service scenario alone runs 2-3 min under emulation). The order within a file is
kept.
"""
from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

_ROOT = Path(__file__).resolve().parent
_UNIT = _ROOT.parent / "deploy" / "systemd" / "thermal-edge.service"

#: Directories (relative to tests/) whose files start first, longest set-up first.
_FIRST = ("vm", "deploy", "service", "discovery", "fleet")


def _rank(item: pytest.Item) -> int:
    try:
        part = Path(str(item.path)).resolve().relative_to(_ROOT).parts[0]
    except (ValueError, IndexError):
        return len(_FIRST)
    return _FIRST.index(part) if part in _FIRST else len(_FIRST)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    items.sort(key=_rank)  # stable: the order within a directory and a file is kept


#: the SocketCAN VM's summary lines handed over by xdist workers (tests/vm/conftest.py)
_VM_LINES: list[str] = []


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error) -> None:
    line = getattr(node, "workeroutput", {}).get("vm_summary")
    if line:
        _VM_LINES.append(line)


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    if _VM_LINES:
        terminalreporter.section("SocketCAN VM")
        for line in _VM_LINES:
            terminalreporter.write_line(line)


@pytest.fixture
def unit_nice() -> Iterator[int]:
    """The test's thread at the scheduling priority the systemd unit gives the service (its
    ``Nice=``), as deployed: the unit raises it so that the TE_Limits cadence holds on a busy edge
    computer, and a cadence test judges it so. Threads the test starts inherit it; without the right
    to raise it (not root) the test runs as it is."""
    nice = int(re.search(r"^Nice=(-?\d+)", _UNIT.read_text(), re.M).group(1))
    before = os.getpriority(os.PRIO_PROCESS, 0)
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)  # Linux: the calling thread
    except PermissionError:
        pass
    yield nice
    try:
        os.setpriority(os.PRIO_PROCESS, 0, before)
    except PermissionError:
        pass


@pytest.fixture(autouse=True)
def _command_log_handlers_removed() -> Iterator[None]:
    """A test that calls ``thermal_edge.cli.main`` in this process leaves the root logger as the
    command set it (``run`` installs its handler at its level): the handlers the commands install
    (those with the rate limit's filter) and the level are undone after the test, so that a later
    test's command does not print another command's log lines."""
    import logging

    from thermal_edge.log_rate import RateLimit

    root = logging.getLogger()
    before, level = set(root.handlers), root.level
    yield
    for h in list(root.handlers):
        if h not in before and any(isinstance(f, RateLimit) for f in h.filters):
            root.removeHandler(h)
    root.setLevel(level)
