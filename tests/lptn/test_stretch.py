"""Stretches at one operating point run vectorised in time (``thermal_edge.lptn.stretch``).

References: the same recursion written as a plain loop here, the simulator's step-by-step path
(``vectorised=False``), and central finite differences of the simulation. Inputs vary every
sample (relative noise on the current, as in recorded data), so every stretch carries a
time-varying copper-loss feedback.
"""
from __future__ import annotations

import numpy as np
import pytest
from lptn_ref import pm10kw_inputs, tiny_inputs
from test_sensitivities import finite_difference_check

from thermal_edge.lptn import Simulator, simulate, stretch


def _loop(mu, f, x0, G, E, D):
    """The recursion step by step; ``f`` (n, c, L), the states (n, c, L)."""
    x, out = x0, []
    for k in range(f.shape[2]):
        x = mu[:, None] * x + f[:, :, k] + G @ (D[k] @ (E @ x))
        out.append(x)
    return np.stack(out, axis=2)


@pytest.mark.parametrize("L", [1, 5, 16, 17, 100, 333])
def test_modal_scan_is_the_recursion(L):
    rng = np.random.default_rng(L)
    n, c = 7, 3
    mu = np.concatenate([[0.0, 1e-200, 0.9999999], rng.uniform(0.0, 1.0, n - 3)])
    f, x0 = rng.standard_normal((n, c, L)), rng.standard_normal((n, c))
    ref = _loop(mu, f, x0, np.zeros((n, 1)), np.zeros((1, n)), np.zeros((L, 1, 1)))
    np.testing.assert_allclose(stretch.modal_scan(mu, f, x0), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("L", [3, 16, 50, 161])
def test_solve_stretch_with_time_varying_feedback(L):
    """Rank-2 feedback series (two currents), two loss nodes, rows picked by W: against the loop."""
    rng = np.random.default_rng(L)
    n, c, nl, ntv = 9, 4, 3, 2
    mu = rng.uniform(0.0, 0.999, n)
    f, x0 = rng.standard_normal((n, c, L)), rng.standard_normal((n, c))
    G, E = 0.1 * rng.standard_normal((n, nl)), rng.standard_normal((ntv, n))
    D = (rng.uniform(0.5, 1.5, (L, 1, 1)) * rng.standard_normal((1, nl, ntv))
         + rng.uniform(0.5, 1.5, (L, 1, 1)) ** 2 * rng.standard_normal((1, nl, ntv))) * 0.1
    W = rng.standard_normal((3, n))
    ref = _loop(mu, f, x0, G, E, D)
    rows, end = stretch.solve_stretch(mu, f, x0, G, E, D, W)
    want = np.tensordot(W, ref, axes=1)
    np.testing.assert_allclose(rows, want, rtol=0, atol=1e-11 * np.abs(want).max())
    np.testing.assert_allclose(end, ref[:, :, -1], rtol=0, atol=1e-11 * np.abs(ref).max())


@pytest.mark.parametrize("nr", [2, 6])
@pytest.mark.parametrize("L", [7, 16, 33, 160, 170])
def test_scan_rows_is_the_recursion_seen_through_rows(L, nr):
    """The rows of the padded scan and the end state, against the plain loop: a few rows (the
    block starts projected on their own) and as many rows as modes (projected with the blocks)."""
    rng = np.random.default_rng(L)
    n, c = 6, 3
    mu = np.concatenate([[1e-60, 0.99999], rng.uniform(0.0, 1.0, n - 2)])
    Lp = stretch.padded_length(L)
    f = np.zeros((n, c, Lp))
    f[:, :, :L] = rng.standard_normal((n, c, L))
    x0, R = rng.standard_normal((n, c)), rng.standard_normal((nr, n))
    ref = _loop(mu, f[:, :, :L], x0, np.zeros((n, 1)), np.zeros((1, n)), np.zeros((L, 1, 1)))
    rows, end = stretch.scan_rows(mu, f, x0, R, L)
    want = np.tensordot(R, ref, axes=1)
    np.testing.assert_allclose(rows.reshape(nr, c, Lp)[:, :, :L], want, rtol=0, atol=1e-12 * np.abs(want).max())
    np.testing.assert_allclose(end, ref[:, :, -1], rtol=0, atol=1e-12 * np.abs(ref).max())


def test_stretch_serves_several_forcings():
    """One set-up of the feedback, solved for two forcings (one padded, one not) and two sets of
    rows: each equals its own loop."""
    rng = np.random.default_rng(3)
    n, nl, ntv, L = 8, 2, 2, 45
    mu = rng.uniform(0.0, 0.999, n)
    G, E = 0.1 * rng.standard_normal((n, nl)), rng.standard_normal((ntv, n))
    D = rng.uniform(0.5, 1.5, (L, 1, 1)) * rng.standard_normal((1, nl, ntv)) * 0.1
    st = stretch.Stretch(mu, G, E, D)
    for c, pad, nr in [(1, True, n), (5, False, 2)]:
        f, x0, W = rng.standard_normal((n, c, L)), rng.standard_normal((n, c)), rng.standard_normal((nr, n))
        fp = np.concatenate([f, np.zeros((n, c, stretch.padded_length(L) - L))], axis=2) if pad else f
        ref = _loop(mu, f, x0, G, E, D)
        rows, end = st.solve(fp, x0, W)
        want = np.tensordot(W, ref, axes=1)
        np.testing.assert_allclose(rows, want, rtol=0, atol=1e-11 * np.abs(want).max())
        np.testing.assert_allclose(end, ref[:, :, -1], rtol=0, atol=1e-11 * np.abs(ref).max())


@pytest.mark.parametrize("c", [1, 3])
@pytest.mark.parametrize("nr", [2, 8])
def test_rank_one_feedback_with_steps_without_current(nr, c):
    """One current (rank one in time) that is zero on some steps, blocks among them entirely:
    the feedback's unknowns on those steps are exactly zero (1/s = inf on the block's diagonal);
    few rows and most of the state, one column (BLAS trsv) and several (trsm), against the loop."""
    rng = np.random.default_rng(nr)
    n, nl, ntv, L = 8, 3, 2, 70
    mu = rng.uniform(0.0, 0.999, n)
    G, E = 0.1 * rng.standard_normal((n, nl)), rng.standard_normal((ntv, n))
    i2 = rng.uniform(0.5, 1.5, L) ** 2
    i2[[0, 5, 6, 40]] = 0.0
    i2[16:32] = 0.0  # a whole block
    D = i2[:, None, None] * rng.standard_normal((1, nl, ntv)) * 0.1
    st = stretch.Stretch(mu, G, E, D)
    assert st.r == 1
    f, x0, W = rng.standard_normal((n, c, L)), rng.standard_normal((n, c)), rng.standard_normal((nr, n))
    ref = _loop(mu, f, x0, G, E, D)
    rows, end = st.solve(f, x0, W)
    assert np.all(np.isfinite(rows)) and np.all(np.isfinite(end))
    want = np.tensordot(W, ref, axes=1)
    np.testing.assert_allclose(rows, want, rtol=0, atol=1e-11 * np.abs(want).max())
    np.testing.assert_allclose(end, ref[:, :, -1], rtol=0, atol=1e-11 * np.abs(ref).max())


def test_live_entries_given_or_found():
    """The entries of D that can be nonzero, given (as the simulator does) or found by scanning
    D, give the same stretch; given entries that stay zero all along leave no feedback."""
    rng = np.random.default_rng(11)
    n, nl, ntv, L, c = 7, 3, 2, 40, 2
    mu = rng.uniform(0.0, 0.999, n)
    G, E = 0.1 * rng.standard_normal((n, nl)), rng.standard_normal((ntv, n))
    D = np.zeros((L, nl, ntv))
    D[:, 0, 1] = rng.uniform(0.5, 1.5, L) ** 2 * 0.1
    D[:, 2, 0] = D[:, 0, 1] * 0.3
    f, x0, W = rng.standard_normal((n, c, L)), rng.standard_normal((n, c)), rng.standard_normal((2, n))
    found = stretch.Stretch(mu, G, E, D).solve(f, x0, W)
    given = stretch.Stretch(mu, G, E, D, live=np.array([0 * ntv + 1, 2 * ntv + 0, 1 * ntv + 1])).solve(f, x0, W)
    np.testing.assert_allclose(given[0], found[0], rtol=0, atol=1e-13 * np.abs(found[0]).max())
    quiet = stretch.Stretch(mu, G, E, np.zeros((L, nl, ntv)), live=np.array([1]))
    assert quiet.r == 0
    ref = _loop(mu, f, x0, G, E, np.zeros((L, nl, ntv)))
    np.testing.assert_allclose(quiet.solve(f, x0, W)[0], np.tensordot(W, ref, axes=1), rtol=0,
                               atol=1e-12 * np.abs(ref).max())


def test_time_factors_rank_one_and_svd():
    """Proportional rows give one series without a decomposition, and it reproduces D; two
    independent series go through the SVD (rank two), reproducing D to round-off."""
    rng = np.random.default_rng(7)
    D1 = np.outer(rng.uniform(0.0, 2.0, 50), rng.standard_normal(6))
    s, Wt = stretch.time_factors(D1)
    assert s.shape == (50, 1)
    np.testing.assert_allclose(s @ Wt, D1, rtol=0, atol=1e-15 * np.abs(D1).max() * 10)
    D2 = D1 + np.outer(rng.uniform(0.0, 1.0, 50), rng.standard_normal(6))
    s, Wt = stretch.time_factors(D2)
    assert s.shape == (50, 2)
    np.testing.assert_allclose(s @ Wt, D2, rtol=0, atol=1e-14 * np.abs(D2).max())


def test_stretch_without_feedback_is_the_scan():
    """No loss feedback (no current): the stretch is the open-loop scan, against the loop."""
    rng = np.random.default_rng(4)
    n, c, L = 5, 2, 40
    mu = rng.uniform(0.0, 0.999, n)
    f, x0, W = rng.standard_normal((n, c, L)), rng.standard_normal((n, c)), rng.standard_normal((3, n))
    D = np.zeros((L, 2, 1))
    rows, end = stretch.solve_stretch(mu, f, x0, rng.standard_normal((n, 2)), rng.standard_normal((1, n)), D, W)
    ref = _loop(mu, f, x0, np.zeros((n, 2)), np.zeros((1, n)), D)
    np.testing.assert_allclose(rows, np.tensordot(W, ref, axes=1), rtol=0, atol=1e-12 * np.abs(ref).max() * 3)
    np.testing.assert_allclose(end, ref[:, :, -1], rtol=0, atol=1e-12 * np.abs(ref).max())


def test_powers_flush_below_round_off():
    """Powers of a fast mode that would be subnormal are zero (subnormals slow every product)."""
    pw = stretch.powers(np.array([1e-45, 0.5]), 16)
    assert pw[0, 7] == 0.0 and pw[0, 6] == pytest.approx(1e-270) and pw[1, 16] == 0.5 ** 16
    assert not np.any((pw > 0) & (pw < np.finfo(float).tiny))


def _noisy(inputs, seed=0, rel=1e-3):
    rng = np.random.default_rng(seed)
    out = dict(inputs)
    out["i_rms"] = np.asarray(inputs["i_rms"], float) * (1.0 + rel * rng.standard_normal(len(inputs["i_rms"])))
    return out


@pytest.fixture
def count_stretches(monkeypatch):
    """Steps run vectorised (the simulator's and the sensitivities' stretches alike)."""
    steps: list[int] = []
    real = stretch.Stretch.solve

    def counted(self, f, *a, **k):
        steps.append(f.shape[2])
        return real(self, f, *a, **k)

    monkeypatch.setattr(stretch.Stretch, "solve", counted)
    return steps


def _agree(model, inputs, dt, T0, wrt, rows, steps, vectorised=True):
    vec = Simulator(model).simulate(model.nominal(), inputs, dt, T0, wrt=wrt, rows=rows)
    n_vec = sum(steps)
    ref = Simulator(model, vectorised=False).simulate(model.nominal(), inputs, dt, T0, wrt=wrt, rows=rows)
    assert sum(steps) == n_vec  # the reference steps every sample
    N = len(vec.T)
    if vectorised:
        assert n_vec > N, (n_vec, N)  # most of the run vectorised, in the simulation and the sensitivities
    else:
        assert n_vec == 0
    assert np.abs(vec.T - ref.T).max() <= 1e-9 * np.abs(ref.T).max()
    for j, name in enumerate(wrt):
        scale = np.abs(ref.S[:, :, j]).max()
        assert np.abs(vec.S[:, :, j] - ref.S[:, :, j]).max() <= 1e-9 * scale, name


@pytest.mark.parametrize("rows", [None, "sensors"])
def test_pm10kw_noisy_current_equals_stepping(pm10kw_model, rows, count_stretches):
    """3000 s of the drive cycle with relative noise 1e-3 on the current, all 14 parameters."""
    from thermal_edge.lptn import steady_state

    m = pm10kw_model
    inputs, dt, _ = pm10kw_inputs(m, 3000.0)
    inputs = _noisy(inputs)
    T0, _ = steady_state(m, {k: float(v[0]) for k, v in inputs.items()})
    _agree(m, inputs, dt, T0, list(m.adaptable), list(m.sensors.values()) if rows else None, count_stretches)


def test_pm10kw_noisy_current_loss_parameters_equal_stepping(pm10kw_model, count_stretches):
    """As above with two losses' own parameters among those asked for: the stretches' forcing
    then carries ``Γ_P ∂P/∂θ`` as well."""
    from thermal_edge.lptn import steady_state

    m = pm10kw_model
    inputs, dt, _ = pm10kw_inputs(m, 1500.0)
    inputs = _noisy(inputs)
    T0, _ = steady_state(m, {k: float(v[0]) for k, v in inputs.items()})
    _agree(m, inputs, dt, T0, list(m.adaptable) + ["P_pm_ref", "P_fe_y_ref"], list(m.sensors.values()),
           count_stretches)


def test_paderborn4_equals_stepping(paderborn_model, paderborn_run, count_stretches):
    """Recorded data (run_a, 3000 rows: every input varies every sample), all parameters. The
    conductances of paderborn4 depend on the coolant temperature (a new operating point every
    sample) and one loss law is not affine in temperature: no stretch qualifies, and the default
    simulator must be exactly the stepped one."""
    m = paderborn_model
    run = paderborn_run.slice(0, 3000)
    inputs = {c: run.columns[c] for c in m.inputs}
    T0 = np.array([run.columns[s][0] for s in ("pm", "stator_yoke", "stator_tooth", "stator_winding")])
    _agree(m, inputs, run.dt, T0, list(m.parameter_names), None, count_stretches, vectorised=False)


def test_tiny_noisy_current_finite_differences(tiny_model, count_stretches):
    """Vectorised stretches against central finite differences (ZOH)."""
    inputs = _noisy(tiny_inputs(N=401, seed=5, hold=100), seed=2, rel=1e-2)
    inputs = {k: inputs[k] for k in tiny_model.inputs}
    finite_difference_check(tiny_model, inputs, 10.0, np.array([45.0, 60.0, 35.0]), tiny_model.parameter_names, "zoh")
    assert sum(count_stretches) > 400


def test_held_inputs_are_stepped(pm10kw_model, count_stretches):
    """Held inputs keep the step-by-step recursion (cheaper there): nothing is vectorised."""
    m = pm10kw_model
    inputs, dt, _ = pm10kw_inputs(m, 900.0)
    Simulator(m).simulate(m.nominal(), inputs, dt, np.full(len(m.nodes), 40.0))
    assert count_stretches == []
    assert simulate.stretches is stretch.stretches


def test_stretch_forcing_against_dense_derivatives(pm10kw_model, monkeypatch):
    """The sensitivities' forcing of a stretch (mode-major product, the edges per parameter,
    padded in time, the simulation's modal temperatures) against ``V⁻¹ (dΦ T + dΓ w + Γ_P ∂P/∂θ)``
    from the dense node-coordinate derivatives, step by step."""
    from thermal_edge.lptn import sensitivity, steady_state

    m = pm10kw_model
    inputs, dt, _ = pm10kw_inputs(m, 1200.0)
    inputs = _noisy(inputs)
    T0, _ = steady_state(m, {k: float(v[0]) for k, v in inputs.items()})
    seen = []
    real = sensitivity.Sensitivities.stretch_forcing

    def spy(self, o, T, w, dP, Lp=None, out=None, modal=None):
        X = real(self, o, T, w, dP, Lp, out, modal)
        seen.append((self, o, T, w, dP, Lp, X.copy(), modal))  # X is scratch memory, reused by the next stretch
        return X

    monkeypatch.setattr(sensitivity.Sensitivities, "stretch_forcing", spy)
    wrt = list(m.adaptable) + ["P_pm_ref", "P_fe_y_ref"]  # two losses' own parameters too
    Simulator(m).simulate(m.nominal(), inputs, dt, T0, wrt=wrt)
    assert seen
    self, o, T, w, dP, Lp, X, modal = seen[0]
    d = self.d
    _, Vi = d.basis(o)
    # the simulation's own modal temperatures of the stretch serve the forcing: they are V⁻¹ T
    assert modal is not None
    np.testing.assert_allclose(modal, Vi @ T.T, rtol=0, atol=1e-12 * np.abs(modal).max())
    nb = self.nb
    ref = np.einsum("jab,kb->ajk", d.dPhi[o], T) + np.einsum("jam,km->ajk", d.dGam[o], w)
    ref += np.einsum("al,klj->ajk", d.Gam[o][:, nb:], dP)
    ref = np.einsum("ca,ajk->cjk", Vi, ref)
    B = len(T)
    assert X.shape == (len(Vi), len(wrt), Lp) and Lp >= B and np.any(dP)
    np.testing.assert_allclose(X[:, :, :B], ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    assert not np.any(X[:, :, B:])
