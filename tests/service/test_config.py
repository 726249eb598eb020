"""config/edge.yaml: the shipped file is complete and valid; broken files name the file and the key."""
from __future__ import annotations

import subprocess
import sys
from dataclasses import fields

import pytest
import yaml

from svc_testlib import EDGE_YAML, REPO, env, write_yaml
from thermal_edge.bus import DEFAULT_DBC_PATH, FrameCodec
from thermal_edge.config import ConfigError, config_from_mapping, load_config
from thermal_edge.estimation.adapter import AdapterConfig
from thermal_edge.service.engine import load_service_model


def shipped() -> dict:
    """The shipped file, its relative paths made absolute (the tests write it elsewhere)."""
    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["model"]["path"] = str(REPO / "config" / "machines" / "pm10kw.yaml")
    raw["codec"]["dbc"] = str(REPO / "dbc" / "thermal_edge.dbc")
    return raw


def test_shipped_config_is_valid_and_complete():
    cfg = load_config(EDGE_YAML)
    model = load_service_model(cfg)
    cfg.check_model(model)
    cfg.check_dbc(FrameCodec(cfg.codec.dbc or DEFAULT_DBC_PATH))
    assert cfg.metrics.address == "127.0.0.1" and cfg.metrics.port == 9108
    assert cfg.clock.mode == "wall" and cfg.clock.tick_s == 1.0
    assert set(cfg.inputs) == set(model.inputs)
    assert set(cfg.sensors) == set(model.sensors)
    assert cfg.inputs["i_rms"].reduce == "dq_rms"
    # every AdapterConfig field is spelled out in the file (commented documentation of each setting)
    text = EDGE_YAML.read_text()
    for f in fields(AdapterConfig):
        assert f"{f.name}:" in text, f"adaptation.{f.name} missing from edge.yaml"
    # every section is commented
    for section in ("bus", "codec", "model", "clock", "signals", "timeouts", "derating", "lookahead", "adaptation",
                    "observer", "metrics", "state", "recording", "transmit"):
        assert f"\n{section}:" in text


@pytest.mark.parametrize(
    "edit, key, words",
    [
        (lambda r: r["derating"].__setitem__("safe_current_a", -3), "derating.safe_current_a", "must be positive"),
        (lambda r: r["derating"].__setitem__("safe_current_a", 99), "derating.safe_current_a", "must not exceed"),
        (lambda r: r["derating"].pop("max_current_a"), "derating.max_current_a", "is required"),
        (lambda r: r["lookahead"].__setitem__("horizon_s", "long"), "lookahead.horizon_s", "expected a number"),
        (lambda r: r["clock"].__setitem__("mode", "sundial"), "clock.mode", "must be one of"),
        (lambda r: r["adaptation"].__setitem__("period_s", 0), "adaptation.period_s", "must be positive"),
        (lambda r: r["adaptation"].__setitem__("method", "guess"), "adaptation.method", "must be one of"),
        (lambda r: r["metrics"].__setitem__("port", 70000), "metrics.port", "at most 65535"),
        (lambda r: r.__setitem__("derating_typo", {}), "derating_typo", "unknown key"),
        (lambda r: r["derating"]["limits"]["hot_spot"].__setitem__("max_c", 100), "derating.limits.hot_spot.max_c",
         "must be above warn_c"),
        (lambda r: r["signals"]["inputs"]["i_rms"].__setitem__("reduce", "median"), "signals.inputs.i_rms.reduce",
         "must be one of"),
        (lambda r: r["signals"]["inputs"]["i_rms"].__setitem__("signals", ["INV_Id"]), "signals.inputs.i_rms.signals",
         "dq_rms needs"),
        (lambda r: r["signals"].__setitem__("valid_range_c", [300, 10]), "signals.valid_range_c", "low < high"),
        (lambda r: r["observer"].__setitem__("q_k", True), "observer.q_k", "expected a number"),
        (lambda r: r["state"].__setitem__("save_interval_s", -1), "state.save_interval_s", "must be positive"),
        (lambda r: r["bus"].__setitem__("bitrate", -5), "bus.bitrate", "positive integer"),
        (lambda r: r["model"].pop("path"), "model.path", "is required"),
    ],
)
def test_broken_config_names_file_and_key(tmp_path, edit, key, words):
    raw = shipped()
    edit(raw)
    path = write_yaml(tmp_path / "edge.yaml", raw)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    msg = str(err.value)
    assert msg.startswith(f"edge.yaml: {key}:"), msg
    assert words in msg
    assert "\n" not in msg


