#!/usr/bin/env python3
"""Render the generated reference tables of README.md ("Deployment and operation").

Three tables, each between ``<!-- BEGIN GENERATED name -->`` and ``<!-- END GENERATED name -->``:

- ``can``: the CAN interface, from ``dbc/thermal_edge.dbc`` (cantools);
- ``config``: every key of ``config/edge.yaml`` with its shipped value, the code's default
  (``thermal_edge.config``: the value the loader uses when the key is left out), unit and the
  file's own comment;
- ``metrics``: every metric family of the running service (its ``/metrics`` HELP and TYPE lines;
  labels from the samples and from ``thermal_edge/service/metrics.py``);
- ``alerts``: the Prometheus alert rules (``deploy/prometheus/rules/thermal-edge.yml``).

``--update`` also rewrites ``deploy/compose/edge-sim.yaml`` (``config/edge.yaml`` for the compose
demo's simulated machine).

Usage (from the repository root, with the package installed, e.g. ``.venv/bin/python``)::

    python deploy/gen_docs.py can|config|metrics|alerts   # print one table
    python deploy/gen_docs.py --update README.md       # rewrite all three in place
    python deploy/gen_docs.py --check README.md        # exit 1 if any table is stale

``metrics`` starts ``thermal-edge demo`` (the service against the simulated machine) on a free
port and scrapes it; ``--metrics-from FILE`` renders a saved scrape instead.
"""
from __future__ import annotations

import argparse
import ast
import copy
import math
import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from enum import Enum
from pathlib import Path
from typing import Any, Callable

import yaml

REPO = Path(__file__).resolve().parents[1]
DBC = REPO / "dbc" / "thermal_edge.dbc"
EDGE_YAML = REPO / "config" / "edge.yaml"
TABLES = ("can", "config", "metrics", "alerts")


def _cell(x: Any) -> str:
    return str(x).replace("|", "\\|").replace("\n", " ").strip()


def _table(header: list[str], rows: list[list[Any]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(_cell(c) for c in r) + " |" for r in rows]
    return out


def _num(x: Any) -> str:
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, float):
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return f"{x:g}"
    return str(x)


# ---------------------------------------------------------------------------------------------
# CAN interface
def render_can(dbc: Path = DBC) -> str:
    """The DBC as two tables: frames, then signals."""
    import cantools

    db = cantools.database.load_file(str(dbc))
    text = dbc.read_text(encoding="utf-8", errors="replace")
    net = re.search(r'^CM_ "((?:[^"\\]|\\.)*)";', text, re.M | re.S)
    baud = db.dbc.attributes.get("Baudrate") if db.dbc is not None else None
    out = [f"`{dbc.relative_to(REPO) if dbc.is_relative_to(REPO) else dbc}` (version {db.version or '-'}"
           + (f", {int(baud.value) // 1000} kbit/s" if baud is not None else "") + ")."]
    if net:
        out += ["", " ".join(net.group(1).split())]
    rows = []
    for m in db.messages:
        cycle = f"{m.cycle_time} ms" if m.cycle_time else "event"
        rows.append([f"`{m.name}`", f"0x{m.frame_id:03X} ({m.frame_id})", m.length, cycle,
                     f"{', '.join(m.senders)} → {', '.join(sorted(m.receivers)) or '-'}", m.comment or ""])
    out += ["", *_table(["Frame", "ID", "DLC", "Cycle", "From → to", "Content"], rows)]
    rows = []
    for m in db.messages:
        for s in sorted(m.signals, key=lambda s: s.start):
            order = "Intel" if s.byte_order == "little_endian" else "Motorola"
            rng = f"{_num(s.minimum)} … {_num(s.maximum)}" if s.minimum is not None and s.maximum is not None else ""
            meaning = s.comment or ""
            if s.choices:
                meaning += " Values: " + ", ".join(f"{int(k)} `{v}`" for k, v in sorted(s.choices.items(), key=lambda kv: int(kv[0])))
            rows.append([m.name, f"`{s.name}`", s.start, s.length, f"{order}, {'signed' if s.is_signed else 'unsigned'}",
                         f"{_num(s.scale)}, {_num(s.offset)}", rng, s.unit or "", meaning.strip()])
    out += ["", *_table(["Frame", "Signal", "Start bit", "Bits", "Byte order, sign", "Factor, offset", "Range", "Unit",
                         "Meaning"], rows)]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# configuration reference
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


class _Row:
    def __init__(self, path: tuple[str, ...], value: str | None, comment: str, section: str, shipped: bool,
                 parent: bool) -> None:
        self.path, self.value, self.comment, self.section = path, value, comment, section
        self.shipped, self.parent = shipped, parent


