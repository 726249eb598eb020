"""EKF and observer converge on cases with a known answer."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.estimation.ekf import run_ekf
from thermal_edge.estimation.observer import Observer


def test_ekf_recovers_a_housing_resistance(pm10kw, varied_1h):
    start = pm10kw.with_parameters({"R_e_hous": 6.1})
    run = varied_1h.run
    res = run_ekf(start, {c: run.columns[c] for c in start.inputs}, {s: run.columns[s] for s in start.sensors},
                  run.dt, varied_1h.truth.T[0], names=["R_e_hous"])
    final = res.theta[start.parameter_index(["R_e_hous"])[0]]
    assert final == pytest.approx(9.1, rel=0.05)
    assert len(res.trace) == int(len(run) // 60)  # one update per minute


def test_observer_converges_on_every_node(pm10kw, varied_1h):
    truth, run = varied_1h.truth, varied_1h.run
    for spread, bound in (({}, 0.5), (None, 0.75)):
        # state noise only; and with the parameters' declared spread (the gain then also allows for
        # the adaptable parameters being off, which costs a little on a plant that has them exact)
        ob = Observer(pm10kw, truth.T[0] + 5.0, spread=spread)
        errs = []
        for k in range(len(run)):
            ob.update({s: float(run.columns[s][k]) for s in pm10kw.sensors})
            errs.append(np.abs(ob.T - truth.T[k]).max())
            ob.predict({c: float(run.columns[c][k]) for c in pm10kw.inputs})
        assert errs[0] > 4.0
        assert errs[-1] < bound
    # measured nodes are pulled in within the first minute
    n = pm10kw.node_index(pm10kw.sensors["slot_winding"])
    ob2 = Observer(pm10kw, truth.T[0] + 5.0)
    for k in range(60):
        ob2.update({s: float(run.columns[s][k]) for s in pm10kw.sensors})
        ob2.predict({c: float(run.columns[c][k]) for c in pm10kw.inputs})
    assert abs(ob2.T[n] - truth.T[60, n]) < 0.5
    assert ob2.std()[n] < ob2.std().max()
