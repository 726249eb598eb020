"""Closing the gap to the window's optimum once the model predicts within the threshold: a
refinement fit when the window pins a parameter away from its value, and challengers judged
from their own shadow observer."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.estimation.adapter import AdapterConfig, OnlineAdapter
from thermal_edge.estimation.observer import Observer
from thermal_edge.estimation.shadow import ShadowObserver

HOURS = 3.0


@pytest.fixture(scope="module")
def varied_3h(pm10kw, make_run):
    return make_run(pm10kw, "varied_drive.yaml", HOURS * 3600.0, seed=7)


def _feed(ad: OnlineAdapter, model, plant, ks) -> None:
    run = plant.run
    for k in ks:
        ad.record(float(run.t[k]), {c: float(run.columns[c][k]) for c in model.inputs},
                  {s: float(run.columns[s][k]) for s in model.sensors}, plant.truth.T[k])


def _adapter(model, theta, threshold_k: float) -> OnlineAdapter:
    # the error trigger off (threshold far above the error): only the window's pinning can trigger a fit
    return OnlineAdapter(model, AdapterConfig(threshold_k=threshold_k, min_window_s=1800.0, decimate=5), 1.0, theta)


def test_a_window_that_pins_a_parameter_away_triggers_a_refinement_toward_the_plant(pm10kw, varied_3h):
    plant_value = pm10kw.nominal()[pm10kw.parameter_index(["r_c_hous"])[0]]
    theta = pm10kw.nominal()
    theta[pm10kw.parameter_index(["r_c_hous"])[0]] = plant_value * 1.10
    ad = _adapter(pm10kw, theta, threshold_k=5.0)
    n = len(varied_3h.run)
    _feed(ad, pm10kw, varied_3h, range(n))
    d = ad.decide(float(varied_3h.run.t[n - 1]))
    assert d.error_before_k < 5.0 and d.horizon_error_k < 5.0  # the error alone triggers nothing
    assert d.triggered and "pins r_c_hous" in d.reason and ad.challenger is not None
    # the window's pinned step said how far: -9.5 % in log is the way back to the plant's value
    off = float(d.reason.split("pins r_c_hous ")[1].split(" %")[0])
    assert off == pytest.approx(100 * np.log(1 / 1.10), abs=3.0)
    # the refinement's challenger is within 3 % of the plant's value (it started 10 % off)
    cand = ad.challenger[1][pm10kw.parameter_index(["r_c_hous"])[0]]
    assert abs(cand / plant_value - 1.0) < 0.03


def test_an_infinite_threshold_never_adapts(pm10kw, varied_3h):
    theta = pm10kw.nominal()
    theta[pm10kw.parameter_index(["r_c_hous"])[0]] *= 1.10
    ad = _adapter(pm10kw, theta, threshold_k=np.inf)
    n = len(varied_3h.run)
    _feed(ad, pm10kw, varied_3h, range(n))
    d = ad.decide(float(varied_3h.run.t[n - 1]))
    assert not d.triggered and ad.challenger is None


def test_at_the_plant_s_parameters_the_window_pins_nothing_away(pm10kw, varied_3h):
    ad = _adapter(pm10kw, pm10kw.nominal(), threshold_k=5.0)
    n = len(varied_3h.run)
    _feed(ad, pm10kw, varied_3h, range(n))
    d = ad.decide(float(varied_3h.run.t[n - 1]))
    assert not d.triggered and d.reason == "error below threshold" and ad.challenger is None


def test_the_shadow_observer_is_the_kalman_filter_with_its_own_parameters(pm10kw, make_run):
    """Counted another way: the Observer stepped sample by sample by hand gives the same estimates;
    with the plant's parameters it finds the unmeasured yoke from a state 5 K off, with
    parameters 30 % off in the yoke's contact it settles elsewhere."""
    plant = make_run(pm10kw, "varied_drive.yaml", 1800.0, seed=9)
    run = plant.run
    t = run.t
    inputs = {c: run.columns[c] for c in pm10kw.inputs}
    meas = {s: run.columns[s] for s in pm10kw.sensors}
    T0 = plant.truth.T[0] + 5.0
    yoke = pm10kw.node_index("yoke_1")
    theta = pm10kw.nominal()
    sh = ShadowObserver(pm10kw, theta, 1.0, float(t[0]), T0, {c: float(v[0]) for c, v in inputs.items()})
    sh.follow(t, inputs, meas)
    ref = Observer(pm10kw, T0, theta, 1.0, spread={})
    for k in range(1, len(t)):
        ref.predict({c: float(v[k - 1]) for c, v in inputs.items()})
        ref.update({s: float(v[k]) for s, v in meas.items()})
        if k % 600 == 0:
            np.testing.assert_allclose(sh.state_at(float(t[k])), ref.T, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sh.state_at(float(t[-1])), ref.T, rtol=0, atol=1e-9)
    assert abs(sh.state_at(float(t[-1]))[yoke] - plant.truth.T[-1, yoke]) < 0.5
    other = theta.copy()
    other[pm10kw.parameter_index(["r_c_hous"])[0]] *= 1.3
    sh2 = ShadowObserver(pm10kw, other, 1.0, float(t[0]), T0, {c: float(v[0]) for c, v in inputs.items()})
    sh2.follow(t, inputs, meas)
    assert np.max(np.abs(sh2.state_at(float(t[-1])) - sh.state_at(float(t[-1])))) > 0.05
    # followed in pieces: the same as at once
    sh3 = ShadowObserver(pm10kw, theta, 1.0, float(t[0]), T0, {c: float(v[0]) for c, v in inputs.items()})
    for k1 in (300, 900, len(t)):
        sl = slice(0, k1)
        sh3.follow(t[sl], {c: v[sl] for c, v in inputs.items()}, {s: v[sl] for s, v in meas.items()})
    np.testing.assert_allclose(sh3.state_at(float(t[-1])), sh.state_at(float(t[-1])), rtol=0, atol=1e-12)