def parse_commented_yaml(text: str) -> list[_Row]:
    """Keys (and commented-out example keys) of a commented YAML file with their comments."""
    rows: list[_Row] = []
    stack: list[tuple[int, str]] = []
    section = ""
    last: _Row | None = None
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
            row = _Row(path, value if value else None, comment or "", section, True, not value)
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
            row = _Row(path, cm.group(3).strip(), cm.group(4).strip(), section, False, False)
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


def _lookup(cfg: Any, path: tuple[str, ...]) -> Any:
    """The loaded value of an edge.yaml key path (KeyError if it has no single loaded value)."""
    head, rest = path[0], path[1:]
    if head == "bus":
        bus = cfg.bus
        (k,) = rest
        if hasattr(bus, k):
            return getattr(bus, k)
        return bus.options[k]
    if head == "signals":
        if rest[0] == "valid_range_c":
            return cfg.valid_range_c
        items = cfg.inputs if rest[0] == "inputs" else cfg.sensors
        obj = items[rest[1]]
        if len(rest) == 2:
            raise KeyError(path)
        if rest[2] == "signal" and hasattr(obj, "signals"):
            return obj.signals[0]
        return getattr(obj, rest[2])
    if head == "timeouts":
        return cfg.timeouts.get(rest[0])
    if head == "adaptation" and len(rest) == 1 and not hasattr(cfg.adaptation, rest[0]):
        return getattr(cfg.adaptation.adapter, rest[0])
    obj: Any = getattr(cfg, head)
    for k in rest:
        obj = obj[k] if isinstance(obj, dict) else getattr(obj, k)
    return obj


def _fmt(v: Any, sentinel: str) -> str:
    if v is None:
        return "—"
    if isinstance(v, Path):
        return "`$STATE_DIRECTORY`" if str(v) == sentinel else f"`{v}`"
    if isinstance(v, Enum):
        return v.name.lower()
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_num(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_num(x)}" for k, x in v.items()) + "}" if v else "{}"
    if hasattr(v, "__dataclass_fields__"):
        return "—"
    return _num(v)


_UNITS = [("_a_per_s", "A/s"), ("_nm_per_arms", "N·m/A rms"), ("_s", "s"), ("_c", "°C"), ("_k", "K"), ("_a", "A rms"),
          ("_nm", "N·m")]


def _unit(path: tuple[str, ...], value: str | None) -> str:
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
    from thermal_edge.config import ConfigError, config_from_mapping

    text = edge_yaml.read_text(encoding="utf-8")
    rows = parse_commented_yaml(text)
    raw = yaml.safe_load(text)
    sentinel = "/STATE_DIRECTORY-sentinel"
    saved = os.environ.get("STATE_DIRECTORY")
    os.environ["STATE_DIRECTORY"] = sentinel
    try:
        shipped_cfg = config_from_mapping(copy.deepcopy(raw), edge_yaml)

        def default_of(path: tuple[str, ...], shipped: bool) -> str:
            if not shipped:
                try:
                    return _fmt(_lookup(shipped_cfg, path), sentinel)
                except (KeyError, AttributeError, ValueError, TypeError):
                    return "—"
            r = copy.deepcopy(raw)
            node = r
            for k in path[:-1]:
                node = node[k]
            del node[path[-1]]
            try:
                cfg = config_from_mapping(r, edge_yaml)
            except ConfigError as exc:
                return "required" if f"{'.'.join(path)}: is required" in str(exc) else "—"
            try:
                return _fmt(_lookup(cfg, path), sentinel)
            except (KeyError, AttributeError, ValueError, TypeError):
                return "—"

        out: list[str] = []
        section = None
        table: list[list[Any]] = []

        def flush() -> None:
            if table:
                out.extend([*_table(["Key", "edge.yaml", "Default", "Unit", "Meaning"], table), ""])
                table.clear()

        for row in rows:
            if row.section != section:
                flush()
                section = row.section
                out.append(f"**{section}**")
                out.append("")
            if row.parent:
                if not row.comment:
                    continue  # a plain mapping: its keys follow
                table.append([f"`{'.'.join(row.path)}`", "(mapping)", "—", "", row.comment])
                continue
            else:
                default = default_of(row.path, row.shipped)
                shown = f"`{row.value}`" if row.shipped else f"not set (e.g. `{row.value}`)"
            table.append([f"`{'.'.join(row.path)}`", shown, default, _unit(row.path, row.value), row.comment])
        flush()
    finally:
        if saved is None:
            os.environ.pop("STATE_DIRECTORY", None)
        else:
            os.environ["STATE_DIRECTORY"] = saved
    head = [f"`{edge_yaml.relative_to(REPO) if edge_yaml.is_relative_to(REPO) else edge_yaml}`, validated at start by "
            "`thermal_edge/config.py`. *Default* is what the service uses when the key is left out "
            "(*required*: it must be given; `$STATE_DIRECTORY`: set by systemd's `StateDirectory=`). "
            "Relative paths are relative to the file's directory."]
    return "\n".join(head + [""] + out).rstrip() + "\n"


