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
    assert r.returncode == 2 and r.stderr.startswith(f"thermal-edge flux: error: {tmp_path / 'g.json'}: ")
    assert "flux model: no r20" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    (tmp_path / "h.json").write_text('{"params": 3}')  # wrong types: the same one line, no traceback
    r = te_here("flux", "score", tmp_path / "h.json", tmp_path / "use.csv")
    assert r.returncode == 2 and "not a file written by flux calibrate" in r.stderr and "Traceback" not in r.stderr


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


