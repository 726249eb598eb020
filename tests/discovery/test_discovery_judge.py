"""The judgement of a verdict: winner against runner-up with the uncertainty of the held-out gap,
the operating region the training part lacks, and "no gap" against "a gap nothing explains".

Fits here are predictions written by hand (the comparison reads only predictions and readings),
and every expected figure is computed again in the test from its definition.
"""
from __future__ import annotations

import math

import numpy as np

from thermal_edge.data import Run
from thermal_edge.discovery import fitting as F
from thermal_edge.discovery import judge as J
from thermal_edge.discovery import residuals as R
from thermal_edge.lptn import DEFAULT_COLUMNS, Role

N, SPLIT = 3000, 2000
SENSORS = ["a", "b"]
# data without a model: the default column names, each input's role
ROLES = {r: DEFAULT_COLUMNS[r] for r in (Role.SPEED, Role.CURRENT, Role.AMBIENT)}
BOUNDARIES = {"ambient": ROLES[Role.AMBIENT]}


def _data(speed: np.ndarray | None = None) -> F.Data:
    rng = np.random.default_rng(0)
    t = np.arange(N, dtype=float)
    cols = {s: 40.0 + rng.normal(0, 0.1, N) for s in SENSORS}
    cols[ROLES[Role.SPEED]] = np.full(N, 1000.0) if speed is None else speed
    cols[ROLES[Role.CURRENT]] = np.full(N, 20.0)
    cols[ROLES[Role.AMBIENT]] = np.full(N, 25.0)
    return F.Data(Run(t, cols, "hand"), list(SENSORS), SPLIT, 5, {"n_ref": 1000.0, "i_ref": 20.0}, dict(ROLES))


def _fit(label: str, data: F.Data, err: np.ndarray) -> F.Fit:
    """A fit whose prediction is the reading plus ``err`` (N, ns)."""
    Y = np.column_stack([data.run.columns[s] for s in SENSORS])
    f = F.Fit(label, {}, None, np.zeros(0), ())
    f.traj_T = Y + err
    f.heldout_mse = {s: float(np.mean(err[SPLIT:, j] ** 2)) for j, s in enumerate(SENSORS)}
    return f


def _by_hand_se(ea: np.ndarray, eb: np.ndarray) -> float:
    """Standard error of gap_b - gap_a from 10 block means of the per-sample loss difference."""
    la, lb = np.mean(ea[SPLIT:] ** 2, axis=1), np.mean(eb[SPLIT:] ** 2, axis=1)
    blocks = (lb - la).reshape(J.N_BLOCKS, -1).mean(axis=1)
    return float(blocks.std(ddof=1) / math.sqrt(J.N_BLOCKS) / (math.sqrt(la.mean()) + math.sqrt(lb.mean())))


def test_close_fits_are_confusable_and_far_ones_are_not():
    data = _data()
    rng = np.random.default_rng(1)
    t = np.arange(N)[:, None]
    slow = 0.3 * np.sin(2 * np.pi * t / 700.0) * np.ones((1, 2))  # correlated over minutes, like thermal residuals
    ea = slow + rng.normal(0, 0.05, (N, 2))
    eb = slow + rng.normal(0, 0.05, (N, 2))  # the same slow error, other noise: confusable
    ec = 3.0 * slow + rng.normal(0, 0.05, (N, 2))  # clearly worse
    a, b, c = _fit("A", data, ea), _fit("B", data, eb), _fit("C", data, ec)
    ref = 1.0  # the refit's held-out gap, K
    ab = J.compare(a, b, ref, data)
    assert ab.ambiguous
    assert math.isclose(ab.se_diff, _by_hand_se(ea, eb), rel_tol=1e-9)
    assert math.isclose(ab.share, (ref - b.gap) / (ref - a.gap), rel_tol=1e-12)
    ac = J.compare(a, c, ref, data)
    assert not ac.ambiguous and ac.z > J.Z_SEPARATE and ac.share < J.CLOSE_SHARE


def test_held_out_data_from_a_new_region_decides():
    """The last 500 held-out samples run at a speed the training part never saw; there the
    runner-up is clearly worse, and that decides a pair the whole held-out part cannot."""
    speed = np.full(N, 1000.0)
    speed[-500:] = 1500.0
    data = _data(speed)
    mask, desc = J.novel_region(data, BOUNDARIES)
    assert mask.sum() == 500 and mask[-500:].all() and "speed (rpm) above 1000" in desc
    rng = np.random.default_rng(2)
    ea = rng.normal(0, 0.2, (N, 2))
    eb = ea.copy()
    eb[-500:] += 0.15  # worse only at the new speed
    eb[SPLIT:-500] *= 0.8  # better elsewhere: over the whole held-out part the two are level
    a, b = _fit("A", data, ea), _fit("B", data, eb)
    cmp = J.compare(a, b, 1.0, data)
    assert cmp.ambiguous
    cmp = J.decide_novel(cmp, a, b, data, BOUNDARIES)
    assert not cmp.ambiguous and not cmp.swapped and "speed" in cmp.decided_by
    assert math.isclose(cmp.novel_gap_b, math.sqrt(np.mean(eb[-500:] ** 2)), rel_tol=1e-12)
    # the other way round: the runner-up wins there, so the pair is swapped
    cmp2 = J.decide_novel(J.compare(b, a, 1.0, data), b, a, data, BOUNDARIES)
    assert cmp2.swapped


def test_no_gap_and_an_unexplained_gap_are_told_apart():
    data = _data()
    noise = 0.1
    resid = np.random.default_rng(3).normal(0, noise, (N, 2))
    an = R.analyse(data.run, SENSORS, np.column_stack([data.run.columns[s] for s in SENSORS]) + resid, SPLIT,
                   BOUNDARIES, data.refs, data.roles)
    t_h = np.arange(N - SPLIT) / 3600.0
    st = J.gap_status(0.12, noise, 0.05, False, resid[SPLIT:], t_h, an.sensors, [])
    assert st.status == "none" and st.threshold_k == J.NO_GAP_FACTOR * noise + 0.05
    # a bump of 2 K over 100 samples in the held-out part: a gap, located in time
    bumped = resid.copy()
    bumped[2400:2500, 1] += 2.0
    gap = float(np.sqrt(np.mean(bumped[SPLIT:] ** 2)))
    an = R.analyse(data.run, SENSORS, np.column_stack([data.run.columns[s] for s in SENSORS]) + bumped, SPLIT,
                   BOUNDARIES, data.refs, data.roles)
    st = J.gap_status(gap, noise, 0.05, False, bumped[SPLIT:], t_h, an.sensors, [("x", 0.5, 0.01)])
    assert st.status == "unexplained" and st.worst_sensor == "b"
    assert math.isclose(st.ratio, gap / noise)
    h0, h1 = (float(x) for x in st.when.split(" h")[0].split("–"))
    assert h0 * 3600 <= 400 <= h1 * 3600 + 1  # the window covers the bump (held-out samples 400-500)
    assert st.nearest == [("x", 0.5, 0.01)]
    assert J.gap_status(gap, noise, 0.05, True, bumped[SPLIT:], t_h, an.sensors, []).status == "partly explained"
