"""Replay of the Paderborn run with the published 4-node LPTN (``config/machines/paderborn4.yaml``).

Reference figures (``../shared/reference/paderborn-lptn.md``): open-loop from the measured first
row, Euler at 0.5 s sub-steps, inputs held over each 2.5 s row: mean-over-targets MSE about
1.8 K² (pm ≈ 4.1, yoke ≈ 1.1, tooth ≈ 1.4, winding ≈ 0.65 K²), max abs error ≈ 3.8 K.
Skipped visibly when the data directory is absent.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

PADERBORN = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "paderborn"
REPO = Path(__file__).resolve().parents[2]

REFERENCE_MSE = {"pm": 4.1, "stator_yoke": 1.1, "stator_tooth": 1.4, "stator_winding": 0.65}


@pytest.fixture(scope="module")
def data_dir():
    if not (PADERBORN / "run_a.csv").exists():
        pytest.skip(f"Paderborn data not found at {PADERBORN}")
    return PADERBORN


@pytest.fixture(scope="module")
def replay(data_dir):
    from thermal_edge.data import read_run
    from thermal_edge.estimation.predict import open_loop
    from thermal_edge.lptn import load_model

    model = load_model(REPO / "config" / "machines" / "paderborn4.yaml", data_dir=data_dir)
    run = read_run(data_dir / "run_a.csv", "paderborn")
    traj, scores = open_loop(model, run)
    return model, run, traj, scores


def test_mean_mse(replay):
    _, _, _, scores = replay
    assert set(scores.mse) == set(REFERENCE_MSE)
    assert 1.6 <= scores.mean_mse <= 2.0, scores.as_dict()


@pytest.mark.parametrize("sensor", sorted(REFERENCE_MSE))
def test_per_target_mse(replay, sensor):
    _, _, _, scores = replay
    ref = REFERENCE_MSE[sensor]
    assert 0.75 * ref <= scores.mse[sensor] <= 1.25 * ref, (sensor, scores.mse[sensor], ref)


def test_max_abs_error(replay):
    _, _, _, scores = replay
    worst = max(scores.max_abs.values())
    assert 3.3 <= worst <= 4.3, scores.max_abs


def test_scores_are_recomputable_from_the_trajectory(replay):
    """The scores are what they say: MSE and max abs of the node series against the raw CSV."""
    model, run, traj, scores = replay
    raw = _raw_columns()
    for s in REFERENCE_MSE:
        e = traj.node(model.sensors[s]) - raw[s]
        assert scores.mse[s] == pytest.approx(float(np.mean(e**2)), rel=1e-12)
        assert scores.max_abs[s] == pytest.approx(float(np.max(np.abs(e))), rel=1e-12)
    # the prediction starts at the measured first row
    for s in REFERENCE_MSE:
        assert traj.node(model.sensors[s])[0] == pytest.approx(raw[s][0], abs=1e-9)


def test_replay_with_zoh_is_close_to_euler(replay):
    """The published Euler at 0.5 s and the exact ZOH differ by little on this slow model."""
    from thermal_edge.estimation.predict import open_loop

    model, run, traj, scores = replay
    traj_z, scores_z = open_loop(model, run, method="zoh")
    assert np.abs(traj_z.T - traj.T).max() < 0.5
    assert abs(scores_z.mean_mse - scores.mean_mse) < 0.2


_RAW = None


def _raw_columns():
    global _RAW
    if _RAW is None:
        with open(PADERBORN / "run_a.csv", newline="") as fh:
            rows = list(csv.reader(fh))
        header = rows[0]
        data = [[float(v) for v in r] for r in rows[1:] if r]
        _RAW = {h: np.array([r[i] for r in data]) for i, h in enumerate(header)}
    return _RAW


def test_reader_time_and_current(data_dir):
    from thermal_edge.data import read_run

    run = read_run(data_dir / "run_a.csv", "paderborn")
    raw = _raw_columns()
    n = len(raw["i_d"])
    assert len(run) == n == 3003
    np.testing.assert_array_equal(run.t, 2.5 * np.arange(n))
    assert run.dt == 2.5
    i_rms = np.array([math.sqrt(d * d + q * q) / math.sqrt(2.0) for d, q in zip(raw["i_d"], raw["i_q"])])
    np.testing.assert_allclose(run.columns["i_rms"], i_rms, rtol=1e-14, atol=0)
    # renamed columns carry the raw values
    for src, dst in [("motor_speed", "speed_rpm"), ("torque", "torque_nm"), ("ambient", "ambient_c"), ("coolant", "coolant_c")]:
        np.testing.assert_array_equal(run.columns[dst], raw[src])
    for s in REFERENCE_MSE:
        np.testing.assert_array_equal(run.columns[s], raw[s])
