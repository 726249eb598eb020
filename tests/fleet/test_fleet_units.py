"""The fleet's pieces without a cluster: finding machines, the robust screen, the simulated fleet."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from thermal_edge.data import RunError
from thermal_edge.fleet.results import read_table, row, write_table
from thermal_edge.fleet.runs import find_machines
from thermal_edge.fleet.screen import MAD_SCALE, screen
from thermal_edge.lptn import load_model
from thermal_edge.shipped import config_path
from thermal_edge.sim.cycles import load_cycle
from thermal_edge.sim.fleet import FAULTS, SPREAD_REL, SPREAD_TRUNC, machine_run, plan_fleet

MODEL = load_model(config_path("machines/pm10kw.yaml"))


def _csv(path: Path, machine_id: float | None = None) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    head = "t,x" + (",unit" if machine_id is not None else "")
    tail = f",{machine_id}" if machine_id is not None else ""
    path.write_text(f"# a run\n{head}\n0,1{tail}\n1,2{tail}\n")
    return path


def test_machines_from_files_directories_globs_and_a_column(tmp_path):
    a = _csv(tmp_path / "flat" / "a.csv")
    b = _csv(tmp_path / "flat" / "b.csv")
    d1 = _csv(tmp_path / "dirs" / "m7" / "day1.csv")
    d2 = _csv(tmp_path / "dirs" / "m7" / "day2.csv")
    assert [(m.id, m.runs) for m in find_machines([str(tmp_path / "flat" / "*.csv")])] == [("a", (str(a),)), ("b", (str(b),))]
    assert [(m.id, m.runs) for m in find_machines([str(tmp_path / "dirs" / "m7")])] == [("m7", (str(d1), str(d2)))]
    assert [m.id for m in find_machines([str(tmp_path / "dirs" / "*"), str(a)])] == ["a", "m7"]
    # the id from a column: two files of unit 12 are one machine
    u1, u2, u3 = (_csv(tmp_path / "col" / f"{n}.csv", i) for n, i in (("x", 12.0), ("y", 12), ("z", 3)))
    got = find_machines([str(tmp_path / "col" / "*.csv")], id_column="unit")
    assert [(m.id, m.runs) for m in got] == [("12", (str(u1), str(u2))), ("3", (str(u3),))]


def test_machine_discovery_errors_name_the_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope"):
        find_machines([str(tmp_path / "nope.csv")])
    with pytest.raises(FileNotFoundError, match="no file or directory matches"):
        find_machines([str(tmp_path / "*.csv")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no \\*.csv run files"):
        find_machines([str(tmp_path / "empty")])
    _csv(tmp_path / "p" / "a.csv")
    _csv(tmp_path / "q" / "a.csv")
    with pytest.raises(KeyError, match="machine id 'a' from both"):
        find_machines([str(tmp_path / "p" / "a.csv"), str(tmp_path / "q" / "a.csv")])
    with pytest.raises(RunError, match="no machine id column 'unit'"):
        find_machines([str(tmp_path / "p" / "a.csv")], id_column="unit")


def _fleet_rows(values: dict[str, list[float]], rel_std: dict[str, list[float]]) -> list[dict]:
    rows = []
    for name, vals in values.items():
        for i, (v, s) in enumerate(zip(vals, rel_std[name])):
            rows.append(row(machine=f"m{i}", kind="parameter", name=name, value=v, nominal=1.0, rel_std=s,
                            identifiable=s < 0.25))
    return rows


def test_screen_z_is_the_robust_distance_with_the_machines_own_sigma():
    rng = np.random.default_rng(3)
    n = 41
    a = np.exp(0.05 * rng.standard_normal(n))
    a[7] *= 1.6  # a real outlier on a well-identified parameter
    b = np.exp(0.05 * rng.standard_normal(n))
    b[11] *= 3.0  # far off, but this machine's runs cannot pin b down (σ = 200 %)
    sd_a = np.full(n, 0.01)
    sd_b = np.full(n, 0.01)
    sd_b[11] = 2.0
    rows = _fleet_rows({"a": list(a), "b": list(b)}, {"a": list(sd_a), "b": list(sd_b)})
    spreads, outliers = screen(rows, threshold=5.0)
    # independent computation of z for parameter a
    x = np.log(a)
    med = np.median(x)
    mad = 1.4826 * np.median(np.abs(x - med))
    z = (x - med) / np.sqrt(mad**2 + sd_a**2)
    got = np.array([r["z"] for r in rows if r["name"] == "a"])
    np.testing.assert_allclose(got, z, rtol=1e-4)
    assert MAD_SCALE == pytest.approx(1 / 0.6744897501960817)
    assert [(o.machine, o.parameter) for o in outliers] == [("m7", "a")]
    assert outliers[0].ratio == pytest.approx(a[7] / np.exp(med))
    zb = next(r["z"] for r in rows if r["name"] == "b" and r["machine"] == "m11")
    assert abs(zb) < 1.0  # 3x off, yet within its own uncertainty
    sp = {s.parameter: s for s in spreads}
    assert sp["a"].median == pytest.approx(math.exp(med)) and sp["a"].spread_rel == pytest.approx(mad, rel=1e-4)
    assert sp["b"].identifiable == n - 1


def test_result_table_round_trip(tmp_path):
    rows = [row(machine="m1", kind="parameter", name="R_e_hous", value=9.5, rel_std=0.01, identifiable=True, samples=10),
            row(machine="m2", kind="error", name="RunError", message="m2.csv: no data rows")]
    write_table(tmp_path / "t.parquet", rows)
    assert read_table(tmp_path / "t.parquet") == rows
    with pytest.raises(KeyError, match="no result column"):
        row(machine="m1", colour="red")
    (tmp_path / "bad.parquet").write_text("not parquet")
    with pytest.raises(KeyError, match="not a Parquet table"):
        read_table(tmp_path / "bad.parquet")


def test_simulated_fleet_is_seeded_spread_within_bounds_and_faults_as_declared():
    specs = plan_fleet(MODEL, 60, faulty=6, seed=4)
    again = plan_fleet(MODEL, 60, faulty=6, seed=4)
    assert [s.params for s in specs] == [s.params for s in again]
    assert [s.params for s in plan_fleet(MODEL, 60, faulty=6, seed=5)] != [s.params for s in specs]
    nominal = dict(zip(MODEL.parameter_names, MODEL.nominal()))
    faulty = [s for s in specs if s.fault]
    assert len(faulty) == 6 and {s.fault["kind"] for s in faulty} == set(FAULTS)
    limit = math.exp(SPREAD_REL * SPREAD_TRUNC) * (1 + 1e-12)
    for s in specs:
        assert set(s.params) == set(MODEL.adaptable)
        for name, v in s.params.items():
            factor = FAULTS[s.fault["kind"]][1] if s.fault and s.fault["parameter"] == name else 1.0
            assert 1 / limit <= v / (nominal[name] * factor) <= limit
    logs = np.log([s.params["c_p_hous"] / nominal["c_p_hous"] for s in specs])
    assert 0.03 < np.std(logs) < 0.07  # the declared 5 % spread


def test_a_faulty_housing_path_runs_hotter(tmp_path):
    cycle = load_cycle(config_path("cycles/varied_drive.yaml"))
    spec = plan_fleet(MODEL, 1, faulty=0, seed=1)[0]
    hot = type(spec)(**{**spec.__dict__, "params": {**spec.params, "R_e_hous": spec.params["R_e_hous"] * 1.5}})
    a = machine_run(MODEL, cycle, spec, 1800.0)
    b = machine_run(MODEL, cycle, hot, 1800.0)
    assert len(a) == 1801 and np.allclose(a.columns["speed_rpm"], b.columns["speed_rpm"])
    assert b.columns["housing"][-1] > a.columns["housing"][-1] + 0.5


def test_an_error_row_carries_a_key_errors_message_without_quotes():
    from thermal_edge.fleet.runs import Machine
    from thermal_edge.fleet.task import run_machine

    def job():
        raise KeyError("model m has no parameter(s) R_x")

    rows = run_machine(job, Machine("m1", ("a.csv",)))
    assert rows[0]["message"] == "model m has no parameter(s) R_x"
