"""``thermal-edge flux calibrate`` and ``flux score`` on a CSV run written from the voltage
equations with known parameters: the file it writes gives them back, the score on a second run is
the noise level, and bad options are one-line errors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_in_process import te_here

TRUE = {"r20": 0.018, "v_err": 1.5, "psi20": 0.11, "beta": -0.11 * 0.11 / 100.0, "ld0": 5e-4, "ld1": -6e-5,
        "lq0": 9e-4, "lq1": -1.2e-4}


def voltages(p, i_d, i_q, rpm, t_w, t_m, pole_pairs=4):
    """u_d, u_q (V) of a PMSM at steady state (copper 0.393 %/K, the inverter losing V_e along the current)."""
    w = rpm * 2 * np.pi / 60 * pole_pairs
    r = p["r20"] * (1 + 0.00393 * (t_w - 20))
    ia = np.sqrt(i_d**2 + i_q**2)
    ld, lq = p["ld0"] + p["ld1"] * ia / 100, p["lq0"] + p["lq1"] * ia / 100
    psi = p["psi20"] + p["beta"] * (t_m - 20)
    k = p["v_err"] / np.maximum(ia, 5.0)
    return r * i_d - w * lq * i_q + k * i_d, r * i_q + w * (ld * i_d + psi) + k * i_q


def write_run(path: Path, seed: int, n: int = 1500) -> None:
    g = np.random.default_rng(seed)
    rpm = np.repeat(g.uniform(1500, 6000, n // 5), 5)
    i_d, i_q = g.uniform(-200, 0, n), g.uniform(-50, 150, n)
    t_w, t_m = g.uniform(20, 140, n), g.uniform(20, 130, n)
    u_d, u_q = voltages(TRUE, i_d, i_q, rpm, t_w, t_m)
    cols = {"t": np.arange(n, dtype=float), "u_d_v": u_d + g.normal(0, 0.05, n), "u_q_v": u_q + g.normal(0, 0.05, n),
            "i_d": i_d, "i_q": i_q, "speed_rpm": rpm, "stator_winding": t_w, "pm": t_m}
    lines = [",".join(cols)] + [",".join(f"{cols[c][k]:.9g}" for c in cols) for k in range(n)]
    path.write_text("\n".join(lines) + "\n")


def test_calibrate_then_score(tmp_path):
    write_run(tmp_path / "fit.csv", 1)
    write_run(tmp_path / "use.csv", 2)
    out = tmp_path / "flux.json"
    r = te_here("flux", "calibrate", tmp_path / "fit.csv", "--pole-pairs", 4, "--out", out)
    assert r.returncode == 0, r.stderr
    assert "temperature coefficient of the flux linkage: -0.110 %/K" in r.stdout
    saved = json.loads(out.read_text())
    assert saved["params"]["psi20"] == pytest.approx(TRUE["psi20"], rel=0.01)
    assert saved["params"]["beta"] == pytest.approx(TRUE["beta"], rel=0.01)
    r = te_here("flux", "score", out, tmp_path / "use.csv", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    # 0.05 V of noise at 1500-6000 rpm and 4 pole pairs: 0.1-0.5 K
    assert s["informative_share"] > 0.5 and s["rms_k"] < 1.0


@pytest.mark.parametrize("extra, message", [
    (["--prior", "psi=0.1,0.1"], "--prior psi=0.1,0.1: unknown parameter 'psi'"),
    (["--prior", "r20=0.1"], "--prior r20=0.1: expected NAME=MEAN,SIGMA"),
    (["--prior", "r20=0.1,0"], "--prior r20=0.1,0: MEAN finite and SIGMA > 0"),
    (["--magnet-column", "rotor"], "no magnet temperature column 'rotor'"),
    (["--speed-min", "1e4"], "only 0 samples at or above 10000 rpm"),
    (["--speed-min", "1e6"], "argument --speed-min: "),
    (["--pole-pairs", "0"], "argument --pole-pairs: "),
    (["--minutes", "0"], "argument --minutes: "),
    (["--u-d-column", "ud"], "fit.csv: no column(s) ud"),
])
def test_bad_options_are_one_line_errors(tmp_path, extra, message):
    write_run(tmp_path / "fit.csv", 1, n=200)
    r = te_here("flux", "calibrate", tmp_path / "fit.csv", "--pole-pairs", 4, "--out", tmp_path / "f.json", *extra)
    assert r.returncode == 2
    assert message in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_score_of_a_file_that_is_not_a_flux_model(tmp_path):
    write_run(tmp_path / "use.csv", 2, n=50)
    (tmp_path / "f.json").write_text("{not json")
    r = te_here("flux", "score", tmp_path / "f.json", tmp_path / "use.csv")
    assert r.returncode == 2 and "not a file written by flux calibrate" in r.stderr
    (tmp_path / "g.json").write_text('{"params": {}}')
    r = te_here("flux", "score", tmp_path / "g.json", tmp_path / "use.csv")
    assert r.returncode == 2 and r.stderr.startswith(f"thermal-edge flux score: error: {tmp_path / 'g.json'}: ")
    assert "flux model: no params.r20" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    (tmp_path / "h.json").write_text('{"params": 3}')  # wrong types: the same one line, no traceback
    r = te_here("flux", "score", tmp_path / "h.json", tmp_path / "use.csv")
    assert r.returncode == 2 and "params must be an object, got 3 (a number)" in r.stderr and "Traceback" not in r.stderr


def test_simulate_with_voltages_feeds_flux_calibrate(tmp_path):
    """``simulate --voltages`` writes what a test bench with a rotor telemetry records: the dq
    voltages of the simulated machine's electrical side and the magnet's true temperature as ``pm``;
    ``flux calibrate`` on it gives back the electrical side's flux linkage and its slope."""
    from thermal_edge.lptn import NodeRole, load_model
    from thermal_edge.shipped import config_path
    from thermal_edge.sim.pmsm import Pmsm

    run, nodes = tmp_path / "bench.csv", tmp_path / "nodes.csv"
    for out, extra in ((run, ()), (nodes, ("--all-nodes",))):
        r = te_here("simulate", "--model", "pm10kw", "--cycle", "commissioning", "--duration", 5400, "--voltages",
                    "--out", out, *extra)
        assert r.returncode == 0, r.stderr
    import csv

    def columns(path: Path) -> dict[str, np.ndarray]:
        rows = list(csv.reader(line for line in path.read_text().splitlines() if not line.startswith("#")))
        return {k: np.array([float(r[i]) for r in rows[1:]]) for i, k in enumerate(rows[0])}

    c, full = columns(run), columns(nodes)
    assert {"u_d_v", "u_q_v", "pm", "i_d", "i_q"} <= set(c) and not any(k.startswith("T_") for k in c)
    model = load_model(config_path("machines", "pm10kw.yaml"))
    magnets = [n for n, role in model.node_roles.items() if role is NodeRole.MAGNET]
    np.testing.assert_allclose(c["pm"], np.mean([full[f"T_{n}"] for n in magnets], axis=0), rtol=1e-5, atol=1e-4)
    out = tmp_path / "flux.json"
    r = te_here("flux", "calibrate", run, "--pole-pairs", Pmsm().pole_pairs, "--winding-column", "slot_winding",
                "--out", out)
    assert r.returncode == 0, r.stderr
    got = json.loads(out.read_text())["params"]
    pm = Pmsm()
    assert got["psi20"] == pytest.approx(pm.psi(20.0), rel=0.03)
    assert got["beta"] == pytest.approx(pm.psi(21.0) - pm.psi(20.0), rel=0.15)


