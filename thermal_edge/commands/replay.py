"""``thermal-edge replay``: run the model over a recorded run and score every sensor."""
from __future__ import annotations

import argparse
import json

from ..data import FORMATS, read_run
from ..estimation.predict import open_loop
from .common import add_model_args, model_from_args


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("replay", help="replay a recorded run through the model", description=__doc__)
    add_model_args(p)
    p.add_argument("--run", required=True, help="recorded run")
    p.add_argument("--format", default="csv", choices=FORMATS, help="run file format (default csv)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--no-adapt", dest="adapt", action="store_false", help="open-loop prediction (default)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run, adapt=False)


def run(args: argparse.Namespace) -> int:
    model = model_from_args(args)
    rec = read_run(args.run, args.format)
    _, scores = open_loop(model, rec, method=args.method, max_substep=args.max_substep)
    out = scores.as_dict()
    out.update({"model": model.name, "run": args.run, "samples": len(rec), "adapt": False})
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{model.name} on {args.run}: {len(rec)} samples, open loop")
    print(f"{'sensor':<18}{'MSE K²':>10}{'RMS K':>10}{'max |e| K':>11}")
    for s in scores.mse:
        print(f"{s:<18}{scores.mse[s]:>10.3f}{scores.rms[s]:>10.3f}{scores.max_abs[s]:>11.3f}")
    print(f"{'mean':<18}{scores.mean_mse:>10.3f}")
    return 0
