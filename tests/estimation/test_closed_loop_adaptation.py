"""Online adaptation in closed loop: a model that is not the machine yet may trade a sensor it
predicts better than its average for a large gain elsewhere; what the operator sees of it."""
from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest

from thermal_edge.estimation.adapter import Decision, judge

NOISE, Z, GAIN, TOL = 0.15, 2.0, 0.5, 0.02  # config/edge.yaml's judge


def _stalled_evidence(rng: np.random.Generator, housing_after: float) -> tuple[dict, dict, np.ndarray]:
    """Ten periods as the demo's judge saw them once the housing was learned: the champion 1.3 K
    off on both windings and 0.16 K on the housing, the challenger 0.4 K on the windings and
    ``housing_after`` on the housing (errors as constant offsets plus PT100 noise)."""
    n, per = 1800, 180
    noise = {s: rng.normal(0, 0.1, n) for s in ("slot_winding", "end_winding", "housing")}
    champ = {"slot_winding": 1.33 + noise["slot_winding"], "end_winding": 1.17 + noise["end_winding"],
             "housing": 0.16 + noise["housing"]}
    chal = {"slot_winding": 0.40 + noise["slot_winding"], "end_winding": 0.32 + noise["end_winding"],
            "housing": housing_after + noise["housing"]}
    return champ, chal, np.repeat(np.arange(n // per), per)


def _rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)))


def test_a_sensor_predicted_better_than_the_average_does_not_veto_a_large_gain():
    champ, chal, blocks = _stalled_evidence(np.random.default_rng(5), 0.45)
    # counted independently: the housing's RMS error grows by far more than the 0.02 K tolerance
    # (the per-sensor veto that refused every such challenger), yet stays below the champion's
    # RMS error over all three sensors
    grow = _rms(chal["housing"]) - _rms(champ["housing"])
    overall = _rms(np.concatenate(list(champ.values())))
    assert grow > 0.25 and _rms(chal["housing"]) < overall
    gain = np.mean(np.concatenate(list(champ.values())) ** 2) - np.mean(np.concatenate(list(chal.values())) ** 2)
    v = judge(champ, chal, NOISE, Z, GAIN, TOL, share=1.0, blocks=blocks)
    assert v.improvement_k2 == pytest.approx(gain, rel=1e-9)
    assert v.outcome == "promote" and v.vetoed_by == ()


def test_a_sensor_left_worse_than_the_model_in_use_predicts_on_average_still_vetoes():
    # the same windings' gain, but the housing ends worse than the champion's overall error
    champ, chal, blocks = _stalled_evidence(np.random.default_rng(6), 1.08)
    overall = _rms(np.concatenate(list(champ.values())))
    assert _rms(chal["housing"]) > overall
    v = judge(champ, chal, NOISE, Z, GAIN, TOL, share=1.0, blocks=blocks)
    assert v.improvement_k2 > v.margin_k2  # better in all, still refused
    assert v.outcome == "drop" and v.vetoed_by == ("housing",)


def test_the_operator_sees_the_last_refusal_on_metrics_in_monitor_and_in_the_status_line(tmp_path: Path):
    from thermal_edge.bench.protection import edge_config
    from thermal_edge.monitor.snapshot import from_metrics
    from thermal_edge.monitor.view import render
    from thermal_edge.service import status_line
    from thermal_edge.service.adaptation import AdaptationResult
    from thermal_edge.service.engine import ThermalEngine
    from thermal_edge.service.metrics import ServiceMetrics

    eng = ThermalEngine(edge_config(tmp_path), worker_mode="sync")
    try:
        m = ServiceMetrics()
        m.attach(eng)
        assert re.search(r'thermal_edge_adaptation_status\{thermal_edge_adaptation_status="starting"\} 1', m.text())
        d = Decision(t=5000.0, error_before_k=1.2, triggered=True, verdict="dropped", refusal="predicts housing worse",
                     evaluations=2, reason="challenger dropped (predicts housing worse) on the 1800 s after its fit: ...")
        eng.adaptation._apply(AdaptationResult(1, 5000.0, decision=d, theta=eng.adaptation.theta))
        text = m.text()
        assert re.search(r'thermal_edge_adaptation_status\{thermal_edge_adaptation_status="refusing"\} 1', text)
        assert re.search(r'thermal_edge_adaptation_last_refusal_timestamp_seconds\{reason="predicts housing worse"\} 5000', text)
        snap = from_metrics(text, "test")
        assert snap.adapt_status == "refusing" and snap.adapt_refusal == "predicts housing worse"
        assert "adaptation status: refusing   last refusal: predicts housing worse" in render(snap)
        # a later challenger under judgement: waiting for evidence; the last refusal stays on show
        d2 = Decision(t=5180.0, error_before_k=1.2, triggered=True, verdict="undecided", evaluations=2)
        eng.adaptation._apply(AdaptationResult(2, 5180.0, decision=d2, theta=eng.adaptation.theta))
        snap = from_metrics(m.text(), "test")
        assert snap.adapt_status == "waiting_for_evidence" and snap.adapt_refusal == "predicts housing worse"
        out = dataclasses.replace(eng.placeholder(5180.0), adapt_status=eng.adaptation.status)
        assert status_line(out).endswith("model waiting for evidence")
        out = dataclasses.replace(out, adapt_status="refusing", adapt_refusal="not better")
        assert status_line(out).endswith("model refusing (not better)")
    finally:
        eng.close()


