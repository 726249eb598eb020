"""``bench real`` and ``bench paper`` report their progress per replayed sample, every 100 samples
and at the end, to the benchmark's ``Progress`` (the command draws the bar)."""
from __future__ import annotations

from thermal_edge.bench.real import sample_counter
from thermal_edge.estimation.adapter import AdapterConfig
from thermal_edge.estimation.online import run_online


def test_sample_counter_reports_every_100_samples_and_the_end():
    calls: list[tuple[str, float, float, str]] = []
    count = sample_counter(lambda *a: calls.append(a), "start 1 of 1 (published)", 250)
    for _ in range(250):
        count(1)
    assert calls == [("start 1 of 1 (published)", 100, 250, "sample"), ("start 1 of 1 (published)", 200, 250, "sample"),
                     ("start 1 of 1 (published)", 250, 250, "sample")]


def test_the_online_replay_counts_every_sample(pm10kw, make_run):
    plant = make_run(pm10kw, "paper_600rpm_70nm.yaml", 400.0, seed=5)
    calls: list[tuple[str, float, float, str]] = []
    run_online(pm10kw, plant.run, AdapterConfig(params=("R_e_hous",)), T0=plant.truth.T[0],
               progress=sample_counter(lambda *a: calls.append(a), "E1", len(plant.run)))
    n = len(plant.run)
    assert [c[1] for c in calls] == list(range(100, n + 1, 100)) + ([n] if n % 100 else [])
    assert calls[-1] == ("E1", n, n, "sample")
