"""The derating policy in the closed loop on the simulated machine: the service's engine and policy,
the plant and frames of the inverter emulator (through the DBC), frame clock, no bus
(thermal_edge.bench.protection). The plant's true temperatures are the independent reference."""
from __future__ import annotations

import io
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from thermal_edge.bench import protection as P
from thermal_edge.bus import DerateReason
from thermal_edge.lptn import steady_state
from thermal_edge.service.journal import JournalFormatter, RateLimit

R = DerateReason
HOT, HOT_MAX, HOT_WARN = "end_winding_2", 155.0, 140.0


def cycle(tmp_path: Path, *segments: tuple[float, float, float]) -> Path:
    """A cycle file of (duration s, speed rpm, torque Nm) segments."""
    path = tmp_path / "cycle.yaml"
    path.write_text(yaml.safe_dump({"name": "test", "dt_s": 1.0, "ambient_c": 25.0, "segments": [
        {"duration_s": d, "speed_rpm": n, "torque_nm": m} for d, n, m in segments]}))
    return path


class Loop:
    """The service's engine and policy closing the loop over the simulated machine; per tick the
    limits and the plant's true hot spot."""

    def __init__(self, tmp_path: Path, cyc: Path, warm_a: float | None = None) -> None:
        self.cfg = P.edge_config(tmp_path)
        from thermal_edge.service.engine import load_service_model

        model = load_service_model(self.cfg)
        self.model = model
        self.emu = P.emulator_for(P.plant_for(model, P.CASES["nominal"]), cyc, P.CASES["nominal"], None)
        if warm_a is not None:  # the machine starts in its steady state at this current, 900 rpm
            self.emu.plant.T, _ = steady_state(model, {"speed_rpm": 900.0, "i_rms": warm_a, "torque_nm": 5.6 * warm_a,
                                                       "ambient_c": 25.0})
        self.kt = float(self.cfg.kt(model))
        self.pol = P.ThermalEdgePolicy(self.emu, self.cfg.derating.max_current_a, self.cfg.derating.max_torque_nm, self.cfg)
        self.hot = model.node_index(HOT)
        self.ticks: list[tuple[float, float, R, float, dict[str, float]]] = []  # (t, limit, reason, true hot spot, measured)
        self.events: list[tuple[float, object]] = []  # (elapsed s, action) applied by observe

    def observe(self, emu, pol) -> None:
        while self.events and emu.elapsed >= self.events[0][0] - 1e-9:
            self.events.pop(0)[1]()
        out = pol.last_out
        if out is not None and (not self.ticks or self.ticks[-1][0] != out.t - P.T0):
            self.ticks.append((out.t - P.T0, pol.limit, out.limits.reason, float(emu.plant.T[self.hot]), dict(out.measured)))

    def run(self) -> dict[str, float]:
        limits = [(lim.name, self.model.node_index(lim.node), self.cfg.limit_band(lim)[1]) for lim in self.model.limits]
        try:
            return P.closed_loop(self.emu, self.pol, self.kt, limits, self.observe)
        finally:
            self.pol.close()


def test_a_cold_machine_gets_the_full_rated_current(tmp_path):
    """Cold, at rated load: after the start-up ramp from the safe limit (recovering), 40 A with no reason."""
    loop = Loop(tmp_path, cycle(tmp_path, (400.0, 900.0, 106.0)))
    loop.run()
    after = [(t, i, r) for t, i, r, _, _ in loop.ticks if t > 70.0]
    assert after and all(i == 40.0 and r == R.NONE for _, i, r in after), after[:3]
    # the start: starting (safe limit), then recovering at the rise rate, never a thermal reason
    assert loop.ticks[0][2] in (R.STARTING, R.RECOVERING)
    assert {r for _, _, r, _, _ in loop.ticks} <= {R.STARTING, R.RECOVERING, R.NONE}


def test_the_limit_falls_before_the_max_on_an_overload(tmp_path):
    """Warm (rated steady state), then the maximum torque for 15 min: the limit falls smoothly
    while the true hot spot is still below its max, and the true hot spot never exceeds it."""
    loop = Loop(tmp_path, cycle(tmp_path, (900.0, 900.0, 220.0)), warm_a=19.0)
    r = loop.run()
    assert r["over_s"] == 0.0 and r[f"peak_{'hot_spot'}"] < HOT_MAX
    t_fall, _, reason, hot_at_fall, _ = next(x for x in loop.ticks if x[0] > 70.0 and x[1] < 40.0)
    assert reason == R.WINDING and hot_at_fall < HOT_MAX
    # full current until then: the overload capacity of a warm machine was used (~2.5 min at 40 A)
    assert t_fall > 120.0
    # smooth: the limit passes through intermediate values, and settles at the holding current
    falling = [i for t, i, _, _, _ in loop.ticks if t >= t_fall]
    assert any(25.0 < i < 39.0 for i in falling)
    assert 15.0 < falling[-1] < 30.0
    assert max(np.abs(np.diff(falling))) < 10.0  # no jump to a fixed safe value


