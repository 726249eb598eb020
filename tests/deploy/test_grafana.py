"""The Grafana dashboard and its provisioning: every metric the dashboard queries is exposed by
the running service, every query parses (promtool), the datasource is the provisioned one."""
from __future__ import annotations

import json
import re
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import deploylib as dl
import pytest
import yaml

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


#: How every panel, target, annotation and query variable names its datasource: the dashboard's
#: datasource variable (the provisioned default Prometheus, or the one chosen at a UI import).
DS_REF = {"type": "prometheus", "uid": "${datasource}"}


def test_dashboard_structure() -> None:
    d = dashboard()
    uid = DS_REF["uid"]
    assert d["uid"] == "thermal-edge" and d["title"]
    ids = [p["id"] for p in all_panels(d["panels"])]
    assert len(ids) == len(set(ids)), "panel ids must be unique"
    for p in all_panels(d["panels"]):
        if p["type"] == "row":
            continue
        assert p["datasource"] == DS_REF, p["title"]
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
        pytest.skip("promtool not available (make test-deps installs Debian's prometheus)")
    rules = [{"record": f"dashboard:q{i}", "expr": grafana_to_promql(e)} for i, (_, e) in enumerate(exprs(dashboard()))]
    f = tmp_path / "dashboard-queries.yml"
    f.write_text(yaml.safe_dump({"groups": [{"name": "dashboard", "rules": rules}]}))
    r = subprocess.run([promtool, "check", "rules", str(f)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_datasource_variable_resolves_when_provisioned_and_when_imported() -> None:
    """Provisioned, the datasource variable falls back to the default Prometheus (the provisioned
    one is the default); imported through the UI, Grafana replaces ``${DS_PROMETHEUS}`` of
    ``__inputs`` with the datasource the user picks, which becomes the variable's value."""
    d = dashboard()
    assert provisioned_datasource()["isDefault"] is True
    (var,) = [v for v in d["templating"]["list"] if v["type"] == "datasource"]
    assert var["name"] == "datasource" and var["query"] == "prometheus"
    assert d["templating"]["list"][0] == var  # resolved before the query variables use it
    (inp,) = d["__inputs"]
    assert inp == {**inp, "name": "DS_PROMETHEUS", "type": "datasource", "pluginId": "prometheus"}
    text = DASHBOARD.read_text()
    assert set(re.findall(r"\$\{(DS_[A-Z_]+)\}", text)) == {"DS_PROMETHEUS"}  # every placeholder is an input
    imported = json.loads(text.replace("${DS_PROMETHEUS}", "chosen-uid"))  # what the UI import does
    (var,) = [v for v in imported["templating"]["list"] if v["type"] == "datasource"]
    assert var["current"]["value"] == "chosen-uid"
    requires = {(r["type"], r["id"]) for r in d["__requires"]}
    assert {("grafana", "grafana"), ("datasource", "prometheus")} <= requires
    used = {p["type"] for p in all_panels(d["panels"]) if p["type"] != "row"}
    assert used == {i for t, i in requires if t == "panel"}


def test_the_drive_label_selects_the_drive() -> None:
    """Every drive's service is scraped at 127.0.0.1:9108: the dashboard selects by the ``drive``
    label that prometheus.yml attaches, never by ``instance``."""
    d = dashboard()
    (var,) = [v for v in d["templating"]["list"] if v["name"] == "drive"]
    assert re.fullmatch(r"label_values\(thermal_edge_\w+\{job=\"thermal-edge\"\}, drive\)", var["query"]["query"])
    assert "instance" not in json.dumps(d["templating"]) + " ".join(e for _, e in exprs(d))
    for where, e in exprs(d):
        if where == "variable 'drive'":
            continue
        for m in re.finditer(r"\bthermal_edge_\w+", e):
            assert e[m.end():].startswith('{drive=~"$drive"'), (where, e)
    for a in d["annotations"]["list"]:
        if a.get("expr"):
            assert a["tagKeys"] == "drive", a["name"]
    prom = yaml.safe_load((dl.DEPLOY / "prometheus" / "prometheus.yml").read_text())
    (job,) = [j for j in prom["scrape_configs"] if j["job_name"] == "thermal-edge"]
    assert all("drive" in sc["labels"] for sc in job["static_configs"])
