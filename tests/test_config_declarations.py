"""thermal_edge.config reads edge.yaml from its dataclass declarations: light to import, every
section refuses unknown keys naming the closest one, every declared range is applied."""
from __future__ import annotations

import copy
import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from thermal_edge.config import ConfigError, EdgeConfig, config_from_mapping, field_default, file_key
from thermal_edge.settings import AdapterConfig, spec_of

ROOT = Path(__file__).resolve().parents[1]
EDGE_YAML = ROOT / "config" / "edge.yaml"
SHIPPED = yaml.safe_load(EDGE_YAML.read_text())


def load(raw: dict) -> EdgeConfig:
    return config_from_mapping(raw, EDGE_YAML)


def test_config_imports_nothing_from_estimation():
    code = "import json, sys, thermal_edge.config; print(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, timeout=60)
    mods = json.loads(out.stdout)
    assert "thermal_edge.config" in mods
    assert [m for m in mods if m.startswith(("thermal_edge.estimation", "scipy.optimize", "thermal_edge.service"))] == []


# (section, key as shipped, the same key misspelt): one per section read as a dataclass
TYPOS = [
    (("codec",), "resync_after_cycles", "resync_after_cycle"),
    (("model",), "path", "pth"),
    (("clock",), "tick_s", "tik_s"),
    (("signals",), "valid_range_c", "valid_range"),
    (("signals", "inputs", "speed_rpm"), "signal", "signall"),
    (("signals", "sensors", "housing"), "status", "stauts"),
    (("derating",), "max_current_a", "max_curent_a"),
    (("derating", "faults"), "hold_s", "hold_ss"),
    (("derating", "limits", "hot_spot"), "warn_c", "warn"),
    (("lookahead",), "horizon_s", "horizont_s"),
    (("adaptation",), "apply_delay_ticks", "apply_delay_tick"),
    (("adaptation",), "window_s", "windows_s"),  # an AdapterConfig key in the same section
    (("observer",), "restart_p0_k", "restart_p0"),
    (("metrics",), "address", "adress"),
    (("state",), "save_interval_s", "save_intervall_s"),
    (("recording",), "channel", "chanel"),
    (("transmit",), "bus_silence_s", "bus_silence"),
]


@pytest.mark.parametrize("section, key, typo", TYPOS, ids=[".".join(t[0]) + "." + t[2] for t in TYPOS])
def test_a_misspelt_key_is_named_with_the_closest(section, key, typo):
    raw = copy.deepcopy(SHIPPED)
    node = raw
    for k in section:
        node = node[k]
    node[typo] = node.pop(key)
    with pytest.raises(ConfigError) as err:
        load(raw)
    assert str(err.value) == f"edge.yaml: {'.'.join((*section, typo))}: unknown key (did you mean {key!r}?)"


def test_every_adapter_setting_is_read_from_the_adaptation_section():
    raw = copy.deepcopy(SHIPPED)
    for f in dataclasses.fields(AdapterConfig):
        d = field_default(f)
        if isinstance(d, bool) or not isinstance(d, (int, float)):
            continue
        raw["adaptation"][f.name] = d * 2 if spec_of(f).max is None else d
        assert getattr(load(raw).adaptation.adapter, f.name) == raw["adaptation"][f.name], f.name


@pytest.mark.parametrize("section, key, bad, words", [
    ("adaptation", "coverage", 1.5, "must be at most 1"),
    ("adaptation", "decimate", 0, "must be at least 1"),
    ("adaptation", "decimate", 2.5, "expected an integer"),
    ("adaptation", "weighting", "flat", "must be one of paper, forgetting, uniform"),
    ("derating", "reaction_time_s", 601, "must be at most 600"),
    ("lookahead", "steps", 10001, "must be at most 10000"),
    ("clock", "tick_s", float("inf"), "must be finite"),
    ("metrics", "enabled", "yes", "expected true or false"),
    ("recording", "channel", "", "expected a non-empty string"),
])
def test_declared_ranges_are_applied(section, key, bad, words):
    raw = copy.deepcopy(SHIPPED)
    raw[section][key] = bad
    with pytest.raises(ConfigError) as err:
        load(raw)
    assert str(err.value).startswith(f"edge.yaml: {section}.{key}: {words}"), str(err.value)
    assert file_key(type(getattr(load(SHIPPED), section)), key) is not None
