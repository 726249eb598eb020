"""Every winding PT100 bounds the winding's limit from below: a slot-winding reading above the
end-winding hot spot's estimate raises the hot spot's upper band to it (the winding limit holds for
all of its copper), judged against the readings' own mean of the last ticks."""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from svc_testlib import engine_on_emulator

from thermal_edge.bench.service import _config
from thermal_edge.lptn import NodeRole, load_model
from thermal_edge.service.derating import FLOOR_TICKS, bounding_sensors
from thermal_edge.shipped import config_path

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
    def hotter(name: str, ts: float, sig: dict) -> dict:
        if name == "INV_StatorTemps" and ts >= RAISED_FROM_S:
            return {**sig, "INV_T_WindingSlot": sig["INV_T_WindingSlot"] + RAISE_K}
        return sig

    with tempfile.TemporaryDirectory() as tmp:
        outs, _, _ = engine_on_emulator(_config(Path(tmp), {"interface": "virtual"}, adapt=False), "overload",
                                        RAISED_FROM_S + 120.0, hotter)
    late = [k for k, o in enumerate(outs) if o.t >= RAISED_FROM_S + 60.0]
    raised = 0
    for k in late:
        slot = np.mean([outs[j].measured["slot_winding"] for j in range(k - FLOOR_TICKS + 1, k + 1)])
        assert outs[k].hot_spot.upper_c >= slot - 1e-9
        raised += slot > outs[k].hot_spot.estimate_c + 1.0
    assert raised >= len(late) // 2  # the reading did lie above the estimate: the floor was what held
