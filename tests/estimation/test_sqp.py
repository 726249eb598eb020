"""The SQP fits: the analytic one simulates each point SLSQP evaluates once, adds the
sensitivities only where SLSQP asks for the gradient, and follows the same path as value and
gradient asked for separately; the objective's kept simulation; the fits run BLAS on one thread."""
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
    """Counts the simulations (``points``) and the sensitivities added to kept ones (``late``)."""

    def __init__(self, model):
        super().__init__(model)
        self.points: list[bytes] = []
        self.late: list[bytes] = []

    def simulate(self, theta, *args, **kwargs):
        self.points.append(np.asarray(theta).tobytes())
        return super().simulate(theta, *args, **kwargs)

    def simulate_run(self, theta, *args, **kwargs):
        self.points.append(np.asarray(theta).tobytes())
        run = super().simulate_run(theta, *args, **kwargs)
        late, key = run.sensitivities, np.asarray(theta).tobytes()

        def sensitivities(*a, **k):
            self.late.append(key)
            return late(*a, **k)

        run.sensitivities = sensitivities
        return run


def _objective(start, window, sim=None):
    return Objective(sim or Simulator(start), ParamSpace(start, NAMES, start.nominal()), window, prior_weight=1e-4)


def test_analytic_sqp_simulates_each_point_once_on_the_path_of_separate_value_and_gradient(problem):
    start, window = problem
    sim = CountingSimulator(start)
    r = fit_sqp(_objective(start, window, sim), max_iter=3)
    assert len(sim.points) == len(set(sim.points))  # no point simulated twice (value, then gradient)
    assert sim.late and set(sim.late) <= set(sim.points[1:])  # gradients from the kept simulations
    assert len(sim.late) < len(sim.points) - 1  # and not at every point (rejected line-search trials)
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


def _fields(ev):
    return (ev.value, ev.grad, ev.hess, ev.residuals, ev.jac, ev.T)


def test_kept_simulation_gives_the_derivatives_of_a_fresh_evaluation(problem):
    start, window = problem
    sim = CountingSimulator(start)
    obj = _objective(start, window, sim)
    phi = np.log(obj.space.values()) + np.array([0.05, -0.03, 0.02])
    value = obj.evaluate(phi, derivatives=False, keep=True)
    assert value.value == obj.evaluate(phi, derivatives=False).value and len(sim.points) == 1
    full = obj.evaluate(phi)  # from the kept simulation: no second one
    assert len(sim.points) == 1 and len(sim.late) == 1 and obj.evaluations == 1
    fresh = _objective(start, window).evaluate(phi)
    for a, b in zip(_fields(full), _fields(fresh)):
        assert np.array_equal(a, b)
    assert obj.evaluate(phi) is full and len(sim.late) == 1  # remembered with its derivatives


def test_a_changed_point_does_not_use_the_kept_simulation(problem):
    start, window = problem
    sim = CountingSimulator(start)
    obj = _objective(start, window, sim)
    phi = np.log(obj.space.values())
    obj.evaluate(phi, derivatives=False, keep=True)
    other = phi.copy()
    other[1] += 1e-6
    got = obj.evaluate(other)
    assert len(sim.points) == 2 and sim.late == []  # simulated afresh, with its sensitivities
    fresh = _objective(start, window).evaluate(other)
    for a, b in zip(_fields(got), _fields(fresh)):
        assert np.array_equal(a, b)
    # back at the first point: the kept simulation is gone (only the last point's is kept)
    obj.evaluate(phi)
    assert len(sim.points) == 3 and sim.late == []


def test_keep_is_ignored_by_a_simulator_that_cannot_keep_a_run(problem):
    start, window = problem

    class Plain:  # only simulate(), as the reduced-order simulator
        def __init__(self, model):
            self.model, self.inner, self.calls = model, Simulator(model), 0

        def simulate(self, *args, **kwargs):
            self.calls += 1
            return self.inner.simulate(*args, **kwargs)

    plain = Plain(start)
    obj = Objective(plain, ParamSpace(start, NAMES, start.nominal()), window, prior_weight=1e-4)
    phi = np.log(obj.space.values())
    v = obj.evaluate(phi, derivatives=False, keep=True).value
    ev = obj.evaluate(phi)
    assert ev.value == v and plain.calls == 2 and np.any(ev.grad)


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
