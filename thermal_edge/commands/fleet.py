"""``thermal-edge fleet``: calibrate, evaluate and screen a fleet's recorded runs on Dask.

RUNS are files, directories or globs: a directory is one machine (its ``*.csv`` runs), a file is
one machine's run with the machine id from its name (or from ``--id-column``). Every machine is
one Dask task, on a local cluster of one worker process per core (``--workers``), or on a running
cluster (``--scheduler tcp://HOST:8786``; the model and run paths must be readable by its
workers). Results: one Parquet table (``--out``, a row per machine and parameter or sensor) and
a Markdown report with plots (``--report``, default next to the table).

  calibrate  each machine's parameters from its own runs, with their uncertainty
  evaluate   a model (or with --calibrated, each machine's own) replayed over every run: errors per sensor
  screen     calibrate (or --table), then the fleet's distribution and the machines that stand out

Needs the ``fleet`` extra: pip install thermal-edge[fleet] (plots: thermal-edge[report]).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..data import FORMATS, RunError
from ..errors import UsageError
from ..shipped import config_path
from .common import add_model_args, check_param_names
from .options import integer, names, number, output_file
from .runs import read_checked

#: Run files whose summary is printed before a fleet job (the rest are counted).
SUMMARY_FILES = 5


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from ..fleet.calibrate import DECIMATE, GENERATIONS, POPSIZE
    from ..fleet.screen import THRESHOLD

    p = sub.add_parser("fleet", help="calibrate, evaluate and screen many machines' runs on Dask", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    which = p.add_subparsers(dest="fleet", required=True, metavar="JOB")

    def common(q: argparse.ArgumentParser, model_required: bool = True) -> None:
        add_model_args(q, required=model_required)
        q.add_argument("runs", nargs="*", metavar="RUNS", help="run files, machine directories or globs")
        q.add_argument("--format", default="csv", choices=FORMATS, help="run file format (default csv)")
        q.add_argument("--config", default=str(config_path("edge.yaml")),
                       help="the service configuration whose CAN matrix, signal mapping and tick decode the CAN logs "
                            "among RUNS (default: the example edge.yaml)")
        q.add_argument("--id-column", help="take the machine id from this column (default: file or directory name)")
        q.add_argument("--out", required=True, type=output_file, help="result table to write (Parquet)")
        q.add_argument("--report", type=output_file, help="Markdown report to write (default: the table's name with .md)")
        q.add_argument("--workers", type=integer(1), help="local worker processes (default: one per core); with "
                       "--scheduler, wait for this many workers")
        q.add_argument("--scheduler", help="address of a running Dask scheduler, e.g. tcp://HOST:8786")
        q.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")

    def fit(q: argparse.ArgumentParser) -> None:
        q.add_argument("--params", type=names, help="comma-separated parameters to fit (default: the adaptable ones)")
        q.add_argument("--sensors", type=names, help="comma-separated sensors to fit to (default: all in the runs)")
        q.add_argument("--decimate", type=integer(1), default=DECIMATE, help=f"samples per optimiser step (default {DECIMATE})")
        q.add_argument("--generations", type=integer(1), default=GENERATIONS,
                       help=f"differential-evolution generations (default {GENERATIONS})")
        q.add_argument("--popsize", type=integer(1), default=POPSIZE, help=f"population multiplier (default {POPSIZE})")
        q.add_argument("--seed", type=integer(0), default=0)

    c = which.add_parser("calibrate", help="each machine's parameters from its own runs, with their uncertainty")
    common(c)
    fit(c)
    c.set_defaults(func=run_calibrate)
    e = which.add_parser("evaluate", help="replay a model over every machine's runs: errors per sensor")
    common(e)
    e.add_argument("--calibrated", help="a fleet calibrate/screen table: replay each machine with its own parameters")
    e.set_defaults(func=run_evaluate)
    s = which.add_parser("screen", help="the fleet's parameter distribution and the machines that stand out")
    common(s, model_required=False)
    fit(s)
    s.add_argument("--table", help="screen this fleet calibrate table instead of calibrating RUNS")
    s.add_argument("--threshold", type=number(0, lo_open=True), default=THRESHOLD,
                   help=f"|z| above which a machine stands out (default {THRESHOLD:g})")
    s.set_defaults(func=run_screen)


def _names(arg: str | None) -> list[str] | None:
    return [x.strip() for x in arg.split(",") if x.strip()] if arg else None


def _abs(path: str | None) -> str | None:
    """Absolute paths: the workers may run elsewhere (another directory, another host's mount)."""
    return str(Path(path).resolve()) if path else None


def _machines(args: argparse.Namespace) -> tuple[list[Any], list[dict[str, Any]]]:
    """The machines of RUNS, every run CSV checked against the model before any task is sent
    (:func:`~thermal_edge.commands.runs.read_checked`; the CAN logs are decoded on the workers).

    Returns the machines to send and an ``error`` row for each refused one (a broken or
    implausible run fails its machine, not the fleet: one line on stderr each). If every machine
    is refused, :class:`~thermal_edge.data.RunError` with the first reason. Prints the first
    :data:`SUMMARY_FILES` runs' summaries and a total.
    """
    from ..config import load_config
    from ..fleet.results import row
    from ..fleet.runs import find_machines
    from ..lptn import load_model
    from ..service.logruns import is_can_log

    if not args.runs:
        raise UsageError("no RUNS given (files, machine directories or globs)")
    try:
        machines = find_machines([_abs(r) or r for r in args.runs], args.id_column)
    except FileNotFoundError as exc:  # its message names the file, directory or glob
        raise UsageError(f"RUNS: {exc}") from None
    model = load_model(args.model, data_dir=args.data_dir)
    if any(is_can_log(f) for m in machines for f in m.runs):
        load_config(args.config)  # a broken configuration is refused here, not by every worker
    check_param_names(model, _names(getattr(args, "params", None)))
    sensors = _names(getattr(args, "sensors", None))
    ok, refused, errors, files, samples = [], [], [], 0, 0
    for m in machines:
        try:
            for f in m.runs:
                if is_can_log(f):
                    continue
                rec, summary = read_checked(f, args.format, model, sensors)
                if files < SUMMARY_FILES:
                    print(summary, flush=True)
                files, samples = files + 1, samples + len(rec)
        except RunError as exc:
            errors.append(str(exc))
            refused.append(row(machine=m.id, kind="error", name="RunError", message=str(exc), runs=";".join(m.runs)))
            continue
        ok.append(m)
    if not ok:
        raise RunError(errors[0])
    for e in errors:
        print(f"thermal-edge fleet {args.fleet}: refused, an error row: {e}", file=sys.stderr, flush=True)
    if files > SUMMARY_FILES:
        print(f"... {files - SUMMARY_FILES} more; {files} run files checked, {samples} samples in all", flush=True)
    return ok, refused


def _guard(job: Any) -> Any:
    """Run a fleet job; a missing extra or an unreachable scheduler is one line and status 2."""

    def wrapped(args: argparse.Namespace) -> int:
        from ..fleet import MissingExtra

        try:
            return int(job(args))
        except (MissingExtra, OSError) as exc:
            if isinstance(exc, FileNotFoundError):
                raise
            print(f"thermal-edge fleet {args.fleet}: error: {exc}", file=sys.stderr)
            return 2

    return wrapped


def _table(path: str, option: str) -> list[dict[str, Any]]:
    """A fleet result table named by ``option``; a missing or unreadable one is a :class:`UsageError`."""
    from ..fleet.results import read_table

    try:
        return read_table(path)
    except (OSError, KeyError, ValueError) as exc:  # missing, not a Parquet table: the message names the file
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else str(exc)
        raise UsageError(f"{option} {str(msg).splitlines()[0]}") from None


def _calibrate_rows(args: argparse.Namespace, client: Any, machines: list[Any]) -> list[dict[str, Any]]:
    from ..fleet.calibrate import calibrate_machine
    from ..fleet.cluster import map_machines

    per = map_machines(client, calibrate_machine, machines, progress=args.progress, desc="calibrate",
                       model_path=_abs(args.model), data_dir=_abs(args.data_dir), fmt=args.format,
                       id_column=args.id_column, params=_names(args.params), sensors=_names(args.sensors),
                       decimation=args.decimate, generations=args.generations, popsize=args.popsize, seed=args.seed,
                       can_config=_abs(args.config))
    return [r for rows in per for r in rows]


def _finish(args: argparse.Namespace, title: str, rows: list[dict[str, Any]], intro: list[str], **screen: Any) -> int:
    from ..fleet.report import summary_text, write_report
    from ..fleet.results import write_table

    write_table(args.out, rows)
    report = Path(args.report) if args.report else Path(args.out).with_suffix(".md")
    write_report(report, title, rows, intro, **screen)
    print(summary_text(rows, screen.get("spreads", ()), screen.get("outliers")))
    print(f"wrote {args.out} ({len(rows)} rows) and {report}")
    return 0


def _intro(args: argparse.Namespace, machines: list[Any], job: str) -> list[str]:
    return [f"`thermal-edge fleet {job}` with model `{args.model}` on {len(machines)} machines "
            f"({sum(len(m.runs) for m in machines)} run files)."]


@_guard
def run_calibrate(args: argparse.Namespace) -> int:
    from ..fleet import require_fleet_extra
    from ..fleet.cluster import connect
    from ..fleet.screen import distribution

    require_fleet_extra()
    machines, refused = _machines(args)
    with connect(args.scheduler, args.workers) as client:
        rows = refused + _calibrate_rows(args, client, machines)
    return _finish(args, "Fleet calibration", rows, _intro(args, machines, "calibrate"), spreads=distribution(rows))


@_guard
def run_evaluate(args: argparse.Namespace) -> int:
    from ..fleet import require_fleet_extra
    from ..fleet.cluster import connect, map_machines
    from ..fleet.evaluate import evaluate_machine
    require_fleet_extra()
    machines, refused = _machines(args)
    params: list[dict[str, float] | None] = [None] * len(machines)
    if args.calibrated:
        fitted: dict[str, dict[str, float]] = {}
        for r in _table(args.calibrated, "--calibrated"):
            if r["kind"] == "parameter":
                fitted.setdefault(r["machine"], {})[r["name"]] = r["value"]
        missing = [m.id for m in machines if m.id not in fitted]
        if missing:
            raise UsageError(f"{args.calibrated}: no parameters for machine(s) {', '.join(missing[:5])}")
        params = [fitted[m.id] for m in machines]
    with connect(args.scheduler, args.workers) as client:
        per = map_machines(client, evaluate_machine, machines, params, progress=args.progress, desc="evaluate",
                           model_path=_abs(args.model), data_dir=_abs(args.data_dir), fmt=args.format,
                           id_column=args.id_column, can_config=_abs(args.config))
    rows = refused + [r for rs in per for r in rs]
    intro = _intro(args, machines, "evaluate") + [
        f"Each machine replayed with its own parameters from `{args.calibrated}`." if args.calibrated
        else "Every machine replayed with the model's own parameters."]
    return _finish(args, "Fleet evaluation", rows, intro)


@_guard
def run_screen(args: argparse.Namespace) -> int:
    from ..fleet import require_fleet_extra
    from ..fleet.cluster import connect
    from ..fleet.screen import screen

    require_fleet_extra()
    if args.table:
        if args.runs:
            raise UsageError("give either RUNS or --table, not both")
        rows = [r for r in _table(args.table, "--table") if r["kind"] in ("parameter", "error")]
        intro = [f"`thermal-edge fleet screen` of the calibration table `{args.table}`."]
    else:
        if not args.model:
            raise UsageError("--model is required to calibrate RUNS (or screen a calibration with --table)")
        machines, refused = _machines(args)
        with connect(args.scheduler, args.workers) as client:
            rows = refused + _calibrate_rows(args, client, machines)
        intro = _intro(args, machines, "screen")
    spreads, outliers = screen(rows, args.threshold)
    intro.append(f"Outlier threshold |z| > {args.threshold:g}.")
    return _finish(args, "Fleet screen", rows, intro, spreads=spreads, outliers=outliers, threshold=args.threshold)


def add_simulate_args(p: argparse.ArgumentParser) -> None:
    """``simulate --fleet N --faulty K``: the options ``thermal-edge simulate`` takes for a fleet."""
    from ..sim.fleet import FAULTY

    p.add_argument("--fleet", type=integer(1), metavar="N",
                   help="simulate a fleet of N machines of the model, one run CSV each, into the directory --out "
                        "(with manifest.json of their true parameters and faults; --seed seeds the fleet)")
    p.add_argument("--faulty", type=integer(0), default=FAULTY, help=f"--fleet: machines with a fault (default {FAULTY})")


def simulate_fleet(args: argparse.Namespace) -> int:
    """``thermal-edge simulate --fleet N --out DIR``: write the simulated fleet."""
    from ..lptn import load_model
    from ..sim.cycles import load_cycle
    from ..sim.fleet import plan_fleet, write_machine, write_manifest

    if args.format != "csv" or args.effect or getattr(args, "set", None):
        raise UsageError("--fleet writes run CSVs of the model's design: no --format can, --effect or --set")
    model = load_model(args.model, data_dir=args.data_dir)
    cycle = load_cycle(args.cycle)
    duration = args.duration if args.duration is not None else cycle.duration_s
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.faulty > args.fleet:
        raise UsageError(f"--faulty {args.faulty}: more than the --fleet of {args.fleet} machines")
    try:
        specs = plan_fleet(model, args.fleet, args.faulty, args.seed)
    except KeyError as exc:  # the faults need parameters of the model the fleet is planned for
        raise UsageError(f"--fleet: {exc.args[0] if exc.args else exc}") from None
    for spec in specs:
        write_machine(model, cycle, spec, out, duration, args.noise, args.resolution)
    write_manifest(out, args.model, args.cycle, specs, duration, args.seed)
    bad = [f"{s.id} ({s.fault['kind']})" for s in specs if s.fault]
    print(f"wrote {len(specs)} machines of {model.name} to {out}/ ({duration:g} s of {cycle.name} each); "
          f"faulty: {', '.join(bad) or 'none'} (manifest.json)")
    return 0
