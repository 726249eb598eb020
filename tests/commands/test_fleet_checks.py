"""fleet: every run CSV is checked against the model before any task is sent; a run that cannot
be right fails its machine (an error row and one line on stderr), not the fleet."""
from __future__ import annotations

import pytest
from cmd_testlib import TWO_NODE, te

pq = pytest.importorskip("pyarrow.parquet")
pytest.importorskip("distributed")


def test_a_kelvin_run_is_an_error_row_and_the_rest_is_evaluated(good_run, tmp_path):
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    header, *rows = [ln.split(",") for ln in good_run.read_text().splitlines() if ln and not ln.startswith("#")]
    j = header.index("housing")
    (fleet / "m1.csv").write_text(good_run.read_text())
    kelvin = [[f"{float(v) + 273.15:.6g}" if i == j else v for i, v in enumerate(r)] for r in rows]
    (fleet / "m2.csv").write_text("\n".join(",".join(r) for r in [header, *kelvin]) + "\n")
    out = tmp_path / "eval.parquet"
    r = te("fleet", "evaluate", "--model", TWO_NODE, fleet / "*.csv", "--out", out, "--workers", "1", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    refused = [ln for ln in r.stderr.splitlines() if "refused" in ln]
    assert len(refused) == 1 and str(fleet / "m2.csv") in refused[0] and "kelvin" in refused[0], r.stderr
    assert r.stdout.startswith(f"{fleet / 'm1.csv'}: 1801 samples every 1 s")  # the summary of the good run
    rows = pq.read_table(out).to_pylist()
    err = [x for x in rows if x["kind"] == "error"]
    assert [(x["machine"], x["name"]) for x in err] == [("m2", "RunError")] and "kelvin" in err[0]["message"]
    assert {x["machine"] for x in rows if x["kind"] == "sensor"} == {"m1"}
