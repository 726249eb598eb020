"""Fixtures of the service tests; ``async def`` tests run in a fresh event loop (no plugin needed)."""
from __future__ import annotations

import asyncio
import inspect
import itertools
import os
import sys
from pathlib import Path

import pytest

if str(Path(__file__).parent) not in sys.path:  # svc_testlib importable under any --import-mode
    sys.path.insert(0, str(Path(__file__).parent))

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from svc_testlib import MODEL, free_udp_port, udp_available

_ids = itertools.count()
#: the least time limit of an async service test: a hang guard, generous for a busy host (a test's
#: own ``async_timeout`` may only raise it), not a performance bound, s
DEFAULT_ASYNC_TIMEOUT_S = 600.0


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "async_timeout(seconds): time limit of an async service test (a hang guard, "
                                       "at least DEFAULT_ASYNC_TIMEOUT_S)")


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function) -> bool | None:
    if not inspect.iscoroutinefunction(pyfuncitem.obj):
        return None
    marker = pyfuncitem.get_closest_marker("async_timeout")
    timeout = max(float(marker.args[0]), DEFAULT_ASYNC_TIMEOUT_S) if marker else DEFAULT_ASYNC_TIMEOUT_S
    kwargs = {name: pyfuncitem.funcargs[name] for name in pyfuncitem._fixtureinfo.argnames}
    asyncio.run(asyncio.wait_for(pyfuncitem.obj(**kwargs), timeout))
    return True


@pytest.fixture(scope="session")
def model():
    from thermal_edge.lptn import load_model

    return load_model(MODEL)


@pytest.fixture
def channel() -> str:
    """A virtual bus name unique to the test (python-can virtual buses are process-global)."""
    return f"te-svc-{os.getpid()}-{next(_ids)}"


@pytest.fixture(scope="session")
def udp_ok() -> None:
    why = udp_available(free_udp_port())
    if why is not None:
        pytest.skip(f"udp_multicast unavailable on this machine: {why}")


@pytest.fixture
def udp_port(udp_ok) -> int:
    return free_udp_port()
