"""Helpers of the command tests: the two-node model, the CLI run as a user runs it."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from cli_in_process import te_here  # noqa: F401  (re-exported for the command tests)

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
MODELS = HERE / "models"
TWO_NODE = MODELS / "two_node.yaml"
CYCLE = ROOT / "config" / "cycles" / "varied_drive.yaml"
#: Length of the simulated run, s: two steps of the cycle (speed and current change once).
RUN_S = 1800


def te(*args: object, cwd: Path | None = None, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """``thermal-edge ARGS`` in a new process (the entry point a user runs), output captured."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONWARNINGS": "default"}
    return subprocess.run([sys.executable, "-m", "thermal_edge.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=timeout)
