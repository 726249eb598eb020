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
