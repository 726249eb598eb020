"""The unit a DBC declares for a mapped signal: the package's (or empty) is read, another is
refused at load with one line naming the key, and for a known unit the scaling that gives the
package's. That scaling is checked here by decoding the same frame bytes with cantools through the
user's DBC and through the DBC corrected as the line says."""
from __future__ import annotations

import math
import re
from pathlib import Path

import cantools
import pytest
import yaml
from svc_testlib import EDGE_YAML, REPO

from benchmarks.faults.units import rescaled
from thermal_edge.config import ConfigError, config_from_mapping
from thermal_edge.service.engine import load_service_model

DBC = REPO / "dbc" / "thermal_edge.dbc"


def _config(tmp_path: Path, signal: str, scaling: str, unit: str):
    """The shipped configuration on the shipped DBC with ``signal`` declared as ``(scaling) "unit"``."""
    dbc = tmp_path / "inverter.dbc"
    dbc.write_text(rescaled(DBC.read_text(), signal, scaling, unit))
    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["model"]["path"] = str(REPO / "config" / "machines" / "pm10kw.yaml")
    raw["codec"]["dbc"] = str(dbc)
    cfg = config_from_mapping(raw, tmp_path / "edge.yaml")
    return cfg, dbc


def _check(cfg) -> None:
    cfg.check_dbc(cfg.codec.frame_codec(cfg.fname), load_service_model(cfg).input_roles)


@pytest.mark.parametrize("signal, frame, key, scaling, unit, value, want", [
    # a speed of 100 rad/s sent as rad/s: 954.9 rpm
    ("INV_Speed", "INV_Mechanics", "signals.inputs.speed_rpm", "0.01,0", "rad/s", 100.0, 100.0 * 60 / (2 * math.pi)),
    # a housing at 350 K: 76.85 degC
    ("INV_T_Housing", "INV_StatorTemps", "signals.sensors.housing", "0.1,0", "K", 350.0, 350.0 - 273.15),
    # an ambient of 77 degF: 25 degC
    ("INV_T_Ambient", "INV_AmbientTemps", "signals.inputs.ambient_c", "0.1,0", "degF", 77.0, 25.0),
    # a d-axis current of 20 A sent in mA (the RMS current is read from the dq currents)
    ("INV_Id", "INV_Currents", "signals.inputs.i_rms", "1,0", "mA", -20000.0, -20.0),
])
def test_a_unit_not_the_packages_is_refused_with_the_scaling_that_gives_it(tmp_path, signal, frame, key, scaling, unit,
                                                                           value, want):
    cfg, dbc = _config(tmp_path, signal, scaling, unit)
    with pytest.raises(ConfigError) as err:
        _check(cfg)
    msg = str(err.value)
    assert msg.startswith(f"edge.yaml: {key}: inverter.dbc gives {signal} in {unit!r}") and "\n" not in msg
    factor, offset, ours = re.search(r'factor (\S+), offset (\S+), unit "([^"]+)"', msg).groups()
    # the same bytes, decoded through the corrected DBC, are the value in the package's unit
    theirs = cantools.database.load_file(str(dbc)).get_message_by_name(frame)
    fixed = rescaled(dbc.read_text(), signal, f"{factor},{offset}", ours)
    mine = cantools.database.load_string(fixed, "dbc").get_message_by_name(frame)
    values = {s.name: (s.minimum or 0) if s.name != signal else value for s in theirs.signals}
    data = theirs.encode(values, strict=False, scaling=True)
    raw = theirs.decode(data, decode_choices=False, scaling=False)[signal]
    got = mine.decode(data, decode_choices=False)[signal]
    assert got == pytest.approx(want, abs=2 * abs(float(factor)) + 1e-9), (raw, got)


def test_an_unknown_unit_is_refused_naming_the_spellings_read(tmp_path):
    cfg, _ = _config(tmp_path, "INV_Torque", "0.1,0", "lbf ft")
    with pytest.raises(ConfigError, match=r"^edge.yaml: signals.inputs.torque_nm: inverter.dbc gives INV_Torque in "
                                          r"'lbf ft'.*give the signal in Nm in the DBC \(its unit written .*'Nm'"):
        _check(cfg)


