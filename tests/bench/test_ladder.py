"""``bench ladder``: the figures of a small rung recomputed independently (the full model by an ODE
solver, the reduced model and its bound, the two paths' fits against each other), and the command's
table and JSON."""
from __future__ import annotations

import json

import numpy as np
import pytest
from cli_in_process import te_here
from lptn_ref import reference_run  # the lptn tests' independent ODE-solver reference (conftest)

from thermal_edge.bench import ladder
from thermal_edge.estimation.adapter import AdapterConfig
from thermal_edge.estimation.common import decimate, window_from_arrays
from thermal_edge.lptn.chain import chain_model
from thermal_edge.lptn.reduced import ReducedSimulator

NODES, HOURS = 24, 0.75


@pytest.fixture(scope="module")
def row() -> ladder.LadderRow:
    return ladder.rung(NODES, repeat=2, hours=HOURS)


def test_the_measured_error_is_the_reduced_models_distance_from_an_ode_solution(row):
    """The bench's measured error, recomputed with the full model integrated by ``solve_ivp`` (inputs
    and losses held over each of the optimiser's steps, as the discrete model holds them)."""
    m = chain_model(NODES)
    cols, _, _, t, T0 = ladder._history(m, HOURS, seed=0)
    win = decimate(window_from_arrays(m, cols, {}, T0, 1.0, t), AdapterConfig().decimate)
    approx = ReducedSimulator(m).simulate(m.nominal(), win.inputs, win.dt, win.T0).T
    full = reference_run(m, m.nominal(), win.inputs, win.dt, win.T0, hold_losses=True, rtol=1e-9, atol=1e-9)
    sensors = [m.node_index(x) for x in m.sensors.values()]
    assert row.measured_k == pytest.approx(float(np.max(np.abs(full[:, sensors] - approx[:, sensors]))), abs=1e-6)


def test_a_rung_reports_what_was_measured(row):
    assert row.nodes == NODES
    assert row.modes < row.states <= NODES
    assert 0.0 < row.measured_k <= row.bound_k  # the run is near enough the reference for the bound
    assert len(row.dense_runs_s) == len(row.reduced_runs_s) == 2
    assert row.dense_s > 0 and row.reduced_s > 0 and row.ratio > 0
    assert row.selected  # the screening chose parameters: the step optimised
    assert row.fit_rel_diff < 0.02  # both paths fit the same parameters to within 2 %


def test_the_command_prints_the_table_and_json():
    r = te_here("bench", "ladder", "--nodes", "20", "--repeat", "1", "--hours", "0.5")
    assert r.returncode == 0, r.stderr
    assert "dense step s" in r.stdout and "reduced step s" in r.stdout and "error bound K" in r.stdout
    assert "20 nodes: reduced step" in r.stdout
    r = te_here("bench", "ladder", "--nodes", "20", "--repeat", "1", "--hours", "0.5", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert [x["nodes"] for x in out["rows"]] == [20] and out["repeat"] == 1
    assert out["rows"][0]["measured_k"] <= out["rows"][0]["bound_k"]


def test_too_small_a_model_is_a_usage_error():
    r = te_here("bench", "ladder", "--nodes", "8")
    assert r.returncode == 2 and "--nodes" in r.stderr
