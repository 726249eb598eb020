"""The flux-linkage estimate of the magnet temperature against synthetic machines whose
electrical parameters are known: voltages written here from the steady-state equations directly
(not through the module's regressors), then the commissioning fit must give them back."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.estimation.flux import (
    ALPHA_CU,
    PARAMS,
    Electrical,
    FluxError,
    FluxModel,
    back_emf,
    fit_flux_model,
    steady,
)

P = 4
TRUE = {"r20": 0.018, "v_err": 1.5, "psi20": 0.11, "beta": -0.11 * 0.11 / 100.0, "ld0": 5e-4, "ld1": -6e-5,
        "lq0": 9e-4, "lq1": -1.2e-4}


def voltages(p: dict[str, float], i_d, i_q, rpm, t_w, t_m, pole_pairs=P):
    """u_d, u_q (V) of a PMSM at steady state, from the equations in their textbook form."""
    w = rpm * 2 * np.pi / 60 * pole_pairs
    r = p["r20"] * (1 + ALPHA_CU * (t_w - 20))
    ia = np.sqrt(i_d**2 + i_q**2)
    ld = p["ld0"] + p["ld1"] * ia / 100
    lq = p["lq0"] + p["lq1"] * ia / 100
    psi = p["psi20"] + p["beta"] * (t_m - 20)
    ve_d = p["v_err"] * i_d / np.maximum(ia, 5.0)  # the inverter loses V_e along the current
    ve_q = p["v_err"] * i_q / np.maximum(ia, 5.0)
    return r * i_d - w * lq * i_q + ve_d, r * i_q + w * (ld * i_d + psi) + ve_q


def synthetic(n=3000, seed=0, noise_v=0.05, rpm_range=(1500.0, 6000.0)):
    """Operating points and temperatures varied independently (a rich commissioning run)."""
    g = np.random.default_rng(seed)
    i_d = g.uniform(-220, 0, n)
    i_q = g.uniform(-80, 150, n)
    rpm = np.repeat(g.uniform(*rpm_range, n // 5), 5)  # each speed held for five samples: a steady state
    t_w = g.uniform(20, 140, n)
    t_m = g.uniform(20, 130, n)
    u_d, u_q = voltages(TRUE, i_d, i_q, rpm, t_w, t_m)
    u_d = u_d + g.normal(0, noise_v, n)
    u_q = u_q + g.normal(0, noise_v, n)
    return Electrical(u_d, u_q, i_d, i_q, rpm, t_w), t_m


def true_model(**kw) -> FluxModel:
    return FluxModel(dict(TRUE), {}, P, 20.0, {b: 0.05**2 for b in range(15)}, 500.0, **kw)


def test_fit_recovers_the_parameters():
    e, t_m = synthetic()
    m = fit_flux_model(e, t_m, P, dt=1.0, speed_min_rpm=0.0, folds=3)
    for k in PARAMS:
        assert m.params[k] == pytest.approx(TRUE[k], rel=0.03, abs=2e-6), k
    assert m.tempco_per_k == pytest.approx(-0.0011, rel=0.01)
    # the posterior σ is small where the data see a parameter: every one here
    for k in ("psi20", "beta", "ld0", "lq0"):
        assert m.sigma[k] < 0.01 * abs(TRUE[k]), k


def test_estimate_inverts_the_equations():
    e, t_m = synthetic(noise_v=0.0)
    T, s, ok = true_model().estimate(e)
    assert ok.all()
    np.testing.assert_allclose(T, t_m, atol=1e-8)


def test_variance_table_is_the_voltage_noise_over_omega_beta():
    noise = 0.2
    g = np.random.default_rng(3)
    n = 4000
    i_d, i_q = np.full(n, -150.0) + g.normal(0, 3, n), np.full(n, 80.0) + g.normal(0, 3, n)
    rpm = np.full(n, 4000.0)
    t_w = np.linspace(30, 120, n)
    t_m = np.linspace(25, 110, n) + 5 * np.sin(np.arange(n) / 50)
    u_d, u_q = voltages(TRUE, i_d, i_q, rpm, t_w, t_m)
    e = Electrical(u_d + g.normal(0, noise, n), u_q + g.normal(0, noise, n), i_d, i_q, rpm, t_w)
    m = fit_flux_model(e, t_m, P, dt=1.0)
    expected = noise / (4000 * 2 * np.pi / 60 * P * abs(TRUE["beta"]))  # white noise: σ_u / (ω_el |β|)
    (sig,) = m.sigma_table(4000.0).values()
    assert sig == pytest.approx(expected, rel=0.25)
    assert m.tau_s < 5.0  # white residuals: no correlation time to speak of


def test_standstill_low_speed_and_unseen_currents_are_uninformative():
    e, t_m = synthetic(rpm_range=(3000.0, 6000.0))
    m = fit_flux_model(e, t_m, P, dt=1.0, speed_min_rpm=0.0)
    p5 = np.percentile(e.speed_rpm, 5.0)  # of 3000-6000 rpm
    assert m.speed_min_rpm == pytest.approx(0.9 * p5, rel=0.02)
    probe = Electrical(np.array([1.0, -5.0, -20.0, -20.0]), np.array([0.0, 10.0, 60.0, 60.0]),
                       np.array([0.0, -50.0, -100.0, -100.0]), np.array([0.0, 40.0, 50.0, 400.0]),
                       np.array([0.0, 500.0, 4500.0, 4500.0]), np.full(4, 60.0))
    T, s, ok = m.estimate(probe)
    assert list(ok) == [False, False, True, False]  # standstill, below the run's speeds, seen, 400 A never seen
    assert np.isinf(s[[0, 1, 3]]).all() and np.isfinite(s[2])


def test_pole_pairs_only_scale_flux_and_inductance():
    e, t_m = synthetic(n=1500, seed=4)
    a = fit_flux_model(e, t_m, 4, dt=1.0, speed_min_rpm=0.0, folds=3)
    b = fit_flux_model(e, t_m, 2, dt=1.0, speed_min_rpm=0.0, folds=3,
                       priors={k: (2 * v[0], 2 * v[1]) for k, v in
                               {"psi20": (0.1, 0.1), "beta": (-1e-4, 1e-3), "ld0": (5e-4, 5e-3), "ld1": (0.0, 1e-4),
                                "lq0": (1e-3, 5e-3), "lq1": (0.0, 1e-4)}.items()})
    assert b.params["psi20"] == pytest.approx(2 * a.params["psi20"], rel=1e-3)
    np.testing.assert_allclose(a.estimate(e)[0], b.estimate(e)[0], atol=0.05)


def test_round_trip_and_errors():
    e, t_m = synthetic(n=600, seed=5)
    m = fit_flux_model(e, t_m, P, dt=1.0, speed_min_rpm=0.0, folds=3)
    back = FluxModel.from_dict(m.as_dict())
    np.testing.assert_array_equal(back.estimate(e)[0], m.estimate(e)[0])
    np.testing.assert_array_equal(back.estimate(e)[1], m.estimate(e)[1])
    with pytest.raises(FluxError, match="only 0 samples"):
        fit_flux_model(e, t_m, P, dt=1.0, speed_min_rpm=1e5)
    with pytest.raises(FluxError, match="unknown parameter 'psi'"):
        fit_flux_model(e, t_m, P, dt=1.0, priors={"psi": (0.1, 0.1)})
    with pytest.raises(FluxError, match="rises with the magnet"):
        fit_flux_model(e, 200.0 - t_m, P, dt=1.0, speed_min_rpm=0.0, priors={"beta": (1e-4, 1e-5)})
    with pytest.raises(FluxError, match="no sigma, pole_pairs"):
        FluxModel.from_dict({"params": TRUE, "bin_a": 20.0, "speed_min_rpm": 0.0})


def test_sigma_grows_with_the_distance_from_the_runs_temperatures():
    """σ² = table / (ω β)² + ((T − T_mean) β_spread / β)², written out here."""
    m = true_model()
    m.beta_spread, m.magnet_mean_c = 0.05 * abs(TRUE["beta"]), 60.0
    t_m = np.array([60.0, 100.0, 140.0])
    n = len(t_m)
    i_d, i_q, rpm, t_w = np.full(n, -50.0), np.full(n, 40.0), np.full(n, 3000.0), np.full(n, 80.0)
    u_d, u_q = voltages(TRUE, i_d, i_q, rpm, t_w, t_m)
    T, s, ok = m.estimate(Electrical(u_d, u_q, i_d, i_q, rpm, t_w))
    w_beta = 3000 * 2 * np.pi / 60 * P * abs(TRUE["beta"])
    expected = np.sqrt(0.05**2 / w_beta**2 + ((t_m - 60.0) * 0.05) ** 2)
    np.testing.assert_allclose(s, expected, rtol=1e-9)
    assert ok.all() and s[0] < s[1] < s[2]


def test_a_run_held_at_one_speed_is_informative_at_that_speed():
    """Speed noise of hundredths of an rpm must not gate out the operating point the run was
    commissioned on: counted here as the share of the run's own samples at or above the limit."""
    e, t_m = synthetic(noise_v=0.02)
    g = np.random.default_rng(3)
    rpm = 5500.0 + g.normal(0.0, 0.01, len(t_m))
    e = Electrical(*voltages(TRUE, e.i_d, e.i_q, rpm, e.winding_c, t_m), e.i_d, e.i_q, rpm, e.winding_c)
    m = fit_flux_model(e, t_m, P, dt=1.0, folds=3)
    assert 0.85 * 5500.0 < m.speed_min_rpm < 0.95 * 5500.0
    assert np.mean(np.abs(rpm) >= m.speed_min_rpm) == 1.0


