"""The README and the manual's generated reference pages.

The reference pages (configuration, metrics, CAN frames, alerts, command line) are rendered at
build time by deploy/gen_docs.py from their one home each; here every renderer is checked against
its source read another way (cantools, the YAML file, a live scrape, the alert rules, the parser),
each reference page is checked to include its table, and the README against what it promises: at
most 300 lines, the two set-up commands first, a minimal edge.yaml that passes ``run --check``, a
CAN contract that agrees with the DBC, links that resolve, and no development history in the
README, the manual or the package.
"""
from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path
from types import ModuleType

import deploylib as dl
import pytest

README = dl.REPO / "README.md"
DOCS = dl.REPO / "docs"


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


def readme() -> str:
    return README.read_text(encoding="utf-8")


# ---- the generated reference tables against their sources

def test_can_table_from_the_dbc() -> None:
    import cantools

    rendered = gen_docs().render_can(dl.DBC)
    db = cantools.database.load_file(str(dl.DBC))
    for m in db.messages:  # independent of the renderer: every frame and signal is in the table
        assert f"`{m.name}`" in rendered and f"0x{m.frame_id:03X}" in rendered
        for s in m.signals:
            assert f"`{s.name}`" in rendered


def test_config_reference_from_edge_yaml() -> None:
    import yaml

    rendered = gen_docs().render_config(dl.EDGE_YAML)
    raw = yaml.safe_load(dl.EDGE_YAML.read_text())

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
        assert f"`{key}`" in rendered, key


def test_metrics_table_from_the_running_service(live_metrics: str) -> None:
    rendered = gen_docs().render_metrics(live_metrics)
    families = set(re.findall(r"^# TYPE (thermal_edge_\w+) ", live_metrics, re.M))
    families = {f for f in families if not f.endswith("_created")}
    assert len(families) >= 50
    for f in families:  # every family the service exposes, from the exposition read another way
        assert f"`{f}`" in rendered, f


def test_alerts_table_from_the_rules() -> None:
    import yaml

    rendered = gen_docs().render_alerts()
    rules = yaml.safe_load((dl.DEPLOY / "prometheus" / "rules" / "thermal-edge.yml").read_text())
    names = [r["alert"] for g in rules["groups"] for r in g["rules"] if "alert" in r]
    assert names
    for n in names:
        assert f"`{n}`" in rendered, n


def test_cli_reference_from_the_parser() -> None:
    from thermal_edge.commands import COMMANDS

    rendered = gen_docs().render_cli()
    for c in COMMANDS:  # every command with its own --help text
        assert f"## `thermal-edge {c.name}`" in rendered, c.name
        assert f"usage: thermal-edge {c.name}" in rendered, c.name
    for bench in ("jacobian", "paper", "protection", "real", "fleet", "service"):
        assert f"### `thermal-edge bench {bench}`" in rendered
        assert f"usage: thermal-edge bench {bench}" in rendered


def test_write_tables_writes_every_table_and_leaves_unchanged_files_alone(tmp_path) -> None:
    scrape = tmp_path / "metrics.txt"
    scrape.write_text("# HELP thermal_edge_up 1 while the service runs\n# TYPE thermal_edge_up gauge\nthermal_edge_up 1.0\n")
    g = gen_docs()
    paths = g.write_tables(tmp_path / "out", metrics_from=str(scrape))
    assert sorted(p.name for p in paths) == sorted(f"{n}.md" for n in g.TABLES)
    assert "`thermal_edge_up`" in (tmp_path / "out" / "metrics.md").read_text()
    stamps = {p: p.stat().st_mtime_ns for p in paths}
    import time

    time.sleep(0.05)
    g.write_tables(tmp_path / "out", metrics_from=str(scrape))
    assert {p: p.stat().st_mtime_ns for p in paths} == stamps  # Sphinx sees no change, rebuilds nothing


@pytest.mark.parametrize("page,table", [("configuration", "config"), ("metrics", "metrics"), ("can-frames", "can"),
                                        ("alerts", "alerts"), ("cli", "cli")])
def test_each_reference_page_includes_its_generated_table(page: str, table: str) -> None:
    text = (DOCS / "reference" / f"{page}.md").read_text(encoding="utf-8")
    assert re.search(rf"^```{{include}} \.\./_generated/{table}\.md$", text, re.M), page
    assert table in gen_docs().TABLES


def test_compose_sim_config_in_sync() -> None:
    g = gen_docs()
    assert g.SIM_CONFIG.read_text(encoding="utf-8") == g.render_sim_config(), \
        "deploy/compose/edge-sim.yaml is stale (python deploy/gen_docs.py --compose)"


def test_sim_config_loads() -> None:
    """The compose demo's configuration is valid for the service (paths moved to this checkout)."""
    import yaml

    from thermal_edge.config import config_from_mapping

    raw = yaml.safe_load(gen_docs().SIM_CONFIG.read_text())
    raw["model"]["path"] = str(dl.MODEL)
    config_from_mapping(raw, dl.EDGE_YAML)


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


