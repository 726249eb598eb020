"""The Grafana dashboard and its provisioning: every metric the dashboard queries is exposed by
the running service, every query parses (promtool), the datasource is the provisioned one."""
from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path
from typing import Any, Iterator

import pytest
import yaml

import deploylib as dl

GRAFANA = dl.DEPLOY / "grafana"
DASHBOARD = GRAFANA / "dashboards" / "thermal-edge.json"
DS_FILE = GRAFANA / "provisioning" / "datasources" / "thermal-edge.yaml"
DASH_PROVIDER = GRAFANA / "provisioning" / "dashboards" / "thermal-edge.yaml"


def dashboard() -> dict[str, Any]:
    return json.loads(DASHBOARD.read_text())


def all_panels(panels: list[dict[str, Any]]) -> Iterator[dict[str, Any]]:
    for p in panels:
        yield p
        yield from all_panels(p.get("panels", []))


def exprs(d: dict[str, Any]) -> list[tuple[str, str]]:
    """(where, PromQL) of every panel target, annotation and query variable."""
    out = []
    for p in all_panels(d["panels"]):
        for t in p.get("targets", []):
            if t.get("expr"):
                out.append((f"panel {p['title']!r} {t.get('refId')}", t["expr"]))
    for a in d.get("annotations", {}).get("list", []):
        if a.get("expr"):
            out.append((f"annotation {a['name']!r}", a["expr"]))
    for v in d.get("templating", {}).get("list", []):
        if v.get("type") == "query":
            q = v["query"]["query"] if isinstance(v["query"], dict) else v["query"]
            m = re.fullmatch(r"\s*label_values\((.*),\s*\w+\s*\)\s*", q)
            out.append((f"variable {v['name']!r}", m.group(1) if m else q))
    return out


def provisioned_datasource() -> dict[str, Any]:
    doc = yaml.safe_load(DS_FILE.read_text())
    assert doc["apiVersion"] == 1
    (ds,) = doc["datasources"]
    return ds


def test_datasource_provisioning() -> None:
    ds = provisioned_datasource()
    assert ds["type"] == "prometheus"
    assert ds["uid"] == "thermal-edge-prometheus"
    assert ds["url"].startswith("http")
    assert ds["access"] == "proxy"


def test_dashboard_provisioning_points_at_the_dashboard() -> None:
    doc = yaml.safe_load(DASH_PROVIDER.read_text())
    assert doc["apiVersion"] == 1
    (prov,) = doc["providers"]
    assert prov["type"] == "file"
    assert prov["options"]["path"].startswith("/")


def test_dashboard_structure() -> None:
    d = dashboard()
    uid = provisioned_datasource()["uid"]
    assert d["uid"] == "thermal-edge" and d["title"]
    ids = [p["id"] for p in all_panels(d["panels"])]
    assert len(ids) == len(set(ids)), "panel ids must be unique"
    for p in all_panels(d["panels"]):
        if p["type"] == "row":
            continue
        assert p["datasource"] == {"type": "prometheus", "uid": uid}, p["title"]
        assert p["targets"], p["title"]
        for t in p["targets"]:
            assert t["datasource"]["uid"] == uid, p["title"]
        g = p["gridPos"]
        assert 0 <= g["x"] and g["x"] + g["w"] <= 24, p["title"]
    for a in d["annotations"]["list"]:
        if a.get("expr"):
            assert a["datasource"]["uid"] == uid
    for v in d["templating"]["list"]:
        if v["type"] == "query":
            assert v["datasource"]["uid"] == uid
    # what the issue asks the dashboard to show
    titles = " | ".join(p["title"].lower() for p in all_panels(d["panels"]))
    queries = " ".join(e for _, e in exprs(d))
    for metric in ("thermal_edge_node_estimate_celsius", "thermal_edge_node_estimate_stddev_celsius",
                   "thermal_edge_node_prediction_celsius", "thermal_edge_sensor_measurement_celsius",
                   "thermal_edge_prediction_error_celsius", "thermal_edge_parameter_value", "thermal_edge_current_limit_amperes",
                   "thermal_edge_derate_reason_code", "thermal_edge_frames_received_total", "thermal_edge_frames_dropped_total",
                   "thermal_edge_tick_duration_seconds_bucket"):
        assert metric in queries, metric
    for word in ("prediction error", "parameter", "limit", "frames", "tick"):
        assert word in titles, word
    ann = " ".join(a.get("expr", "") for a in d["annotations"]["list"])
    assert "adaptation_accepted_total" in ann and "prediction_error" in ann
    # the uncertainty band is filled between its edges
    fills = [pr for p in all_panels(d["panels"]) for o in p.get("fieldConfig", {}).get("overrides", [])
             for pr in o["properties"] if pr["id"] == "custom.fillBelowTo"]
    assert fills


def test_promql_names() -> None:
    assert dl.promql_metric_names('sum by (le) (rate(a_b_bucket{x=~"$i"}[$__rate_interval]))') == {"a_b_bucket"}
    assert dl.promql_metric_names("x - $z * y offset 5m") == {"x", "y"}
    assert dl.promql_metric_names('m{l="a b"} > bool 0 and on(instance) up') == {"m", "up"}


def test_every_dashboard_metric_is_exposed(live_metrics: str) -> None:
    exposed = dl.exposed_names(live_metrics)
    missing = {}
    for where, e in exprs(dashboard()):
        miss = dl.missing_metrics(dl.promql_metric_names(e), exposed)
        if miss:
            missing[where] = sorted(miss)
    assert not missing, f"queried but not exposed by the running service: {missing}"


def grafana_to_promql(expr: str) -> str:
    s = expr.replace("$__rate_interval", "1m").replace("$__interval", "1m").replace("$__range", "1h")
    s = re.sub(r"\$(z|adapt_threshold)\b", "1", s)
    return re.sub(r"\$\{?\w+\}?", "x", s)


def test_dashboard_promql_parses(tmp_path: Path) -> None:
    promtool = dl.which("promtool")
    if promtool is None:
        pytest.skip("promtool not available (Debian: apt-get install prometheus)")
    rules = [{"record": f"dashboard:q{i}", "expr": grafana_to_promql(e)} for i, (_, e) in enumerate(exprs(dashboard()))]
    f = tmp_path / "dashboard-queries.yml"
    f.write_text(yaml.safe_dump({"groups": [{"name": "dashboard", "rules": rules}]}))
    r = subprocess.run([promtool, "check", "rules", str(f)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
