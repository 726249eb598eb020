"""config/edge.yaml: the shipped file is complete and valid; broken files name the file and the key."""
from __future__ import annotations

import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import pytest
import yaml
from cli_in_process import te_here
from svc_testlib import EDGE_YAML, REPO, env, write_yaml

from thermal_edge.bus import DEFAULT_DBC_PATH, FrameCodec
from thermal_edge.config import ConfigError, config_from_mapping, load_config
from thermal_edge.estimation.adapter import AdapterConfig
from thermal_edge.service.engine import load_service_model


def shipped() -> dict:
    """The shipped file, its relative paths made absolute (the tests write it elsewhere)."""
    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["model"]["path"] = str(REPO / "config" / "machines" / "pm10kw.yaml")
    raw["codec"]["dbc"] = str(REPO / "dbc" / "thermal_edge.dbc")
    return raw


def test_shipped_config_is_valid_and_complete():
    cfg = load_config(EDGE_YAML)
    model = load_service_model(cfg)
    cfg.check_model(model)
    cfg.check_dbc(FrameCodec(cfg.codec.dbc or DEFAULT_DBC_PATH))
    assert cfg.metrics.address == "127.0.0.1" and cfg.metrics.port == 9108
    assert cfg.clock.mode == "wall" and cfg.clock.tick_s == 1.0
    assert set(cfg.inputs) == set(model.inputs)
    assert set(cfg.sensors) == set(model.sensors)
    assert cfg.inputs["i_rms"].reduce == "dq_rms"
    # every AdapterConfig field is spelled out in the file (commented documentation of each setting)
    text = EDGE_YAML.read_text()
    for f in fields(AdapterConfig):
        assert f"{f.name}:" in text, f"adaptation.{f.name} missing from edge.yaml"
    # every section is commented
    for section in ("bus", "codec", "model", "clock", "signals", "timeouts", "derating", "lookahead", "adaptation",
                    "observer", "metrics", "state", "recording", "transmit"):
        assert f"\n{section}:" in text


@pytest.mark.parametrize(
    "edit, key, words",
    [
        (lambda r: r["derating"].__setitem__("safe_current_a", -3), "derating.safe_current_a", "must be positive"),
        (lambda r: r["derating"].__setitem__("safe_current_a", 99), "derating.safe_current_a", "must not exceed"),
        (lambda r: r["derating"].pop("max_current_a"), "derating.max_current_a", "is required"),
        (lambda r: r["derating"].__setitem__("safe_torque_nm", 500), "derating.safe_torque_nm",
         "must not exceed max_torque_nm (220)"),
        (lambda r: r["lookahead"].__setitem__("horizon_s", "long"), "lookahead.horizon_s", "expected a number"),
        (lambda r: r["clock"].__setitem__("mode", "sundial"), "clock.mode", "must be one of"),
        (lambda r: r["adaptation"].__setitem__("period_s", 0), "adaptation.period_s", "must be positive"),
        (lambda r: r["adaptation"].__setitem__("method", "guess"), "adaptation.method", "must be one of"),
        (lambda r: r["metrics"].__setitem__("port", 70000), "metrics.port", "at most 65535"),
        (lambda r: r.__setitem__("derating_typo", {}), "derating_typo", "unknown key"),
        (lambda r: r["derating"]["limits"]["hot_spot"].__setitem__("max_c", 100), "derating.limits.hot_spot.max_c",
         "must be above warn_c"),
        (lambda r: r["signals"]["inputs"]["i_rms"].__setitem__("reduce", "median"), "signals.inputs.i_rms.reduce",
         "must be one of"),
        (lambda r: r["signals"]["inputs"]["i_rms"].__setitem__("signals", ["INV_Id"]), "signals.inputs.i_rms.signals",
         "dq_rms needs"),
        (lambda r: r["signals"].__setitem__("valid_range_c", [300, 10]), "signals.valid_range_c", "low < high"),
        (lambda r: r["observer"].__setitem__("q_k", True), "observer.q_k", "expected a number"),
        (lambda r: r["state"].__setitem__("save_interval_s", -1), "state.save_interval_s", "must be positive"),
        (lambda r: r["state"].__setitem__("save_interval_s", 86400000), "state.save_interval_s", "at most 86400"),
        (lambda r: r["signals"].__setitem__("valid_current_factor", 0.5), "signals.valid_current_factor",
         "must be at least 1"),
        (lambda r: r["signals"].__setitem__("valid_torque_factor", 0.5), "signals.valid_torque_factor",
         "must be at least 1"),
        (lambda r: r["bus"].__setitem__("bitrate", -5), "bus.bitrate", "positive integer"),
        (lambda r: r["model"].pop("path"), "model.path", "is required"),
    ],
)
def test_broken_config_names_file_and_key(tmp_path, edit, key, words):
    raw = shipped()
    edit(raw)
    path = write_yaml(tmp_path / "edge.yaml", raw)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    msg = str(err.value)
    assert msg.startswith(f"edge.yaml: {key}:"), msg
    assert words in msg
    assert "\n" not in msg


