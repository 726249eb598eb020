"""Discretisation: ZOH against an ODE solver and against ``expm``; explicit Euler's stability
check, its sub-steps and its convergence to ZOH.

The references are built independently of ``Network.continuous`` and ``discretise``: the full
conductance Laplacian is assembled from ``model.edges`` (``lptn_ref.Assembly``), the algebraic
points are solved inside the right-hand side, and losses are evaluated from the loss laws.
"""
from __future__ import annotations

import math
import re

import numpy as np
import pytest
from lptn_ref import Assembly, law_env, pm10kw_inputs, reference_run, tiny_inputs, tiny_raw
from scipy.linalg import expm, expm_frechet

from thermal_edge.lptn import Network, Simulator, UnstableDiscretisation, discretise
from thermal_edge.lptn.loader import build_model


def op_of(model, inputs, k=0):
    """The values of every input at sample k (the network picks those it needs)."""
    return {c: np.array([float(np.asarray(inputs[c])[k])]) for c in model.inputs}


def augmented(A, W, c, dt):
    n, m = W.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n] = A / c[:, None]
    M[:n, n:] = W / c[:, None]
    return M * dt


def check_zoh_against_expm(model, inputs, dt, k=0):
    theta = model.nominal()
    asm = Assembly(model, theta, {c: float(np.asarray(inputs[c])[k]) for c in model.inputs})
    A, W = asm.reduced()
    n = len(model.nodes)
    E = expm(augmented(A, W, asm.c, dt))
    d = discretise(Network(model).continuous(theta, op_of(model, inputs, k)), dt, "zoh")
    Phi, Gam = d.Phi[0], d.Gam[0]
    assert np.abs(Phi - E[:n, :n]).max() <= 1e-11 * max(1.0, np.abs(E[:n, :n]).max())
    for j in range(W.shape[1]):  # column by column: boundary columns are K/K, loss columns K/W
        ref = E[:n, n + j]
        assert np.abs(Gam[:, j] - ref).max() <= 1e-10 * np.abs(ref).max() + 1e-15, j
    return asm, E


def test_zoh_vs_expm_tiny(tiny_plus_model):
    m = tiny_plus_model
    for k, dt in [(0, 1.0), (15, 10.0), (40, 600.0)]:
        check_zoh_against_expm(m, tiny_inputs(N=60, seed=5), dt, k)


def test_zoh_vs_expm_pm10kw(pm10kw_model):
    inputs, dt, _ = pm10kw_inputs(pm10kw_model, 120.0)
    check_zoh_against_expm(pm10kw_model, inputs, dt, 0)
    check_zoh_against_expm(pm10kw_model, inputs, 60.0, len(next(iter(inputs.values()))) - 2)


def test_one_simulated_step_is_the_expm_step(tiny_plus_model):
    """One step of ``Simulator.simulate`` = expm of the augmented matrix applied to
    [T0; U0; P(T0)], with the losses evaluated from their laws at T0."""
    m = tiny_plus_model
    inputs = {k: v[:2] for k, v in tiny_inputs(N=2, seed=6).items()}
    T0 = np.array([55.0, 80.0, 41.0])
    asm, E = check_zoh_against_expm(m, inputs, 7.0, 0)
    P0 = asm.losses(T0)
    n = len(T0)
    ref = E[:n, :n] @ T0 + E[:n, n:] @ np.concatenate([asm.U, P0])
    got = Simulator(m, method="zoh").simulate(m.nominal(), inputs, 7.0, T0).T[1]
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10)


