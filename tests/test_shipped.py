"""The package data through :mod:`thermal_edge.shipped`: every packaged model and cycle by name, a
file before a name, one line listing the names when neither, the example configuration."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

from thermal_edge import shipped
from thermal_edge.cli import main
from thermal_edge.errors import UsageError
from thermal_edge.lptn import load_model
from thermal_edge.sim.cycles import load_cycle

RESOURCES = Path(__file__).resolve().parents[1] / "thermal_edge" / "resources"


def _stems(folder: Path) -> list[str]:
    return sorted(f[:-5] for f in os.listdir(folder) if f.endswith(".yaml"))


def test_names_are_the_packaged_files():
    assert shipped.names(shipped.MACHINES) == _stems(RESOURCES / "machines") == ["paderborn4", "pm10kw"]
    assert shipped.names(shipped.CYCLES) == _stems(RESOURCES / "cycles")
    assert "varied_drive" in shipped.names(shipped.CYCLES)


@pytest.mark.parametrize("name", _stems(RESOURCES / "cycles"))
def test_every_packaged_cycle_loads_by_name(name):
    path = Path(shipped.cycle_file(name))
    assert path.read_bytes() == (RESOURCES / "cycles" / f"{name}.yaml").read_bytes()
    assert load_cycle(path).duration_s > 0


def test_packaged_model_by_name_with_or_without_suffix():
    a, b = shipped.model_file("pm10kw"), shipped.model_file("pm10kw.yaml")
    assert a == b and Path(a).read_bytes() == (RESOURCES / "machines" / "pm10kw.yaml").read_bytes()
    assert len(load_model(a).nodes) == 39


def test_a_file_wins_over_a_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "pm10kw").write_text("a user's file\n")
    assert shipped.model_file("pm10kw") == "pm10kw"  # as given: the user's file
    assert shipped.model_file(str(tmp_path / "pm10kw")) == str(tmp_path / "pm10kw")


@pytest.mark.parametrize("ref", ["pm11", "machines/pm10kw.yaml", "/nowhere/pm10kw.yaml"])
def test_neither_file_nor_name_lists_the_packaged_ones(ref, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UsageError) as err:
        shipped.model_file(ref)
    assert str(err.value) == f"--model {ref}: no such file, nor a packaged model of that name (packaged: paderborn4, pm10kw)"
    with pytest.raises(UsageError, match=r"^--cycle x: .*\(packaged: commissioning, heldout_drive, overload, "):
        shipped.cycle_file("x")


def test_config_example_prints_the_packaged_file(capsys):
    assert main(["config", "example"]) == 0
    assert capsys.readouterr().out == (RESOURCES / "edge.yaml").read_text(encoding="utf-8")
    assert shipped.example_config() == shipped.config_path("edge.yaml").read_text(encoding="utf-8")


def test_config_example_with_a_model_beside_it_uses_that_file(tmp_path, capsys):
    """The install steps' configuration names the model copied beside it, so editing that copy
    changes what the service runs (a broken copy fails the check, naming the file)."""
    (tmp_path / "machines").mkdir()
    model = tmp_path / "machines" / "pm10kw.yaml"
    model.write_text((RESOURCES / "machines" / "pm10kw.yaml").read_text(encoding="utf-8"), encoding="utf-8")
    assert main(["config", "example", "--model", "machines/pm10kw.yaml"]) == 0
    text = capsys.readouterr().out
    cfg = tmp_path / "edge.yaml"
    cfg.write_text(text, encoding="utf-8")
    assert yaml.safe_load(text)["model"]["path"] == "machines/pm10kw.yaml"
    # everything but the model line is the packaged example
    changed = [(a, b) for a, b in zip(text.splitlines(), shipped.example_config().splitlines()) if a != b]
    assert len(changed) == 1 and changed[0][0].split() == ["path:", "machines/pm10kw.yaml", *changed[0][1].split()[2:]]
    assert main(["run", "--check", "--config", str(cfg)]) == 0
    assert "model pm10kw" in capsys.readouterr().out
    model.write_text("garbage: [\n", encoding="utf-8")
    assert main(["run", "--check", "--config", str(cfg)]) == 2
    assert "pm10kw.yaml" in capsys.readouterr().err


@pytest.mark.parametrize("path", ["a b.yaml", "#m.yaml", "[x].yaml", "m: x.yaml", "'q.yaml", "C:\\m x.yaml"])
def test_config_example_writes_any_printable_path_as_yaml_reads_it(capsys, path):
    assert main(["config", "example", "--model", path]) == 0
    assert yaml.safe_load(capsys.readouterr().out)["model"]["path"] == path


def test_config_example_refuses_a_path_with_a_control_character(capsys):
    assert main(["config", "example", "--model", "a\nb.yaml"]) == 2
    assert "--model 'a\\nb.yaml': a path of printable characters" in capsys.readouterr().err


def test_config_example_help_says_which_models_map_onto_the_example(capsys):
    with pytest.raises(SystemExit):
        main(["config", "example", "--help"])
    assert "only pm10kw (or a copy of it) maps onto them" in " ".join(capsys.readouterr().out.split())