@pytest.mark.parametrize(
    "edit, key, words",
    [
        (lambda r: r["signals"]["inputs"].pop("ambient_c"), "signals.inputs.ambient_c", "needs this input"),
        (lambda r: r["signals"]["sensors"].__setitem__("rotor", {"frame": "INV_StatorTemps", "signal": "INV_T_Housing"}),
         "signals.sensors.rotor", "has no sensor"),
        (lambda r: r["derating"]["limits"].__setitem__("bearing", {"warn_c": 80, "max_c": 90}), "derating.limits.bearing",
         "no limited node"),
        (lambda r: r["model"]["parameters"].__setitem__("R_e_hous", 1000.0), "model.parameters.R_e_hous",
         "1000 is outside the model's bounds [3, 30] K/W (bounds of pm10kw.yaml)"),
        # a torque constant off by a decade: every torque limit sent would be 10 x too high
        (lambda r: r["derating"].__setitem__("kt_nm_per_arms", 56.0), "derating.kt_nm_per_arms",
         "56 Nm/A is 10 x model pm10kw's drive.kt_nm_per_arms (5.6 Nm/A)"),
        # kt x safe current above the maximum torque: the safe torque would be the full torque
        (lambda r: (r["derating"].pop("safe_torque_nm"), r["derating"].update(kt_nm_per_arms=11.0, safe_current_a=25.0)),
         "derating.kt_nm_per_arms",
         "= 275 Nm exceeds max_torque_nm (220): the safe torque would be the full torque"),
        (lambda r: r["signals"]["inputs"].__setitem__("i_rms", {"frame": "INV_Currents", "reduce": "mean",
                                                                "signal": "INV_IphRms"}),
         "signals.inputs.i_rms.reduce", "need its mean square over the tick"),
        (lambda r: r["signals"]["inputs"]["speed_rpm"].__setitem__("reduce", "rms"), "signals.inputs.speed_rpm.reduce",
         "signed: mean (or latest)"),
    ],
)
def test_config_checked_against_the_model(tmp_path, edit, key, words):
    raw = shipped()
    edit(raw)
    cfg = config_from_mapping(raw, tmp_path / "edge.yaml")
    with pytest.raises(ConfigError) as err:
        cfg.check_model(load_service_model(cfg))
    assert str(err.value).startswith(f"edge.yaml: {key}:") and words in str(err.value)


def test_config_checked_against_the_dbc(tmp_path):
    raw = shipped()
    raw["signals"]["sensors"]["housing"]["signal"] = "INV_T_Hosuing"
    cfg = config_from_mapping(raw, tmp_path / "edge.yaml")
    with pytest.raises(ConfigError,
                       match=r"^edge.yaml: signals.sensors.housing: frame INV_StatorTemps has no signal 'INV_T_Hosuing'"):
        cfg.check_dbc(FrameCodec(cfg.codec.dbc))
    raw = shipped()
    raw["timeouts"]["INV_Nothing"] = 1.0
    cfg = config_from_mapping(raw, tmp_path / "edge.yaml")
    with pytest.raises(ConfigError, match=r"^edge.yaml: timeouts.INV_Nothing: no frame"):
        cfg.check_dbc(FrameCodec(cfg.codec.dbc))