def test_zoh_derivatives_vs_expm_frechet(tiny_plus_model):
    """dΦ/dθ and dΓ/dθ of the discretisation = the Fréchet derivative of expm of the augmented
    matrix in the direction of its derivative (taken here by central differences of the
    independently assembled matrices, which are smooth and cheap)."""
    m = tiny_plus_model
    inputs = tiny_inputs(N=3, seed=8)
    theta = m.nominal()
    dt = 30.0
    scal = {c: float(inputs[c][0]) for c in m.inputs}

    def M_of(th):
        asm = Assembly(m, th, scal)
        A, W = asm.reduced()
        return augmented(A, W, asm.c, dt)

    M = M_of(theta)
    n = len(m.nodes)
    wrt = list(range(len(theta)))
    d = discretise(Network(m).continuous(theta, op_of(m, inputs), wrt=wrt), dt, "zoh")
    for j in wrt:
        h = 1e-5 * theta[j]
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        dM = (M_of(tp) - M_of(tm)) / (2 * h)
        _, dE = expm_frechet(M, dM)
        scale = np.abs(dE[:n]).max()
        if scale == 0:
            assert np.abs(d.dPhi[0, j]).max() == 0 and np.abs(d.dGam[0, j]).max() == 0
            continue
        np.testing.assert_allclose(d.dPhi[0, j], dE[:n, :n], rtol=0, atol=1e-7 * scale, err_msg=m.parameter_names[j])
        np.testing.assert_allclose(d.dGam[0, j], dE[:n, n:], rtol=0, atol=1e-7 * scale, err_msg=m.parameter_names[j])


# ---------------------------------------------------------------------------------------------
# ZOH vs solve_ivp


def _compare_with_ivp(model, inputs, dt, T0, tol_cont, tol_held):
    theta = model.nominal()
    T = Simulator(model, method="zoh").simulate(theta, inputs, dt, T0).T
    held = reference_run(model, theta, inputs, dt, T0, hold_losses=True)
    err_held = np.abs(T - held).max()
    assert err_held <= tol_held, f"ZOH vs ODE solver with the losses held over each step: {err_held:.3g} K"
    cont = reference_run(model, theta, inputs, dt, T0, hold_losses=False)
    err_cont = np.abs(T - cont).max()
    assert err_cont <= tol_cont, f"ZOH vs ODE solver with continuous losses: {err_cont:.3g} K"
    assert np.ptp(T) > 5.0  # the run does something
    return err_held, err_cont


def test_zoh_vs_solve_ivp_tiny(tiny_plus_model):
    m = tiny_plus_model
    inputs = tiny_inputs(N=301, seed=9, hold=30)
    T0 = np.array([30.0, 32.0, 28.0])
    eh, ec = _compare_with_ivp(m, inputs, 1.0, T0, tol_cont=0.01, tol_held=1e-7)
    print(f"tiny_plus: held {eh:.2e} K, continuous {ec:.2e} K")


def test_zoh_vs_solve_ivp_tiny_brief_model(tiny_model):
    m = tiny_model
    inputs = {k: v for k, v in tiny_inputs(N=301, seed=10, hold=30).items() if k in m.inputs}
    T0 = np.array([30.0, 32.0, 28.0])
    _compare_with_ivp(m, inputs, 1.0, T0, tol_cont=0.01, tol_held=1e-7)


def test_zoh_vs_solve_ivp_pm10kw(pm10kw_model):
    """900 s of a drive cycle from a warm start; continuous losses over the whole run (samples
    with identical inputs merged into one smooth segment), and, over a 200-s window around the
    first ramp (every 1-s sample its own segment), losses held over each sample."""
    m = pm10kw_model
    inputs, dt, what = pm10kw_inputs(m, 900.0)
    from thermal_edge.lptn import steady_state

    first = {k: float(v[0]) for k, v in inputs.items()}
    Ts, _ = steady_state(m, first)
    T0 = 0.5 * (Ts + first.get("ambient_c", 25.0))
    theta = m.nominal()
    T = Simulator(m, method="zoh").simulate(theta, inputs, dt, T0).T
    assert np.abs(T[-1] - T[0]).max() > 5.0  # the run heats the machine
    cont = reference_run(m, theta, inputs, dt, T0, hold_losses=False)
    err = np.abs(T - cont).max()
    print(f"pm10kw ({what}): ZOH vs continuous-loss ODE {err:.3g} K")
    assert err <= 0.01
    a, b = 550, 750
    win = {k: v[a:b] for k, v in inputs.items()}
    held = reference_run(m, theta, win, dt, T[a], hold_losses=True)
    Tw = Simulator(m, method="zoh").simulate(theta, win, dt, T[a]).T
    np.testing.assert_allclose(Tw, T[a:b], rtol=0, atol=1e-9)  # restarting mid-run changes nothing
    err_held = np.abs(Tw - held).max()
    print(f"pm10kw: ZOH vs held-loss ODE {err_held:.3g} K")
    assert err_held <= 1e-7


# ---------------------------------------------------------------------------------------------
# explicit Euler


