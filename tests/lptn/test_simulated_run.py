"""A simulation whose sensitivities follow later (``Simulator.simulate_run``).

The sensitivities added to a simulated run must be what a simulation asked for them at once
gives (to the last bit: the same operations on the same numbers), for any parameters and any
number of times, on held inputs (closed form), on a noisy current (stretches vectorised in
time), on the Paderborn model and on a run simulated in time chunks; the pieces they come from
(the continuous system's derivatives from the kept solves, the discretisation's from its
eigendecomposition) equal the ones computed at once.
"""
from __future__ import annotations

import numpy as np
import pytest
from lptn_ref import pm10kw_inputs

from thermal_edge.lptn import Simulator, discretise, steady_state
from thermal_edge.lptn.discretise import derive
from thermal_edge.lptn.network import Network


def _setup(model, seconds=900.0, noisy=False):
    inputs, dt, _ = pm10kw_inputs(model, seconds)
    inputs = {k: np.asarray(v, float).copy() for k, v in inputs.items()}
    if noisy:  # a current that is not held exactly: every step a new loss feedback
        rng = np.random.default_rng(7)
        inputs["i_rms"] = inputs["i_rms"] * (1.0 + 1e-3 * rng.standard_normal(len(inputs["i_rms"])))
    T0, _ = steady_state(model, {k: float(v[0]) for k, v in inputs.items()})
    return inputs, dt, 0.5 * (T0 + 25.0)


def _same(a, b):
    assert a.shape == b.shape
    assert np.array_equal(a, b), float(np.abs(a - b).max())


@pytest.mark.parametrize("noisy", [False, True])
def test_sensitivities_of_a_kept_run_equal_those_asked_at_once(pm10kw_model, noisy):
    m = pm10kw_model
    inputs, dt, T0 = _setup(m, noisy=noisy)
    sim = Simulator(m)
    theta = m.nominal() * (1.0 + 0.05 * np.cos(np.arange(len(m.nominal()))))  # not the nominal point
    rows = list(m.sensors.values())
    run = sim.simulate_run(theta, inputs, dt, T0)
    value = sim.simulate(theta, inputs, dt, T0)
    np.testing.assert_allclose(run.trajectory.T, value.T, rtol=1e-12, atol=1e-12)
    for wrt, keep in ((m.adaptable, rows), (m.adaptable[:5], None), (m.adaptable[3:9], rows)):
        late = run.sensitivities(wrt, keep)
        now = sim.simulate(theta, inputs, dt, T0, wrt=wrt, rows=keep)
        _same(late.T, now.T)
        _same(late.S, now.S)
        assert late.wrt == tuple(wrt)
    assert run.sensitivities(()) is run.trajectory and run.trajectory.S is None


def test_kept_run_on_paderborn4(paderborn_model, paderborn_run):
    m = paderborn_model
    run = paderborn_run.slice(0, 900)
    inputs = {c: run.columns[c] for c in m.inputs}
    T0 = np.array([run.columns[s][0] for s in m.sensors])
    sim = Simulator(m)
    late = sim.simulate_run(m.nominal(), inputs, run.dt, T0).sensitivities(m.parameter_names)
    now = sim.simulate(m.nominal(), inputs, run.dt, T0, wrt=m.parameter_names)
    _same(late.T, now.T)
    _same(late.S, now.S)


def test_a_chunked_run_is_simulated_again(pm10kw_model):
    m = pm10kw_model
    inputs, dt, T0 = _setup(m, 600.0)
    inputs["speed_rpm"] = np.linspace(1000.0, 2000.0, len(inputs["speed_rpm"])).round(1)  # a point per step
    sim = Simulator(m, max_operating_points=40)
    late = sim.simulate_run(m.nominal(), inputs, dt, T0).sensitivities(m.adaptable[:4])
    now = sim.simulate(m.nominal(), inputs, dt, T0, wrt=m.adaptable[:4])
    _same(late.T, now.T)
    _same(late.S, now.S)


@pytest.mark.parametrize("method", ["zoh", "euler"])
def test_derivatives_from_kept_solves_and_eigendecomposition(pm10kw_model, method):
    m = pm10kw_model
    net = Network(m)
    op = {k: np.array([900.0, 2400.0]) for k in net.matrix_inputs}
    wrt = list(m.parameter_index(m.adaptable))
    theta = m.nominal()
    at_once = net.continuous(theta, op, K=2, wrt=wrt)
    kept = net.continuous(theta, op, K=2, solves=True)
    later = net.derivatives(kept, theta, op, wrt)
    for name in ("A", "W", "c", "dZ", "dV", "dg", "dc"):
        _same(getattr(later, name), getattr(at_once, name))
    with pytest.raises(ValueError, match="solves"):
        net.derivatives(net.continuous(theta, op, K=2), theta, op, wrt)
    sub = 0.01 if method == "euler" else None  # a stable sub-step on this stiff network
    d_now = discretise(at_once, 1.0, method, sub)
    d_late = derive(discretise(kept, 1.0, method, sub), later, 1.0, method)
    assert type(d_late) is type(d_now)
    for name in ("Phi", "Gam", "mu", "phi", "Ht", "Zh", "Yt", "dPhit", "dGamt"):
        _same(getattr(d_late, name), getattr(d_now, name))
