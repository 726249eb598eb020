"""The alert rules table, from ``deploy/prometheus/rules/thermal-edge.yml``."""
from __future__ import annotations

import re
from pathlib import Path

import yaml

from .markdown import table
from .paths import RULES, shown


def render_alerts(rules: Path = RULES) -> str:
    """The alert rules: name, severity, condition, for, summary."""
    doc = yaml.safe_load(rules.read_text(encoding="utf-8"))
    rows = []
    for g in doc["groups"]:
        for r in g["rules"]:
            if "alert" not in r:
                continue
            summary = re.sub(r"\{\{[^}]*\}\}", "…", r.get("annotations", {}).get("summary", ""))
            summary = re.sub(r"^thermal-edge on … ?:? ?", "", summary)
            rows.append([f"`{r['alert']}`", r.get("labels", {}).get("severity", ""), f"`{' '.join(str(r['expr']).split())}`",
                         r.get("for", "0s"), summary])
    return "\n".join([f"`{shown(rules)}`:", "", *table(["Alert", "Severity", "Condition", "For", "Summary"], rows)])