def test_a_can_log_with_voltages_exports_them_per_tick(tmp_path):
    """``simulate --format can --voltages`` logs INV_Voltages beside the other frames; ``export``
    writes the dq voltages and currents per tick (what flux calibrate reads). Their mean over the
    run against the frames decoded independently with cantools."""
    import cantools

    from thermal_edge.bus import DEFAULT_DBC_PATH

    log = tmp_path / "drive.log"
    r = te_here("simulate", "--model", "pm10kw", "--cycle", "commissioning", "--duration", 600, "--voltages",
                "--format", "can", "--out", log)
    assert r.returncode == 0, r.stderr
    r = te_here("export", log, "--out", tmp_path / "run.csv")
    assert r.returncode == 0, r.stderr
    rows = [ln.split(",") for ln in (tmp_path / "run.csv").read_text().splitlines() if not ln.startswith("#")]
    cols = {k: np.array([float(x[i]) for x in rows[1:]]) for i, k in enumerate(rows[0])}
    assert {"u_d_v", "u_q_v", "i_d", "i_q"} <= set(cols) and np.all(np.isfinite(cols["u_q_v"]))
    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))
    msg = db.get_message_by_name("INV_Voltages")
    uq = [db.decode_message(msg.frame_id, bytes.fromhex(ln.split("#")[1].split()[0]))["INV_Uq"]
          for ln in log.read_text().splitlines() if f" {msg.frame_id:03X}#" in ln]
    assert len(uq) > 0.9 * 600 * 100  # one per 10 ms
    assert float(np.mean(cols["u_q_v"])) == pytest.approx(float(np.mean(uq)), rel=0.01)




