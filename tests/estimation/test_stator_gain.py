"""The sensor update of the observer with the flux estimate fused: the stator's rows of the gain
are those of the observer without the flux estimate (an independent :class:`Observer` run in
lockstep), the rotor's rows and the offset's the optimal gain of the fused covariance (computed
here by hand), and the covariance the Joseph form of that mixed gain, symmetric positive definite
throughout."""
from __future__ import annotations

import dataclasses

import numpy as np
from test_flux_changes import MAGNET, SENSORS, TRUE, electrical

from thermal_edge.estimation.flux import PARAMS, FluxModel
from thermal_edge.estimation.fusion import FluxFusion, FluxObserver, flux_samples, rotor_nodes
from thermal_edge.estimation.observer import Observer
from thermal_edge.estimation.predict import initial_from_run, model_inputs


def commissioned() -> FluxModel:
    """Seen: the 40-60 A bin only, its error held over 30 s with a white share of a half."""
    row = [TRUE[k] for k in PARAMS]
    return dataclasses.replace(FluxModel(dict(TRUE), {}, 4, 20.0, {2: 0.3**2}, 500.0, 10.0, tau_s=30.0,
                                         cv_params=[row, row]), white_share=0.5)


def joint(obs: FluxObserver) -> np.ndarray:
    """The covariance the sensor update uses: over ``[T; φ_a]`` and, while anchored, the extra states."""
    if not obs.anchored:
        return obs.Pa.copy()
    return np.block([[obs.Pa, obs.Ce], [obs.Ce.T, obs.Ve]])


def spd(obs: FluxObserver) -> None:
    """The covariances symmetric, those of the temperatures (with and without the flux estimate)
    positive definite, the joint one positive semi-definite (the change error's variance is zero
    at a commissioned operating point, where the estimate is used as it is)."""
    C = joint(obs)
    np.testing.assert_array_equal(C, C.T)
    assert np.linalg.eigvalsh(C).min() > -1e-12 * np.abs(C).max()
    for C in (obs.Pa, obs.covariance(), obs.unfused if obs.unfused is not None else obs.Pa):
        np.testing.assert_allclose(C, C.T, rtol=0.0, atol=1e-15 * np.abs(C).max())
        assert np.linalg.eigvalsh(0.5 * (C + C.T)).min() > 0.0


def test_stator_gain_is_the_unfused_observers_rotor_gain_the_fused_optimum(pm10kw, heated):
    truth = heated.columns["magnet_true"]
    e = electrical(heated, truth, ld_second_half=5.3e-4)
    fm = commissioned()
    fs = flux_samples(fm, e, heated.dt, extrapolate=True)
    inputs = model_inputs(pm10kw, heated)
    T0 = initial_from_run(pm10kw, heated)
    obs = FluxObserver(pm10kw, T0, None, heated.dt)
    ref = Observer(pm10kw, T0, None, heated.dt)  # the observer without the flux estimate
    m = pm10kw.node_index(MAGNET)
    fusion = FluxFusion(fm, [m], heated.dt)
    n = len(pm10kw.nodes)
    rotor = rotor_nodes(pm10kw, [m])
    stator = np.setdiff1d(np.arange(n), rotor)
    idx = [pm10kw.node_index(pm10kw.sensors[s]) for s in SENSORS]
    used = relative = anchored_updates = differs = 0
    for k in range(len(heated)):
        if k:
            ref.T = obs.T.copy()  # its transition linearised where the fused one's is
            u = {c: float(v[k - 1]) for c, v in inputs.items()}
            obs.predict(u)
            ref.predict(u)
        np.testing.assert_allclose(obs.Pa if obs.unfused is None else obs.unfused, ref.Pa, rtol=1e-10, atol=1e-12)
        y = np.array([float(heated.columns[s][k]) for s in SENSORS])
        before, xe0, P = obs.T.copy(), obs.xe.copy(), joint(obs)
        nu = y - before[idx]
        Sy = lambda C: C[np.ix_(idx, idx)] + np.eye(len(idx)) * obs.r2  # noqa: E731
        k_ref = np.linalg.solve(Sy(ref.Pa), ref.Pa[idx, :n]).T  # the unfused observer's gain, by hand
        k_opt = np.linalg.solve(Sy(P), P[idx, :]).T  # the optimal gain of the fused covariance
        obs.update(dict(zip(SENSORS, y)))
        ref.update(dict(zip(SENSORS, y)))
        dT = obs.T - before
        np.testing.assert_allclose(dT[stator], k_ref[stator] @ nu, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(dT[rotor], k_opt[rotor] @ nu, rtol=1e-9, atol=1e-12)
        # the whole covariance: the Joseph form of the gain just used (the parameters' rows and the
        # change error's zero: considered)
        K = k_opt.copy()
        K[stator] = k_ref[stator]
        K[n:len(obs.Pa)] = 0.0
        if obs.anchored:
            anchored_updates += 1
            K[-1] = 0.0
            np.testing.assert_allclose(obs.xe - xe0, K[-2:] @ nu, rtol=1e-9, atol=1e-12)
        H = np.zeros((len(idx), len(P)))
        H[np.arange(len(idx)), idx] = 1.0
        A = np.eye(len(P)) - K @ H
        np.testing.assert_allclose(joint(obs), A @ P @ A.T + obs.r2 * K @ K.T, rtol=1e-9, atol=1e-10)
        differs += bool(np.max(np.abs(k_ref[stator] - k_opt[stator])) > 1e-4)
        spd(obs)
        a, b = fusion.step(obs, k * heated.dt, fs, k, e)
        used, relative = used + a, relative + b
        spd(obs)
    # both kinds of fusion ran, the stator's gain was not the fused optimum's, and the unfused
    # observer's covariance was carried through
    assert used > 0.9 * len(heated) and relative > 0.3 * len(heated) and anchored_updates > 0.9 * len(heated)
    assert differs > 0.5 * len(heated)
    assert obs.unfused is not None and set(obs.unfused_rows) == set(stator)


def test_a_covariance_set_from_outside_drops_the_unfused_one(pm10kw, heated):
    """A restart or a gap sets the covariance: the unfused one is dropped, the next direct
    estimate starts it again from the covariance then."""
    obs = FluxObserver(pm10kw, initial_from_run(pm10kw, heated), None, heated.dt)
    m = pm10kw.node_index(MAGNET)
    rotor = rotor_nodes(pm10kw, [m])
    assert obs.unfused is None
    assert obs.update_node(m, float(obs.T[m]) + 1.0, 1.0, corrects=rotor)
    assert obs.unfused is not None and not np.allclose(obs.unfused, obs.Pa)
    obs.P = obs.P + np.eye(len(obs.T))
    assert obs.unfused is None
    P0 = obs.Pa.copy()
    assert obs.update_node(m, float(obs.T[m]) + 1.0, 1.0, corrects=rotor)
    np.testing.assert_array_equal(obs.unfused, P0)
    # an estimate that corrects every node considers none: no unfused covariance is carried
    plain = FluxObserver(pm10kw, initial_from_run(pm10kw, heated), None, heated.dt)
    assert plain.update_node(m, float(plain.T[m]) + 1.0, 1.0, corrects=np.arange(len(plain.T)))
    assert plain.unfused is None