def test_the_cross_validation_fits_are_kept_and_read_back():
    e, t_m = synthetic()
    m = fit_flux_model(e, t_m, P, dt=1.0, speed_min_rpm=0.0, folds=3)
    assert len(m.cv_params) == 4 and all(len(row) == len(PARAMS) for row in m.cv_params)
    assert m.ensemble()[-1] == pytest.approx(m.params)  # the last is the fit on the whole run
    back = FluxModel.from_dict(m.as_dict())
    assert back.cv_params == m.cv_params and back.fit_info == m.fit_info
    old = {k: v for k, v in m.as_dict().items() if k not in ("cv_params", "fit_info")}
    assert FluxModel.from_dict(old).cv_params == []  # a file written before: nothing to extrapolate with
    np.testing.assert_array_equal(m.temperature(e), m.temperature(e, m.params))


def one_point_run(with_ramp: bool):
    """A start-up ramp at zero current (1,200, 3,500, 5,100 rpm: not steady), then one loaded
    operating point at 5,500 rpm while the magnet heats from 22 to 95 °C."""
    n = 600
    g = np.random.default_rng(8)
    t_m = np.concatenate([np.full(3, 22.0), np.linspace(22.0, 95.0, n)])
    t_w = np.concatenate([np.full(3, 22.0), np.linspace(22.0, 115.0, n)])
    rpm = np.concatenate([[1200.0, 3500.0, 5100.0], np.full(n, 5500.0)])
    i_d = np.concatenate([np.zeros(3), np.linspace(-193.0, -203.0, n) + g.normal(0, 0.3, n)])
    i_q = np.concatenate([np.zeros(3), np.full(n, 66.0) + g.normal(0, 0.3, n)])
    u_d, u_q = voltages(TRUE, i_d, i_q, rpm, t_w, t_m)
    e = Electrical(u_d + g.normal(0, 0.05, n + 3), u_q + g.normal(0, 0.05, n + 3), i_d, i_q, rpm, t_w)
    if not with_ramp:
        e = Electrical(*(np.asarray(a)[3:] for a in (e.u_d, e.u_q, e.i_d, e.i_q, e.speed_rpm, e.winding_c)))
        t_m = t_m[3:]
    return e, t_m


def test_zero_current_samples_of_a_ramp_measure_the_flux_linkage():
    """One operating point cannot separate ψ_20 from L_d i_d; the open-circuit back-EMF of a start-up
    ramp can, although a ramp is not steady: at zero current u_q = ω_el ψ_PM at any speed."""
    e, t_m = one_point_run(with_ramp=True)
    assert not steady(e.speed_rpm)[1:3].any() and back_emf(e)[:3].all() and not back_emf(e)[3:].any()
    m = fit_flux_model(e, t_m, P, dt=1.0)
    assert m.params["psi20"] == pytest.approx(TRUE["psi20"], rel=0.01)
    assert m.speed_min_rpm == pytest.approx(0.9 * 5500.0)  # the ramp's speeds saw no loaded point
    ld_200 = m.params["ld0"] + 2.0 * m.params["ld1"]
    assert ld_200 == pytest.approx(TRUE["ld0"] + 2.0 * TRUE["ld1"], rel=0.03)
    e1, t1 = one_point_run(with_ramp=False)
    blind = fit_flux_model(e1, t1, P, dt=1.0)
    assert blind.sigma["psi20"] > 10.0 * m.sigma["psi20"]  # without it the run barely pins ψ_20
