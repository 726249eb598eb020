"""The optional voltage frame in the service's tick (thermal_edge.service.flux_input): the engine and
the inverter emulator in the closed loop without a bus (thermal_edge.bench.protection), the flux
estimate commissioned on a simulated bench run (thermal_edge.bench.commissioning). References: the
same engine without the frame, the plant's true temperatures, the emulator's pause schedule."""
from __future__ import annotations

import io
import json
import logging
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from thermal_edge.bench import protection as P
from thermal_edge.config import ConfigError, config_from_mapping
from thermal_edge.estimation.flux import FluxModel
from thermal_edge.service.engine import ThermalEngine, load_service_model
from thermal_edge.service.journal import JournalFormatter
from thermal_edge.service.metrics import ServiceMetrics
from thermal_edge.shipped import config_path
from thermal_edge.sim.pmsm import Pmsm

MAGNET = "magnet_2"  # the magnet limit's node
NOMINAL = P.CASES["nominal"]


def cycle(tmp_path: Path, *segments: tuple[float, float, float]) -> Path:
    """A cycle file of (duration s, speed rpm, torque Nm) segments."""
    path = tmp_path / "cycle.yaml"
    path.write_text(yaml.safe_dump({"name": "test", "dt_s": 1.0, "ambient_c": 25.0, "segments": [
        {"duration_s": d, "speed_rpm": n, "torque_nm": m} for d, n, m in segments]}))
    return path