def test_invalid_yaml_and_missing_file(tmp_path):
    p = tmp_path / "edge.yaml"
    p.write_text("bus: [unclosed\n")
    with pytest.raises(ConfigError, match=r"^edge.yaml: not valid YAML"):
        load_config(p)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.yaml")


def test_model_path_a_file_beside_the_config_before_a_packaged_name(tmp_path):
    """``model.path``: a file relative to the configuration wins; a bare name with no such file is the
    packaged model (``pm10kw`` or ``pm10kw.yaml``); anything else stays the path it names."""
    raw = yaml.safe_load(EDGE_YAML.read_text())
    packaged = (REPO / "thermal_edge" / "resources" / "machines" / "pm10kw.yaml").resolve()

    def model_path(ref: str) -> Path:
        return config_from_mapping({**raw, "model": {"path": ref}}, tmp_path / "edge.yaml").model.path

    assert model_path("pm10kw").resolve() == packaged
    assert model_path("pm10kw.yaml").resolve() == packaged
    assert model_path("sub/pm10kw.yaml") == tmp_path / "sub" / "pm10kw.yaml"  # a path, never a name
    assert model_path("pm11") == tmp_path / "pm11"  # unknown: loading it names the missing file
    (tmp_path / "pm10kw.yaml").write_text("a user's own model\n")
    assert model_path("pm10kw.yaml") == tmp_path / "pm10kw.yaml"


def test_relative_paths_resolve_against_the_config_directory(tmp_path):
    cfg = load_config(EDGE_YAML)  # its model by name: the packaged file
    assert cfg.model.path.resolve() == (REPO / "config" / "machines" / "pm10kw.yaml").resolve()
    assert cfg.codec.dbc is None  # the packaged DBC
    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["codec"]["dbc"] = "../dbc/thermal_edge.dbc"
    cfg = config_from_mapping(raw, tmp_path / "etc" / "edge.yaml")
    assert cfg.codec.dbc.resolve() == (tmp_path / "dbc" / "thermal_edge.dbc").resolve()


def test_run_command_rejects_a_broken_config_with_one_line(tmp_path):
    raw = shipped()
    raw["derating"]["safe_current_a"] = -3
    path = write_yaml(tmp_path / "edge.yaml", raw)
    proc = subprocess.run([sys.executable, "-m", "thermal_edge.cli", "run", "--config", str(path)], capture_output=True,
                          text=True, env=env(), cwd=str(REPO), timeout=60)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert lines == ["thermal-edge run: error: edge.yaml: derating.safe_current_a: must be positive, got -3"], proc.stderr


def _set(path: str, value):
    """An edit of the raw configuration: set the dotted ``path`` (creating sections) to ``value``."""
    def edit(raw: dict, tmp: Path) -> None:
        *parents, last = path.split(".")
        d = raw
        for k in parents:
            d = d.setdefault(k, {})
        d[last] = value(tmp) if callable(value) else value
    return edit


def _a_file(tmp: Path) -> str:
    (tmp / "a_file").write_text("x")
    return str(tmp / "a_file")


def _rename(section: str, old: str, new: str):
    def edit(raw: dict, tmp: Path) -> None:
        d = raw[section] if section else raw
        d[new] = d.pop(old)
    return edit


