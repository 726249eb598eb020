"""The model's vocabulary: inputs and nodes asked for by role, one definition of "at rest".

Checked against the model files themselves (read as plain YAML, independently of the loader) and
against the small test model.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from lptn_ref import MACHINES, PADERBORN_DIR, tiny_plus_raw

from thermal_edge.lptn import DEFAULT_COLUMNS, NodeRole, Role, Stepper, cool_down, load_model
from thermal_edge.lptn.loader import build_model
from thermal_edge.lptn.vocabulary import FRAME, STATOR_IRON, parse_role

MODEL_FILES = sorted(MACHINES.glob("*.yaml"))


@pytest.mark.parametrize("path", MODEL_FILES, ids=[p.stem for p in MODEL_FILES])
def test_every_input_of_a_model_file_declares_a_known_role(path):
    raw = yaml.safe_load(path.read_text())
    for name, spec in raw["inputs"].items():
        assert "role" in spec, f"{path.name}: inputs.{name} declares no role"
        assert parse_role(spec["role"], Role).value == spec["role"]


@pytest.mark.parametrize("path", MODEL_FILES, ids=[p.stem for p in MODEL_FILES])
def test_model_answers_by_role_what_the_file_declares(path):
    if path.stem == "paderborn4":
        from lptn_ref import require_paderborn
        require_paderborn()
    raw = yaml.safe_load(path.read_text())
    model = load_model(path, data_dir=PADERBORN_DIR if path.stem == "paderborn4" else None)
    for name, spec in raw["inputs"].items():
        assert model.input_name(Role(spec["role"])) == name
    roles = {**{n["name"]: n.get("role") for n in raw.get("nodes", [])},
             **{a["name"]: a.get("role") for a in raw.get("arcs", [])}}
    for role in NodeRole:
        assert set(model.nodes_with(role)) == {n for n, r in roles.items() if r == role.value}
    limits_on_windings = [lim.node for lim in model.limits if lim.name == "hot_spot"]
    assert set(limits_on_windings) <= set(model.nodes_with(NodeRole.WINDING))


def test_missing_role_is_a_model_error_naming_the_model(tiny_model):
    from thermal_edge.errors import ThermalEdgeError
    from thermal_edge.lptn import ModelError

    assert tiny_model.find_input(Role.COOLANT) is None
    with pytest.raises(ModelError, match="tiny has no input with role 'coolant'") as err:
        tiny_model.input_name(Role.COOLANT)
    assert isinstance(err.value, ThermalEdgeError) and not isinstance(err.value, KeyError)
    assert not str(err.value).startswith("'")  # printed as it reads, not quoted as a KeyError's message


def test_node_groups(tiny_model):
    assert tiny_model.nodes_with(NodeRole.WINDING) == ("wind",)
    assert tiny_model.nodes_with(*STATOR_IRON) == ()
    assert tiny_model.nodes_with(*FRAME) == ()
    assert tiny_model.nodes_with(NodeRole.ROTOR_IRON, NodeRole.WINDING) == ("wind", "rotor")  # state order


def test_at_rest_holds_the_temperatures_and_zeroes_the_rest(tiny_plus_model):
    last = {"speed_rpm": 900.0, "i_rms": 12.0, "ambient_c": 31.0, "coolant_c": 40.0}
    assert tiny_plus_model.at_rest(last) == {"speed_rpm": 0.0, "i_rms": 0.0, "ambient_c": 31.0, "coolant_c": 40.0}
    with pytest.raises(ValueError, match="coolant_c"):
        tiny_plus_model.at_rest({"ambient_c": 20.0})
    with pytest.raises(ValueError, match="ambient_c"):
        tiny_plus_model.at_rest({"ambient_c": math.nan, "coolant_c": 20.0})


def test_a_boundary_input_without_a_role_is_still_a_temperature():
    raw = tiny_plus_raw()
    raw["inputs"]["coolant_c"] = {}
    model = build_model(raw, fname="x.yaml")
    assert model.temperature_inputs == ("ambient_c", "coolant_c")
    assert model.at_rest({"ambient_c": 20.0, "coolant_c": 50.0})["coolant_c"] == 50.0


def test_cool_down_is_one_zoh_step_at_rest(tiny_plus_model):
    theta = tiny_plus_model.nominal()
    T = np.array([80.0, 120.0, 60.0])
    last = {"speed_rpm": 900.0, "i_rms": 12.0, "ambient_c": 25.0, "coolant_c": 30.0}
    T1, Phi = cool_down(tiny_plus_model, theta, T, 600.0, last)
    # independent: 600 steps of 1 s at rest (ZOH is exact for held inputs, so the two agree)
    st = Stepper(tiny_plus_model, theta, 1.0, method="zoh")
    rest = {"speed_rpm": 0.0, "i_rms": 0.0, "ambient_c": 25.0, "coolant_c": 30.0}
    x = T.copy()
    for _ in range(600):
        x, _ = st.step(x, rest)
    np.testing.assert_allclose(T1, x, atol=1e-6)
    assert np.all(np.abs(np.linalg.eigvals(Phi)) < 1.0)
    T0, I = cool_down(tiny_plus_model, theta, T, 0.0, last)
    np.testing.assert_array_equal(T0, T)
    np.testing.assert_array_equal(I, np.eye(3))


def test_default_columns_name_every_role_once():
    assert set(DEFAULT_COLUMNS) == set(Role)
    assert len(set(DEFAULT_COLUMNS.values())) == len(Role)
    assert Role.CURRENT.default_column == "i_rms"


def test_plausible_ranges_name_the_unit_a_value_looks_like():
    """One value: kelvin named where the value converts into the range; a series: the unit when it
    is the series' (10 % or more outside, all plausible converted, or every value above the kelvin
    floor), else the first sample at fault."""
    import numpy as np

    from thermal_edge.lptn.vocabulary import LIMIT, TEMPERATURE, Role

    assert LIMIT.problem(155.0) is None
    assert "looks like kelvin (154.9 degC)" in LIMIT.problem(428.0)
    assert "outside" in LIMIT.problem(5.0) and "kelvin" not in LIMIT.problem(5.0)
    current = Role.CURRENT.plausible
    idle_then_load_ma = np.r_[np.zeros(50), np.linspace(5000, 30000, 50)]  # half the run idles in range
    assert current.series_problem(idle_then_load_ma)[0] is None
    assert "looks like mA" in current.series_problem(idle_then_load_ma)[1]
    spike = np.r_[np.linspace(5, 30, 200), 1e6, np.linspace(30, 5, 200)]
    k, why = current.series_problem(spike)
    assert k == 200 and "mA" not in why  # one sample: not the series' unit
    at, why = Role.AMBIENT.plausible.series_problem(np.r_[np.full(100, 25.0), 298.15, np.full(100, 25.0)])
    assert at == 100 and "looks like kelvin (25 degC)" in why  # one sample that converts into the rest's span
    negated = -np.linspace(5, 30, 200)  # a sign error: neither A nor mA makes it plausible
    k, why = current.series_problem(np.r_[0.0, negated])
    assert k == 1 and "outside" in why and "looks like" not in why
    warm_kelvin = np.full(30, 300.15)  # each value alone a plausible degC (a hot machine)
    assert TEMPERATURE.problem(290.0) is None and TEMPERATURE.series_problem(warm_kelvin)[0] is None
    assert current.series_problem(np.array([0.0, np.nan, 12.0])) is None  # NaN: not measured, not judged here


def test_a_sign_error_is_not_named_as_another_unit():
    """A negated RMS current converts to a few negative mA, inside the span of the idle samples but
    outside the plausible range: the sample is named as outside, not as given in mA."""
    import numpy as np

    from thermal_edge.lptn.vocabulary import Role

    negated = -np.r_[np.zeros(20), np.full(100, 7.14286)]
    k, why = Role.CURRENT.plausible.series_problem(negated)
    assert k == 20 and why == "-7.14286 A is outside the plausible 0 to 4000 A"
    one_in_ma = np.r_[np.full(50, 7.0), 7100.0, np.full(50, 7.0)]  # one sample in mA still is
    assert "looks like mA (7.1 A)" in Role.CURRENT.plausible.series_problem(one_in_ma)[1]
