"""``thermal-edge demo``: the edge service against the simulated machine, in one process.

The service (the packaged example ``edge.yaml`` with a python-can ``virtual`` bus and the frame clock) and the
inverter emulator (the 10 kW machine over a drive cycle, closed loop: it obeys TE_Limits) run
accelerated; by default the service's model starts off by the paper's Table 4 variations, so
the online adaptation has something to do. Live metrics on http://127.0.0.1:9108/metrics and a
one-line status each second: simulated time, state, hot spot estimate/upper band, magnet, limit,
reason, prediction error, adaptations accepted/run, and the plant's true hot spot.
"""
from __future__ import annotations

import argparse
import asyncio
import logging
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from ..shipped import config_path
from ..yamlfile import read_document
from .options import frame_period_s, integer, ip_address, number, output_dir, output_file, positive_s


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("demo", description=__doc__,  # (its help line: thermal_edge.commands.COMMANDS)
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=str(config_path("edge.yaml")),
                   help="service configuration (default: the packaged example, `thermal-edge config example`)")
    p.add_argument("--cycle", default="overload", help="drive cycle: a file or a packaged name (default overload)")
    p.add_argument("--speed", type=number(0, 10000, lo_open=True), default=30.0,
                   help="simulated seconds per wall second (default 30: the 3 h overload cycle in 6 min). The loop "
                        "stays closed as on a drive up to about 30: faster, TE_Limits (10 per wall second) reaches "
                        "the simulated inverter only every --speed/10 simulated s, and the plant may pass a limit "
                        "the service would have kept (156 degC at 200 against 151 at 30)")
    p.add_argument("--duration", type=positive_s, default=None, help="simulated seconds (default: the whole cycle)")
    p.add_argument("--current-period", type=frame_period_s, default=0.05,
                   help="INV_Currents/INV_Mechanics period in simulated s (default 0.05; the DBC's 0.01 at low speed)")
    p.add_argument("--temperature-period", type=frame_period_s, default=0.1, help="INV_*Temps period in simulated s")
    p.add_argument("--no-table4", dest="table4", action="store_false",
                   help="start the service's model at the plant's parameters (nothing to adapt)")
    p.add_argument("--open-loop", action="store_true", help="the machine ignores TE_Limits (to compare)")
    p.add_argument("--metrics-address", type=ip_address, default="127.0.0.1", help="address the metrics listen on")
    p.add_argument("--metrics-port", type=integer(0, 65535), default=9108, help="metrics port (0: any free one)")
    p.add_argument("--state-dir", type=output_dir, default=None,
                   help="state directory, kept (default: a fresh temporary one, removed when the demo ends)")
    p.add_argument("--record", type=output_file, default=None,
                   help="record the bus traffic to this CAN log (format by suffix: .log candump -L, .asc, .blf, .trc, "
                        ".mf4, .csv), stamped in simulated time; TE_Limits keeps its 100 ms cycle in wall time, so "
                        "with --speed above 1 it comes --speed times less often in the log (--speed 1 keeps the "
                        "contract's cycle)")
    p.add_argument("--voltages", action="store_true",
                   help="the inverter also sends INV_Voltages and the service fuses the magnet estimate from them "
                        "(the configuration's flux.calibration, else one commissioned first on a simulated bench run); "
                        "without it no INV_Voltages are sent and flux.calibration is not used")
    p.add_argument("--quiet", action="store_true", help="no status lines")
    p.set_defaults(func=run)


