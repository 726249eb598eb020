"""Every winding PT100 bounds the winding's limit from below: a slot-winding reading above the
end-winding hot spot's estimate raises the hot spot's upper band to it (the winding limit holds for
all of its copper), judged against the readings' own mean of the last ticks."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from thermal_edge.bench.service import _config
from thermal_edge.bus.codec import DecodedFrame
from thermal_edge.lptn import NodeRole, load_model
from thermal_edge.service.clock import FrameClock
from thermal_edge.service.derating import FLOOR_TICKS, bounding_sensors
from thermal_edge.service.engine import ThermalEngine
from thermal_edge.shipped import config_path
from thermal_edge.sim.inverter import EmulatorConfig, InverterEmulator

RAISED_FROM_S, RAISE_K = 600.0, 25.0


def test_a_winding_sensor_bounds_the_winding_limit_even_where_the_model_puts_it_hotter():
    m = load_model(config_path("machines", "pm10kw.yaml"))
    sensors = {s: m.node_index(n) for s, n in m.sensors.items()}
    limits = {lim.name: m.node_index(lim.node) for lim in m.limits}
    bound = bounding_sensors(m, m.nominal(), sensors, limits, 40.0, 5.6)
    winding = [s for s, n in m.sensors.items() if m.node_roles.get(n) == NodeRole.WINDING]
    hot = [lim.name for lim in m.limits if m.node_roles.get(lim.node) == NodeRole.WINDING]
    assert len(winding) == 2 and hot == ["hot_spot"]
    assert set(winding) <= set(bound["hot_spot"])
    assert not set(winding) & set(bound.get("magnet", []))  # a magnet limit is not the winding's


def test_a_slot_reading_above_the_hot_spot_estimate_raises_the_band_sent_to_it():
    with tempfile.TemporaryDirectory() as tmp:
        cfg = _config(Path(tmp), {"interface": "virtual"}, adapt=False)
        eng = ThermalEngine(cfg)
        emu = InverterEmulator(EmulatorConfig(cycle_path=config_path("cycles", "overload.yaml"), t0=0.0,
                                              plant_dt_s=0.5, trace_every_s=1e9, record_estimates=False, closed_loop=False))
        clock, outs = FrameClock(cfg.clock.tick_s), []
        while not outs or outs[-1].t < RAISED_FROM_S + 120.0:
            for ts, name, sig in emu.step(None):
                if name == "INV_StatorTemps" and ts >= RAISED_FROM_S:
                    sig = {**sig, "INV_T_WindingSlot": sig["INV_T_WindingSlot"] + RAISE_K}
                f = DecodedFrame(name, 0, sig, 0, ts)
                for b in eng.ticks_for(clock.observe(f.timestamp)):
                    outs.append(eng.tick(b))
                eng.add_frame(f, clock.now())
        eng.close()
    late = [k for k, o in enumerate(outs) if o.t >= RAISED_FROM_S + 60.0]
    raised = 0
    for k in late:
        slot = np.mean([outs[j].measured["slot_winding"] for j in range(k - FLOOR_TICKS + 1, k + 1)])
        assert outs[k].hot_spot.upper_c >= slot - 1e-9
        raised += slot > outs[k].hot_spot.estimate_c + 1.0
    assert raised >= len(late) // 2  # the reading did lie above the estimate: the floor was what held
