"""Fault cases on the persistence and configuration side: SIGKILL at random moments (also during
saves) and SIGTERM with learned parameters, corrupt or foreign state files, broken configurations,
and an accelerated soak with adaptation while bad frames arrive."""
from __future__ import annotations

import contextlib
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import yaml

from thermal_edge.process_signals import EXIT_STATE_NOT_SAVED, IGNORED_SIGNALS

from .. import ROOT
from . import wire
from .harness import (
    HOT_SPOT_BAND,
    START_TIMEOUT_S,
    Bed,
    Case,
    Check,
    Inverter,
    Monitor,
    Service,
    common_checks,
    edge_config,
    env,
    free_port,
    gaps,
    metric,
    service_config_path,
    thermal_edge_cmd,
    unique_group,
    unit_memory_max_bytes,
)

STATE = "state.json"
HOT_FUTURE = "hot_state_saved_in_the_future"
LEARNED_SCALE = 1.2  # learned parameters: the nominal value moved by this factor (inside the bounds)


def _model_parameters() -> dict[str, dict[str, Any]]:
    """The adaptable parameters of the service's model file with their value and bounds."""
    raw = yaml.safe_load(service_config_path("machines", "pm10kw.yaml").read_text())
    return {k: v for k, v in raw["parameters"].items() if isinstance(v, dict) and v.get("adaptable")}


def learned_parameters() -> dict[str, float]:
    """Three adapted parameters as the service would persist them: moved off nominal, in bounds."""
    p = _model_parameters()
    return {k: min(float(p[k]["max"]), float(p[k]["value"]) * LEARNED_SCALE) for k in ("k_a_ew", "c_p_ew", "k_r_ew")}


#: the learned parameter whose model value the ``learned_from_another_model_value`` state says was another
OUTDATED = "k_a_ew"


def _nominal_moved(name: str) -> dict[str, float]:
    """The model values saved with :func:`learned_parameters`, ``name``'s not the model file's (half of it)."""
    p = _model_parameters()
    return {k: float(p[k]["value"]) * (0.5 if k == name else 1.0) for k in learned_parameters()}


def parameter_metrics(m: dict[str, float]) -> dict[str, float]:
    """``thermal_edge_parameter_value`` by parameter name."""
    out = {}
    for k, v in m.items():
        if k.startswith("thermal_edge_parameter_value{"):
            out[k.split('parameter="')[1].split('"')[0]] = v
    return out


def params_lost(expected: dict[str, float], got: dict[str, float], rel: float = 1e-9) -> int:
    """Parameters of ``expected`` missing from ``got`` or different (relative ``rel``)."""
    return sum(1 for k, v in expected.items() if k not in got or not math.isclose(got[k], v, rel_tol=rel, abs_tol=1e-12))


def _bed(svc: Service, mon: Monitor, group: str, port: int, workdir: Path) -> Bed:
    """A service and its monitor as the common checks take them."""
    return Bed(workdir, group, port, svc, mon, None)


class Rig:
    """One group/port with the monitor and the inverter; services started on it one after another."""

    def __init__(self, name: str) -> None:
        self.workdir = Path(tempfile.mkdtemp(prefix=f"te-faults-{name}-"))
        self.group, self.port = unique_group(), free_port()
        self.monitor = Monitor(self.group, self.port, self.workdir)
        self.inverter = Inverter(self.group, self.port).start()
        self.n = 0

    def config(self, state_dir: Path, **sections: Any) -> dict[str, Any]:
        return edge_config(state_dir, self.group, self.port, **sections)

    def start(self, raw: dict[str, Any], timeout: float = START_TIMEOUT_S) -> tuple[Service, float | None]:
        """A service started on this rig and the time from spawn to its first TE_Limits (s; None
        if none within ``timeout``)."""
        self.n += 1
        svc = Service(raw, self.workdir, f"svc{self.n}")
        svc.start()
        first = self.monitor.first_after(svc.started, timeout)
        svc.wait_metrics(3)
        return svc, None if first is None else first - svc.started

    def close(self) -> None:
        self.inverter.close()
        self.monitor.close()
        shutil.rmtree(self.workdir, ignore_errors=True)


@contextlib.contextmanager
def rig(name: str) -> Iterator[Rig]:
    r = Rig(name)
    try:
        yield r
    finally:
        r.close()


def _seed(r: Rig, state_dir: Path) -> tuple[dict[str, Any], float]:
    """A state file written by the service itself (thermal state included), then given learned
    parameters; and the CPU time a clean start used until its first TE_Limits (s)."""
    svc, first = r.start(r.config(state_dir))
    time.sleep(3.0)
    svc.stop()
    cpu = svc.cpu_at(svc.started + first) if first is not None else math.nan
    st = json.loads((state_dir / STATE).read_text())
    st["parameters"] = {**st.get("parameters", {}), **learned_parameters()}
    st["param_version"] = int(st.get("param_version", 0)) + 1
    (state_dir / STATE).write_text(json.dumps(st))
    if first is None:
        raise RuntimeError(f"the service sent no TE_Limits within {START_TIMEOUT_S:g} s of a clean start:\n"
                           + svc.log_text()[-2000:])
    return st, cpu


def _state_check(state_dir: Path, learned: dict[str, float]) -> tuple[int, str]:
    """Items of the persisted state lost: the learned parameters, and the thermal state."""
    try:
        st = json.loads((state_dir / STATE).read_text())
    except (OSError, ValueError) as exc:
        return len(learned) + 1, f"state.json unreadable ({type(exc).__name__})"
    lost = params_lost(learned, {k: float(v) for k, v in st.get("parameters", {}).items()})
    lost += 0 if st.get("T") else 1
    return lost, ""


