"""``thermal-edge simulate --effect`` and ``thermal-edge discover`` from the command line."""
from __future__ import annotations

import json

import pytest

from benchmarks.discovery import PM10KW
from thermal_edge.cli import main
from thermal_edge.shipped import config_path

CYCLE = config_path("cycles", "varied_drive.yaml")


def test_simulate_help_documents_the_effects(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    out = capsys.readouterr().out
    assert "--effect NAME[:TARGET][=PARAM=VALUE,...]" in out
    for name in ("copper_temperature", "speed_convection", "sensor_lag", "contact_resistance", "ambient_offset"):
        assert name in out


@pytest.mark.parametrize("spec,msg", [
    ("warp_drive", "unknown effect 'warp_drive'"),
    ("sensor_lag", "needs a target"),
    ("speed_convection:nope", "unknown target 'nope'"),
    ("bearing_loss=p=x", "not a number"),
    # magnitudes the effect's law cannot take: named, not a math domain error or a division by zero
    ("sensor_lag:end_winding=tau=-5", "tau must be > 0 s (the effect's range is 1 to 3600 s), got -5"),
    ("sensor_lag:end_winding=tau=0", "tau must be > 0 s"),
    ("copper_temperature=k100=0", "k100 must be > 0 (the effect's range is 0.3 to 3), got 0"),
    ("bearing_loss=p=-60", "p must be > 0 W"),
    ("sensor_lag:end_winding=tau=inf", "tau must be a finite number, got inf"),
])
def test_bad_effect_is_one_line(spec, msg, tmp_path, capsys):
    rc = main(["simulate", "--model", str(PM10KW), "--cycle", str(CYCLE), "--effect", spec, "--out", str(tmp_path / "r.csv")])
    err = capsys.readouterr().err
    assert rc == 2 and msg in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_simulate_then_discover(tmp_path, capsys):
    """A sensor lag hidden on the command line is named by discover --json, which writes the
    augmented model and the report."""
    run = tmp_path / "run.csv"
    rc = main(["simulate", "--model", str(PM10KW), "--cycle", str(CYCLE), "--effect", "sensor_lag:end_winding=tau=240",
               "--seed", "7", "--duration", "7200", "--out", str(run)])
    assert rc == 0
    assert "hidden effects: sensor_lag:end_winding=tau=240" in run.read_text().splitlines()[1]
    capsys.readouterr()
    out = tmp_path / "disc"
    rc = main(["discover", "--model", str(PM10KW), "--run", str(run), "--out", str(out), "--json"])
    assert rc == 0
    d = json.loads(capsys.readouterr().out)
    assert d["named_effect"] == "sensor_lag" and d["target"] == "end_winding", d["rounds"]
    assert d["gap_after"] < 0.4 * d["gap_before"]
    assert {"name", "target", "score", "improvement"} <= set(d["candidates"][0])
    # the judgement: the runner-up (named, with the comparison when it explains the residual
    # too), whether the two are confusable, the noise floor the gap is judged against
    assert {"runner_up", "ambiguous", "gap_noise_floor", "gap_status", "comparison"} <= set(d)
    assert isinstance(d["ambiguous"], bool) and d["gap_noise_floor"] == d["noise_floor_k"] > 0
    assert d["runner_up"] and d["runner_up"] != "sensor_lag:end_winding"
    assert d["gap_status"] in ("explained", "partly explained")
    model_out = out / "pm10kw+sensor_lag-end_winding.yaml"
    assert d["model_out"] == str(model_out) and model_out.exists()
    assert (out / "report.md").exists()
    # the written model is a valid model with the probe node
    from thermal_edge.lptn import load_model

    m = load_model(model_out)
    assert m.sensors["end_winding"] == "end_winding_probe"
    tau = m.nominal()[m.parameter_index(["lag_end_winding_tau"])[0]]
    assert 120 < tau < 480


def test_discover_list_effects(capsys):
    assert main(["discover", "--model", str(PM10KW), "--list-effects"]) == 0
    out = capsys.readouterr().out
    assert "R_e_hous" in out and "copper_temperature" in out


def test_discover_bad_sensor_is_one_line(tmp_path, capsys):
    run = tmp_path / "run.csv"
    assert main(["simulate", "--model", str(PM10KW), "--cycle", str(CYCLE), "--duration", "600", "--out", str(run)]) == 0
    capsys.readouterr()
    rc = main(["discover", "--model", str(PM10KW), "--run", str(run), "--sensors", "rotor"])
    err = capsys.readouterr().err
    assert rc == 2 and "rotor" in err and "Traceback" not in err
