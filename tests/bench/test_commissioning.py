"""The simulated commissioning run (thermal_edge.bench.commissioning.bench_run): the packaged
cycle asks for more than the winding takes (the plant run open loop at i_d = 0, by
thermal_edge.sim.plant.simulate_plant, passes the hot spot's max), and the bench's own protection
holds every limited node below its max while the magnets still reach the range the protection
bench runs them in."""
from __future__ import annotations

import math

import numpy as np
import pytest

from thermal_edge.bench.commissioning import BENCH_MARGIN_K, bench_run
from thermal_edge.lptn import load_model
from thermal_edge.shipped import config_path
from thermal_edge.sim.cycles import cycle_run, load_cycle
from thermal_edge.sim.plant import simulate_plant
from thermal_edge.sim.pmsm import Pmsm


@pytest.mark.slow
def test_the_bench_protection_caps_the_commissioning_run():
    model = load_model(config_path("machines", "pm10kw.yaml"))
    cycle = config_path("cycles", "commissioning.yaml")
    run = cycle_run(load_cycle(cycle), 5.6)
    open_loop = simulate_plant(model, run, noise_k=0.0, resolution_k=0.0, all_nodes=True).run.columns
    b = bench_run(model, Pmsm(), cycle)
    for lim in model.limits:
        assert lim.max_c - BENCH_MARGIN_K + 1.0 >= b.T[:, model.node_index(lim.node)].max()
    hot = next(lim for lim in model.limits if lim.name == "hot_spot")
    assert np.max(open_loop[f"T_{hot.node}"]) > hot.max_c + 10.0  # what the cycle asks for, uncapped
    magnet = next(lim for lim in model.limits if lim.name == "magnet")
    assert b.T[:, model.node_index(magnet.node)].max() > magnet.max_c - 10.0
    # the protection took torque, never more than asked, and the field weakening ran at 1500 rpm
    assert np.all(np.abs(b.torque_nm) <= np.abs(b.torque_demand_nm) + 1e-6)
    assert np.sum(np.abs(b.torque_nm)) < 0.97 * np.sum(np.abs(b.torque_demand_nm))
    assert np.all(b.i_d[b.speed_rpm < 1300] == 0.0) and np.min(b.i_d[b.speed_rpm >= 1500]) < -5.0
    assert np.allclose(b.torque_nm, b.i_q / math.sqrt(2.0) * 5.6)