@pytest.mark.parametrize("signal, unit", [("INV_Speed", "1/min"), ("INV_Speed", "RPM"), ("INV_Speed", ""),
                                          ("INV_Id", "Arms"), ("INV_Torque", "N m")])
def test_the_packages_units_and_an_empty_one_are_read(tmp_path, signal, unit):
    cfg, _ = _config(tmp_path, signal, "0.5,0", unit)
    _check(cfg)


def test_without_the_roles_the_inputs_are_not_judged(tmp_path):
    """The unit of an input is its role's: a caller without the model checks the sensors only."""
    cfg, _ = _config(tmp_path, "INV_Speed", "0.01,0", "rad/s")
    cfg.check_dbc(cfg.codec.frame_codec(cfg.fname))


def test_a_degree_sign_of_a_dbc_saved_in_utf8_is_read(tmp_path):
    """cantools reads a DBC as cp1252: "°C" saved in UTF-8 arrives as "Â°C" and is degC all the same."""
    cfg, dbc = _config(tmp_path, "INV_T_Housing", "0.1,-50", "°C")
    dbc.write_bytes(dbc.read_text().encode("utf-8"))
    assert cantools.database.load_file(str(dbc)).get_message_by_name("INV_StatorTemps").get_signal_by_name(
        "INV_T_Housing").unit == "Â°C"
    _check(cfg)


def test_an_empty_unit_is_read_with_a_warning_naming_the_key_and_the_unit_assumed(tmp_path, caplog):
    """A unit the DBC leaves out cannot be judged: the value is read in the role's unit and one
    WARNING says so (a speed in rad/s does not pass unsaid); a signal with its unit gets none."""
    cfg, _ = _config(tmp_path, "INV_Speed", "0.01,0", "")
    with caplog.at_level("WARNING", logger="thermal_edge.config"):
        _check(cfg)
    lines = [r for r in caplog.records if r.name == "thermal_edge.config" and r.levelname == "WARNING"]
    assert len(lines) == 1
    msg = lines[0].getMessage()
    assert msg.startswith("signals.inputs.speed_rpm: INV_Mechanics.INV_Speed has no unit in inverter.dbc: read as rpm")
    caplog.clear()
    cfg, _ = _config(tmp_path, "INV_Speed", "0.01,0", "rpm")
    with caplog.at_level("WARNING", logger="thermal_edge.config"):
        _check(cfg)
    assert not [r for r in caplog.records if r.name == "thermal_edge.config"]


@pytest.mark.parametrize("encoding", ["utf-8", "cp1252"])
def test_a_unit_with_a_degree_sign_is_read_as_written_in_either_encoding(tmp_path, encoding):
    """DBC editors write cp1252, text editors UTF-8: ``°F`` is read as ``°F`` from both (cantools'
    default cp1252 had made UTF-8's two bytes ``Â°F``), so the refusal names the unit as written."""
    cfg, dbc = _config(tmp_path, "INV_T_Ambient", "0.1,0", "°F")
    dbc.write_bytes(dbc.read_text(encoding="utf-8").encode(encoding))
    with pytest.raises(ConfigError) as err:
        _check(cfg)
    assert "inverter.dbc gives INV_T_Ambient in '°F'" in str(err.value), str(err.value)


@pytest.mark.parametrize("scaling, unit, said", [("0.1,0", "degC", "scaled (factor 0.1, offset 0), unit 'degC'"),
                                                  ("1,-40", "", "scaled (factor 1, offset -40)")])
def test_a_status_signal_that_is_not_a_code_is_refused_naming_its_key(tmp_path, scaling, unit, said):
    """A temperature mapped as a sensor's ``status`` would be judged as codes (85.3 °C as code 85):
    refused at load, naming the key and what the DBC says the signal is."""
    cfg, _ = _config(tmp_path, "INV_S_Housing", scaling, unit)
    with pytest.raises(ConfigError) as err:
        _check(cfg)
    assert str(err.value) == (f"edge.yaml: signals.sensors.housing.status: INV_S_Housing in inverter.dbc is {said}: "
                              "not a status code (a status is a whole number, 0 valid, 1 open circuit, 2 short "
                              "circuit, 3 not fitted)"), str(err.value)
