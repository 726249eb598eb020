"""The configuration reference: every key of ``config/edge.yaml`` with its shipped value, its
default, unit and the file's own comment.

The defaults are read as data from the declarations in :mod:`thermal_edge.config` (the dataclass
fields, their defaults and :class:`thermal_edge.settings.Spec`): the same declarations the loader
reads the file with, so the table cannot show a default the service does not use.
"""
from __future__ import annotations

import dataclasses
import re
import typing
from enum import Enum
from pathlib import Path
from typing import Any

import yaml

from .markdown import num, table
from .paths import EDGE_YAML, shown

_KEY = re.compile(r"^(\s*)([A-Za-z_][\w]*):(.*)$")
_COMMENTED_KEY = re.compile(r"^(\s*)#\s?([A-Za-z_][\w]*):\s+(\S.*?)\s+#\s?(.*)$")
_SECTION = re.compile(r"^# -+ (.*?) -+\s*$")


def _split_comment(rest: str) -> tuple[str, str | None, int | None]:
    """``value  # comment`` -> (value, comment, column of '#' in ``rest``) outside quotes."""
    quote = None
    for i, ch in enumerate(rest):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or rest[i - 1] in " \t"):
            return rest[:i].strip(), rest[i + 1:].strip(), i
    return rest.strip(), None, None


@dataclasses.dataclass
class Row:
    """One key of the file: its path, shipped (or example) value, comment and section heading."""

    path: tuple[str, ...]
    value: str | None
    comment: str
    section: str
    shipped: bool  # False: an optional key shown commented out
    parent: bool  # a mapping whose keys follow


def parse_commented_yaml(text: str) -> list[Row]:
    """Keys (and commented-out example keys) of a commented YAML file with their comments."""
    rows: list[Row] = []
    stack: list[tuple[int, str]] = []
    section = ""
    last: Row | None = None
    last_col: int | None = None
    for line in text.splitlines():
        if not line.strip():
            last, last_col = None, None
            continue
        sm = _SECTION.match(line)
        if sm:
            section, last, last_col = sm.group(1).strip(), None, None
            continue
        km = _KEY.match(line)
        if km and not line.lstrip().startswith("#"):
            indent, key, rest = len(km.group(1)), km.group(2), km.group(3)
            while stack and stack[-1][0] >= indent:
                stack.pop()
            path = tuple(k for _, k in stack) + (key,)
            value, comment, col = _split_comment(rest)
            stack.append((indent, key))
            if comment is not None and last is not None and last.comment and (
                    comment.startswith("  ") or re.search(r"(,|:|\b(from|to|and|or|the|of))$", last.comment)):
                # "#   i_rms = ..." indented further, or a sentence that runs on: the previous key's comment
                last.comment += " " + comment.strip()
                comment = ""
            row = Row(path, value if value else None, comment or "", section, True, not value)
            rows.append(row)
            last, last_col = row, (len(km.group(1)) + len(key) + 1 + col) if col is not None else None
            continue
        stripped = line.lstrip()
        if not stripped.startswith("#"):
            continue
        cm = _COMMENTED_KEY.match(line)
        if cm:  # an optional key shown commented out: "# key: example   # meaning"
            indent, key = len(cm.group(1)), cm.group(2)
            parents = tuple(k for i, k in stack if i < indent)
            path = parents + (key,)
            if any(r.path == path for r in rows):  # an alternative spelling of a key shown above
                key_row = next(r for r in rows if r.path == path)
                key_row.comment += f" Alternative: `{cm.group(3).strip()}` ({cm.group(4).strip()})."
                continue
            row = Row(path, cm.group(3).strip(), cm.group(4).strip(), section, False, False)
            rows.append(row)
            last, last_col = row, None
            continue
        col = len(line) - len(stripped)
        body = stripped[1:].strip()
        if last is not None and last_col is not None and abs(col - last_col) <= 1:
            last.comment += " " + body  # continuation at the comment column
            continue
        # a note at key indentation: belongs to the enclosing mapping
        parents = tuple(k for i, k in stack if i < col)
        target = next((r for r in reversed(rows) if r.path == parents), None)
        if target is not None and body:
            target.comment += " " + body
    for r in rows:
        r.comment = " ".join(r.comment.split())
    return rows


