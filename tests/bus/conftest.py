"""Shared fixtures for the CAN layer tests."""

from __future__ import annotations

import asyncio
import dataclasses
import inspect
import itertools
import os
import re
import sys
from pathlib import Path

import can
import pytest

from thermal_edge.bus import FrameCodec, create_bus

if str(Path(__file__).parent) not in sys.path:  # bus_testlib importable under any --import-mode
    sys.path.insert(0, str(Path(__file__).parent))

from bus_testlib import DBC_PATH, MATRIX_PATH, REPO, MatrixSignal, free_udp_port, parse_can_matrix

_channel_ids = itertools.count()


@pytest.fixture(scope="session")
def matrix() -> list[MatrixSignal]:
    if not MATRIX_PATH.is_file():
        pytest.skip(f"CAN matrix {MATRIX_PATH} not present: cannot cross-check the DBC against it")
    rows = parse_can_matrix(MATRIX_PATH.read_text(encoding="utf-8"))
    assert len(rows) >= 20, "CAN matrix tables could not be parsed"
    # enumeration values the project appends to the shared matrix (docs/can-matrix-additions.md)
    added = re.findall(r"^\| (\w+) \| (\d+) \| (\w+) \|", (REPO / "docs" / "can-matrix-additions.md").read_text(), re.M)
    return [dataclasses.replace(r, unit=r.unit + "".join(f", {v} {n}" for s, v, n in added if s == r.name)) for r in rows]


@pytest.fixture(scope="session")
def added_frames() -> list[MatrixSignal]:
    """The frames the project appends to the shared matrix (docs/can-matrix-additions.md, same table form)."""
    rows = parse_can_matrix((REPO / "docs" / "can-matrix-additions.md").read_text(encoding="utf-8"))
    assert rows, "no frame table in docs/can-matrix-additions.md"
    return rows


@pytest.fixture
def codec() -> FrameCodec:
    return FrameCodec(DBC_PATH)


@pytest.fixture
def virtual_channel() -> str:
    """A virtual bus name unique to the test (python-can virtual buses are process-global)."""
    return f"te-test-{os.getpid()}-{next(_channel_ids)}"


@pytest.fixture
def udp_port() -> int:
    """A free port on which multicast loopback works, else skip with the reason."""
    port = free_udp_port()
    try:
        a = create_bus({"interface": "udp_multicast", "port": port})
    except Exception as exc:  # no multicast on loopback / msgpack missing ...
        pytest.skip(f"udp_multicast unavailable on this machine: {type(exc).__name__}: {exc}")
    try:
        b = create_bus({"interface": "udp_multicast", "port": port})
        try:
            a.send(can.Message(arbitration_id=0x7FF, data=b"probe", is_extended_id=False))
            msg = b.recv(1.0)
        finally:
            b.shutdown()
    finally:
        a.shutdown()
    if msg is None or msg.arbitration_id != 0x7FF:
        pytest.skip("udp_multicast unavailable on this machine: loopback probe not received")
    return port


#: a hang guard (a generous upper bound of an async test), not a performance bound, s
ASYNC_TEST_TIMEOUT_S = 180.0


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function) -> bool | None:
    """Run ``async def`` tests of this folder in a fresh event loop (no pytest-asyncio needed)."""
    if not inspect.iscoroutinefunction(pyfuncitem.obj):
        return None
    kwargs = {name: pyfuncitem.funcargs[name] for name in pyfuncitem._fixtureinfo.argnames}
    asyncio.run(asyncio.wait_for(pyfuncitem.obj(**kwargs), ASYNC_TEST_TIMEOUT_S))
    return True
