"""Screening picks the parameters that were actually perturbed, and its potentials follow eq. 40."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.estimation.common import ParamSpace, decimate, window_from_arrays
from thermal_edge.estimation.objective import Objective
from thermal_edge.estimation.screening import potentials, screen, select
from thermal_edge.lptn import Simulator


def test_potential_formula_by_hand():
    grad = np.array([2.0, -3.0, 0.5, 0.0])
    phi = np.log([5.0, 5.0, 1.0, 3.0])
    lo, hi = np.array([1.0, 1.0, 1.0, 1.0]), np.array([10.0, 10.0, 10.0, 10.0])
    pot = potentials(grad, phi, lo, hi)
    # positive gradient: decreasing helps, room log(5/1); negative: increasing helps, room log(10/5)
    assert pot == pytest.approx([2 * np.log(5), 3 * np.log(2), 0.0, 0.0])
    assert select(("a", "b", "c", "d"), pot, 0.98) == ("a", "b")
    assert select(("a", "b", "c", "d"), pot, 0.5) == ("a",)
    assert select(("a",), np.zeros(1)) == ()


def test_screening_picks_the_perturbed_parameters(pm10kw, varied_1h):
    # the plant is the nominal machine; the model has two parameters off
    model = pm10kw.with_parameters({"R_e_hous": 6.0, "r_ins_sw": 0.02})
    run = varied_1h.run
    win = decimate(window_from_arrays(model, {c: run.columns[c] for c in model.inputs},
                                      {s: run.columns[s] for s in model.sensors}, varied_1h.truth.T[0], 1.0), 5)
    names = model.adaptable
    obj = Objective(Simulator(model), ParamSpace(model, names, model.nominal()), win)
    phi = np.log(obj.space.values())
    ev = obj.evaluate(phi)
    sc = screen(obj.space.names, ev.grad, ev.hess, phi, obj.space.lower, obj.space.upper)
    ranked = [names[i] for i in np.argsort(-sc.potential)]
    assert set(ranked[:2]) == {"R_e_hous", "r_ins_sw"}
    assert {"R_e_hous", "r_ins_sw"} <= set(sc.selected)
    # moving the two parameters in the direction screening points to reduces the objective
    i, j = names.index("R_e_hous"), names.index("r_ins_sw")
    assert ev.grad[i] < 0 < ev.grad[j]  # R_e_hous too low, r_ins_sw too high
