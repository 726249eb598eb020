"""The RMS current against the torque: a current far below ``|T| / kt`` (a DBC scaling 10x low, a
second sender diluting the current frame) is not believed. Judged against counts made here from the
same inputs, an engine fed by the simulated machine with its current frame scaled, and a real
machine's measured currents and torque (the Paderborn run, skipped where absent)."""
from __future__ import annotations

import logging
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from svc_testlib import REPO, engine_on_emulator

from thermal_edge.bench.service import _config
from thermal_edge.bus.frames import DerateReason
from thermal_edge.service.current_torque import CONFIRM_TICKS, JUDGED_FROM, CurrentTorqueCheck

PADERBORN = REPO.parent / "shared" / "data" / "paderborn" / "run_a.csv"


def test_a_low_current_is_doubted_after_the_confirming_ticks_and_believed_again_at_once():
    chk = CurrentTorqueCheck("i", "T", kt_nm_per_arms=2.0, max_current_a=100.0, ratio=0.5)
    # judged from 20 A (a fifth of 100 A), i.e. from 40 Nm; low: i < 0.5 * |T| / 2
    ticks = [(30.0, 60.0), (5.0, 30.0), (10.0, 50.0), (12.0, -60.0), (12.0, 60.0), (12.0, 60.0), (40.0, 60.0)]
    got = [chk.judge({"i": i, "T": t}) for i, t in ticks]
    low = [abs(t) / 2.0 >= JUDGED_FROM * 100.0 and i < 0.5 * abs(t) / 2.0 for i, t in ticks]
    assert low == [False, False, True, True, True, True, False]
    run, expect = 0, []
    for x in low:
        run = run + 1 if x else 0
        expect.append(run >= CONFIRM_TICKS)
    assert [v.doubted for v in got] == expect
    assert [v.started for v in got].count(True) == 1 and got[expect.index(True)].started
    assert got[-1].ended and not got[-1].doubted
    assert math.isnan(got[1].needed) and got[0].needed == 30.0  # 30 Nm takes 15 A: not judged


def _drive(scale_from: float, seconds: float) -> tuple:
    """The engine on the overload cycle's frames, the current frame's signals scaled by 0.1 from
    ``scale_from`` (s): the tick outputs, the count of the fault, kt and the safe current."""
    def tenth(name: str, ts: float, sig: dict) -> dict:
        if name == "INV_Currents" and ts >= scale_from:
            return {k: v * 0.1 if isinstance(v, float) else v for k, v in sig.items()}
        return sig

    with tempfile.TemporaryDirectory() as tmp:
        cfg = _config(Path(tmp), {"interface": "virtual"}, adapt=False)
        outs, eng, _ = engine_on_emulator(cfg, "overload", seconds, tenth)
    return outs, eng.accumulator.bad_readings["current_below_torque"], eng.kt, cfg.derating.safe_current_a


def test_a_current_scaled_ten_times_low_is_a_sensor_fault_and_the_model_heats_with_the_torques(caplog):
    with caplog.at_level(logging.ERROR, logger="thermal_edge.service.engine"):
        outs, counted, kt, safe = _drive(scale_from=900.0, seconds=1000.0)
    before = [o for o in outs if o.t <= 900.0]
    assert before and not any(o.faults.get("i_rms") for o in before)
    after = [o for o in outs if o.t > 901.0]
    judged = [o for o in after if abs(o.inputs["torque_nm"]) / kt >= JUDGED_FROM * 40.0]
    assert len(judged) > 20  # the cycle loads the machine after the scaling starts
    first = outs.index(judged[0])
    doubted = [o for o in outs[first + CONFIRM_TICKS:] if abs(o.inputs["torque_nm"]) / kt >= JUDGED_FROM * 40.0]
    for o in doubted:  # every judged tick after the confirming ones
        assert o.faults.get("i_rms") == "current_below_torque"
        assert o.limits.reason == DerateReason.SENSOR_FAULT and o.limits.current_a <= safe
        assert o.lookahead_a <= o.limits.current_a  # no advice (TE_Forecast) above the limit the fault forces
    assert counted >= 1
    # what the model heated with: the current the torque takes (the simulated machine's own), not the
    # frame's tenth: its open-loop prediction is the unscaled run's
    control, _, _, _ = _drive(scale_from=math.inf, seconds=1000.0)
    assert not any(o.faults.get("i_rms") for o in control)
    assert np.abs(outs[-1].prediction - control[len(outs) - 1].prediction).max() < 0.5  # K
    assert outs[-1].prediction.max() - outs[first].prediction.max() > 1.0  # K: it did heat meanwhile
    lines = [r.getMessage() for r in caplog.records if "below 0.5 of the" in r.getMessage()]
    assert lines and lines[0].startswith("current i_rms at t=")


@pytest.mark.skipif(not PADERBORN.exists(), reason=f"Paderborn data not found at {PADERBORN}")
def test_a_real_machines_currents_and_torque_are_never_doubted():
    """The measured dq currents and torque of a real interior-magnet machine (reluctance torque,
    field weakening) over its whole run: no tick is doubted with the default margin (kt taken as
    the median torque per A where the machine is loaded)."""
    d = np.genfromtxt(PADERBORN, delimiter=",", names=True)
    i_rms = np.sqrt((d["i_d"] ** 2 + d["i_q"] ** 2) / 2.0)
    loaded = np.abs(d["torque"]) > 0.3 * np.abs(d["torque"]).max()
    kt = float(np.median(np.abs(d["torque"][loaded]) / i_rms[loaded]))
    chk = CurrentTorqueCheck("i", "T", kt, float(i_rms.max()), ratio=0.5)
    verdicts = [chk.judge({"i": float(i), "T": float(t)}) for i, t in zip(i_rms, d["torque"])]
    assert sum(np.isfinite(v.needed) for v in verdicts) > 1000  # most of the run is judged
    assert not any(v.doubted for v in verdicts)
