"""Runs that visit many operating points are simulated in time chunks (``thermal_edge.lptn.simulate``).

A speed that sweeps (a new operating point every step) between a held set point with a noisy
current (a stretch run vectorised in time) and a held one (closed form): chunked with at most a
few dozen operating points discretised at once, against the same run in one piece and against
the step-by-step reference. The operating points alive at once are counted (the discretisations
not yet freed when the next one is made), not timed.
"""
from __future__ import annotations

import gc
import weakref

import numpy as np
import pytest
from lptn_ref import pm10kw_inputs

from thermal_edge.lptn import Simulator, simulate, steady_state

LIMIT = 40


def _assert_sensitivities_close(S, ref, wrt, rel=1e-9):
    """Each parameter's sensitivities within ``rel`` of that parameter's largest reference entry."""
    for j, name in enumerate(wrt):
        assert np.abs(S[:, :, j] - ref[:, :, j]).max() <= rel * np.abs(ref[:, :, j]).max(), name


def _sweep_run(model):
    inputs, dt, _ = pm10kw_inputs(model, 1000.0)
    N = len(inputs["i_rms"])
    rng = np.random.default_rng(3)
    out = {k: np.asarray(v, float).copy() for k, v in inputs.items()}
    out["i_rms"][:300] = 40.0 * (1.0 + 1e-3 * rng.standard_normal(300))  # noisy current at a held speed
    out["i_rms"][600:800] = 30.0  # held current and speed: a held run
    speed = np.empty(N)
    speed[:300] = 1500.0
    speed[300:600] = np.linspace(1500.0, 2500.0, 300).round(1)  # a new operating point every step
    speed[600:800] = 2500.0
    speed[800:] = np.linspace(2500.0, 900.0, N - 800).round(1)
    out["speed_rpm"] = speed
    out["torque_nm"] = out["i_rms"] * model.drive["kt_nm_per_arms"]
    T0, _ = steady_state(model, {k: float(v[0]) for k, v in out.items()})
    return out, dt, T0


@pytest.fixture
def live_points(monkeypatch):
    """The operating points of the discretisations alive at each new discretisation."""
    alive: list = []
    counts: list[int] = []
    real = simulate.discretise

    def counted(cont, *a, **k):
        gc.collect()
        counts.append(sum(K for ref, K in alive if ref() is not None) + cont.A.shape[0])
        d = real(cont, *a, **k)
        alive.append((weakref.ref(d), cont.A.shape[0]))
        return d

    monkeypatch.setattr(simulate, "discretise", counted)
    return counts


@pytest.mark.parametrize("rows", [None, "sensors"])
def test_chunked_run_equals_one_piece(pm10kw_model, rows, live_points, monkeypatch):
    m = pm10kw_model
    inputs, dt, T0 = _sweep_run(m)
    wrt, keep = list(m.adaptable), (list(m.sensors.values()) if rows else None)
    visits = len(np.unique(inputs["speed_rpm"][:-1]))
    assert visits > 10 * LIMIT
    monkeypatch.setattr(simulate, "MAX_OPERATING_POINTS", 10**9)
    whole = Simulator(m).simulate(m.nominal(), inputs, dt, T0, wrt=wrt, rows=keep)
    assert live_points == [visits]  # one piece: every operating point at once
    live_points.clear()
    monkeypatch.setattr(simulate, "MAX_OPERATING_POINTS", LIMIT)
    chunked = Simulator(m).simulate(m.nominal(), inputs, dt, T0, wrt=wrt, rows=keep)
    assert len(live_points) >= visits // LIMIT  # in chunks ...
    assert max(live_points) <= LIMIT  # ... with at most LIMIT operating points alive at once
    assert chunked.T.shape == whole.T.shape and chunked.S.shape == whole.S.shape
    assert np.abs(chunked.T - whole.T).max() <= 1e-12 * np.abs(whole.T).max()
    np.testing.assert_allclose(chunked.P, whole.P, rtol=1e-12)
    _assert_sensitivities_close(chunked.S, whole.S, wrt)


def test_chunked_run_equals_stepping(pm10kw_model, monkeypatch):
    """The chunked run against the step-by-step reference (no closed form, nothing vectorised)."""
    m = pm10kw_model
    inputs, dt, T0 = _sweep_run(m)
    wrt = list(m.adaptable)
    monkeypatch.setattr(simulate, "MAX_OPERATING_POINTS", LIMIT)
    chunked = Simulator(m).simulate(m.nominal(), inputs, dt, T0, wrt=wrt)
    monkeypatch.setattr(simulate, "MAX_OPERATING_POINTS", 10**9)
    ref = Simulator(m, closed_form=False, vectorised=False).simulate(m.nominal(), inputs, dt, T0, wrt=wrt)
    assert np.abs(chunked.T - ref.T).max() <= 1e-9 * np.abs(ref.T).max()
    _assert_sensitivities_close(chunked.S, ref.S, wrt)


def test_chunks_share_their_end_samples(pm10kw_model, monkeypatch):
    """The chunks cover every step once, each with at most the limit of operating points."""
    m = pm10kw_model
    inputs, _, _ = _sweep_run(m)
    monkeypatch.setattr(simulate, "MAX_OPERATING_POINTS", LIMIT)
    sim = Simulator(m)
    N = len(inputs["i_rms"])
    chunks = sim._chunks(sim._grouped(m.nominal(), inputs).ops, N)
    assert chunks[0][0] == 0 and chunks[-1][1] == N - 1
    assert all(b == a2 for (_, b), (a2, _) in zip(chunks[:-1], chunks[1:]))
    speed = inputs["speed_rpm"]
    assert all(len(np.unique(speed[a:b])) <= LIMIT for a, b in chunks)
    assert all(len(np.unique(speed[a:b + 1])) > LIMIT for a, b in chunks[:-1])  # each as long as it may be


def test_held_runs_do_not_depend_on_later_samples(pm10kw_model):
    """The simulation up to a sample is the same to the last bit whatever the inputs after it:
    the same drive cycle with its ambient temperature changed after t* (which cuts a held run
    short), and cut off at t*."""
    m = pm10kw_model
    inputs, dt, _ = pm10kw_inputs(m, 3000.0)
    T0, _ = steady_state(m, {k: float(v[0]) for k, v in inputs.items()})
    sim = Simulator(m)
    whole = sim.simulate(m.nominal(), inputs, dt, T0).T
    for k in (1000, 1234, 2017):
        later = {c: v.copy() for c, v in inputs.items()}
        later["ambient_c"][k + 1:] += 15.0
        changed = sim.simulate(m.nominal(), later, dt, T0).T
        cut = sim.simulate(m.nominal(), {c: v[: k + 1] for c, v in inputs.items()}, dt, T0).T
        np.testing.assert_array_equal(changed[: k + 1], whole[: k + 1])
        np.testing.assert_array_equal(cut, whole[: k + 1])
        assert np.abs(changed[k + 2:] - whole[k + 2:]).max() > 1.0  # the change is seen after t*
