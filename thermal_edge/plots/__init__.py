"""Figures of the offline commands (matplotlib, imported here only: the optional ``report`` extra)."""
from __future__ import annotations

import importlib

#: How to get an optional dependency, by the module a command needs.
INSTALL = {
    "matplotlib": "pip install 'thermal-edge[report]'",
    "pyarrow": "pip install 'thermal-edge[fleet]' (or pip install pyarrow)",
}


def missing(module: str) -> str | None:
    """None if ``module`` can be imported, else one line saying how to install it."""
    try:
        importlib.import_module(module)
    except ImportError:
        return f"this needs {module}, which is not installed: {INSTALL[module]}"
    return None