def stiff_raw():
    """The small model with a tiny-capacity air node between the winding and the rotor."""
    raw = tiny_raw()
    raw["nodes"].append({"name": "air", "capacity": 0.05})
    raw["conductances"][2] = {"between": ["wind.r_in", "air"], "g": "h_gap * (1 + speed_rpm/1000)"}
    raw["conductances"].append({"between": ["air", "rotor"], "g": 15.0})
    return raw


def _eigs(model, inputs, k=0):
    asm = Assembly(model, model.nominal(), {c: float(np.asarray(inputs[c])[k]) for c in model.inputs})
    A, _ = asm.reduced()
    return np.linalg.eigvals(A / asm.c[:, None]).real


def test_euler_unstable_step_is_refused_with_a_clear_message():
    m = build_model(stiff_raw(), fname="stiff.yaml")
    inputs = {k: v[:20] for k, v in tiny_inputs(N=20, seed=11).items() if k in m.inputs}
    inputs = {k: np.full(20, v[0]) for k, v in inputs.items()}  # one operating point
    lam = _eigs(m, inputs)
    h_max = 2.0 / -lam.min()
    rho = np.abs(1.0 + 1.0 * lam).max()
    assert h_max < 0.1 and rho > 1  # the premise: Euler at 1 s diverges
    with pytest.raises(UnstableDiscretisation) as ei:  # one step asked for (the sub-step limit at the step)
        Simulator(m, method="euler", max_substep=1.0).simulate(m.nominal(), inputs, 1.0, np.full(4, 25.0))
    msg = str(ei.value)
    assert "spectral radius" in msg
    nums = [float(x) for x in re.findall(r"[-+]?\d+\.?\d*(?:[eE][-+]?\d+)?", msg)]
    assert any(abs(x - rho) <= 5e-3 * rho for x in nums), (msg, rho)  # the radius it found
    assert any(abs(x - h_max) <= 5e-3 * h_max for x in nums), (msg, h_max)  # a stable step
    assert "zoh" in msg.lower()
    # a sub-step limit that is still too long is refused too
    with pytest.raises(UnstableDiscretisation):
        Simulator(m, method="euler", max_substep=1.5 * h_max).simulate(m.nominal(), inputs, 1.0, np.full(4, 25.0))


def test_euler_with_small_substeps_runs_and_matches_my_own_euler():
    m = build_model(stiff_raw(), fname="stiff.yaml")
    N, dt = 30, 1.0
    inputs = {k: v for k, v in tiny_inputs(N=N, seed=12, hold=7).items() if k in m.inputs}
    h_max = min(2.0 / -_eigs(m, inputs, k).min() for k in range(N - 1))
    sub = 0.9 * h_max
    T0 = np.array([40.0, 60.0, 35.0, 45.0])
    sim = Simulator(m, method="euler", max_substep=sub)
    T = sim.simulate(m.nominal(), inputs, dt, T0).T
    assert np.all(np.isfinite(T))
    # independent explicit Euler on the continuous system: ceil(dt/sub) sub-steps per sample,
    # losses at the start of the sample held over it (the discrete model's rule)
    msub = math.ceil(dt / sub - 1e-9)
    h = dt / msub
    x = T0.copy()
    ref = [x.copy()]
    for k in range(N - 1):
        asm = Assembly(m, m.nominal(), {c: float(inputs[c][k]) for c in m.inputs})
        P = asm.losses(x)
        for _ in range(msub):
            x = x + h * asm.rhs(x, P)
        ref.append(x.copy())
    np.testing.assert_allclose(T, np.array(ref), rtol=0, atol=1e-9)


def test_euler_converges_to_zoh(tiny_plus_model):
    """First-order convergence: the error against ZOH falls ~10x per 10x smaller sub-step."""
    m = tiny_plus_model
    inputs = tiny_inputs(N=61, seed=13)
    T0 = np.array([30.0, 35.0, 28.0])
    dt = 10.0
    zoh = Simulator(m, method="zoh").simulate(m.nominal(), inputs, dt, T0).T
    errs = []
    for sub in (1.0, 0.1, 0.01):
        eu = Simulator(m, method="euler", max_substep=sub).simulate(m.nominal(), inputs, dt, T0).T
        errs.append(np.abs(eu - zoh).max())
    assert errs[0] > 1e-4  # the first-order error is visible
    assert 5 < errs[0] / errs[1] < 20 and 5 < errs[1] / errs[2] < 20, errs
    assert errs[2] < 1e-3


