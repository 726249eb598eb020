"""Helpers of the service tests (a uniquely named module: importable from any test layout)."""
from __future__ import annotations

import asyncio
import contextlib
import copy
import json
import math
import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from own_ports import own_tcp_port, own_udp_port
from waiting import async_wait_until, wait_until  # noqa: F401 (the tests import them from here)

REPO = Path(__file__).resolve().parents[2]
EDGE_YAML = REPO / "config" / "edge.yaml"
MODEL = REPO / "config" / "machines" / "pm10kw.yaml"
CYCLES = REPO / "config" / "cycles"
DBC = REPO / "dbc" / "thermal_edge.dbc"
T0 = 1_700_000_000.0  # simulated epoch of the test runs

# the accelerated test scenario: frames coarser than the DBC's cycle (10x fewer), same physics
CURRENT_PERIOD_S = 0.1
TEMPERATURE_PERIOD_S = 1.0
PLANT_DT_S = 0.5
SPEED = 1000.0  # cap; flow control paces to the service


def env() -> dict[str, str]:
    e = dict(os.environ)
    e["OPENBLAS_NUM_THREADS"] = "1"
    e["OMP_NUM_THREADS"] = "1"
    e["PYTHONPATH"] = str(REPO) + os.pathsep + e.get("PYTHONPATH", "")
    e.pop("NOTIFY_SOCKET", None)
    e.pop("WATCHDOG_USEC", None)
    return e


def edge_raw(state_dir: Path, bus: dict[str, Any], *, table4: bool = True, adapt: bool = True, metrics_port: int | None = None,
             record: Path | None = None, save_interval_s: float = 60.0, **sections: Any) -> dict[str, Any]:
    """The shipped edge.yaml adapted to an accelerated test: frame clock, test bus, temp state dir."""
    raw = yaml.safe_load(EDGE_YAML.read_text())
    raw["bus"] = {**bus, "preserve_timestamps": True}
    raw["codec"] = {"dbc": str(DBC), "resync_after_cycles": 1000}
    raw["model"] = {"path": str(MODEL), "parameters": table4_model_params() if table4 else {}}
    raw["clock"]["mode"] = "frame"
    raw["timeouts"] = {"INV_Currents": 2.0, "INV_Mechanics": 2.0, "INV_StatorTemps": 3.0, "INV_AmbientTemps": 3.0}
    raw["adaptation"]["enabled"] = adapt
    raw["metrics"] = {"enabled": metrics_port is not None, "address": "127.0.0.1", "port": metrics_port or 0}
    raw["state"] = {"dir": str(state_dir), "save_interval_s": save_interval_s}
    raw["recording"] = {"candump": str(record) if record else None}
    raw["transmit"]["bus_silence_s"] = 2.0
    for k, v in sections.items():
        if isinstance(v, dict) and isinstance(raw.get(k), dict):
            raw[k] = {**raw[k], **v}
        else:
            raw[k] = v
    return raw


