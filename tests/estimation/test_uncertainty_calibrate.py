"""Uncertainty from the Fisher information, offline calibration, and the calibrated model file."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import ROOT  # tests/estimation is on sys.path under pytest's rootdir

from thermal_edge.estimation.calibrate import calibrate, write_calibrated
from thermal_edge.estimation.common import ParamSpace, decimate, window_from_arrays
from thermal_edge.estimation.objective import Objective
from thermal_edge.estimation.uncertainty import estimate_uncertainty, integrated_autocorrelation
from thermal_edge.lptn import Simulator


def test_covariance_matches_the_textbook_formula_and_flags_what_sensors_cannot_see(pm10kw, varied_1h):
    run = varied_1h.run
    names = ("R_e_hous", "r_ins_sw", "k_a_sw")
    win = decimate(window_from_arrays(pm10kw, {c: run.columns[c] for c in pm10kw.inputs},
                                      {s: run.columns[s] for s in pm10kw.sensors}, varied_1h.truth.T[0], 1.0), 5)
    obj = Objective(Simulator(pm10kw), ParamSpace(pm10kw, names, pm10kw.nominal()), win, weighting="uniform")
    phi = np.log(obj.space.values())
    ev = obj.evaluate(phi)
    unc = estimate_uncertainty(obj, ev)
    # independent: σ² (JᵀJ / τ)⁻¹ from the stacked unweighted residual Jacobian (uniform weights),
    # τ by the direct sums of Sokal's estimator; the gate's σ with τ = 1
    J = ev.jac.reshape(-1, len(names))
    r = ev.residuals.ravel()
    s2 = float(r @ r) / (len(r) - len(names))
    tau = _tau_direct(ev.residuals)
    assert unc.sigma2 == pytest.approx(s2, rel=1e-9)
    assert unc.tau == pytest.approx(tau, rel=1e-9)
    assert unc.cov == pytest.approx(s2 * tau * np.linalg.inv(J.T @ J), rel=1e-6)
    assert unc.rel_std_independent == pytest.approx(np.sqrt(np.diag(s2 * np.linalg.inv(J.T @ J))), rel=1e-6)
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


def _tau_direct(r: np.ndarray, c: float = 5.0) -> float:
    """Sokal's integrated autocorrelation time by explicit lag sums, sensors pooled by their
    residuals' sum of squares (the definition, no FFT)."""
    taus, weights = [], []
    for x in np.asarray(r, dtype=float).T:
        y = x - x.mean()
        c0 = float(y @ y)
        tau, m = 1.0, 0
        while m < len(y) - 1:
            m += 1
            tau += 2.0 * float(y[:-m] @ y[m:]) / c0
            if m >= c * tau:
                break
        taus.append(tau)
        weights.append(float(x @ x))
    return max(float(np.average(taus, weights=weights)), 1.0)


def test_autocorrelation_time_of_an_ar1_process_is_its_theoretical_value():
    """AR(1) residuals x_k = a x_{k−1} + e_k have τ = (1 + a)/(1 − a): 1 (white), 3, 19; the
    Fisher covariance of a mean fitted to them then grows by τ, as the variance of their mean does."""
    rng = np.random.default_rng(3)
    for a, expected in ((0.0, 1.0), (0.5, 3.0), (0.9, 19.0)):
        e = rng.normal(size=(40_000, 2))
        x = np.empty_like(e)
        x[0] = e[0]
        for k in range(1, len(e)):
            x[k] = a * x[k - 1] + e[k]
        got = integrated_autocorrelation(x)
        assert got == pytest.approx(expected, rel=0.15), (a, got)
        assert got == pytest.approx(_tau_direct(x), rel=1e-9)
    # anti-correlated residuals never narrow the bound below white noise's
    assert integrated_autocorrelation(np.tile([1.0, -1.0], 500)) == 1.0
    # masked samples count as zero residual; a column with too few readings is left out
    mask = np.ones((200, 2), dtype=bool)
    mask[:, 1] = False
    mask[:2, 1] = True
    r = rng.normal(size=(200, 2))
    r[:, 0] = np.convolve(r[:, 0], np.ones(5) / 5, mode="same")  # τ well above 1
    assert integrated_autocorrelation(r, mask) == pytest.approx(integrated_autocorrelation(r[:, :1]), rel=1e-12)
    assert integrated_autocorrelation(r, mask) > 3.0


def test_write_calibrated_keeps_comments_and_moves_data_dir(tmp_path):
    src = tmp_path / "models" / "paderborn4.yaml"  # the packaged model with a data_dir relative to it
    src.parent.mkdir()
    src.write_text((ROOT / "config" / "machines" / "paderborn4.yaml").read_text().replace(
        "\ntables:", "\ndata_dir: ../tables/paderborn\ntables:", 1))
    out = tmp_path / "sub" / "cal.yaml"
    out.parent.mkdir()
    write_calibrated(src, {"C_sy": 7000.0, "R_c_sy": 0.02}, out, note="test")
    text = out.read_text()
    assert text.startswith("# calibrated by thermal-edge calibrate from paderborn4.yaml: test")
    assert "C_sy: {value: 7000, min: 1.5e3" in text and "R_c_sy: {value: 0.02," in text
    assert text.count("\n#") >= src.read_text().count("\n#")  # comments survive
    data_dir = next(line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("data_dir:"))
    original = (tmp_path / "tables" / "paderborn").resolve()
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


