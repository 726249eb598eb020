"""The repository files the tables are rendered from (and written to)."""
from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DBC = REPO / "dbc" / "thermal_edge.dbc"
EDGE_YAML = REPO / "config" / "edge.yaml"
RULES = REPO / "deploy" / "prometheus" / "rules" / "thermal-edge.yml"
SIM_CONFIG = REPO / "deploy" / "compose" / "edge-sim.yaml"


def shown(path: Path) -> Path:
    """``path`` relative to the repository when it lies inside, as the tables name it."""
    return path.relative_to(REPO) if path.is_relative_to(REPO) else path
