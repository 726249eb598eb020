"""The test run discovery recommends is one a drive may hold: no current at standstill (a locked
rotor's DC phase currents heat one phase twice as much as the RMS current says), and every limited
node 10 K below its warning temperature in both fitted models. Two pm10kw fits that differ in the
housing's resistance to the air (×0.5): they differ most where the most heat must leave at the
least air flow, at standstill with current, which is no test to run."""
from __future__ import annotations

import dataclasses

import numpy as np

from thermal_edge.discovery import fitting as F
from thermal_edge.discovery import judge
from thermal_edge.lptn import Role, load_model, steady_state
from thermal_edge.shipped import config_path
from thermal_edge.sim.cycles import cycle_run, load_cycle


def test_the_separating_point_is_a_test_a_drive_may_hold():
    model = load_model(config_path("machines", "pm10kw.yaml"))
    run = cycle_run(load_cycle(config_path("cycles", "varied_drive.yaml")), model.drive["kt_nm_per_arms"], 1800.0)
    theta_b = model.nominal().copy()
    theta_b[model.parameter_index(["R_e_hous"])[0]] *= 0.5
    a = F.Fit("a", {}, model, model.nominal(), ())
    b = dataclasses.replace(a, label="b", theta=theta_b)
    data = F.Data(run, list(model.sensors), len(run) // 2, 1, {})
    p = judge.separating_point(a, b, data)
    assert p is not None
    speed, current = p.inputs[model.find_input(Role.SPEED)], p.inputs[model.find_input(Role.CURRENT)]
    assert not (speed == 0.0 and current > 0.0), p.describe()
    for fit in (a, b):
        T, _ = steady_state(model, p.inputs, fit.theta)
        for lim in model.limits:
            assert float(T[model.node_index(lim.node)]) < lim.warn_c - judge.TEST_MARGIN_K, (p.describe(), lim.name)
    assert np.isfinite(p.diff) and p.diff > 0
