"""``bench service``: the edge service's timing, throughput and memory.

- **tick duration** (p50/p99): the 1 Hz tick's compute time (losses, LPTN step, observer,
  look-ahead, derating, outputs) of the real :class:`~thermal_edge.service.engine.ThermalEngine`
  on the 10 kW model, fed with the frames of the simulated machine; once with the adapter idle and
  once while an adaptation decision is running in the worker thread all the time (back to back,
  threshold 0, on a 3 h history), as the service runs it;
- **max lossless inbound frame rate**: a separate process sends the inverter's frames over
  ``udp_multicast`` (hop limit 0) at rising rates for a few seconds each to the service running
  with the wall clock, as on a drive; a rate is lossless if the service accepted every frame sent
  (alive counters without gaps, nothing dropped); the highest such rate is reported;
- **resident memory**: the service as it is deployed, ``thermal-edge run`` in a process of its own
  (the model off by the paper's Table 4 variations, adaptation on), fed by the simulated machine in
  the bench's process over ``udp_multicast`` (hop limit 0), closed loop and accelerated (the
  emulator's flow control keeps it at most 10 simulated seconds ahead of the service's ticks)
  through 24 h of the varied drive cycle repeated. The service process's ``VmRSS`` and ``VmHWM``
  (its peak) are read from ``/proc/<pid>/status`` every simulated hour: the figure an edge computer
  must hold, without the emulator's memory.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from ..shipped import config_path
from .common import Progress, no_progress

if TYPE_CHECKING:
    from ..config import EdgeConfig

RATES = (2000, 4000, 6000, 8000, 10000, 12000, 14000, 16000, 20000, 24000, 28000, 32000)


@dataclass
class ServiceResult:
    """What ``bench service`` measured: tick times in ms, frame rates in frames/s, memory in MB."""

    tick_p50_ms: float
    tick_p99_ms: float
    tick_max_ms: float
    tick_p50_adapting_ms: float
    tick_p99_adapting_ms: float
    tick_max_adapting_ms: float
    adaptation_decisions_during: int
    ticks_measured: int
    max_lossless_fps: int
    fps_runs: list[dict[str, Any]]  #: one per rate tried
    fps_seconds_per_rate: float
    rss_mb: float  #: the service process's VmRSS at the end of the memory run
    hwm_mb: float  #: its VmHWM (peak resident set) over the run
    rss_at_start_mb: float  #: VmRSS when it said READY=1
    rss_after_1h_mb: float
    rss_growth_mb: float
    rss_samples: list[tuple[float, float, float]]  #: (simulated hour, VmRSS MB, VmHWM MB)
    memory_run_hours: float
    memory_run_wall_s: float
    memory_run_adaptations: list[int]  #: [accepted, run]
    targets: dict[str, float]


def proc_memory(pid: int | str = "self") -> dict[str, float]:
    """``VmRSS``, ``VmHWM`` (the peak resident set), ``RssAnon`` and ``RssFile`` of a process, MB
    (Linux ``/proc/<pid>/status``; empty where there is none)."""
    out: dict[str, float] = {}
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                if key in ("VmRSS", "VmHWM", "RssAnon", "RssFile"):
                    out[key] = int(value.split()[0]) * 1024 / 1e6  # kB
    except (OSError, ValueError):
        pass
    return out


def _config(state_dir: Path, bus: dict[str, Any], *, clock: str = "frame", adapt: bool = True, table4: bool = True,
            **sections: Any) -> EdgeConfig:
    from ..config import config_from_mapping

    return config_from_mapping(_raw(state_dir, bus, clock=clock, adapt=adapt, table4=table4, **sections),
                               config_path("edge.yaml"))


def _raw(state_dir: Path, bus: dict[str, Any], *, clock: str = "frame", adapt: bool = True, table4: bool = True,
         **sections: Any) -> dict[str, Any]:
    """The packaged ``edge.yaml`` as a mapping, for a bench run: this bus, the packaged DBC, pm10kw
    (off by the Table 4 variations with ``table4``), no metrics, state in ``state_dir``."""
    from ..lptn import load_model
    from ..sim.inverter import table4_parameters

    raw = yaml.safe_load(config_path("edge.yaml").read_text())
    raw["bus"] = {**bus, "preserve_timestamps": True}
    raw["codec"] = {"dbc": None, "resync_after_cycles": 1000}  # the packaged DBC
    model = load_model(config_path("machines", "pm10kw.yaml"))
    raw["model"] = {"path": str(config_path("machines", "pm10kw.yaml")),
                    "parameters": table4_parameters(model) if table4 else {}}
    raw["clock"]["mode"] = clock
    raw["adaptation"]["enabled"] = adapt
    raw["metrics"] = {"enabled": False}
    raw["state"] = {"dir": str(state_dir), "save_interval_s": 600}
    raw["recording"] = {}
    for k, v in sections.items():
        raw[k] = {**raw.get(k, {}), **v} if isinstance(v, dict) else v
    return raw


# ----------------------------------------------------------------------------------------------
def _frames(emu: Any) -> list[Any]:
    """The next plant step's frames as decoded frames (no bus)."""
    from ..bus.codec import DecodedFrame

    return [DecodedFrame(name, 0, sig, 0, ts) for ts, name, sig in emu.step(None)]