# ---- the README

def test_readme_is_short_and_opens_with_the_two_set_up_commands() -> None:
    text = readme()
    assert len(text.splitlines()) <= 300
    first = re.search(r"```sh\n(.*?)```", text, re.S)
    assert first is not None and text.index(first.group(0)) < text.index("\n## ")
    commands = [ln.split("#")[0].strip() for ln in first.group(1).splitlines() if ln.split("#")[0].strip()]
    assert commands == ["make demo", "make test"]


def test_readme_sections_for_a_drive_engineer() -> None:
    headings = re.findall(r"^## (.+)$", readme(), re.M)
    for h in ("Install", "Try it without hardware", "On a drive", "Commands", "Documentation"):
        assert h in headings, h
    text = readme()
    for needle in ("pip install", "docker build", "systemctl enable --now thermal-edge", "make demo",
                   "http://127.0.0.1:9108/metrics", "thermal-edge monitor", "run --check"):
        assert needle in text, needle


def minimal_edge_yaml() -> str:
    text = readme()
    i = text.index("<!-- minimal-edge-yaml")
    m = re.compile(r"```yaml\n(.*?)```", re.S).search(text, i)
    assert m, "no yaml block after <!-- minimal-edge-yaml"
    return m.group(1)


def test_the_minimal_edge_yaml_passes_run_check(tmp_path) -> None:
    from cli_in_process import te_here

    cfg = tmp_path / "edge.yaml"  # alone in its directory: the model is the packaged one it names
    cfg.write_text(minimal_edge_yaml(), encoding="utf-8")
    r = te_here("run", "--check", "--config", cfg)
    assert r.returncode == 0, r.stderr
    assert re.search(r"edge\.yaml: ok \(model pm10kw, 39 nodes, bus socketcan\)", r.stdout + r.stderr)
    # the check can fail: the same file without its timeouts is refused with one line naming the key
    cfg.write_text(re.sub(r"^timeouts:.*\n", "", minimal_edge_yaml(), flags=re.M), encoding="utf-8")
    r = te_here("run", "--check", "--config", cfg)
    assert r.returncode == 2 and "timeouts" in r.stderr


def test_the_can_contract_agrees_with_the_dbc() -> None:
    import cantools

    db = cantools.database.load_file(str(dl.DBC))
    text = readme()
    contract = text[text.index("**The CAN contract**"):text.index("**A minimal `edge.yaml`**")]
    items = re.findall(r"^\d+\. (.*)$", contract, re.M)
    assert len(items) == 5
    named = re.findall(r"`(\w+)` \(0x([0-9A-F]{3})\)", contract)
    assert len(named) >= 5
    for name, frame_id in named:  # each identifier and cycle time as the DBC says
        m = db.get_message_by_name(name)
        assert m.frame_id == int(frame_id, 16), name
        line = next(i for i in items if f"`{name}`" in i)
        cycle = re.search(r"every (\d+) ms", line)
        assert cycle is not None and int(cycle.group(1)) == m.cycle_time, (name, m.cycle_time)
    assert "300 ms" in contract and "500 kbit/s" in contract


def test_every_relative_link_of_the_readme_resolves() -> None:
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", readme())
    local = [u for u in links if not re.match(r"^[a-z]+://", u)]
    assert len(local) >= 15
    assert [u for u in local if not (dl.REPO / u).exists()] == []


# ---- no history in the README, the manual or the package

HISTORY = re.compile(r"session [0-9]|old code|black-box client|issue [0-9]+", re.I)
MISSING_FILES = re.compile(r"DESIGN\.md|findings\.md|reference/[\w.-]+\.(?:md|txt)")


def _text_files() -> list[Path]:
    files = [README]
    files += [p for p in DOCS.rglob("*") if p.is_file() and p.suffix in (".md", ".py") and "_generated" not in p.parts]
    files += list((dl.REPO / "thermal_edge").rglob("*.py"))
    return files


def test_no_development_history_in_the_readme_the_manual_or_the_package() -> None:
    found = []
    for p in _text_files():
        for n, line in enumerate(p.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if HISTORY.search(line):
                found.append(f"{p.relative_to(dl.REPO)}:{n}: {line.strip()[:100]}")
    assert found == []


def test_no_module_cites_a_file_the_repository_lacks() -> None:
    found = []
    package = dl.REPO / "thermal_edge"
    for p in [*package.rglob("*.py"), *package.rglob("*.yaml")]:  # the modules and the packaged files
        for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
            for m in MISSING_FILES.finditer(line):
                if not [f for f in dl.REPO.rglob(Path(m.group(0)).name) if not {".venv", "build"} & set(f.parts)]:
                    found.append(f"{p.relative_to(dl.REPO)}:{n}: {m.group(0)}")
    assert found == []
