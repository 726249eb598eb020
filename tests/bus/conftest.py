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

import pytest

from thermal_edge.bus import FrameCodec

if str(Path(__file__).parent) not in sys.path:  # bus_testlib importable under any --import-mode
    sys.path.insert(0, str(Path(__file__).parent))

from bus_testlib import DBC_PATH, MATRIX_PATH, REPO, MatrixSignal, parse_can_matrix

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


@pytest.fixture
def codec() -> FrameCodec:
    return FrameCodec(DBC_PATH)


@pytest.fixture
def virtual_channel() -> str:
    """A virtual bus name unique to the test (python-can virtual buses are process-global)."""
    return f"te-test-{os.getpid()}-{next(_channel_ids)}"


ASYNC_TEST_TIMEOUT_S = 20.0


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function) -> bool | None:
    """Run ``async def`` tests of this folder in a fresh event loop (no pytest-asyncio needed)."""
    if not inspect.iscoroutinefunction(pyfuncitem.obj):
        return None
    kwargs = {name: pyfuncitem.funcargs[name] for name in pyfuncitem._fixtureinfo.argnames}
    asyncio.run(asyncio.wait_for(pyfuncitem.obj(**kwargs), ASYNC_TEST_TIMEOUT_S))
    return True