@pytest.mark.slow
def test_the_demo_scenario_that_stalled_learns_in_closed_loop():
    """The demo's closed loop (Table 4 start, overload cycle, derating active), first 1.5 h: the
    per-sensor veto kept the model at 1.3 K on the windings while challengers at 0.4 K were
    refused; now the housing is learned, then the windings, and each promotion predicts the
    next hour better (computed by the bench from the observer's state with the parameters before
    and after)."""
    from thermal_edge.bench import adaptation as ab

    r = ab.run_scenario(dataclasses.replace(ab.SCENARIOS["demo"], duration_s=5400.0))
    assert len(r.promotions) >= 2
    assert all(p.next_after_k < p.next_before_k for p in r.promotions)
    assert not any("worse" in why for _, why in r.refusals)
    assert r.final_pred_err_k <= ab.WITHIN_K and math.isfinite(r.within_1k_from_s)
    # the housing's resistance to ambient (the slowest mode, 5.1 at the start) learned to 5 %
    assert abs(r.final["R_e_hous"] / r.plant["R_e_hous"] - 1.0) < 0.05
    assert r.derated_s > 0.0 and r.peak_hot_spot_c > 140.0  # closed loop: the hot spot near its limit, derated


@pytest.mark.slow
@pytest.mark.parametrize("name", ["demo", "varied"])
def test_the_identifiable_parameters_end_within_10_percent_of_the_plant(name: str):
    """The whole 3 h in closed loop. Once the open-loop error was within the threshold no fit was
    made, and a challenger at the window's optimum, judged from the observer's state (which suits
    the parameters in use), was dropped: ``r_c_hous`` (yoke to housing, pinned to 2 % by the data)
    ended +12.9 % in the demo and +15.6 % on the varied cycle. Now the window's pinned step
    triggers a refinement, judged from the challenger's own shadow observer, and every
    identifiable parameter ends within 10 % of the plant's (the bench's own figures, computed from
    the plant's parameters), with no promotion that made the next hour worse."""
    from thermal_edge.bench import adaptation as ab

    r = ab.run_scenario(ab.SCENARIOS[name])
    assert "r_c_hous" in r.identifiable
    errors = r.param_errors_pct
    assert all(abs(errors[k]) <= 100 * ab.PARAM_TOLERANCE for k in r.identifiable), errors
    assert any(kind.startswith("the window pins") for kind in r.outcomes)
    assert r.final_pred_err_k <= ab.WITHIN_K and not any(p.harmed for p in r.promotions)
    assert r.passed


@pytest.mark.slow
def test_at_the_plant_s_parameters_nothing_is_promoted_in_closed_loop():
    from thermal_edge.bench import adaptation as ab

    r = ab.run_scenario(ab.SCENARIOS["at_plant"])
    assert not r.promotions and not any(kind.startswith("the window pins") for kind in r.outcomes)


def test_a_restart_shows_what_the_saved_decisions_left(tmp_path: Path):
    from thermal_edge.bench.protection import edge_config
    from thermal_edge.service.adaptation import Adaptation
    from thermal_edge.service.engine import load_service_model
    from thermal_edge.service.persistence import PersistedState

    cfg = edge_config(tmp_path)
    model = load_service_model(cfg)
    dropped = Decision(t=100.0, error_before_k=1.0, triggered=True, verdict="dropped", refusal="not better",
                       reason="challenger dropped (not better) on the 1800 s after its fit; challenger fitted")
    waiting = Decision(t=280.0, error_before_k=1.0, triggered=True, verdict="undecided")
    saved = PersistedState(model=model.name, saved_at=300.0, parameters={},
                           decisions=[dropped.as_dict(), waiting.as_dict()])
    ad = Adaptation(model, cfg.adaptation, 1.0, True, 500, saved, worker_mode="sync")
    try:
        assert ad.status == "waiting_for_evidence"
        assert ad.last_refusal == (100.0, "not better", "challenger dropped (not better) on the 1800 s after its fit")
    finally:
        ad.close()


def test_a_challenger_with_too_few_samples_scored_is_said_so_not_as_a_nan_score():
    """After a state re-initialised by a model fault the periods after a fit may hold fewer than
    three samples with both predictions finite: the judge waits, then drops, and the log says why in
    words (it had said ``MSE +nan K²``)."""
    from thermal_edge.estimation.adapter import drop_cause, judge, verdict_reason

    nan = np.full(10, np.nan)
    some = np.concatenate([np.full(8, np.nan), [0.3, 0.2]])
    for share, outcome, words in ((0.5, "wait", "waiting for the next period"),
                                  (1.0, "drop", "challenger dropped (never scored)")):
        v = judge({"winding": some}, {"winding": nan}, 0.1, 2.0, 0.05, 1.0, share=share)
        assert v.outcome == outcome and v.samples == 0 and not np.isfinite(v.improvement_k2)
        reason = verdict_reason(v, 180.0)
        assert "nan" not in reason.lower() and words in reason and "too few of them scored (0 with" in reason, reason
    assert drop_cause(v) == "never scored"
    # a scored verdict keeps its numbers
    rng = np.random.default_rng(0)
    a, b = 0.5 + 0.05 * rng.standard_normal(200), 0.05 * rng.standard_normal(200)
    v = judge({"winding": a}, {"winding": b}, 0.1, 2.0, 0.05, 1.0, share=1.0)
    assert v.outcome == "promote" and verdict_reason(v, 1800.0).startswith("challenger promoted: better on the 1800 s "
                                                                            f"after its fit: MSE {v.improvement_k2:+.4g} K²")
