"""The objective's gradient, Gauss-Newton Hessian and residual Jacobian against finite differences
of the objective itself (simulations only, no sensitivities)."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.estimation.common import ParamSpace, decimate, window_from_arrays
from thermal_edge.estimation.objective import Objective, weights
from thermal_edge.lptn import Simulator

NAMES = ("R_e_hous", "r_ins_sw", "c_p_sw", "k_r_sw", "R_e_cap")


@pytest.fixture(scope="module")
def objective(pm10kw, varied_1h):
    start = pm10kw.with_parameters({"R_e_hous": 7.0, "r_ins_sw": 0.013, "k_r_sw": 2.0})
    run = varied_1h.run
    win = window_from_arrays(start, {c: run.columns[c] for c in start.inputs},
                             {s: run.columns[s] for s in start.sensors}, varied_1h.truth.T[0], run.dt)
    return Objective(Simulator(start), ParamSpace(start, NAMES, start.nominal()), decimate(win, 5), prior_weight=1e-3)


def fd4(f, phi, h=1e-3):
    """Fourth-order central differences of ``f`` along each log-parameter. The simulation's own
    round-off (~1e-10 K) rules out tiny steps; this one keeps truncation below 1e-8 relative."""
    cols = []
    for e in np.eye(len(phi)) * h:
        cols.append((-f(phi + 2 * e) + 8 * f(phi + e) - 8 * f(phi - e) + f(phi - 2 * e)) / (12 * h))
    return np.array(cols).T


def test_gradient_matches_central_differences(objective):
    phi = np.log(objective.space.values())
    ev = objective.evaluate(phi)
    fd = fd4(objective.value, phi)
    assert ev.grad == pytest.approx(fd, rel=1e-5, abs=1e-6 * np.abs(fd).max())


def test_residual_jacobian_and_gauss_newton_hessian(objective):
    phi = np.log(objective.space.values())
    J = objective.residual_jacobian(phi)
    Jfd = fd4(objective.residual_vector, phi)
    big = np.abs(Jfd) > 1e-2 * np.abs(Jfd).max(axis=0)
    assert np.max(np.abs(J[big] - Jfd[big]) / np.abs(Jfd[big])) < 1e-5
    # the objective is the squared norm of the residual vector; its GN Hessian is 2 JᵀJ
    r = objective.residual_vector(phi)
    assert float(r @ r) == pytest.approx(objective.value(phi), rel=1e-12)
    ev = objective.evaluate(phi)
    assert ev.hess == pytest.approx(2 * Jfd.T @ Jfd, rel=1e-5, abs=1e-6 * np.abs(ev.hess).max())


def test_weights_favour_recent_samples_and_sum_to_one():
    t = np.arange(1000.0)
    paper = weights(t, "paper", F=0.05)
    k = np.arange(1, 1001)
    expect = (1 - np.exp(-0.05 * k)) / np.sum(1 - np.exp(-0.05 * k))
    assert paper == pytest.approx(expect, rel=1e-12)
    assert np.all(np.diff(paper) >= 0) and paper.sum() == pytest.approx(1.0)
    forget = weights(t, "forgetting", tau_s=100.0)
    assert forget[-1] / forget[-101] == pytest.approx(np.e, rel=1e-9)
    with pytest.raises(ValueError):
        weights(t, "nonsense")


def test_missing_readings_do_not_count(objective):
    phi = np.log(objective.space.values())
    base = objective.value(phi)
    w = objective.window
    gappy = {s: y.copy() for s, y in w.measured.items()}
    first = next(iter(gappy))
    gappy[first][10:20] = np.nan
    o2 = Objective(objective.sim, objective.space, type(w)(w.inputs, gappy, w.T0, w.dt, w.t), prior_weight=1e-3)
    v2 = o2.value(phi)
    assert np.isfinite(v2) and v2 != base


def _window(model, run, T0):
    return decimate(window_from_arrays(model, {c: run.columns[c] for c in model.inputs},
                                       {s: run.columns[s] for s in model.sensors}, T0, run.dt), 5)


def test_a_free_start_fits_the_start_offsets_by_least_squares(pm10kw, varied_1h):
    """With ``start_free`` the objective is the prediction error minimised over the start's offsets:
    against an independent minimisation over them (fresh simulations from ``T0 + D δ``), and its
    gradient against central differences of the objective itself."""
    from scipy.optimize import least_squares

    from thermal_edge.estimation.predict import start_with_directions

    run = varied_1h.run
    _, D = start_with_directions(pm10kw, run)
    assert D.shape == (len(pm10kw.nodes), len(pm10kw.sensors))
    win = _window(pm10kw, run, varied_1h.truth.T[0] + 0.3)  # a start 0.3 K off everywhere
    space = ParamSpace(pm10kw, NAMES[:3], pm10kw.nominal())
    obj = Objective(Simulator(pm10kw), space, win, weighting="uniform", start_free=D)
    phi = np.log(space.values()) + np.array([0.05, -0.03, 0.02])
    value = obj.value(phi)
    sim, th = Simulator(pm10kw), space.full(np.exp(phi))
    rows = [pm10kw.node_index(n) for n in obj.rows]
    sw = np.sqrt(obj.w)

    def res(delta):
        pred = sim.simulate(th, win.inputs, win.dt, win.T0 + D @ delta).T[:, rows]
        return (sw * np.where(obj.mask, pred - obj.Y0, 0.0)).ravel()

    best = least_squares(res, np.zeros(D.shape[1]), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    assert value == pytest.approx(float(best.fun @ best.fun), rel=1e-7)
    assert value < float(res(np.zeros(D.shape[1])) @ res(np.zeros(D.shape[1]))) * 0.9  # the offsets mattered
    ev = obj.evaluate(phi)
    fd = fd4(obj.value, phi)
    assert ev.grad == pytest.approx(fd, rel=1e-5, abs=1e-6 * np.abs(fd).max())


def test_a_start_reading_off_biases_a_fit_only_without_a_free_start(pm10kw, varied_1h):
    """A start 0.3 K off on the measured nodes (a noisy first reading), fitted from the truth: held,
    the fit takes the slow mode's memory of it for the parameters (errors of percents, residuals
    correlated over many samples); with the start's offsets free, the errors are a tenth of that or
    less, within three of the stated standard deviations, and the residuals white."""
    from scipy.optimize import least_squares

    from thermal_edge.estimation.predict import start_with_directions
    from thermal_edge.estimation.uncertainty import estimate_uncertainty

    run = varied_1h.run
    _, D = start_with_directions(pm10kw, run)
    names = ("R_e_hous", "r_ins_sw")
    err, z, tau = {}, {}, {}
    for key, free in (("held", None), ("free", D)):
        win = _window(pm10kw, run, varied_1h.truth.T[0] + D @ np.full(D.shape[1], 0.3))
        obj = Objective(Simulator(pm10kw), ParamSpace(pm10kw, names, pm10kw.nominal()), win, weighting="uniform",
                        start_free=free)
        phi0 = np.log(obj.space.values())
        fit = least_squares(obj.residual_vector, phi0, jac=obj.residual_jacobian, xtol=1e-12, ftol=1e-14)
        unc = estimate_uncertainty(obj, obj.evaluate(fit.x))
        err[key], z[key], tau[key] = np.abs(fit.x - phi0), np.abs(fit.x - phi0) / unc.rel_std, unc.tau
    assert np.all(err["held"] > 0.005) and np.all(err["free"] < 0.1 * err["held"]), err
    assert np.max(z["free"]) < 3.0, z
    assert tau["held"] > 10.0 and tau["free"] < 1.5, tau
