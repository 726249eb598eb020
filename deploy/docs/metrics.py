"""The metrics table, from a ``/metrics`` scrape of the running service (``thermal-edge demo``)."""
from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

from .markdown import table

_SAMPLE = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(?:\{([^}]*)\})?\s")
_LABEL = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)="')
_METRIC_UNITS = [("_celsius", "°C"), ("_seconds", "s"), ("_amperes", "A rms"), ("_newton_meters", "N·m"),
                 ("_total", "1"), ("_info", "—")]


def declared_labels() -> dict[str, list[str]]:
    """Label names of the service's labelled families (``thermal_edge.service.metrics.LABELS``), by
    full metric name: they name the labels of a family that has no sample yet."""
    try:
        from thermal_edge.service.metrics import LABELS, P
    except Exception:  # the service package is not importable: labels from samples only
        return {}
    return {P + name: list(labels) for name, labels in LABELS.items()}


def parse_exposition(text: str) -> list[dict[str, Any]]:
    """Metric families in exposition order: name, type, help, label names (``_created`` dropped)."""
    fams: dict[str, dict[str, Any]] = {}
    order: list[str] = []
    for line in text.splitlines():
        if line.startswith("# HELP ") or line.startswith("# TYPE "):
            parts = line.split(" ", 3)
            name = parts[2]
            fam = fams.setdefault(name, {"name": name, "type": "untyped", "help": "", "labels": []})
            if name not in order:
                order.append(name)
            if parts[1] == "HELP":
                fam["help"] = (parts[3] if len(parts) > 3 else "").replace("\\n", " ").replace("\\\\", "\\")
            else:
                fam["type"] = parts[3] if len(parts) > 3 else "untyped"
        elif line and not line.startswith("#"):
            m = _SAMPLE.match(line)
            if not m:
                continue
            sample = m.group(1)
            fam_name = next((n for n in (sample, re.sub(r"_(bucket|sum|count|total|created|info)$", "", sample))
                             if n in fams), None)
            if fam_name is None:
                continue
            for lab in _LABEL.findall(m.group(2) or ""):
                if lab not in ("le", "quantile") and lab not in fams[fam_name]["labels"]:
                    fams[fam_name]["labels"].append(lab)
    out = []
    for name in order:
        f = fams[name]
        base = name[:-len("_created")] if name.endswith("_created") else None
        if base is not None and (base in fams or base + "_total" in fams):
            continue
        if name.endswith("_created") and f["type"] == "gauge" and any(
                n.startswith(name[:-len("_created")]) and n != name for n in order):
            continue
        out.append(f)
    return out


def render_metrics(text: str) -> str:
    """The metric families of a /metrics scrape as a table."""
    labels = declared_labels()
    rows = []
    for f in parse_exposition(text):
        name, typ = f["name"], f["type"]
        base = name[:-len("_total")] if name.endswith("_total") else name
        labs = list(f["labels"])
        for lab in labels.get(base, labels.get(name, [])):
            if lab not in labs:
                labs.append(lab)
        shown = f"`{name}`"
        if typ == "histogram":
            shown += " (`_bucket`, `_sum`, `_count`)"
        unit = next((u for s, u in _METRIC_UNITS if name.endswith(s)), "")
        if name.endswith("_total") and typ == "counter":
            unit = "count"
        if "unit" in labs and not unit:
            unit = "label `unit`"
        meaning = f["help"]
        if name in labs:  # a state set: one sample per state, 1 for the current one
            meaning += " (state set: 1 for the current state)"
        rows.append([shown, typ, ", ".join(f"`{l}`" for l in labs) or "—", unit or "—", meaning])
    head = ("All metrics carry the prefix `thermal_edge_` and base units; the endpoint is "
            "`http://127.0.0.1:9108/metrics` (read only). Generated from the running service's `/metrics`.")
    return "\n".join([head, "", *table(["Metric", "Type", "Labels", "Unit", "Meaning"], rows)])


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def metrics_ready(text: str, min_ticks: float = 20.0) -> bool:
    """Ticks running with frames received, and the families that appear only with data present."""
    def val(name: str) -> float:
        m = re.search(rf"^{name}(?:{{[^}}]*}})? (\S+)$", text, re.M)
        return float(m.group(1)) if m else 0.0

    return (val("thermal_edge_ticks_total") >= min_ticks and val("thermal_edge_frames_received_total") > 0
            and "# TYPE thermal_edge_prediction_error_rms_celsius" in text
            and "# TYPE thermal_edge_lookahead_current_amperes" in text
            and val("thermal_edge_flux_used_total") > 0)  # the voltage input's gauges appear with its first estimate


def scrape_demo(timeout: float = 120.0) -> str:
    """Start ``thermal-edge demo`` (service + simulated machine) on a free port; scrape once ready."""
    port = _free_port()
    exe = Path(sys.executable).parent / "thermal-edge"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "thermal_edge.cli"]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    for k in ("NOTIFY_SOCKET", "WATCHDOG_USEC"):
        env.pop(k, None)
    state = tempfile.TemporaryDirectory(prefix="gen-docs-demo-")
    # with the optional voltage input, so that its metrics are in the table too
    proc = subprocess.Popen([*cmd, "demo", "--metrics-port", str(port), "--quiet", "--speed", "30", "--voltages",
                             "--state-dir", state.name],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise RuntimeError(f"thermal-edge demo exited {proc.returncode}: {proc.stderr.read() if proc.stderr else ''}")
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:  # noqa: S310
                    text = r.read().decode()
                if metrics_ready(text):
                    return text
            except OSError:
                pass
            time.sleep(0.5)
        raise TimeoutError("thermal-edge demo: metrics not ready")
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
        state.cleanup()
