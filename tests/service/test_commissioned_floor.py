"""The commissioned floor: both winding PT100s reading low by less than the gap that refuses them
(15 K, under ``commissioned_gap_k`` 20 K) do not take the hot spot's band sent further below the
machine's true hot spot than ``commissioned_floor_k``; judged against the simulated machine's own
temperatures (the plant is the model file, so the commissioned prediction is its truth)."""
from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np
import pytest
from svc_testlib import engine_on_emulator

from thermal_edge.bench.service import _config

LOW_K, SECONDS = 15.0, 2400.0


def _run(floor_k: float) -> tuple[list, np.ndarray, float]:
    """Ticks of the overload cycle with both winding PT100s drifting ``LOW_K`` low, the plant's hot spot at
    each tick's time and the floor used."""
    def low(name: str, ts: float, sig: dict) -> dict:
        if name != "INV_StatorTemps":
            return sig
        k = min(LOW_K, max(0.0, (ts - 300.0) / 300.0 * LOW_K))  # drifting low from 300 s, LOW_K at 600 s
        return {**sig, "INV_T_WindingSlot": sig["INV_T_WindingSlot"] - k, "INV_T_EndWinding": sig["INV_T_EndWinding"] - k}

    with tempfile.TemporaryDirectory() as tmp:
        cfg = _config(Path(tmp), {"interface": "virtual"}, adapt=False, table4=False,
                      derating={"faults": {"commissioned_floor_k": floor_k}})
        outs, eng, emu = engine_on_emulator(cfg, "overload", SECONDS, low, trace_every_s=1.0)
    hot = next(lim for lim in eng.model.limits if lim.name == "hot_spot")
    tr = emu.trace()
    truth = np.interp([o.t for o in outs], tr["t"], tr["T"][:, eng.model.node_index(hot.node)])
    return outs, truth, floor_k


def test_readings_drifted_low_under_the_gap_leave_the_band_at_most_the_floor_below_the_truth(caplog):
    with caplog.at_level(logging.WARNING, logger="thermal_edge.service.engine"):
        outs, truth, k = _run(5.0)
    late = [i for i, o in enumerate(outs) if o.t > 900.0 and o.hot_spot is not None]
    short = max(truth[i] - outs[i].hot_spot.upper_c for i in late)
    assert short <= k + 1.5  # K: the floor, and the prediction stepped every 10 ticks (~1 K of heating)
    assert all(o.limits.reason.name != "MODEL_FAULT" for i, o in enumerate(outs) if i in late)  # never refused
    assert any("lies more than 5 K below the commissioned model" in r.getMessage() for r in caplog.records)
    # the floor out of reach: the band sent follows the drifted readings, 15 K below the truth
    outs_off, truth_off, _ = _run(100.0)
    short_off = max(truth_off[i] - outs_off[i].hot_spot.upper_c for i in late)
    assert short_off == pytest.approx(LOW_K, abs=3.0)
