"""Derating policy and look-ahead against independent computations."""
from __future__ import annotations

import math

import numpy as np
import pytest

from thermal_edge.bus import DerateReason
from thermal_edge.config import DeratingConfig
from thermal_edge.lptn import Stepper, steady_state
from thermal_edge.service.derating import FLOOR_TICKS, DeratingPolicy, LimitSpec, MeasuredFloor, NodeBand
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


def test_full_current_while_the_reaction_current_allows_it():
    """The reaction-time current at or above the maximum: full current, no reason, whatever the
    temperature (a hot machine that can still take 40 A for the reaction time gets it)."""
    for react in (40.0, 55.0, math.inf):
        lim = policy().update(bands(150.0, 110.0), (react, W))
        assert lim.current_a == 40.0 and lim.torque_nm == 220.0
        assert lim.reason == DerateReason.NONE and not lim.active


def test_reaction_current_binds_with_the_node_that_sets_it():
    lim = policy().update(bands(146.0, 50.0), (25.0, W))
    assert lim.current_a == 25.0 and lim.torque_nm == pytest.approx(5.6 * 25.0)
    assert lim.reason == W and lim.active
    lim = policy().update(bands(120.0, 110.0), (12.5, M))
    assert lim.current_a == 12.5 and lim.reason == M
    # at or past the max: zero
    assert policy().update(bands(156.0, 50.0), (0.0, W)).current_a == 0.0


def test_approach_falls_linearly_below_max_less_the_margin():
    """Full current up to (max - margin - approach) on the upper band, zero at (max - margin), linear
    between (margin 1.5 K, approach 3 K: 150.5-153.5 degC for the hot spot, 115.5-118.5 for the magnet)."""
    for hot in (140.0, 150.5, 151.0, 152.0, 153.0, 153.5, 154.0, 160.0):
        lim = policy().update(bands(hot, 50.0), (math.inf, W))
        expected = 40.0 * min(1.0, max(0.0, (155.0 - 1.5 - hot) / 3.0))
        assert lim.current_a == pytest.approx(expected)
        assert lim.reason == (W if expected < 40.0 else DerateReason.NONE)
    lim = policy().update(bands(151.0, 117.0), (math.inf, W))
    assert lim.reason == M and lim.current_a == pytest.approx(40.0 * 1.5 / 3.0)  # the magnet is closer
    lim = policy(margin_k=0.0, approach_k=5.0).update(bands(152.0, 50.0), (math.inf, W))
    assert lim.current_a == pytest.approx(40.0 * 3.0 / 5.0)


def test_a_band_with_a_margin_of_its_own_ends_its_approach_there():
    """A node band that carries its own margin (the magnet while the voltages observe it, 0.5 K)
    approaches max - 0.5 K; the other bands keep derating.margin_k (1.5 K)."""
    for mag in (112.0, 116.0, 117.5, 118.5, 119.0, 119.6):
        own = [NodeBand("hot_spot", 98.0, 100.0, 140.0, 155.0, W),
               NodeBand("magnet", mag - 1, mag, 100.0, 120.0, M, margin_k=0.5)]
        lim = policy().update(own, (math.inf, M))
        assert lim.current_a == pytest.approx(40.0 * min(1.0, max(0.0, (120.0 - 0.5 - mag) / 3.0)))
    hot_own = [NodeBand("hot_spot", 150.0, 152.0, 140.0, 155.0, W), NodeBand("magnet", 50.0, 52.0, 100.0, 120.0, M, margin_k=0.5)]
    assert policy().update(hot_own, (math.inf, W)).current_a == pytest.approx(40.0 * (155.0 - 1.5 - 152.0) / 3.0)


def test_limits_fall_at_once_and_rise_slowly_with_hysteresis_reason_recovering():
    p = policy(rise_rate_a_per_s=0.5, hysteresis_a=1.0)
    assert p.update(bands(150.0, 50.0), (20.0, W)).current_a == 20.0  # falls at once
    # cooler: the candidate is the maximum again; the limit climbs 0.5 A per tick, reason recovering
    seq = [p.update(bands(130.0, 50.0), (60.0, W)) for _ in range(4)]
    assert [x.current_a for x in seq] == pytest.approx([20.0 + 0.5 * k for k in range(1, 5)])
    assert all(x.reason == DerateReason.RECOVERING and x.active for x in seq)
    # a candidate within the hysteresis does not move the limit up; the binding node is the reason
    p2 = policy(rise_rate_a_per_s=0.5, hysteresis_a=1.0)
    p2.update(bands(149.0, 50.0), (20.0, W))
    lim = p2.update(bands(148.9, 50.0), (20.8, W))
    assert lim.current_a == 20.0 and lim.reason == W
    # a candidate that rose past the hysteresis but still binds: recovering while climbing to it,
    # then the node again once there
    reasons = [p2.update(bands(148.0, 50.0), (23.0, W)).reason for _ in range(8)]
    assert reasons[0] == DerateReason.RECOVERING and reasons[-1] == W
    # it reaches the full current and the reason clears
    for _ in range(200):
        lim = p.update(bands(130.0, 50.0), (60.0, W))
    assert lim.current_a == 40.0 and lim.reason == DerateReason.NONE and not lim.active


