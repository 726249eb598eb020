"""Derating policy and look-ahead against independent computations."""
from __future__ import annotations

import math

import numpy as np
import pytest

from thermal_edge.bus import DerateReason
from thermal_edge.config import DeratingConfig
from thermal_edge.lptn import Stepper, steady_state
from thermal_edge.service.derating import DeratingPolicy, NodeBand
from thermal_edge.service.lookahead import Lookahead

W, M = DerateReason.WINDING, DerateReason.MAGNET


def policy(**kw) -> DeratingPolicy:
    cfg = DeratingConfig(max_current_a=40.0, max_torque_nm=220.0, safe_current_a=10.0, **kw)
    p = DeratingPolicy(cfg, kt_nm_per_arms=5.6, tick_s=1.0)
    p.current, p.reason = 40.0, DerateReason.NONE  # running at full current
    return p


def bands(hot_upper: float, mag_upper: float) -> list[NodeBand]:
    return [NodeBand("hot_spot", hot_upper - 2, hot_upper, 140.0, 155.0, W),
            NodeBand("magnet", mag_upper - 2, mag_upper, 100.0, 120.0, M)]


def test_linear_band_derate_on_the_upper_band():
    p = policy()
    for hot in (130.0, 140.0, 143.0, 147.5, 154.0, 155.0, 170.0):
        p = policy()
        lim = p.update(bands(hot, 50.0), None)
        expected = 40.0 * min(1.0, max(0.0, (155.0 - hot) / 15.0))
        assert lim.current_a == pytest.approx(expected)
        assert lim.torque_nm == pytest.approx(min(220.0, 5.6 * expected))
        assert lim.reason == (W if expected < 40.0 else DerateReason.NONE)
        assert lim.active == (expected < 40.0)
    # the magnet binds when it is relatively closer to its maximum
    lim = policy().update(bands(145.0, 112.0), None)
    assert lim.reason == M and lim.current_a == pytest.approx(40.0 * 8.0 / 20.0)


def test_lookahead_binds_when_lower():
    lim = policy().update(bands(142.0, 50.0), 25.0)
    assert lim.current_a == 25.0 and lim.reason == DerateReason.LOOK_AHEAD


def test_limits_fall_at_once_and_rise_slowly_with_hysteresis():
    p = policy(rise_rate_a_per_s=0.5, hysteresis_a=1.0)
    assert p.update(bands(150.0, 50.0), None).current_a == pytest.approx(40 / 3)  # falls at once
    # cooler: the candidate is 40 A again; the limit climbs 0.5 A per tick
    seq = [p.update(bands(130.0, 50.0), None).current_a for _ in range(4)]
    assert seq == pytest.approx([40 / 3 + 0.5 * k for k in range(1, 5)])
    assert p.last.reason == W  # still derated by what caused it
    # a candidate within the hysteresis does not move the limit up
    p2 = policy(rise_rate_a_per_s=0.5, hysteresis_a=1.0)
    p2.update(bands(149.0, 50.0), None)
    held = p2.last.current_a
    assert p2.update(bands(148.9, 50.0), None).current_a == held
    # it reaches the full current and the reason clears
    for _ in range(200):
        lim = p.update(bands(130.0, 50.0), None)
    assert lim.current_a == 40.0 and lim.reason == DerateReason.NONE and not lim.active


def test_forced_safe_limit_and_precedence():
    for forced, reason in (([DerateReason.STALE_INPUT], DerateReason.STALE_INPUT),
                           ([DerateReason.SENSOR_FAULT, DerateReason.STALE_INPUT], DerateReason.STALE_INPUT),
                           ([DerateReason.SENSOR_FAULT, DerateReason.MODEL_FAULT], DerateReason.MODEL_FAULT)):
        lim = policy().update(bands(120.0, 50.0), None, forced)
        assert lim.current_a == 10.0 and lim.torque_nm == pytest.approx(56.0) and lim.reason == reason and lim.active
    # a hotter machine keeps the lower thermal limit under a forced one
    lim = policy().update(bands(153.5, 50.0), None, [DerateReason.SENSOR_FAULT])
    assert lim.current_a == pytest.approx(4.0) and lim.reason == DerateReason.SENSOR_FAULT
    # non-finite band -> zero factor, model fault
    lim = policy().update([NodeBand("hot_spot", math.nan, math.nan, 140, 155, W)], None)
    assert lim.current_a == 0.0