def tick_latency(ticks: int = 600, warmup_s: float = 3600.0, adapting: bool = False,
                 progress: Progress = no_progress) -> dict[str, float]:
    """Tick compute times (ms) of the engine; with ``adapting`` a decision runs in a worker thread
    all the time. ``progress`` counts the ticks, warm-up included."""
    from ..service.adaptation import AdaptationWorker
    from ..service.clock import FrameClock
    from ..service.engine import ThermalEngine
    from ..sim.inverter import EmulatorConfig, InverterEmulator

    with tempfile.TemporaryDirectory() as tmp:
        cfg = _config(Path(tmp), {"interface": "virtual"}, adapt=False)
        engine = ThermalEngine(cfg)
        emu = InverterEmulator(EmulatorConfig(cycle_path=config_path("cycles", "varied_drive.yaml"), t0=0.0,
                                              current_period_s=0.01, temperature_period_s=0.1, plant_dt_s=0.5,
                                              trace_every_s=1e9, record_estimates=False))
        busy = None
        if adapting:
            from dataclasses import replace

            ad_cfg = replace(cfg.adaptation.adapter, threshold_k=0.0, min_window_s=600.0)
            busy = AdaptationWorker(engine.model, ad_cfg, 1.0, engine.adaptation.theta, engine.adaptation.offline_theta,
                                   mode="thread")
        clock = FrameClock(cfg.clock.tick_s)
        last_tick = 0.0
        durations: list[float] = []
        decisions = 0
        stop_at = warmup_s + ticks
        stage = "ticks, adaptation running" if adapting else "ticks, adapter idle"
        while last_tick < stop_at:
            progress(stage, last_tick, stop_at, "tick")
            for f in _frames(emu):
                for b in engine.ticks_for(clock.observe(f.timestamp)):  # the service's frame clock
                    out = engine.tick(b)
                    x_ol = engine.estimate.prediction
                    if busy is not None and x_ol is not None:
                        busy.record(b - 1, out.inputs, out.measured, x_ol)
                    if b > warmup_s:
                        durations.append(out.compute_s)
                        if busy is not None and not busy.busy:
                            busy.request(b - 1)
                            decisions += 1
                        time.sleep(0.002)  # the loop's other work; lets the worker hold the GIL meanwhile
                    last_tick = b
                engine.add_frame(f, clock.now())
        if busy is not None:
            busy.close(timeout=30)
        engine.close()
    d = np.array(durations) * 1e3
    return {"p50_ms": float(np.percentile(d, 50)), "p99_ms": float(np.percentile(d, 99)), "max_ms": float(d.max()),
            "ticks": len(d), "decisions": decisions}