# (case, edit, key, words): each gives exit 2 and exactly one line on stderr, naming the file and the key
BROKEN = [
    ("limits period above the inverter timeout", _set("transmit.limits_period_s", 0.5), "transmit.limits_period_s",
     "must be at most 0.15 s (the inverter drops TE_Limits after 300 ms"),
    ("limits period at the inverter timeout", _set("transmit.limits_period_s", 0.3), "transmit.limits_period_s",
     "at most 0.15 s"),
    ("state.dir is a file", _set("state.dir", _a_file), "state.dir", "is not a directory"),
    ("state.dir under a file", _set("state.dir", lambda t: _a_file(t) + "/state"), "state.dir", "cannot be created"),
    ("recording a directory", _set("recording.candump", lambda t: (t / "dir.log").mkdir() or str(t / "dir.log")),
     "recording.candump", "is a directory, not a log file"),
    ("recording under a file", _set("recording.candump", lambda t: _a_file(t) + "/can.log"), "recording.candump",
     "(the directory of can.log) is not a directory"),
    ("recording where no directory can be", _set("recording.candump", "/proc/thermal-edge/can.log"), "recording.candump",
     "cannot be created under /proc"),
    ("parameter below its bound", _set("model.parameters", {"R_e_hous": 0.91}), "model.parameters.R_e_hous",
     "0.91 is outside the model's bounds [3, 30] K/W"),
    ("parameter a round-off below its bound", _set("model.parameters", {"c_p_ew": 299.99999999999994}),
     "model.parameters.c_p_ew", "299.99999999999994 is outside the model's bounds [300, 900]"),
    ("unknown parameter", _set("model.parameters", {"R_e_house": 9.1}), "model.parameters.R_e_house",
     "has no parameter 'R_e_house' (did you mean 'R_e_hous'?)"),
    ("parameter not a number", _set("model.parameters", {"c_p_ew": "hot"}), "model.parameters.c_p_ew", "expected a number"),
    ("parameters a list", _set("model.parameters", [1, 2]), "model.parameters", "expected a mapping"),
    ("typo under bus", _rename("bus", "channel", "chanel"), "bus.chanel", "did you mean 'channel'"),
    ("typo under state", _rename("state", "save_interval_s", "save_intervall_s"), "state.save_intervall_s",
     "unknown key (did you mean 'save_interval_s'?)"),
    ("typo of a section", _rename("", "transmit", "transmitt"), "transmitt", "unknown key (did you mean 'transmit'?)"),
    ("negative safe current", _set("derating.safe_current_a", -3), "derating.safe_current_a", "must be positive"),
    ("port out of range", _set("metrics.port", 70000), "metrics.port", "at most 65535"),
    ("unknown clock mode", _set("clock.mode", "sundial"), "clock.mode", "must be one of"),
    ("unknown reduction", _set("signals.inputs.i_rms.reduce", "median"), "signals.inputs.i_rms.reduce", "must be one of"),
    ("model file missing", _set("model.path", "/nonexistent/pm10kw.yaml"), "model.path", "cannot read"),
    ("model file not a model", _set("model.path", str(EDGE_YAML)), "model.path", "unknown section"),
    ("DBC missing", _set("codec.dbc", "/nonexistent/te.dbc"), "codec.dbc", "cannot load DBC"),
    ("unknown adaptable parameter", _set("adaptation.params", ["R_e_house"]), "adaptation.params", "did you mean 'R_e_hous'"),
    ("unknown sensor", _set("signals.sensors.rotor", {"frame": "INV_StatorTemps", "signal": "INV_T_Housing"}),
     "signals.sensors.rotor", "has no sensor"),
    ("warn above max", _set("derating.limits.hot_spot.max_c", 100), "derating.limits.hot_spot.max_c", "must be above warn_c"),
    ("too many decisions kept", _set("state.max_decisions", 100000), "state.max_decisions", "at most 5000"),
    ("zero timeout", _set("timeouts.INV_Currents", 0), "timeouts.INV_Currents", "must be positive"),
    ("boolean noise", _set("observer.q_k", True), "observer.q_k", "expected a number"),
    ("frame not in the DBC", _set("signals.inputs.i_rms.frame", "INV_Nothing"), "signals.inputs.i_rms.frame", "no frame"),
    ("transmitted limit unknown", _set("transmit.hot_spot_limit", "nowhere"), "transmit.hot_spot_limit", "no limited node"),
    ("bitrate negative", _set("bus.bitrate", -5), "bus.bitrate", "positive integer"),
    ("state.dir on a file system that cannot hold it", _set("state.dir", "/proc/thermal-edge/state"), "state.dir",
     "cannot be created under /proc"),
    ("metrics address a name", _set("metrics.address", "not an address"), "metrics.address", "not an IP address"),
    ("udp_multicast channel a unicast address", _set("bus", {"interface": "udp_multicast", "channel": "192.0.2.1"}),
     "bus.channel", "not a multicast group"),
    ("maximum current the DBC cannot carry", _set("derating.max_current_a", 3400), "derating.max_current_a",
     "must be at most 3276.75, the largest value TE_CurrentLimit carries in thermal_edge.dbc; got 3400"),
    ("maximum torque the DBC cannot carry", _set("derating.max_torque_nm", 10000), "derating.max_torque_nm",
     "must be at most 6553.5, the largest value TE_TorqueLimit carries"),
    ("no hold after a model fault", _set("derating.faults.hold_s", 0), "derating.faults.hold_s", "must be at least 10, got 0"),
    # values that would switch protection off
    ("a hold shorter than a tick", _set("derating.faults.hold_s", 1e-9), "derating.faults.hold_s", "must be at least 10"),
    ("a frame timeout of 1e9 s", _set("timeouts.INV_StatorTemps", 1e9), "timeouts.INV_StatorTemps", "must be at most 10"),
    ("bus silence of 1e9 s", _set("transmit.bus_silence_s", 1e9), "transmit.bus_silence_s", "must be at most 10"),
    ("no timeouts at all", _set("timeouts", {}), "timeouts.INV_Currents",
     "missing: signals.inputs.i_rms reads frame INV_Currents, which needs a timeout"),
    ("model-fault threshold of 1e9 K", _set("derating.faults.prediction_error_k", 1e9), "derating.faults.prediction_error_k",
     "must be at most 200"),
    ("stuck check of 1e9 K", _set("derating.faults.stuck_model_k", 1e9), "derating.faults.stuck_model_k", "must be at most 50"),
    ("plausible current of 1e9 x the maximum", _set("signals.valid_current_factor", 1e9), "signals.valid_current_factor",
     "must be at most 10"),
    ("a tick of a day", _set("clock.tick_s", 86400), "clock.tick_s", "must be at most 10"),
    # periods that would starve or flood
    ("a tick of a millisecond", _set("clock.tick_s", 0.001), "clock.tick_s", "must be at least 0.1, got 0.001"),
    ("TE_Limits every microsecond", _set("transmit.limits_period_s", 1e-6), "transmit.limits_period_s",
     "must be at least 0.01"),
    ("status frames every microsecond", _set("transmit.status_period_s", 1e-6), "transmit.status_period_s",
     "must be at least 0.1"),
]
# the checks that need more than the file also hold when the service starts (not only with --check)
AT_START = {"limits period above the inverter timeout", "state.dir is a file", "state.dir under a file",
            "parameter below its bound", "unknown parameter", "typo under bus", "maximum current the DBC cannot carry"}


