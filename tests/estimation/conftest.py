"""Fixtures for the estimation tests: the 10 kW model, short simulated runs, and a tiny model."""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from pathlib import Path

import numpy as np
import pytest

from thermal_edge.lptn import load_model
from thermal_edge.sim.cycles import cycle_run, load_cycle
from thermal_edge.sim.plant import simulate_plant

ROOT = Path(__file__).resolve().parents[2]
PADERBORN = ROOT.parent / "shared" / "data" / "paderborn"


@pytest.fixture(scope="session")
def pm10kw():
    return load_model(ROOT / "config" / "machines" / "pm10kw.yaml")


def plant_run(model, cycle: str, seconds: float, seed: int, params=None, noise=0.1):
    inputs = cycle_run(load_cycle(ROOT / "config" / "cycles" / cycle), model.drive["kt_nm_per_arms"], seconds)
    return simulate_plant(model, inputs, params, noise_k=noise, resolution_k=0.1 if noise else 0.0, seed=seed)


@pytest.fixture(scope="session")
def make_run():
    """The factory ``plant_run(model, cycle, seconds, seed, params=None, noise=0.1)``."""
    return plant_run


@pytest.fixture(scope="session")
def varied_1h(pm10kw):
    return plant_run(pm10kw, "varied_drive.yaml", 3600.0, seed=5)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="module")
def heated(pm10kw, make_run):
    """20 min of the varied drive cycle on pm10kw with the true magnet (``magnet_2``) as a column:
    the run the flux-fusion tests feed their voltages from."""
    res = make_run(pm10kw, "varied_drive.yaml", 1200.0, seed=7)
    res.run.columns["magnet_true"] = res.truth.node("magnet_2")
    return res.run