# ----------------------------------------------------------------------------------------------
def _sender(port: int, rate: float, seconds: float) -> None:
    """Send the inverter's 10 ms and 100 ms frames at ``rate`` frames/s over udp_multicast (a process)."""
    import can

    from ..bus import FrameCodec, create_bus

    codec = FrameCodec()
    bus = create_bus({"interface": "udp_multicast", "port": port})
    cur = [codec.encode("INV_Currents", {"INV_Id": 0.0, "INV_Iq": 30.0 + k % 7, "INV_IphRms": 21.0}, counter=k)
           for k in range(16)]
    mech = [codec.encode("INV_Mechanics", {"INV_Speed": 900.0, "INV_Torque": 120.0, "INV_Udc": 560.0}, counter=k)
            for k in range(16)]
    stat = [codec.encode("INV_StatorTemps", {"INV_T_WindingSlot": 60.0, "INV_T_EndWinding": 62.0, "INV_T_Housing": 45.0,
                                             "INV_S_WindingSlot": 0, "INV_S_EndWinding": 0, "INV_S_Housing": 0}, counter=k)
            for k in range(16)]
    amb = [codec.encode("INV_AmbientTemps", {"INV_T_Ambient": 25.0, "INV_T_Coolant": math.nan, "INV_S_Ambient": 0,
                                             "INV_S_Coolant": 3}, counter=k) for k in range(16)]
    pattern = [(0x0A0, cur), (0x0A1, mech)] * 10 + [(0x0B0, stat), (0x0B1, amb)]  # the DBC's 10:1 mix
    counters = {0x0A0: 0, 0x0A1: 0, 0x0B0: 0, 0x0B1: 0}
    sent = 0
    t0 = time.monotonic()
    slot = 0.001
    i = 0
    while True:
        now = time.monotonic() - t0
        if now >= seconds:
            break
        due = int(min(now + slot, seconds) * rate)
        while sent < due:
            fid, table = pattern[i % len(pattern)]
            i += 1
            k = counters[fid]
            counters[fid] = (k + 1) % 16
            bus.send(can.Message(arbitration_id=fid, data=table[k], is_extended_id=False, timestamp=time.time()))
            sent += 1
        time.sleep(max(0.0, slot - ((time.monotonic() - t0) - now)))
    bus.shutdown()
    print(json.dumps({"sent": sent, "seconds": time.monotonic() - t0}))


def max_lossless_fps(rates: tuple[int, ...] = RATES, seconds: float = 4.0,
                     progress: Progress = no_progress) -> dict[str, Any]:
    """Highest sustained inbound frame rate the service accepts without loss (udp_multicast, wall clock);
    ``progress`` counts the rates tried."""
    from ..service import EdgeService

    results: list[dict[str, Any]] = []
    best = 0
    # the sender: this interpreter, this environment and working directory, so it imports this same package
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    for k, rate in enumerate(rates):
        progress("frame rates", k, len(rates), "rate")
        port = _free_udp_port()
        with tempfile.TemporaryDirectory() as tmp:
            cfg = _config(Path(tmp), {"interface": "udp_multicast", "port": port}, clock="wall", adapt=False)

            async def one(cfg: EdgeConfig, port: int, rate: int) -> dict[str, Any]:
                svc = EdgeService(cfg, serve_metrics=False)
                await svc.start()
                st = svc.codec.stats
                proc = await asyncio.create_subprocess_exec(
                    sys.executable, "-m", "thermal_edge.bench.service", "--send", str(port), str(rate), str(seconds),
                    stdout=asyncio.subprocess.PIPE, env=env)
                names = ("INV_Currents", "INV_Mechanics", "INV_StatorTemps", "INV_AmbientTemps")
                out, _ = await proc.communicate()
                at_end = sum(st.received[k] for k in names)  # accepted when the sender stopped
                await asyncio.sleep(0.3)  # the last frames
                report = json.loads(out.decode().strip().splitlines()[-1])
                sent = report["sent"]
                received = sum(st.received[k] for k in names)
                res = {"rate": rate, "achieved_rate": round(sent / report["seconds"]), "sent": sent, "received": received,
                       "backlog_at_end": sent - at_end, "lost": st.lost, "dropped": st.dropped_total,
                       "ticks": svc.engine.ticks, "max_tick_lateness_ms": round(svc.max_lateness_s * 1e3, 2)}
                await svc.stop()
                return res

            r = asyncio.run(one(cfg, port, rate))
        # lossless and sustained: every frame accepted, the service kept up (backlog under 50 ms of frames
        # when the sender stopped) and the ticks stayed on time
        r["lossless"] = (r["received"] == r["sent"] and r["lost"] == 0 and r["dropped"] == 0
                         and r["backlog_at_end"] <= 0.05 * rate and r["max_tick_lateness_ms"] < 100
                         and r["achieved_rate"] >= 0.95 * rate)
        results.append(r)
        if r["lossless"]:
            best = rate
        else:
            break
    return {"max_lossless_fps": best, "runs": results}


