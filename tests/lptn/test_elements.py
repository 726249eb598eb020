"""Arc elements (T-model): exact mean temperature under uniform heat generation.

A single arc element with uniform generation ``q`` (W) and two opposite faces held at fixed
temperatures must, at steady state, have its node at the *area-mean* temperature of the exact
1-D solution in that direction. The exact solutions are derived here, and their means taken by
numerical quadrature (``scipy.integrate.quad``/``dblquad``) of the analytic T(r), T(x), T(φ).
The faces are tied to the boundaries through a negligible extra resistance (1e-9 K/W).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from lptn_ref import Assembly
from scipy.integrate import dblquad, quad

from thermal_edge.lptn import steady_state
from thermal_edge.lptn.expr import evaluate_const
from thermal_edge.lptn.loader import build_model

T_A, T_B = 40.0, 25.0  # the two held face temperatures, °C
TINY_R = 1e-9
# the 1e9 W/K ties next to ~10 W/K element conductances cost about 1e8·eps of relative accuracy in
# the eliminated network; a wrong T-model formula is off by 1e-3 or more
CONDITIONING = 1e-7

GEOMETRIES = [
    # r1, r2, theta, length, k, count
    (0.08, 0.10, 3.0, 0.10, 2.0, 1),
    (0.10, 0.12, 6.28, 0.10, 28.0, 1),
    (0.02, 0.10, 0.5236, 0.046, 1.5, 12),
    (0.050, 0.051, 1.0, 0.2, 0.8, 3),
    (0.03, 0.09, 2.0, 0.05, 380.0, 2),
]
IDS = [f"r1={g[0]}-r2={g[1]}-n={g[5]}" for g in GEOMETRIES]
FACE_PAIRS = {"radial": ("r_out", "r_in"), "axial": ("a_front", "a_back"), "circ": ("c_pos", "c_neg")}


def one_arc(direction: str, r1, r2, theta, length, k, count, rho=8000.0, c_p=450.0):
    """An arc whose two faces in ``direction`` are tied to boundaries ``b1`` (R1 face) and ``b2``
    (R2 face); only the conductivity of that direction matters (the others are adiabatic)."""
    f1, f2 = FACE_PAIRS[direction]
    raw = {
        "name": f"one_{direction}",
        "inputs": {"t1": {}, "t2": {}, "q": {}},
        "boundaries": {"b1": "t1", "b2": "t2"},
        "parameters": {
            "k": {"value": k, "min": k / 10, "max": k * 10},
            "rho": {"value": rho, "min": 1, "max": 1e5},
            "c_p": {"value": c_p, "min": 1, "max": 1e4},
        },
        "materials": {"m": {"k_r": "k", "k_a": "k", "k_c": "k", "rho": "rho", "c_p": "c_p"}},
        "arcs": [{"name": "e", "r1": r1, "r2": r2, "theta": theta, "length": length, "count": count, "material": "m"}],
        "conductances": [
            {"between": [f"e.{f1}", "b1"], "r": TINY_R},
            {"between": [f"e.{f2}", "b2"], "r": TINY_R},
        ],
        "losses": [{"node": "e", "power": "q"}],
        "sensors": {"e": {"node": "e"}},
    }
    return build_model(raw, fname=f"one_{direction}.yaml")


def node_temperature(model, q):
    """Steady node temperature, by the package's steady_state and by an independent solve of
    the full nodal balance (Laplacian assembled from the model's edges); both must agree."""
    inputs = {"t1": T_A, "t2": T_B, "q": q}
    T, P = steady_state(model, inputs)
    asm = Assembly(model, model.nominal(), inputs)
    # full system: every point (node and algebraic) in balance, node loss q
    inj = asm.point_injection(np.array([q]))
    Tall = np.linalg.solve(asm.L, inj + asm.KU @ asm.U)
    assert T[0] == pytest.approx(Tall[0], rel=1e-10, abs=1e-9)
    return Tall[0], asm, Tall


# ---------------------------------------------------------------------------------------------
# exact 1-D solutions


def radial_mean(r1, r2, k, qv, T_out, T_in):
    """1-D radial: (1/r)(r k T')' = -q'''; T(r) = -q''' r²/(4k) + C1 ln r + C2."""
    p = lambda r: -qv * r * r / (4 * k)  # noqa: E731
    C1 = ((T_out - p(r2)) - (T_in - p(r1))) / math.log(r2 / r1)
    C2 = T_in - p(r1) - C1 * math.log(r1)
    T = lambda r: p(r) + C1 * math.log(r) + C2  # noqa: E731
    assert T(r1) == pytest.approx(T_in) and T(r2) == pytest.approx(T_out)
    num = quad(lambda r: T(r) * r, r1, r2, epsabs=0, epsrel=1e-13)[0]
    den = quad(lambda r: r, r1, r2, epsabs=0, epsrel=1e-13)[0]
    return num / den, T, C1


def axial_mean(L, k, qv, T_front, T_back):
    """1-D slab: k T'' = -q'''; T(x) = -q''' x²/(2k) + C1 x + C2 with T(0)=front, T(L)=back."""
    C2 = T_front
    C1 = (T_back - T_front + qv * L * L / (2 * k)) / L
    T = lambda x: -qv * x * x / (2 * k) + C1 * x + C2  # noqa: E731
    assert T(L) == pytest.approx(T_back)
    return quad(T, 0, L, epsabs=0, epsrel=1e-13)[0] / L


def circ_mean(r1, r2, theta, k, qv, T_pos, T_neg):
    """1-D circumferential (heat flows only along φ, each ring r independently):
    (k/r²) ∂²T/∂φ² = -q'''; T(r, φ) = T_neg + (T_pos - T_neg) φ/θ + q''' r² φ (θ - φ)/(2k)."""
    T = lambda phi, r: T_neg + (T_pos - T_neg) * phi / theta + qv * r * r * phi * (theta - phi) / (2 * k)  # noqa: E731
    num = dblquad(lambda phi, r: T(phi, r) * r, r1, r2, 0, theta, epsabs=0, epsrel=1e-12)[0]
    return num / (theta * (r2 * r2 - r1 * r1) / 2)


def volume(r1, r2, theta, length, count):
    return count * theta / 2 * length * (r2 * r2 - r1 * r1)


def tol(q):
    """The 1e-9 K/W ties to the boundaries shift the faces by at most q·1e-9 K."""
    return 2 * abs(q) * TINY_R + 1e-9




# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("geom", GEOMETRIES, ids=IDS)
@pytest.mark.parametrize("q", [0.0, 35.0, 400.0])
def test_radial_T_model_gives_exact_mean_temperature(geom, q):
    r1, r2, theta, length, k, count = geom
    model = one_arc("radial", *geom)
    qv = q / volume(r1, r2, theta, length, count)
    exact, _, _ = radial_mean(r1, r2, k, qv, T_out=T_A, T_in=T_B)
    got, _, _ = node_temperature(model, q)
    assert got == pytest.approx(exact, rel=CONDITIONING, abs=tol(q))


@pytest.mark.parametrize("geom", GEOMETRIES, ids=IDS)
def test_radial_face_heat_flows_are_exact(geom):
    """With generation the heat leaving through each face equals the exact flux
    -k θ L r T'(r) at that face (a property of the correct T-model)."""
    r1, r2, theta, length, k, count = geom
    model = one_arc("radial", *geom)
    q = 150.0
    qv = q / volume(r1, r2, theta, length, count)
    _, T, C1 = radial_mean(r1, r2, k, qv, T_out=T_A, T_in=T_B)
    dT = lambda r: -qv * r / (2 * k) + C1 / r  # noqa: E731
    out_exact = -k * count * theta * length * r2 * dT(r2)  # W leaving through the outer face
    in_exact = k * count * theta * length * r1 * dT(r1)  # W leaving through the inner face
    assert out_exact + in_exact == pytest.approx(q, rel=1e-12)
    _, asm, Tall = node_temperature(model, q)
    flows = {}
    for e, g in zip(model.edges, asm.edge_g):
        if e.b in model.boundaries:
            flows[e.b] = g * (Tall[asm.names.index(e.a)] - asm.U[list(model.boundaries).index(e.b)])
    assert flows["b1"] + flows["b2"] == pytest.approx(q, rel=1e-10, abs=1e-9)  # energy is conserved
    assert flows["b1"] == pytest.approx(out_exact, rel=10 * CONDITIONING, abs=1e-7)
    assert flows["b2"] == pytest.approx(in_exact, rel=10 * CONDITIONING, abs=1e-7)


@pytest.mark.parametrize("geom", GEOMETRIES, ids=IDS)
def test_radial_T_resistance_values_are_exact_up_to_face_labels(geom):
    """The three radial resistances, derived here from the exact solution: total conduction
    resistance ln(r2/r1)/(θ L k); the node (mean temperature, q = 0) divides it into R_in and
    R_out; the interior R3 follows from the mean-temperature rise under generation. The
    package's {R1, R2} are the right two values (whatever face they are attached to) and R3 is
    right."""
    from thermal_edge.lptn.elements import arc_resistances
    from thermal_edge.lptn.expr import Num

    r1, r2, theta, length, k, count = geom
    R_tot = math.log(r2 / r1) / (theta * length * k * count)
    mean0, _, _ = radial_mean(r1, r2, k, 0.0, T_out=1.0, T_in=0.0)
    R_in, R_out = mean0 * R_tot, (1 - mean0) * R_tot  # node at the mean: divider R_in : R_out
    q = 1.0
    mean_q, _, _ = radial_mean(r1, r2, k, q / volume(r1, r2, theta, length, count), T_out=0.0, T_in=0.0)
    R3 = mean_q / q - R_in * R_out / R_tot
    R = [evaluate_const(x) for x in arc_resistances(r1, r2, theta, length, Num(k), Num(k), Num(k), count)["radial"]]
    assert sorted(R[:2]) == pytest.approx(sorted([R_in, R_out]), rel=1e-9)
    assert R[2] == pytest.approx(R3, rel=1e-7)
    assert R[2] < 0


@pytest.mark.parametrize("geom", GEOMETRIES, ids=IDS)
@pytest.mark.parametrize("q", [0.0, 35.0, 400.0])
def test_axial_T_model_gives_exact_mean_temperature(geom, q):
    r1, r2, theta, length, k, count = geom
    model = one_arc("axial", *geom)
    A = volume(r1, r2, theta, length, count) / length
    qv = q / (A * length)
    exact = axial_mean(length, k, qv, T_front=T_A, T_back=T_B)
    # the closed form of the same mean: (T1+T2)/2 + q L / (12 k A)
    assert exact == pytest.approx((T_A + T_B) / 2 + q * length / (12 * k * A), rel=1e-12)
    got, _, _ = node_temperature(model, q)
    assert got == pytest.approx(exact, rel=CONDITIONING, abs=tol(q))


@pytest.mark.parametrize("geom", GEOMETRIES, ids=IDS)
def test_circumferential_conduction_without_generation_is_exact(geom):
    r1, r2, theta, length, k, count = geom
    model = one_arc("circ", *geom)
    got, asm, Tall = node_temperature(model, 0.0)
    assert got == pytest.approx(circ_mean(r1, r2, theta, k, 0.0, T_A, T_B), rel=1e-10)
    g_exact = count * length * k * math.log(r2 / r1) / theta  # W/K through the element
    flow = [g * (Tall[asm.names.index(e.a)] - asm.U[0]) for e, g in zip(model.edges, asm.edge_g) if e.b == "b1"]
    assert flow[0] == pytest.approx(g_exact * (T_B - T_A), rel=1e-7)  # W out of the element into b1


@pytest.mark.parametrize("geom", GEOMETRIES, ids=IDS)
@pytest.mark.parametrize("q", [35.0, 400.0])
def test_circumferential_T_model_gives_exact_mean_temperature(geom, q):
    r1, r2, theta, length, k, count = geom
    model = one_arc("circ", *geom)
    qv = q / volume(r1, r2, theta, length, count)
    exact = circ_mean(r1, r2, theta, k, qv, T_pos=T_A, T_neg=T_B)
    got, _, _ = node_temperature(model, q)
    assert got == pytest.approx(exact, rel=CONDITIONING, abs=1e-7)


def test_circumferential_T_model_is_right_for_a_thin_arc():
    """For a thin arc (r2/r1 → 1) the exact value tends to the flat-slab one: the node's rise
    above its faces is right for a thin arc too."""
    geom = (0.050, 0.0501, 1.0, 0.2, 0.8, 3)
    r1, r2, theta, length, k, count = geom
    q = 5.0
    qv = q / volume(r1, r2, theta, length, count)
    exact = circ_mean(r1, r2, theta, k, qv, T_pos=T_A, T_neg=T_B)
    got, _, _ = node_temperature(one_arc("circ", *geom), q)
    rise = exact - (T_A + T_B) / 2
    assert rise > 1.0
    assert got - (T_A + T_B) / 2 == pytest.approx(rise, rel=1e-5)


def test_circumferential_R3_against_the_exact_formula():
    """The exact R3 (derived in the circumferential mean test above, and printed in the paper's
    Table 2): R3 = θ/(12 L k) ((r2²+r1²)/(r2²−r1²) − 3/ln(r2/r1))."""
    from thermal_edge.lptn.elements import arc_resistances
    from thermal_edge.lptn.expr import Num

    r1, r2, theta, length, k = 0.08, 0.10, 3.0, 0.10, 2.0
    R1, R2, R3 = (evaluate_const(x) for x in arc_resistances(r1, r2, theta, length, Num(k), Num(k), Num(k))["circ"])
    ln = math.log(r2 / r1)
    assert R1 == pytest.approx(theta / (2 * length * k * ln), rel=1e-13)
    assert R2 == pytest.approx(R1, rel=1e-13)
    exact_R3 = theta / (12 * length * k) * ((r2**2 + r1**2) / (r2**2 - r1**2) - 3 / ln)
    # node rise above the face mean under generation q: q (R1/2 + R3); with the exact R3 this is
    # the exact mean rise q''' θ² (r1² + r2²) / (24 k)
    qv = 1.0 / volume(r1, r2, theta, length, 1)
    assert R1 / 2 + exact_R3 == pytest.approx(qv * theta**2 * (r1**2 + r2**2) / (24 * k), rel=1e-12)
    assert R3 == pytest.approx(exact_R3, rel=1e-12)  # fails: node rise is 1.6 % low for r2/r1 = 1.25


@pytest.mark.parametrize("geom", GEOMETRIES, ids=IDS)
def test_capacity(geom):
    r1, r2, theta, length, k, count = geom
    rho, c_p = 7650.0, 460.0
    model = one_arc("radial", *geom, rho=rho, c_p=c_p)
    cap = float(np.asarray(model.capacities[0].compile()({"k": k, "rho": rho, "c_p": c_p})))
    assert cap == pytest.approx(c_p * rho * theta / 2 * length * (r2**2 - r1**2) * count, rel=1e-13)
    # and the capacity law follows its parameters exactly (derivative wrt rho is c/rho)
    d = float(np.asarray(model.capacities[0].diff("rho").compile()({"k": k, "rho": rho, "c_p": c_p})))
    assert d == pytest.approx(cap / rho, rel=1e-13)


def test_count_is_elements_in_parallel():
    """``count`` identical elements in parallel: resistances divided by ``count`` and capacity
    multiplied by it. Three axial elements of angle θ/3 are the same as one element of angle θ
    (axial conductances and capacity scale with θ), so their node temperatures agree."""
    one = one_arc("axial", 0.05, 0.08, 0.3, 0.1, 2.0, 1)
    many = one_arc("axial", 0.05, 0.08, 0.1, 0.1, 2.0, 3)
    t1, _, _ = node_temperature(one, 60.0)
    t3, _, _ = node_temperature(many, 60.0)
    assert t1 == pytest.approx(t3, rel=1e-12)
    cap = lambda m: float(np.asarray(m.capacities[0].compile()({"k": 2.0, "rho": 8000.0, "c_p": 450.0})))  # noqa: E731
    assert cap(one) == pytest.approx(cap(many), rel=1e-13)