# ---------------------------------------------------------------------------------------------
# metrics reference
_SAMPLE = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(?:\{([^}]*)\})?\s")
_LABEL = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)="')
_METRIC_UNITS = [("_celsius", "°C"), ("_seconds", "s"), ("_amperes", "A rms"), ("_newton_meters", "N·m"),
                 ("_total", "1"), ("_info", "—")]


def static_labels() -> dict[str, list[str]]:
    """Label names declared in thermal_edge/service/metrics.py, by base metric name."""
    try:
        import thermal_edge.service.metrics as mod
    except Exception:  # the service package is not importable: labels from samples only
        return {}
    tree = ast.parse(Path(mod.__file__).read_text(encoding="utf-8"))
    prefix = getattr(mod, "P", "thermal_edge_")
    out: dict[str, list[str]] = {}
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call) or not node.args:
            continue
        first = node.args[0]
        name = None
        if isinstance(first, ast.BinOp) and isinstance(first.right, ast.Constant) and isinstance(first.right.value, str):
            name = prefix + first.right.value
        elif isinstance(first, ast.Constant) and isinstance(first.value, str) and first.value.startswith(prefix):
            name = first.value
        if name is None:
            continue
        for kw in node.keywords:
            if kw.arg in ("labels", "labelnames") and isinstance(kw.value, (ast.List, ast.Tuple)):
                out[name] = [e.value for e in kw.value.elts if isinstance(e, ast.Constant)]
    return out


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
    labels = static_labels()
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
    return "\n".join([head, "", *_table(["Metric", "Type", "Labels", "Unit", "Meaning"], rows)])


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
            and "# TYPE thermal_edge_lookahead_current_amperes" in text)