# ----------------------------------------------------------------------------------------------
class _Notifications:
    """The systemd notification socket of a service started by the bench (``NOTIFY_SOCKET``)."""

    def __init__(self, path: Path) -> None:
        import socket

        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))

    def wait_ready(self, proc: subprocess.Popen[bytes], timeout_s: float) -> bool:
        """True when the service said ``READY=1``; False if it exited or ``timeout_s`` passed first."""
        self.sock.settimeout(0.2)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and proc.poll() is None:
            try:
                if b"READY=1" in self.sock.recv(4096):
                    return True
            except TimeoutError:
                continue
        return False

    def close(self) -> None:
        self.sock.close()


def memory_run(hours: float = 24.0, current_period_s: float = 0.5, progress: Progress = no_progress) -> dict[str, Any]:
    """Resident memory of the service process (``thermal-edge run``) over an accelerated closed-loop
    run of ``hours``, the simulated machine in this process; ``progress`` counts the simulated hours.

    Raises
    ------
    RuntimeError
        The service did not start or did not run to the end (its log's last lines say why): a fault
        of the code or the host, not of any input.
    """
    from ..lptn import load_model
    from ..service.persistence import StateStore
    from ..sim.inverter import EmulatorConfig, InverterEmulator

    samples: list[tuple[float, float, float]] = []  # (simulated hour, VmRSS MB, VmHWM MB)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        port = _free_udp_port()
        bus = {"interface": "udp_multicast", "port": port}
        timeouts = {"INV_Currents": 3.0, "INV_Mechanics": 3.0, "INV_StatorTemps": 3.0, "INV_AmbientTemps": 3.0}
        cfg_path = tmp / "edge.yaml"
        cfg_path.write_text(yaml.safe_dump(_raw(tmp / "state", bus, adapt=True, timeouts=timeouts), sort_keys=False))
        notify = _Notifications(tmp / "notify")
        log_path = tmp / "service.log"
        env = {**os.environ, "NOTIFY_SOCKET": str(tmp / "notify")}
        env.pop("WATCHDOG_USEC", None)
        with open(log_path, "wb") as log_fh:
            proc = subprocess.Popen([sys.executable, "-m", "thermal_edge.cli", "run", "--config", str(cfg_path),
                                     "--log-level", "warning"], env=env, stdout=log_fh, stderr=subprocess.STDOUT)

        def fail(why: str) -> RuntimeError:
            tail = log_path.read_text(errors="replace").strip().splitlines()[-5:]
            return RuntimeError(f"bench service: memory run: {why}" + (": " + " | ".join(tail) if tail else ""))

        try:
            if not notify.wait_ready(proc, 180.0):
                raise fail("the service did not become ready")
            at_start = proc_memory(proc.pid)
            emu = InverterEmulator(EmulatorConfig(cycle_path=config_path("cycles", "varied_drive.yaml"), duration_s=hours * 3600,
                                                  speed=1000.0, t0=1.7e9, current_period_s=current_period_s,
                                                  temperature_period_s=1.0, plant_dt_s=max(0.5, current_period_s),
                                                  trace_every_s=1e9, record_estimates=False, max_lead_s=10.0,
                                                  flow_timeout_s=10.0),
                                   {**bus, "preserve_timestamps": True})

            async def main() -> Any:
                task = asyncio.create_task(emu.run())
                next_h = 1.0
                while not task.done():
                    h = emu.elapsed / 3600.0
                    progress("memory run", h, hours, "h")
                    if h >= next_h:
                        m = proc_memory(proc.pid)
                        samples.append((h, m.get("VmRSS", math.nan), m.get("VmHWM", math.nan)))
                        next_h += 1.0
                    await asyncio.sleep(0.1)
                return await task

            t = time.monotonic()
            summary = asyncio.run(main())
            wall = time.monotonic() - t
            time.sleep(1.0)  # the service works through the last frames in flight
            if proc.poll() is not None:
                raise fail(f"the service exited with {proc.returncode} during the run")
            end = proc_memory(proc.pid)
            if samples and samples[-1][0] >= emu.elapsed / 3600.0 - 1e-6:
                samples.pop()  # the last hour's sample is the end's
            samples.append((emu.elapsed / 3600.0, end.get("VmRSS", math.nan), end.get("VmHWM", math.nan)))
            proc.send_signal(signal.SIGTERM)
            if proc.wait(60) != 0:
                raise fail(f"the service exited with {proc.returncode} on SIGTERM")
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            notify.close()
        state = StateStore(tmp / "state", load_model(config_path("machines", "pm10kw.yaml"))).load()
    after_1h = next((m for h, m, _ in samples if h >= 1.0), samples[0][1])
    return {"wall_s": wall, "accepted": state.param_version if state else 0, "runs": state.adapt_runs if state else 0,
            "service_pid": proc.pid, "flow_timeouts": summary.flow_timeouts, "rx_lost": summary.rx_lost,
            "at_start": at_start, "at_end": end,
            "rss_mb": samples[-1][1], "hwm_mb": samples[-1][2], "rss_after_1h_mb": after_1h,
            "rss_growth_mb": samples[-1][1] - after_1h,
            "rss_samples": [(round(h, 2), round(m, 1), round(p, 1)) for h, m, p in samples], "hours": hours}


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as s:
        s.bind(("::", 0))
        port: int = s.getsockname()[1]
    return port