def write_yaml(path: Path, raw: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def table4_model_params() -> dict[str, float]:
    """The service's initial model: the plant (pm10kw nominal) moved by the paper's Table 4."""
    from thermal_edge.lptn import load_model
    from thermal_edge.sim.inverter import table4_parameters

    return table4_parameters(load_model(MODEL))


def free_udp_port() -> int:
    """A UDP port for this test's ``udp_multicast`` buses, no other process's while this one runs."""
    return own_udp_port()


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 for a server this test starts, no other process's while this one runs."""
    return own_tcp_port()


def logged_metrics_port(log: Path, timeout: float = 300.0) -> int | None:
    """The port the service bound for its metrics (``metrics.port: 0``), read from its log (``--log-level
    info``); None if not logged within ``timeout`` s. A port picked by the service itself cannot be taken
    by another process between a test's choosing it and the service's binding it."""
    import re

    deadline = time.monotonic() + timeout
    while True:
        m = re.search(r"metrics on http://127\.0\.0\.1:(\d+)/metrics", log.read_text(errors="replace") if log.exists() else "")
        if m:
            return int(m.group(1))
        if time.monotonic() > deadline:
            return None
        time.sleep(0.05)


@contextlib.contextmanager
def host_interface_lock(interface: str, timeout: float = 1800.0):
    """Hold the lock of a network interface every test process of this host shares (``vcan0``): a
    second suite running beside this one waits for it instead of putting its frames on the same bus.
    The lock file's path is fixed on purpose (it is the meeting point); ``flock`` frees it when the
    holder ends, however it ends."""
    import fcntl
    import tempfile

    with open(Path(tempfile.gettempdir()) / f"thermal-edge-tests-{interface}.lock", "a") as fh:
        deadline = time.monotonic() + timeout  # a hang guard
        while True:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{interface} held by another test process for {timeout:g} s") from None
                time.sleep(0.1)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def udp_available(port: int) -> str | None:
    """None if udp_multicast loopback works on ``port``, else the reason."""
    import can

    from thermal_edge.bus import create_bus

    try:
        a = create_bus({"interface": "udp_multicast", "port": port})
    except Exception as exc:
        return f"{type(exc).__name__}: {exc}"
    try:
        b = create_bus({"interface": "udp_multicast", "port": port})
        try:
            a.send(can.Message(arbitration_id=0x7FF, data=b"probe", is_extended_id=False))
            msg = b.recv(1.0)
        finally:
            b.shutdown()
    finally:
        a.shutdown()
    return None if msg is not None and msg.arbitration_id == 0x7FF else "loopback probe not received"


# ----------------------------------------------------------------------------------------------
def heldout_rms(theta_model_params: dict[str, float]) -> float:
    """Open-loop RMS error (K, all sensors) on config/cycles/heldout_drive.yaml of the model with
    these parameters against the plant (pm10kw nominal) readings, from the measured initial state
    (an independent computation with ``thermal_edge.lptn.Simulator``)."""
    from thermal_edge.lptn import Simulator, initial_state, load_model
    from thermal_edge.sim.cycles import cycle_run, load_cycle
    from thermal_edge.sim.plant import simulate_plant

    plant_model = load_model(MODEL)
    run = cycle_run(load_cycle(CYCLES / "heldout_drive.yaml"), plant_model.drive["kt_nm_per_arms"])
    plant = simulate_plant(plant_model, run, seed=7)
    model = plant_model.with_parameters(theta_model_params)
    cols = {c: plant.run.columns[c] for c in model.inputs}
    y0 = {s: float(plant.run.columns[s][0]) for s in model.sensors}
    T0 = initial_state(model, {c: float(v[0]) for c, v in cols.items()}, y0)
    traj = Simulator(model).simulate(model.nominal(), cols, run.dt, T0)
    errs = np.concatenate([traj.node(model.sensors[s]) - plant.run.columns[s] for s in model.sensors])
    return float(np.sqrt(np.mean(errs**2)))


def open_loop_true_max(node: str, cycle: str = "overload.yaml") -> float:
    """The plant's true maximum of a node over a cycle without any derating (independent)."""
    from thermal_edge.lptn import load_model
    from thermal_edge.sim.cycles import cycle_run, load_cycle
    from thermal_edge.sim.plant import simulate_plant

    m = load_model(MODEL)
    res = simulate_plant(m, cycle_run(load_cycle(CYCLES / cycle), m.drive["kt_nm_per_arms"]), noise_k=0, resolution_k=0)
    return float(res.truth.node(node).max())


def final_parameters(state_dir: Path) -> dict[str, float]:
    """The adapted parameters the service persisted, on top of its initial (Table 4) ones."""
    st = json.loads((state_dir / "state.json").read_text())
    params = table4_model_params()
    params.update(st["parameters"])
    return params


def scrape(port: int) -> dict[str, float]:
    """``/metrics`` as {sample name with labels: value}."""
    from prometheus_client.parser import text_string_to_metric_families

    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    out: dict[str, float] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            key = s.name + ("{" + ",".join(f'{k}="{v}"' for k, v in sorted(s.labels.items())) + "}" if s.labels else "")
            out[key] = s.value
    return out


def metric_sum(samples: dict[str, float], name: str) -> float:
    return sum(v for k, v in samples.items() if k == name or k.startswith(name + "{"))


class NotifySocket:
    """A unix datagram socket standing in for systemd's NOTIFY_SOCKET."""

    def __init__(self, path: Path | None = None, abstract: str | None = None) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        if abstract is not None:
            self.sock.bind(b"\0" + abstract.encode())
            self.address = "@" + abstract
        else:
            assert path is not None
            self.sock.bind(str(path))
            self.address = str(path)
        self.sock.settimeout(0.1)
        self.messages: list[str] = []
        self._running = False

    def wait_for(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in m for m in list(self.messages)):
                return True
            if self._running:
                time.sleep(0.02)
                continue
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except TimeoutError:
                continue
        return any(text in m for m in list(self.messages))

    def start_thread(self) -> None:
        """Keep reading in a daemon thread (systemd reads its socket all the time; a full queue
        would make the service's notifications fail)."""
        import threading

        self._running = True

        def loop() -> None:
            while self._running:
                try:
                    self.messages.append(self.sock.recv(4096).decode())
                except TimeoutError:
                    continue
                except OSError:
                    return

        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()

    def drain(self) -> list[str]:
        self.sock.settimeout(0.0)
        try:
            while True:
                self.messages.append(self.sock.recv(4096).decode())
        except (TimeoutError, BlockingIOError):
            pass
        self.sock.settimeout(0.1)
        return self.messages

    def close(self) -> None:
        self._running = False
        self.sock.close()


def start_service(config: Path, notify: NotifySocket | None = None, watchdog_usec: int | None = None,
                  log: Path | None = None) -> subprocess.Popen[bytes]:
    e = env()
    if notify is not None:
        e["NOTIFY_SOCKET"] = notify.address
    if watchdog_usec:
        e["WATCHDOG_USEC"] = str(watchdog_usec)
    out = open(log, "ab") if log else subprocess.DEVNULL
    return subprocess.Popen([sys.executable, "-m", "thermal_edge.cli", "run", "--config", str(config), "--log-level", "info"],
                            cwd=str(REPO), env=e, stdout=out, stderr=subprocess.STDOUT if log else subprocess.DEVNULL)


def emulator_cmd(port: int, summary: Path, trace: Path, *, duration: float | None = None, table4: str = "none",
                 open_loop: bool = False, fallback_current: float | None = None, seed: int = 0,
                 cycle: str = "overload.yaml", ready_file: Path | None = None, speed: float = SPEED,
                 flow_timeout: float = 60.0, max_free: float | None = None, limits_timeout: float | None = None) -> list[str]:
    """``python -m thermal_edge.sim.inverter`` for a test on udp_multicast ``port``. ``flow_timeout``, the wall
    time the emulator waits for a silent service before it runs on, is a generous hang guard by default (a
    busy host may keep the service from ticking for seconds); a test of a service that is gone sets it short."""
    cmd = [sys.executable, "-m", "thermal_edge.sim.inverter", "--interface", "udp_multicast", "--port", str(port),
           "--model", str(MODEL), "--cycle", str(CYCLES / cycle), "--speed", str(speed), "--t0", str(T0),
           "--flow-timeout", str(flow_timeout), "--max-lead", str(MAX_LEAD_S),
           "--current-period", str(CURRENT_PERIOD_S), "--temperature-period", str(TEMPERATURE_PERIOD_S),
           "--plant-dt", str(PLANT_DT_S), "--seed", str(seed), "--summary", str(summary), "--trace", str(trace),
           "--table4", table4]
    if duration is not None:
        cmd += ["--duration", str(duration)]
    if max_free is not None:
        cmd += ["--max-free", str(max_free)]
    if limits_timeout is not None:
        cmd += ["--limits-timeout", str(limits_timeout)]
    if open_loop:
        cmd.append("--open-loop")
    if fallback_current is not None:
        cmd += ["--fallback-current", str(fallback_current)]
    if ready_file is not None:
        cmd += ["--ready-file", str(ready_file)]
    return cmd


def emulator_config(**kw: Any):
    from thermal_edge.sim.inverter import EmulatorConfig

    base = dict(model_path=MODEL, cycle_path=CYCLES / "overload.yaml", speed=SPEED, t0=T0, current_period_s=CURRENT_PERIOD_S,
                temperature_period_s=TEMPERATURE_PERIOD_S, plant_dt_s=PLANT_DT_S, trace_every_s=1.0, record_estimates=True)
    base.update(kw)
    return EmulatorConfig(**base)


def deep_copy(x: Any) -> Any:
    return copy.deepcopy(x)


def isfinite(x: float) -> bool:
    return isinstance(x, float) and math.isfinite(x)


#: Simulated seconds the emulator of :func:`running` may lead the service.
MAX_LEAD_S = 2.0
#: Generous upper bound of a wait on the emulator or the service (a hang guard for a busy host, not
#: a performance bound), s.
HANG_S = 300.0


@contextlib.asynccontextmanager
async def running(tmp_path, channel, *, speed=150.0, duration=3600.0, metrics=False, **sections):
    """An in-process service and the inverter emulator on one ``virtual`` channel, frame clock, accelerated.

    The emulator logs TE_Limits at its own simulated time, at most :data:`MAX_LEAD_S` ahead of the
    service's ticks: a short lead keeps "within N s of the fault" a statement about the service, also
    on a busy host."""
    from thermal_edge.config import load_config
    from thermal_edge.service import EdgeService
    from thermal_edge.sim.inverter import InverterEmulator

    raw = edge_raw(tmp_path / "state", {"interface": "virtual", "channel": channel}, table4=False, adapt=False,
                   metrics_port=0 if metrics else None, **sections)
    cfg = load_config(write_yaml(tmp_path / "edge.yaml", raw))
    svc = EdgeService(cfg)
    await svc.start()
    cycle = cfg.model.path.parents[1] / "cycles" / "rated_heat_cool.yaml"
    emu = InverterEmulator(emulator_config(duration_s=duration, speed=speed, max_lead_s=MAX_LEAD_S, cycle_path=cycle),
                           {"interface": "virtual", "channel": channel, "preserve_timestamps": True})
    task = asyncio.get_running_loop().create_task(emu.run())
    try:
        assert await async_wait_until(lambda: emu.elapsed > 0 and emu.bus is not None, HANG_S)
        yield svc, emu
    finally:
        emu.stop()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(task, 10)
        await svc.stop()


async def sim_until(emu, t_rel: float, timeout: float = HANG_S) -> None:
    assert await async_wait_until(lambda: emu.elapsed >= t_rel, timeout), f"emulator stuck at {emu.elapsed}"


def engine_on_emulator(cfg: Any, cycle: str, seconds: float, alter: Any = None, trace_every_s: float = 1e9) -> tuple:
    """The engine of ``cfg`` fed, tick by tick through the frame clock, with the simulated machine's
    frames of the packaged ``cycle`` (open loop) until ``seconds``; ``alter(name, t, signals)``
    may change a frame's signals first. Returns the tick outputs, the (closed) engine and the
    emulator (its ``trace()`` is the machine's truth)."""
    from thermal_edge.bus.codec import DecodedFrame
    from thermal_edge.service.clock import FrameClock
    from thermal_edge.service.engine import ThermalEngine
    from thermal_edge.shipped import config_path
    from thermal_edge.sim.inverter import EmulatorConfig, InverterEmulator

    eng = ThermalEngine(cfg)
    emu = InverterEmulator(EmulatorConfig(cycle_path=config_path("cycles", f"{cycle}.yaml"), t0=0.0, plant_dt_s=0.5,
                                          trace_every_s=trace_every_s, record_estimates=False, closed_loop=False))
    clock, outs = FrameClock(cfg.clock.tick_s), []
    try:
        while not outs or outs[-1].t < seconds:
            for ts, name, sig in emu.step(None):
                f = DecodedFrame(name, 0, alter(name, ts, sig) if alter is not None else sig, 0, ts)
                for b in eng.ticks_for(clock.observe(f.timestamp)):
                    outs.append(eng.tick(b))
                eng.add_frame(f, clock.now())
    finally:
        eng.close()
    return outs, eng, emu