@pytest.mark.parametrize(
    "edit, key, words",
    [
        (lambda r: r["signals"]["inputs"].pop("ambient_c"), "signals.inputs.ambient_c", "needs this input"),
        (lambda r: r["signals"]["sensors"].__setitem__("rotor", {"frame": "INV_StatorTemps", "signal": "INV_T_Housing"}),
         "signals.sensors.rotor", "has no sensor"),
        (lambda r: r["derating"]["limits"].__setitem__("bearing", {"warn_c": 80, "max_c": 90}), "derating.limits.bearing",
         "no limited node"),
        (lambda r: r["model"]["parameters"].__setitem__("R_e_hous", 1000.0), "model.parameters.R_e_hous", "outside"),
    ],
)
def test_config_checked_against_the_model(tmp_path, edit, key, words):
    raw = shipped()
    edit(raw)
    cfg = config_from_mapping(raw, tmp_path / "edge.yaml")
    with pytest.raises(ConfigError) as err:
        cfg.check_model(load_service_model(cfg) if key != "model.parameters.R_e_hous" else _nominal_model(cfg))
    assert str(err.value).startswith(f"edge.yaml: {key}:") and words in str(err.value)


def _nominal_model(cfg):
    from thermal_edge.lptn import load_model

    return load_model(cfg.model.path)


def test_config_checked_against_the_dbc(tmp_path):
    raw = shipped()
    raw["signals"]["sensors"]["housing"]["signal"] = "INV_T_Hosuing"
    cfg = config_from_mapping(raw, tmp_path / "edge.yaml")
    with pytest.raises(ConfigError, match=r"^edge.yaml: signals.sensors.housing: frame INV_StatorTemps has no signal 'INV_T_Hosuing'"):
        cfg.check_dbc(FrameCodec(cfg.codec.dbc))
    raw = shipped()
    raw["timeouts"]["INV_Nothing"] = 1.0
    cfg = config_from_mapping(raw, tmp_path / "edge.yaml")
    with pytest.raises(ConfigError, match=r"^edge.yaml: timeouts.INV_Nothing: no frame"):
        cfg.check_dbc(FrameCodec(cfg.codec.dbc))


def test_invalid_yaml_and_missing_file(tmp_path):
    p = tmp_path / "edge.yaml"
    p.write_text("bus: [unclosed\n")
    with pytest.raises(ConfigError, match=r"^edge.yaml: not valid YAML"):
        load_config(p)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.yaml")


def test_relative_paths_resolve_against_the_config_directory():
    cfg = load_config(EDGE_YAML)
    assert cfg.model.path == (REPO / "config" / "machines" / "pm10kw.yaml")
    assert cfg.codec.dbc is None  # the packaged DBC
    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["codec"]["dbc"] = "../dbc/thermal_edge.dbc"
    cfg = config_from_mapping(raw, EDGE_YAML)
    assert cfg.codec.dbc.resolve() == (REPO / "dbc" / "thermal_edge.dbc").resolve()


def test_run_command_rejects_a_broken_config_with_one_line(tmp_path):
    raw = shipped()
    raw["derating"]["safe_current_a"] = -3
    path = write_yaml(tmp_path / "edge.yaml", raw)
    proc = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "run", "--config", str(path)], capture_output=True,
                          text=True, env=env(), cwd=str(REPO), timeout=60)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert lines == ["thermal-edge run: error: edge.yaml: derating.safe_current_a: must be positive, got -3"], proc.stderr
