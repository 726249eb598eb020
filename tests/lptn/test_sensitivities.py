"""Exact sensitivities ``S = ∂T/∂θ`` of ``Simulator.simulate(..., wrt=...)`` vs central finite
differences of the simulation itself (step 1e-4 relative to each parameter).

Criterion (per parameter j): on every entry of ``S[:, :, j]`` whose magnitude exceeds 1e-3 of
that parameter's max |S|, the relative error is at most 1e-5. Both discretisations: ZOH and
explicit Euler with a stable sub-step. The initial state is fixed (it does not depend on θ),
so ``S[0] = 0``.
"""
from __future__ import annotations

import numpy as np
import pytest
from lptn_ref import Assembly, pm10kw_inputs, tiny_inputs, tiny_raw

from thermal_edge.lptn import Simulator

REL_STEP = 1e-4
REL_TOL = 1e-5
THRESH = 1e-3

STENCILS = {  # central differences: (offset in steps, weight); derivative = Σ w T(θ + k h) / h
    "c2": [(-1, -0.5), (1, 0.5)],
    "c6": [(-3, -1 / 60), (-2, 9 / 60), (-1, -45 / 60), (1, 45 / 60), (2, -9 / 60), (3, 1 / 60)],
}


def finite_difference_check(
    model, inputs, dt, T0, wrt, method, max_substep=None, stencil="c2", rel_step=REL_STEP, noise_allowance=False
):
    """Compare ``S`` with finite differences of the simulation, parameter by parameter.

    With ``noise_allowance`` the round-off floor ε of the simulation itself is measured (the
    change of T under a 1e-13 relative change of the parameter, where the true change is ~1e-13
    of S θ) and every gated entry may differ by 1e-5 |S| + Σ|w_k| ε/h (each run of the stencil
    carries up to ε of round-off; for the 2-point difference that is 2ε/(2h)).
    """
    sim = Simulator(model, method=method, max_substep=max_substep)
    theta = model.nominal()
    traj = sim.simulate(theta, inputs, dt, T0, wrt=list(wrt))
    S = traj.S
    assert S.shape == (len(traj.T), len(model.nodes), len(wrt))
    assert np.all(S[0] == 0.0)
    idx = model.parameter_index(list(wrt))
    run = lambda th: sim.simulate(th, inputs, dt, T0).T  # noqa: E731
    report = {}
    for j, pi in enumerate(idx):
        h = rel_step * theta[pi]
        fd = sum(w * run(np.where(np.arange(len(theta)) == pi, theta[pi] + k * h, theta)) for k, w in STENCILS[stencil]) / h
        Sj = S[:, :, j]
        scale = np.abs(Sj).max()
        assert scale > 0, f"{wrt[j]}: zero sensitivity everywhere (parameter unused?)"
        big = np.abs(Sj) > THRESH * scale
        allow = 0.0
        if noise_allowance:
            eps = max(
                np.abs(run(np.where(np.arange(len(theta)) == pi, theta[pi] * (1 + d), theta)) - traj.T - d * theta[pi] * Sj).max()
                for d in (1e-13, -1e-13, 3e-14)
            )
            allow = sum(abs(w) for _, w in STENCILS[stencil]) * eps / h
        err = np.abs(Sj - fd)
        rel = err[big] / np.abs(Sj[big])
        report[wrt[j]] = float(rel.max())
        ok = err[big] <= REL_TOL * np.abs(Sj[big]) + allow
        assert ok.all(), (
            f"{method}/{stencil}: {wrt[j]}: {np.count_nonzero(~ok)} entries off, max relative error {rel.max():.2e} "
            f"(allowance {allow:.2e})"
        )
        # the small entries left out above are still right in absolute terms
        assert err.max() <= 1e-5 * scale + allow, wrt[j]
    return traj, report


def stable_substep(model, inputs, dt, safety=0.8):
    """Largest stable explicit-Euler sub-step over the run's operating points, from the
    eigenvalues of C⁻¹A computed here (independent assembly), times a safety factor."""
    names = list(model.inputs)
    N = len(next(iter(inputs.values())))
    X = np.unique(np.stack([np.broadcast_to(np.asarray(inputs[k], float), (N,)) for k in names], axis=1)[:-1], axis=0)
    lam_min = 0.0
    for row in X:
        asm = Assembly(model, model.nominal(), dict(zip(names, row)))
        A, _ = asm.reduced()
        lam = np.linalg.eigvals(A / asm.c[:, None]).real
        lam_min = min(lam_min, lam.min())
    h = safety * 2.0 / -lam_min
    return min(h, dt)


# ---------------------------------------------------------------------------------------------
# the small models


