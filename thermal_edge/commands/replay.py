"""``thermal-edge replay``: run the model over a recorded run and score every sensor.

Open loop (``--no-adapt``, the default) predicts the whole run from its measured initial state.
With ``--adapt`` the online adapter runs over the run as the service would, learning only from
``--sensors``, and every sensor in the file is scored (the unseen ones too).
A ``candump -L`` log (``--format candump``) goes through the service's own pipeline with the
service configuration ``--config`` (frame timestamps as the clock) and is summarised.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from ..data import FORMATS, read_run
from ..estimation.adapter import AdapterConfig
from ..estimation.online import run_online
from ..estimation.predict import open_loop, score, sensor_columns
from ..bench.common import config_path
from ..lptn import Trajectory
from ..service.replay import format_summary, replay_summary
from .common import add_model_args, model_from_args


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("replay", help="replay a recorded run through the model", description=__doc__)
    add_model_args(p, required=False, discretisation=True)
    p.add_argument("--run", required=True, help="recorded run, or a candump -L log with --format candump")
    p.add_argument("--format", default="csv", choices=(*FORMATS, "candump"), help="run file format (default csv)")
    p.add_argument("--config", default=str(config_path("edge.yaml")),
                   help="candump: the service configuration to replay with (default config/edge.yaml)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--no-adapt", dest="adapt", action="store_false", help="open-loop prediction (default)")
    mode.add_argument("--adapt", dest="adapt", action="store_true", help="run the online adapter over the run")
    p.add_argument("--sensors", help="comma-separated sensors the adapter may learn from (default: all)")
    p.add_argument("--period", type=float, default=AdapterConfig.period_s, help="adaptation period, s")
    p.add_argument("--threshold", type=float, default=AdapterConfig.threshold_k, help="adaptation threshold, K RMS")
    p.add_argument("--decimate", type=int, default=AdapterConfig.decimate, help="samples per optimiser step")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run, adapt=False)


def run(args: argparse.Namespace) -> int:
    if args.format == "candump":
        summary = replay_summary(args.run, args.config, args.model)
        print(json.dumps(summary, indent=2, default=float) if args.json else format_summary(summary))
        return 0
    if not args.model:
        raise KeyError("--model is required for CSV runs")
    model = model_from_args(args)
    rec = read_run(args.run, args.format)
    out: dict[str, object] = {"model": model.name, "run": args.run, "samples": len(rec), "adapt": bool(args.adapt)}
    if args.adapt:
        sensors = tuple(s.strip() for s in args.sensors.split(",")) if args.sensors else None
        sensor_columns(model, rec, sensors)  # names a sensor the model or the run lacks
        cfg = AdapterConfig(period_s=args.period, threshold_k=args.threshold, decimate=args.decimate, sensors=sensors)
        res = run_online(model, rec, cfg)
        scores = score(model, Trajectory(T=res.T, P=np.zeros((len(rec), 0)), nodes=model.nodes), sensor_columns(model, rec))
        _, final = open_loop(model, rec, theta=res.theta, method=args.method, max_substep=args.max_substep)
        out.update(scores.as_dict())
        out.update({
            "adapted_from": list(res.adapter.sensors),
            "params": res.adapter.params_dict(),
            "decisions": [d.as_dict() for d in res.decisions if d.triggered],
            "final_params_open_loop": final.as_dict(),
        })
    else:
        _, scores = open_loop(model, rec, method=args.method, max_substep=args.max_substep)
        out.update(scores.as_dict())
    if args.json:
        print(json.dumps(out, indent=2, default=float))
        return 0
    mode = f"online adaptation from {', '.join(out['adapted_from'])}" if args.adapt else "open loop"
    print(f"{model.name} on {args.run}: {len(rec)} samples, {mode}")
    print(f"{'sensor':<18}{'MSE K²':>10}{'RMS K':>10}{'max |e| K':>11}")
    for s in scores.mse:
        print(f"{s:<18}{scores.mse[s]:>10.3f}{scores.rms[s]:>10.3f}{scores.max_abs[s]:>11.3f}")
    print(f"{'mean':<18}{scores.mean_mse:>10.3f}")
    if args.adapt:
        acc = sum(1 for d in out["decisions"] if d["accepted"])  # type: ignore[union-attr]
        print(f"{len(out['decisions'])} optimisations, {acc} accepted; final parameters: "  # type: ignore[arg-type]
              + ", ".join(f"{k}={v:.4g}" for k, v in out["params"].items()))  # type: ignore[union-attr]
    return 0