@pytest.fixture(scope="module")
def calibration(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("flux")
    cfg = P.edge_config(d / "state")
    return P.flux_calibration(load_service_model(cfg), d / "flux.json")


def loop(tmp_path: Path, cyc: Path, *, flux: Path | None, voltages: bool, events=(), name: str = "run"):
    """Run the engine over the cycle; per tick (t, estimate, sigma, current limit, flux outcome, the plant's
    magnets' mean, the flux estimate's σ) and the policy."""
    cfg = P.edge_config(tmp_path / name, None, flux)
    model = load_service_model(cfg)
    emu = P.emulator_for(P.plant_for(model, NOMINAL), cyc, NOMINAL, None, pmsm=Pmsm(), voltages=voltages)
    pol = P.ThermalEdgePolicy(emu, cfg.derating.max_current_a, cfg.derating.max_torque_nm, cfg)
    ticks: list[tuple[float, np.ndarray, np.ndarray, float, str | None, float]] = []
    pending = sorted(events, key=lambda e: e[0])
    magnet_rows = [model.node_index(n) for n in P.FLUX_MAGNET_NODES]

    def observe(emu, pol) -> None:
        while pending and emu.elapsed >= pending[0][0] - 1e-9:
            pending.pop(0)[1](emu)
        out = pol.last_out
        if out is not None and (not ticks or ticks[-1][0] != out.t):
            ticks.append((out.t, out.estimate.copy(), out.sigma.copy(), out.limits.current_a,
                          out.flux.outcome if out.flux is not None else None, float(np.mean(emu.plant.T[magnet_rows])),
                          out.flux.sigma_k if out.flux is not None else math.nan))

    limits = [(lim.name, model.node_index(lim.node), cfg.limit_band(lim)[1]) for lim in model.limits]
    try:
        P.closed_loop(emu, pol, float(cfg.kt(model)), limits, observe)
    finally:
        pol.close()
    return ticks, pol, model


def test_the_flux_section_is_typed_and_its_errors_name_file_and_key(tmp_path, calibration):
    raw = yaml.safe_load(config_path("edge.yaml").read_text())
    cfg = config_from_mapping(raw, tmp_path / "edge.yaml")
    assert not cfg.flux.enabled and cfg.flux.frame == "INV_Voltages" and cfg.flux.magnet_nodes == ("magnet_1", "magnet_2")

    def error(flux: dict, engine: bool = False) -> str:
        r = {**raw, "flux": {**raw["flux"], **flux}, "state": {"dir": str(tmp_path / "s")}}
        with pytest.raises(ConfigError) as info:
            c = config_from_mapping(r, tmp_path / "edge.yaml")
            model = load_service_model(c)
            c.check_model(model)
            c.check_dbc(c.codec.frame_codec())
            if engine:
                ThermalEngine(c, model, worker_mode="sync")
        return str(info.value)

    assert error({"timeout_s": 0}).startswith("edge.yaml: flux.timeout_s: must be at least 0.02")
    assert error({"timeout_s": 0.001}).startswith("edge.yaml: flux.timeout_s: must be at least 0.02")
    assert "flux.colibration: unknown key (did you mean 'calibration'?)" in error({"colibration": "x.json"})
    cal = str(calibration)
    assert error({"calibration": cal, "winding_node": "slot_windin_1"}).startswith(
        "edge.yaml: flux.winding_node: model pm10kw has no node 'slot_windin_1' (did you mean 'slot_winding_1'?)")
    assert error({"calibration": cal, "magnet_nodes": ["rotor"]}).startswith("edge.yaml: flux.magnet_nodes: model pm10kw")
    assert error({"calibration": cal, "voltage_q": "INV_Uqq"}).startswith(
        "edge.yaml: flux.voltage_q: frame INV_Voltages has no signal 'INV_Uqq'")
    assert error({"calibration": cal, "frame": "INV_Volts"}).startswith("edge.yaml: flux.frame: no frame 'INV_Volts'")
    # nodes: at least one magnet node, each once, none the winding's; roles as the model declares them
    assert error({"calibration": cal, "magnet_nodes": []}).startswith("edge.yaml: flux.magnet_nodes: empty")
    assert error({"calibration": cal, "magnet_nodes": ["magnet_1", "magnet_1"]}).startswith(
        "edge.yaml: flux.magnet_nodes: names a node twice")
    assert error({"calibration": cal, "winding_node": "slot_winding_1", "magnet_nodes": ["magnet_1", "slot_winding_1"]}
                 ).startswith("edge.yaml: flux.magnet_nodes: 'slot_winding_1' is flux.winding_node")
    assert error({"calibration": cal, "magnet_nodes": ["slot_winding_2"]}).startswith(
        "edge.yaml: flux.magnet_nodes: node 'slot_winding_2' of model pm10kw has role winding, not magnet")
    # frames and signals: a frame the inverter sends, two different signals
    assert error({"calibration": cal, "frame": "TE_Limits"}).startswith(
        "edge.yaml: flux.frame: TE_Limits is a frame thermal_edge sends")
    assert error({"calibration": cal, "voltage_q": "INV_Ud"}).startswith(
        "edge.yaml: flux.voltage_q: is 'INV_Ud', the same signal as flux.voltage_d")
    assert error({"calibration": str(tmp_path / "none.json")}, engine=True).startswith(
        "edge.yaml: flux.calibration: cannot read")
    (tmp_path / "bad.json").write_text(json.dumps({"params": {}}))
    assert "is not a flux model" in error({"calibration": str(tmp_path / "bad.json")}, engine=True)
    # off, the flux keys are not checked against a model or a DBC that lack them
    off = config_from_mapping({**raw, "flux": {**raw["flux"], "winding_node": "nope"}}, tmp_path / "edge.yaml")
    off.check_model(load_service_model(off))


def test_without_the_frame_configured_nothing_changes(tmp_path):
    """The same run without INV_Voltages on the bus and with it (but flux.calibration null): every
    tick's estimate, band and limit bit-identical."""
    cyc = cycle(tmp_path, (300.0, 900.0, 170.0), (300.0, 1500.0, 130.0))
    plain, pol_a, _ = loop(tmp_path, cyc, flux=None, voltages=False, name="a")
    sent, pol_b, _ = loop(tmp_path, cyc, flux=None, voltages=True, name="b")
    assert pol_a.engine.flux is None and pol_b.engine.flux is None
    assert len(plain) == len(sent) > 550
    for a, b in zip(plain, sent):
        assert a[0] == b[0] and a[3] == b[3] and a[4] is None and b[4] is None
        np.testing.assert_array_equal(a[1], b[1])
        np.testing.assert_array_equal(a[2], b[2])


def test_at_standstill_and_low_speed_the_band_is_what_it_is_without_voltages(tmp_path, calibration):
    """Standstill, then below the commissioning's lowest speed: the voltage input computes nothing,
    the estimate and every band are exactly those without it."""
    flux = FluxModel.from_dict(json.loads(calibration.read_text()))
    slow = 0.6 * flux.speed_min_rpm
    cyc = cycle(tmp_path, (120.0, 0.0, 0.0), (300.0, slow, 150.0), (60.0, 0.0, 60.0))
    plain, _, _ = loop(tmp_path, cyc, flux=None, voltages=False, name="a")
    fused, pol, _ = loop(tmp_path, cyc, flux=calibration, voltages=True, name="b")
    assert len(plain) == len(fused) > 450
    for a, b in zip(plain, fused):
        np.testing.assert_array_equal(a[1], b[1])
        np.testing.assert_array_equal(a[2], b[2])
    counts = pol.engine.flux.counts
    assert counts["low_speed"] == sum(1 for t in fused if t[4] is not None) and not counts["used"]


def test_at_speed_the_voltages_narrow_the_magnet_band_around_the_truth(tmp_path, calibration):
    cyc = cycle(tmp_path, (300.0, 900.0, 150.0), (600.0, 1500.0, 130.0))
    plain, _, model = loop(tmp_path, cyc, flux=None, voltages=False, name="a")
    fused, pol, _ = loop(tmp_path, cyc, flux=calibration, voltages=True, name="b")
    i = model.node_index(MAGNET)
    late = slice(len(fused) // 2, None)
    sig_plain = np.array([t[2][i] for t in plain[late]])
    sig_fused = np.array([t[2][i] for t in fused[late]])
    assert np.all(sig_fused < 0.85 * sig_plain)
    # the error the estimate carries from one tick to the next is a state: the band settles at about
    # the estimate's own σ (the variance table's), never far above it however the rotor model's band grows
    sig_flux = np.array([t[6] for t in fused[late]])
    assert np.all(np.isfinite(sig_flux)) and np.all(sig_fused <= 1.2 * sig_flux)
    assert sig_plain[-1] - sig_plain[0] > 0.5 and sig_fused[-1] - sig_fused[0] < 0.5 * (sig_plain[-1] - sig_plain[0])
    # the estimate of the magnets' mean (what the flux sees) within its band of the plant's truth
    rows = [model.node_index(n) for n in P.FLUX_MAGNET_NODES]
    err = np.array([np.mean(t[1][rows]) - t[5] for t in fused[late]])
    assert np.all(np.abs(err) <= 1.96 * sig_fused)
    counts = pol.engine.flux.counts
    assert counts["used"] > 0.9 * len(fused) and not any(counts[r] for r in ("disagreement", "stale", "implausible"))
    # the magnet's band is the measured one: its derating margin is flux.magnet_margin_k, the hot spot's the usual
    out = pol.last_out
    assert out.magnet.margin_k == pol.config.flux.magnet_margin_k == 0.5 and out.hot_spot.margin_k is None


def test_refusals_are_counted_logged_with_their_priority_and_on_metrics(tmp_path, calibration):
    """A 30 s pause of INV_Voltages (stale), 20 s of voltages in kV (implausible), and a flux linkage
    10 % off (disagreement): each tick refused is counted as often as the schedule says, logged at
    its journald priority, and exported on /metrics; the limits never see them."""
    cyc = cycle(tmp_path, (400.0, 900.0, 150.0))
    factor = {"u": 1.0}

    def scaled(emu) -> None:  # the voltages times factor["u"] (1e-3: the inverter sends kV)
        orig = emu._voltage_signals
        emu._voltage_signals = lambda i_d, i_q, n: {k: v * factor["u"] for k, v in orig(i_d, i_q, n).items()}

    events = [(1.0, scaled), (200.0, lambda e: e.paused.add("INV_Voltages")),
              (230.0, lambda e: e.paused.discard("INV_Voltages")),
              (300.0, lambda e: factor.update(u=1e-3)), (320.0, lambda e: factor.update(u=1.0))]
    lines = io.StringIO()
    handler = logging.StreamHandler(lines)
    handler.setFormatter(JournalFormatter("%(message)s"))
    logger = logging.getLogger("thermal_edge.service.flux_input")
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        ticks, pol, _ = loop(tmp_path, cyc, flux=calibration, voltages=True, events=events)
        bad = tmp_path / "psi_off.json"
        flux = FluxModel.from_dict(json.loads(calibration.read_text()))
        flux = replace(flux, params={**flux.params, "psi20": 1.1 * flux.params["psi20"]})
        bad.write_text(json.dumps(flux.as_dict()))
        wrong, pol_w, _ = loop(tmp_path, cycle(tmp_path, (200.0, 900.0, 150.0)), flux=bad, voltages=True, name="w")
    finally:
        logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
    counts = pol.engine.flux.counts
    # ticks k cover [k - 1, k): the pause from 200 s to 230 s leaves ticks 201..230 without voltages
    assert counts["stale"] == 30
    assert counts["implausible"] == 20
    assert counts["disagreement"] == 0
    text = lines.getvalue().splitlines()
    assert sum(1 for x in text if x.startswith("<5>flux estimate refused (stale)")) == 30
    assert sum(1 for x in text if x.startswith("<4>flux estimate refused (implausible)")) == 20
    steady = [t for t in wrong if t[4] is not None and t[4] != "transient"]
    assert pol_w.engine.flux.counts["disagreement"] >= 0.9 * len(steady)
    assert sum(1 for x in text if x.startswith("<4>flux estimate refused (disagreement)")) == \
        pol_w.engine.flux.counts["disagreement"]
    metrics = ServiceMetrics()
    metrics.attach(pol.engine)
    scrape = metrics.text()

    def value(name: str, label: str = "") -> float:
        m = re.search(rf"^thermal_edge_{name}{re.escape(label)} (\S+)$", scrape, re.M)
        assert m, name + label
        return float(m.group(1))

    assert value("flux_refused_total", '{reason="stale"}') == 30
    assert value("flux_refused_total", '{reason="implausible"}') == 20
    assert value("flux_refused_total", '{reason="disagreement"}') == 0
    assert value("flux_used_total") == counts["used"] > 0
    mg = pol.last_out.magnet
    assert value("magnet_band_celsius") == pytest.approx(mg.observer_upper_c - mg.estimate_c)
    assert math.isfinite(value("flux_magnet_celsius"))
    # the wrong calibration's run ends refusing: the gauge shows the last fused value, never a refused one
    fw = pol_w.engine.flux
    scrape_w = ServiceMetrics()
    scrape_w.attach(pol_w.engine)
    text_w = scrape_w.text()
    assert fw.last is not None and fw.last.outcome != "used"
    shown = re.search(r"^thermal_edge_flux_magnet_celsius (\S+)$", text_w, re.M)
    if fw.counts["used"]:
        assert shown and float(shown.group(1)) == fw.last_used.estimate_c and fw.last_used.outcome == "used"
        assert float(shown.group(1)) != fw.last.estimate_c
    else:
        assert shown is None
    # no metric of the voltage input without it
    plain = ServiceMetrics()
    plain.attach(ThermalEngine(P.edge_config(tmp_path / "plain"), worker_mode="sync"))
    assert "flux_" not in plain.text() and "magnet_band" not in plain.text()


@pytest.mark.slow
def test_bench_with_the_voltage_frame_and_with_a_wrong_calibration():
    """The protection bench's cycle: with the voltage frame at least 97 % of the oracle and never
    over max; with the electrical calibration wrong (inductances +20 %, voltage error doubled) the
    disagreement check fires and nothing overheats."""
    good = P.run_case(NOMINAL, policies=("thermal_edge_voltages", "oracle"))
    assert good["thermal_edge_voltages"]["seconds_over_max"] == 0.0
    assert good["thermal_edge_voltages"]["oracle_share_pct"] >= 97.0
    bad = P.run_case(P.CASES["electrical_wrong"], policies=("thermal_edge_voltages",))["thermal_edge_voltages"]
    assert bad["seconds_over_max"] == 0.0
    assert bad["flux"]["disagreement"] > 100


def test_the_bench_table_puts_both_runs_side_by_side():
    """One row per case: without and with the voltage frame beside the PT100 rule and I²t, and the
    flux ticks used / refused (counted here from the figures)."""
    def fig(share: float, over: float, **extra) -> dict:
        return {"oracle_share_pct": share, "seconds_over_max": over, **extra}

    res = P.ProtectionResult("protection.yaml", None, list(P.POLICIES), 10.0, {}, cases={
        "nominal": {"thermal_edge": fig(95.5, 0), "thermal_edge_voltages": fig(99.6, 0, flux={"used": 70, "transient": 3}),
                    "pt100_linear": fig(98.4, 0), "i2t": fig(76.7, 0), "oracle": fig(100, 0)},
        "electrical_wrong": {"thermal_edge": fig(95.5, 0), "pt100_linear": fig(98.4, 0), "i2t": fig(76.7, 0),
                             "thermal_edge_voltages": fig(94.8, 0, flux={"used": 10, "disagreement": 50, "stale": 2})}})
    rows = P.side_by_side_rows(res)
    assert rows == [["nominal", "95.5 / 0", "99.6 / 0", "98.4 / 0", "76.7 / 0", "70 / 0"],
                    ["electrical_wrong", "95.5 / 0", "94.8 / 0", "98.4 / 0", "76.7 / 0", "10 / 52"]]
    assert len(P.SIDE_BY_SIDE_HEADERS) == len(rows[0])


@pytest.mark.parametrize("edit, words", [
    (lambda d: d["params"].__setitem__("beta", 0.0), "params.beta must be negative"),
    (lambda d: d["params"].__setitem__("beta", 1e-4), "params.beta must be negative"),
    (lambda d: d["params"].__setitem__("r20", float("nan")), "params.r20 is not a finite number"),
    (lambda d: d["params"].__setitem__("psi20", -0.1), "params.psi20 must be positive"),
    (lambda d: d.__setitem__("pole_pairs", 0), "pole_pairs must be 1 to 100"),
    (lambda d: d.__setitem__("bin_a", 0), "bin_a must be positive"),
    (lambda d: d.__setitem__("var_u", {}), "var_u is empty"),
    (lambda d: d.__setitem__("cov", [[1.0, 2.0]]), "cov must be a finite 8 x 8 matrix"),
])
def test_a_flux_model_file_that_no_commissioning_could_write_is_refused_at_start(tmp_path, calibration, edit, words):
    """A hand-edited or foreign calibration fails where it is read (run --check and the service's
    start: exit 2, one line naming the file's entry), not in the tick (a division by zero, a model
    fault every 30 s)."""
    from thermal_edge.cli import main

    d = json.loads(calibration.read_text())
    edit(d)
    bad = tmp_path / "flux.json"
    bad.write_text(json.dumps(d))
    raw = yaml.safe_load(config_path("edge.yaml").read_text())
    raw["flux"] = {**raw["flux"], "calibration": str(bad), "winding_node": "slot_winding_1"}
    raw["state"] = {"dir": str(tmp_path / "state")}
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(ConfigError) as info:
        cfg = config_from_mapping(raw, path)
        ThermalEngine(cfg, load_service_model(cfg), worker_mode="sync")
    assert str(info.value).startswith(f"edge.yaml: flux.calibration: {bad} is not a flux model"), str(info.value)
    assert words in str(info.value)
    assert main(["run", "--check", "--config", str(path)]) == 2


def test_run_check_reads_the_calibration_and_names_it(tmp_path, calibration, capsys):
    from thermal_edge.cli import main

    raw = yaml.safe_load(config_path("edge.yaml").read_text())
    raw["state"] = {"dir": str(tmp_path / "state")}
    raw["flux"] = {**raw["flux"], "calibration": str(tmp_path / "missing.json"), "winding_node": "slot_winding_1"}
    path = tmp_path / "edge.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    assert main(["run", "--check", "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "flux.calibration: cannot read" in err[0], err
    raw["flux"]["calibration"] = str(calibration)
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    assert main(["run", "--check", "--config", str(path)]) == 0
    out = capsys.readouterr().out
    pp = json.loads(calibration.read_text())["pole_pairs"]
    assert f"INV_Voltages: the magnet from the voltages, {calibration} ({pp} pole pairs" in out, out


def test_a_bad_crc_on_the_voltage_frame_is_counted_by_frame_on_metrics(tmp_path, calibration):
    """Voltage frames with a corrupted CRC byte are dropped by the service's codec and shown on
    /metrics under their frame's name (counted here: 3 corrupted of 5 sent), the voltage frame's
    series present from the first scrape."""
    from thermal_edge.bus.codec import FrameCodec
    from thermal_edge.bus.frames import DEFAULT_DBC_PATH

    cfg = P.edge_config(tmp_path / "s", None, calibration)
    engine = ThermalEngine(cfg, worker_mode="sync")
    tx, rx = FrameCodec(DEFAULT_DBC_PATH), FrameCodec(DEFAULT_DBC_PATH)
    metrics = ServiceMetrics()
    metrics.attach(engine, codec=rx)

    def value(text: str, frame: str) -> float:
        m = re.search(rf'^thermal_edge_frames_dropped_by_frame_total{{frame="{frame}"}} (\S+)$', text, re.M)
        assert m, frame
        return float(m.group(1))

    assert value(metrics.text(), "INV_Voltages") == 0
    fid = tx.frame_id("INV_Voltages")
    for k in range(5):
        data = bytearray(tx.encode("INV_Voltages", {"INV_Ud": -50.0, "INV_Uq": 240.0}))
        if k % 2 == 0:
            data[7] ^= 0xFF  # the CRC byte
        rx.decode(fid, bytes(data), timestamp=0.01 * k)
    scrape = metrics.text()
    assert value(scrape, "INV_Voltages") == 3
    assert rx.stats.crc == 3 and rx.stats.received["INV_Voltages"] == 2
    engine.close()


def test_each_refusal_cause_has_its_own_log_budget(tmp_path, calibration):
    """Through the journal's rate limit (5 lines per format and minute): 20 implausible and 20 old
    refusals use up their own budgets only; a disagreement after them is still logged."""
    from thermal_edge.service.flux_input import FluxTick
    from thermal_edge.service.journal import RateLimit

    cfg = P.edge_config(tmp_path / "s", None, calibration)
    engine = ThermalEngine(cfg, worker_mode="sync")
    lines = io.StringIO()
    handler = logging.StreamHandler(lines)
    handler.addFilter(RateLimit(burst=5, window_s=60.0, clock=lambda: 0.0))
    logger = logging.getLogger("thermal_edge.service.flux_input")
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        for _ in range(20):
            engine.flux._done(FluxTick("implausible", 900.0), "voltages in kV")
        for _ in range(20):
            engine.flux._done(FluxTick("old"), "voltages 1200 s behind the frame clock")
        engine.flux._done(FluxTick("disagreement", 60.0, 1.0), "the model says 90 degC")
    finally:
        logger.removeHandler(handler)
        logger.setLevel(logging.NOTSET)
        engine.close()
    text = lines.getvalue().splitlines()
    assert sum(1 for x in text if x.startswith("flux estimate refused (implausible)")) == 5
    assert sum(1 for x in text if x.startswith("flux estimate refused (old)")) == 5
    assert sum(1 for x in text if x.startswith("flux estimate refused (disagreement)")) == 1


def test_a_wrong_inductance_table_is_refused_in_field_weakening_only(tmp_path, calibration):
    """Every inductance of the calibration 20 % high (the voltage error right): at 900 rpm the
    inverter runs at i_d = 0 and the estimate is unaffected (used, never refused); at 1500 rpm it
    weakens the field, L_d i_d enters the estimate, and the disagreement check refuses it; the
    magnet's estimate there is then the model's without voltages, tick for tick."""
    from thermal_edge.bench.commissioning import miscalibrated

    flux = FluxModel.from_dict(json.loads(calibration.read_text()))
    bad = tmp_path / "l_high.json"
    bad.write_text(json.dumps(miscalibrated(flux, inductance_factor=1.2, voltage_error_factor=1.0).as_dict()))
    slow, pol_s, _ = loop(tmp_path, cycle(tmp_path, (300.0, 900.0, 150.0)), flux=bad, voltages=True, name="s")
    assert pol_s.engine.flux.counts["used"] > 250 and pol_s.engine.flux.counts["disagreement"] == 0
    fast_cycle = cycle(tmp_path, (300.0, 1500.0, 150.0))
    fast, pol_f, model = loop(tmp_path, fast_cycle, flux=bad, voltages=True, name="f")
    plain, _, _ = loop(tmp_path, fast_cycle, flux=None, voltages=False, name="p")
    counts = pol_f.engine.flux.counts
    steady_ticks = [t for t in fast if t[4] not in (None, "transient", "low_speed")]
    assert counts["disagreement"] >= 0.9 * len(steady_ticks) and counts["used"] <= 0.1 * len(steady_ticks)
    if counts["used"] == 0:
        i = model.node_index(MAGNET)
        for a, b in zip(plain, fast):
            assert a[1][i] == pytest.approx(b[1][i], abs=1e-9)


@pytest.mark.async_timeout(600)
async def test_voltage_frames_far_behind_the_frame_clock_are_refused_as_old(tmp_path, channel, calibration, caplog):
    """The service in frame-clock mode on a ``virtual`` bus with the inverter emulator (voltages on,
    900 rpm): once the emulator's INV_Voltages stop, an independent client sends the voltages it
    heard, stamped 20 min before the newest frame on the bus. Every tick with such frames is refused
    as ``old`` (the ticks counted by the client from its own stamps; on /metrics; a WARNING line
    each) and nothing is fused; the same voltages stamped on time are fused again (it is the stamp
    that is refused, not the values)."""
    import asyncio

    import can
    from svc_testlib import MAX_LEAD_S, async_wait_until, edge_raw, emulator_config, scrape, sim_until, write_yaml

    from thermal_edge.bus.codec import FrameCodec
    from thermal_edge.config import load_config
    from thermal_edge.service import EdgeService
    from thermal_edge.sim.inverter import InverterEmulator

    raw = edge_raw(tmp_path / "state", {"interface": "virtual", "channel": channel}, table4=False, adapt=False,
                   metrics_port=0, flux={"calibration": str(calibration)})
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", raw))
    tick = cfg.clock.tick_s
    svc = EdgeService(cfg)
    await svc.start()
    emu = InverterEmulator(emulator_config(duration_s=3600.0, speed=100.0, max_lead_s=MAX_LEAD_S, pmsm=Pmsm(),
                                           cycle_path=config_path("cycles", "rated_heat_cool.yaml")),
                           {"interface": "virtual", "channel": channel, "preserve_timestamps": True})
    client = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    codec = FrameCodec()  # the client's own: its own counters
    ids = {n: codec.frame_id(n) for n in ("INV_Currents", "INV_Voltages")}
    heard: dict[str, float] = {}
    mode: dict[str, float | None] = {"age": None}  # None: listen only; else the age (s) of the voltages sent
    old_ticks: set[int] = set()  # the service's ticks that get the client's old voltages
    sent = {"old": 0, "on time": 0}

    async def listen_and_send() -> None:
        """Drain the bus, then (when sending) an INV_Voltages for each INV_Currents heard, stamped
        ``age`` s before the newest frame heard. The service reads it right after that frame, so
        it falls in the tick that frame's time falls in: the one ending at the next boundary."""
        while True:
            newest, currents = -math.inf, 0
            while (msg := client.recv(timeout=0.0)) is not None:
                newest = max(newest, msg.timestamp)
                if msg.arbitration_id == ids["INV_Voltages"]:
                    heard.update(codec.decode(msg.arbitration_id, msg.data, timestamp=msg.timestamp).signals)
                currents += msg.arbitration_id == ids["INV_Currents"]
            age = mode["age"]
            for _ in range(currents if age is not None and heard else 0):
                data = codec.encode("INV_Voltages", {"INV_Ud": heard["INV_Ud"], "INV_Uq": heard["INV_Uq"]})
                client.send(can.Message(timestamp=newest - age, arbitration_id=ids["INV_Voltages"], data=data,
                                        is_extended_id=False))
                sent["old" if age else "on time"] += 1
                if age:
                    old_ticks.add(math.floor(newest / tick))
            await asyncio.sleep(0.0002)

    loop = asyncio.get_running_loop()
    tasks = [loop.create_task(emu.run()), loop.create_task(listen_and_send())]
    caplog.set_level(logging.WARNING, logger="thermal_edge.service.flux_input")
    fx = svc.engine.flux
    try:
        assert await async_wait_until(lambda: emu.elapsed > 0 and emu.bus is not None, 300.0)
        await sim_until(emu, 120.0)
        first = dict(fx.counts)
        emu.paused.add("INV_Voltages")
        await sim_until(emu, 120.0 + 2 * MAX_LEAD_S)  # the emulator's last voltages through
        used = fx.counts["used"]
        mode["age"] = 1200.0
        await sim_until(emu, 240.0)
        mode["age"] = None  # a gap: no tick has old voltages and on-time ones
        await sim_until(emu, 240.0 + 2 * MAX_LEAD_S)
        old, used_old = fx.counts["old"], fx.counts["used"]
        mode["age"] = 0.0  # the same voltages, on time
        await sim_until(emu, 360.0)
        m = scrape(svc.metrics.port)
    finally:
        emu.stop()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        client.shutdown()
        await svc.stop()
    assert first.get("used", 0) > 100 and first.get("old", 0) == 0  # the emulator's voltages: on time
    assert sent["old"] > 100 and len(old_ticks) > 30
    assert old == len(old_ticks)  # every tick with only old voltages refused, as the client counts them
    assert used_old == used  # none fused
    assert fx.counts["old"] == old and fx.counts["used"] > used  # on time: fused again, none old
    assert m['thermal_edge_flux_refused_total{reason="old"}'] == old
    lines = [r for r in caplog.records if r.getMessage().startswith("flux estimate refused (old)")]
    assert len(lines) == old and all(r.levelno == logging.WARNING for r in lines)
    assert "1200.0 s behind the frame clock" in lines[0].getMessage()


def test_how_far_a_frame_lies_behind_the_frame_clock() -> None:
    """``FrameClock.behind`` against the stamps' own differences: 0 for a frame that advances the
    clock, the jitter for one a little back, 20 min for one stamped 20 min back, and 0 again for
    the frames of a backward segment once the clock has joined it on (and the wall clock: 0)."""
    from thermal_edge.service.clock import FrameClock, WallClock

    c = FrameClock(1.0)
    seg1 = [100.0 + 0.1 * i for i in range(50)]  # 100.0 .. 104.9
    seen = []
    for ts in seg1:
        c.observe(ts)
        seen.append(c.behind(ts))
    assert seen == [0.0] * len(seg1)
    c.observe(104.85)  # jitter
    assert c.behind(104.85) == pytest.approx(0.05)
    c.observe(104.9 - 1200.0)  # a stamp 20 min back, between frames on time
    assert c.behind(104.9 - 1200.0) == pytest.approx(1200.0)
    seg2 = [50.0 + 0.1 * i for i in range(50)]  # a new segment 55 s back: joined on after a few frames
    last = []
    for ts in seg2:
        c.observe(ts)
        last.append(c.behind(ts))
    assert c.stats.joined == 1 and last[0] == pytest.approx(104.9 - 50.0) and last[-1] == 0.0
    assert c.behind(None) == 0.0 and WallClock().behind(100.0) == 0.0
