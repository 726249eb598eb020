"""``bench real``'s figures for one start on the first 40 min of the Paderborn run: every key the
issue names, and the 1σ the run allows for each final parameter (the residuals' correlation
counted) ordered as the physics says. Skips visibly without ``../shared/data/paderborn``."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from thermal_edge.bench import real
from thermal_edge.data import read_run
from thermal_edge.lptn import load_model
from thermal_edge.shipped import config_path

PADERBORN = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "paderborn"
RUN = PADERBORN / "run_a.csv"


@pytest.mark.skipif(not RUN.exists(), reason=f"{RUN} absent (the Paderborn data are never part of this repository)")
def test_one_start_reports_every_figure_and_the_bands_the_run_allows():
    base = load_model(config_path("machines", "paderborn4.yaml"), data_dir=PADERBORN)
    run = read_run(RUN, "paderborn").slice(0, 960)  # 40 min of 2.5 s rows
    out = real.one_start(base, run, {"R_c_sy": 1.5}, {})
    for target, seen in (("pm", False), ("stator_tooth", False), ("stator_yoke", True), ("stator_winding", True)):
        fig = out[target]
        assert fig["seen"] is seen
        for key in ("mse", "fixed_mse", "observer_mse", "fixed_observer_mse", "band_coverage", "ekf_open_loop_mse"):
            assert np.isfinite(fig[key]), (target, key)
        assert 0.0 <= fig["band_coverage"] <= 1.0
    sd = out["final_rel_std_pct"]
    assert set(sd) == set(out["final_params"]) == set(base.adaptable)
    assert out["autocorrelation_samples"] >= 1.0
    # the steady state (measured most of the time) fixes the resistances; the yoke's capacity
    # shows only in the slow transients, through the yoke PT100 alone
    assert max(sd["R_c_sy"], sd["R_sy_sw"]) < sd["C_sw"] < sd["C_sy"]
    assert out["decisions"] == len(range(180, int(run.t[-1] - run.t[0]) + 1, 180))
