"""The worker re-derives the open-loop state after an accepted decision part by part: the state it
lands on is the adapter's own replay of the whole window, and a part's simulation is all that is
in memory at once."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from svc_testlib import CYCLES, MODEL

from thermal_edge.estimation.adapter import OnlineAdapter
from thermal_edge.lptn import load_model
from thermal_edge.service.adaptation import replayed_state
from thermal_edge.settings import AdapterConfig
from thermal_edge.sim.cycles import cycle_run, load_cycle
from thermal_edge.sim.plant import simulate_plant


@pytest.fixture(scope="module")
def recorded():
    """An adapter with 3 h of a varied drive recorded (its plant's states as the estimates)."""
    model = load_model(MODEL)
    inputs = cycle_run(load_cycle(CYCLES / "varied_drive.yaml"), model.drive["kt_nm_per_arms"], 10800.0)
    r = simulate_plant(model, inputs, {"R_e_hous": 4.0}, noise_k=0.1, resolution_k=0.1, seed=3)
    ad = OnlineAdapter(model, AdapterConfig(window_s=10800.0), 1.0)
    t = r.run.t
    for k in range(len(t)):
        ad.record(float(t[k]), {c: r.run.columns[c][k] for c in model.inputs},
                  {s: r.run.columns[s][k] for s in model.sensors}, r.truth.T[k])
    return ad, float(t[-1])


@pytest.mark.parametrize("chunk", [3, 7, 100, 900])
def test_the_parts_land_on_the_whole_window_s_state(recorded, chunk):
    ad, t_end = recorded
    whole, t_whole = ad.replayed_state(t_end - 1500.0)
    parts, t_parts = replayed_state(ad, t_end - 1500.0, chunk)
    assert t_parts == t_whole == t_end
    assert np.max(np.abs(parts - whole)) < 1e-9  # K


def test_one_part_is_the_adapter_s_replay(recorded):
    ad, t_end = recorded
    assert np.array_equal(replayed_state(ad, t_end - 600.0, 10_000)[0], ad.replayed_state(t_end - 600.0)[0])


def test_parts_hold_less_in_memory_than_the_whole(recorded):
    ad, t_end = recorded

    def peak(f):
        tracemalloc.start()
        try:
            f()
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    whole = peak(lambda: ad.replayed_state(t_end - 10800.0))
    parts = peak(lambda: replayed_state(ad, t_end - 10800.0, 300))
    assert parts < 0.5 * whole
