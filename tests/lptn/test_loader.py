"""Model files: every error names the file and the key (``<file>: <key>: ...``).

Each case writes a broken variant of the small model to a temporary YAML file, loads it with
``load_model`` and checks that the :class:`ModelError` message starts with the file name and the
offending key.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from lptn_ref import tiny_plus_raw, tiny_raw

from thermal_edge.lptn import ModelError, ParameterError, load_model
from thermal_edge.lptn.expr import evaluate_const


def write(tmp_path: Path, raw, name: str = "bad_model.yaml") -> Path:
    p = tmp_path / name
    p.write_text(raw if isinstance(raw, str) else yaml.safe_dump(raw, sort_keys=False, allow_unicode=True))
    return p


def mutate(fn):
    raw = tiny_raw()
    fn(raw)
    return raw


def _set(path, value):
    def f(raw):
        d = raw
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value

    return f


def _del(path):
    def f(raw):
        d = raw
        for k in path[:-1]:
            d = d[k]
        del d[path[-1]]

    return f


def _chain(*fs):
    def f(raw):
        for g in fs:
            g(raw)

    return f


CASES = [
    # (id, mutation, expected key, words the message should contain)
    ("unknown section", _set(["materialz"], {}), "materialz", "unknown section"),
    ("missing name", _del(["name"]), "name", "required"),
    ("missing arc r1", _del(["arcs", 0, "r1"]), "arcs[0].r1", "required"),
    ("missing arc material", _del(["arcs", 1, "material"]), "arcs[1].material", "required"),
    ("missing node capacity", _del(["nodes", 0, "capacity"]), "nodes[0].capacity", "required"),
    ("missing parameter min", _del(["parameters", "R_amb", "min"]), "parameters.R_amb.min", "required"),
    ("missing parameter value", _del(["parameters", "h_gap", "value"]), "parameters.h_gap.value", "required"),
    ("missing loss power", _del(["losses", 1, "power"]), "losses[1].power", "required"),
    ("missing sensor node", _set(["sensors", "w"], {"doc": "wind"}), "sensors.w.node", "required"),
    ("unknown sensor key", _set(["sensors", "w"], {"nod": "wind"}), "sensors.w.nod", "unknown key"),
    ("missing between", _set(["conductances", 0], {"r": "R_amb"}), "conductances[0].between", "required"),
    ("missing material property", _del(["materials", "fe", "c_p"]), "materials.fe.c_p", "required"),
    ("no inputs", _set(["inputs"], {}), "inputs", "input"),
    ("bad law syntax", _set(["conductances", 2, "g"], "h_gap * (1 + "), "conductances[2].g", ""),
    ("bad law function", _set(["conductances", 2, "g"], "h_gap * sin(speed_rpm)"), "conductances[2].g", "unknown function"),
    ("bad law arity", _set(["losses", 1, "power"], "max(speed_rpm)"), "losses[1].power", "argument"),
    ("bad law import", _set(["losses", 1, "power"], "__import__('os')"), "losses[1].power", ""),
    ("bad law attribute", _set(["losses", 1, "power"], "speed_rpm.__class__"), "losses[1].power", "speed_rpm.__class__"),
    ("temperature in conductance", _set(["conductances", 2, "g"], "h_gap * (1 + T.wind/100)"), "conductances[2].g", "T.wind"),
    ("temperature in resistance", _set(["conductances", 0, "r"], "R_amb * (1 + T.yoke/1000)"), "conductances[0].r", "T.yoke"),
    ("input in capacity", _set(["nodes", 0, "capacity"], "2000 + speed_rpm"), "nodes[0].capacity", "speed_rpm"),
    ("temperature in capacity", _set(["nodes", 0, "capacity"], "2000 * T.rotor"), "nodes[0].capacity", "T.rotor"),
    ("input in material", _set(["materials", "cu", "c_p"], "c_w * (1 + i_rms)"), "materials.cu.c_p", "i_rms"),
    ("unknown name in loss", _set(["losses", 0, "power"], "3*R_x*i_rms**2"), "losses[0].power", "R_x"),
    ("temperature of a point in loss", _set(["losses", 0, "power"], "T.wind/radial"), "losses[0].power", ""),
    ("temperature of unknown node", _set(["losses", 0, "power"], "i_rms * T.stator"), "losses[0].power", "T.stator"),
    ("unknown material", _set(["arcs", 0, "material"], "m270"), "arcs[0].material", "m270"),
    ("unknown material property", _set(["materials", "fe", "k_z"], 3), "materials.fe.k_z", "unknown material property"),
    ("r2 equal r1", _set(["arcs", 0, "r2"], 0.1), "arcs[0].r2", "greater than r1"),
    ("r2 below r1", _set(["arcs", 1, "r2"], 0.05), "arcs[1].r2", "greater than r1"),
    ("negative theta", _set(["arcs", 1, "theta"], -1.0), "arcs[1].theta", "positive"),
    ("theta in degrees", _set(["arcs", 1, "theta"], 30.0), "arcs[1].theta", "exceeds a full circle (2π = 6.283 rad): "
     "theta is in rad (30 deg = 0.5236 rad)"),
    ("a negative conductance", _set(["conductances", 0, "r"], -0.5), "conductances[0].r", "must be positive, is -0.5 K/W"),
    ("zero length", _set(["arcs", 0, "length"], 0), "arcs[0].length", "positive"),
    ("unknown endpoint", _set(["conductances", 1, "between"], ["yoke.r_inn", "wind.r_out"]), "conductances[1].between",
     "yoke.r_inn"),
    ("unknown endpoint node", _set(["conductances", 3, "between"], ["stator", "ambient"]), "conductances[3].between", "stator"),
    ("one endpoint", _set(["conductances", 3, "between"], ["rotor"]), "conductances[3].between", "two"),
    ("same endpoints", _set(["conductances", 3, "between"], ["rotor", "rotor"]), "conductances[3].between", "rotor"),
    ("both g and r", _set(["conductances", 3, "g"], 0.2), "conductances[3]", "not both"),
    ("no law without face", _del(["conductances", 3, "r"]), "conductances[3]", "needs g or r"),
    ("sensor on algebraic point", _set(["sensors", "w"], {"node": "wind/radial"}), "sensors.w.node", "heat capacity"),
    ("sensor on boundary", _set(["sensors", "w"], {"node": "ambient"}), "sensors.w.node", "heat capacity"),
    ("sensor on unknown node", _set(["sensors", "w"], {"node": "magnet"}), "sensors.w.node", "magnet"),
    ("loss on unknown node", _set(["losses", 1, "node"], "housing"), "losses[1].node", "housing"),
    ("value above max", _set(["parameters", "R_amb", "value"], 10.0), "parameters.R_amb", "outside"),
    ("value below min", _set(["parameters", "c_w", "value"], 50.0), "parameters.c_w", "outside"),
    ("min not positive", _set(["parameters", "k_cu", "min"], 0.0), "parameters.k_cu.min", "positive"),
    ("parameter shadows input", _set(["parameters", "speed_rpm"], {"value": 1, "min": 0.5, "max": 2}), "parameters.speed_rpm",
     "already used"),
    ("parameter shadows constant", _set(["parameters", "alpha"], {"value": 1, "min": 0.5, "max": 2}), "parameters.alpha",
     "already used"),
    ("boundary of undeclared input", _set(["boundaries", "coolant"], "coolant_c"), "boundaries.coolant", "coolant_c"),
    ("duplicate node name", _set(["nodes", 0, "name"], "wind"), "nodes[0]", "already declared"),
    ("bad discretisation", _set(["discretisation"], {"method": "rk4"}), "discretisation.method", "rk4"),
    ("bad substep", _set(["discretisation"], {"method": "euler", "max_substep_s": -1}), "discretisation.max_substep_s",
     "positive"),
    ("limits inverted", _set(["limits"], {"hot": {"node": "wind", "warn_c": 150, "max_c": 140}}), "limits.hot", "warn_c"),
    ("limit a word", _set(["limits"], {"hot": {"node": "wind", "warn_c": "hot", "max_c": 140}}), "limits.hot.warn_c",
     "expected a number"),
    ("limit on point", _set(["limits"], {"hot": {"node": "yoke/circ", "warn_c": 100, "max_c": 140}}), "limits.hot.node",
     "heat capacity"),
    ("constant not a number", _set(["constants", "alpha"], "speed_rpm * 2"), "constants.alpha", "speed_rpm"),
    ("derived uses parameter", _set(["derived"], {"n": "speed_rpm / R_amb"}), "derived.n", "R_amb"),
    ("arcs not a list", _set(["arcs"], {"name": "x"}), "arcs", "list"),
    ("parameters not a mapping", _set(["parameters"], [1, 2]), "parameters", "mapping"),
    ("unknown input role", _set(["inputs", "i_rms"], {"role": "curent"}), "inputs.i_rms.role", "did you mean 'current'"),
    ("input role twice", _set(["inputs", "ambient_c"], {"role": "speed"}), "inputs.ambient_c.role", "speed_rpm"),
    ("unknown input key", _set(["inputs", "i_rms"], {"rol": "current"}), "inputs.i_rms.rol", "unknown key"),
    ("unknown node role", _set(["nodes", 0, "role"], "magnit"), "nodes[0].role", "did you mean 'magnet'"),
    ("unknown arc role", _set(["arcs", 1, "role"], "windings"), "arcs[1].role", "did you mean 'winding'"),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_error_names_file_and_key(tmp_path, case):
    _, fn, key, words = case
    p = write(tmp_path, mutate(fn))
    with pytest.raises(ModelError) as ei:
        load_model(p)
    msg = str(ei.value)
    assert msg.startswith(f"bad_model.yaml: {key}: "), msg
    assert words in msg, msg


def test_unknown_top_level_is_named_even_among_valid_ones(tmp_path):
    raw = tiny_raw()
    raw["sensor"] = raw.pop("sensors")  # a typo of a known section
    with pytest.raises(ModelError, match=r"^bad_model\.yaml: sensor: unknown section"):
        load_model(write(tmp_path, raw))


@pytest.mark.parametrize(
    "text",
    ["name: tiny\ninputs: {a: {}\n", "name: [unclosed\n", "name: tiny\n  inputs:\n bad indent: 1\n", "\tname: tab\n"],
)
def test_bad_yaml_names_the_file(tmp_path, text):
    p = write(tmp_path, text)
    with pytest.raises(ModelError) as ei:
        load_model(p)
    assert str(ei.value).startswith("bad_model.yaml: "), str(ei.value)
    assert "YAML" in str(ei.value)


@pytest.mark.parametrize("text", ["- just\n- a list\n", "42\n", "''\n"])
def test_top_level_not_a_mapping(tmp_path, text):
    with pytest.raises(ModelError, match=r"^bad_model\.yaml: \(top\): "):
        load_model(write(tmp_path, text))


def test_missing_file_names_the_path(tmp_path):
    p = tmp_path / "nowhere.yaml"
    with pytest.raises(ModelError) as ei:
        load_model(p)
    assert "nowhere.yaml" in str(ei.value)


def test_missing_table_file_names_the_key(tmp_path):
    raw = tiny_raw()
    raw["tables"] = {"drag": {"file": "drag_missing.csv", "kind": "curve"}}
    p = write(tmp_path, raw)
    with pytest.raises(ModelError, match=r"^bad_model\.yaml: tables\.drag\.file: .*drag_missing\.csv"):
        load_model(p, data_dir=tmp_path)


def test_table_arity_and_dependence(tmp_path):
    (tmp_path / "curve.csv").write_text("x,y\n0,0\n1000,10\n2000,40\n")
    raw = tiny_raw()
    raw["tables"] = {"drag": {"file": "curve.csv", "kind": "curve", "lookup": "linear"}}
    raw["losses"][1]["power"] = "drag(speed_rpm, i_rms)"
    with pytest.raises(ModelError, match=r"^bad_model\.yaml: losses\[1\]\.power: .*argument"):
        load_model(write(tmp_path, raw), data_dir=tmp_path)
    raw["losses"][1]["power"] = "drag(speed_rpm)"
    m = load_model(write(tmp_path, raw, "good.yaml"), data_dir=tmp_path)
    f = m.losses[1].power.compile()
    assert float(np.asarray(f({"speed_rpm": 1500.0}))) == pytest.approx(25.0)  # linear between 10 and 40


# ---------------------------------------------------------------------------------------------
# what a valid file becomes


def test_valid_model_loads_and_is_flattened(tmp_path):
    m = load_model(write(tmp_path, tiny_raw(), "tiny.yaml"))
    assert m.name == "tiny"
    assert m.nodes == ("yoke", "wind", "rotor")
    assert set(m.points) == {f"{a}/{d}" for a in ("yoke", "wind") for d in ("radial", "circ", "axial")}
    assert m.parameter_names == ("R_amb", "k_cu", "c_w", "h_gap")
    assert m.sensors == {"w": "wind"}
    assert m.boundaries == {"ambient": "ambient_c"}
    # constants are inlined: no law mentions alpha
    assert all("alpha" not in l.power.free() for l in m.losses)
    assert m.losses[0].power.free() == {"i_rms", "T.wind"}
    # capacity of the winding arc: c_w · ρ · θ/2 · L · (r2² − r1²), a law in c_w
    cap = m.capacities[1]
    assert cap.free() == {"c_w"}
    assert float(np.asarray(cap.compile()({"c_w": 400.0}))) == pytest.approx(400 * 8900 * 1.5 * 0.1 * (0.01 - 0.0064), rel=1e-13)
    assert evaluate_const(m.capacities[2]) == 2000.0


def test_face_resistance_in_series_and_explicit_law(tmp_path):
    """A face with one connection is joined in series: g = 1/(R_face + r); face-to-face with no
    law: g = 1/(R_face_a + R_face_b); a g law with a face: g = 1/(R_face + 1/g)."""
    from thermal_edge.lptn.elements import arc_resistances
    from thermal_edge.lptn.expr import Num

    m = load_model(write(tmp_path, tiny_raw(), "tiny.yaml"))
    k_cu = 2.0
    yoke = arc_resistances(0.1, 0.12, 6.28, 0.1, Num(28.0), Num(2.0), Num(28.0))["radial"]
    wind = arc_resistances(0.08, 0.1, 3.0, 0.1, Num(k_cu), Num(300.0), Num(k_cu))["radial"]
    yr = [evaluate_const(x) for x in yoke]
    wr = [evaluate_const(x) for x in wind]
    env = {"R_amb": 0.5, "k_cu": k_cu, "c_w": 400.0, "h_gap": 20.0, "speed_rpm": 1000.0}
    g = {e.key: float(np.asarray(e.g.compile()(env))) for e in m.edges}
    assert g["conductances[0]"] == pytest.approx(1 / (yr[0] + 0.5), rel=1e-13)  # yoke.r_out (R1) + R_amb
    assert g["conductances[1]"] == pytest.approx(1 / (yr[1] + wr[0]), rel=1e-13)  # yoke.r_in + wind.r_out
    assert g["conductances[2]"] == pytest.approx(1 / (wr[1] + 1 / (20 * 2)), rel=1e-13)
    assert g["conductances[3]"] == pytest.approx(0.2, rel=1e-15)
    assert g["arcs[0] (radial interior)"] == pytest.approx(1 / yr[2], rel=1e-13)


def test_face_with_two_connections_gets_a_point(tmp_path):
    m = load_model(write(tmp_path, tiny_plus_raw(), "plus.yaml"))
    assert "yoke/r_out" in m.points and "gap" in m.points
    ends = {frozenset((e.a, e.b)) for e in m.edges}
    assert frozenset(("yoke/radial", "yoke/r_out")) in ends  # the face resistance alone
    assert frozenset(("yoke/r_out", "ambient")) in ends and frozenset(("yoke/r_out", "coolant")) in ends


def test_face_with_two_connections_needs_laws(tmp_path):
    raw = tiny_plus_raw()
    del raw["conductances"][1]["r"]  # yoke.r_out -> coolant without a law
    with pytest.raises(ModelError, match=r"^bad_model\.yaml: conductances\[1\]: needs g or r"):
        load_model(write(tmp_path, raw))


def test_paderborn_model_file_loads():
    from lptn_ref import PADERBORN_YAML, require_paderborn

    d = require_paderborn()
    m = load_model(PADERBORN_YAML, data_dir=d)
    assert m.nodes == ("pm", "sy", "st", "sw") and len(m.parameters) == 9


def test_pm10kw_model_file_loads():
    from lptn_ref import PADERBORN_DIR, PM10KW_YAML, require_pm10kw

    require_pm10kw()
    m = load_model(PM10KW_YAML, data_dir=PADERBORN_DIR if PADERBORN_DIR.is_dir() else None)
    assert len(m.adaptable) == 14
    for p in m.parameters:
        assert 0 < p.lower <= p.value <= p.upper, p.name


# ---------------------------------------------------------------------------------------------
# unknown keys and parameter overrides



@pytest.mark.parametrize(
    "case",
    [
        ("conductance R for r", _set(["conductances", 0], {"between": ["yoke.r_out", "ambient"], "R": "R_amb"}),
         "conductances[0].R"),
        ("arc count typo", _set(["arcs", 0, "cuont"], 12), "arcs[0].cuont"),
        ("parameter adaptable typo", _set(["parameters", "R_amb", "adaptible"], True), "parameters.R_amb.adaptible"),
        ("loss key typo", _set(["losses", 1, "powr"], "1"), "losses[1].powr"),
    ],
    ids=lambda c: c[0],
)
def test_unknown_key_inside_an_entry_is_an_error(tmp_path, case):
    _, fn, key = case
    with pytest.raises(ModelError) as ei:
        load_model(write(tmp_path, mutate(fn)))
    assert str(ei.value).startswith(f"bad_model.yaml: {key}: ")


def test_with_parameters_replaces_nominal_values(tiny_model):
    m2 = tiny_model.with_parameters({"R_amb": 1.5, "h_gap": 30.0})
    assert dict(zip(m2.parameter_names, m2.nominal())) == {"R_amb": 1.5, "k_cu": 2.0, "c_w": 400.0, "h_gap": 30.0}
    lo, hi = m2.bounds()
    assert list(lo) == [0.1, 0.5, 100, 1] and list(hi) == [5, 10, 1000, 100]
    with pytest.raises(ParameterError, match="R_x"):
        tiny_model.with_parameters({"R_x": 1.0})


def test_with_parameters_refuses_a_value_outside_the_bounds_unless_widening_is_explicit(tiny_model):
    with pytest.raises(ParameterError) as ei:
        tiny_model.with_parameters({"R_amb": 10.0})
    assert "R_amb" in str(ei.value) and "10" in str(ei.value) and "[0.1, 5]" in str(ei.value)
    assert ei.value.bounds == (0.1, 5.0) and ei.value.value == 10.0
    m2 = tiny_model.with_parameters({"R_amb": 10.0}, widen_bounds=True)  # a simulated plant only
    p = m2.parameters[0]
    assert (p.lower, p.upper) == (0.1, 10.0)
    assert p.value == 10.0
    with pytest.raises(ParameterError, match="R_x"):
        tiny_model.with_parameters({"R_x": 1.0}, widen_bounds=True)


def test_check_parameters_names_value_bounds_and_a_close_match(tiny_model):
    tiny_model.check_parameters({"R_amb": 0.1, "k_cu": 10.0})  # the bounds themselves are inside
    for bad in ({"R_amb": 5.000001}, {"c_w": float("nan")}, {"c_w": "400"}, {"c_w": True}):
        with pytest.raises(ParameterError) as ei:
            tiny_model.check_parameters(bad)
        assert str(ei.value).startswith(f"parameter {next(iter(bad))}: ")
    with pytest.raises(ParameterError) as ei:
        tiny_model.check_parameters({"R_ambb": 1.0})
    assert ei.value.suggestion == "R_amb" and "did you mean 'R_amb'" in str(ei.value)
    with pytest.raises(ParameterError) as ei:
        tiny_model.check_parameters({"zzz": 1.0})
    assert ei.value.suggestion is None and "did you mean" not in str(ei.value)


def test_snap_to_bounds_moves_only_round_off_onto_a_bound(tiny_model):
    below = float(np.exp(np.log(0.1)) * (1 - 1e-15))
    snapped = tiny_model.snap_to_bounds({"R_amb": below, "k_cu": 10.0 * (1 + 2e-10), "c_w": 99.0, "h_gap": 50.0})
    assert snapped == {"R_amb": 0.1, "k_cu": 10.0, "c_w": 99.0, "h_gap": 50.0}
    tiny_model.check_parameters({k: v for k, v in snapped.items() if k != "c_w"})


@pytest.mark.parametrize("name, text, kind, says", [
    ("wide.csv", "x,y\n0,0\n1000,10,5\n2000,40\n", "curve", "line 3: 3 values, the header has 2"),
    ("nan.csv", "x,y\n0,0\n1000,nan\n2000,40\n", "curve", "line 3: 'nan' is not a finite number"),
    ("text.csv", "x,y\n0,0\n1000,abc\n2000,40\n", "curve", "line 3: 'abc' is not a number"),
    ("twice.csv", "x,y\n0,0\n1000,10\n1000,40\n", "curve", "line 4: the x does not rise (1000 then 1000)"),
    ("grid.csv", "i/n,0,1000\n10,1,2\n0,3,4\n20,5,6\n", "grid2d", "line 3: the row axis does not rise (10 then 0)"),
    ("short.csv", "x,y\n0,0\n", "curve", "2 non-empty lines: a header and at least two rows are needed"),
])
def test_a_malformed_table_names_its_line(tmp_path, name, text, kind, says):
    """A table file's rows are read as the run CSVs are: each one's width, numbers and order
    checked at load, the line named (a wide row, a NaN, a repeated x or a grid axis out of order
    would otherwise be read without a word, or overflow a law at an operating point later)."""
    (tmp_path / name).write_text(text)
    raw = tiny_raw()
    raw["tables"] = {"drag": {"file": name, "kind": kind}}
    with pytest.raises(ModelError) as ei:
        load_model(write(tmp_path, raw), data_dir=tmp_path)
    assert str(ei.value) == f"bad_model.yaml: tables.drag: cannot read {tmp_path / name}: {says}"


def test_an_unknown_table_kind_is_named_before_the_file_is_looked_for(tmp_path):
    raw = tiny_raw()
    raw["tables"] = {"drag": {"file": "nowhere.csv", "kind": "spline3d"}}
    with pytest.raises(ModelError, match=r"^bad_model\.yaml: tables\.drag\.kind: must be one of curve, grid2d, got "
                                         r"'spline3d'$"):
        load_model(write(tmp_path, raw), data_dir=tmp_path)