def run(hours: float = 24.0, ticks: int = 600, fps_seconds: float = 4.0, rates: tuple[int, ...] = RATES,
        progress: Progress = no_progress) -> ServiceResult:
    """All four measures in turn (tick latency idle and adapting, frame rate, memory); ``progress`` per part."""
    idle = tick_latency(ticks, adapting=False, progress=progress)
    busy = tick_latency(ticks, adapting=True, progress=progress)
    fps = max_lossless_fps(rates, fps_seconds, progress)
    mem = memory_run(hours, progress=progress)
    return ServiceResult(
        tick_p50_ms=idle["p50_ms"], tick_p99_ms=idle["p99_ms"], tick_max_ms=idle["max_ms"],
        tick_p50_adapting_ms=busy["p50_ms"], tick_p99_adapting_ms=busy["p99_ms"], tick_max_adapting_ms=busy["max_ms"],
        adaptation_decisions_during=int(busy["decisions"]), ticks_measured=int(idle["ticks"]),
        max_lossless_fps=fps["max_lossless_fps"], fps_runs=fps["runs"], fps_seconds_per_rate=fps_seconds,
        rss_mb=mem["rss_mb"], hwm_mb=mem["hwm_mb"], rss_at_start_mb=mem["at_start"].get("VmRSS", math.nan),
        rss_after_1h_mb=mem["rss_after_1h_mb"], rss_growth_mb=mem["rss_growth_mb"],
        rss_samples=mem["rss_samples"], memory_run_hours=mem["hours"], memory_run_wall_s=mem["wall_s"],
        memory_run_adaptations=[mem["accepted"], mem["runs"]],
        targets={"tick_p99_adapting_ms": 20.0, "max_lossless_fps": 8000, "rss_mb": 150.0},
    )


if __name__ == "__main__":  # the frame sender process of max_lossless_fps
    ap = argparse.ArgumentParser()
    ap.add_argument("--send", nargs=3, metavar=("PORT", "RATE", "SECONDS"))
    a = ap.parse_args()
    if a.send:
        _sender(int(a.send[0]), float(a.send[1]), float(a.send[2]))