def write_columns(path: Path, cols: dict[str, np.ndarray]) -> Path:
    lines = [",".join(cols)] + [",".join(f"{cols[c][k]:.9g}" for c in cols) for k in range(len(next(iter(cols.values()))))]
    path.write_text("\n".join(lines) + "\n")
    return path


def synthetic_columns(seed: int, n: int = 1500, magnet=(20.0, 130.0), scale_u: float = 1.0) -> dict[str, np.ndarray]:
    """The columns of :func:`write_run` (voltages times ``scale_u``), the magnet uniform over ``magnet``
    and the shaft torque of the same machine (``1.5 p (ψ i_q + (L_d - L_q) i_d i_q)``)."""
    g = np.random.default_rng(seed)
    rpm = np.repeat(g.uniform(1500, 6000, n // 5), 5)
    i_d, i_q = g.uniform(-200, 0, n), g.uniform(-50, 150, n)
    t_w, t_m = g.uniform(20, 140, n), g.uniform(*magnet, n)
    u_d, u_q = voltages(TRUE, i_d, i_q, rpm, t_w, t_m)
    ia = np.hypot(i_d, i_q)
    psi = TRUE["psi20"] + TRUE["beta"] * (t_m - 20)
    ld, lq = TRUE["ld0"] + TRUE["ld1"] * ia / 100, TRUE["lq0"] + TRUE["lq1"] * ia / 100
    torque = 1.5 * 4 * (psi * i_q + (ld - lq) * i_d * i_q)
    return {"t": np.arange(n, dtype=float), "u_d_v": scale_u * (u_d + g.normal(0, 0.05, n)),
            "u_q_v": scale_u * (u_q + g.normal(0, 0.05, n)), "i_d": i_d, "i_q": i_q, "speed_rpm": rpm,
            "stator_winding": t_w, "pm": t_m, "torque_nm": torque}


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> tuple[Path, Path]:
    """A calibration written by ``flux calibrate`` and a second run of the same machine."""
    d = tmp_path_factory.mktemp("flux")
    write_run(d / "fit.csv", 1)
    write_run(d / "use.csv", 2, n=300)
    r = te_here("flux", "calibrate", d / "fit.csv", "--pole-pairs", 4, "--out", d / "flux.json")
    assert r.returncode == 0, r.stderr
    return d / "flux.json", d / "use.csv"


def _edit(d: dict, key: str, value: object) -> dict:
    """``d`` with the dotted ``key`` set to ``value`` (``...`` removes it)."""
    out = json.loads(json.dumps(d))
    *path, last = key.split(".")
    node = out
    for k in path:
        node = node[k]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return out


@pytest.mark.parametrize("key, value, words", [
    ("params.beta", "-0.0005", ["params.beta must be a number", '"-0.0005" (a string)']),
    ("pole_pairs", "6", ["pole_pairs must be a whole number", '"6" (a string)']),
    ("pole_pairs", 6.5, ["pole_pairs must be a whole number"]),
    ("cov", ..., ["no cov"]),
    ("tau_s", ..., ["no tau_s"]),
    ("params.psi20", 110.0, ["params.psi20 110 Wb looks like mWb (0.11 Wb)"]),
    ("params.beta", -0.11 * 0.05, ["params.beta", "no magnet's flux linkage falls faster"]),
    ("params", None, ["params must be an object, got null"]),
    ("params", [1, 2], ["params must be an object, got [1, 2] (a list)"]),
    ("cv_params", "x", ["cv_params must be a list of rows of numbers", '"x" (a string)']),
    ("cv_params", [["x"] * 8], ["cv_params[0][0] must be a number"]),
    ("var_u", {"a": 1.0}, ["var_u: bin 'a' is not a whole number"]),
    ("sigma.r20", True, ["sigma.r20 must be a number, got true (a boolean)"]),
])
def test_a_calibration_file_is_checked_entry_by_entry(good, tmp_path, key, value, words):
    """Each entry as ``flux calibrate`` writes it (a JSON number, not a string holding one; every
    entry it writes) and plausible; the message names the file and the entry, in Python's words never."""
    flux, use = good
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_edit(json.loads(flux.read_text()), key, value)))
    r = te_here("flux", "score", bad, use)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr
    assert err[0].startswith(f"thermal-edge flux score: error: {bad}: flux model: "), err
    for w in words:
        assert w in err[0], err
    assert r.stdout == ""


