"""``replay --plot`` and ``--out``: the figure is a PNG of the expected size, the table has one row
per sample and the columns the docs name, and its numbers agree with what replay prints."""
from __future__ import annotations

import csv
import json
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from cmd_testlib import TWO_NODE, te

SENSORS = ("winding_t", "housing")
PER_NODE = ("predicted", "observer", "band_low", "band_high")


def _png_size(path: Path) -> tuple[int, int]:
    """Width and height from a PNG's signature and IHDR chunk (the file format, not matplotlib)."""
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR"
    return struct.unpack(">II", head[16:24])


def _read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path) as fh:
        rows = [r for r in csv.reader(ln for ln in fh if not ln.startswith("#"))]
    return rows[0], np.array(rows[1:], dtype=float)


def _samples(run: Path) -> int:
    return sum(1 for ln in run.read_text().splitlines() if ln and not ln.startswith("#")) - 1


def test_open_loop_plot_and_csv(good_run, tmp_path):
    png, table = tmp_path / "replay.png", tmp_path / "replay.csv"
    r = te("replay", "--model", TWO_NODE, "--run", good_run, "--plot", png, "--out", table, "--json")
    assert r.returncode == 0, r.stderr
    scores = json.loads(r.stdout)
    w, h = _png_size(png)
    assert (w, h) == (1100, 720)  # 11 in x (2 sensor panels + 1 operating-point panel) x 2.4 in at 100 dpi
    assert 30_000 < png.stat().st_size < 2_000_000
    header, data = _read_csv(table)
    expected = ["t", "speed_rpm", "i_rms", "ambient_c"]
    for s in SENSORS:
        expected += [f"{s}_measured"] + [f"{s}_{k}" for k in PER_NODE]
    expected += [f"hot_spot_{k}" for k in PER_NODE] + ["adaptation"]
    assert header == expected
    assert len(data) == _samples(good_run) == scores["samples"]
    col = {h: data[:, i] for i, h in enumerate(header)}
    run_header, run_data = _read_csv(good_run)
    for s in SENSORS:  # the measured column is the run's; the printed MSE is the one of this prediction
        np.testing.assert_array_equal(col[f"{s}_measured"], run_data[:, run_header.index(s)])
        e = col[f"{s}_predicted"] - col[f"{s}_measured"]
        assert np.mean(e**2) == pytest.approx(scores["mse"][s], rel=1e-3, abs=1e-4)  # 6 digits in the CSV
        lo, mid, hi = col[f"{s}_band_low"], col[f"{s}_observer"], col[f"{s}_band_high"]
        assert np.all(lo < mid) and np.all(mid < hi)
        np.testing.assert_allclose(hi - mid, mid - lo, atol=2e-4)  # symmetric: estimate ± Z95 σ
        inside = np.mean(np.abs(col[f"{s}_measured"] - mid) <= (hi - mid) + 1e-4)
        assert inside > 0.5  # most readings of a good run lie in the observer's 95 % band
    # the winding sensor is the hot-spot node of this model: the same prediction
    np.testing.assert_array_equal(col["hot_spot_predicted"], col["winding_t_predicted"])
    assert not col["adaptation"].any()  # open loop: no decision


def test_adapting_replay_marks_its_decisions_in_parquet_and_png(good_run, tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    png, table = tmp_path / "adapt.png", tmp_path / "adapt.parquet"
    # a wrong start (R_wh x3, R_ha x2) so that the adapter has something to decide
    r = te("replay", "--model", TWO_NODE, "--run", good_run, "--adapt", "--set", "R_wh=0.15", "--set", "R_ha=0.2",
           "--period", "300", "--plot", png, "--out", table, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    t = pq.read_table(table).to_pydict()
    n = _samples(good_run)
    assert all(len(v) == n for v in t.values())
    flags = np.array(t["adaptation"])
    assert int(np.sum(flags > 0)) == len(out["decisions"]) > 0
    assert int(np.sum(flags == 2)) == sum(1 for d in out["decisions"] if d["accepted"])
    times = np.array(t["t"])[flags > 0]
    np.testing.assert_allclose(times, [d["t"] for d in out["decisions"]])
    for p, v in out["final_params"].items():  # the parameter trace ends at the final parameters
        assert t[f"param_{p}"][-1] == pytest.approx(v, rel=1e-9)
    assert _png_size(png) == (1100, 720)


def test_plot_without_matplotlib_says_how_to_install(good_run, tmp_path, monkeypatch):
    """matplotlib is the optional ``report`` extra: without it, one line with the pip command, exit 2,
    and nothing computed."""
    blocker = tmp_path / "block" / "matplotlib"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ImportError('matplotlib blocked for this test')\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(blocker.parent), os.environ.get("PYTHONPATH")])))
    r = te("replay", "--model", TWO_NODE, "--run", good_run, "--plot", tmp_path / "x.png")
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        "thermal-edge replay: error: --plot: this needs matplotlib, which is not installed: "
        "pip install 'thermal-edge[report]'"]
    assert not (tmp_path / "x.png").exists()


def test_discover_report_without_matplotlib_refused_before_any_work(good_run, tmp_path, monkeypatch):
    """``discover --out`` writes a report with figures: without matplotlib it says so before the
    analysis (nothing on stdout: not even the run's summary), and --no-report is the way out."""
    blocker = tmp_path / "block" / "matplotlib"
    blocker.mkdir(parents=True)
    (blocker / "__init__.py").write_text("raise ImportError('matplotlib blocked for this test')\n")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(blocker.parent), os.environ.get("PYTHONPATH")])))
    out = tmp_path / "disc"
    r = te("discover", "--model", TWO_NODE, "--run", good_run, "--out", out)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().splitlines() == [
        f"thermal-edge discover: error: --out {out}: the report needs matplotlib, which is not installed: "
        "pip install 'thermal-edge[report]'; or --no-report for the model alone"]
    assert not out.exists()


def test_discover_on_a_run_without_a_gap_prints_no_trend(good_run):
    """Data simulated from the model itself: the verdict is no gap, and the residual's shape (noise)
    is not printed as a trend to act on; the gap status says the same in --json."""
    r = te("discover", "--model", TWO_NODE, "--run", good_run)
    assert r.returncode == 0, r.stderr
    assert "no gap" in r.stdout.splitlines()[1]
    assert not any(line.startswith("the residual ") for line in r.stdout.splitlines()), r.stdout
    j = te("discover", "--model", TWO_NODE, "--run", good_run, "--json")
    assert json.loads(j.stdout)["gap_status"] == "none"


@pytest.mark.parametrize("option, value", [("--threshold", "0.2"), ("--decimate", "5"), ("--sensors", "housing"),
                                           ("--period", "300")])
def test_an_adapter_option_without_adapt_is_refused_not_ignored(good_run, tmp_path, option, value):
    """Open loop runs no adapter: its options would change nothing (the table of ``--out`` is the
    same to the last digit with any ``--period``), so each is refused in one line naming it."""
    r = te("replay", "--model", TWO_NODE, "--run", good_run, option, value, "--out", tmp_path / "x.csv")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"thermal-edge replay: error: {option}: only with --adapt (the open-loop replay runs no adapter)"]
    assert not (tmp_path / "x.csv").exists()
    r = te("replay", "--model", TWO_NODE, "--run", good_run, option, value, "--adapt", "--json")
    assert r.returncode == 0, r.stderr
