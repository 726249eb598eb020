"""The numeric network: Schur elimination of the algebraic points, steady-state energy balance,
the passivity check, and the exact derivatives of the eliminated system.

References: the same network with tiny capacities on the algebraic points (simulated as
dynamic nodes), and the Laplacian assembled directly from ``model.edges`` (``lptn_ref``).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from lptn_ref import Assembly, law_env, pm10kw_inputs, tiny_inputs, tiny_plus_raw

from thermal_edge.lptn import ModelError, Network, NotPassive, Simulator, discretise, initial_state, steady_state
from thermal_edge.lptn.expr import Num
from thermal_edge.lptn.loader import build_model

MID = ("/radial", "/circ", "/axial")


def lumped_raw():
    """A network of lumped nodes and points only (every conductance positive): three nodes,
    four algebraic points in chains and a star, a loss into a point, boundary edges on points,
    a speed-dependent conductance and a temperature-dependent loss."""
    return {
        "name": "lumped",
        "inputs": {"speed_rpm": {}, "i_rms": {}, "ambient_c": {}, "coolant_c": {}},
        "boundaries": {"ambient": "ambient_c", "coolant": "coolant_c"},
        "parameters": {
            "C1": {"value": 800, "min": 100, "max": 5000},
            "C2": {"value": 300, "min": 50, "max": 5000},
            "G": {"value": 4.0, "min": 0.5, "max": 50},
            "R_c": {"value": 0.3, "min": 0.05, "max": 5},
        },
        "nodes": [{"name": "n1", "capacity": "C1"}, {"name": "n2", "capacity": "C2"}, {"name": "n3", "capacity": 1500}],
        "points": ["p1", "p2", "p3", "p4"],
        "conductances": [
            {"between": ["n1", "p1"], "g": "G"},
            {"between": ["p1", "p2"], "g": "2 * G * (1 + speed_rpm/1500)"},
            {"between": ["p2", "n2"], "g": 6.0},
            {"between": ["p1", "p3"], "r": 0.4},
            {"between": ["p3", "n3"], "g": 3.0},
            {"between": ["p3", "coolant"], "r": "R_c"},
            {"between": ["n2", "p4"], "g": 2.0},
            {"between": ["p4", "ambient"], "g": "1 + speed_rpm/3000"},
            {"between": ["n3", "ambient"], "r": 2.0},
        ],
        "losses": [
            {"node": "n1", "power": "0.4 * i_rms**2 * (1 + 3.9e-3 * (T.n1 - 20))"},
            {"node": "p2", "power": "0.02 * speed_rpm"},
            {"node": "n3", "power": "5 + 0.001 * speed_rpm * (1 - 0.002 * (T.n3 - 40))"},
        ],
        "sensors": {"s1": {"node": "n1"}},
    }


def with_points_as_nodes(model, which, of="min"):
    """The same network with the algebraic points ``which`` turned into dynamic nodes of tiny
    capacity: 1e-6 of the smallest (or, with ``of="median"``, the median) node capacity."""
    theta = model.nominal()
    env = {p.name: float(v) for p, v in zip(model.parameters, theta)}
    caps = [float(np.asarray(c.compile()(env))) for c in model.capacities]
    eps = 1e-6 * (min(caps) if of == "min" else float(np.median(caps)))
    rest = tuple(p for p in model.points if p not in which)
    return dataclasses.replace(
        model,
        nodes=tuple(model.nodes) + tuple(which),
        capacities=tuple(model.capacities) + (Num(eps),) * len(which),
        points=rest,
    )


def check_elimination(model, inputs, dt, T0, which=None, of="min"):
    """Arc mid-points stay algebraic: joined to their node by the negative interior resistance
    R3, they make the full Laplacian indefinite, so with any capacity they would be unstable
    (only their elimination is passive). Every other point is made dynamic."""
    if which is None:
        which = tuple(p for p in model.points if not p.endswith(MID))
    assert which, "nothing to convert"
    full = with_points_as_nodes(model, which, of)
    theta = model.nominal()
    # the converted points start at their algebraic temperatures
    op = {c: np.asarray(inputs[c])[:1] for c in model.inputs}
    asm = Assembly(model, theta, {c: float(np.asarray(inputs[c])[0]) for c in model.inputs})
    Tall = Network(model).point_temperatures(theta, op, T0, asm.U, asm.losses(T0))
    names = list(model.nodes) + list(model.points)
    T0_full = np.concatenate([T0, [Tall[names.index(p)] for p in which]])
    T = Simulator(model, method="zoh").simulate(theta, inputs, dt, T0).T
    Tf = Simulator(full, method="zoh").simulate(theta, inputs, dt, T0_full).T
    n = len(model.nodes)
    err = np.abs(T - Tf[:, :n]).max()
    assert err <= 1e-3, f"Schur elimination vs tiny capacities: {err:.3g} K"
    assert np.abs(T[-1] - T[0]).max() > 1.0  # the run does something
    return err, len(which)


def test_elimination_lumped_network():
    m = build_model(lumped_raw(), fname="lumped.yaml")
    inputs = tiny_inputs(N=200, seed=21, hold=25)
    err, k = check_elimination(m, inputs, 2.0, np.array([40.0, 35.0, 30.0]), which=m.points)
    assert k == 4


def test_elimination_tiny_plus(tiny_plus_model):
    m = tiny_plus_model
    inputs = tiny_inputs(N=200, seed=22, hold=25)
    err, k = check_elimination(m, inputs, 5.0, np.array([45.0, 60.0, 35.0]))
    assert k == 2  # the declared point "gap" and the face point "yoke/r_out"


def test_arc_mid_points_cannot_carry_capacity(tiny_model):
    """Why the elimination tests keep the arc mid-points algebraic: with ALL points made dynamic
    (``points=()``), the negative interior resistances R3 make the network non-passive, and the
    simulator refuses it; the eliminated model of the same network is passive."""
    m = tiny_model
    full = with_points_as_nodes(m, m.points)
    assert full.points == ()
    L = Assembly(full, full.nominal(), {"speed_rpm": 0.0, "i_rms": 0.0, "ambient_c": 25.0}).L
    assert np.linalg.eigvalsh(L).min() < 0  # indefinite: some "conductances" are negative
    inputs = {k: v for k, v in tiny_inputs(N=5, seed=24).items() if k in m.inputs}
    with pytest.raises(NotPassive):
        Simulator(full, method="zoh").simulate(full.nominal(), inputs, 1.0, np.full(len(full.nodes), 25.0))
    Simulator(m, method="zoh").simulate(m.nominal(), inputs, 1.0, np.full(len(m.nodes), 25.0))


def test_elimination_pm10kw(pm10kw_model):
    m = pm10kw_model
    inputs, dt, _ = pm10kw_inputs(m, 900.0)
    T0 = np.full(len(m.nodes), float(inputs["ambient_c"][0]) if "ambient_c" in inputs else 25.0)
    # 1e-6 of the MEDIAN capacity: the smallest pm10kw node is itself a 0.056 J/K air node, and
    # 1e-6 of that (5.6e-8 J/K, a capacity ratio of 4e10) makes the full system so stiff that
    # any double-precision ZOH of it is off by 0.4-3 mK (measured with scipy's expm as well)
    err, k = check_elimination(m, inputs, dt, T0, of="median")
    print(f"pm10kw: {k} points made dynamic, max difference {err:.2e} K")


# ---------------------------------------------------------------------------------------------
# steady state: energy balance


def check_energy_balance(model, inputs):
    theta = model.nominal()
    T, P = steady_state(model, inputs)
    net = Network(model)
    U = np.array([float(inputs[c]) for c in model.boundaries.values()])
    op = {c: np.array([float(inputs[c])]) for c in model.inputs}
    Tall = net.point_temperatures(theta, op, T, U, P)
    names = list(model.nodes) + list(model.points)
    bidx = {b: i for i, b in enumerate(model.boundaries)}
    env = law_env(model, theta, inputs)
    out = 0.0
    for e in model.edges:
        if e.b in bidx:
            g = float(np.asarray(e.g.compile()(env)))
            out += g * (Tall[names.index(e.a)] - U[bidx[e.b]])
    total = float(np.sum(P))
    assert total > 1.0
    assert out == pytest.approx(total, rel=1e-9), (out, total)
    # every point in balance, and the losses are the loss laws at the steady temperatures
    asm = Assembly(model, theta, inputs)
    np.testing.assert_allclose(P, asm.losses(T), rtol=1e-12)
    res = asm.balance(Tall, P)
    assert np.abs(res).max() <= 1e-9 * total, np.abs(res).max()
    np.testing.assert_allclose(Tall, asm.solve_points(T, P), rtol=0, atol=1e-9)
    return T, total


def test_energy_balance_tiny(tiny_model):
    check_energy_balance(tiny_model, {"speed_rpm": 1500.0, "i_rms": 10.0, "ambient_c": 25.0})


def test_energy_balance_tiny_plus(tiny_plus_model):
    check_energy_balance(tiny_plus_model, {"speed_rpm": 2500.0, "i_rms": 8.0, "ambient_c": 22.0, "coolant_c": 35.0})


def test_energy_balance_lumped():
    m = build_model(lumped_raw(), fname="lumped.yaml")
    check_energy_balance(m, {"speed_rpm": 1200.0, "i_rms": 6.0, "ambient_c": 20.0, "coolant_c": 30.0})


def test_energy_balance_pm10kw(pm10kw_model):
    m = pm10kw_model
    point = {"speed_rpm": 900.0, "i_rms": 19.0, "torque_nm": 106.0, "ambient_c": 25.0, "coolant_c": 25.0}
    T, total = check_energy_balance(m, {c: point.get(c, 25.0) for c in m.inputs})
    print(f"pm10kw rated: losses {total:.1f} W, hottest node {T.max():.1f} degC")


def test_energy_balance_paderborn(paderborn_model):
    m = paderborn_model
    check_energy_balance(
        m, {"speed_rpm": 5500.0, "i_rms": 150.0, "torque_nm": 64.0, "ambient_c": 24.0, "coolant_c": 19.5}
    )


# ---------------------------------------------------------------------------------------------
# passivity


def _floating_raw(kind):
    raw = lumped_raw()
    if kind == "island":  # two nodes joined to each other only
        raw["nodes"] += [{"name": "f1", "capacity": 100}, {"name": "f2", "capacity": 200}]
        raw["conductances"].append({"between": ["f1", "f2"], "g": 3.0})
    elif kind == "isolated":  # a node with no conductance at all
        raw["nodes"].append({"name": "f1", "capacity": 100})
    return raw


@pytest.mark.parametrize("kind", ["island", "isolated"])
def test_node_not_tied_to_a_boundary_is_refused_by_the_loader(kind):
    """The file and the node: its heat has no way out (the network would not be passive)."""
    with pytest.raises(ModelError, match=r"^floating\.yaml: nodes\[\d+\]: node 'f1' is not connected to any boundary"):
        build_model(_floating_raw(kind), fname="floating.yaml")


def test_a_conductance_that_vanishes_is_not_passive():
    """A conductance law that is zero at the parameters cuts a node off although the file connects
    it: refused when the model is loaded, naming the key and the value. One that vanishes at an
    operating point only (the speed's law): the network refuses it when it is made there."""
    raw = lumped_raw()
    raw["parameters"]["g_off"] = {"value": 1.0, "min": 1e-9, "max": 2.0}
    raw["nodes"].append({"name": "f1", "capacity": 100})
    raw["conductances"].append({"between": ["f1", raw["nodes"][0]["name"]], "g": "g_off - 1"})
    k = len(raw["conductances"]) - 1
    with pytest.raises(ModelError, match=rf"^floating.yaml: conductances\[{k}\].g: must be positive, is 0 W/K at the "
                                         "nominal parameters$"):
        build_model(raw, fname="floating.yaml")
    raw["conductances"][-1]["g"] = "g_off * abs(speed_rpm) / 100 - g_off"  # zero at 100 rpm, negative below
    m = build_model(raw, fname="floating.yaml")
    with pytest.raises(NotPassive):
        discretise(Network(m).continuous(m.nominal(), {"speed_rpm": np.array([100.0])}), 1.0)
    with pytest.raises(ModelError, match=rf"conductances\[{k}\]: the conductance is -0.5 W/K at speed_rpm 50: a "
                                         "conductance must not be negative"):
        Network(m).continuous(m.nominal(), {"speed_rpm": np.array([300.0, 50.0])}, K=2)


@pytest.mark.parametrize("law, key, says", [
    ("-100", "nodes[{n}].capacity", "must be positive, is -100 J/K"),
    ("c_x - 150", "nodes[{n}].capacity", "must be positive, is -50 J/K at c_x = 100 (its min)"),
])
def test_a_capacity_that_is_not_positive_is_refused_at_load(law, key, says):
    """A capacity, constant or a law of the parameters, that is not positive at the nominal values or
    at any one parameter's bound (where the adaptation may take it): refused naming its key."""
    raw = lumped_raw()
    raw["parameters"]["c_x"] = {"value": 300.0, "min": 100.0, "max": 900.0}
    raw["nodes"].append({"name": "f1", "capacity": law})
    raw["conductances"].append({"between": ["f1", raw["nodes"][0]["name"]], "g": 2.0})
    with pytest.raises(ModelError) as err:
        build_model(raw, fname="m.yaml")
    assert str(err.value) == f"m.yaml: {key.format(n=len(raw['nodes']) - 1)}: {says}"


def test_connected_network_is_passive():
    m = build_model(lumped_raw(), fname="lumped.yaml")
    c = Network(m).continuous(m.nominal(), {"speed_rpm": np.array([0.0, 3000.0])}, K=2)
    for k in range(2):
        A = c.A[k]
        np.testing.assert_allclose(A, A.T, rtol=0, atol=1e-12 * np.abs(A).max())
        assert np.linalg.eigvalsh(A).max() < 0
    discretise(c, 1.0)  # no error


# ---------------------------------------------------------------------------------------------
# the eliminated system and its derivatives


@pytest.mark.parametrize("which", ["tiny_plus", "lumped", "pm10kw"])
def test_continuous_system_and_derivatives(which, request):
    if which == "tiny_plus":
        m = build_model(tiny_plus_raw())
    elif which == "lumped":
        m = build_model(lumped_raw())
    else:
        m = request.getfixturevalue("pm10kw_model")
    point = {"speed_rpm": 700.0, "i_rms": 9.0, "torque_nm": 50.0, "ambient_c": 25.0, "coolant_c": 30.0}
    scal = {c: point.get(c, 25.0) for c in m.inputs}
    theta = m.nominal()
    net = Network(m)
    wrt = list(range(len(theta)))
    c = net.continuous(theta, {k: np.array([v]) for k, v in scal.items()}, wrt=wrt)
    asm = Assembly(m, theta, scal)
    A, W = asm.reduced()
    np.testing.assert_allclose(c.A[0], A, rtol=0, atol=1e-10 * np.abs(A).max())
    np.testing.assert_allclose(c.W[0], W, rtol=0, atol=1e-10 * np.abs(W).max())
    np.testing.assert_allclose(c.c, asm.c, rtol=1e-13)
    for j in wrt:
        h = 1e-4 * theta[j]
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        ap, bp = Assembly(m, tp, scal), Assembly(m, tm, scal)
        (Ap, Wp), (Am, Wm) = ap.reduced(), bp.reduced()
        dA, dW, dc = (Ap - Am) / (2 * h), (Wp - Wm) / (2 * h), (ap.c - bp.c) / (2 * h)
        name = m.parameter_names[j]
        # tolerance: 1e-5 of the largest entry plus the round-off of the difference quotient
        fp = 8 * np.finfo(float).eps / h
        np.testing.assert_allclose(c.dA[0, j], dA, rtol=0, atol=1e-5 * np.abs(dA).max() + fp * np.abs(A).max(), err_msg=name)
        np.testing.assert_allclose(c.dW[0, j], dW, rtol=0, atol=1e-5 * np.abs(dW).max() + fp * np.abs(W).max(), err_msg=name)
        np.testing.assert_allclose(c.dc[j], dc, rtol=0, atol=1e-5 * np.abs(dc).max() + fp * np.abs(asm.c).max(), err_msg=name)


def test_initial_state_keeps_readings_and_balances_the_rest():
    m = build_model(lumped_raw(), fname="lumped.yaml")
    inputs = {"speed_rpm": 800.0, "i_rms": 5.0, "ambient_c": 21.0, "coolant_c": 28.0}
    T = initial_state(m, inputs, {"s1": 55.0})
    assert T[0] == 55.0
    asm = Assembly(m, m.nominal(), inputs)
    A, W = asm.reduced()
    nb = len(m.boundaries)
    res = A @ T + W[:, :nb] @ asm.U  # loss-free balance of the unmeasured nodes
    np.testing.assert_allclose(res[1:], 0.0, atol=1e-9)


@pytest.mark.parametrize("cols", [1, 3])
def test_operating_points_grouped_as_numpy_unique_rows(cols):
    """The simulation's grouping of samples into operating points (a lexsort) gives what
    ``np.unique(axis=0)`` gives: the same distinct rows in the same order, the same indices."""
    from thermal_edge.lptn.simulate import unique_rows

    rng = np.random.default_rng(7)
    keys = rng.integers(0, 4, size=(500, cols)).astype(float) * 250.0  # many ties, as a drive cycle has
    keys[::7, 0] = -0.0  # signed zeros are the same operating point
    uniq, inv = unique_rows(keys)
    ref, ref_inv = np.unique(keys, axis=0, return_inverse=True)
    np.testing.assert_array_equal(uniq, ref)
    np.testing.assert_array_equal(inv, np.asarray(ref_inv).reshape(-1))
    np.testing.assert_array_equal(uniq[inv], keys)


@pytest.mark.parametrize("change, says", [
    (lambda r: r["conductances"][2].update(g=-8.0), "conductances[2].g: must be positive, is -8 W/K"),
    (lambda r: r["conductances"][3].update(r=0.0), "conductances[3].r: must be positive, is 0 K/W"),
    (lambda r: r["conductances"][5].update(r="R_c - 0.1"),
     "conductances[5].r: must be positive, is -0.05 K/W at R_c = 0.05 (its min)"),
    # the units a model's values are in: SI; a prefixed one is named with the value converted
    (lambda r: r["parameters"]["C1"].update(unit="kJ/K", value=0.8, min=0.1, max=5),
     "parameters.C1.unit: 'kJ/K' is not SI: give the values in J/K (0.8 kJ/K = 800 J/K)"),
    # a resistance given as a conductance, a conductance as a capacity
    (lambda r: (r["parameters"]["R_c"].update(unit="K/W"), r["conductances"][5].pop("r"),
                r["conductances"][5].update(g="R_c")),
     "conductances[5].g: parameter R_c is in K/W, a resistance: give it as r: R_c (g is a conductance, in W/K)"),
    (lambda r: (r["parameters"]["G"].update(unit="W/K"), r["nodes"][0].update(capacity="G")),
     "nodes[0].capacity: parameter G is in W/K, a conductance (capacity is a capacity, in J/K)"),
    # a boundary fed by an input that is no temperature (by its role, or by its unit)
    (lambda r: (r["inputs"].update(i_rms={"role": "current", "unit": "A"}), r["boundaries"].update(ambient="i_rms")),
     "boundaries.ambient: input 'i_rms' is the current (A), not a temperature"),
    (lambda r: (r["inputs"].update(i_rms={"unit": "A"}), r["boundaries"].update(ambient="i_rms")),
     "boundaries.ambient: input 'i_rms' is in 'A', not a temperature (degC)"),
    # adaptable, and read by no law: nothing can be learned about it
    (lambda r: r["parameters"].update(K_unused={"value": 1.0, "min": 0.5, "max": 2.0, "adaptable": True}),
     "parameters.K_unused.adaptable: no capacity, conductance or loss reads this parameter: nothing can be "
     "learned about it"),
])
def test_a_model_whose_values_cannot_be_right_is_refused_at_load_naming_the_key(change, says):
    raw = lumped_raw()
    change(raw)
    with pytest.raises(ModelError) as err:
        build_model(raw, fname="m.yaml")
    assert str(err.value) == f"m.yaml: {says}"
