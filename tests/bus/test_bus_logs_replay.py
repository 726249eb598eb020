"""One simulated run stored as a candump, an ASC, a BLF (and a TRC, a gzipped candump, an MF4 with
asammdf installed) log replays to the same estimates, tick by tick: the format is only the container."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from bus_testlib import REPO

from thermal_edge.bus import read_log, readable_suffixes
from thermal_edge.config import load_config
from thermal_edge.service import replay_candump
from thermal_edge.sim.inverter import write_log

MODEL = REPO / "config" / "machines" / "pm10kw.yaml"
CYCLE = REPO / "config" / "cycles" / "rated_heat_cool.yaml"
#: a start off the whole millisecond: ASC and BLF store their start in whole ms
T0 = 1_700_000_000.0004


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("logs")
    out = {}
    mf4 = (".mf4",) if ".mf4" in readable_suffixes() else ()  # with the mf4 extra (asammdf)
    for suffix in (".log", ".asc", ".blf", ".trc", ".log.gz", *mf4):
        out[suffix] = d / f"run{suffix}"
        write_log(MODEL, CYCLE, out[suffix], duration_s=240, t0=T0, current_period_s=0.1, temperature_period_s=1.0,
                  seed=3)
    return out


def _config(tmp_path: Path):
    raw = yaml.safe_load((REPO / "config" / "edge.yaml").read_text())
    raw["bus"] = {"interface": "virtual"}
    raw["codec"] = {"dbc": str(REPO / "dbc" / "thermal_edge.dbc"), "resync_after_cycles": 1000}
    raw["model"] = {"path": str(MODEL)}
    raw["state"] = {"dir": str(tmp_path / "state")}
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return load_config(path)


def _same(a: dict, b: dict) -> bool:
    """Equal signal values (NaN, a signal's "no value", equal to NaN)."""
    return a.keys() == b.keys() and all(a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k])) for k in a)


def test_every_format_holds_the_same_frames(logs):
    ref = read_log(logs[".log"])
    assert len(ref) == 240 * (10 + 10 + 1 + 1)
    for suffix, path in logs.items():
        frames = read_log(path)
        assert [(f.name, f.timestamp, f.counter) for f in frames] == [(f.name, f.timestamp, f.counter) for f in ref], suffix
        assert all(_same(f.signals, g.signals) for f, g in zip(frames, ref)), suffix


def test_candump_asc_and_blf_logs_replay_to_the_same_estimates(logs, tmp_path):
    cfg = _config(tmp_path)
    results = {s: replay_candump(p, cfg) for s, p in logs.items()}
    ref = results[".log"]
    assert 230 < len(ref.t) <= 240 and np.all(np.isfinite(ref.estimate))
    assert ref.frame_stats["lost"] == 0 and ref.frame_stats["crc"] == 0
    for suffix, res in results.items():
        assert res.frames == ref.frames, suffix
        np.testing.assert_array_equal(res.t, ref.t, err_msg=suffix)
        np.testing.assert_array_equal(res.estimate, ref.estimate, err_msg=suffix)
        np.testing.assert_array_equal(res.sigma, ref.sigma, err_msg=suffix)
        np.testing.assert_array_equal(res.current_limit_a, ref.current_limit_a, err_msg=suffix)
        assert res.parameters == ref.parameters, suffix
