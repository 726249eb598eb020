"""The flux estimate at a current the commissioning did not see, used for its changes only
(:class:`~thermal_edge.estimation.fusion.FluxObserver`): the update against the textbook Kalman
update of the state augmented by the offset and the change error, an offset the commissioning
could not know absorbed by the offset state, and a wrong calibration never anchored."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from thermal_edge.data import Run
from thermal_edge.estimation.flux import PARAMS, Electrical, FluxModel
from thermal_edge.estimation.fusion import SLOPE_SIGMA_MIN, FluxObserver, run_fused, slope_sigma
from thermal_edge.estimation.predict import initial_from_run, model_inputs

SENSORS = ("slot_winding", "end_winding", "housing")
MAGNET = "magnet_2"
TRUE = {"r20": 0.0, "v_err": 0.0, "psi20": 0.1, "beta": -1.1e-4, "ld0": 5e-4, "ld1": 0.0, "lq0": 1e-3, "lq1": 0.0}


def warmed(model, run: Run, k: int = 600) -> FluxObserver:
    inputs = model_inputs(model, run)
    obs = FluxObserver(model, initial_from_run(model, run), None, run.dt)
    for j in range(k):
        if j:
            obs.predict({c: float(v[j - 1]) for c, v in inputs.items()})
        obs.update({s: float(run.columns[s][j]) for s in SENSORS})
    return obs


def test_relative_update_is_the_kalman_update_of_the_augmented_state(pm10kw, heated):
    obs = warmed(pm10kw, heated)
    m = pm10kw.node_index(MAGNET)
    obs.anchor(20.0, 0.3)
    T0, C0 = obs.T.copy(), obs.covariance()
    value, var, change = float(T0[m]) + 7.0, 0.5**2, -4.0
    assert obs.update_relative(m, value, var, change)
    # by hand: state [T; b; s], b and s independent of T, measurement T_m + b + s·change
    n = len(T0)
    C = np.zeros((n + 2, n + 2))
    C[:n, :n] = C0
    C[n, n], C[n + 1, n + 1] = 20.0**2, 0.3**2
    h = np.zeros(n + 2)
    h[m], h[n], h[n + 1] = 1.0, 1.0, change
    gain = C @ h / (h @ C @ h + var)
    gain[n + 1] = 0.0  # the change error is considered (Schmidt), never corrected
    np.testing.assert_allclose(obs.T, T0 + gain[:n] * 7.0, atol=1e-10)
    np.testing.assert_allclose(obs.xe, gain[n:] * 7.0, atol=1e-10)
    assert obs.xe[1] == 0.0
    A = np.eye(n + 2) - np.outer(gain, h)
    post = A @ C @ A.T + var * np.outer(gain, gain)  # Joseph form: valid for any gain
    np.testing.assert_allclose(obs.covariance(), post[:n, :n], atol=1e-8)
    np.testing.assert_allclose(obs.extra_covariance(), post[n:, n:], atol=1e-8)
    assert obs.extra_covariance()[1, 1] == pytest.approx(0.3**2)  # its σ stays the prior's


def test_sensor_update_while_anchored_moves_the_offset_by_its_correlation(pm10kw, heated):
    """After a relative update the offset is correlated with the magnet; a sensor update then
    corrects it by the textbook gain of the joint state, and the temperatures as the observer would."""
    obs = warmed(pm10kw, heated)
    m = pm10kw.node_index(MAGNET)
    obs.anchor(20.0, 0.3)
    assert obs.update_relative(m, float(obs.T[m]) + 3.0, 0.5**2, 0.0)
    n = len(obs.T)
    r = pm10kw.node_index(pm10kw.sensors["slot_winding"])
    P = np.block([[obs.Pa, obs.Ce], [obs.Ce.T, obs.Ve]])
    T0, xe0 = obs.T.copy(), obs.xe.copy()
    y = float(T0[r]) + 0.4
    obs.update({"slot_winding": y})
    k = P[:, r] / (P[r, r] + obs.r2)
    k[-1] = 0.0  # the change error: considered
    np.testing.assert_allclose(obs.T, T0 + k[:n] * 0.4, atol=1e-10)
    np.testing.assert_allclose(obs.xe, xe0 + k[-2:] * 0.4, atol=1e-10)
    assert obs.xe[0] != xe0[0] and obs.xe[1] == 0.0


def electrical(run: Run, magnet_c: np.ndarray, ld_second_half: float) -> Electrical:
    """A machine at 3,000 rpm: i_d −40 A in the first half, −120 A in the second, where its true
    L_d differs from the commissioned 0.5 mH (an offset the commissioning could not see)."""
    n = len(run)
    rpm = np.full(n, 3000.0)
    w = rpm * 2 * np.pi / 60 * 4
    half = np.arange(n) >= n // 2
    i_d = np.where(half, -120.0, -40.0)
    ld = np.where(half, ld_second_half, TRUE["ld0"])
    u_q = w * (ld * i_d + TRUE["psi20"] + TRUE["beta"] * (magnet_c - 20))
    return Electrical(np.zeros(n), u_q, i_d, np.zeros(n), rpm, np.full(n, 60.0))


def commissioned(**kw) -> FluxModel:
    """Seen: the 40-60 A bin only; two identical cross-validation fits (the change's σ is the floor)."""
    row = [TRUE[k] for k in PARAMS]
    return FluxModel(dict(TRUE), {}, 4, 20.0, {2: 0.05**2}, 500.0, 10.0, tau_s=30.0, cv_params=[row, row], **kw)


def test_an_unseen_current_tells_the_changes_and_its_offset_is_learnt(pm10kw, heated):
    truth = heated.columns["magnet_true"]
    e = electrical(heated, truth, ld_second_half=5.3e-4)  # ψ̂ 3.6 mWb low: the raw estimate 33 K warm there
    fm = commissioned()
    raw = fm.temperature(e)
    second = np.arange(len(heated)) > len(heated) // 2 + 10
    assert np.mean(raw[second] - truth[second]) == pytest.approx(32.7, abs=0.5)
    plain = run_fused(pm10kw, heated, SENSORS, fm, MAGNET, electrical=e)
    changes = run_fused(pm10kw, heated, SENSORS, fm, MAGNET, electrical=e, extrapolate=True)
    assert plain.relative is not None and not plain.relative.any()
    assert changes.relative is not None and changes.relative[second].all()
    assert changes.refused == 0
    m = pm10kw.node_index(MAGNET)
    err = lambda r: float(np.sqrt(np.mean((r.estimate[second, m] - truth[second]) ** 2)))  # noqa: E731
    assert err(changes) < err(plain)
    # the band still covers the truth (counted here, not by the module's helper)
    inside = np.abs(changes.estimate[second, m] - truth[second]) <= 1.96 * changes.sigma[second, m]
    assert inside.mean() >= 0.9


def test_a_wrong_calibration_is_never_anchored(pm10kw, heated):
    truth = heated.columns["magnet_true"]
    e = electrical(heated, truth, ld_second_half=5.3e-4)
    good = commissioned()
    bad = dataclasses.replace(good, params={**good.params, "ld0": 1.2 * good.params["ld0"]})
    plain = run_fused(pm10kw, heated, SENSORS, None, MAGNET)
    wrong = run_fused(pm10kw, heated, SENSORS, bad, MAGNET, electrical=e, extrapolate=True)
    assert wrong.refused > 0 and not wrong.used.any()
    np.testing.assert_array_equal(wrong.estimate, plain.estimate)


def test_slope_sigma_is_the_spread_of_the_fits_sensitivity():
    one = Electrical(*(np.array([x]) for x in (0.0, 100.0, -100.0, 0.0, 5000.0, 60.0)))
    base = commissioned()
    assert slope_sigma(base, one, 0) == SLOPE_SIGMA_MIN  # identical fits: the floor
    rows = [[TRUE[k] * (f if k == "ld0" else 1.0) for k in PARAMS] for f in (0.5, 1.5)]
    spread = dataclasses.replace(base, cv_params=rows)
    # ∂T/∂i_d = −L_d/β: the fits' sensitivities are 0.5 and 1.5 of the commissioned one, RMS spread 0.5
    assert slope_sigma(spread, one, 0) == pytest.approx(0.5, rel=1e-6)
    assert slope_sigma(dataclasses.replace(base, cv_params=[]), one, 0) == np.inf


def test_at_low_speed_the_band_is_the_observers(pm10kw, heated):
    """Below the commissioning's speeds nothing is used, not even for its changes: bit for bit the
    observer without voltages."""
    truth = heated.columns["magnet_true"]
    e = electrical(heated, truth, ld_second_half=5.3e-4)
    slow = dataclasses.replace(commissioned(), speed_min_rpm=1e6)
    plain = run_fused(pm10kw, heated, SENSORS, None, MAGNET)
    changes = run_fused(pm10kw, heated, SENSORS, slow, MAGNET, electrical=e, extrapolate=True)
    assert not changes.used.any()
    np.testing.assert_array_equal(changes.estimate, plain.estimate)
    np.testing.assert_array_equal(changes.sigma, plain.sigma)


def test_tick_by_tick_is_the_replay(pm10kw, heated):
    """The service's way, one sample per tick (steady from the previous tick's speed), gives the
    replay's run exactly."""
    from thermal_edge.estimation.flux import steady
    from thermal_edge.estimation.fusion import FluxFusion, flux_samples

    truth = heated.columns["magnet_true"]
    e = electrical(heated, truth, ld_second_half=5.3e-4)
    fm = commissioned()
    ref = run_fused(pm10kw, heated, SENSORS, fm, MAGNET, electrical=e, extrapolate=True)
    inputs = model_inputs(pm10kw, heated)
    obs = FluxObserver(pm10kw, initial_from_run(pm10kw, heated), None, heated.dt)
    m = pm10kw.node_index(MAGNET)
    fusion = FluxFusion(fm, [m], heated.dt)
    st = steady(e.speed_rpm)
    used = []
    for k in range(len(heated)):
        if k:
            obs.predict({c: float(v[k - 1]) for c, v in inputs.items()})
        obs.update({s: float(heated.columns[s][k]) for s in SENSORS})
        one = Electrical(*(np.asarray(a)[k:k + 1] for a in (e.u_d, e.u_q, e.i_d, e.i_q, e.speed_rpm, e.winding_c)))
        used.append(fusion.step(obs, k * heated.dt, flux_samples(fm, one, heated.dt, st[k:k + 1], extrapolate=True), 0, one))
        np.testing.assert_allclose(obs.T, ref.estimate[k], atol=1e-9)
    assert [u for u, _ in used] == list(ref.used) and [r for _, r in used] == list(ref.relative)
