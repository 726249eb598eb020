"""Fixtures for the tests that need real SocketCAN: a qemu VM with ``vcan0`` (see vmrun.py).

``vm`` (session scope) is a prepared :class:`vmrun.VM`::

    def test_something(vm):
        res = vm.run("candump -n 1 vcan0 & sleep 2; cansend vcan0 123#00; wait", timeout=90)
        res.check()                                   # raises with the whole report unless exit 0
        res = vm.pytest("tests/some_test.py -k x", timeout=300)
        res = vm.python("import can; ...", timeout=120)

Each call boots the VM afresh (about 6 s under software emulation), runs the
command in the host's tree (read-only, cwd: the tree these tests belong to) and powers off.  When
the VM cannot be had (qemu, the kernel, busybox or can-utils missing: ``make
test-deps`` installs them; KVM/TCG boot failed; THERMAL_EDGE_VM=0) every test
using ``vm`` is skipped with the reason, which names that target.  Inside the
guest (``THERMAL_EDGE_IN_VM=1``) ``vm`` skips too, so a ``vm.pytest`` selection
never tries to boot a VM within the VM.

Every test collected below tests/vm gets the ``vm`` marker (``-m "not vm"``
leaves them out).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

_HERE = Path(__file__).resolve().parent
if str(_HERE) not in sys.path:  # vmrun importable under any --import-mode
    sys.path.insert(0, str(_HERE))

import vmrun  # noqa: E402

_state: dict[str, object] = {}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        try:
            inside = Path(str(item.path)).resolve().is_relative_to(_HERE)
        except (AttributeError, OSError):
            inside = False
        if inside:
            item.add_marker(pytest.mark.vm)


def _report(config: pytest.Config, line: str) -> None:
    """Write a line to the terminal right away (not captured), falling back to stderr."""
    tr = config.pluginmanager.get_plugin("terminalreporter")
    capman = config.pluginmanager.get_plugin("capturemanager")
    if tr is not None and capman is not None:
        with capman.global_and_fixture_disabled():
            tr.write_line(line)
    elif tr is not None:
        tr.write_line(line)
    else:
        print(line, file=sys.__stderr__, flush=True)


@pytest.fixture(scope="session")
def vm(request: pytest.FixtureRequest) -> vmrun.VM:
    """A prepared VM with SocketCAN (vcan0); skips with the reason when it cannot be had."""
    if os.environ.get("THERMAL_EDGE_IN_VM") == "1":
        pytest.skip("already inside the test VM: not booting a VM within it")
    machine = vmrun.VM()
    _state["vm"] = machine
    try:
        machine.prepare()
    except vmrun.VMUnavailable as exc:
        _state["skip"] = str(exc)
        _report(request.config, f"\n[vm] SocketCAN VM unavailable, VM tests skipped: {exc}")
        pytest.skip(f"SocketCAN VM unavailable: {exc}")
    first = machine.first_result
    assert first is not None
    _report(
        request.config,
        f"\n[vm] SocketCAN VM: kernel {first.kernel}, accel {machine.accel}"
        + (f" ({machine.kvm_note})" if machine.kvm_note else "")
        + f", boot-to-ready {first.boot_seconds:.1f} s, boot+poweroff {first.wall_seconds:.1f} s; "
        + f"prepare {machine.prepare_seconds:.1f} s; vcan0: {first.vcan.splitlines()[0] if first.vcan else '?'}",
    )
    return machine


def _summary_line() -> str | None:
    """What this process learnt about the VM, one line, or None if it never tried one."""
    if "skip" in _state:
        return f"unavailable: {_state['skip']}"
    machine = _state.get("vm")
    return machine.summary() if machine is not None else None


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    # an xdist worker hands its line to the controller (tests/conftest.py prints it)
    workeroutput = getattr(session.config, "workeroutput", None)
    line = _summary_line()
    if workeroutput is not None and line is not None:
        workeroutput["vm_summary"] = line


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    # under xdist this conftest is not loaded in the controller: tests/conftest.py prints the workers' lines
    own = _summary_line()
    if own is None:
        return
    terminalreporter.section("SocketCAN VM")
    terminalreporter.write_line(own)
