"""The acceptance check of fleet screening: on 200 simulated machines with 5 faulty ones, ``fleet screen``
names at least 4 faulty machines with the faulty parameter and at most 1 healthy machine."""
from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from thermal_edge.bench.fleet import FLEET_PARAMS
from thermal_edge.cli import main
from thermal_edge.fleet.results import read_table
from thermal_edge.sim.fleet import read_manifest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_screen_of_200_machines_finds_the_faulty_ones(tmp_path):
    fleet = tmp_path / "fleet"
    assert main(["simulate", "--model", str(ROOT / "config/machines/pm10kw.yaml"),
                 "--cycle", str(ROOT / "config/cycles/varied_drive.yaml"), "--fleet", "200", "--faulty", "5",
                 "--seed", "11", "--out", str(fleet)]) == 0
    out = tmp_path / "screen.parquet"
    assert main(["fleet", "screen", "--model", str(ROOT / "config/machines/pm10kw.yaml"), str(fleet / "*.csv"),
                 "--params", ",".join(FLEET_PARAMS), "--out", str(out), "--no-progress"]) == 0
    rows = read_table(out)
    assert not [r for r in rows if r["kind"] == "error"]
    truth = {m["id"]: m["fault"]["parameter"] for m in read_manifest(fleet)["machines"] if m["fault"]}
    assert len(truth) == 5
    # the machine's parameter of largest |z| among its flagged ones: the one the report names
    named: dict[str, tuple[float, str]] = {}
    for r in rows:
        if r["outlier"] and abs(r["z"]) > named.get(r["machine"], (0.0, ""))[0]:
            named[r["machine"]] = (abs(r["z"]), r["name"])
    hits = [m for m, (_, p) in named.items() if truth.get(m) == p]
    false = [m for m in named if m not in truth]
    assert len(hits) >= 4, (named, truth)
    assert len(false) <= 1, (named, truth)
