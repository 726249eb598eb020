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


FOUR_NODE = MODELS / "four_node.yaml"


def four_node_machine(tmp: Path) -> tuple[Path, Path]:
    """A user's own machine: the four-node model copied into ``tmp`` and its service configuration,
    made by ``config example --model four.yaml`` with its own sensors (``winding_t`` on the slot
    winding's PT100, ``housing``) and drive (kt 1.5 Nm/A). Returns both paths."""
    import yaml

    (tmp / "four.yaml").write_text(FOUR_NODE.read_text())
    example = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "config", "example", "--model", "four.yaml"],
                             capture_output=True, text=True, timeout=60, check=True)
    raw = yaml.safe_load(example.stdout)
    raw["signals"]["sensors"] = {
        "winding_t": {"frame": "INV_StatorTemps", "signal": "INV_T_WindingSlot", "status": "INV_S_WindingSlot"},
        "housing": {"frame": "INV_StatorTemps", "signal": "INV_T_Housing", "status": "INV_S_Housing"}}
    raw["derating"].update(kt_nm_per_arms=1.5, max_torque_nm=60.0, safe_torque_nm=15.0)
    (tmp / "edge.yaml").write_text(yaml.safe_dump(raw))
    return tmp / "four.yaml", tmp / "edge.yaml"

