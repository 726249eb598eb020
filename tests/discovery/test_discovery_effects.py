"""The effect catalogue: syntax, augmentations of the model file, zero effect, default magnitudes,
the score test's ranking, and the written YAML (a few lines patched into the original file)."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from benchmarks.discovery import PM10KW, UNOBSERVABLE
from thermal_edge.discovery import effects as E
from thermal_edge.discovery import hidden, yamlpatch
from thermal_edge.lptn import ModelError, Simulator, steady_state
from thermal_edge.shipped import config_path
from thermal_edge.sim.cycles import cycle_run, load_cycle

REFS = {"n_ref": 1200.0, "i_ref": 23.0}


def test_spec_syntax():
    assert E.parse_spec("copper_temperature") == ("copper_temperature", None, {})
    assert E.parse_spec("speed_convection:R_e_hous=k=0.8,m=1.2") == ("speed_convection", "R_e_hous", {"k": 0.8, "m": 1.2})
    assert E.parse_spec("sensor_lag:end_winding=tau=90") == ("sensor_lag", "end_winding", {"tau": 90.0})
    with pytest.raises(E.EffectError, match="unknown effect"):
        E.parse_spec("warp_drive")
    with pytest.raises(E.EffectError, match="has no parameter 'q'"):
        E.parse_spec("bearing_loss=q=3")
    with pytest.raises(E.EffectError, match="not a number"):
        E.parse_spec("bearing_loss=p=lots")
    assert issubclass(E.EffectError, ModelError)  # one-line CLI errors


def test_targets_of_pm10kw(pm10kw_raw, pm10kw_build):
    ctx = E.context(pm10kw_raw, pm10kw_build(pm10kw_raw), REFS, pm10kw_build)
    assert E.targets(ctx, E.get("copper_temperature")) == [None]
    groups = E.targets(ctx, E.get("speed_convection"))
    assert "R_e_hous" in groups and "h_gap0+h_gap1" in groups
    assert len(ctx.groups["R_e_hous"]) == 4  # the four housing-to-ambient conductances
    assert sorted(E.targets(ctx, E.get("sensor_lag"))) == ["end_winding", "housing", "slot_winding"]
    assert E.targets(ctx, E.get("ambient_offset")) == ["ambient"]
    assert "housing_6-yoke_1" in E.targets(ctx, E.get("contact_resistance"))
    # every catalogue effect applies to the 39-node model
    assert {c.effect.name for c in E.applicable(ctx)} == set(E.CATALOGUE)


def _sim(model, inputs, theta=None):
    first = model.at_rest({c: float(v[0]) for c, v in inputs.items()})
    T0, _ = steady_state(model, first, theta)
    tr = Simulator(model).simulate(model.nominal() if theta is None else theta, inputs, 10.0, T0)
    return {s: tr.node(n) for s, n in model.sensors.items()}


@pytest.fixture(scope="module")
def short_inputs(pm10kw_build, pm10kw_raw):
    model = pm10kw_build(pm10kw_raw)
    run = cycle_run(load_cycle(config_path("cycles", "varied_drive.yaml")), 5.6)
    idx = np.arange(0, len(run), 10)
    return {c: run.columns[c][idx] for c in model.inputs}


def test_zero_effect_leaves_the_model_unchanged(pm10kw_raw, pm10kw_build, short_inputs):
    """Every effect at its zero-effect value predicts what the plain model predicts."""
    base_model = pm10kw_build(pm10kw_raw)
    base = _sim(base_model, short_inputs)
    ctx = E.context(pm10kw_raw, base_model, REFS, pm10kw_build)
    seen = set()
    for cand in E.applicable(ctx):
        if cand.effect.name in seen:
            continue
        seen.add(cand.effect.name)
        doc, names, _ = E.augment(pm10kw_raw, [(cand, None)], REFS, pm10kw_build)
        m = pm10kw_build(doc)
        theta = m.nominal()
        sc = E.scale(ctx, cand)
        for p, n in zip(cand.effect.params, names[0]):
            theta[m.parameter_index([n])[0]] = p.null * sc if p.primary else p.nominal
        got = _sim(m, short_inputs, theta)
        tol = 0.2 if cand.effect.name == "sensor_lag" else 1e-6  # a 1 s lag (its zero) at 10 s steps
        for s in base:
            assert np.max(np.abs(got[s] - base[s])) < tol, (cand.label, s)


@pytest.mark.parametrize("spec", ["copper_temperature", "speed_convection:R_e_hous", "iron_loss_frequency",
                                  "magnet_eddy_loss", "bearing_loss", "housing_radiation", "natural_convection",
                                  "sensor_lag:end_winding", "ambient_offset", "contact_resistance:housing_6-yoke_1",
                                  "speed_convection:h_gap0+h_gap1"])
def test_default_magnitude_opens_a_visible_gap(spec, pm10kw_raw, pm10kw_build):
    """Hidden with its default magnitude, every effect makes the plant differ from the model by
    at least 1 K RMS on some sensor over the cycle (raised automatically where the catalogue
    default is too small for the target)."""
    model = pm10kw_build(pm10kw_raw)
    inputs = cycle_run(load_cycle(config_path("cycles", "varied_drive.yaml")), 5.6)
    refs = E.references(model, inputs.columns)
    doc, resolved = hidden.plant_document(pm10kw_raw, [spec], refs, pm10kw_build, inputs=inputs)
    assert hidden.sensor_gap(model, pm10kw_build(doc), inputs) >= 1.0, resolved


@pytest.mark.parametrize("spec", UNOBSERVABLE)
def test_a_joint_with_a_parallel_path_is_seen_by_no_sensor(spec, pm10kw_raw, pm10kw_build):
    """The front flange joint has a parallel path (housing_5 to the same end cap): raised to the
    largest resistance its bounds allow (an open joint), it moves no sensor by as much as the
    noise of the simulated PT100s (0.1 K RMS in 0.1 K steps: 0.104 K RMS) over the cycle, so
    simulated data with it carry no gap to find."""
    model = pm10kw_build(pm10kw_raw)
    inputs = cycle_run(load_cycle(config_path("cycles", "varied_drive.yaml")), 5.6)
    refs = E.references(model, inputs.columns)
    doc, resolved = hidden.plant_document(pm10kw_raw, [spec], refs, pm10kw_build, inputs=inputs)
    cand, values = resolved[0]
    ctx = E.context(pm10kw_raw, model, refs, pm10kw_build)
    assert values["R"] * 2 > cand.effect.params[0].upper * E.scale(ctx, cand)  # raised to its bound
    noise = float(np.hypot(0.1, 0.1 / np.sqrt(12.0)))  # K: Gaussian noise and the rounding's uniform error
    assert hidden.sensor_gap(model, pm10kw_build(doc), inputs) < noise, resolved


def test_hidden_effect_values_and_errors(pm10kw_raw, pm10kw_build):
    ctx = E.context(pm10kw_raw, pm10kw_build(pm10kw_raw), REFS, pm10kw_build)
    cand, vals = E.hidden_candidate(ctx, "speed_convection:R_e_hous=k=0.5")
    assert cand.label == "speed_convection:R_e_hous" and vals == {"k": 0.5, "m": 1.0}
    cand, vals = E.hidden_candidate(ctx, "ambient_offset")
    assert cand.label == "ambient_offset:ambient" and vals["dT"] == 4.0
    with pytest.raises(E.EffectError, match="needs a target"):
        E.hidden_candidate(ctx, "sensor_lag")
    with pytest.raises(E.EffectError, match="takes no target"):
        E.hidden_candidate(ctx, "bearing_loss:shaft_1")
    with pytest.raises(E.EffectError, match="unknown target"):
        E.hidden_candidate(ctx, "sensor_lag:rotor")


def test_copper_temperature_law(pm10kw_raw, pm10kw_build):
    """The added law is the model's own loss plus (k100 - 1)/100 per kelvin of it at t_ref."""
    doc, names, edits = E.augment(pm10kw_raw, [(E.Candidate(E.get("copper_temperature")), {"k100": 1.5, "t_ref": 40.0})],
                                  REFS, pm10kw_build)
    m = pm10kw_build(doc)
    law = next(l for l in m.losses if l.point == "slot_winding_1").power
    env = {"P_cu20": 100.0, "T.slot_winding_1": 90.0, "cuT_k100": 1.5, "cuT_t_ref": 40.0}
    f_sw = 0.092 / (0.092 + 2 * 0.045)
    x = lambda T: 100.0 * f_sw / 2 * (1 + 3.93e-3 * (T - 20))  # noqa: E731
    assert float(law.compile()(env)) == pytest.approx(x(90.0) + 0.5 / 100 * 50.0 * x(40.0), rel=1e-9)
    assert names == [["cuT_k100", "cuT_t_ref"]]
    assert sum(e.kind == "list_replace" for e in edits) == 4  # 2 slot + 2 end-winding losses


