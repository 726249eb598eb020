"""README "Deployment and operation": the generated tables equal what deploy/gen_docs.py renders
from their sources (the DBC, config/edge.yaml + thermal_edge.config, the running service's
/metrics, the alert rules), and the operator sections are there."""
from __future__ import annotations

import importlib.util
import re
import sys
from types import ModuleType

import deploylib as dl
import pytest

README = dl.REPO / "README.md"
HINT = "regenerate: python deploy/gen_docs.py --update README.md"


def gen_docs() -> ModuleType:
    name = "thermal_edge_deploy_gen_docs"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, dl.DEPLOY / "gen_docs.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def section() -> str:
    text = README.read_text(encoding="utf-8")
    i = text.index("\n## Deployment and operation\n")
    return text[i:]


def block(name: str) -> str:
    b = gen_docs().extract_block(README.read_text(encoding="utf-8"), name)
    assert b is not None, f"README has no generated {name} block"
    return b


def assert_same(name: str, rendered: str) -> None:
    have = block(name).splitlines()
    want = rendered.strip("\n").splitlines()
    if have != want:
        import difflib

        diff = "\n".join(difflib.unified_diff(have, want, "README.md", "generated", lineterm="", n=1))
        pytest.fail(f"README's {name} table is stale ({HINT}):\n{diff[:4000]}")


def test_can_table_from_the_dbc() -> None:
    rendered = gen_docs().render_can(dl.DBC)
    assert_same("can", rendered)
    import cantools

    db = cantools.database.load_file(str(dl.DBC))
    b = block("can")
    for m in db.messages:  # independent of the renderer: every frame and signal is in the table
        assert f"`{m.name}`" in b and f"0x{m.frame_id:03X}" in b
        for s in m.signals:
            assert f"`{s.name}`" in b


def test_config_reference_from_edge_yaml() -> None:
    rendered = gen_docs().render_config(dl.EDGE_YAML)
    assert_same("config", rendered)
    import yaml

    raw = yaml.safe_load(dl.EDGE_YAML.read_text())
    b = block("config")

    def leaves(d: dict, prefix: str = "") -> list[str]:
        out = []
        for k, v in d.items():
            key = f"{prefix}{k}"
            if isinstance(v, dict) and v and not key.startswith(("signals.sensors.", "derating.limits.")):
                out += leaves(v, key + ".")
            else:
                out.append(key)
        return out

    for key in leaves(raw):  # every key of the file, independent of the renderer
        assert f"`{key}`" in b, key


def test_metrics_table_from_the_running_service(live_metrics: str) -> None:
    rendered = gen_docs().render_metrics(live_metrics)
    assert_same("metrics", rendered)


def test_alerts_table_from_the_rules() -> None:
    assert_same("alerts", gen_docs().render_alerts())


def test_compose_sim_config_in_sync() -> None:
    g = gen_docs()
    assert g.SIM_CONFIG.read_text(encoding="utf-8") == g.render_sim_config(), \
        f"deploy/compose/edge-sim.yaml is stale ({HINT})"


def test_sim_config_loads() -> None:
    """The compose demo's configuration is valid for the service (paths moved to this checkout)."""
    import yaml

    from thermal_edge.config import config_from_mapping

    raw = yaml.safe_load(gen_docs().SIM_CONFIG.read_text())
    raw["model"]["path"] = str(dl.MODEL)
    config_from_mapping(raw, dl.EDGE_YAML)


def test_operator_sections() -> None:
    s = section()
    for needle in (
        "sudo python3 -m venv /opt/thermal-edge",
        "/etc/thermal-edge/edge.yaml",
        "sudo systemctl enable --now thermal-edge",
        "systemctl status thermal-edge",
        "journalctl -u thermal-edge -f",
        "docker build -t thermal-edge .",
        "--network host",
        "docker compose -f deploy/compose.yaml up",
        "candump -L can0",
        "python -m cantools decode dbc/thermal_edge.dbc",
        "ip link add dev vcan0 type vcan",
        "thermal-edge calibrate",
        "<!-- discovery commands -->",
        "(#the-method)",
    ):
        assert needle in s, needle
    assert re.search(r"^## The method$", README.read_text(encoding="utf-8"), re.M), "the section the benchmarks link to"
    for name in ("can", "config", "metrics", "alerts"):
        block(name)


def test_config_defaults_are_what_the_loader_uses(monkeypatch) -> None:
    """Each Default cell (read from the declarations) against the loader itself: the shipped file with
    that key left out loads to that value, or is refused as missing the key when it says required."""
    import copy

    import yaml

    from thermal_edge.config import ConfigError, config_from_mapping

    gen_docs()
    docs = sys.modules["thermal_edge_deploy_docs.config"]
    text = dl.EDGE_YAML.read_text(encoding="utf-8")
    raw = yaml.safe_load(text)
    monkeypatch.setenv("STATE_DIRECTORY", "/run/te-state:/other")
    checked = 0
    for row in docs.parse_commented_yaml(text):
        if row.parent or not row.shipped:
            continue
        shown = docs.default_of(row.path, raw)
        if shown == "—":
            continue
        r = copy.deepcopy(raw)
        node = r
        for k in row.path[:-1]:
            node = node[k]
        del node[row.path[-1]]
        if shown == "required":
            with pytest.raises(ConfigError, match=rf"^edge.yaml: {re.escape('.'.join(row.path))}: is required"):
                config_from_mapping(r, dl.EDGE_YAML)
            checked += 1
            continue
        cfg = config_from_mapping(r, dl.EDGE_YAML)
        value: object = cfg
        for k in row.path:
            if isinstance(value, dict):
                value = value[k]
            elif k == "signal":  # the one-signal form of signals
                value = value.signals[0]
            elif not hasattr(value, k):  # adaptation: the adapter's keys sit in its section
                value = getattr(value.adapter, k)
            else:
                value = getattr(value, k)
        if shown == "`$STATE_DIRECTORY`":
            assert str(value) == "/run/te-state", row.path
        else:
            assert docs._fmt(value) == shown, (row.path, value, shown)
        checked += 1
    assert checked >= 60, checked  # every section's plain keys were compared
