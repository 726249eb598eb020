"""``thermal-edge bench``: benchmarks that print tables side by side with their baselines."""
from __future__ import annotations

import argparse
import json

from ..bench import jacobian
from ..bench.common import table


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("bench", help="run a benchmark", description=__doc__)
    which = p.add_subparsers(dest="bench", required=True, metavar="BENCH")
    j = which.add_parser("jacobian", help="analytic vs forward-difference Jacobian (39 nodes, 14 parameters, 3 h)")
    j.add_argument("--repeat", type=int, default=3, help="timed repeats (median reported)")
    j.add_argument("--json", action="store_true", help="print one JSON object")
    j.set_defaults(func=run_jacobian)


def run_jacobian(args: argparse.Namespace) -> int:
    r = jacobian.run(repeat=args.repeat)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(f"Jacobian of {r['nodes']} nodes x {r['params']} parameters over {r['samples']} samples "
          f"({r['operating_points']} distinct speeds); median of {args.repeat}")
    print(table(
        ["method", "wall s", "vs analytic"],
        [
            ["analytic (sim + sensitivities)", r["analytic_s"], "1.0x"],
            ["forward differences (p+1 sims)", r["numerical_s"], f"{r['speedup']:.1f}x slower"],
            ["one simulation", r["simulation_s"], f"{r['simulation_s'] / r['analytic_s']:.2f}x"],
            ["arithmetic limit (BLAS rate)", r["arith_limit_s"], f"{r['arith_limit_s'] / r['analytic_s']:.2f}x"],
        ],
    ))
    print(f"max relative error vs central differences: {r['max_rel_err']:.2e}")
    return 0
