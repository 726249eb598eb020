"""``thermal-edge run``: the edge service (CAN in, derating out), e.g. under systemd.

Reads and validates the configuration, loads the saved state, opens the bus and runs until
SIGTERM/SIGINT/SIGQUIT, which save the state and exit 0 (3 if that final save failed); SIGHUP,
SIGUSR1, SIGUSR2 and SIGALRM are ignored (:mod:`thermal_edge.process_signals`). Bad configuration
exits 2 with one line naming the file and the key.
"""
from __future__ import annotations

import argparse
import asyncio
import os
import sys

LOG_LEVELS = ("debug", "info", "notice", "warning", "error")


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("run", description=__doc__)  # (its help line: thermal_edge.commands.COMMANDS)
    p.add_argument("--config", required=True, help="service configuration (start from `thermal-edge config example`)")
    p.add_argument("--log-level", default=os.environ.get("THERMAL_EDGE_LOG_LEVEL", "info"), choices=LOG_LEVELS,
                   help="log level (default info; env THERMAL_EDGE_LOG_LEVEL)")
    p.add_argument("--check", action="store_true", help="validate the configuration, model and DBC, then exit")
    p.set_defaults(func=run)


def fail(msg: str) -> int:
    print(f"thermal-edge run: error: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from ..process_signals import ignore_while_starting

    ignore_while_starting()  # a SIGHUP while the service starts must not kill it (the running service logs them)
    from ..service.journal import setup_logging

    # argparse checks --log-level's choices, not a default taken from the environment: an unknown
    # level here came from THERMAL_EDGE_LOG_LEVEL
    level = (args.log_level or "info").strip().lower() or "info"
    if level not in LOG_LEVELS:
        return fail(f"THERMAL_EDGE_LOG_LEVEL: {args.log_level!r} is not a log level (one of {', '.join(LOG_LEVELS)})")
    setup_logging(level)
    from ..bus import BusConfigError, DbcError
    from ..config import ConfigError, load_config
    from ..lptn import ModelError
    from ..service.memory import limit_heap_retention

    limit_heap_retention()  # before the model is loaded: its temporaries must not stay resident (that module says why)

    def line(exc: BaseException) -> str:
        return (str(exc).strip().splitlines() or [type(exc).__name__])[0]

    try:
        config = load_config(args.config)
        from ..service import EdgeService
        from ..service.engine import load_service_model

        try:
            model = load_service_model(config)
        except (ModelError, OSError) as exc:  # the model file's message names that file and its key
            raise ConfigError(f"{config.fname}: model.path: {line(exc)}") from None
        # only a path where no directory can be is an error; one that cannot be written now is the state store's to report
        config.check_state_dir(create=not args.check)
        config.check_recording()
        try:
            if args.check:  # (the service checks the model itself when it starts)
                config.check_model(model)
                codec = config.codec.frame_codec(config.fname)
                config.check_dbc(codec, model.input_roles)
                if config.flux.enabled:  # read now, as the service reads it at start
                    from ..service.flux_input import load_flux_model

                    flux = load_flux_model(config)
                print(f"{config.fname}: ok (model {model.name}, {len(model.nodes)} nodes, bus {config.bus.interface})")
                problem = config.state_dir_problem()
                if problem is not None:
                    print(f"{config.fname}: state.dir: warning: {problem}: the service will protect without saving "
                          "its state (and cannot lock the directory against a second service)", file=sys.stderr)
                if config.flux.enabled:
                    print(f"  {config.flux.frame}: the magnet from the voltages, {config.flux.calibration} "
                          f"({flux.pole_pairs} pole pairs, informative from {flux.speed_min_rpm:.0f} rpm)")
                # what each read frame is checked for; the voltages' frame goes stale after flux.timeout_s
                read = dict(config.timeouts)
                if config.flux.enabled and config.flux.frame not in read:
                    read[config.flux.frame] = config.flux.timeout_s
                for frame, timeout in read.items():
                    prot = codec.protection(frame)
                    unseen = "; ".join(prot.unseen()) if prot is not None else ""
                    print(f"  {frame}: protection {prot.describe() if prot is not None else 'none'}, stale after "
                          f"{timeout:g} s" + (f"; not detected: {unseen}" if unseen else ""))
                return 0
            service = EdgeService(config, model=model)
        except DbcError as exc:
            raise ConfigError(f"{config.fname}: codec.dbc: {line(exc)}") from None
    except BrokenPipeError:  # the reader of the output went away (`--check | head`): not an error of the input
        raise
    except (ConfigError, DbcError, BusConfigError, ModelError, OSError) as exc:
        if getattr(args, "debug", False):  # --debug: the traceback of a user error too
            raise
        if not isinstance(exc, OSError):
            return fail(line(exc))
        return fail(f"{getattr(exc, 'filename', None) or ''}: {exc.strerror or exc}".lstrip(": "))
    try:
        return asyncio.run(service.run())
    except (BusConfigError, ConfigError) as exc:
        if getattr(args, "debug", False):
            raise
        return fail(str(exc).strip().splitlines()[0])
    except Exception as exc:  # e.g. an interface python-can does not have
        import can

        if isinstance(exc, (can.CanInterfaceNotImplementedError, can.CanInitializationError)):
            return fail(f"{config.fname}: bus: {exc}")
        raise