def test_recovering_reason_after_a_short_dropout(tmp_path):
    """INV_Currents missing for 2 s: stale_input (safe limit) only while stale, then recovering
    while the limit climbs back, then none: never the stale reason once the frames are back."""
    loop = Loop(tmp_path, cycle(tmp_path, (400.0, 900.0, 106.0)))
    loop.events = [(200.0, lambda: loop.emu.paused.add("INV_Currents")),
                   (202.0, lambda: loop.emu.paused.discard("INV_Currents"))]
    loop.run()
    seq = [(t, i, r) for t, i, r, _, _ in loop.ticks if t >= 199.0]
    stale = [t for t, _, r in seq if r == R.STALE_INPUT]
    assert stale and min(stale) <= 203.0 and max(stale) <= 204.0
    assert all(i == 10.0 for t, i, r in seq if r == R.STALE_INPUT)
    after = [(t, i, r) for t, i, r in seq if t > max(stale)]
    rec = [t for t, _, r in after if r == R.RECOVERING]
    assert rec and rec[0] == after[0][0]  # at once after the stale ticks
    assert {r for _, _, r in after} == {R.RECOVERING, R.NONE}
    # climbing at the rise rate (0.5 A/s) from 10 A to 40 A, then none
    assert len(rec) == pytest.approx(60, abs=2)
    assert after[-1][1] == 40.0 and after[-1][2] == R.NONE


def test_forced_limit_obeys_the_band_at_the_measured_end_winding(tmp_path):
    """The forced limit at the measured end winding, through the engine: the housing PT100 open (sensor fault, safe limit) on a
    machine whose measured end winding is ~153.5 degC: the limit is min(10 A, band at the reading)."""
    loop = Loop(tmp_path, cycle(tmp_path, (120.0, 900.0, 140.0)))
    # the plant's steady state with the measured end winding at 153.5 degC (bisection on the current)
    sensor_row = loop.model.node_index(loop.model.sensors["end_winding"])
    lo, hi = 15.0, 30.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        T, _ = steady_state(loop.model, {"speed_rpm": 900.0, "i_rms": mid, "torque_nm": 5.6 * mid, "ambient_c": 25.0})
        lo, hi = (mid, hi) if T[sensor_row] < 153.5 else (lo, mid)
    loop.emu.plant.T = T
    loop.emu.sensor_status["housing"] = 1  # open circuit
    loop.run()
    checked = 0
    for t, i, r, _, meas in loop.ticks:
        reading = meas.get("end_winding", math.nan)
        if not math.isfinite(reading):
            continue
        band = 40.0 * min(1.0, max(0.0, (155.0 - reading) / 15.0))
        assert r in (R.SENSOR_FAULT, R.STARTING) and i <= min(10.0, band) + 0.01, (t, i, reading)  # 0.01: DBC resolution
        checked += reading > 151.3
    assert checked >= 5  # ticks where the band at the reading was below the safe limit


def test_safety_events_logged_with_priorities_and_rate_limited(tmp_path):
    """Reason changes at NOTICE (5) / WARNING (4, a fault forces the safe limit); stale and back;
    a flapping input (2 s out of every 6 s) cannot flood: the journal's limit per call site."""
    loop = Loop(tmp_path, cycle(tmp_path, (400.0, 900.0, 106.0)))
    for k in range(20):
        t0 = 150.0 + 6.0 * k
        loop.events += [(t0, lambda: loop.emu.paused.add("INV_Currents")),
                        (t0 + 2.0, lambda: loop.emu.paused.discard("INV_Currents"))]
    buf = io.StringIO()
    handler = logging.StreamHandler(buf)
    handler.setFormatter(JournalFormatter("%(message)s"))
    limiter = RateLimit(burst=5, window_s=60.0, clock=lambda: loop.emu.elapsed)
    handler.addFilter(limiter)
    logger = logging.getLogger("thermal_edge.service.events")
    old_level, old_prop = logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    try:
        loop.run()
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)
        logger.propagate = old_prop
    lines = buf.getvalue().splitlines()
    reasons = [ln for ln in lines if "derate reason" in ln]
    # the first tick: initialised at once, the limit climbs from the safe limit it started at (NOTICE)
    assert reasons[0].startswith("<5>derate reason - -> recovering")
    assert any(ln.startswith("<5>derate reason recovering -> none") for ln in reasons)
    assert any(ln.startswith("<4>derate reason") and "-> stale_input" in ln for ln in reasons)  # WARNING
    assert any(ln.startswith("<4>input(s) stale: INV_Currents") for ln in lines)
    assert any(ln.startswith("<5>input(s) back: INV_Currents") for ln in lines)
    assert any(ln.startswith("<4>state") and "-> degraded" in ln for ln in lines)
    # 20 dropouts (each: -> stale_input, -> recovering) within 150-270 s: the WARNING call site lets
    # at most 5 lines through per 60 s window, and the 120 s of flapping span at most 3 windows
    stale_warn = [ln for ln in reasons if ln.startswith("<4>")]
    assert len(stale_warn) <= 5 * 3 < 20
    assert limiter.dropped_total > 0
    assert any("similar line(s) suppressed" in ln for ln in lines)


def test_bench_protection_short(tmp_path):
    """The bench's short form: one case, 20 min at the maximum torque from cold (the hot spot reaches
    its max after ~10 min): no policy but the baselines' known weak spots overheats, and
    thermal_edge delivers at least what the PT100 derate does, and at least 90 % of the oracle."""
    cyc = cycle(tmp_path, (1200.0, 900.0, 220.0))
    r = P.run_case(P.CASES["nominal"], cycle=cyc)
    te, pt, ora = r["thermal_edge"], r["pt100_linear"], r["oracle"]
    print({p: {k: round(v, 2) for k, v in f.items() if isinstance(v, float)} for p, f in r.items()})
    assert te["seconds_over_max"] == 0.0 and ora["seconds_over_max"] == 0.0
    assert te["peak_hot_spot_c"] < HOT_MAX and te["peak_magnet_c"] < 120.0
    assert te["oracle_share_pct"] >= 90.0
    if pt["seconds_over_max"] == 0.0:
        assert te["oracle_share_pct"] >= pt["oracle_share_pct"]
    assert 0.0 < te["headroom_pct"] <= 100.0 + 1e-9
