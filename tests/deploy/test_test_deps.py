"""The suite leaves the host's packages alone: no test runs a package manager, and the packages the
system-level tests skip without are the ones ``make test-deps`` installs."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import vmrun  # tests/vm is on sys.path (conftest.py)
from test_systemd import UNIT_COMMANDS

TESTS = Path(__file__).resolve().parents[1]
MAKEFILE = TESTS.parent / "Makefile"
PACKAGE_MANAGERS = {"apt-get", "apt", "aptitude", "dpkg", "/usr/bin/apt-get", "/usr/bin/apt", "/usr/bin/dpkg"}


def test_no_test_runs_a_package_manager() -> None:
    """No program name of a package manager among the string constants of the tests (an argv's
    first word; a message that merely names one is a longer string)."""
    found = [f"{f.relative_to(TESTS)}:{node.lineno} {node.value!r}"
             for f in TESTS.rglob("*.py") if f != Path(__file__).resolve()
             for node in ast.walk(ast.parse(f.read_text(encoding="utf-8")))
             if isinstance(node, ast.Constant) and node.value in PACKAGE_MANAGERS]
    assert found == []


def test_make_test_deps_installs_what_the_skipped_tests_need() -> None:
    text = MAKEFILE.read_text()
    m = re.search(r"^TEST_DEBS\s*:=\s*(.+)$", text, re.MULTILINE)
    assert m and re.search(r"^test-deps:", text, re.MULTILINE)
    debs = set(m.group(1).split())
    assert vmrun.INSTALL_TARGET == "make test-deps"
    assert set(vmrun.APT_PACKAGES.values()) <= debs
    assert set(UNIT_COMMANDS.values()) | {"systemd"} <= debs
    assert "prometheus" in debs  # promtool: tests/deploy/test_prometheus.py, test_grafana.py


def test_the_vm_skip_names_the_make_target(monkeypatch) -> None:
    """With qemu absent the VM is unavailable, and the reason says how to install it."""
    monkeypatch.setattr(vmrun, "find_qemu", lambda: None)
    try:
        vmrun.ensure_tools()
    except vmrun.VMUnavailable as exc:
        assert "qemu-system-x86" in str(exc) and vmrun.INSTALL_TARGET in str(exc)
    else:
        raise AssertionError("no VMUnavailable with qemu absent")
