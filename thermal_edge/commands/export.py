"""``thermal-edge export``: a CAN log as run CSVs, one sample per tick, as the service saw it.

The log (any format python-can reads, by its suffix: ``.log`` candump -L, ``.asc``, ``.blf``,
``.trc``, ``.csv``, ``.mf4`` with the ``mf4`` extra; the text formats gzipped too) goes through the
service's own pipeline with the service configuration ``--config``: its CAN matrix and integrity
checks, its signal mapping and its tick (the time mean of i² for the current, means of speed and
torque, the latest valid temperature readings). The run CSV has ``t`` (s from the first tick) and
one column per model input and sensor, the form every offline command reads (``replay``,
``calibrate``, ``discover``, ``fleet``, a spreadsheet). A log with silences longer than the
configuration's frame timeouts holds several runs: the first goes to ``--out``, the next ones to
``<stem>-1.csv``, ``<stem>-2.csv`` ...
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import UsageError
from ..shipped import config_path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="a CAN log as run CSVs (one sample per tick, as the service saw it)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("log", metavar="LOG", help="the CAN log (format by suffix)")
    p.add_argument("--config", default=str(config_path("edge.yaml")),
                   help="the service configuration whose CAN matrix, signal mapping and tick decode the log "
                        "(default: the example edge.yaml)")
    p.add_argument("--out", required=True, metavar="FILE.csv", help="the run CSV to write (more runs beside it)")
    p.set_defaults(func=run)


def out_paths(out: Path, n: int) -> list[Path]:
    """Where ``n`` runs go: ``out`` first, then ``<stem>-1<suffix>``, ``<stem>-2<suffix>`` ... beside it."""
    return [out] + [out.with_name(f"{out.stem}-{k}{out.suffix}") for k in range(1, n)]


def run(args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..data import write_run
    from ..service.logruns import log_runs
    from .runs import log_line

    out = Path(args.out)
    if out.suffix.lower() != ".csv":
        raise UsageError(f"--out {args.out}: a run CSV must end in .csv")
    if not out.parent.is_dir():
        raise UsageError(f"--out {args.out}: no such directory {str(out.parent)!r}")
    config = load_config(args.config)
    got = log_runs(args.log, config, voltages=True)  # the dq voltages too where the log has them (flux calibrate)
    print(f"{args.log}: {log_line(got)}", file=sys.stderr)
    for path, r in zip(out_paths(out, len(got.runs)), got.runs):
        epoch = float(r.meta["epoch_s"])
        write_run(path, r, comment=f"thermal-edge export {args.log} --config {args.config}\n"
                                   f"t: s from the first tick at {epoch:.6f} s since the epoch ({r.source})")
        print(f"wrote {path}: {len(r)} ticks of {r.dt:g} s, columns t, {', '.join(r.columns)}")
    return 0
