"""``thermal-edge calibrate``: fit a model's parameters offline to recorded runs (global search + SQP)."""
from __future__ import annotations

import argparse

import numpy as np

from ..bench.common import table
from ..data import FORMATS, read_run
from ..estimation.calibrate import calibrate, progress_bar, write_calibrated
from .common import add_model_args, add_set_arg, model_from_args, parse_sets


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("calibrate", help="offline fit of the model to recorded runs", description=__doc__)
    add_model_args(p)
    p.add_argument("--run", required=True, nargs="+", help="recorded run(s)")
    p.add_argument("--format", default="csv", choices=FORMATS)
    p.add_argument("--params", help="comma-separated parameters to fit (default: the adaptable ones)")
    p.add_argument("--sensors", help="comma-separated sensors to fit to (default: all in the runs)")
    p.add_argument("--out", required=True, help="calibrated model file to write")
    p.add_argument("--decimate", type=int, default=1, help="samples per optimiser step")
    p.add_argument("--generations", type=int, default=30, help="differential-evolution generations")
    p.add_argument("--popsize", type=int, default=10)
    p.add_argument("--seed", type=int, default=0)
    add_set_arg(p)
    p.set_defaults(func=run)


def _names(arg: str | None) -> list[str] | None:
    return [x.strip() for x in arg.split(",") if x.strip()] if arg else None


def run(args: argparse.Namespace) -> int:
    model = model_from_args(args)
    sets = parse_sets(model, args.set)  # the starting values; written to --out with the fitted ones
    model = model.with_parameters(sets) if sets else model
    runs = [read_run(r, args.format) for r in args.run]
    res = calibrate(model, runs, _names(args.params), _names(args.sensors), args.decimate, args.generations,
                    args.popsize, args.seed, progress=progress_bar())
    values = dict(zip(res.names, map(float, res.values)))
    write_calibrated(args.model, {**sets, **values}, args.out, note=", ".join(args.run))
    lo, hi = model.bounds()
    idx = model.parameter_index(res.names)
    unc = res.uncertainty
    rows = [[n, res.start[i], res.values[i], lo[idx[i]], hi[idx[i]], 100 * unc.rel_std[i], "yes" if unc.identifiable[i] else "no"]
            for i, n in enumerate(res.names)]
    print(table(["parameter", "start", "fitted", "min", "max", "± % (1σ)", "identifiable"], rows))
    print(f"objective (mean squared error, K²): start {res.objective_start:.4g}, after global search "
          f"{res.objective_global:.4g}, after SQP {res.objective_final:.4g}; {res.evaluations} evaluations, "
          f"{res.wall_s:.1f} s; residual σ {np.sqrt(unc.sigma2):.3f} K")
    print(f"wrote {args.out}")
    return 0
