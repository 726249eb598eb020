"""The SQP fits: the analytic one simulates each point SLSQP evaluates once and follows the same
path as value and gradient asked for separately; the fits run BLAS on one thread."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize
from threadpoolctl import threadpool_info, threadpool_limits

from thermal_edge.estimation.blas import blas_threads, one_blas_thread
from thermal_edge.estimation.common import ParamSpace, window_from_arrays
from thermal_edge.estimation.gauss_newton import fit_gauss_newton
from thermal_edge.estimation.objective import Objective
from thermal_edge.estimation.sqp import fit_sqp
from thermal_edge.lptn import Simulator

NAMES = ("R_e_hous", "r_ins_sw", "k_c_sw")


@pytest.fixture(scope="module")
def problem(pm10kw, make_run):
    run = make_run(pm10kw, "varied_drive.yaml", 900.0, seed=3)
    start = pm10kw.with_parameters({"R_e_hous": 6.5, "k_c_sw": 2.2})
    cols = {c: run.run.columns[c] for c in pm10kw.inputs}
    meas = {s: run.run.columns[s] for s in pm10kw.sensors}
    return start, window_from_arrays(start, cols, meas, run.truth.T[0], 1.0)


class CountingSimulator(Simulator):
    def __init__(self, model):
        super().__init__(model)
        self.points: list[bytes] = []

    def simulate(self, theta, *args, **kwargs):
        self.points.append(np.asarray(theta).tobytes())
        return super().simulate(theta, *args, **kwargs)


def _objective(start, window, sim=None):
    return Objective(sim or Simulator(start), ParamSpace(start, NAMES, start.nominal()), window, prior_weight=1e-4)


def test_analytic_sqp_simulates_each_point_once_on_the_path_of_separate_value_and_gradient(problem):
    start, window = problem
    sim = CountingSimulator(start)
    r = fit_sqp(_objective(start, window, sim), max_iter=3)
    assert len(sim.points) == len(set(sim.points))  # no point simulated twice (value, then gradient)
    assert r.iterations == 3 and r.objective_after < r.objective_before
    # independently: SLSQP asking for the value (one simulation) and the gradient (another) apart
    ref = _objective(start, window)
    phi0 = np.log(ref.space.values())
    res = minimize(ref.value, phi0, jac=lambda phi: ref.evaluate(phi).grad, method="SLSQP",
                   bounds=ref.space.log_bounds(), options={"maxiter": 3, "ftol": 1e-12})
    assert np.allclose(np.log(r.values), res.x, rtol=0, atol=1e-9)


def test_adopt_takes_a_subset_of_a_wider_evaluation_as_a_simulation_gives_it(problem):
    start, window = problem
    wide = Objective(Simulator(start), ParamSpace(start, (*NAMES, "c_p_sw", "R_e_cap"), start.nominal()), window,
                     prior_weight=1e-4)
    ev_wide = wide.evaluate(np.log(wide.space.values()))
    sim = CountingSimulator(start)
    sub = _objective(start, window, sim)
    phi = np.log(sub.space.values())
    got = sub.adopt(phi, ev_wide, wide.space.names)
    assert sub.evaluate(phi) is got and sim.points == []  # remembered: no simulation
    fresh = _objective(start, window).evaluate(phi)
    assert got.value == pytest.approx(fresh.value, rel=1e-12)
    assert np.allclose(got.grad, fresh.grad, rtol=1e-9, atol=0)
    assert np.allclose(got.hess, fresh.hess, rtol=1e-9, atol=0)
    with pytest.raises(ValueError):
        sub.adopt(phi, ev_wide, NAMES)  # names that do not match the evaluation's columns


def test_numerical_sqp_and_gauss_newton_improve_the_objective(problem):
    start, window = problem
    for r in (fit_sqp(_objective(start, window), max_iter=2, gradient="numerical"),
              fit_gauss_newton(_objective(start, window), max_iter=3)):
        assert r.objective_after < r.objective_before


def _blas_counts() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_one_blas_thread_pins_and_restores():
    with threadpool_limits(limits=2, user_api="blas"):
        assert max(_blas_counts()) == 2 == blas_threads()
        with one_blas_thread():
            assert _blas_counts() and set(_blas_counts()) == {1}
        assert max(_blas_counts()) == 2
    with threadpool_limits(limits=1, user_api="blas"), one_blas_thread():
        assert set(_blas_counts()) == {1}
