"""Write an augmented model as a few changed lines of the original YAML file.

The augmented document differs from the original by added parameters, a changed sensor,
changed or appended list entries (losses, conductances, nodes). :func:`patch_text` edits the
original text at exactly those places (comments and layout elsewhere are kept; every changed
line ends in ``# <effect>``), then checks that the patched text parses to the augmented document.
If the layout defeats the patch, :func:`render` falls back to a plain dump of the document.
"""
from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import yaml

from ..errors import ThermalEdgeError

LIST_SECTIONS = ("nodes", "points", "conductances", "losses")
MAP_SECTIONS = ("parameters", "sensors")


class PatchError(ThermalEdgeError, ValueError):
    """The original text could not be patched to the augmented document."""


def flow(entry: Any) -> str:
    """One-line YAML flow form of an entry."""
    return yaml.safe_dump(entry, default_flow_style=True, width=10**9, sort_keys=False).strip()


def changes(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[tuple[str, str, Any]]:
    """(kind, section, key) of every difference; kinds: list_replace, list_add, map_add, map_replace, top."""
    out: list[tuple[str, str, Any]] = []
    for k in new:
        if k in LIST_SECTIONS:
            a, b = list(old.get(k) or []), list(new.get(k) or [])
            if len(b) < len(a):
                raise PatchError(f"{k}: entries were removed")
            out += [("list_replace", k, i) for i in range(len(a)) if a[i] != b[i]]
            out += [("list_add", k, i) for i in range(len(a), len(b))]
        elif k in MAP_SECTIONS:
            ma, mb = dict(old.get(k) or {}), dict(new.get(k) or {})
            if set(ma) - set(mb):
                raise PatchError(f"{k}: entries were removed")
            out += [("map_replace" if key in ma else "map_add", k, key) for key in mb if ma.get(key) != mb[key]]
        elif old.get(k) != new.get(k):
            out.append(("top", k, None))
    if set(old) - set(new):
        raise PatchError("top-level sections were removed")
    return out


def _section(lines: list[str], name: str) -> tuple[int, int] | None:
    """(first line after the header, end) of a top-level block section, end trimmed of trailing
    blank lines and column-0 comments (they introduce the next section)."""
    pat = re.compile(rf"^{re.escape(name)}:\s*(#.*)?$")
    start = next((i for i, ln in enumerate(lines) if pat.match(ln)), None)
    if start is None:
        return None
    end = len(lines)
    for j in range(start + 1, len(lines)):
        if re.match(r"^[^\s#]", lines[j]):
            end = j
            break
    while end > start + 1 and (not lines[end - 1].strip() or lines[end - 1].startswith("#")):
        end -= 1
    return start + 1, end


def _items(lines: list[str], a: int, b: int, mapping: bool) -> tuple[str, list[tuple[int, int, str]]]:
    """Indentation and (start, end, key) spans of the items of a block section."""
    pat = re.compile(r"^(\s+)([A-Za-z_][\w.]*)\s*:") if mapping else re.compile(r"^(\s*)-\s")
    indent = None
    starts: list[tuple[int, str]] = []
    for i in range(a, b):
        m = pat.match(lines[i])
        if not m:
            continue
        if indent is None:
            indent = m.group(1)
        if m.group(1) == indent:
            starts.append((i, m.group(2) if mapping else ""))
    if indent is None:
        raise PatchError("section has no block items")
    spans = []
    for k, (i, key) in enumerate(starts):
        j = starts[k + 1][0] if k + 1 < len(starts) else b
        while j > i + 1 and (not lines[j - 1].strip() or lines[j - 1].lstrip().startswith("#")):
            j -= 1
        spans.append((i, j, key))
    return indent, spans


def _trailing_comment(line: str) -> str:
    m = re.search(r"[}\]]\s+(#.*)$", line)
    return m.group(1) if m else ""


def patch_text(text: str, old: Mapping[str, Any], new: Mapping[str, Any], label: str) -> str:
    """The original ``text`` (parsing to ``old``) edited to parse to ``new``."""
    lines = text.splitlines()
    tag = f"  # {label}" if label else ""
    for kind, section, key in changes(old, new):  # spans are found afresh for every change
        if kind == "top":
            raise PatchError(f"top-level key {section} changed")
        sec = _section(lines, section)
        if sec is None:
            # a new section at the end of the file
            body = [f"  - {flow(new[section][key])}{tag}"] if kind == "list_add" else [f"  {key}: {flow(new[section][key])}{tag}"]
            lines += [f"{section}:"] + body
            continue
        a, b = sec
        mapping = section in MAP_SECTIONS
        indent, spans = _items(lines, a, b, mapping)
        if kind == "list_replace":
            i, j, _ = spans[key]
            old_comment = _trailing_comment(lines[i]) if j == i + 1 else ""
            keep = f"  {old_comment} (was: {flow(old[section][key])})" if old_comment else f"  # was: {flow(old[section][key])}"
            lines[i:j] = [f"{indent}- {flow(new[section][key])}{tag}", f"{indent}  {keep.strip()}"]
        elif kind == "list_add":
            pos = spans[-1][1] if spans else b
            lines[pos:pos] = [f"{indent}- {flow(new[section][key])}{tag}"]
        elif kind == "map_add":
            pos = spans[-1][1] if spans else b
            lines[pos:pos] = [f"{indent}{key}: {flow(new[section][key])}{tag}"]
        elif kind == "map_replace":
            span = next((s for s in spans if s[2] == key), None)
            if span is None:
                raise PatchError(f"{section}.{key} not found")
            i, j, _ = span
            lines[i:j] = [f"{indent}{key}: {flow(new[section][key])}{tag}", f"{indent}# was: {key}: {flow(old[section][key])}"]
    out = "\n".join(lines) + "\n"
    if yaml.safe_load(out) != dict(new):
        raise PatchError("patched text does not parse to the augmented model")
    return out


def render(text: str | None, old: Mapping[str, Any], new: Mapping[str, Any], label: str, header: str = "") -> str:
    """The augmented model file: the patched original when possible, else a full dump."""
    head = "".join(f"# {ln}\n" for ln in header.splitlines()) if header else ""
    if text is not None:
        try:
            return head + patch_text(text, old, new, label)
        except (PatchError, IndexError, KeyError) as exc:
            head += f"# (written as a plain dump: {exc})\n"
    return head + yaml.safe_dump(dict(new), sort_keys=False, width=110, default_flow_style=None, allow_unicode=True)


def snippet(old: Mapping[str, Any], new: Mapping[str, Any]) -> str:
    """The added or changed entries as YAML lines (for the report)."""
    out: list[str] = []
    cur = None
    for kind, section, key in changes(old, new):
        if kind == "top":
            continue
        if section != cur:
            out.append(f"{section}:")
            cur = section
        if section in MAP_SECTIONS:
            out.append(f"  {key}: {flow(new[section][key])}")
        else:
            note = "   # changed" if kind == "list_replace" else ""
            out.append(f"  - {flow(new[section][key])}{note}")
    return "\n".join(out)
