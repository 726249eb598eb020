"""Prometheus: the scrape configuration and the alert rules (promtool if available, and a schema
test that always runs), every metric the rules read exposed by the running service."""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import deploylib as dl
import pytest
import yaml

PROM = dl.DEPLOY / "prometheus"
CONFIG = PROM / "prometheus.yml"
RULES = PROM / "rules" / "thermal-edge.yml"
RULE_TESTS = PROM / "tests" / "thermal-edge.test.yml"
DURATION = re.compile(r"^(\d+(ms|s|m|h|d|w|y))+$")


def promtool() -> str:
    exe = dl.which("promtool")
    if exe is None:
        pytest.skip("promtool not available (make test-deps installs Debian's prometheus); the schema tests still run")
    print(subprocess.run([exe, "--version"], capture_output=True, text=True).stdout.splitlines()[0])
    return exe


def rules() -> list[dict]:
    doc = yaml.safe_load(RULES.read_text())
    return [r for g in doc["groups"] for r in g["rules"]]


def test_promtool_check_config(tmp_path: Path) -> None:
    exe = promtool()
    shutil.copytree(PROM, tmp_path / "prometheus")
    r = subprocess.run([exe, "check", "config", str(tmp_path / "prometheus" / "prometheus.yml")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "1 rule files found" in r.stdout + r.stderr


def test_promtool_check_rules() -> None:
    exe = promtool()
    r = subprocess.run([exe, "check", "rules", str(RULES)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_promtool_rule_unit_tests() -> None:
    exe = promtool()
    r = subprocess.run([exe, "test", "rules", str(RULE_TESTS)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr


def test_rules_schema() -> None:
    doc = yaml.safe_load(RULES.read_text())
    assert set(doc) == {"groups"} and doc["groups"]
    names = []
    for g in doc["groups"]:
        assert set(g) <= {"name", "interval", "rules", "limit"} and g["name"]
        for r in g["rules"]:
            assert set(r) <= {"alert", "expr", "for", "keep_firing_for", "labels", "annotations"}, r
            assert r["alert"] and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", r["alert"])
            assert isinstance(r["expr"], str) and r["expr"].strip()
            if "for" in r:
                assert DURATION.match(str(r["for"])), r["for"]
            assert r["labels"]["severity"] in ("critical", "warning", "info"), r["alert"]
            assert r["annotations"]["summary"] and r["annotations"]["description"], r["alert"]
            assert r["expr"].count("(") == r["expr"].count(")"), r["alert"]
            names.append(r["alert"])
    assert len(names) == len(set(names))
    exprs = {r["alert"]: r["expr"] for r in rules()}
    # the conditions the issue names
    wanted = {
        "stale inputs": "thermal_edge_input_stale",
        "derating active": "thermal_edge_derate_active",
        "prediction error high": "thermal_edge_prediction_error_rms_celsius",
        "adaptation failing": "thermal_edge_adaptation_failures_total",
        "tick overrun": "thermal_edge_tick_duration_seconds_bucket",
    }
    for what, metric in wanted.items():
        assert any(metric in e for e in exprs.values()), what


def test_every_rule_metric_is_exposed(live_metrics: str) -> None:
    exposed = dl.exposed_names(live_metrics)
    missing = {}
    for r in rules():
        miss = dl.missing_metrics(dl.promql_metric_names(r["expr"]), exposed)
        if miss:
            missing[r["alert"]] = sorted(miss)
    assert not missing, f"alert rules read metrics the running service does not expose: {missing}"


def test_scrape_config_matches_the_service() -> None:
    doc = yaml.safe_load(CONFIG.read_text())
    (job,) = [j for j in doc["scrape_configs"] if j["job_name"] == "thermal-edge"]
    targets = [t for sc in job["static_configs"] for t in sc["targets"]]
    edge = yaml.safe_load(dl.EDGE_YAML.read_text())
    assert f"{edge['metrics']['address']}:{edge['metrics']['port']}" in targets
    assert job.get("metrics_path", "/metrics") == "/metrics"
    # the rules reference this job name
    assert all('job="thermal-edge"' in r["expr"] for r in rules())
    for pattern in doc["rule_files"]:
        assert list(CONFIG.parent.glob(pattern)), pattern


def test_the_drive_label_reaches_every_alert() -> None:
    """prometheus.yml names each drive with a ``drive`` label (every drive's service is scraped at
    127.0.0.1:9108, so ``instance`` cannot tell them apart): every summary names it and no
    aggregation or join drops it (promtool's unit tests check two drives behind one address)."""
    doc = yaml.safe_load(CONFIG.read_text())
    (job,) = [j for j in doc["scrape_configs"] if j["job_name"] == "thermal-edge"]
    assert all(sc["labels"]["drive"] for sc in job["static_configs"])
    for r in rules():
        assert "{{ $labels.drive }}" in r["annotations"]["summary"], r["alert"]
        assert "$labels.instance" not in r["annotations"]["summary"], r["alert"]
        for clause in re.findall(r"\b(?:by|on)\s*\(([^)]*)\)", r["expr"]):
            assert "drive" in [c.strip() for c in clause.split(",")], (r["alert"], clause)
    assert 'drive="drive-2"' in RULE_TESTS.read_text()  # the unit test of two drives behind one address


def test_promtool_check_metrics_on_a_live_scrape(live_metrics: str) -> None:
    """The running service's /metrics as Prometheus' own linter sees it."""
    exe = promtool()
    r = subprocess.run([exe, "check", "metrics"], input=live_metrics, capture_output=True, text=True, timeout=120)
    problems = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    assert problems == [] and r.returncode == 0
