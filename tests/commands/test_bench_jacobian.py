"""``bench jacobian``: the varying-input case times the new (vectorised) and the old (stepped)
Jacobian and simulation in one run, and its ratios are the medians of the rounds' own ratios."""
from __future__ import annotations

import statistics

from thermal_edge.bench import jacobian


def test_varying_case_reports_old_and_new_side_by_side():
    v = jacobian.run(repeat=3, hours=0.05).varying
    for key in ("analytic", "analytic_stepped", "numerical", "simulation", "simulation_stepped"):
        runs = v[f"{key}_runs_s"]
        assert len(runs) == 3 and all(t > 0 for t in runs)
        assert v[f"{key}_s"] == statistics.median(runs)
    # the ratios recomputed from the rounds, pair by pair
    pair = lambda a, b: statistics.median([x / y for x, y in zip(v[a], v[b])])  # noqa: E731
    assert v["speedup_vs_stepped"] == pair("analytic_stepped_runs_s", "analytic_runs_s")
    assert v["simulation_speedup"] == pair("simulation_stepped_runs_s", "simulation_runs_s")
    assert v["speedup_vs_forward"] == pair("numerical_runs_s", "analytic_runs_s")
    assert v["stepped_speedup_vs_forward"] == pair("numerical_runs_s", "analytic_stepped_runs_s")
    assert v["stepped_over_limit"] == v["analytic_stepped_s"] / v["arith_limit_s"]
    # the new way is the old one reordered: the same numbers to round-off
    assert v["vectorised_vs_stepped_max_rel"] < 1e-9 and v["simulation_vs_stepped_max_rel"] < 1e-9
