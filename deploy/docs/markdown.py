"""Markdown cells and tables of the generated reference pages."""
from __future__ import annotations

import math
from typing import Any


def cell(x: Any) -> str:
    """One table cell: pipes escaped, on one line."""
    return str(x).replace("|", "\\|").replace("\n", " ").strip()


def table(header: list[str], rows: list[list[Any]]) -> list[str]:
    """A markdown table as lines."""
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(cell(c) for c in r) + " |" for r in rows]
    return out


def num(x: Any) -> str:
    """A value as YAML would write it: ``true``/``false``, ``%g`` floats, ``inf``."""
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, float):
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return f"{x:g}"
    return str(x)
