"""The reduced-order path: the stated error bound holds against an ODE solver's run of the full
model, the outputs' steady state is the full model's, the sensitivities are the exact derivatives
of the reduced model (central differences) and close to the full model's (central differences of
the full model), and the path is chosen only where it applies."""
from __future__ import annotations

import numpy as np
import pytest
from lptn_ref import reference_run

from thermal_edge.estimation.adapter import AdapterConfig, OnlineAdapter
from thermal_edge.lptn import ModelError, Simulator, steady_state
from thermal_edge.lptn.chain import chain_document, chain_model
from thermal_edge.lptn.loader import build_model
from thermal_edge.lptn.losses import LossLaws
from thermal_edge.lptn.network import Network
from thermal_edge.lptn.reduced import REDUCE_ABOVE, ReducedSimulator, simulator_for
from thermal_edge.lptn.reduction import check_reducible, output_rows, reduce

SPEED = 600.0  # the reference operating point of the bound's test (rpm)


def _held(N: int, seed: int, hold: int, speed: np.ndarray | float = SPEED) -> dict[str, np.ndarray]:
    """Piecewise-constant current and ambient (and ``speed``) over ``N`` samples."""
    rng = np.random.default_rng(seed)
    seg = -(-N // hold)
    current = np.repeat(rng.uniform(0.0, 25.0, seg), hold)[:N]
    return {"speed_rpm": np.broadcast_to(np.asarray(speed, dtype=float), (N,)).copy(), "i_rms": current,
            "torque_nm": 5.6 * current, "ambient_c": np.repeat(rng.uniform(20.0, 35.0, seg), hold)[:N]}


def _at_rest(model, inputs):
    return steady_state(model, model.at_rest({"ambient_c": float(inputs["ambient_c"][0])}))[0]


def test_the_error_bound_holds_against_an_ode_solver():
    """At the reference (speed held, nominal parameters) and with losses that do not feel the
    temperature (copper coefficient 0: a linear time-invariant system driven by its inputs), the
    reduced model's sensor and limit temperatures stay within the stated bound of the full model
    integrated by ``solve_ivp`` with the inputs held over each step."""
    doc = chain_document(40)
    doc["constants"]["alpha_cu"] = 0.0
    m = build_model(doc, fname="chain40-linear")
    dt = 20.0
    inputs = _held(181, seed=3, hold=9)
    T0 = _at_rest(m, inputs)
    red = reduce(m, op={"speed_rpm": SPEED}, dt=dt)
    assert red.modes < red.size < len(m.nodes)  # modes were dropped, and static vectors added
    approx = ReducedSimulator(m, red).simulate(m.nominal(), inputs, dt, T0)
    full = reference_run(m, m.nominal(), inputs, dt, T0, hold_losses=True, rtol=1e-9, atol=1e-9)
    rows = [m.node_index(x) for x in red.rows]
    err = np.max(np.abs(approx.T[:, rows] - full[:, rows]), axis=0)
    bound = red.bound(dt, np.column_stack([inputs["ambient_c"], approx.P]))
    assert np.all(err <= bound), (err, bound)
    assert np.all(bound < 0.1)  # and it says something
    assert np.ptp(full[:, rows]) > 20.0  # the run heats the machine


def test_the_outputs_steady_state_is_the_full_models():
    """Held inputs at the reference operating point, run for two days in 1 h steps: the reduced
    model's outputs settle where the full model's steady state is (the adjoint static vectors)."""
    m = chain_model(40)
    red = reduce(m, op={"speed_rpm": SPEED}, dt=3600.0)
    held = {"speed_rpm": SPEED, "i_rms": 0.0, "torque_nm": 0.0, "ambient_c": 25.0}  # iron losses only
    T_ss, _ = steady_state(m, held)
    inputs = {k: np.full(49, v) for k, v in held.items()}
    T = ReducedSimulator(m, red).simulate(m.nominal(), inputs, 3600.0, np.full(len(m.nodes), 25.0)).T
    assert np.max(np.abs(T[0] - 25.0)) < 1e-9  # a machine at rest is in the basis: its state projects exactly
    rows = [m.node_index(x) for x in output_rows(m)]
    assert np.max(np.abs(T[-1, rows] - T_ss[rows])) < 1e-8
    assert np.ptp(T_ss) > 1.0  # the losses heat the machine
    others = np.setdiff1d(np.arange(len(m.nodes)), rows)
    assert np.max(np.abs(T[-1, others] - T_ss[others])) > 1e-6  # only the outputs are exact


@pytest.fixture(scope="module")
def varied():
    """A 40-node model on 40 min of speed steps, varying current (copper feedback) and ambient."""
    m = chain_model(40)
    inputs = _held(121, seed=5, hold=6, speed=np.repeat([0.0, 300.0, 900.0, 1200.0, 600.0, 900.0], 21)[:121])
    return m, inputs, 20.0, _at_rest(m, inputs)


CHECKED = ["k_r_sw", "c_p_sw", "R_e_hous", "h_gap0", "r_ins_ew", "c_p_hous"]


def _central(sim, theta, i, inputs, dt, T0, rows, rel=1e-3):
    h = rel * theta[i]

    def at(delta):
        th = theta.copy()
        th[i] += delta
        return sim.simulate(th, inputs, dt, T0).T[:, rows]

    return (-at(2 * h) + 8 * at(h) - 8 * at(-h) + at(-2 * h)) / (12 * h)


def test_sensitivities_are_the_reduced_models_exact_derivatives(varied):
    m, inputs, dt, T0 = varied
    sim = ReducedSimulator(m)
    theta = m.nominal()
    sensors = list(m.sensors.values())
    rows = [m.node_index(x) for x in sensors]
    S = sim.simulate(theta, inputs, dt, T0, wrt=CHECKED, rows=sensors).S
    for j, i in enumerate(m.parameter_index(CHECKED)):
        fd = _central(sim, theta, i, inputs, dt, T0, rows)
        assert np.max(np.abs(S[:, :, j] - fd)) <= 1e-6 * np.max(np.abs(fd)), CHECKED[j]


def test_sensitivities_are_close_to_the_full_models(varied):
    """Against central differences of the full (dense) model: the reduced model's sensitivities at
    the sensors agree to a small fraction of their size (the reduction is not exact)."""
    m, inputs, dt, T0 = varied
    theta = m.nominal()
    sensors = list(m.sensors.values())
    rows = [m.node_index(x) for x in sensors]
    S = ReducedSimulator(m).simulate(theta, inputs, dt, T0, wrt=CHECKED, rows=sensors).S
    full = Simulator(m)
    for j, i in enumerate(m.parameter_index(CHECKED)):
        fd = _central(full, theta, i, inputs, dt, T0, rows)
        assert np.max(np.abs(S[:, :, j] - fd)) <= 5e-3 * np.max(np.abs(fd)), CHECKED[j]


def test_temperatures_close_to_the_full_model_off_the_reference(varied):
    """Speeds, currents and parameters away from the reference: the sensors within 10 mK; the
    trajectory's losses are the loss laws at its temperatures."""
    m, inputs, dt, T0 = varied
    theta = m.with_parameters({"k_r_sw": 3.0, "c_p_sw": 300.0, "R_e_hous": 0.2, "h_gap0": 90.0}).nominal()
    sensors = [m.node_index(x) for x in m.sensors.values()]
    full = Simulator(m).simulate(theta, inputs, dt, T0).T[:, sensors]
    approx = ReducedSimulator(m).simulate(theta, inputs, dt, T0)
    assert np.max(np.abs(full - approx.T[:, sensors])) < 0.01
    assert np.ptp(full) > 10.0
    P = LossLaws(m).power(Network(m).env(theta, inputs), approx.T, len(approx.T))
    assert np.max(np.abs(approx.P - P)) < 1e-9 * np.max(np.abs(P))


def test_the_path_is_chosen_where_it_applies(tiny_plus_model):
    small, large = chain_model(40), chain_model(48)
    assert type(simulator_for(small)) is Simulator  # below the node count: the exact dense path
    assert type(simulator_for(large, reduce_above=45)) is ReducedSimulator
    assert type(OnlineAdapter(chain_model(REDUCE_ABOVE + 1), AdapterConfig(), 1.0).sim) is ReducedSimulator
    assert type(OnlineAdapter(small, AdapterConfig(), 1.0).sim) is Simulator
    # a network with algebraic points, or a loss law not affine in temperature: the dense path
    assert Network(tiny_plus_model).n_points > len(tiny_plus_model.nodes)
    assert type(simulator_for(tiny_plus_model, reduce_above=1)) is Simulator
    with pytest.raises(ModelError, match="lumped network"):
        check_reducible(tiny_plus_model)
    doc = chain_document(20)
    doc["losses"][0]["power"] = "P_cu20 * (1 + 1e-5 * T.winding_1 ** 2)"
    with pytest.raises(ModelError, match=r"losses\[0\].*affine"):
        check_reducible(build_model(doc))


def test_scatter_matrices_match_the_dense_outer_products(tiny_plus_model):
    """The network's sparse scatter of edge conductances, built entry by entry, is the dense
    outer product of the incidence rows."""
    for m in (tiny_plus_model, chain_model(20)):
        net = Network(m)
        for a, b, S in ((net.inc, net.inc, net._scatter_L), (net.pinc, net.binc, net._scatter_K)):
            assert np.array_equal(S.toarray(), np.einsum("ea,eb->eab", a, b).reshape(len(a), -1))
