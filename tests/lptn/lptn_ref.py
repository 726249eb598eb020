"""Independent reference computations and shared model documents for the LPTN tests.

Nothing here calls ``Network.continuous``, ``discretise`` or the simulator: the conductance
Laplacian is assembled directly from ``model.edges`` (each edge law evaluated with
``edge.g.compile()``), the algebraic points are solved by plain linear algebra, and losses are
evaluated from the model's loss laws. Tests compare the package against these.
"""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
MACHINES = REPO / "config" / "machines"
CYCLES = REPO / "config" / "cycles"
PADERBORN_DIR = REPO.parent / "shared" / "data" / "paderborn"
PADERBORN_YAML = MACHINES / "paderborn4.yaml"
PM10KW_YAML = MACHINES / "pm10kw.yaml"

TINY_RAW = {
    "name": "tiny",
    "inputs": {"speed_rpm": {"role": "speed"}, "i_rms": {"role": "current"}, "ambient_c": {"role": "ambient"}},
    "boundaries": {"ambient": "ambient_c"},
    "constants": {"alpha": 3.93e-3},
    "parameters": {
        "R_amb": {"value": 0.5, "min": 0.1, "max": 5},
        "k_cu": {"value": 2.0, "min": 0.5, "max": 10},
        "c_w": {"value": 400, "min": 100, "max": 1000},
        "h_gap": {"value": 20, "min": 1, "max": 100},
    },
    "materials": {
        "fe": {"k_r": 28, "k_a": 2, "k_c": 28, "rho": 7650, "c_p": 460},
        "cu": {"k_r": "k_cu", "k_a": 300, "k_c": "k_cu", "rho": 8900, "c_p": "c_w"},
    },
    "arcs": [
        {"name": "yoke", "r1": 0.1, "r2": 0.12, "theta": 6.28, "length": 0.1, "material": "fe"},
        {"name": "wind", "role": "winding", "r1": 0.08, "r2": 0.1, "theta": 3.0, "length": 0.1, "material": "cu"},
    ],
    "nodes": [{"name": "rotor", "role": "rotor_iron", "capacity": 2000}],
    "conductances": [
        {"between": ["yoke.r_out", "ambient"], "r": "R_amb"},
        {"between": ["yoke.r_in", "wind.r_out"]},
        {"between": ["wind.r_in", "rotor"], "g": "h_gap * (1 + speed_rpm/1000)"},
        {"between": ["rotor", "ambient"], "r": 5.0},
    ],
    "losses": [
        {"node": "wind", "power": "3*0.5*i_rms**2 * (1 + alpha*(T.wind - 20))"},
        {"node": "yoke", "power": "0.01*speed_rpm"},
    ],
    "sensors": {"w": {"node": "wind"}},
}


def tiny_raw() -> dict:
    """A fresh (deep) copy of the small model document, safe to modify."""
    return copy.deepcopy(TINY_RAW)


def tiny_plus_raw() -> dict:
    """The small model plus: a parameter in a loss law, a loss that is *not* affine in
    temperature, a declared algebraic point carrying a loss, a face with two connections (its
    own face point) and a second boundary. Exercises every path of the simulator and network."""
    raw = tiny_raw()
    raw["inputs"]["coolant_c"] = {"role": "coolant"}
    raw["boundaries"]["coolant"] = "coolant_c"
    raw["parameters"]["R_ph"] = {"value": 0.5, "min": 0.05, "max": 5}
    raw["parameters"]["R_cool"] = {"value": 0.8, "min": 0.1, "max": 5}
    raw["parameters"]["k_fe"] = {"value": 0.02, "min": 0.001, "max": 0.1}
    raw["losses"] = [
        {"node": "wind", "power": "3*R_ph*i_rms**2 * (1 + alpha*(T.wind - 20))"},
        {"node": "yoke", "power": "k_fe*speed_rpm * (1 + 2e-3*(T.yoke - 20))**1.5"},
        {"node": "gap", "power": "1e-3*speed_rpm"},
    ]
    raw["points"] = ["gap"]
    raw["conductances"] = [
        {"between": ["yoke.r_out", "ambient"], "r": "R_amb"},
        {"between": ["yoke.r_out", "coolant"], "r": "R_cool"},  # yoke.r_out has two connections
        {"between": ["yoke.r_in", "wind.r_out"]},
        {"between": ["wind.r_in", "gap"], "g": "h_gap * (1 + speed_rpm/1000)"},
        {"between": ["gap", "rotor"], "g": "2 * h_gap * (1 + speed_rpm/2000)"},
        {"between": ["rotor", "ambient"], "r": 5.0},
        {"between": ["wind.a_front", "coolant"], "r": 2.0},
    ]
    return raw


def require_paderborn() -> Path:
    if not PADERBORN_DIR.is_dir() or not (PADERBORN_DIR / "run_a.csv").exists():
        pytest.skip(f"Paderborn data not found at {PADERBORN_DIR} (needs run_a.csv and the loss tables)")
    if not PADERBORN_YAML.exists():
        pytest.skip(f"{PADERBORN_YAML} not found")
    return PADERBORN_DIR


