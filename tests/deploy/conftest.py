"""Fixtures of the deployment tests: the running service (once per session) and tool lookup."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

for _dir in (Path(__file__).parent, Path(__file__).parents[1] / "vm"):  # deploylib, vmrun (INSTALL_TARGET)
    if str(_dir) not in sys.path:  # importable under any --import-mode
        sys.path.insert(0, str(_dir))

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import deploylib  # noqa: E402


@pytest.fixture(scope="session")
def live_metrics(tmp_path_factory: pytest.TempPathFactory) -> str:
    """/metrics of the service running against the simulated machine (ticks, frames, all families)."""
    with deploylib.live_service(tmp_path_factory.mktemp("live")) as svc:
        text = deploylib.wait_metrics(svc, deploylib.ready_for_docs, timeout=120)
        print(f"live service: {svc.mode}, {svc.url}")
        return text
