"""The paper's 10 kW machine model file (config/machines/pm10kw.yaml) and its drive cycles.

The steady state is solved here from first principles, independently of
``thermal_edge.lptn.network`` / ``steady``: every edge law of the flattened model is evaluated,
the conductance Laplacian over all nodes and algebraic points is assembled, and

    L T = g_U U + P(T)        (all nodes and points; P affine in T through the copper law)

is solved by fixed-point iteration on the temperature-dependent losses. The package's own
``Network`` and ``steady_state`` are then checked against it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from thermal_edge.lptn import load_model

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "config" / "machines" / "pm10kw.yaml"
CYCLES = REPO / "config" / "cycles"

RATED_TORQUE = 10_000 / (900 * 2 * np.pi / 60)  # 106.1 Nm

# Table 1 of the paper, in node order 1..39
TABLE1 = (
    [f"housing_{i}" for i in range(1, 9)]
    + [f"yoke_{i}" for i in range(1, 5)]
    + [f"tooth_{i}" for i in range(1, 5)]
    + ["end_winding_1", "end_winding_2", "slot_winding_1", "slot_winding_2"]
    + ["slot_wedge_1", "slot_wedge_2", "magnet_1", "magnet_2"]
    + [f"rotor_iron_{i}" for i in range(1, 5)]
    + ["rotor_retaining_plate_1", "rotor_retaining_plate_2", "shaft_1", "shaft_2", "air_gap"]
    + ["stator_retaining_plate_1", "stator_retaining_plate_2", "end_space_1", "end_space_2"]
    + ["end_cap_1", "end_cap_2"]
)

ADAPTABLE = {
    "k_r_sw", "k_c_sw", "k_a_sw", "c_p_sw",
    "k_r_ew", "k_c_ew", "k_a_ew", "c_p_ew",
    "r_ins_sw", "r_ins_ew",
    "R_e_hous", "R_e_cap", "c_p_hous", "r_c_hous",
}


@pytest.fixture(scope="module")
def model():
    return load_model(MODEL)


def rated_inputs(model, ambient=25.0, speed=900.0, torque=RATED_TORQUE):
    kt = model.drive["kt_nm_per_arms"]
    return {"speed_rpm": speed, "i_rms": abs(torque) / kt, "torque_nm": torque, "ambient_c": ambient}


# ------------------------------------------------------------------------------------------
# independent first-principles solver
def _env(model, theta, inputs):
    env = dict(zip(model.parameter_names, (float(v) for v in theta)))
    env.update({k: float(v) for k, v in inputs.items()})
    for k, law in model.derived.items():  # declaration order: later ones may use earlier ones
        env[k] = float(law.compile()(env))
    return env


def _laplacian(model, theta, inputs):
    """Laplacian over nodes + points and the boundary injection matrix, from the edge laws."""
    pts = list(model.nodes) + list(model.points)
    idx = {p: i for i, p in enumerate(pts)}
    bnames = list(model.boundaries)
    n = len(pts)
    L = np.zeros((n, n))
    GU = np.zeros((n, len(bnames)))
    env = _env(model, theta, inputs)
    for e in model.edges:
        g = float(e.g.compile()(env))
        a = idx[e.a]
        if e.b in bnames:
            L[a, a] += g
            GU[a, bnames.index(e.b)] += g
        else:
            b = idx[e.b]
            L[a, a] += g
            L[b, b] += g
            L[a, b] -= g
            L[b, a] -= g
    U = np.array([float(inputs[c]) for c in model.boundaries.values()])
    return L, GU, U, idx, env


def independent_steady_state(model, inputs, theta=None):
    """Steady temperatures of all nodes (°C) and total losses (W), fixed point on P(T)."""
    theta = model.nominal() if theta is None else theta
    L, GU, U, idx, env = _laplacian(model, theta, inputs)
    laws = [(idx[loss.point], loss.power.compile()) for loss in model.losses]
    n = len(model.nodes)
    T = np.full(L.shape[0], float(np.mean(U)))
    for _ in range(500):
        e = dict(env)
        e.update({f"T.{node}": T[i] for i, node in enumerate(model.nodes)})
        P = np.zeros(L.shape[0])
        for i, f in laws:
            P[i] += float(f(e))
        T_new = np.linalg.solve(L, GU @ U + P)
        if np.max(np.abs(T_new - T)) < 1e-10:
            return T_new[:n], P.sum()
        T = T_new
    raise AssertionError("steady state did not converge")


def independent_system(model, inputs, theta=None):
    """Reduced continuous system C dT/dt = A T + B U (points eliminated) and capacities."""
    theta = model.nominal() if theta is None else theta
    L, GU, U, idx, env = _laplacian(model, theta, inputs)
    n = len(model.nodes)
    D, Q = slice(0, n), slice(n, None)
    X = np.linalg.solve(L[Q, Q], L[Q, D])
    A = -(L[D, D] - L[D, Q] @ X)
    B = GU[D] - X.T @ GU[Q]
    c = np.array([float(cap.compile()(env)) for cap in model.capacities])
    return A, B, c


# ------------------------------------------------------------------------------------------
def test_node_set_follows_table_1(model):
    assert len(model.nodes) == 39
    assert list(model.nodes) == TABLE1
    caps = np.array([float(c.compile()(_env(model, model.nominal(), rated_inputs(model)))) for c in model.capacities])
    assert np.all(caps > 0)


def test_fourteen_adaptable_parameters(model):
    assert set(model.adaptable) == ADAPTABLE
    assert len(model.adaptable) == 14
    p = {q.name: q for q in model.parameters}
    assert p["R_e_hous"].value == pytest.approx(9.1)
    assert p["R_e_hous"].unit == "K/W"
    for q in model.parameters:
        assert 0 < q.lower <= q.value <= q.upper, q.name
    # Table 4 of the paper stays inside the bounds
    for name, delta in {"k_r_sw": 4.0, "k_c_sw": 1.5, "c_p_sw": -50.0, "R_e_hous": -4.0}.items():
        v = p[name].value + delta
        assert p[name].lower <= v <= p[name].upper, name
    # non-adaptable parameters exist too (air gap, rotor side)
    assert {"h_gap0", "h_gap1", "r_bearing"} <= set(model.parameter_names) - set(model.adaptable)


def test_sensors_limits_drive(model):
    assert set(model.sensors) == {"slot_winding", "end_winding", "housing"}
    assert model.sensors["slot_winding"].startswith("slot_winding_")
    assert model.sensors["end_winding"].startswith("end_winding_")
    assert model.sensors["housing"].startswith("housing_")
    limits = {lim.name: lim for lim in model.limits}
    assert limits["hot_spot"].node.startswith("end_winding_")
    assert (limits["hot_spot"].warn_c, limits["hot_spot"].max_c) == (140.0, 155.0)
    assert limits["magnet"].node.startswith("magnet_")
    assert model.boundaries == {"ambient": "ambient_c"}
    assert {"speed_rpm", "i_rms", "torque_nm", "ambient_c"} <= set(model.inputs)
    assert model.discretisation.method == "zoh"
    kt = model.drive["kt_nm_per_arms"]
    assert 3.0 < kt < 10.0 and 10 < RATED_TORQUE / kt < 40


@pytest.mark.parametrize("speed", [0.0, 900.0, 1200.0])
def test_conductances_positive_at_any_speed(model, speed):
    env = _env(model, model.nominal(), rated_inputs(model, speed=speed))
    for e in model.edges:
        g = float(e.g.compile()(env))
        if "interior" in e.key:  # T-model R3 is negative by construction
            assert g < 0, e.key
        else:
            assert g > 0 and np.isfinite(g), e.key


def test_rated_steady_state_hot_spot(model):
    T, P = independent_steady_state(model, rated_inputs(model))
    hot = {lim.name: lim.node for lim in model.limits}
    i_hot = model.nodes.index(hot["hot_spot"])
    ew = [model.nodes.index(n) for n in ("end_winding_1", "end_winding_2")]
    # the limit sits on the hotter end winding and the winding is the hottest part
    assert T[i_hot] == pytest.approx(max(T[ew]))
    assert T[i_hot] == pytest.approx(T.max(), abs=1e-9)
    assert 100.0 <= T[i_hot] <= 130.0
    # magnets below their warning level, housing a plausible frame temperature
    assert T[model.nodes.index(hot["magnet"])] < 100.0
    assert 60.0 < T[model.nodes.index(model.sensors["housing"])] < 100.0
    # losses: a 10 kW machine at 93-96 % efficiency
    assert 400.0 < P < 750.0


def test_package_agrees_with_independent_solution(model):
    from thermal_edge.lptn import Network, steady_state

    inputs = rated_inputs(model)
    T_ref, _ = independent_steady_state(model, inputs)
    T_pkg, _ = steady_state(model, inputs)
    np.testing.assert_allclose(T_pkg, T_ref, atol=1e-6)
    A, B, c = independent_system(model, inputs)
    cont = Network(model).continuous(model.nominal(), {k: np.array([v]) for k, v in inputs.items()})
    np.testing.assert_allclose(cont.A[0], A, rtol=1e-9, atol=1e-9 * np.abs(A).max())
    np.testing.assert_allclose(cont.W[0][:, : B.shape[1]], B, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cont.c, c, rtol=1e-12)


def test_time_constant_and_three_hour_heat_up(model):
    inputs = rated_inputs(model)
    A, B, c = independent_system(model, inputs)
    lam = np.linalg.eigvals(A / c[:, None]).real
    assert np.all(lam < 0)
    tau_min = -1.0 / lam.max() / 60.0
    assert 30.0 < tau_min < 120.0  # tens of minutes
    # 3 h at rated from cold (ZOH, 60 s steps, losses held per step): close to steady state
    T_ss, _ = independent_steady_state(model, inputs)
    L, GU, U, idx, env = _laplacian(model, model.nominal(), inputs)
    n = len(model.nodes)
    X = np.linalg.solve(L[n:, n:], L[n:, :n])
    laws = [(idx[loss.point], loss.power.compile()) for loss in model.losses]
    dt = 60.0
    s = np.sqrt(c)
    lam_s, Q = np.linalg.eigh(A / np.outer(s, s))  # C^-1 A is similar to C^-1/2 A C^-1/2
    Phi = (Q * np.exp(lam_s * dt)) @ Q.T / s[:, None] * s[None, :]
    G = (Phi - np.eye(n)) @ np.linalg.inv(A)  # ZOH: T+ = Phi T + (Phi - I) A^-1 (B U + P)
    T = np.full(n, 25.0)
    i_hot = model.nodes.index(next(lim.node for lim in model.limits if lim.name == "hot_spot"))
    for _ in range(int(3 * 3600 / dt)):
        e = dict(env)
        e.update({f"T.{node}": T[i] for i, node in enumerate(model.nodes)})
        P = np.zeros(L.shape[0])
        for i, f in laws:
            P[i] += float(f(e))
        P_red = P[:n] - X.T @ P[n:]  # losses injected at points reach the nodes through X^T
        T = Phi @ T + G @ (B @ U + P_red)
    rise = (T[i_hot] - 25.0) / (T_ss[i_hot] - 25.0)
    assert 0.85 < rise < 1.0


# ------------------------------------------------------------------------------------------
CYCLE_NAMES = ["paper_600rpm_70nm", "rated_heat_cool", "varied_drive", "heldout_drive", "overload"]


def _cycle(name):
    return yaml.safe_load((CYCLES / f"{name}.yaml").read_text())


@pytest.mark.parametrize("name", CYCLE_NAMES)
def test_cycle_files(name):
    d = _cycle(name)
    assert d["name"] == name
    assert d["dt_s"] > 0
    segs = d["segments"]
    total = sum(s["duration_s"] for s in segs) * d.get("repeat", 1)
    assert total == pytest.approx(3 * 3600)
    for s in segs:
        assert set(s) <= {"duration_s", "speed_rpm", "torque_nm", "ambient_c", "coolant_c", "ramp_s"}
        assert 0 <= s["speed_rpm"] <= 1200 and 0 <= s["torque_nm"] <= 160
        assert 0 <= s.get("ramp_s", 0) < s["duration_s"]
        assert 15 <= s.get("ambient_c", d.get("ambient_c", 25.0)) <= 35


def test_cycle_contents():
    paper = _cycle("paper_600rpm_70nm")["segments"]
    assert [(s["speed_rpm"], s["torque_nm"]) for s in paper] == [(600, 70)]
    rated = _cycle("rated_heat_cool")["segments"]
    assert (rated[0]["speed_rpm"], rated[0]["torque_nm"]) == (900, 106)
    assert (rated[-1]["speed_rpm"], rated[-1]["torque_nm"]) == (0, 0)
    varied, held = _cycle("varied_drive")["segments"], _cycle("heldout_drive")["segments"]
    assert varied != held
    for segs in (varied, held):
        assert len(segs) >= 10
        assert max(s["torque_nm"] for s in segs) > 1.2 * RATED_TORQUE  # some overload
        assert any(s["speed_rpm"] == 0 for s in segs) and any("ramp_s" in s for s in segs)
        assert len({s["speed_rpm"] for s in segs}) <= 8  # few distinct operating points
    amb = {s.get("ambient_c", 25.0) for s in varied}
    assert min(amb) <= 20 and max(amb) >= 30
    over = _cycle("overload")["segments"]
    long_overload = sum(s["duration_s"] for s in over if s["torque_nm"] >= 1.3 * RATED_TORQUE)
    assert long_overload >= 2 * 3600


def test_overload_cycle_exceeds_limit_open_loop(model):
    """Open loop, the overload cycle's steady state at its heaviest segment is far above 155 °C
    and the rated one is not: the cycle really needs derating."""
    heavy = max(_cycle("overload")["segments"], key=lambda s: s["torque_nm"])
    T, _ = independent_steady_state(model, rated_inputs(model, speed=heavy["speed_rpm"], torque=heavy["torque_nm"]))
    i_hot = model.nodes.index(next(lim.node for lim in model.limits if lim.name == "hot_spot"))
    assert T[i_hot] > 155.0
