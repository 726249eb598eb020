"""The magnet temperature from the inverter's voltages as a measurement of the magnet node:
the update against the textbook Kalman update of the whole covariance, the disagreement check,
and the observer unchanged where the estimate is absent or uninformative."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.data import Run
from thermal_edge.estimation.flux import Electrical, FluxModel
from thermal_edge.estimation.fusion import run_fused
from thermal_edge.estimation.observer import Observer
from thermal_edge.estimation.predict import initial_from_run, model_inputs

SENSORS = ("slot_winding", "end_winding", "housing")
MAGNET = "magnet_2"


@pytest.fixture(scope="module")
def heated(pm10kw, make_run):
    """20 min of the varied cycle with the plant's true magnet temperature and an observer warmed
    up on it (the magnet's band then carries the rotor-side parameters' spread)."""
    res = make_run(pm10kw, "varied_drive.yaml", 1200.0, seed=7)
    res.run.columns["magnet_true"] = res.truth.node(MAGNET)
    return res.run


def warmed(model, run: Run, k: int = 600) -> Observer:
    inputs = model_inputs(model, run)
    obs = Observer(model, initial_from_run(model, run), None, run.dt)
    for j in range(k):
        if j:
            obs.predict({c: float(v[j - 1]) for c, v in inputs.items()})
        obs.update({s: float(run.columns[s][j]) for s in SENSORS})
    return obs


def test_update_is_the_kalman_update_of_the_whole_covariance(pm10kw, heated):
    obs = warmed(pm10kw, heated)
    m = pm10kw.node_index(MAGNET)
    T0, C0 = obs.T.copy(), obs.covariance()
    value, var = float(T0[m]) + 1.5, 0.8**2
    assert obs.update_node(m, value, var)
    gain = C0[:, m] / (C0[m, m] + var)
    np.testing.assert_allclose(obs.T, T0 + gain * (value - T0[m]), atol=1e-10)
    np.testing.assert_allclose(obs.covariance(), C0 - np.outer(gain, C0[m, :]), atol=1e-9)
    assert obs.std()[m] < np.sqrt(C0[m, m])  # the magnet's band narrows
    assert (obs.node_updates_used, obs.node_updates_refused) == (1, 0)


def test_disagreement_beyond_both_bands_is_refused_and_counted(pm10kw, heated):
    obs = warmed(pm10kw, heated)
    m = pm10kw.node_index(MAGNET)
    T0, s0 = obs.T.copy(), obs.std()[m]
    far = float(T0[m]) - 1.96 * (s0 + 1.0) - 0.5  # beyond the model's band and a 1 K estimate's band
    assert not obs.update_node(m, far, 1.0)
    assert obs.node_updates_refused == 1
    np.testing.assert_array_equal(obs.T, T0)
    near = float(T0[m]) - 1.96 * (s0 + 1.0) + 0.5
    assert obs.update_node(m, near, 1.0)
    assert obs.node_updates_used == 1


def test_uninformative_values_leave_the_observer_alone(pm10kw, heated):
    obs = warmed(pm10kw, heated, k=50)
    m = pm10kw.node_index(MAGNET)
    T0, P0 = obs.T.copy(), obs.covariance()
    for var in (np.inf, np.nan, 0.0, -1.0):
        assert not obs.update_node(m, 80.0, var)
    assert not obs.update_node(m, np.nan, 1.0)
    np.testing.assert_array_equal(obs.T, T0)
    np.testing.assert_array_equal(obs.covariance(), P0)
    assert (obs.node_updates_used, obs.node_updates_refused) == (0, 0)


def electrical(run: Run, magnet_c: np.ndarray, rpm_floor: float = 0.0) -> Electrical:
    """Voltages of a machine with ψ = 0.1 (1 − 0.0011 (T_m − 20)) Wb, L_d 0.5 mH, 4 pole pairs."""
    n = len(run)
    rpm = np.maximum(run.columns["speed_rpm"], rpm_floor)
    w = rpm * 2 * np.pi / 60 * 4
    i_d, i_q = np.full(n, -40.0), run.columns["i_rms"] * np.sqrt(2)
    u_q = w * (5e-4 * i_d + 0.1 * (1 - 0.0011 * (magnet_c - 20)))
    return Electrical(np.zeros(n), u_q, i_d, i_q, rpm, np.full(n, 60.0))


def flux_model(sigma_max_k: float = 10.0, speed_min_rpm: float = 500.0) -> FluxModel:
    params = {"r20": 0.0, "v_err": 0.0, "psi20": 0.1, "beta": -1.1e-4, "ld0": 5e-4, "ld1": 0.0, "lq0": 1e-3, "lq1": 0.0}
    return FluxModel(params, {}, 4, 1000.0, {0: 0.1**2}, speed_min_rpm, sigma_max_k, tau_s=10.0)


def test_without_the_voltages_the_observer_is_as_before(pm10kw, heated):
    """No flux model: exactly the service's loop (and its prediction before each sample's
    readings); a flux model whose every point is uninformative
    (the machine slower than the run it was commissioned on: low speed): the same, bit for bit."""
    inputs = model_inputs(pm10kw, heated)
    obs = Observer(pm10kw, initial_from_run(pm10kw, heated), None, heated.dt)
    ref_T, ref_s, ref_p = [], [], []
    for k in range(len(heated)):
        if k:
            obs.predict({c: float(v[k - 1]) for c, v in inputs.items()})
        ref_p.append(obs.T.copy())
        obs.update({s: float(heated.columns[s][k]) for s in SENSORS})
        ref_T.append(obs.T.copy())
        ref_s.append(obs.std())
    plain = run_fused(pm10kw, heated, SENSORS, None, MAGNET)
    np.testing.assert_array_equal(plain.estimate, np.array(ref_T))
    np.testing.assert_array_equal(plain.sigma, np.array(ref_s))
    np.testing.assert_array_equal(plain.prediction, np.array(ref_p))  # before each sample's readings
    truth = heated.columns["magnet_true"]
    slow = run_fused(pm10kw, heated, SENSORS, flux_model(speed_min_rpm=1e6), MAGNET,
                     electrical=electrical(heated, truth))
    assert slow.informative == 0 and not slow.used.any()
    np.testing.assert_array_equal(slow.estimate, plain.estimate)
    np.testing.assert_array_equal(slow.sigma, plain.sigma)


def test_an_informative_estimate_narrows_the_magnet_band(pm10kw, heated):
    truth = heated.columns["magnet_true"]
    e = electrical(heated, truth, rpm_floor=1000.0)
    plain = run_fused(pm10kw, heated, SENSORS, None, MAGNET)
    fused = run_fused(pm10kw, heated, SENSORS, flux_model(), MAGNET, electrical=e)
    m = pm10kw.node_index(MAGNET)
    assert fused.used.sum() > 0.9 * len(heated)
    # the estimate's error correlated over tau_s is a state of the filter: consecutive estimates
    # tell less than as many independent ones, and the band narrows by what they do tell
    assert np.median(fused.sigma[300:, m]) < 0.6 * np.median(plain.sigma[300:, m])
    err = lambda r: np.sqrt(np.mean((r.estimate[300:, m] - truth[300:]) ** 2))  # noqa: E731
    assert err(fused) <= err(plain)


def test_update_of_the_mean_of_two_nodes_is_the_kalman_update(pm10kw, heated):
    obs = warmed(pm10kw, heated)
    idx = [pm10kw.node_index("magnet_1"), pm10kw.node_index("magnet_2")]
    h = np.zeros(len(obs.T))
    h[idx] = 0.5
    T0, C0 = obs.T.copy(), obs.covariance()
    value, var = float(h @ T0) - 1.0, 0.5**2
    assert obs.update_node(idx, value, var)
    s = float(h @ C0 @ h) + var
    gain = C0 @ h / s
    np.testing.assert_allclose(obs.T, T0 + gain * (value - h @ T0), atol=1e-10)
    np.testing.assert_allclose(obs.covariance(), C0 - np.outer(gain, h @ C0), atol=1e-9)


def test_inflation_weakens_the_gain_not_the_check(pm10kw, heated):
    obs = warmed(pm10kw, heated)
    m = pm10kw.node_index(MAGNET)
    T0, C0, s0 = obs.T.copy(), obs.covariance(), obs.std()[m]
    far = float(T0[m]) + 1.96 * (s0 + 1.0) + 0.5  # outside both bands with σ 1 K, inside with σ 10 K
    assert not obs.update_node(m, far, 1.0, inflate=100.0)
    assert obs.update_node(m, float(T0[m]) + 1.0, 1.0, inflate=100.0)
    gain = C0[:, m] / (C0[m, m] + 100.0)
    np.testing.assert_allclose(obs.T, T0 + gain * 1.0, atol=1e-10)


def test_the_stator_considered_the_rotor_rows_are_the_kalman_gains(pm10kw, heated):
    """``corrects`` = the rotor's nodes: the stator's estimates and their covariance stay as they
    were (Schmidt), the rotor's move by the textbook gain's rows, and the whole covariance is the
    Joseph form of that gain (computed here by hand)."""
    from thermal_edge.estimation.fusion import rotor_nodes

    obs = warmed(pm10kw, heated)
    m = pm10kw.node_index(MAGNET)
    rotor = rotor_nodes(pm10kw, [m])
    roles = {pm10kw.node_roles[pm10kw.nodes[i]] for i in rotor}
    assert {"magnet", "rotor_iron", "shaft"} == {str(r) for r in roles}
    stator = np.setdiff1d(np.arange(len(obs.T)), rotor)
    assert {pm10kw.node_index(n) for n in pm10kw.sensors.values()} <= set(stator)
    T0, C0 = obs.T.copy(), obs.covariance()
    value, var = float(T0[m]) + 2.0, 0.8**2
    assert obs.update_node(m, value, var, corrects=rotor)
    gain = C0[:, m] / (C0[m, m] + var)
    gain[stator] = 0.0
    np.testing.assert_allclose(obs.T, T0 + gain * 2.0, atol=1e-10)
    np.testing.assert_array_equal(obs.T[stator], T0[stator])
    A = np.eye(len(T0)) - np.outer(gain, np.eye(len(T0))[m])
    np.testing.assert_allclose(obs.covariance(), A @ C0 @ A.T + var * np.outer(gain, gain), atol=1e-8)
    np.testing.assert_allclose(obs.covariance()[np.ix_(stator, stator)], C0[np.ix_(stator, stator)], atol=1e-9)
    # the magnet's own correction is the unconstrained filter's
    full = warmed(pm10kw, heated)
    assert full.update_node(m, value, var)
    assert obs.T[m] == pytest.approx(full.T[m], abs=1e-10)
    assert obs.std()[m] == pytest.approx(full.std()[m], abs=1e-9)


def test_the_fusion_never_moves_a_sensed_stator_node(pm10kw, heated):
    """Over a fused run every flux update leaves the stator's nodes where the sensor update put
    them: replayed tick by tick, the stator's estimate after the fusion step equals the one before."""
    from thermal_edge.estimation.fusion import FluxFusion, FluxObserver, flux_samples, rotor_nodes

    truth = heated.columns["magnet_true"]
    e = electrical(heated, truth, rpm_floor=1000.0)
    fm = flux_model()
    m = pm10kw.node_index(MAGNET)
    stator = np.setdiff1d(np.arange(len(pm10kw.nodes)), rotor_nodes(pm10kw, [m]))
    inputs = model_inputs(pm10kw, heated)
    obs = FluxObserver(pm10kw, initial_from_run(pm10kw, heated), None, heated.dt)
    fusion = FluxFusion(fm, [m], heated.dt)
    fs = flux_samples(fm, e, heated.dt)
    used = 0
    for k in range(len(heated)):
        if k:
            obs.predict({c: float(v[k - 1]) for c, v in inputs.items()})
        obs.update({s: float(heated.columns[s][k]) for s in SENSORS})
        before = obs.T.copy()
        u, _ = fusion.step(obs, k * heated.dt, fs, k, e)
        used += u
        np.testing.assert_array_equal(obs.T[stator], before[stator])
        assert obs.T[m] != before[m] or not u
    assert used > 0.9 * len(heated)