def _fmt(v: Any) -> str:
    if v is None:
        return "—"
    if isinstance(v, Path):
        return f"`{v}`"
    if isinstance(v, Enum):
        return v.name.lower()
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(num(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {num(x)}" for k, x in v.items()) + "}" if v else "{}"
    if dataclasses.is_dataclass(v):
        return "—"
    return num(v)


def _describe(f: dataclasses.Field[Any]) -> str:
    """The Default cell of a field: its default, *required*, or the environment variable that gives it."""
    from thermal_edge.config import field_default
    from thermal_edge.settings import spec_of

    env = spec_of(f).env
    if env:
        return f"`${env}`"
    d = field_default(f)
    return "required" if d is dataclasses.MISSING else _fmt(d)


def default_of(path: tuple[str, ...], raw: Any) -> str:
    """The Default cell of the key ``path`` of the file (``raw``: the file as loaded, for the form of
    an entry), from the declarations of :class:`thermal_edge.config.EdgeConfig`.

    A key that names an entry of a mapping the file fills (an input, a sensor, a limited node, a
    frame's timeout) has no default: "—".
    """
    from thermal_edge.config import EdgeConfig, InputSignal, file_key, without_none

    cls: Any = EdgeConfig
    keys = list(path)
    node = raw
    while keys:
        k = keys.pop(0)
        node = node.get(k) if isinstance(node, dict) else None
        found = file_key(cls, k)
        if found is None:
            return "—"
        f, tp = found
        tp = without_none(tp)
        if not keys:
            return _describe(f)
        if dataclasses.is_dataclass(tp):
            cls = tp
            continue
        entry = typing.get_args(tp)[1] if typing.get_origin(tp) is dict else None
        name = keys.pop(0)
        node = node.get(name) if isinstance(node, dict) else None
        if not keys or not dataclasses.is_dataclass(entry):
            return "—"
        cls = entry
        if cls is InputSignal and isinstance(node, dict) and node.get("reduce") == "dq_rms" and keys[0] in ("reduce", "signals"):
            # the dq_rms form gives its reduction and its two signals together: neither has a
            # default there (reduce's "mean" is the one-signal form's)
            return "—"
    return "—"


_UNITS = [("_a_per_s", "A/s"), ("_nm_per_arms", "N·m/A rms"), ("_s", "s"), ("_c", "°C"), ("_k", "K"), ("_a", "A rms"),
          ("_nm", "N·m")]


def _unit(path: tuple[str, ...]) -> str:
    key = path[-1]
    if key == "bitrate":
        return "bit/s"
    if path[0] == "timeouts" and len(path) == 2:
        return "s"
    if path[:2] == ("derating", "limits") and len(path) == 3:
        return "°C"
    for suffix, unit in _UNITS:
        if key.endswith(suffix):
            return unit
    return ""


def render_config(edge_yaml: Path = EDGE_YAML) -> str:
    """Every key of edge.yaml: shipped value, default (thermal_edge.config), unit, meaning."""
    from thermal_edge.config import load_config

    load_config(edge_yaml)  # the shipped file is valid (ConfigError names the key otherwise)
    text = edge_yaml.read_text(encoding="utf-8")
    raw = yaml.safe_load(text)
    out: list[str] = []
    section = None
    rows: list[list[Any]] = []

    def flush() -> None:
        if rows:
            out.extend([*table(["Key", "edge.yaml", "Default", "Unit", "Meaning"], rows), ""])
            rows.clear()

    for row in parse_commented_yaml(text):
        if row.section != section:
            flush()
            section = row.section
            out.append(f"**{section}**")
            out.append("")
        key = f"`{'.'.join(row.path)}`"
        if row.parent:
            if row.comment:  # (a plain mapping without comment: its keys follow)
                rows.append([key, "(mapping)", "—", "", row.comment])
            continue
        shipped = f"`{row.value}`" if row.shipped else f"not set (e.g. `{row.value}`)"
        rows.append([key, shipped, default_of(row.path, raw), _unit(row.path), row.comment])
    flush()
    head = [f"`{shown(edge_yaml)}`, validated at start by "
            "`thermal_edge/config.py`. *Default* is what the service uses when the key is left out "
            "(*required*: it must be given; `$STATE_DIRECTORY`: set by systemd's `StateDirectory=`). "
            "Relative paths are relative to the file's directory."]
    return "\n".join(head + [""] + out).rstrip() + "\n"