def test_a_window_of_a_few_samples_identifies_nothing():
    """A fit that matches its few readings exactly (here: readings that are the model's own
    prediction) has a residual variance of zero, so its covariance "pins" every parameter to
    ±0 %: with fewer than MIN_RESIDUAL_DOF readings beyond the parameters none is identifiable;
    the same exact match over 30 samples is (the counter-case)."""
    from thermal_edge.estimation.uncertainty import MIN_RESIDUAL_DOF
    from thermal_edge.lptn import load_model

    model = load_model(ROOT / "tests" / "commands" / "models" / "two_node.yaml")
    inputs = {"speed_rpm": np.full(40, 600.0), "i_rms": np.linspace(5.0, 25.0, 40), "ambient_c": np.full(40, 25.0)}

    def gate(n: int) -> np.ndarray:
        def objective(meas: dict[str, np.ndarray]) -> Objective:
            win = window_from_arrays(model, {c: v[:n] for c, v in inputs.items()}, meas, np.array([25.0, 25.0]), 1.0)
            return Objective(Simulator(model), ParamSpace(model, model.adaptable, model.nominal()), win, weighting="uniform")

        phi = np.log(ParamSpace(model, model.adaptable, model.nominal()).values())
        r0 = objective({s: np.zeros(n) for s in model.sensors}).evaluate(phi).residuals
        best = None
        for sign in (1.0, -1.0):  # readings equal to the prediction, whichever sign the residual has
            obj = objective({s: sign * r0[:, j] for j, s in enumerate(model.sensors)})
            ev = obj.evaluate(phi)
            if best is None or np.abs(ev.residuals).max() < np.abs(best[1].residuals).max():
                best = (obj, ev)
        assert np.abs(best[1].residuals).max() < 1e-9
        return estimate_uncertainty(*best).identifiable

    assert 2 * len(model.sensors) - len(model.adaptable) < MIN_RESIDUAL_DOF
    assert not gate(2).any()
    assert gate(30).all()


def test_a_noisy_first_reading_does_not_start_the_fit(pm10kw, make_run, monkeypatch):
    """The plant's readings without noise, but the first sample of every sensor 0.3 K high (one
    PT100 draw). Started from that sample with the start held (the control), the open-loop
    prediction carries the error for as long as the slowest mode remembers it and the fit absorbs
    it into R_e_hous (4 % off). Either guard alone keeps the fit within 1 % of the plant's: the
    start from the line through the first half minute (:func:`start_reading`; it still leans a
    little towards the one high sample among its 31), or the start's offsets fitted alongside
    (:func:`start_with_directions`)."""
    from thermal_edge.data import Run
    from thermal_edge.estimation import calibrate as calibrate_module
    from thermal_edge.estimation.predict import start_reading, start_with_directions

    plant = make_run(pm10kw, "varied_drive.yaml", 2400.0, seed=9, noise=0.0)
    cols = {k: np.array(v, dtype=float) for k, v in plant.run.columns.items()}
    for s in pm10kw.sensors:
        t = np.asarray(plant.run.t, dtype=float)
        # the line through the first half minute: within rounding of the true first reading
        assert start_reading(cols[s], t, 0, 30.0) == pytest.approx(cols[s][0], abs=0.02)
        cols[s][0] += 0.3
        assert start_reading(cols[s], t, 0, 30.0) == pytest.approx(cols[s][0] - 0.3, abs=0.05)
    bumped = Run(plant.run.t, cols, "bumped")
    wrong = pm10kw.with_parameters({"R_e_hous": 5.0})

    def fitted() -> float:
        res = calibrate(wrong, [bumped], names=["R_e_hous"], decimation=5, maxiter=4, popsize=4, seed=1)
        return float(dict(zip(res.names, res.values))["R_e_hous"])

    def held(model, run, theta=None, k=0, span_s=0.0):  # the start, no direction of it free
        return start_with_directions(model, run, theta, k, span_s)[0], np.zeros((len(model.nodes), 0))

    assert fitted() == pytest.approx(9.1, rel=0.01)  # both guards
    monkeypatch.setattr(calibrate_module, "START_SPAN_S", 0.0)
    assert fitted() == pytest.approx(9.1, rel=0.01)  # the offsets fitted, from the one sample
    monkeypatch.setattr(calibrate_module, "start_with_directions", held)
    assert abs(fitted() / 9.1 - 1.0) > 0.03  # neither
    monkeypatch.setattr(calibrate_module, "START_SPAN_S", 30.0)
    assert fitted() == pytest.approx(9.1, rel=0.01)  # the line, the start held
    assert start_with_directions(pm10kw, bumped)[1].shape == (len(pm10kw.nodes), len(pm10kw.sensors))