# ----------------------------------------------------------------------------------------------
def crash_safety(full: bool) -> Iterator[Case]:
    """SIGKILL at random moments (saves every 0.2 s, so many kills fall into one) and SIGTERM; after
    each the state file must hold the learned parameters and the thermal state, and the next start
    must load it (nothing moved aside)."""
    kills = 200 if full else 10
    terms = 20 if full else 3
    rng = random.Random(14)
    with rig("crash") as r:
        sd = r.workdir / "state"
        _seed(r, sd)
        learned = learned_parameters()
        raw = r.config(sd, state={"save_interval_s": 0.2})
        lost = 0
        during_save = 0
        starts: list[float] = []
        c = Check()
        notes: list[str] = []
        for k in range(kills):
            svc, first = r.start(raw)
            if first is None:
                c.add(1, f"kill {k}: no TE_Limits within {START_TIMEOUT_S:g} s of the start")
            else:
                starts.append(first)
            if k == 0 or k == kills - 1:  # the loaded parameters as the service reports them
                lost += params_lost(learned, parameter_metrics(svc.metrics()), rel=1e-6)
            if k % 2:  # at a random moment
                time.sleep(rng.uniform(0.0, 1.5))
            else:  # the moment a save's temporary file appears (polled every ~0.2 ms)
                deadline = time.monotonic() + 3.0
                while time.monotonic() < deadline and not any(".tmp" in p.name for p in sd.iterdir()):
                    time.sleep(0.0002)
            t_kill = time.time()
            svc.kill(signal.SIGKILL)
            assert svc.proc is not None
            svc.proc.wait()
            if first is not None:  # TE_Limits while this run lived
                g = gaps(r.monitor.read(), svc.started + first, t_kill)
                c.add(len(g), f"kill {k}: TE_Limits gap(s) of {', '.join(f'{x * 1e3:.0f}' for x in g)} ms while up")
            during_save += any(p.name.startswith(STATE + ".tmp") or p.name.endswith(".tmp") for p in sd.iterdir())
            n, why = _state_check(sd, learned)
            lost += n
            if why:
                notes.append(why)
            c.add(svc.tracebacks(), f"kill {k}: traceback")
        aside = len(list(sd.glob(STATE + ".corrupt-*")))
        lost += aside
        did = (f"{kills} SIGKILLs, {during_save} left a temp file (killed in a save); {aside} state files moved aside; "
               f"start to first TE_Limits {min(starts, default=math.nan):.1f}-{max(starts, default=math.nan):.1f} s "
               + (f"; {notes[0]}" if notes else ""))
        yield Case.of("sigkill_random_moments", "crash safety", kills, did, c, lost)
        # SIGTERM: exit 0 and a saved state with everything learned
        c = Check()
        lost = 0
        codes = []
        for _ in range(terms):
            svc, first = r.start(raw)
            time.sleep(rng.uniform(0.5, 2.0))
            before = (sd / STATE).stat().st_mtime_ns
            code = svc.stop()
            codes.append(code)
            c.add(int(code != 0), f"SIGTERM exit {code}")
            c.add(svc.tracebacks(), "traceback")
            n, _ = _state_check(sd, learned)
            lost += n + int((sd / STATE).stat().st_mtime_ns == before)
        yield Case.of("sigterm_saves", "crash safety", terms, f"exit codes {sorted(set(codes), key=str)}; state saved each time",
                      c, lost)
        yield _second_service_on_one_state_dir(r, raw, learned)