def learned(engine: Any, plant: Any) -> str:
    """What the adaptation learned: the final open-loop prediction error, promotions and refusals,
    and every adapted parameter against the plant's value."""
    from ..service import adapt_phrase

    out = engine.last
    err = f"{out.pred_err_rms:.2f} K" if out is not None and math.isfinite(out.pred_err_rms) else "--"
    ad = engine.adaptation
    decisions = ad.decisions
    dropped = sum(1 for d in decisions if d.get("verdict") == "dropped")
    plant_values = dict(zip(plant.parameter_names, plant.nominal()))
    start = dict(zip(engine.model.parameter_names, engine.model.nominal()))
    moved = [f"{k} {v:.4g} ({100 * (v / plant_values[k] - 1):+.1f} % vs plant)"
             for k, v in ad.values().items() if k in plant_values and (v != start.get(k) or v != plant_values[k])]
    refusal = ad.last_refusal
    last = f"; last refusal: {refusal[1]}" if refusal is not None else ""
    return (f"model: open-loop prediction error {err} at the end; {ad.counts.accepted} promoted, {dropped} refused{last}; "
            f"now {adapt_phrase(ad.status, refusal[1] if refusal else '')}\n"
            f"parameters: {', '.join(moved) if moved else 'as the plant'}")


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    from ..config import ConfigError, config_from_mapping
    from ..lptn import load_model
    from ..service import EdgeService, status_line
    from ..sim.inverter import (
        DEFAULT_SENSOR_SIGNALS,
        STATOR_FRAME,
        TABLE4_VARIATIONS,
        EmulatorConfig,
        InverterEmulator,
        mapped_sensor_signals,
        table4_parameters,
    )
    from ..sim.pmsm import Pmsm

    cfg_path = Path(args.config)
    raw = read_document(cfg_path, ConfigError)
    config_from_mapping(raw, cfg_path)  # the file as it is, each key checked and named, before the demo's changes
    channel = f"thermal-edge-demo-{os.getpid()}"
    own_dir = None if args.state_dir else tempfile.mkdtemp(prefix="thermal-edge-demo-")  # removed at the end
    # a relative --state-dir is relative to where the user is, not to the configuration file (the
    # packaged example's lies inside the installed package)
    state_dir = str(Path(args.state_dir).resolve()) if args.state_dir else own_dir
    raw = dict(raw or {})
    raw["bus"] = {"interface": "virtual", "channel": channel, "preserve_timestamps": True}
    raw["clock"] = {**(raw.get("clock") or {}), "mode": "frame"}
    raw["codec"] = {**(raw.get("codec") or {}), "resync_after_cycles": 1000}  # frames 10 cycles apart, accelerated
    raw["metrics"] = {"enabled": True, "address": args.metrics_address, "port": args.metrics_port}
    raw["state"] = {**(raw.get("state") or {}), "dir": state_dir}
    slow = max(args.current_period, args.temperature_period)
    raw["timeouts"] = {k: max(float(v), 5 * slow) for k, v in (raw.get("timeouts") or {}).items()}
    # a relative --record is relative to where the user is, not to the configuration file
    raw["recording"] = {"candump": str(Path(args.record).resolve())} if args.record else {}
    config = config_from_mapping(raw, cfg_path)  # the model as the service finds it (a file or a packaged name)
    plant_model = load_model(config.model.path)
    flux_dir: Path | None = None
    voltages = ""
    if args.voltages:
        given = (raw.get("flux") or {}).get("calibration")
        if given:  # the user's own commissioning: used as it is, and said so
            voltages = f"voltages: the calibration of {config.fname}, {config.flux.calibration}"
            raw["flux"] = {**raw["flux"], "timeout_s": max(float(raw["flux"].get("timeout_s", 0.5)), 5 * args.current_period)}
        else:
            from ..bench.protection import flux_calibration

            flux_dir = Path(tempfile.mkdtemp(prefix="thermal-edge-demo-flux-"))  # removed at the end
            path = flux_calibration(plant_model, flux_dir / "flux.json")
            voltages = "voltages: commissioned on a simulated bench run of the plant (thermal-edge flux calibrate)"
            raw["flux"] = {**(raw.get("flux") or {}), "calibration": str(path),
                           "timeout_s": max(float((raw.get("flux") or {}).get("timeout_s", 0.5)), 5 * args.current_period)}
        config = config_from_mapping(raw, cfg_path)
    elif (raw.get("flux") or {}).get("calibration"):  # as --help says: voltages only with --voltages
        raw["flux"] = {**raw["flux"], "calibration": None}
        config = config_from_mapping(raw, cfg_path)
        voltages = (f"voltages: off (the inverter sends no INV_Voltages without --voltages; the flux.calibration of "
                    f"{config.fname} is not used)")
    notes = []
    missing = [k for k in TABLE4_VARIATIONS if k not in plant_model.parameter_names]
    table4 = args.table4 and not missing
    if args.table4 and missing:  # another machine's model: the paper's variations name pm10kw's parameters
        notes.append(f"model {plant_model.name} has not the parameters the Table 4 start moves ({', '.join(missing)}): "
                     "the service starts at the plant's values")
    if table4:
        raw["model"] = {**raw.get("model", {}), "parameters": table4_parameters(plant_model)}
        config = config_from_mapping(raw, cfg_path)
    # the simulated inverter sends the PT100s of its INV_StatorTemps frame; the configuration says which
    # of the model's sensors each one is
    sensor_signals = mapped_sensor_signals(config.sensors)
    unsent = [f"{name} ({spec.frame} {spec.signal})" for name, spec in config.sensors.items()
              if name not in sensor_signals.values()]
    if unsent:
        notes.append(f"the simulated inverter sends only {STATOR_FRAME}'s {', '.join(DEFAULT_SENSOR_SIGNALS)}: "
                     f"no reading of {', '.join(unsent)}")
    service = EdgeService(config)
    emu_cfg = EmulatorConfig(model_path=plant_model.path or config_path("machines", "pm10kw.yaml"), cycle_path=args.cycle,
                             duration_s=args.duration, speed=args.speed, current_period_s=args.current_period,
                             temperature_period_s=args.temperature_period, plant_dt_s=max(0.1, args.current_period),
                             closed_loop=not args.open_loop, t0=float(math.floor(time.time())),
                             pmsm=Pmsm.with_kt(config.kt(plant_model)) if config.flux.enabled else None,
                             sensor_signals=sensor_signals)
    emulator = InverterEmulator(emu_cfg, {"interface": "virtual", "channel": channel, "preserve_timestamps": True},
                                model=plant_model)

    async def main() -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        import signal

        for sig in (signal.SIGTERM, signal.SIGINT):
            try:
                loop.add_signal_handler(sig, stop.set)
            except (NotImplementedError, RuntimeError):
                pass
        await service.start()
        if service.metrics_address:
            host, port = service.metrics_address
            print(f"metrics: http://{host}:{port}/metrics   state: {state_dir}", flush=True)
        else:
            print(f"metrics: not served (port {args.metrics_port} busy?)   state: {state_dir}", flush=True)
        for note in notes:
            print(note, flush=True)
        print(f"{'model ' + ('off by Table 4' if table4 else 'at the plant')}, cycle {Path(args.cycle).stem}, "
              f"{args.speed:g}x, {'open' if args.open_loop else 'closed'} loop; Ctrl-C stops", flush=True)
        if voltages:
            print(voltages, flush=True)

        async def status() -> None:
            hs_node = next((lim.node for lim in plant_model.limits if lim.name == config.transmit.hot_spot_limit), None)
            while True:
                await asyncio.sleep(1.0)
                if not args.quiet:
                    true_hs = f"  true {emulator.true(hs_node):6.1f} °C" if hs_node else ""
                    print(status_line(service.engine.last) + true_hs, flush=True)

        st = loop.create_task(status())
        emu = loop.create_task(emulator.run(stop))
        stopper = loop.create_task(stop.wait())
        await asyncio.wait({emu, stopper}, return_when=asyncio.FIRST_COMPLETED)
        emulator.stop()
        summary = await emu
        stopper.cancel()
        st.cancel()
        await service.stop()
        peaks = ", ".join(f"{k} {v:.1f} °C" for k, v in summary.true_max_c.items())
        print(f"done: {summary.sim_seconds / 3600:.2f} h simulated in {summary.wall_seconds:.0f} s; plant peaks: {peaks}; "
              f"adaptations accepted {service.engine.adapt_accepted}/{service.engine.adapt_runs}")
        print(learned(service.engine, plant_model))
        return 0

    try:
        return asyncio.run(main())
    finally:
        if own_dir is not None:
            shutil.rmtree(own_dir, ignore_errors=True)
        if flux_dir is not None:
            shutil.rmtree(flux_dir, ignore_errors=True)
