"""Uncertainty from the Fisher information, offline calibration, and the calibrated model file."""
from __future__ import annotations

import numpy as np
import pytest

from thermal_edge.estimation.calibrate import calibrate, write_calibrated
from thermal_edge.estimation.common import ParamSpace, decimate, window_from_arrays
from thermal_edge.estimation.objective import Objective
from thermal_edge.estimation.uncertainty import estimate_uncertainty
from thermal_edge.lptn import Simulator, load_model

from conftest import ROOT  # noqa: E402  (tests/estimation is on sys.path under pytest's rootdir)


def test_covariance_matches_the_textbook_formula_and_flags_what_sensors_cannot_see(pm10kw, varied_1h):
    run = varied_1h.run
    names = ("R_e_hous", "r_ins_sw", "k_a_sw")
    win = decimate(window_from_arrays(pm10kw, {c: run.columns[c] for c in pm10kw.inputs},
                                      {s: run.columns[s] for s in pm10kw.sensors}, varied_1h.truth.T[0], 1.0), 5)
    obj = Objective(Simulator(pm10kw), ParamSpace(pm10kw, names, pm10kw.nominal()), win, weighting="uniform")
    phi = np.log(obj.space.values())
    ev = obj.evaluate(phi)
    unc = estimate_uncertainty(obj, ev)
    # independent: σ² (JᵀJ)⁻¹ from the stacked unweighted residual Jacobian (uniform weights)
    J = ev.jac.reshape(-1, len(names))
    r = ev.residuals.ravel()
    s2 = float(r @ r) / (len(r) - len(names))
    assert unc.sigma2 == pytest.approx(s2, rel=1e-9)
    assert unc.cov == pytest.approx(s2 * np.linalg.inv(J.T @ J), rel=1e-6)
    # noise is 0.1 K with 0.1 K steps: the residual σ at the true parameters is about that
    assert 0.08 < np.sqrt(unc.sigma2) < 0.13
    # with all 14 parameters free, the housing path is pinned and the slot winding's
    # circumferential conductivity is not (heat density in the slots is low)
    full = Objective(Simulator(pm10kw), ParamSpace(pm10kw, pm10kw.adaptable, pm10kw.nominal()), win, weighting="uniform")
    u14 = estimate_uncertainty(full, full.evaluate(np.log(full.space.values())))
    ident = dict(zip(pm10kw.adaptable, u14.identifiable))
    assert ident["R_e_hous"] and ident["c_p_sw"] and not ident["k_c_sw"]
    # bands: a measured node is pinned tighter than the unmeasured magnet at the end of the run
    S = Simulator(pm10kw).simulate(pm10kw.nominal(), win.inputs, win.dt, win.T0, wrt=names).S
    band = unc.node_band(S[-1] * obj.space.values()[None, :])
    assert band.shape == (len(pm10kw.nodes),) and np.all(band >= 0)


def test_write_calibrated_keeps_comments_and_moves_data_dir(tmp_path):
    src = ROOT / "config" / "machines" / "paderborn4.yaml"
    out = tmp_path / "sub" / "cal.yaml"
    out.parent.mkdir()
    write_calibrated(src, {"C_sy": 7000.0, "R_c_sy": 0.02}, out, note="test")
    text = out.read_text()
    assert text.startswith("# calibrated by thermal-edge calibrate from paderborn4.yaml: test")
    assert "C_sy: {value: 7000, min: 1.5e3" in text and "R_c_sy: {value: 0.02," in text
    assert text.count("\n#") >= src.read_text().count("\n#")  # comments survive
    data_dir = next(line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("data_dir:"))
    original = (src.parent / "../../../shared/data/paderborn").resolve()
    assert (out.parent / data_dir).resolve() == original
    with pytest.raises(KeyError, match="nope"):
        write_calibrated(src, {"nope": 1.0}, tmp_path / "x.yaml")


def test_calibration_recovers_a_perturbed_parameter(pm10kw, make_run):
    plant = make_run(pm10kw, "varied_drive.yaml", 2400.0, seed=9)
    wrong = pm10kw.with_parameters({"R_e_hous": 5.0})
    res = calibrate(wrong, [plant.run], names=["R_e_hous"], decimation=5, maxiter=4, popsize=4, seed=1)
    got = dict(zip(res.names, res.values))
    assert got["R_e_hous"] == pytest.approx(9.1, rel=0.02)
    assert res.objective_final < 0.1 * res.objective_start
