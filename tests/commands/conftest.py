"""Fixtures of the command tests: a simulated run of the two-node model."""
from __future__ import annotations

from pathlib import Path

import pytest
from cmd_testlib import CYCLE, RUN_S, TWO_NODE, te


@pytest.fixture(scope="session")
def good_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated run of the two-node model (CSV, 1 s samples, 30 min of the varied drive cycle)."""
    out = tmp_path_factory.mktemp("runs") / "two_node.csv"
    r = te("simulate", "--model", TWO_NODE, "--cycle", CYCLE, "--duration", RUN_S, "--out", out)
    assert r.returncode == 0, r.stderr
    return out
