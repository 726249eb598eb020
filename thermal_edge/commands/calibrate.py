"""``thermal-edge calibrate``: fit a model's parameters offline to recorded runs (global search + SQP).

A CAN log (``--format can``: candump ``.log``, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ``.mf4``, by
suffix) is read through the service's own pipeline with the service configuration ``--config``: one
run per stretch of traffic, one sample per tick, as the service on the drive saw it.
Every run is checked and summarised first (sample period, duration, columns used and ignored,
ranges). The global search (differential evolution) stops at ``--generations``, when its
population has converged, when the best objective has not improved for ``--patience``
generations, or at ``--max-time``; SQP then polishes the best point within the time left.
"""
from __future__ import annotations

import argparse

import numpy as np

from ..data import FORMATS
from ..estimation.calibrate import PATIENCE, calibrate, write_calibrated
from ..text_table import table
from .common import add_model_args, add_set_arg, check_param_names, model_from_args, parse_sets
from .options import integer, names, output_model_file, positive_s
from .progress import bar
from .runs import add_can_args, read_checked_runs, require_finite_prediction


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("calibrate", help="offline fit of the model to recorded runs", description=__doc__)
    add_model_args(p)
    p.add_argument("--run", required=True, nargs="+", help="recorded run(s), or CAN log(s) with --format can")
    add_can_args(p, FORMATS)
    p.add_argument("--params", type=names, help="comma-separated parameters to fit (default: the adaptable ones)")
    p.add_argument("--sensors", type=names, help="comma-separated sensors to fit to (default: all in the runs)")
    p.add_argument("--out", required=True, type=output_model_file, help="calibrated model file to write (.yaml)")
    p.add_argument("--decimate", type=integer(1), default=1, help="samples per optimiser step")
    p.add_argument("--generations", type=integer(1), default=30, help="differential-evolution generations, at most")
    p.add_argument("--popsize", type=integer(1), default=10, help="population multiplier (default 10)")
    p.add_argument("--seed", type=integer(0), default=0)
    p.add_argument("--patience", type=integer(1), default=PATIENCE,
                   help=f"stop the global search after this many generations without improvement (default {PATIENCE})")
    p.add_argument("--max-time", type=positive_s, metavar="SECONDS",
                   help="wall-time budget of the fit, s (default: none): no generation or SQP iteration starts "
                        "after it; the one under way and the uncertainty estimate still finish")
    add_set_arg(p)
    p.set_defaults(func=run)


def _names(arg: str | None) -> list[str] | None:
    return [x.strip() for x in arg.split(",") if x.strip()] if arg else None


def run(args: argparse.Namespace) -> int:
    model = model_from_args(args)
    check_param_names(model, _names(args.params))
    sets = parse_sets(model, args.set)  # the starting values; written to --out with the fitted ones
    model = model.with_parameters(sets) if sets else model
    runs = []
    for path in args.run:
        for rec, summary in read_checked_runs(path, args.format, model, _names(args.sensors), args.config):
            require_finite_prediction(model, rec)  # a law that overflows on the run, named before the search
            print(summary, flush=True)
            runs.append(rec)
    with bar(args.generations, "calibrate: global search", "generation") as pb:
        def progress(done: int, total: int, best: float) -> None:
            pb.update(1)
            pb.set_postfix_str(f"best objective {best:.4g} K²")

        res = calibrate(model, runs, _names(args.params), _names(args.sensors), args.decimate, args.generations,
                        args.popsize, args.seed, progress=progress, patience=args.patience, max_time_s=args.max_time)
    values = dict(zip(res.names, map(float, res.values)))
    write_calibrated(args.model, {**sets, **values}, args.out, note=", ".join(args.run))
    lo, hi = model.bounds()
    idx = model.parameter_index(res.names)
    unc = res.uncertainty
    unresolved = unc.unresolved if unc.unresolved is not None else np.zeros(len(res.names), dtype=bool)
    rows = [[n, res.start[i], res.values[i], lo[idx[i]], hi[idx[i]], 100 * unc.rel_std[i],
             "yes" if unc.identifiable[i] else
             "no: acts only together with others (or on nothing)" if unresolved[i] else "not identifiable"]
            for i, n in enumerate(res.names)]
    print(table(["parameter", "start", "fitted", "min", "max", "± % (1σ)", "identifiable"], rows))
    print(f"objective (sum over the sensors of each one's mean squared error, K²): start {res.objective_start:.4g}, "
          f"after global search "
          f"{res.objective_global:.4g} ({res.generations} generations: {res.stopped}), after SQP "
          f"{res.objective_final:.4g}; {res.evaluations} evaluations, {res.wall_s:.1f} s; "
          f"residual σ {np.sqrt(unc.sigma2):.3f} K, "
          f"correlated over {unc.tau:.3g} samples (± counts it; identifiable: as if independent)")
    print(f"wrote {args.out}")
    return 0
