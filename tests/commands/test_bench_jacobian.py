"""``bench jacobian``: the varying-input case times the new (vectorised) and the old (stepped)
Jacobian and simulation in one run, by the wall clock and in CPU time, and its ratios are the
medians of the rounds' own ratios."""
from __future__ import annotations

import statistics

from thermal_edge.bench import jacobian


def test_varying_case_reports_old_and_new_side_by_side():
    r = jacobian.run(repeat=3, hours=0.05)
    v = r.varying
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
    # the same in CPU time, and the bound on forward differences / analytic: p + 1 simulations
    # against one simulation and the sensitivities
    for key in ("analytic", "analytic_stepped", "numerical", "simulation", "simulation_stepped"):
        runs = v[f"{key}_cpu_runs_s"]
        assert len(runs) == 3 and all(t >= 0 for t in runs)
        assert v[f"{key}_cpu_s"] == statistics.median(runs)
    assert v["cpu_speedup_vs_stepped"] == pair("analytic_stepped_cpu_runs_s", "analytic_cpu_runs_s")
    assert v["cpu_speedup_vs_forward"] == pair("numerical_cpu_runs_s", "analytic_cpu_runs_s")
    bound = statistics.median([(r.params + 1) * s / a for s, a in zip(v["simulation_runs_s"], v["analytic_runs_s"])])
    assert v["forward_bound"] == bound
    # the sensitivities alone: each round's Jacobian less that round's simulation, in limits
    beyond = statistics.median([(a - s) / v["arith_limit_s"] for a, s in zip(v["analytic_runs_s"], v["simulation_runs_s"])])
    assert v["sensitivities_over_limit"] == beyond
    # the new way is the old one reordered: the same numbers to round-off
    assert v["vectorised_vs_stepped_max_rel"] < 1e-9 and v["simulation_vs_stepped_max_rel"] < 1e-9
    # a speed that sweeps: one piece and chunks agree, peaks and times measured for both
    w = r.sweep
    assert w["operating_points"] > 1
    for key in ("whole_simulation", "chunked_simulation", "whole_jacobian", "chunked_jacobian"):
        assert w[f"{key}_peak_mb"] > 0 and w[f"{key}_s"] > 0
    assert w["temperatures_max_rel"] < 1e-9 and w["sensitivities_max_rel"] < 1e-9
