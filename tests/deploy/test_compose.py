"""deploy/compose.yaml, validated by structure (no Docker engine here): the four services, images
and builds, host network for the service, the mounts of the Prometheus and Grafana provisioning,
and that the pieces point at each other (ports, paths, bus)."""
from __future__ import annotations

import re
from pathlib import Path

import deploylib as dl
import yaml

from thermal_edge import shipped

COMPOSE = dl.DEPLOY / "compose.yaml"


def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def mounts(svc: dict) -> dict[str, tuple[str, str]]:
    """container path -> (source, mode)"""
    out = {}
    for v in svc.get("volumes", []):
        parts = v.split(":")
        src, dst = parts[0], parts[1]
        out[dst] = (src, parts[2] if len(parts) > 2 else "rw")
    return out


def arg(cmd: list[str], name: str) -> str | None:
    for i, a in enumerate(cmd):
        if a.startswith(name + "="):
            return a.split("=", 1)[1]
        if a == name and i + 1 < len(cmd):
            return cmd[i + 1]
    return None


def test_services_and_images() -> None:
    c = compose()
    s = c["services"]
    assert set(s) == {"thermal-edge", "simulated-machine", "prometheus", "grafana"}
    for name in ("thermal-edge", "simulated-machine"):
        b = s[name]["build"]
        assert (COMPOSE.parent / b["context"] / b.get("dockerfile", "Dockerfile")).resolve() == (dl.REPO / "Dockerfile")
        assert s[name]["image"] == s["thermal-edge"]["image"]
    assert re.fullmatch(r"prom/prometheus:v\d+\.\d+\.\d+", s["prometheus"]["image"])
    assert re.fullmatch(r"grafana/grafana(-oss)?:\d+\.\d+\.\d+", s["grafana"]["image"])
    # SocketCAN and the 127.0.0.1 metrics live in the host's network namespace
    for name, svc in s.items():
        assert svc.get("network_mode") == "host", name
        assert "ports" not in svc, f"{name}: ports are meaningless with network_mode host"
    for name, svc in s.items():
        for src, _ in mounts(svc).values():
            if src.startswith("."):
                assert (COMPOSE.parent / src).exists(), f"{name}: {src} does not exist"
            else:
                assert src in (c.get("volumes") or {}), f"{name}: named volume {src} not declared"


def test_service_runs_the_sim_config() -> None:
    s = compose()["services"]
    te = s["thermal-edge"]
    cfg_path = arg(te["command"], "--config")
    assert te["command"][0] == "run" and cfg_path
    src, mode = mounts(te)[cfg_path]
    assert mode == "ro"
    sim_cfg = yaml.safe_load((COMPOSE.parent / src).read_text())
    assert "/var/lib/thermal-edge" in mounts(te)
    assert sim_cfg["state"]["dir"] == "/var/lib/thermal-edge"
    # the machine and the service on the same bus
    sm = s["simulated-machine"]
    assert sm["entrypoint"][-2:] == ["-m", "thermal_edge.sim.inverter"]
    assert arg(sm["command"], "--interface") == sim_cfg["bus"]["interface"]
    assert sim_cfg["clock"]["mode"] == "frame" or float(arg(sm["command"], "--speed") or 1) == 1.0
    # the model and the cycle are packaged ones, named: the image holds them inside the wheel
    model = arg(sm["command"], "--model")
    cycle = arg(sm["command"], "--cycle")
    assert model == sim_cfg["model"]["path"]
    assert model in shipped.names(shipped.MACHINES) and cycle in shipped.names(shipped.CYCLES)
    assert sm["depends_on"]["thermal-edge"]["condition"] in ("service_healthy", "service_started")


def test_prometheus_and_grafana_mounts() -> None:
    s = compose()["services"]
    prom = s["prometheus"]
    conf = arg(prom["command"], "--config.file")
    m = mounts(prom)
    assert (COMPOSE.parent / m[conf][0]).resolve() == (dl.DEPLOY / "prometheus" / "prometheus.yml").resolve()
    prom_cfg = yaml.safe_load((dl.DEPLOY / "prometheus" / "prometheus.yml").read_text())
    for rf in prom_cfg["rule_files"]:  # relative to the config file: mounted beside it
        rule_dir = str(Path(conf).parent / Path(rf).parent)
        assert rule_dir in m
        assert (COMPOSE.parent / m[rule_dir][0]).resolve() == (dl.DEPLOY / "prometheus" / "rules").resolve()
    listen = arg(prom["command"], "--web.listen-address") or "0.0.0.0:9090"
    prom_port = listen.rsplit(":", 1)[1]
    # Prometheus scrapes what the service's config serves
    sim_cfg = yaml.safe_load((dl.DEPLOY / "compose" / "edge-sim.yaml").read_text())
    targets = [t for j in prom_cfg["scrape_configs"] for sc in j["static_configs"] for t in sc["targets"]]
    assert f"{sim_cfg['metrics']['address']}:{sim_cfg['metrics']['port']}" in targets
    graf = s["grafana"]
    gm = mounts(graf)
    assert (COMPOSE.parent / gm["/etc/grafana/provisioning"][0]).resolve() == \
        (dl.DEPLOY / "grafana" / "provisioning").resolve()
    provider = yaml.safe_load((dl.DEPLOY / "grafana" / "provisioning" / "dashboards" / "thermal-edge.yaml").read_text())
    dash_path = provider["providers"][0]["options"]["path"]
    assert dash_path in gm
    assert (COMPOSE.parent / gm[dash_path][0]).resolve() == (dl.DEPLOY / "grafana" / "dashboards").resolve()
    home = graf["environment"].get("GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH")
    assert home is None or (home.startswith(dash_path) and (dl.DEPLOY / "grafana" / "dashboards" / Path(home).name).exists())
    ds = yaml.safe_load((dl.DEPLOY / "grafana" / "provisioning" / "datasources" / "thermal-edge.yaml").read_text())
    url = ds["datasources"][0]["url"]
    assert re.fullmatch(rf"http://(localhost|127\.0\.0\.1):{prom_port}/?", url), (url, prom_port)