def test_the_safe_torque_is_one_value_in_a_tick_and_between_ticks():
    """A tick's forced limit and the sender's limit between ticks (inputs silent, tick stalled,
    before the first tick) carry the same torque, never above kt x the safe current, whatever
    the configuration says (the configuration check refuses more; this is the depth below it)."""
    for configured in (None, 30.0, 150.0, 500.0):
        p = policy(safe_torque_nm=configured) if configured else policy()
        p.bus_silence_s = 1.0
        expect = min(configured or math.inf, 5.6 * 10.0)
        ticked = p.update(bands(120.0, 50.0), (60.0, W), [DerateReason.STALE_INPUT])
        assert ticked.torque_nm == pytest.approx(expect)
        assert p.between_ticks(None, 0.0, None).torque_nm == pytest.approx(expect)  # starting
        assert p.between_ticks(ticked, 5.0, None).torque_nm == pytest.approx(expect)  # inputs silent
        assert p.between_ticks(ticked, 0.0, 60.0).torque_nm == pytest.approx(expect)  # tick loop stuck
        assert p.safe(DerateReason.STALE_INPUT).torque_nm <= 5.6 * p.safe(DerateReason.STALE_INPUT).current_a + 1e-9


def test_forced_safe_limit_and_precedence():
    for forced, reason in (([DerateReason.STALE_INPUT], DerateReason.STALE_INPUT),
                           ([DerateReason.SENSOR_FAULT, DerateReason.STALE_INPUT], DerateReason.STALE_INPUT),
                           ([DerateReason.SENSOR_FAULT, DerateReason.MODEL_FAULT], DerateReason.MODEL_FAULT)):
        lim = policy().update(bands(120.0, 50.0), (60.0, W), forced)
        assert lim.current_a == 10.0 and lim.torque_nm == pytest.approx(56.0) and lim.reason == reason and lim.active
    # a hotter machine keeps the lower thermal limit under a forced one
    lim = policy().update(bands(145.0, 50.0), (4.0, W), [DerateReason.SENSOR_FAULT])
    assert lim.current_a == pytest.approx(4.0) and lim.reason == DerateReason.SENSOR_FAULT
    # non-finite band or reaction current -> zero... the safe limit, reason model fault
    lim = policy().update([NodeBand("hot_spot", math.nan, math.nan, 140, 155, W)], (60.0, W))
    assert lim.current_a == 10.0 and lim.reason == DerateReason.MODEL_FAULT
    lim = policy().update(bands(100.0, 50.0), (math.nan, W))
    assert lim.current_a == 10.0 and lim.reason == DerateReason.MODEL_FAULT


def test_forced_limit_never_above_the_band_at_the_measured_temperature():
    """10 A must not be sent with the measured end winding at 151-155 degC. Forced, the
    limit is min(safe, band at the reading): 40 A x (155 - T) / 15 below 10 A from 151.25 degC."""
    for reading in (120.0, 145.0, 151.0, 152.0, 153.0, 154.9, 155.0, 160.0):
        measured = [NodeBand("hot_spot", reading, reading, 140.0, 155.0, W)]
        expected = min(10.0, 40.0 * min(1.0, max(0.0, (155.0 - reading) / 15.0)))
        for forced in (DerateReason.MODEL_FAULT, DerateReason.STALE_INPUT, DerateReason.SENSOR_FAULT, DerateReason.STARTING):
            p = policy()
            lim = p.update([], None, [forced], measured)
            assert lim.current_a == pytest.approx(expected) and lim.reason == forced
            assert lim.torque_nm == pytest.approx(min(56.0, 5.6 * expected))
    # trusted, the readings do not limit (the model's upper band, which the readings correct, does)
    lim = policy().update(bands(150.0, 50.0), (60.0, W), [], [NodeBand("hot_spot", 152.0, 152.0, 140.0, 155.0, W)])
    assert lim.current_a == 40.0


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


def test_lookahead_names_the_binding_limit(model):
    """The limit that sets the look-ahead current: the magnet at high speed from a magnet-hot state,
    the winding at low speed from a winding-hot state (independently: which node's bound is lower
    when each is computed alone)."""
    limits = [(lim.name, model.node_index(lim.node), lim.max_c) for lim in model.limits]
    bindings = []
    for speed, i_pre in ((600.0, 22.0), (1800.0, 16.0)):
        u = {"speed_rpm": speed, "i_rms": 10.0, "torque_nm": 56.0, "ambient_c": 25.0}
        T0, _ = steady_state(model, {**u, "i_rms": i_pre})
        r = Lookahead(model, model.nominal(), limits, horizon_s=60.0, steps=6).compute(T0, u)
        loss_t = max(m for *_, m in limits)  # the same conservative copper temperature
        alone = [Lookahead(model, model.nominal(), [lim], horizon_s=60.0, steps=6,
                           loss_temperature_c=loss_t).compute(T0, u).current_a
                 for lim in limits]
        bindings.append(r.binding)
        assert r.binding == int(np.argmin(alone)) and r.current_a == pytest.approx(min(alone))
    assert bindings == [0, 1]  # winding, then magnet


def test_a_sensor_bounding_two_nodes_is_averaged_over_its_own_last_readings():
    """The floor under a node's upper band is the mean of its bounding sensor's last FLOOR_TICKS
    readings, one a tick, also when the sensor bounds two limited nodes (it was recorded once per
    node: twice a tick, a mean over half the ticks)."""
    specs = [LimitSpec("hot_spot", 0, 140.0, 155.0, DerateReason.WINDING),
             LimitSpec("end_turn", 1, 140.0, 155.0, DerateReason.WINDING)]
    floor = MeasuredFloor(specs, {"hot_spot": ["end_winding"], "end_turn": ["end_winding"]})
    readings = [100.0, 101.0, 102.0, 103.0, 104.0, 105.0, 106.0]
    for v in readings:
        upper = np.zeros(2)
        floor.raise_upper(upper, {"end_winding": v})
    want = float(np.mean(readings[-FLOOR_TICKS:]))
    assert upper.tolist() == pytest.approx([want, want])