def require_pm10kw() -> Path:
    if not PM10KW_YAML.exists():
        pytest.skip(f"{PM10KW_YAML} not found (model file not written yet)")
    return PM10KW_YAML


def synthetic_inputs(model, duration_s: float, dt: float, seed: int = 0, hold_s: float = 60.0) -> dict[str, np.ndarray]:
    """Piecewise-constant inputs for any model, chosen by the inputs' roles (rpm, A, Nm, °C)."""
    from thermal_edge.lptn import Role

    rng = np.random.default_rng(seed)
    N = int(round(duration_s / dt)) + 1
    seg = max(1, int(round(hold_s / dt)))
    nseg = -(-N // seg)
    kt = float(model.drive.get("kt_nm_per_arms", 6.0)) if getattr(model, "drive", None) else 6.0
    speed = np.repeat(rng.choice([0.0, 300.0, 600.0, 900.0, 1200.0], nseg), seg)[:N]
    torque = np.repeat(rng.uniform(-60.0, 110.0, nseg), seg)[:N]
    by_role = {Role.SPEED: speed, Role.TORQUE: torque, Role.CURRENT: np.abs(torque) / kt, Role.CURRENT_D: np.zeros(N),
               Role.CURRENT_Q: np.sqrt(2.0) * torque / kt}
    out: dict[str, np.ndarray] = {}
    for name in model.inputs:
        role = model.input_roles.get(name)
        if role in by_role:
            out[name] = by_role[role]
        elif name in model.temperature_inputs:
            out[name] = np.repeat(rng.uniform(20.0, 35.0, nseg), seg)[:N]
        else:
            out[name] = np.repeat(rng.uniform(0.5, 1.5, nseg), seg)[:N]
    return out


def pm10kw_inputs(model, duration_s: float = 900.0):
    """About ``duration_s`` of a drive cycle from config/cycles (if one exists and gives every
    input the model needs), else synthetic piecewise-constant inputs; returns (inputs, dt, what)."""
    if CYCLES.is_dir():
        from thermal_edge.sim.cycles import cycle_run, load_cycle

        files = sorted(CYCLES.glob("*.yaml"), key=lambda f: (f.name != "varied_drive.yaml", f.name))
        for f in files:
            try:
                cyc = load_cycle(f)
                run = cycle_run(cyc, float(model.drive.get("kt_nm_per_arms", 6.0)), duration_s=duration_s)
            except Exception:
                continue
            if all(c in run.columns for c in model.inputs):
                return {c: np.asarray(run.columns[c], float) for c in model.inputs}, float(cyc.dt_s), f"cycle {f.name}"
    dt = 1.0
    return synthetic_inputs(model, duration_s, dt, seed=3), dt, "synthetic piecewise-constant inputs"


def tiny_inputs(N: int = 121, seed: int = 1, hold: int = 10) -> dict[str, np.ndarray]:
    """Piecewise-constant inputs for the small models (speed levels, moderate currents)."""
    rng = np.random.default_rng(seed)
    nseg = -(-N // hold)
    rep = lambda v: np.repeat(v, hold)[:N]  # noqa: E731
    return {
        "speed_rpm": rep(rng.choice([0.0, 500.0, 1500.0, 3000.0], nseg)),
        "i_rms": rep(rng.uniform(2.0, 12.0, nseg)),
        "ambient_c": rep(rng.uniform(20.0, 30.0, nseg)),
        "coolant_c": rep(rng.uniform(25.0, 40.0, nseg)),
    }




# ---------------------------------------------------------------------------------------------
# independent reference: law environments, the full Laplacian, the continuous right-hand side


def law_env(model, theta, inputs) -> dict:
    """Name -> value for laws: parameters, the given inputs, and the derived inputs evaluated
    in declaration order from their own laws (scalars or arrays)."""
    env: dict = {p.name: float(v) for p, v in zip(model.parameters, np.asarray(theta, float))}
    env.update({k: (np.asarray(v, float) if np.ndim(v) else float(v)) for k, v in inputs.items()})
    for k, law in model.derived.items():
        env[k] = law.compile()(env)
    return env


class Assembly:
    """Full conductance Laplacian over all points (dynamic nodes first, then algebraic points)
    and point-to-boundary conductances, at one operating point (scalar inputs)."""

    def __init__(self, model, theta, inputs) -> None:
        self.model = model
        names = list(model.nodes) + list(model.points)
        self.names = names
        idx = {p: i for i, p in enumerate(names)}
        bnames = list(model.boundaries)
        bidx = {b: i for i, b in enumerate(bnames)}
        n_all, nb = len(names), len(bnames)
        self.n = len(model.nodes)
        env = law_env(model, theta, inputs)
        self.env = env
        L = np.zeros((n_all, n_all))
        KU = np.zeros((n_all, nb))
        self.edge_g = []
        for e in model.edges:
            g = float(np.asarray(e.g.compile()(env)))
            self.edge_g.append(g)
            a = idx[e.a]
            if e.b in bidx:
                L[a, a] += g
                KU[a, bidx[e.b]] += g
            else:
                b = idx[e.b]
                L[a, a] += g
                L[b, b] += g
                L[a, b] -= g
                L[b, a] -= g
        self.L, self.KU = L, KU
        penv = {p.name: float(v) for p, v in zip(model.parameters, np.asarray(theta, float))}
        self.c = np.array([float(np.asarray(c.compile()(penv))) for c in model.capacities])
        self.loss_point = np.array([idx[l.point] for l in model.losses], dtype=int)
        self.loss_f = [l.power.compile() for l in model.losses]
        self.U = np.array([float(np.asarray(inputs[col])) for col in model.boundaries.values()])

    # reduced (Schur) matrices computed here with plain numpy, for the expm comparisons
    def reduced(self):
        n, L, KU = self.n, self.L, self.KU
        D, Q = slice(0, n), slice(n, None)
        M = np.zeros((L.shape[0], len(self.loss_point)))
        M[self.loss_point, np.arange(len(self.loss_point))] = 1.0
        if L.shape[0] > n:
            Xt = np.linalg.solve(L[Q, Q].T, L[D, Q].T).T  # L_DQ L_QQ^-1
        else:
            Xt = np.zeros((n, 0))
        A = -(L[D, D] - Xt @ L[Q, D])
        B = KU[D] - Xt @ KU[Q]
        E = M[D] - Xt @ M[Q]
        return A, np.concatenate([B, E], axis=1)

    def losses(self, T_nodes) -> np.ndarray:
        env = dict(self.env)
        for i, node in enumerate(self.model.nodes):
            env["T." + node] = float(T_nodes[i])
        return np.array([float(np.asarray(f(env))) for f in self.loss_f])

    def point_injection(self, P) -> np.ndarray:
        out = np.zeros(self.L.shape[0])
        np.add.at(out, self.loss_point, P)
        return out

    def solve_points(self, T_nodes, P) -> np.ndarray:
        """All point temperatures from the node temperatures: algebraic balance at the points."""
        n, L = self.n, self.L
        if L.shape[0] == n:
            return np.asarray(T_nodes, float)
        q = self.point_injection(P)
        rhs = q[n:] - L[n:, :n] @ T_nodes + self.KU[n:] @ self.U
        return np.concatenate([T_nodes, np.linalg.solve(L[n:, n:], rhs)])

    def rhs(self, T_nodes, P=None) -> np.ndarray:
        """dT/dt of the dynamic nodes; losses at ``T_nodes`` unless ``P`` is given (held)."""
        if P is None:
            P = self.losses(T_nodes)
        Tall = self.solve_points(T_nodes, P)
        q = self.point_injection(P)
        n = self.n
        flow = q[:n] - self.L[:n] @ Tall + self.KU[:n] @ self.U
        return flow / self.c

    def balance(self, Tall, P) -> np.ndarray:
        """Net heat (W) into every point: losses minus conduction out (zero at steady state)."""
        return self.point_injection(P) - self.L @ Tall + self.KU @ self.U


def reference_run(model, theta, inputs, dt, T0, hold_losses=False, rtol=1e-10, atol=1e-10, method="Radau"):
    """Integrate the continuous model with scipy's ``solve_ivp`` sample by sample: inputs held
    over each sample (consecutive identical samples merged into one segment), losses evaluated
    continuously at the current temperatures (or, with ``hold_losses``, at the temperatures at
    the start of each sample, as the discrete model does)."""
    from scipy.integrate import solve_ivp

    names = list(model.inputs)
    N = len(next(iter(inputs.values())))
    X = np.stack([np.broadcast_to(np.asarray(inputs[k], float), (N,)) for k in names], axis=1)
    T = np.empty((N, len(model.nodes)))
    T[0] = T0
    cache: dict = {}
    k = 0
    while k < N - 1:
        j = k + 1
        if not hold_losses:  # merge samples with identical inputs into one smooth segment
            while j < N - 1 and np.array_equal(X[j], X[k]):
                j += 1
        key = tuple(X[k])
        asm = cache.get(key)
        if asm is None:
            asm = cache[key] = Assembly(model, theta, dict(zip(names, X[k])))
        P_held = asm.losses(T[k]) if hold_losses else None

        def fun(t, y, a=asm, P=P_held):
            return a.rhs(y, P)

        t_eval = dt * np.arange(1, j - k + 1)
        sol = solve_ivp(fun, (0.0, dt * (j - k)), T[k], method=method, rtol=rtol, atol=atol, t_eval=t_eval)
        assert sol.success, sol.message
        T[k + 1 : j + 1] = sol.y.T
        k = j
    return T