def test_euler_without_substep_limit_is_one_step_when_stable(tiny_model):
    m = tiny_model
    inputs = {k: v for k, v in tiny_inputs(N=11, seed=14).items() if k in m.inputs}
    T0 = np.array([30.0, 35.0, 28.0])
    dt = 5.0
    T = Simulator(m, method="euler").simulate(m.nominal(), inputs, dt, T0).T
    x = T0.copy()
    for k in range(10):
        asm = Assembly(m, m.nominal(), {c: float(inputs[c][k]) for c in m.inputs})
        x = x + dt * asm.rhs(x, asm.losses(x))
        np.testing.assert_allclose(T[k + 1], x, rtol=0, atol=1e-10)


def test_unknown_method_is_refused(tiny_model):
    with pytest.raises(ValueError, match="rk4"):
        Simulator(tiny_model, method="rk4").simulate(
            tiny_model.nominal(), {"speed_rpm": np.zeros(3), "i_rms": np.zeros(3), "ambient_c": np.zeros(3)}, 1.0, np.zeros(3)
        )


def test_law_env_matches_derived_inputs(paderborn_model, paderborn_run):
    """Sanity of the reference itself on a model with derived inputs and tables: the
    independent environment gives the same losses as the simulator reports."""
    m = paderborn_model
    run = paderborn_run.slice(100, 103)
    inputs = {c: run.columns[c] for c in m.inputs}
    T0 = np.array([60.0, 50.0, 70.0, 90.0])
    traj = Simulator(m).simulate(m.nominal(), inputs, run.dt, T0)
    env = law_env(m, m.nominal(), {c: float(inputs[c][0]) for c in m.inputs})
    env.update({f"T.{n}": T0[i] for i, n in enumerate(m.nodes)})
    P = [float(np.asarray(l.power.compile()(env))) for l in m.losses]
    np.testing.assert_allclose(traj.P[0], P, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# the loss rule of the discrete model: every loss law evaluated at the temperatures at the start
# of each step, whatever its form


def _expm_steps(model, inputs, dt, T0):
    """Independent discrete model: expm of the augmented matrix, losses from their laws at T_k."""
    names = list(model.inputs)
    N = len(inputs[names[0]])
    x, out = np.asarray(T0, float).copy(), [np.asarray(T0, float).copy()]
    n = len(x)
    for k in range(N - 1):
        asm = Assembly(model, model.nominal(), {c: float(inputs[c][k]) for c in names})
        A, W = asm.reduced()
        E = expm(augmented(A, W, asm.c, dt))
        x = E[:n, :n] @ x + E[:n, n:] @ np.concatenate([asm.U, asm.losses(x)])
        out.append(x.copy())
    return np.array(out)


@pytest.mark.parametrize(
    "law",
    [
        "0.01*speed_rpm",  # no temperature
        "20 * (1 + 4e-3 * (T.yoke - 20))",  # affine in T
        "20 * (1 + 2e-3 * (T.yoke - 20))**1.5",  # not affine
        "10 + max(T.yoke - 35, 0)",  # piecewise affine
        "20 * abs(T.yoke - 30) / 10",
        "20 + 20 * sign(T.yoke - 30)",  # a step: not affine, though its derivative is zero
    ],
)
def test_every_loss_law_is_evaluated_at_the_step_start(tiny_model, law):
    raw = tiny_raw()
    raw["losses"][1]["power"] = law
    m = build_model(raw, fname="law.yaml")
    N = 40
    inputs = {k: v for k, v in tiny_inputs(N=N, seed=31, hold=8).items() if k in m.inputs}
    T0 = np.array([40.0, 45.0, 38.0])
    T = Simulator(m, method="zoh").simulate(m.nominal(), inputs, 10.0, T0).T
    ref = _expm_steps(m, inputs, 10.0, T0)
    np.testing.assert_allclose(T, ref, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["zoh", "euler"])
def test_forcing_is_the_dense_derivative_applied(tiny_plus_model, method):
    """``Discrete.forcing`` applied to temperatures and inputs, one operating point per row (the
    Daleckii–Krein form row by row) and one for all rows (the dense derivative), equals
    ``dΦ_j T + dΓ_j w`` from the dense derivatives (checked against the Fréchet derivative of
    expm above), mapped to the modal basis."""
    m = tiny_plus_model
    inputs = tiny_inputs(N=40, seed=11, hold=1)
    K = 8  # operating points: the inputs of the first 8 samples
    op = {c: np.asarray(inputs[c], dtype=float)[:K] for c in m.inputs}
    assert len(np.unique(op["speed_rpm"])) > 1
    wrt = list(range(len(m.parameter_names)))
    d = discretise(Network(m).continuous(m.nominal(), op, K=K, wrt=wrt), 2.0, method, 0.05 if method == "euler" else None)
    rng = np.random.default_rng(3)
    ops = rng.integers(0, K, 25)
    T = rng.uniform(20.0, 120.0, (25, len(m.nodes)))
    w = rng.uniform(0.0, 50.0, (25, d.Gam.shape[2]))
    V, Vi = d.basis(ops)
    y = (Vi @ T[:, :, None])[:, :, 0] + (d.Ht[ops] @ w[:, :, None])[:, :, 0]
    v = (d.Yt[ops] @ w[:, :, None])[:, :, 0]
    X = V @ d.forcing(ops, y, v)
    dense = np.einsum("bjac,bc->baj", d.dPhi[ops], T) + np.einsum("bjac,bc->baj", d.dGam[ops], w)
    assert np.abs(dense).max() > 0
    np.testing.assert_allclose(X, dense, rtol=0, atol=1e-10 * np.abs(dense).max())
    o = int(ops[0])  # the same rows, all at one operating point
    same = ops == o
    np.testing.assert_allclose(V[same] @ d.forcing(o, y[same], v[same]), dense[same], rtol=0, atol=1e-10 * np.abs(dense).max())


def test_euler_at_a_spectral_radius_of_exactly_one_is_refused():
    """``h λ = -2`` to the last bit (1 node, G = 10 W/K, C = 5 J/K, h = 1 s): an undamped oscillation
    of ±(T0 − T_amb) forever; round-off may compute the radius a hair below 1. Refused, and a step a
    little shorter is not."""
    from thermal_edge.lptn.discretise import euler_substeps

    lam = np.array([-10.0 / 5.0 * (1.0 - 1e-16), -0.01])
    with pytest.raises(UnstableDiscretisation):
        euler_substeps(lam, 1.0, 1.0)
    with pytest.raises(UnstableDiscretisation):
        euler_substeps(np.array([-2.0 + 2e-12]), 1.0, 1.0)
    assert euler_substeps(np.array([-2.0]), 1.0, 0.99) == 2
    assert euler_substeps(np.array([-1.99, -1e-12]), 1.0, None) == 1  # slow modes near 1 are stable
    # without a sub-step limit: the fewest sub-steps that are stable (h |λ| ≤ 1.8) instead
    assert euler_substeps(lam, 1.0, None) == 2 and euler_substeps(np.array([-7.3]), 1.0, None) == 5
    with pytest.raises(UnstableDiscretisation, match="more than 1000 sub-steps"):
        euler_substeps(np.array([-5000.0]), 1.0, None)


def test_euler_without_a_substep_limit_substeps_a_step_it_cannot_take_at_once():
    """A step explicit Euler cannot take at once (the stiff model at 1 s) without ``max_substep_s``:
    as many equal sub-steps as make it stable, the same numbers as those sub-steps asked for."""
    from thermal_edge.lptn.discretise import euler_substeps

    m = build_model(stiff_raw(), fname="stiff.yaml")
    inputs = {k: np.full(20, v[0]) for k, v in tiny_inputs(N=20, seed=11).items() if k in m.inputs}
    k = euler_substeps(_eigs(m, inputs), 1.0, None)
    assert k > 1
    auto = Simulator(m, method="euler").simulate(m.nominal(), inputs, 1.0, np.full(4, 25.0)).T
    asked = Simulator(m, method="euler", max_substep=1.0 / k).simulate(m.nominal(), inputs, 1.0, np.full(4, 25.0)).T
    np.testing.assert_array_equal(auto, asked)
    assert np.all(np.isfinite(auto)) and np.abs(auto).max() < 1e3
