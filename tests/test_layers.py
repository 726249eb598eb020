"""The package's parts depend one way (docs/architecture.md): every ``import`` of the package read
from the source (ast), each edge between parts checked against the allowed table."""
from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "thermal_edge"

#: leaves every part may import
EVERYONE = {"errors"}

#: part -> parts it may import (docs/architecture.md)
ALLOWED: dict[str, set[str]] = {
    "settings": set(),
    "yamlfile": set(),
    "process_signals": set(),
    "shipped": set(),
    "errors": set(),
    "text_table": set(),
    "log_rate": set(),
    "lptn": {"yamlfile"},
    "data": {"lptn", "yamlfile"},
    "plots": set(),
    "bus": set(),
    "estimation": {"lptn", "data", "settings"},
    "config": {"bus", "lptn", "settings", "shipped", "yamlfile"},
    "sim": {"bus", "data", "lptn", "shipped"},
    "service": {"bus", "config", "data", "estimation", "lptn", "settings", "process_signals", "log_rate"},
    "discovery": {"data", "estimation", "lptn", "sim"},
    "monitor": {"bus"},
    "fleet": {"bus", "config", "data", "estimation", "lptn", "service", "sim", "settings", "shipped", "text_table"},
    "bench": {"bus", "config", "data", "estimation", "lptn", "service", "sim", "fleet", "settings", "shipped", "text_table"},
    "commands": {"bench", "bus", "config", "data", "discovery", "estimation", "fleet", "lptn", "monitor", "plots",
                 "process_signals", "service", "settings", "shipped", "sim", "text_table", "yamlfile", "log_rate"},
    "cli": {"commands"},
    "__init__": set(),
}


def _edges() -> set[tuple[str, str, str]]:
    """(part, imported part, imported module below the package) for every import of the package."""
    out = set()
    for f in PKG.rglob("*.py"):
        rel = f.relative_to(PKG)
        part = rel.parts[0].removesuffix(".py")
        pkg = ["thermal_edge", *rel.parts[:-1]]
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            targets: list[list[str]] = []
            if isinstance(node, ast.ImportFrom):
                base = pkg[: len(pkg) - node.level + 1] if node.level else []
                targets.append(base + (node.module.split(".") if node.module else []))
            elif isinstance(node, ast.Import):
                targets.extend(a.name.split(".") for a in node.names)
            for t in targets:
                if len(t) > 1 and t[0] == "thermal_edge" and t[1] != part:
                    out.add((part, t[1], ".".join(t[1:3])))
    return out


def test_every_part_is_in_the_table():
    parts = {p.name.removesuffix(".py") for p in PKG.iterdir() if p.suffix == ".py" or (p / "__init__.py").exists()}
    assert parts == set(ALLOWED)


def test_dependencies_point_one_way():
    edges = _edges()
    assert len(edges) > 30  # the scan sees the package's imports at all
    bad = sorted((a, mod) for a, b, mod in edges if b not in ALLOWED[a] | EVERYONE)
    assert bad == []


def test_allowed_table_has_no_cycle():
    seen: dict[str, int] = {}

    def visit(p: str) -> None:
        assert seen.get(p) != 1, f"cycle through {p}"
        if seen.get(p) == 2:
            return
        seen[p] = 1
        for q in ALLOWED[p]:
            visit(q)
        seen[p] = 2

    for p in ALLOWED:
        visit(p)


def test_input_names_are_written_only_in_the_vocabulary():
    """The usual input column names (``i_rms``, ``speed_rpm`` ...) are written in
    ``lptn/vocabulary.py`` and the model files only; code finds an input by its role. Read from the
    source (ast string constants), not by a grep of comments and docstrings."""
    from thermal_edge.lptn.vocabulary import DEFAULT_COLUMNS

    names = set(DEFAULT_COLUMNS.values())
    found = []
    for f in PKG.rglob("*.py"):
        if f.relative_to(PKG).as_posix() == "lptn/vocabulary.py":
            continue
        tree = ast.parse(f.read_text(encoding="utf-8"))
        docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                      if isinstance(n, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and n.body
                      and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and node.value in names and id(node) not in docstrings:
                found.append(f"{f.relative_to(PKG)}:{node.lineno} {node.value!r}")
    assert found == []