# ---------------------------------------------------------------------------------------------
def test_lookahead_current_is_the_largest_that_keeps_every_limit(model):
    """The affine solve against an independent fine-step simulation of the same conservative
    losses (1 s steps instead of the look-ahead's 30 s checkpoints)."""
    limits = [(lim.name, model.node_index(lim.node), lim.max_c) for lim in model.limits]
    la = Lookahead(model, model.nominal(), limits, horizon_s=1800.0, steps=60)
    u = {"speed_rpm": 900.0, "i_rms": 19.0, "torque_nm": 106.0, "ambient_c": 25.0}
    T0, _ = steady_state(model, {**u, "i_rms": 15.0})  # warm start
    T0 = T0 + 3.0  # an upper band
    r = la.compute(T0, u)
    assert 0 < r.current_a < 60

    fine = Stepper(model, model.nominal(), 1.0)
    Phi, Gam = fine.matrices(u)
    nb = len(model.boundaries)
    T_eval = np.full(len(T0), la.loss_T)

    def peak(i: float) -> float:
        P = fine.losses(T_eval, {**u, "i_rms": i})
        f = Gam[:, :nb] @ fine.boundary(u) + Gam[:, nb:] @ P
        x, worst = T0.copy(), -np.inf
        for k in range(1, 1801):
            x = Phi @ x + f
            if k % 30 == 0:  # the checkpoints
                worst = max(worst, max(x[i] - m for _, i, m in limits))
        return worst

    assert peak(r.current_a) == pytest.approx(0.0, abs=1e-6)  # touches a limit exactly
    assert peak(r.current_a * 1.01) > 0 and peak(r.current_a * 0.99) < 0


def test_time_to_limit_at_the_present_load(model):
    limits = [(lim.name, model.node_index(lim.node), lim.max_c) for lim in model.limits]
    la = Lookahead(model, model.nominal(), limits, horizon_s=3600.0, steps=120)
    u = {"speed_rpm": 900.0, "i_rms": 30.0, "torque_nm": 168.0, "ambient_c": 25.0}
    T0, _ = steady_state(model, {**u, "i_rms": 19.0})
    r = la.compute(T0, u)
    # independent: 1 s simulation with the same conservative losses, first crossing
    fine = Stepper(model, model.nominal(), 1.0)
    Phi, Gam = fine.matrices(u)
    nb = len(model.boundaries)
    P = fine.losses(np.full(len(T0), la.loss_T), u)
    f = Gam[:, :nb] @ fine.boundary(u) + Gam[:, nb:] @ P
    x, t_hit = T0.copy(), None
    for k in range(1, 3601):
        x = Phi @ x + f
        if any(x[i] >= m for _, i, m in limits):
            t_hit = k
            break
    assert t_hit is not None and r.time_to_limit_s == pytest.approx(t_hit, abs=3.0)
    # light load: not within the horizon
    assert la.compute(T0, {**u, "i_rms": 5.0}).time_to_limit_s == math.inf


def test_lookahead_is_conservative_against_the_real_temperature_dependent_losses(model):
    """Holding the look-ahead current, the true (temperature-dependent) plant stays below every limit."""
    limits = [(lim.name, model.node_index(lim.node), lim.max_c) for lim in model.limits]
    la = Lookahead(model, model.nominal(), limits, horizon_s=1800.0, steps=60)
    u = {"speed_rpm": 600.0, "i_rms": 10.0, "torque_nm": 56.0, "ambient_c": 30.0}
    T0, _ = steady_state(model, u)
    i = la.compute(T0, u).current_a
    st = Stepper(model, model.nominal(), 1.0)
    x = T0.copy()
    worst = -np.inf
    for _ in range(1800):
        x, _ = st.step(x, {**u, "i_rms": i})
        worst = max(worst, max(x[k] - m for _, k, m in limits))
    assert worst < 0