@pytest.mark.parametrize("text, words", [
    ("[1, 2]", "the file holds a list, not an object"),
    ("", "empty, not a file written by flux calibrate"),
    ('{"params": ', "not a file written by flux calibrate (not JSON"),
])
def test_a_file_that_is_no_calibration_says_what_it_holds(good, tmp_path, text, words):
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    r = te_here("flux", "score", bad, good[1])
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [f"thermal-edge flux score: error: {bad}: " +
                                                                    r.stderr.split(f"{bad}: ", 1)[1].strip()]
    assert words in r.stderr and "object has no attribute" not in r.stderr


def test_the_written_calibration_is_read_back_unchanged(good):
    """What ``flux calibrate`` writes passes the reader's checks and reads back as written."""
    from thermal_edge.estimation.flux import FluxModel

    d = json.loads(good[0].read_text())
    assert json.loads(json.dumps(FluxModel.from_dict(d).as_dict())) == d


def test_score_refuses_a_run_where_the_estimate_is_never_informative(good, tmp_path):
    """No RMS of nothing: a run below the informative speed is refused in one line, never ``nan``."""
    flux, _ = good
    cols = synthetic_columns(3, n=100)
    cols["speed_rpm"] = np.full(100, 100.0)  # far below the commissioning run's 1500 rpm
    run = write_columns(tmp_path / "slow.csv", cols)
    for extra in ((), ("--json",)):
        r = te_here("flux", "score", flux, run, *extra)
        assert r.returncode == 2 and "informative on none of the samples" in r.stderr, r.stderr
        assert "nan" not in (r.stdout + r.stderr).lower() and len(r.stderr.strip().splitlines()) == 1


def test_calibrate_refuses_swapped_d_and_q_and_writes_nothing(tmp_path):
    """Swapped voltage columns fit a flux linkage that rises with the temperature (here) or is
    negative (below): refused as the service would refuse the file, with the likely cause, and no
    file is written."""
    write_run(tmp_path / "fit.csv", 1)
    out = tmp_path / "flux.json"
    r = te_here("flux", "calibrate", tmp_path / "fit.csv", "--pole-pairs", 4, "--out", out,
                "--u-d-column", "u_q_v", "--u-q-column", "u_d_v")
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr
    assert err[0].startswith(f"thermal-edge flux calibrate: error: {tmp_path / 'fit.csv'}: the fit is no magnet's: "), err
    assert "are u_d and u_q swapped" in err[0]
    assert not out.exists() and r.stdout == ""


@pytest.mark.parametrize("scale, unit", [(1e-3, "kV"), (1e3, "mV")])
def test_calibrate_refuses_voltages_in_another_unit(tmp_path, scale, unit):
    run = write_columns(tmp_path / "fit.csv", synthetic_columns(1, scale_u=scale))
    out = tmp_path / "flux.json"
    r = te_here("flux", "calibrate", run, "--pole-pairs", 4, "--out", out)
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr
    assert f"{run}: columns u_d_v, u_q_v: |u| at speed (95th percentile)" in err[0] and f"looks like {unit}" in err[0]
    assert not out.exists()


