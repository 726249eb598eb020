"""Per-step transition matrices computed a block at a time (``thermal_edge.lptn.transitions``).

Inputs that change every sample (relative noise 1e-3 on speed and current, the speed rounded to
1 rpm, as a drive reports them) give a distinct transition matrix per step. References: the same
run with every matrix in one block (what holding them all gives), and the tracemalloc peak of
the same run length with held inputs (the run's own arrays, without per-step matrices).
"""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from lptn_ref import pm10kw_inputs

from thermal_edge.lptn import Simulator, steady_state, transitions


def _noisy_drive(model, duration_s, seed=0):
    inputs, dt, _ = pm10kw_inputs(model, duration_s)
    rng = np.random.default_rng(seed)
    out = dict(inputs)
    for c in ("speed_rpm", "i_rms"):
        out[c] = np.asarray(inputs[c], float) * (1.0 + 1e-3 * rng.standard_normal(len(inputs[c])))
    out["speed_rpm"] = np.round(out["speed_rpm"])
    T0, _ = steady_state(model, {k: float(v[0]) for k, v in inputs.items()})
    return inputs, out, dt, T0


def _peak(fn):
    tracemalloc.start()
    try:
        result = fn()
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_3h_noisy_run_memory_is_bounded_by_the_block(pm10kw_model, monkeypatch):
    m = pm10kw_model
    held, noisy, dt, T0 = _noisy_drive(m, 10800.0)
    sim = Simulator(m)
    n, steps = len(m.nodes), len(noisy["i_rms"]) - 1
    _, peak_held = _peak(lambda: sim.simulate(m.nominal(), held, dt, T0))
    blocked, peak = _peak(lambda: sim.simulate(m.nominal(), noisy, dt, T0))
    # the run's own arrays (the held run's peak), the block of matrices and its temporaries
    # (three blocks' worth), and 8 MB for what noise adds besides (more operating points)
    block = transitions.CHUNK * n * n * 8
    bound = peak_held + 3 * block + 8e6
    per_step = steps * n * n * 8  # every step's matrix held at once
    assert bound < peak_held + per_step / 2  # the bound tells the two apart
    assert peak < bound, (peak / 1e6, bound / 1e6, peak_held / 1e6)
    monkeypatch.setattr(transitions, "CHUNK", steps + 1)  # every matrix in one block
    one = Simulator(m).simulate(m.nominal(), noisy, dt, T0)
    assert np.abs(blocked.T - one.T).max() <= 1e-12 * np.abs(one.T).max()


@pytest.mark.parametrize("chunk", [1, 7])
def test_sensitivities_do_not_depend_on_the_block(pm10kw_model, monkeypatch, chunk):
    """Blocks far shorter than the sensitivities' forcing blocks: every boundary crossed."""
    m = pm10kw_model
    _, noisy, dt, T0 = _noisy_drive(m, 1500.0, seed=1)
    wrt, rows = list(m.adaptable), list(m.sensors.values())
    monkeypatch.setattr(transitions, "CHUNK", len(noisy["i_rms"]))
    one = Simulator(m).simulate(m.nominal(), noisy, dt, T0, wrt=wrt, rows=rows)
    monkeypatch.setattr(transitions, "CHUNK", chunk)
    blocked = Simulator(m).simulate(m.nominal(), noisy, dt, T0, wrt=wrt, rows=rows)
    assert np.abs(blocked.T - one.T).max() <= 1e-12 * np.abs(one.T).max()
    for j, name in enumerate(wrt):
        scale = np.abs(one.S[:, :, j]).max()
        assert np.abs(blocked.S[:, :, j] - one.S[:, :, j]).max() <= 1e-12 * scale, name


def test_without_feedback_each_operating_point_has_its_matrix():
    Phi = np.arange(3 * 4, dtype=float).reshape(3, 2, 2)
    ops = np.array([2, 0, 0, 1])
    sm = transitions.StepMatrices(Phi, np.zeros((3, 2, 1)), np.array([0]), ops, np.zeros((4, 1, 1)))
    assert [sm.matrix(k).tolist() for k in range(4)] == [Phi[o].tolist() for o in ops]


def test_blocks_give_every_step_its_matrix():
    """Against the matrices computed directly, step by step, for several block sizes."""
    rng = np.random.default_rng(2)
    K, n, nl, steps = 3, 4, 2, 23
    Phi, GP = rng.random((K, n, n)), rng.random((K, n, nl))
    tv = np.array([1, 3])
    ops = rng.integers(0, K, steps)
    dPdT = np.repeat(rng.random((8, nl, len(tv))), 3, axis=0)[:steps]  # held over 3 steps
    need = rng.random(steps) < 0.8
    for chunk in (1, 2, 5, 100):
        sm = transitions.StepMatrices(Phi, GP, tv, ops, dPdT, need, chunk=chunk)
        seen = {}
        edges = np.flatnonzero(np.diff(np.concatenate([[0], need.astype(int), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):  # the runs of needed steps
            for lo, hi, mats, local in sm.segments(int(a), int(b)):
                for k in range(lo, hi):
                    seen[k] = mats[local[k]]
        assert sorted(seen) == np.nonzero(need)[0].tolist()
        for k, M in seen.items():
            ref = Phi[ops[k]].copy()
            ref[:, tv] += GP[ops[k]] @ dPdT[k]
            assert np.allclose(M, ref, rtol=1e-14, atol=0.0)
            assert np.array_equal(sm.matrix(k), M)
        with pytest.raises(IndexError):
            sm.matrix(int(np.nonzero(~need)[0][0]))
