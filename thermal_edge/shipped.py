"""Where the files that ship beside the package live: the source tree's root and its ``config/``
directory (machine models, drive cycles, ``edge.yaml``). A leaf: every part may use it."""
from __future__ import annotations

from pathlib import Path

__all__ = ["CONFIG", "ROOT", "config_path"]

#: the source tree (the directory holding ``thermal_edge/`` and ``config/``)
ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "config"


def config_path(*parts: str) -> Path:
    """A file under the source tree's ``config/`` directory."""
    return CONFIG.joinpath(*parts)