def test_the_voltage_unit_is_checked_against_the_shaft_power():
    """Voltages whose magnitude is plausible alone (a 3 kV machine's in kV: a few V) but whose power
    is a thousandth of the shaft's are refused; the same machine in V passes."""
    from thermal_edge.commands.flux import check_voltage_unit
    from thermal_edge.estimation.flux import Electrical, FluxError

    cols = synthetic_columns(4, n=500)
    cols["u_d_v"], cols["u_q_v"] = 10.0 * cols["u_d_v"], 10.0 * cols["u_q_v"]  # a machine of ~3 kV ...
    cols["torque_nm"] = 10.0 * cols["torque_nm"]  # ... and ten times the torque at the same currents
    use = np.ones(500, dtype=bool)
    p_el = 1.5 * (cols["u_d_v"] * cols["i_d"] + cols["u_q_v"] * cols["i_q"])
    p_m = cols["torque_nm"] * cols["speed_rpm"] * 2 * np.pi / 60
    big = np.abs(p_m) > 0.2 * np.percentile(np.abs(p_m), 95)
    assert 0.8 < np.median(p_el[big] / p_m[big]) < 1.25  # the power balance of this machine, computed here

    def check(scale_u: float) -> None:
        e = Electrical(scale_u * cols["u_d_v"], scale_u * cols["u_q_v"], cols["i_d"], cols["i_q"], cols["speed_rpm"],
                       cols["stator_winding"])
        check_voltage_unit(e, use, cols["torque_nm"], "run.csv: columns u_d_v, u_q_v")

    check(1.0)
    with pytest.raises(FluxError, match=r"run.csv: columns u_d_v, u_q_v: the electrical power .* look like kV"):
        check(1e-3)


def test_calibrate_warns_when_the_temperature_coefficient_is_not_identified(tmp_path):
    """A run whose magnet stays within half a kelvin cannot give beta: written (its sigma at that
    temperature is real), with a warning saying so; a run over 20-130 degC gives none. Both say
    at which magnet temperatures the sigma figures hold."""
    narrow = write_columns(tmp_path / "narrow.csv", synthetic_columns(1, magnet=(60.0, 60.5)))
    r = te_here("flux", "calibrate", narrow, "--pole-pairs", 4, "--out", tmp_path / "n.json", "--prior", "beta=-1e-4,1e-3")
    assert r.returncode == 0, r.stderr
    warn = r.stderr.strip().splitlines()
    assert len(warn) == 1 and warn[0].startswith("thermal-edge flux calibrate: warning: the temperature coefficient is "
                                                 "not identified: the magnet spans only 0.4 K"), warn
    assert (tmp_path / "n.json").exists()
    pm = np.loadtxt(narrow, delimiter=",", skiprows=1, usecols=7)
    assert f"at the magnet temperatures of the run ({pm.min():.1f} to {pm.max():.1f} degC)" in r.stdout
    wide = write_columns(tmp_path / "wide.csv", synthetic_columns(1))
    r = te_here("flux", "calibrate", wide, "--pole-pairs", 4, "--out", tmp_path / "w.json")
    assert r.returncode == 0 and r.stderr == "", r.stderr
    r = te_here("flux", "calibrate", narrow, "--pole-pairs", 4, "--out", tmp_path / "n.json", "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["warnings"][0].startswith("the temperature coefficient is not")


def test_a_magnet_column_of_another_node_is_warned_about(tmp_path):
    """``--magnet-column housing``: in pm10kw (given, or packaged) the sensor of a housing node."""
    cols = synthetic_columns(1)
    cols["housing"] = cols.pop("pm")
    run = write_columns(tmp_path / "fit.csv", cols)
    for extra in ((), ("--model", "pm10kw")):
        r = te_here("flux", "calibrate", run, "--pole-pairs", 4, "--out", tmp_path / "f.json", "--magnet-column",
                    "housing", *extra)
        assert r.returncode == 0, r.stderr
        assert ("warning: --magnet-column housing: in model pm10kw, housing is the sensor of node housing_2 (role "
                "housing), not of a magnet") in r.stderr, r.stderr
    r = te_here("flux", "calibrate", run, "--pole-pairs", 4, "--out", tmp_path / "f.json", "--magnet-column", "housing",
                "--winding-column", "housing")
    assert r.returncode == 2 and "the same column as --winding-column" in r.stderr


def test_calibrate_refuses_a_fit_the_reader_refuses(tmp_path, monkeypatch):
    """Whatever the fit gives, what is written is what :meth:`FluxModel.from_dict` accepts: a fit
    with a negative flux linkage (as swapped columns give on the simulated bench) is refused with
    the reader's words and the hint."""
    import thermal_edge.commands.flux as cmd

    real = cmd.fit_flux_model

    def negative_psi(*a, **k):
        m = real(*a, **k)
        m.params = {**m.params, "psi20": -m.params["psi20"]}
        return m

    monkeypatch.setattr(cmd, "fit_flux_model", negative_psi)
    write_run(tmp_path / "fit.csv", 1)
    r = te_here("flux", "calibrate", tmp_path / "fit.csv", "--pole-pairs", 4, "--out", tmp_path / "f.json")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "the fit is no magnet's: flux model: params.psi20 must be positive (the flux linkage), got -0.11" in r.stderr
    assert "are u_d and u_q swapped" in r.stderr and not (tmp_path / "f.json").exists()


def _config(tmp_path: Path, **flux: object) -> Path:
    """The packaged edge.yaml with these ``flux:`` entries."""
    import yaml

    from thermal_edge.shipped import config_path

    raw = yaml.safe_load(config_path("edge.yaml").read_text())
    raw["state"] = {"dir": str(tmp_path / "state")}
    raw["flux"] = {**raw["flux"], "winding_node": "slot_winding_1", **flux}
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def test_run_check_lists_the_voltages_frame_protection_and_timeout(good, tmp_path):
    """``run --check`` lists INV_Voltages' counter, CRC and staleness (``flux.timeout_s``) as every
    other read frame's, named here from the DBC."""
    import cantools

    from thermal_edge.bus.frames import DEFAULT_DBC_PATH

    names = {s.name for s in cantools.database.load_file(str(DEFAULT_DBC_PATH)).get_message_by_name("INV_Voltages").signals}
    assert {"INV_Voltages_Counter", "INV_Voltages_CRC"} <= names
    r = te_here("run", "--check", "--config", _config(tmp_path, calibration=str(good[0]), timeout_s=0.7))
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("  INV_Voltages: protection")]
    assert len(lines) == 1 and "counter INV_Voltages_Counter, CRC INV_Voltages_CRC" in lines[0], r.stdout
    assert lines[0].endswith("stale after 0.7 s"), lines