def _second_service_on_one_state_dir(r: Rig, raw: dict[str, Any], learned: dict[str, float]) -> Case:
    """A second service started on the state directory of a running one (by hand beside the unit):
    it must stop at start with one line naming the directory, before it touches the state, while
    the first one's TE_Limits go on; the first one's learned state survives."""
    c = Check()
    first, t_first = r.start(raw)
    second = Service(raw, r.workdir, f"svc{r.n + 1}-second")
    second.start()
    assert second.proc is not None
    try:
        code = second.proc.wait(timeout=START_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        second.kill(signal.SIGKILL)
        code = None
    line = next((ln for ln in second.log_text().splitlines() if "in use by another thermal-edge" in ln), "")
    c.add(int(code != 2), f"the second service exited {code}, not 2")
    c.add(int(not line), "no line naming the state directory in use")
    time.sleep(1.0)
    if t_first is not None:
        g = gaps(r.monitor.read(), first.started + t_first, time.time())
        c.add(len(g), f"the first service's TE_Limits gap(s) of {', '.join(f'{x * 1e3:.0f}' for x in g)} ms")
    c.add(int(not first.alive()), "the first service died")
    code_first = first.stop()
    c.add(int(code_first != 0), f"the first service's SIGTERM exit {code_first}")
    c.add(first.tracebacks() + second.tracebacks(), "traceback")
    lost, _ = _state_check(r.workdir / "state", learned)
    return Case.of("second_service_same_state_dir", "crash safety", 1,
                   f"second service exit {code}: {line.split('error: ', 1)[-1].strip()[:100] or 'no message'}", c, lost)


# ----------------------------------------------------------------------------------------------
def _valid_state(seed: dict[str, Any]) -> bytes:
    return json.dumps(seed).encode()


def _state_variants(seed: dict[str, Any], full: bool) -> dict[str, tuple[Callable[[Path], None], bool]]:
    """Corrupt or foreign state files: name -> (write it into a state dir, whether it is usable and
    must be kept with its parameters)."""

    def write(data: bytes) -> Callable[[Path], None]:
        def prepare(d: Path) -> None:
            d.mkdir(parents=True, exist_ok=True)
            (d / STATE).write_bytes(data)
        return prepare

    def with_(**kw: Any) -> Callable[[Path], None]:
        return write(json.dumps({**seed, **kw}).encode())

    def big(d: Path) -> None:  # 256 MiB of valid JSON numbers
        d.mkdir(parents=True, exist_ok=True)
        head = json.dumps({**seed, "T": []})[:-1].replace('"T": []', '"T": [')
        with open(d / STATE, "wb") as fh:
            fh.write(head.encode())
            chunk = b"25.0," * (1 << 20)
            fh.writelines(chunk for _ in range(256 // 5 + 1))
            fh.write(b"25.0]}")

    def temp_left(d: Path) -> None:
        write(_valid_state(seed))(d)
        (d / f"{STATE}.tmp-99999").write_bytes(_valid_state(seed)[:100])

    def directory(d: Path) -> None:
        (d / STATE).mkdir(parents=True)

    def symlink(target: str) -> Callable[[Path], None]:
        def prepare(d: Path) -> None:
            d.mkdir(parents=True, exist_ok=True)
            os.symlink(target, d / STATE)
        return prepare

    def fifo(d: Path) -> None:
        d.mkdir(parents=True, exist_ok=True)
        os.mkfifo(d / STATE)

    valid = _valid_state(seed)
    digits = (b'{"format": "thermal_edge.state", "version": 1, "model": "pm10kw", "saved_at": 1' + b"0" * 5000
              + b', "parameters": {}}')
    roundoff = dict(seed["parameters"], c_p_ew=299.99999999999994)
    cold_magnet = [-99.0 if "magnet" in n else x for n, x in zip(seed["nodes"], seed["T"])]
    return {
        "nested_brackets_100k": (write(b"[" * 100_000), False),
        "nested_objects_100k": (write(b'{"a":' * 100_000), False),
        "number_5000_digits": (write(digits), False),
        "file_256mib": (big, False),
        "decisions_abc": (with_(decisions="abc"), False),
        "truncated": (write(valid[: len(valid) // 2]), False),
        "binary_garbage": (write(random.Random(2).randbytes(4096)), False),
        "empty": (write(b""), False),
        "json_null": (write(b"null"), False),
        "foreign_format": (with_(format="something.else"), False),
        "other_model": (with_(model="pm99kw"), False),
        "version_99": (with_(version=99), False),
        "nan_in_T": (write(_valid_state(seed).replace(b'"T": [', b'"T": [NaN, ', 1)), False),
        "parameters_a_list": (with_(parameters=[1, 2]), False),
        "T_wrong_length": (with_(T=seed["T"][:5]), False),
        "parameter_out_of_bounds": (with_(parameters=dict(seed["parameters"], c_p_ew=5000.0)), False),
        "utf16_encoded": (write(json.dumps(seed).encode("utf-16")), False),
        "huge_model_name_50mb": (with_(model="x" * (50 << 20)), False),
        "state_is_a_directory": (directory, False),
        "symlink_to_dev_zero": (symlink("/dev/zero"), False),
        "fifo": (fifo, False),
        "temp_file_left_over": (temp_left, True),
        "parameter_at_bound_roundoff": (with_(parameters=roundoff), True),
        # well-formed but no machine's state (a doctored file: the magnet at -99 degC, every
        # variance zero); it must not be used and go onto the bus
        "magnet_at_minus_99c": (with_(T=cold_magnet, T_pred=cold_magnet), False),
        "zero_covariance": (with_(P=[[0.0] * len(seed["T"]) for _ in seed["T"]], sigma=[0.0] * len(seed["T"])), False),
        # a model update renamed or removed a parameter: the others are kept
        "unknown_parameter_name": (with_(parameters=dict(seed["parameters"], R_nosuch=1.0)), True),
        # saved a day "in the future" (the clock set back: an RTC reset) by a machine 60 K hotter than
        # the readings: its age is unknown, the temperatures start from the readings, the parameters kept
        # (used as it was, it made healthy PT100s "stuck" and a model fault of half an hour)
        HOT_FUTURE: (with_(saved_at=time.time() + 86400.0, T=[x + 60.0 for x in seed["T"]],
                           T_pred=[x + 60.0 for x in seed.get("T_pred") or seed["T"]]), True),
        # a new model file (or edge.yaml model.parameters) moved where k_a_ew starts: its learned value
        # belongs to the old start and is dropped, the others kept
        "learned_from_another_model_value": (with_(nominal=_nominal_moved(OUTDATED)), True),
    }


def corrupt_states(full: bool) -> Iterator[Case]:
    """Each corrupt or foreign state file: the service starts, sends TE_Limits after at most 1 s more
    CPU time than a clean start (CPU, not wall time: the shared machine's load varies), moves the
    file aside (or, if usable, keeps its parameters), stays below the unit's MemoryMax; and a usable
    file survives a SIGTERM and the next start. The 1 s of CPU is a margin for the moving aside and
    the log lines, not for the host's load (CPU time is not stretched by other processes)."""
    cap = unit_memory_max_bytes()
    with rig("states") as r:
        seed_dir = r.workdir / "seed"
        seed, clean_cpu = _seed(r, seed_dir)
        for name, (prepare, usable) in _state_variants(seed, full).items():
            sd = r.workdir / f"state-{name}"
            prepare(sd)
            svc, first = r.start(r.config(sd), timeout=20.0)
            t0 = time.time()
            time.sleep(1.5)
            m = svc.metrics()
            peak = svc.peak_rss
            c = common_checks(_bed(svc, r.monitor, r.group, r.port, r.workdir), t0, time.time())
            cpu = svc.cpu_at(svc.started + first) if first is not None else math.inf
            c.add(int(cpu > clean_cpu + 1.0), f"first TE_Limits after {cpu:.2f} s of CPU (a clean start: {clean_cpu:.2f} s)")
            c.add(int(peak > cap), f"peak RSS {peak / 2**20:.0f} MiB above MemoryMax {cap / 2**20:.0f} MiB")
            aside = list(sd.glob(STATE + ".corrupt-*"))
            temps = [p.name for p in sd.iterdir() if ".tmp" in p.name]
            lost = 0
            if usable:
                expected = dict(learned_parameters())
                if name == "parameter_at_bound_roundoff":
                    expected["c_p_ew"] = 300.0
                if name == "learned_from_another_model_value":  # dropped: the model file's value
                    expected[OUTDATED] = float(_model_parameters()[OUTDATED]["value"])
                lost = params_lost(expected, parameter_metrics(m), rel=1e-6) + len(aside)
                c.add(len(temps), f"temp file(s) left: {temps}")
                if name == HOT_FUTURE:  # a model fault needs its ticks: 5 of innovation above 15 K
                    time.sleep(8.0)
                    faults = metric(svc.metrics(), "thermal_edge_model_faults_total")
                    stuck = _log_names(svc, "stuck")
                    c.add(int(faults > 0 or stuck), f"{faults:.0f} model fault(s){', sensors judged stuck' if stuck else ''}"
                                                    " against a state of unknown age")
            else:
                c.add(int(not aside), "the file was not moved aside (the next start meets it again)")
            code = svc.stop()
            if usable:  # the state it saves on SIGTERM loads again with the same parameters
                svc2, _ = r.start(r.config(sd))
                time.sleep(1.0)
                lost += params_lost(expected, parameter_metrics(svc2.metrics()), rel=1e-6)
                lost += len(list(sd.glob(STATE + ".corrupt-*"))) - len(aside)
                c.add(svc2.tracebacks(), "traceback on the restart")
                svc2.stop()
            did = (f"first TE_Limits {'none' if first is None else f'{first:.1f} s ({cpu:.1f} s CPU)'}; "
                   f"{'moved aside' if aside else 'kept'}; load errors {metric(m, 'thermal_edge_state_load_errors_total'):.0f}; "
                   + (f"parameters dropped {metric(m, 'thermal_edge_state_params_dropped_total'):.0f}; " if usable else "")
                   + f"peak RSS {peak / 2**20:.0f} MiB; exit {code}")
            yield Case.of(f"state_{name}", "corrupt state", 1, did, c, lost)
            shutil.rmtree(sd, ignore_errors=True)


# ----------------------------------------------------------------------------------------------
def _config_variants(base: dict[str, Any], workdir: Path) -> dict[str, Any]:
    """Broken configurations: name -> the YAML mapping, or raw bytes, or None (no file at all)."""
    from thermal_edge.lptn import Role, load_model

    current = load_model(base["model"]["path"]).input_name(Role.CURRENT)  # the input left unmapped

    def set_(path: str, value: Any) -> dict[str, Any]:
        raw = json.loads(json.dumps(base))
        *parents, key = path.split(".")
        node = raw
        for p in parents:
            node = node[p]
        if value is _DELETE:
            del node[key]
        else:
            node[key] = value
        return raw

    a_file = workdir / "a-file"
    a_file.write_text("not a directory\n")
    return {
        "limits_period_0.5s": set_("transmit.limits_period_s", 0.5),
        "bus_key_typo_chanel": set_("bus.chanel", "ff15::1"),
        "state_dir_is_a_file": set_("state.dir", str(a_file)),
        "state_dir_cannot_be_created": set_("state.dir", "/proc/te-faults/state"),
        "unknown_model_parameter": set_("model.parameters", {"R_bogus": 1.0}),
        "unknown_top_level_key": set_("bogus", 1),
        "negative_safe_current": set_("derating.safe_current_a", -3),
        "safe_current_above_max": set_("derating.safe_current_a", 50.0),
        "negative_timeout": set_("timeouts.INV_Currents", -1.0),
        "unknown_frame_in_timeouts": set_("timeouts.INV_Bogus", 1.0),
        "clock_mode_sundial": set_("clock.mode", "sundial"),
        "tick_zero": set_("clock.tick_s", 0),
        "model_file_missing": set_("model.path", "/nonexistent/pm10kw.yaml"),
        "dbc_file_missing": set_("codec.dbc", "/nonexistent/thermal_edge.dbc"),
        "input_not_mapped": set_("signals.inputs", {k: v for k, v in base["signals"]["inputs"].items() if k != current}),
        "sensor_signal_unknown": set_("signals.sensors", {**base["signals"]["sensors"],
                                                          "housing": {"frame": "INV_StatorTemps", "signal": "INV_T_Bogus"}}),
        "valid_range_reversed": set_("signals.valid_range_c", [250, -40]),
        "band_warn_above_max": set_("derating.limits", {**base["derating"]["limits"],
                                                        "hot_spot": {"warn_c": 160, "max_c": 155, "reason": "winding"}}),
        # the machine's insulation limit is its model file's: a configuration may lower it only
        "limit_above_the_machines": set_("derating.limits", {**base["derating"]["limits"],
                                                             "hot_spot": {"warn_c": 230, "max_c": 250, "reason": "winding"}}),
        "max_current_a_string": set_("derating.max_current_a", "forty"),
        "max_current_a_nan": set_("derating.max_current_a", float("nan")),
        "metrics_port_70000": set_("metrics.port", 70000),
        "metrics_address_not_an_address": set_("metrics.address", "not an address"),
        "bus_interface_unknown": set_("bus.interface", "nonexistent_interface"),
        "udp_channel_unicast_address": set_("bus.channel", "192.0.2.1"),
        "adaptation_method_unknown": set_("adaptation.method", "guessing"),
        # what PyYAML alone misreads or crashes on, and limits TE_Limits cannot carry
        "max_current_a_above_the_dbc": set_("derating.max_current_a", 5000.0),
        "model_fault_hold_zero": set_("derating.faults.hold_s", 0),
        "tick_a_day": set_("clock.tick_s", 86400),
        # valid-looking timings that must be refused: every input falsely stale / the bus flooded
        "tick_a_millisecond": set_("clock.tick_s", 0.001),
        "limits_every_microsecond": set_("transmit.limits_period_s", 1e-6),
        "status_every_microsecond": set_("transmit.status_period_s", 1e-6),
        # each must be refused by --check: accepted, a fault would never reach the bus, or stale
        # inputs would go unnoticed while the limit rose
        "hold_a_nanosecond": set_("derating.faults.hold_s", 1e-9),
        "stator_timeout_1e9_s": set_("timeouts.INV_StatorTemps", 1e9),
        "bus_silence_1e9_s": set_("transmit.bus_silence_s", 1e9),
        "no_timeouts": set_("timeouts", {}),
        "model_fault_threshold_1e9_k": set_("derating.faults.prediction_error_k", 1e9),
        "a_section_twice": (yaml.safe_dump(base, sort_keys=False) + "bus:\n  interface: virtual\n").encode(),
        "nested_5000_deep": b"bus: " + b"[" * 5000 + b"]" * 5000 + b"\n",
        "yaml_syntax_error": b"bus: [unclosed\n",
        "empty_file": b"",
        "yaml_a_list": b"- 1\n- 2\n",
        "binary_garbage": bytes(range(256)) * 4,
        "config_file_missing": None,
    }


_DELETE = object()


def broken_configs(full: bool) -> Iterator[Case]:
    """Each broken configuration through ``run --check`` (and, full, a real start too): exit 2, one
    line naming the file (the configuration, or the file it names that cannot be read), no traceback."""
    workdir = Path(tempfile.mkdtemp(prefix="te-faults-configs-"))
    try:
        base = edge_config(workdir / "state", unique_group(), free_port())
        for name, variant in _config_variants(base, workdir).items():
            path = workdir / f"edge-{name}.yaml"
            if isinstance(variant, dict):
                path.write_text(yaml.safe_dump(variant, sort_keys=False))
            elif isinstance(variant, bytes):
                path.write_bytes(variant)
            c = Check()
            seen = []
            msg = ""
            for how in (["--check"], []) if full else (["--check"],):
                code, err = _run_config(path, how)
                lines = [ln for ln in err.splitlines() if ln.strip()]
                what = "check" if how else "start"
                c.add(int(code != 2), f"{what}: exit {code}")
                c.add(int("Traceback" in err), f"{what}: traceback")
                c.add(int(code == 2 and len(lines) != 1), f"{what}: {len(lines)} lines on stderr")
                seen.append(f"{what} exit {code}")
                msg = lines[-1] if code == 2 and lines else msg
            if msg and name != "config_file_missing":
                c.add(int(path.name not in msg and "/nonexistent/" not in msg), "the line does not name the file")
            did = ", ".join(seen) + (f": {msg[:110]}" if msg else "")
            yield Case.of(f"config_{name}", "broken configs", len(seen), did, c)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def _run_config(path: Path, extra: list[str], start_timeout: float = 10.0) -> tuple[int | None, str]:
    """Exit code and stderr of ``thermal-edge run --config path`` (+ ``extra``); a service still
    running after ``start_timeout`` s accepted the configuration: it is stopped, exit code None."""
    proc = subprocess.Popen(thermal_edge_cmd() + ["run", "--config", str(path)] + extra, cwd=str(path.parent),
                            env=env(service=True), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _, err = proc.communicate(timeout=start_timeout)
        return proc.returncode, err.decode(errors="replace")
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGTERM)
        try:
            _, err = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
        return None, err.decode(errors="replace")


# ----------------------------------------------------------------------------------------------
def soak(full: bool) -> Iterator[Case]:
    """An accelerated closed-loop run (frame clock, the project's inverter emulator as the normal
    traffic, the model off by the paper's Table 4, adaptation on with a short period) while bad
    frames arrive all along: 7 days full, 2 h short. TE_Limits, the true hot spot (a failure to
    derate), frames lost, RSS, and the adapted state loadable at the end."""
    hours = 168.0 if full else 2.0
    workdir = Path(tempfile.mkdtemp(prefix="te-faults-soak-"))
    group, port = unique_group(), free_port()
    mon = Monitor(group, port, workdir)
    try:
        from thermal_edge.lptn import load_model
        from thermal_edge.sim.inverter import table4_parameters

        model = load_model(service_config_path("machines", "pm10kw.yaml"))
        raw = edge_config(workdir / "state", group, port, clock="frame", adapt=True,
                          model={"parameters": table4_parameters(model)},
                          timeouts={"INV_Currents": 2.0, "INV_Mechanics": 2.0, "INV_StatorTemps": 3.0, "INV_AmbientTemps": 3.0},
                          transmit={"bus_silence_s": 5.0},
                          adaptation={"period_s": 60, "min_window_s": 600},
                          codec={"resync_after_cycles": 1000})
        svc = Service(raw, workdir)
        svc.start()
        first = mon.first_after(svc.started, START_TIMEOUT_S)
        svc.wait_metrics(5)
        rss0 = svc.rss()
        summary = workdir / "summary.json"
        cmd = [sys.executable, "-m", "thermal_edge.sim.inverter", "--interface", "udp_multicast", "--channel", group,
               "--port", str(port), "--model", str(service_config_path("machines", "pm10kw.yaml")),
               "--cycle", str(service_config_path("cycles", "varied_drive.yaml")), "--duration", str(hours * 3600),
               "--speed", "0", "--t0", "1700000000", "--current-period", "0.1", "--temperature-period", "1.0",
               "--plant-dt", "0.5", "--summary", str(summary), "--flow-timeout", "2.0"]
        t0 = time.time()
        emu = subprocess.Popen(cmd, env=env(), cwd=str(ROOT), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        sock = wire.sender_socket(group)
        bad = 0
        # decodable bad frames only: the emulator (the normal traffic here) stops at an undecodable
        # datagram; those are the bad_frames and floods groups' subject
        kinds = ("bad_crc", "unknown_id", "short_dlc", "garbage_known_id")
        while emu.poll() is None:  # bad frames all along, 20 a second
            sock.sendto(wire.bad_frame(kinds[bad % len(kinds)], bad), (group, port))
            bad += 1
            time.sleep(0.05)
            t1 = time.time()
        sock.close()
        err = emu.stderr.read().decode(errors="replace") if emu.stderr else ""
        time.sleep(1.0)
        m = svc.metrics()
        rss1 = svc.rss()
        c = common_checks(_bed(svc, mon, group, port, workdir), t0, t1)
        s = json.loads(summary.read_text()) if summary.exists() else {}
        sent = sum(s.get("frames_sent", {}).values())
        got = int(sum(m.get(f'thermal_edge_frames_received_total{{frame="{n}"}}', 0.0) for n in wire.INPUT_FRAMES))
        hot = s.get("true_max_c", {}).get("hot_spot", math.nan)
        c.add(int(not hot < HOT_SPOT_BAND[1]), f"true hot spot {hot:.1f} degC reached the maximum {HOT_SPOT_BAND[1]:g}")
        c.add(int(emu.returncode != 0), f"emulator exit {emu.returncode}: {err[-200:]}")
        did = (f"{s.get('sim_seconds', 0) / 3600:.1f} h simulated in {t1 - t0:.0f} s; true hot spot max {hot:.1f} degC; "
               f"{bad} bad frames; RSS {rss0 / 2**20:.0f} -> {rss1 / 2**20:.0f} MiB; first TE_Limits "
               f"{'none' if first is None else f'{first - svc.started:.1f} s'}")
        yield Case.of(f"soak_{hours:g}h_accelerated", "soak", int(s.get("sim_seconds", 0)), did, c, max(0, sent - got))
        # adaptation under bad frames: accepted sets, parameters in bounds, the state loads again
        accepted = int(metric(m, "thermal_edge_adaptation_accepted_total"))
        runs = {k: int(metric(m, f"thermal_edge_adaptation_{k}_total")) for k in ("runs", "rejected", "failures", "skipped")}
        c_fail = runs["failures"]
        svc.stop()
        c = Check()
        c.add(svc.tracebacks(), "traceback")
        c.add(c_fail, f"{c_fail} adaptation(s) failed with an error")
        bounds = _model_parameters()
        params = parameter_metrics(m)
        out = sum(1 for k, v in params.items() if k in bounds and not float(bounds[k]["min"]) <= v <= float(bounds[k]["max"]))
        c.add(out, f"{out} parameter(s) outside their bounds")
        svc2 = Service(raw, workdir, "svc-restart")
        svc2.start()
        svc2.wait_metrics(START_TIMEOUT_S)
        time.sleep(1.0)
        after = parameter_metrics(svc2.metrics())
        lost = params_lost(params, after, rel=1e-6) + len(list((workdir / "state").glob(STATE + ".corrupt-*")))
        svc2.stop()
        yield Case.of("adaptation_under_bad_frames", "adaptation", runs["runs"] + runs["skipped"],
                      f"{runs['runs']} adaptations run ({accepted} accepted, {runs['rejected']} rolled back, "
                      f"{runs['skipped']} skipped), {len(params)} parameters reported, all reloaded after restart: "
                      f"{'yes' if not lost else 'no'}", c, lost)
    finally:
        mon.close()
        shutil.rmtree(workdir, ignore_errors=True)


# ----------------------------------------------------------------------------------------------


def _log_names(svc: Service, *words: str) -> bool:
    return any(all(w in line for w in words) for line in svc.log_text().splitlines())


def _block_saves(sd: Path, pid: int) -> Path:
    """Make every save of the service ``pid`` fail for real: its temporary file's name taken by a directory."""
    blocker = sd / f"{STATE}.tmp-{pid}"
    blocker.mkdir(parents=True, exist_ok=True)
    return blocker


@contextlib.contextmanager
def _small_fs(path: Path) -> Iterator[bool]:
    """A 1 MiB tmpfs at ``path`` (True), or False where this user cannot mount (not root)."""
    path.mkdir(parents=True, exist_ok=True)
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(path)], capture_output=True).returncode == 0
    try:
        yield ok
    finally:
        if ok:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)


def _remount(path: Path, mode: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{mode}", str(path)], check=True, capture_output=True)


def persist(full: bool) -> Iterator[Case]:
    """Signals and unwritable state: each of SIGHUP, SIGUSR1, SIGUSR2, SIGALRM
    is logged by name and ignored while TE_Limits flows on; SIGQUIT stops cleanly with the state saved;
    saves that fail while running are logged again (not only the first) and a failed final save is
    reported as such with exit 3; a read-only state directory at start does not stop the protection,
    nor a full one at the first start (no lock file yet), nor a lock path taken by a directory or a
    FIFO (named in the log); a configuration refused at start leaves the state file where it was."""
    rounds = 5 if full else 1
    with rig("persist") as r:
        sd = r.workdir / "state"
        _seed(r, sd)
        learned = learned_parameters()
        raw = r.config(sd, state={"save_interval_s": 0.2})
        # ignored signals: each in turn to a running service (a fresh one if the last signal killed it),
        # TE_Limits watched for 2 s after each
        svc, first = r.start(raw)
        for name in (sig.name for sig in IGNORED_SIGNALS):
            if not svc.alive():
                svc, first = r.start(raw)
            t0 = time.time()
            for _ in range(rounds):
                svc.kill(getattr(signal, name))
                time.sleep(2.0)
            c = common_checks(_bed(svc, r.monitor, r.group, r.port, r.workdir), t0, time.time())
            c.add(int(not _log_names(svc, name, "ignored")), f"no log line names {name}")
            n = sum(1 for t in r.monitor.read().t if t >= t0)
            yield Case.of(f"signal_{name}", "signals", rounds,
                          f"{'alive' if svc.alive() else f'dead (exit {svc.proc.returncode if svc.proc else None})'}; "
                          f"{n} TE_Limits in the {time.time() - t0:.0f} s after it", c)
        svc.stop()
        # SIGHUP while the service starts: at its first log line (loading the state), before the running
        # service's handlers exist
        c = Check()
        up = 0
        for k in range(rounds):
            svc = Service(raw, r.workdir, f"early{k}")
            svc.start()
            deadline = time.monotonic() + START_TIMEOUT_S
            while not svc.log_text().strip() and time.monotonic() < deadline and svc.alive():
                time.sleep(0.01)
            svc.kill(signal.SIGHUP)
            first = r.monitor.first_after(time.time(), START_TIMEOUT_S)
            up += first is not None
            c.add(int(first is None), f"start {k}: no TE_Limits after the SIGHUP (exit "
                                      f"{svc.proc.returncode if svc.proc else None})")
            code = svc.stop()
            c.add(int(code != 0), f"start {k}: exit {code}")
        yield Case.of("signal_SIGHUP_while_starting", "signals", rounds, f"{up} of {rounds} start(s) sent TE_Limits "
                      "after the SIGHUP", c)
        # SIGTERM while the service starts: a clean stop, said in the log (not the signal's default
        # action: exit -15, no line). Sent the moment the process catches SIGTERM, before it runs
        # (once running, the line says "received SIGTERM: stopping", not "while starting")
        c = Check()
        codes = []
        for k in range(rounds):
            svc = Service(raw, r.workdir, f"early-term{k}")
            svc.start()
            svc.catches(signal.SIGTERM)
            code = svc.stop(30)
            codes.append(code)
            c.add(int(code != 0), f"start {k}: exit {code}")
            c.add(int("received SIGTERM while starting: stopping" not in svc.log_text()),
                  f"start {k}: no line 'received SIGTERM while starting'")
        yield Case.of("signal_SIGTERM_while_starting", "signals", rounds, f"exit {codes}", c)
        # SIGQUIT: a clean stop with the state saved
        c = Check()
        lost = 0
        codes = []
        for _ in range(rounds):
            svc, first = r.start(raw)
            time.sleep(1.0)
            before = (sd / STATE).stat().st_mtime_ns
            code = svc.stop(20, signal.SIGQUIT)
            codes.append(code)
            c.add(int(code != 0), f"SIGQUIT exit {code}")
            c.add(svc.tracebacks(), "traceback")
            c.add(int(not _log_names(svc, "SIGQUIT")), "no log line names SIGQUIT")
            n, _ = _state_check(sd, learned)
            lost += n + int((sd / STATE).stat().st_mtime_ns == before)
        yield Case.of("signal_SIGQUIT", "signals", rounds, f"exit codes {sorted(set(codes), key=str)}; state saved "
                      f"{'each time' if not lost else 'NOT each time'}", c, lost)
        # saves failing while running: reported more than once, then back; a failed final save is not "saved"
        svc, first = r.start(raw)
        blocker = _block_saves(sd, svc.pid)
        t0 = time.monotonic()
        errors = 0.0
        while errors < 9 and time.monotonic() - t0 < 30 and svc.alive():  # saves run with the 1 Hz tick
            time.sleep(0.5)
            errors = metric(svc.metrics(), "thermal_edge_state_save_errors_total")
        took = time.monotonic() - t0
        c = Check()
        lines = [ln for ln in svc.log_text().splitlines() if "cannot save state" in ln]
        c.add(int(errors >= 4 and len(lines) < 3), f"{errors:.0f} failed saves but {len(lines)} log line(s)")
        c.add(int(len(lines) > max(3, errors / 2)), f"{len(lines)} log lines for {errors:.0f} failed saves (a flood)")
        blocker.rmdir()
        time.sleep(1.0)
        c.add(int(not _log_names(svc, "saved again")), "no log line says the saves work again")
        _block_saves(sd, svc.pid)
        time.sleep(0.5)
        code = svc.stop()
        claims = _log_names(svc, "stopped, state saved")
        c.add(int(claims), "the stop line says 'state saved' after a failed final save")
        c.add(int(not _log_names(svc, "WITHOUT saving")), "no log line says the final save failed")
        c.add(int(code != EXIT_STATE_NOT_SAVED), f"exit {code} (expected {EXIT_STATE_NOT_SAVED})")
        c.add(svc.tracebacks(), "traceback")
        shutil.rmtree(blocker, ignore_errors=True)
        yield Case.of("save_fails_at_stop", "persistence", 1,
                      f"{errors:.0f} failed saves in {took:.0f} s, {len(lines)} ERROR line(s); exit {code}; stop line "
                      f"{'claims saved' if claims else 'says not saved'}", c)
        yield from _lock_not_a_file(r, sd, learned)
        yield _refused_config_keeps_the_state(r, sd)
        # a full state directory at the first start (no lock file yet: its pid cannot be written)
        fs = r.workdir / "full-state"
        with _small_fs(fs) as mounted:
            if mounted:
                shutil.copy(sd / STATE, fs / STATE)
                subprocess.run(["dd", "if=/dev/zero", f"of={fs / 'filler'}", "bs=64k"], capture_output=True)
                svc, first = r.start(r.config(fs, state={"save_interval_s": 0.5}), timeout=20.0)
                t0 = time.time()
                time.sleep(2.0)
                c = common_checks(_bed(svc, r.monitor, r.group, r.port, r.workdir), t0, time.time())
                c.add(int(first is None), f"no TE_Limits after the start (exit {svc.proc.returncode if svc.proc else None})")
                failing = metric(svc.metrics(), "thermal_edge_state_save_failing")
                c.add(int(not failing >= 1), f"state_save_failing {failing:g} while the directory is full")
                lost = params_lost(learned, parameter_metrics(svc.metrics()), rel=1e-6)
                code = svc.stop()
                c.add(svc.tracebacks(), "traceback")
                yield Case.of("state_dir_full_at_first_start", "persistence", 1,
                              f"first TE_Limits {'none' if first is None else f'{first:.1f} s'}; state_save_failing "
                              f"{failing:g}; exit {code}", c, lost)
            else:
                yield Case("state_dir_full_at_first_start", "persistence", 0, "not run: mounting a tmpfs needs root")
        # a read-only state directory at start (a filesystem remounted read-only after an I/O error)
        ro = r.workdir / "ro-state"
        with _small_fs(ro) as mounted:
            if not mounted:
                yield Case("state_dir_read_only_at_start", "persistence", 0, "not run: mounting a tmpfs needs root")
                return
            shutil.copy(sd / STATE, ro / STATE)
            _remount(ro, "ro")
            svc, first = r.start(r.config(ro, state={"save_interval_s": 0.5}), timeout=20.0)
            t0 = time.time()
            time.sleep(2.0)
            c = common_checks(_bed(svc, r.monitor, r.group, r.port, r.workdir), t0, time.time())
            c.add(int(first is None), "no TE_Limits after the start")
            failing = metric(svc.metrics(), "thermal_edge_state_save_failing")
            c.add(int(not failing >= 1), f"state_save_failing {failing:g} while the directory is read-only")
            c.add(int(not _log_names(svc, "ERROR", str(ro))), "no ERROR line names the state directory")
            lost = params_lost(learned, parameter_metrics(svc.metrics()), rel=1e-6)
            _remount(ro, "rw")
            time.sleep(1.5)
            c.add(int(not _log_names(svc, "saved again")), "the saves did not resume once the directory was writable")
            code = svc.stop()
            n, _ = _state_check(ro, learned)
            yield Case.of("state_dir_read_only_at_start", "persistence", 1,
                          f"first TE_Limits {'none' if first is None else f'{first:.1f} s'}; state_save_failing "
                          f"{failing:g}; exit {code}", c, lost + n)


def _lock_not_a_file(r: Rig, sd: Path, learned: dict[str, float]) -> Iterator[Case]:
    """The lock path taken by a directory or a FIFO: the service starts, protects and names it (it
    had run silently without its lock, or exited 2 "Invalid argument"); the state is kept."""
    for kind in ("directory", "fifo"):
        d = r.workdir / f"lock-{kind}"
        d.mkdir()
        shutil.copy(sd / STATE, d / STATE)
        if kind == "directory":
            (d / "lock").mkdir()
        else:
            os.mkfifo(d / "lock")
        svc, first = r.start(r.config(d))
        t0 = time.time()
        time.sleep(1.5)
        c = common_checks(_bed(svc, r.monitor, r.group, r.port, r.workdir), t0, time.time())
        c.add(int(first is None), f"no TE_Limits after the start (exit {svc.proc.returncode if svc.proc else None})")
        named = _log_names(svc, "cannot lock the state directory", str(d / "lock"))
        c.add(int(not named), "no line names the lock path")
        lost = params_lost(learned, parameter_metrics(svc.metrics()), rel=1e-6)
        code = svc.stop()
        c.add(int(code != 0), f"exit {code}")
        c.add(svc.tracebacks(), "traceback")
        n, _ = _state_check(d, learned)
        yield Case.of(f"lock_is_a_{kind}", "persistence", 1, f"first TE_Limits {'none' if first is None else f'{first:.1f} s'}"
                      f"; {'named' if named else 'not named'}; exit {code}", c, lost + n)


def _refused_config_keeps_the_state(r: Rig, sd: Path) -> Case:
    """edge.yaml pointed at another model by mistake: refused (exit 2), and the state file of the
    machine is where it was, byte for byte (it had been moved aside before the refusal)."""
    d = r.workdir / "refused-config"
    d.mkdir()
    shutil.copy(sd / STATE, d / STATE)
    before = (d / STATE).read_bytes()
    raw = r.config(d)
    raw["model"] = {**raw["model"], "path": str(ROOT / "tests" / "commands" / "models" / "two_node.yaml")}
    path = d.parent / "refused-config.yaml"
    path.write_text(yaml.safe_dump(raw))
    code, err = _run_config(path, [])
    c = Check()
    c.add(int(code != 2), f"exit {code}, not 2")
    kept = (d / STATE).exists() and (d / STATE).read_bytes() == before
    c.add(int(not kept), "the state file was moved or changed")
    aside = [p.name for p in d.iterdir() if p.name.startswith(STATE + ".corrupt")]
    return Case.of("config_refused_keeps_the_state", "persistence", 1,
                   f"exit {code}: {err.strip().splitlines()[-1][-90:] if err.strip() else 'no message'}; state "
                   f"{'kept' if kept else 'NOT kept'}{'; moved aside: ' + ', '.join(aside) if aside else ''}", c,
                   int(not kept))


GROUPS = {"crash": crash_safety, "states": corrupt_states, "configs": broken_configs, "soak": soak, "persist": persist}