def test_sensor_lag_moves_the_sensor(pm10kw_raw, pm10kw_build):
    ctx = E.context(pm10kw_raw, pm10kw_build(pm10kw_raw), REFS, pm10kw_build)
    doc, names, _ = E.augment(pm10kw_raw, [(E.Candidate(E.get("sensor_lag"), "end_winding"), {"tau": 60.0})], REFS, pm10kw_build)
    m = pm10kw_build(doc)
    assert m.sensors["end_winding"] == "end_winding_probe"
    c = m.capacities[m.node_index("end_winding_probe")]
    assert float(c.compile()({"lag_end_winding_tau": 60.0})) == pytest.approx(60.0 * E.PROBE_G)
    del ctx, names


def test_written_model_is_the_original_plus_a_few_lines(pm10kw_raw, pm10kw_build, tmp_path):
    text = PM10KW.read_text()
    doc, _, _ = E.augment(pm10kw_raw, [(E.Candidate(E.get("speed_convection"), "R_e_hous"), {"k": 0.7, "m": 1.1})],
                          REFS, pm10kw_build)
    out = yamlpatch.render(text, pm10kw_raw, doc, "speed_convection:R_e_hous", "header line")
    assert yaml.safe_load(out) == doc
    old_lines, new_lines = set(text.splitlines()), out.splitlines()
    added = [ln for ln in new_lines if ln not in old_lines]
    assert len(added) <= 2 + 4 * 2 + 1  # 2 parameters, 4 changed conductances (+ "was" comments), header
    assert all("speed_convection:R_e_hous" in ln or ln.lstrip().startswith("#") for ln in added)
    # the comments of the original file are kept
    assert "# Node numbering (Table 1)" in out
    p = tmp_path / "m.yaml"
    p.write_text(out)
    from thermal_edge.lptn import load_model

    m = load_model(p)
    assert m.parameter_index(["sc_R_e_hous_k"]).size == 1
