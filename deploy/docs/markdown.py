"""Markdown cells and tables, and the README's generated blocks."""
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


def block_markers(name: str) -> tuple[str, str]:
    return (f"<!-- BEGIN GENERATED {name} (python deploy/gen_docs.py --update README.md) -->",
            f"<!-- END GENERATED {name} -->")


def extract_block(readme: str, name: str) -> str | None:
    """The body of the generated block ``name`` (None if the README has none)."""
    begin, end = block_markers(name)
    i, j = readme.find(begin), readme.find(end)
    if i < 0 or j < 0 or j < i:
        return None
    return readme[i + len(begin):j].strip("\n")


def replace_block(readme: str, name: str, body: str) -> str:
    """The README with the generated block ``name`` replaced by ``body``."""
    begin, end = block_markers(name)
    i, j = readme.find(begin), readme.find(end)
    if i < 0 or j < 0:
        raise KeyError(f"README has no {begin!r} … {end!r} block")
    return readme[:i] + begin + "\n" + body.strip("\n") + "\n" + readme[j:]