def test_a_promoted_refinement_hands_the_service_its_own_estimate(pm10kw, make_run, monkeypatch):
    """The worker's result of an accepted decision carries the promoted parameters' shadow estimate,
    and the service steps it to the present with the new parameters (checked against the model
    step applied by hand)."""
    from thermal_edge.estimation.adapter import Decision
    from thermal_edge.lptn import Stepper
    from thermal_edge.service.adaptation import AdaptationWorker

    plant = make_run(pm10kw, "varied_drive.yaml", 120.0, seed=4)
    run = plant.run
    w = AdaptationWorker(pm10kw, AdapterConfig(), 1.0, pm10kw.nominal(), pm10kw.nominal(), mode="sync", bands=False)
    inputs = [{c: float(run.columns[c][k]) for c in pm10kw.inputs} for k in range(len(run))]
    for k in range(100):
        w.record(float(run.t[k]), inputs[k], {s: float(run.columns[s][k]) for s in pm10kw.sensors}, plant.truth.T[k])
    t_last = float(run.t[99])
    promoted = plant.truth.T[99] + 1.5  # any estimate other than the recorded one
    theta_new = pm10kw.nominal()
    theta_new[pm10kw.parameter_index(["r_c_hous"])[0]] *= 0.9

    def decide(t: float) -> Decision:
        ad = w.adapter
        ad.theta, ad.version, ad.promoted_state = theta_new.copy(), ad.version + 1, (t_last, promoted.copy())
        d = Decision(t=t, error_before_k=0.1, triggered=True, accepted=True, verdict="promoted")
        ad.decisions.append(d)
        return d

    monkeypatch.setattr(w.adapter, "decide", decide)
    rid = w.request(t_last)
    res = w.result(rid)
    assert res is not None
    assert res.accepted and res.state_t == t_last
    np.testing.assert_array_equal(res.estimate, promoted)
    stepper = Stepper(pm10kw, theta_new, 1.0)
    recent = [(float(run.t[k]), inputs[k]) for k in range(95, 105)]
    x = promoted.copy()
    for k in range(99, 105):
        x, _ = stepper.step(x, inputs[k])
    np.testing.assert_allclose(res.state_now(stepper, recent, "estimate"), x, rtol=0, atol=1e-12)
    w.close()