def scrape_demo(timeout: float = 120.0) -> str:
    """Start ``thermal-edge demo`` (service + simulated machine) on a free port; scrape once ready."""
    port = _free_port()
    exe = Path(sys.executable).parent / "thermal-edge"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "thermal_edge.cli"]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    for k in ("NOTIFY_SOCKET", "WATCHDOG_USEC"):
        env.pop(k, None)
    import tempfile

    state = tempfile.TemporaryDirectory(prefix="gen-docs-demo-")
    proc = subprocess.Popen([*cmd, "demo", "--metrics-port", str(port), "--quiet", "--speed", "30", "--state-dir", state.name],
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


# ---------------------------------------------------------------------------------------------
# alerts
RULES = REPO / "deploy" / "prometheus" / "rules" / "thermal-edge.yml"


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
    return "\n".join([f"`{rules.relative_to(REPO) if rules.is_relative_to(REPO) else rules}`:", "",
                      *_table(["Alert", "Severity", "Condition", "For", "Summary"], rows)])


# ---------------------------------------------------------------------------------------------
# the compose demo's service configuration
SIM_CONFIG = REPO / "deploy" / "compose" / "edge-sim.yaml"
#: paths inside the image (Dockerfile)
IMAGE_ETC = "/etc/thermal-edge"
IMAGE_STATE = "/var/lib/thermal-edge"


def render_sim_config(edge_yaml: Path = EDGE_YAML) -> str:
    """``deploy/compose/edge-sim.yaml``: ``config/edge.yaml`` for the simulated machine of the compose
    demo -- udp_multicast bus, frame clock, the model started off by the paper's Table 4 variations
    (as ``thermal-edge demo``), paths inside the image; every other setting as shipped."""
    from thermal_edge.lptn import load_model
    from thermal_edge.sim.inverter import table4_parameters

    raw = yaml.safe_load(edge_yaml.read_text(encoding="utf-8"))
    model_rel = Path(raw["model"]["path"])
    model = load_model((edge_yaml.parent / model_rel).resolve())
    raw["bus"] = {"interface": "udp_multicast", "preserve_timestamps": True}
    codec = dict(raw.get("codec") or {})
    codec.pop("dbc", None)  # the DBC the package finds (installed there by the Dockerfile)
    codec["resync_after_cycles"] = 1000
    raw["codec"] = codec
    raw["model"] = {**raw["model"], "path": f"{IMAGE_ETC}/{model_rel.as_posix()}",
                    "parameters": {k: round(v, 6) for k, v in table4_parameters(model).items()}}
    raw["clock"] = {**(raw.get("clock") or {}), "mode": "frame"}
    raw["metrics"] = {"enabled": True, "address": "127.0.0.1", "port": 9108}
    raw["state"] = {**(raw.get("state") or {}), "dir": IMAGE_STATE}
    raw["recording"] = {"candump": None}
    head = (
        "# GENERATED by `python deploy/gen_docs.py --update README.md` from config/edge.yaml: do not edit.\n"
        "# The service's configuration in deploy/compose.yaml (the simulated machine on a udp_multicast bus,\n"
        "# host network, frame clock so the demo can run accelerated; the model starts off by the paper's\n"
        "# Table 4 variations so the online adaptation has work). Everything else as config/edge.yaml.\n"
    )
    return head + yaml.safe_dump(raw, sort_keys=False, default_flow_style=False, width=110)


# ---------------------------------------------------------------------------------------------
def block_markers(name: str) -> tuple[str, str]:
    return (f"<!-- BEGIN GENERATED {name} (python deploy/gen_docs.py --update README.md) -->",
            f"<!-- END GENERATED {name} -->")


def extract_block(readme: str, name: str) -> str | None:
    begin, end = block_markers(name)
    i, j = readme.find(begin), readme.find(end)
    if i < 0 or j < 0 or j < i:
        return None
    return readme[i + len(begin):j].strip("\n")


def replace_block(readme: str, name: str, body: str) -> str:
    begin, end = block_markers(name)
    i, j = readme.find(begin), readme.find(end)
    if i < 0 or j < 0:
        raise KeyError(f"README has no {begin!r} … {end!r} block")
    return readme[:i] + begin + "\n" + body.strip("\n") + "\n" + readme[j:]


def render(name: str, metrics_text: Callable[[], str]) -> str:
    if name == "can":
        return render_can()
    if name == "config":
        return render_config()
    if name == "alerts":
        return render_alerts()
    return render_metrics(metrics_text())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("table", nargs="?", choices=TABLES, help="print one table")
    p.add_argument("--update", metavar="README", help="rewrite the generated blocks of this file")
    p.add_argument("--check", metavar="README", help="exit 1 if a generated block differs")
    p.add_argument("--metrics-from", metavar="FILE", help="a saved /metrics scrape (default: run thermal-edge demo)")
    p.add_argument("--only", choices=TABLES, action="append", help="with --update/--check: only these tables")
    args = p.parse_args(argv)
    cache: dict[str, str] = {}

    def metrics_text() -> str:
        if "m" not in cache:
            cache["m"] = Path(args.metrics_from).read_text() if args.metrics_from else scrape_demo()
        return cache["m"]

    if args.table and not (args.update or args.check):
        print(render(args.table, metrics_text))
        return 0
    target = args.update or args.check
    if not target:
        p.error("give a table to print, or --update/--check README.md")
    readme = Path(target).read_text(encoding="utf-8")
    names = args.only or ([args.table] if args.table else list(TABLES))
    stale = []
    new = readme
    for name in names:
        body = render(name, metrics_text)
        if extract_block(readme, name) != body.strip("\n"):
            stale.append(name)
        new = replace_block(new, name, body)
    sim = render_sim_config() if not args.only or "config" in args.only else None
    sim_stale = sim is not None and (not SIM_CONFIG.exists() or SIM_CONFIG.read_text(encoding="utf-8") != sim)
    if args.update:
        if new != readme:
            Path(target).write_text(new, encoding="utf-8")
        if sim_stale:
            SIM_CONFIG.parent.mkdir(parents=True, exist_ok=True)
            SIM_CONFIG.write_text(sim, encoding="utf-8")  # type: ignore[arg-type]
        done = stale + ([str(SIM_CONFIG.relative_to(REPO))] if sim_stale else [])
        print(f"{target}: {'updated ' + ', '.join(done) if done else 'up to date'}")
        return 0
    if stale or sim_stale:
        what = stale + ([str(SIM_CONFIG.relative_to(REPO))] if sim_stale else [])
        print(f"{target}: stale generated content: {', '.join(what)} (python deploy/gen_docs.py --update {target})")
        return 1
    print(f"{target}: generated tables up to date")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except Exception as exc:  # one line, not a traceback: e.g. config/edge.yaml does not load
        print(f"gen_docs: error: {type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}",
              file=sys.stderr)
        sys.exit(2)