def test_run_check_refuses_a_calibration_in_another_unit(good, tmp_path):
    bad = tmp_path / "mwb.json"
    d = json.loads(good[0].read_text())
    bad.write_text(json.dumps({**d, "params": {**d["params"], "psi20": 1000 * d["params"]["psi20"]}}))
    r = te_here("run", "--check", "--config", _config(tmp_path, calibration=str(bad)))
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1, r.stderr
    assert "edge.yaml: flux.calibration:" in err[0] and "params.psi20 110" in err[0] and "Wb looks like mWb (0.11 Wb)" in err[0]


def test_a_voltage_signal_naming_the_frames_counter_says_so(good, tmp_path):
    r = te_here("run", "--check", "--config", _config(tmp_path, calibration=str(good[0]), voltage_d="INV_Voltages_Counter"))
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "thermal-edge run: error: edge.yaml: flux.voltage_d: INV_Voltages_Counter is the alive counter of frame "
        "INV_Voltages (its protection), not a signal with a value; its signals: INV_Ud, INV_Uq"], r.stderr


@pytest.mark.parametrize("column, convert, words", [
    ("stator_winding", lambda x: x + 273.15, "looks like kelvin"),
    ("pm", lambda x: x + 273.15, "looks like kelvin"),
    ("i_q", lambda x: x * 1000.0, "looks like mA"),
])
def test_calibrate_and_score_refuse_a_column_in_another_unit(tmp_path, good, column, convert, words):
    """The winding's temperature sets R_s, the magnet's the flux linkage's slope, the currents the
    inductances: a whole column in kelvin or mA would be fitted into a calibration wrong
    throughout. Both commands refuse it naming the column and the unit, with nothing written."""
    cols = synthetic_columns(3)
    cols[column] = convert(cols[column])
    run = write_columns(tmp_path / "run.csv", cols)
    out = tmp_path / "flux.json"
    r = te_here("flux", "calibrate", run, "--pole-pairs", 4, "--out", out)
    assert r.returncode == 2 and not out.exists(), r.stderr
    assert r.stderr.startswith(f"thermal-edge flux calibrate: error: {run}: column '{column}': ") and words in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    flux, _ = good
    r = te_here("flux", "score", flux, run)
    assert r.returncode == 2 and f"column '{column}'" in r.stderr and words in r.stderr, r.stderr