@pytest.mark.parametrize("method", ["zoh", "euler"])
def test_tiny_model(tiny_model, method):
    inputs = tiny_inputs(N=121, seed=1)
    inputs = {k: inputs[k] for k in tiny_model.inputs}
    T0 = np.array([45.0, 60.0, 35.0])
    wrt = tiny_model.parameter_names
    sub = stable_substep(tiny_model, inputs, 10.0) if method == "euler" else None
    if method == "euler":
        sub = min(sub, 2.0)  # several sub-steps per sample: exercises the sub-step derivative
    finite_difference_check(tiny_model, inputs, 10.0, T0, wrt, method, sub)


@pytest.mark.parametrize("method", ["zoh", "euler"])
def test_tiny_plus_model(tiny_plus_model, method):
    """With a parameter in a loss law, a loss not affine in T, a loss into an algebraic point,
    a face point and two boundaries."""
    m = tiny_plus_model
    inputs = tiny_inputs(N=121, seed=2)
    T0 = np.array([50.0, 70.0, 40.0])
    sub = min(stable_substep(m, inputs, 10.0), 2.5) if method == "euler" else None
    finite_difference_check(m, inputs, 10.0, T0, m.parameter_names, method, sub)


def test_subset_of_parameters_matches_full(tiny_plus_model):
    """``wrt`` picks columns: a subset in another order gives the same columns."""
    m = tiny_plus_model
    inputs = tiny_inputs(N=61, seed=4)
    sim = Simulator(m, method="zoh")
    T0 = np.array([50.0, 70.0, 40.0])
    full = sim.simulate(m.nominal(), inputs, 10.0, T0, wrt=m.parameter_names)
    sub = sim.simulate(m.nominal(), inputs, 10.0, T0, wrt=["h_gap", "R_amb"])
    i = {p: k for k, p in enumerate(m.parameter_names)}
    np.testing.assert_allclose(sub.S[:, :, 0], full.S[:, :, i["h_gap"]], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(sub.S[:, :, 1], full.S[:, :, i["R_amb"]], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(sub.T, full.T)


# ---------------------------------------------------------------------------------------------
# paderborn4: all 8 parameters on a 600-row slice of run_a (cold start and heat-up)


@pytest.mark.parametrize("method", ["zoh", "euler"])
def test_paderborn4(paderborn_model, paderborn_run, method):
    m = paderborn_model
    run = paderborn_run.slice(0, 600)
    inputs = {c: run.columns[c] for c in m.inputs}
    T0 = np.array([run.columns[s][0] for s in ("pm", "stator_yoke", "stator_tooth", "stator_winding")])
    assert [m.sensors[s] for s in ("pm", "stator_yoke", "stator_tooth", "stator_winding")] == list(m.nodes)
    sub = 0.5 if method == "euler" else None  # the published sub-step; stable (checked below)
    if method == "euler":
        assert stable_substep(m, inputs, run.dt, safety=1.0) > 0.5
    finite_difference_check(m, inputs, run.dt, T0, m.parameter_names, method, sub)


# ---------------------------------------------------------------------------------------------
# pm10kw: all 14 adaptable parameters, ~900 s of a drive cycle


def _pm10kw_setup(m):
    from thermal_edge.lptn import steady_state

    # 700 s of the cycle: two operating points and the 30 s ramp between them (the whole of the
    # first 900 s took 18-48 s a method with the sixth-order stencil, 84 simulations)
    inputs, dt, what = pm10kw_inputs(m, 700.0)
    assert len(m.adaptable) == 14, f"expected 14 adaptable parameters, got {len(m.adaptable)}"
    # a warm start: half-way between ambient and the steady state at the first operating point
    first = {k: float(v[0]) for k, v in inputs.items()}
    Ts, _ = steady_state(m, first)
    T0 = 0.5 * (Ts + first.get("ambient_c", 25.0))
    return inputs, dt, T0, what


@pytest.mark.parametrize("method", ["zoh", "euler"])
def test_pm10kw_high_order(pm10kw_model, method):
    """On this 39-node stiff network the simulation's own round-off (~1e-10 K) divided by a
    1e-4 step swamps 1e-5 of the small entries, so the reference is a sixth-order central
    difference with a 2 % step (truncation below 1e-6 relative here): relative error <= 1e-5 on
    every entry above 1e-3 of the parameter's max |S|, plus the measured round-off term."""
    m = pm10kw_model
    inputs, dt, T0, what = _pm10kw_setup(m)
    sub = stable_substep(m, inputs, dt) if method == "euler" else None
    _, report = finite_difference_check(
        m, inputs, dt, T0, m.adaptable, method, sub, stencil="c6", rel_step=2e-2, noise_allowance=True
    )
    print(what, method, "substep", sub, "max rel err", max(report.values()))


# ---------------------------------------------------------------------------------------------
# held inputs: the closed form over runs of held inputs (thermal_edge.lptn.sensitivity)


def _closed_form_calls(monkeypatch):
    """Lengths of the held runs the closed form was applied to during the test."""
    from thermal_edge.lptn import sensitivity

    calls = []
    orig = sensitivity._HeldRun.apply

    def apply(self, s0, out, work):
        calls.append(len(out))
        return orig(self, s0, out, work)

    monkeypatch.setattr(sensitivity._HeldRun, "apply", apply)
    return calls


@pytest.mark.parametrize("method", ["zoh", "euler"])
def test_tiny_model_held_inputs(tiny_model, method, monkeypatch):
    """Inputs held for 100 steps at a time: the closed form (ZOH) against finite differences."""
    calls = _closed_form_calls(monkeypatch)
    inputs = tiny_inputs(N=401, seed=5, hold=100)
    inputs = {k: inputs[k] for k in tiny_model.inputs}
    T0 = np.array([45.0, 60.0, 35.0])
    sub = min(stable_substep(tiny_model, inputs, 10.0), 2.0) if method == "euler" else None
    finite_difference_check(tiny_model, inputs, 10.0, T0, tiny_model.parameter_names, method, sub)
    if method == "zoh":
        assert calls == [100, 100, 100, 100], calls  # 400 steps, inputs held for 100 at a time


def test_cross_coupled_loss_is_stepped(monkeypatch):
    """A loss at one node that depends on another node's temperature makes the closed-loop
    transition non-symmetrisable: the held runs are stepped instead, and still exact."""
    from thermal_edge.lptn.loader import build_model

    raw = tiny_raw()
    raw["losses"][0]["power"] = "3*0.5*i_rms**2 * (1 + alpha*(T.yoke - 20))"
    m = build_model(raw, fname="tiny_cross.yaml")
    calls = _closed_form_calls(monkeypatch)
    inputs = tiny_inputs(N=301, seed=6, hold=100)
    inputs = {k: inputs[k] for k in m.inputs}
    finite_difference_check(m, inputs, 10.0, np.array([45.0, 60.0, 35.0]), m.parameter_names, "zoh")
    assert calls == []


@pytest.mark.parametrize("rows", [None, "sensors"])
def test_pm10kw_closed_form_equals_stepping(pm10kw_model, rows, monkeypatch):
    """The closed form over held runs and the step-by-step recursion give the same S, all 14
    parameters, on 3000 s of the drive cycle (all nodes, or the sensor rows only)."""
    from thermal_edge.lptn import steady_state

    m = pm10kw_model
    inputs, dt, _ = pm10kw_inputs(m, 3000.0)
    first = {k: float(v[0]) for k, v in inputs.items()}
    T0, _ = steady_state(m, first)
    sim = Simulator(m)
    keep = list(m.sensors.values()) if rows else None
    calls = _closed_form_calls(monkeypatch)
    closed = sim.simulate(m.nominal(), inputs, dt, T0, wrt=m.adaptable, rows=keep)
    assert sum(calls) > 0.8 * (len(closed.T) - 1), calls  # most of the cycle is held
    n_calls = len(calls)
    stepped = Simulator(m, closed_form=False).simulate(m.nominal(), inputs, dt, T0, wrt=m.adaptable, rows=keep)
    assert len(calls) == n_calls  # no closed form the second time
    # the simulation steps the held runs in blocks of the transition's powers: the same to round-off
    assert np.abs(closed.T - stepped.T).max() <= 1e-12 * np.abs(stepped.T).max()
    for j, name in enumerate(m.adaptable):
        scale = np.abs(stepped.S[:, :, j]).max()
        err = np.abs(closed.S[:, :, j] - stepped.S[:, :, j]).max()
        assert err <= 1e-9 * scale, f"{name}: {err:.3g} vs max |S| {scale:.3g}"


def test_divided_powers():
    """DD_k(x, y) = Σ_{i<k} x^(k−1−i) y^i by direct summation, for far, close, equal and tiny arguments."""
    from thermal_edge.lptn.sensitivity import divided_powers

    pairs = [(0.9, 0.5), (0.99999, 0.99998), (0.7, 0.7), (0.7, 0.7 * (1 + 1e-12)), (1e-14, 0.3), (1.0, 0.999)]
    for x, y in pairs:
        for k in (1, 2, 7, 250):
            direct = sum(x ** (k - 1 - i) * y ** i for i in range(k))
            got = float(divided_powers(np.array(x), np.array(y), np.array(float(k))))
            assert abs(got - direct) <= 1e-12 * abs(direct), (x, y, k, got, direct)


BRANCHES_RAW = {
    "name": "branches",
    "inputs": {"i_rms": {}, "ambient_c": {}},
    "boundaries": {"ambient": "ambient_c"},
    "constants": {"alpha": 3.93e-3},
    "parameters": {
        "g_a": {"value": 4.0, "min": 0.5, "max": 20},
        "g_b": {"value": 4.0, "min": 0.5, "max": 20},
        "g_c": {"value": 4.0, "min": 0.5, "max": 20},
        "R_amb": {"value": 0.5, "min": 0.1, "max": 5},
        "c_n": {"value": 800, "min": 100, "max": 5000},
        "g_store": {"value": 0.5, "min": 0.1, "max": 5},
    },
    "nodes": [
        {"name": "a", "capacity": "c_n"},
        {"name": "b", "capacity": "c_n"},
        {"name": "c", "capacity": "c_n"},
        {"name": "hub", "capacity": 3000},
        {"name": "store", "capacity": 2e8},
    ],
    "conductances": [
        {"between": ["a", "hub"], "g": "g_a"},
        {"between": ["b", "hub"], "g": "g_b"},
        {"between": ["a", "ambient"], "r": "R_amb"},
        {"between": ["b", "ambient"], "r": "R_amb"},
        {"between": ["c", "hub"], "g": "g_c"},
        {"between": ["c", "ambient"], "r": "R_amb"},
        {"between": ["hub", "store"], "g": "g_store"},
        {"between": ["store", "ambient"], "g": 0.1},
    ],
    "losses": [
        {"node": "a", "power": "0.5*i_rms**2 * (1 + alpha*(T.a - 20))"},
        {"node": "b", "power": "0.5*i_rms**2 * (1 + alpha*(T.b - 20))"},
        {"node": "c", "power": "0.5*i_rms**2 * (1 + alpha*(T.c - 20))"},
    ],
    "sensors": {"a": {"node": "a"}},
}


def test_close_modes_and_repeated_set_points(monkeypatch):
    """Three identical branches on a hub (a repeated eigenvalue, coupled by the parameters that
    break the symmetry), a node whose mode is within 1e-6 of μ = 1 (the constant forcing's), and set points
    met again at another ambient temperature (runs that share one transition): the closed form
    takes its close-pair terms and agrees with stepping and with finite differences."""
    from thermal_edge.lptn import sensitivity
    from thermal_edge.lptn.loader import build_model

    m = build_model(BRANCHES_RAW, fname="branches.yaml")
    seen = []
    orig = sensitivity._HeldRun.apply

    def apply(self, s0, out, work):
        seen.append(self.extra)
        return orig(self, s0, out, work)

    monkeypatch.setattr(sensitivity._HeldRun, "apply", apply)
    hold = 100
    inputs = {
        "i_rms": np.repeat([6.0, 10.0, 6.0, 0.0, 0.0, 10.0], hold),
        "ambient_c": np.repeat([20.0, 25.0, 30.0, 22.0, 28.0, 21.0], hold),
    }
    inputs = {k: np.append(v, v[-1]) for k, v in inputs.items()}
    T0 = np.array([40.0, 35.0, 38.0, 30.0, 25.0])
    traj, _ = finite_difference_check(m, inputs, 10.0, T0, m.parameter_names, "zoh")
    assert len(seen) == 6
    pairs = [set(zip(e[0].tolist(), e[1].tolist())) for e in seen if e is not None]
    assert len(pairs) == 6, "every run has close modes"
    n = len(m.nodes)
    assert all(any(b == n for _, b in p) for p in pairs), "the store's mode is close to μ = 1"
    assert all(any(b < n for _, b in p) for p in pairs), "the branches' modes are close to each other"
    stepped = Simulator(m, closed_form=False).simulate(m.nominal(), inputs, 10.0, T0, wrt=m.parameter_names)
    scale = np.abs(stepped.S).max(axis=(0, 1))
    assert np.all(np.abs(traj.S - stepped.S).max(axis=(0, 1)) <= 1e-9 * scale)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_held_runs_are_the_long_runs_of_held_steps(seed):
    """The runs of held inputs at least ``min_len`` long, against a plain walk over the steps
    (mostly varying steps with a few long holds, as recorded data give)."""
    from thermal_edge.lptn.sensitivity import held_runs

    rng = np.random.default_rng(seed)
    held = rng.random(3000) < 0.3
    for a in rng.integers(0, 2900, 6):
        held[a: a + rng.integers(10, 100)] = True
    held[0] = False
    ref, start = [], 0
    for k in range(1, len(held) + 1):
        if k == len(held) or not held[k]:
            if k - start >= 20:
                ref.append((start, k))
            start = k
    assert held_runs(held, True, 20) == ref
    assert held_runs(held, False, 20) == []
