"""``thermal-edge replay``: run the model over a recorded run and score every sensor.

Open loop (``--no-adapt``, the default) predicts the whole run from its measured initial state.
With ``--adapt`` the observer and the online adapter run over the run as the service would,
learning only from ``--sensors``, and every sensor in the file is scored (the unseen ones too):
the online trace, the same with the parameters fixed, the observer and its 95 % band coverage.
``--set NAME=VALUE`` replaces a parameter's value (within the model's bounds) before anything runs.
A ``candump -L`` log (``--format candump``) goes through the service's own pipeline with the
service configuration ``--config`` (frame timestamps as the clock) and is summarised.
"""
from __future__ import annotations

import argparse
import json

from ..data import FORMATS, read_run
from ..estimation.adapter import AdapterConfig
from ..estimation.online import online_report
from ..estimation.predict import open_loop, sensor_columns
from ..bench.common import config_path
from ..service.replay import format_summary, replay_summary
from .common import add_model_args, add_set_arg, model_from_args, model_with_sets, parse_sets, split_sets


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
    add_set_arg(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run, adapt=False)


def run(args: argparse.Namespace) -> int:
    if args.format == "candump":
        summary = replay_summary(args.run, args.config, args.model, sets=split_sets(args.set))
        print(json.dumps(summary, indent=2, default=float) if args.json else format_summary(summary))
        return 0
    if not args.model:
        raise KeyError("--model is required for CSV runs")
    model = model_with_sets(model_from_args(args), args.set)
    rec = read_run(args.run, args.format)
    out: dict[str, object] = {"model": model.name, "run": args.run, "samples": len(rec), "adapt": bool(args.adapt)}
    if args.set:
        out["set"] = parse_sets(model, args.set)
    if not args.adapt:
        _, scores = open_loop(model, rec, method=args.method, max_substep=args.max_substep)
        out.update(scores.as_dict())
        if args.json:
            print(json.dumps(out, indent=2, default=float))
            return 0
        print(f"{model.name} on {args.run}: {len(rec)} samples, open loop")
        print(f"{'sensor':<18}{'MSE K²':>10}{'RMS K':>10}{'max |e| K':>11}")
        for s in scores.mse:
            print(f"{s:<18}{scores.mse[s]:>10.3f}{scores.rms[s]:>10.3f}{scores.max_abs[s]:>11.3f}")
        print(f"{'mean':<18}{scores.mean_mse:>10.3f}")
        return 0
    sensors = tuple(s.strip() for s in args.sensors.split(",")) if args.sensors else None
    sensor_columns(model, rec, sensors)  # names a sensor the model or the run lacks
    cfg = AdapterConfig(period_s=args.period, threshold_k=args.threshold, decimate=args.decimate, sensors=sensors)
    rep = online_report(model, rec, cfg)
    res = rep["result"]
    _, final = open_loop(model, rec, theta=res.theta, method=args.method, max_substep=args.max_substep)
    out.update({
        "adapted_from": list(res.adapter.sensors),
        "mse": {t: v["mse"] for t, v in rep["targets"].items()},  # the online trace, as before per target
        "targets": rep["targets"],
        "mean": rep["mean"],
        "final_params": rep["final_params"],
        "final_params_open_loop": final.as_dict(),
        "adapt_step_median_s": rep["adapt_step_median_s"],
        "decisions": [d.as_dict() for d in rep["decisions"] if d.triggered],
    })
    if args.json:
        print(json.dumps(out, indent=2, default=float))
        return 0
    print(f"{model.name} on {args.run}: {len(rec)} samples, online adaptation from {', '.join(out['adapted_from'])}")
    print("mse: the online trace (each period predicted open loop from the observer's state); fixed: the same, "
          "parameters never changed; observer: its live estimate; coverage: readings inside its 95 % band")
    print(f"{'target':<18}{'seen':>5}{'mse K²':>9}{'fixed K²':>10}{'observer K²':>13}{'coverage':>10}")
    for s, v in rep["targets"].items():
        print(f"{s:<18}{'yes' if v['seen'] else 'no':>5}{v['mse']:>9.3f}{v['fixed_mse']:>10.3f}"
              f"{v['observer_mse']:>13.3f}{v['band_coverage']:>10.3f}")
    m = rep["mean"]
    print(f"{'mean':<18}{'':>5}{m['mse']:>9.3f}{m['fixed_mse']:>10.3f}{m['observer_mse']:>13.3f}")
    ds = out["decisions"]
    print(f"{len(ds)} decisions, {sum(1 for d in ds if d['accepted'])} challengers promoted; "  # type: ignore[union-attr]
          f"median adaptation step {rep['adapt_step_median_s']:.3f} s; final parameters: "
          + ", ".join(f"{k}={v:.4g}" for k, v in rep["final_params"].items()))
    return 0