def _run(path: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """``thermal-edge run [--check] --config path``: ``--check`` in this process (it cannot start the
    service), a start in a process of its own (a config that wrongly passes would start it)."""
    if "--check" in extra:
        return te_here("run", *extra, "--config", path)
    return subprocess.run([sys.executable, "-m", "thermal_edge.cli", "run", *extra, "--config", str(path)],
                          capture_output=True, text=True, env=env(), cwd=str(REPO), timeout=120)


CASES = [(*b, "--check") for b in BROKEN] + [(*b, "start") for b in BROKEN if b[0] in AT_START]


@pytest.mark.parametrize("case, edit, key, words, mode", CASES, ids=[f"{c[0]} ({c[4]})" for c in CASES])
def test_broken_config_exits_2_with_one_line_naming_file_and_key(tmp_path, case, edit, key, words, mode):
    raw = shipped()
    raw["state"]["dir"] = str(tmp_path / "state")
    edit(raw, tmp_path)
    path = write_yaml(tmp_path / "broken.yaml", raw)
    proc = _run(path, *(["--check"] if mode == "--check" else []))
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith(f"thermal-edge run: error: broken.yaml: {key}: "), lines[0]
    assert words in lines[0], lines[0]
    assert not (tmp_path / "state" / "state.json").exists()


def test_check_accepts_the_shipped_file_with_a_state_dir_still_to_create(tmp_path):
    raw = shipped()
    raw["state"]["dir"] = str(tmp_path / "not" / "yet")
    proc = _run(write_yaml(tmp_path / "edge.yaml", raw), "--check")
    assert proc.returncode == 0 and proc.stdout.startswith("edge.yaml: ok"), proc.stderr
    assert not (tmp_path / "not").exists()  # --check creates nothing


# what PyYAML alone gets wrong in a hand-typed file: each is still
# exit 2 and one line naming the file (and the key or the line)
TEXT_EDITS = [
    ("a number written 1e9", lambda t: t.replace("  tick_s: 1.0 ", "  tick_s: 1e9 "),
     "clock.tick_s: must be at most 10, got 1e+09"),
    ("a number written 5e-1", lambda t: t.replace("  tick_s: 1.0 ", "  tick_s: 5e-1 "), None),
    ("a section given twice", lambda t: t + "\nbus:\n  interface: virtual\n", "key 'bus' appears twice (first on line"),
    ("nested 5,000 deep", lambda t: t + "\nextra: " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply to read"),
]


@pytest.mark.parametrize("case, edit, words", TEXT_EDITS, ids=[c[0] for c in TEXT_EDITS])
def test_hand_typed_yaml_is_read_as_an_engineer_means_it(tmp_path, case, edit, words):
    text = EDGE_YAML.read_text()
    text = text.replace("path: machines/pm10kw.yaml", f"path: {REPO / 'config' / 'machines' / 'pm10kw.yaml'}")
    text = text.replace("  dir: ", f"  dir: {tmp_path / 'state'}  # ", 1)
    changed = edit(text)
    assert changed != text
    path = tmp_path / "edge.yaml"
    path.write_text(changed)
    proc = _run(path, "--check")
    if words is None:  # read as the number it looks like: the file is valid
        assert proc.returncode == 0, proc.stderr
        assert load_config(path).clock.tick_s == 0.5
        return
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("thermal-edge run: error: edge.yaml: ") and words in lines[0], lines[0]


# -- another inverter's CAN matrix: codec.protection and the d/q convention ---------------------------
EXAMPLE = REPO / "config" / "examples" / "acme-mc7"


def example() -> dict:
    """The Acme MC-7 example's edge.yaml, its relative paths made absolute."""
    raw = yaml.safe_load((EXAMPLE / "edge.yaml").read_text())
    raw["codec"]["dbc"] = str(EXAMPLE / "acme-mc7.dbc")
    raw["model"]["path"] = str(REPO / "config" / "machines" / "pm10kw.yaml")
    return raw


FOREIGN_BROKEN = [
    ("protection left out", lambda r: r["codec"]["protection"].pop("MC7_Motion"), "codec.protection.MC7_Motion",
     "signals.inputs.speed_rpm reads MC7_Motion, and it has neither the CAN matrix's MC7_Motion_Counter"),
    ("protection of a missing frame", lambda r: r["codec"]["protection"].__setitem__("MC7_Motoin", "none"),
     "codec.protection.MC7_Motoin", "no frame 'MC7_Motoin' to protect (did you mean 'MC7_Motion'?)"),
    ("counter that is no signal", lambda r: r["codec"]["protection"].__setitem__("MC7_Motion", {"counter": "MC7_Alive"}),
     "codec.protection.MC7_Motion", "no signal 'MC7_Alive' in the frame"),
    ("CRC that spans two bytes", lambda r: r["codec"]["protection"].__setitem__(
        "MC7_Motion", {"crc": "MC7_OperatingState", "crc_algorithm": "crc8_autosar"}),
     "codec.protection.MC7_Motion", "must be an unsigned 8-bit signal filling one payload byte"),
    ("CRC without its algorithm", lambda r: r["codec"]["protection"].__setitem__("MC7_Motion", {"crc": "X"}),
     "codec.protection.MC7_Motion.crc_algorithm", "required with crc: one of crc8_sae_j1850"),
    ("unknown CRC algorithm", lambda r: r["codec"]["protection"].__setitem__(
        "MC7_Motion", {"crc": "X", "crc_algorithm": "crc16"}), "codec.protection.MC7_Motion.crc_algorithm", "must be one of"),
    ("data ID beyond 16 bits", lambda r: r["codec"]["protection"].__setitem__(
        "MC7_Motion", {"crc": "X", "crc_algorithm": "crc8_autosar", "data_id": 0x12345}),
     "codec.protection.MC7_Motion.data_id", "16-bit integer"),
    ("data ID without CRC", lambda r: r["codec"]["protection"].__setitem__("MC7_Motion", {"data_id": 5}),
     "codec.protection.MC7_Motion.data_id", "needs crc:"),
    ("misspelt protection key", lambda r: r["codec"]["protection"].__setitem__("MC7_Motion", {"countr": "X"}),
     "codec.protection.MC7_Motion.countr", "unknown key (did you mean 'counter'?)"),
    ("empty protection", lambda r: r["codec"]["protection"].__setitem__("MC7_Motion", {}),
     "codec.protection.MC7_Motion", "or none for a frame without protection"),
    ("the service's own frame", lambda r: r["codec"]["protection"].__setitem__("TE_Limits", "none"),
     "codec.protection.TE_Limits", "the service's own frame: it keeps the CAN matrix's protection"),
    ("unknown d/q convention", lambda r: r["signals"]["inputs"]["i_rms"].__setitem__("dq", "peak"),
     "signals.inputs.i_rms.dq", "must be one of amplitude_invariant, power_invariant, rms_scaled"),
    ("d/q convention on a mean", lambda r: r["signals"]["inputs"]["speed_rpm"].__setitem__("dq", "power_invariant"),
     "signals.inputs.speed_rpm.dq", "only with reduce: dq_rms"),
    ("a 29-bit frame mapped", lambda r: r["signals"]["sensors"]["housing"].update(frame="MC7_Diagnostics",
                                                                                  signal="MC7_FaultCode"),
     "signals.sensors.housing.frame", "cannot be read: it has a 29-bit identifier"),
]


@pytest.mark.parametrize("case, edit, key, words", FOREIGN_BROKEN, ids=[c[0] for c in FOREIGN_BROKEN])
def test_a_foreign_matrix_config_that_does_not_fit_exits_2_naming_the_key(tmp_path, case, edit, key, words):
    raw = example()
    raw["state"]["dir"] = str(tmp_path / "state")
    edit(raw)
    proc = _run(write_yaml(tmp_path / "broken.yaml", raw), "--check")
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith(f"thermal-edge run: error: broken.yaml: {key}: "), lines[0]
    assert words in lines[0], lines[0]


def test_the_example_declares_what_the_shipped_file_leaves_to_defaults(tmp_path):
    cfg = config_from_mapping(example(), tmp_path / "edge.yaml")
    assert cfg.inputs["i_rms"].dq == "power_invariant" and load_config(EDGE_YAML).inputs["i_rms"].dq == "amplitude_invariant"
    assert set(cfg.codec.protection) == {"MC7_Currents", "MC7_Motion", "MC7_StatorTemps", "MC7_Environment"}
    assert all(p.none for p in cfg.codec.protection.values())
    raw = example()
    raw["codec"]["protection"]["MC7_Motion"] = {"counter": "MC7_OperatingState"}  # 4 bits: a counter it could be
    codec = config_from_mapping(raw, tmp_path / "edge.yaml").codec.frame_codec()
    assert codec.protection("MC7_Motion").counter == "MC7_OperatingState"
    assert "MC7_OperatingState" not in codec.signal_names("MC7_Motion")


def test_a_safe_torque_the_safe_current_cannot_carry_is_refused_against_the_model(tmp_path):
    """The torque limit is never above kt x the current limit: a safe torque above kt x
    safe_current_a would never be sent, so the check refuses it, naming both."""
    raw = shipped()
    raw["derating"]["safe_torque_nm"] = 150  # kt 5.6 Nm/A x 10 A = 56 Nm
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", raw))
    with pytest.raises(ConfigError) as err:
        cfg.check_model(load_service_model(cfg))
    assert str(err.value).startswith("edge.yaml: derating.safe_torque_nm: must not exceed kt x safe_current_a "
                                     "(5.6 Nm/A x 10 A = 56 Nm), got 150"), str(err.value)
    raw["derating"]["safe_torque_nm"] = 30  # below: kept, and used
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", raw))
    cfg.check_model(load_service_model(cfg))


def test_plausible_readings_must_reach_every_limit(tmp_path):
    """A reading on its way to a limit's max must not be taken for a sensor fault."""
    raw = shipped()
    raw["signals"]["valid_range_c"] = [-40, 100]  # the hot spot's max is 155 degC
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", raw))
    with pytest.raises(ConfigError) as err:
        cfg.check_model(load_service_model(cfg))
    assert str(err.value) == ("edge.yaml: signals.valid_range_c: the plausible readings (-40 to 100 degC) must reach "
                              "every limit's max_c: hot_spot has 155")
