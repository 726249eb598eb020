"""``thermal-edge discover``: find the physical effect a model lacks, add it, show the gap shrink.

Refits the model's adaptable parameters on the first 2/3 of the run, analyses the residuals
against the operating conditions, scores every catalogue effect on every applicable target
(score test), fits the best few, ranks them on the held-out last third, adds the winner and
repeats until no candidate improves the held-out gap significantly. With ``--out DIR`` it writes
``DIR/report.md`` (Markdown with PNG figures; needs matplotlib, the ``report`` extra) and the
augmented model ``DIR/<model>+<effect>.yaml``. The effect catalogue: ``--list-effects``.
A CAN log (``--format can``, any format python-can reads) is read through the service's own
pipeline with the service configuration ``--config``: one sample per tick, as the service saw it.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from ..data import FORMATS, RunError
from ..errors import UsageError
from ..plots import missing
from .common import add_set_arg, parse_sets
from .options import integer, kelvin, names, number, output_dir, output_file, positive_s
from .runs import CAN_FORMAT, add_can_args, read_checked_runs, require_finite_prediction


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("discover", help="find, name and add the physical effect a model lacks", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True, help="machine model: a file, or the name of a packaged one (pm10kw, paderborn4)")
    p.add_argument("--data-dir", help="directory of the model's table files (overrides the model's data_dir)")
    p.add_argument("--run", help="recorded run (CSV), or a CAN log with --format can")
    add_can_args(p, FORMATS)
    p.add_argument("--sensors", type=names, help="comma-separated sensors to use (default: every model sensor the run has)")
    p.add_argument("--out", type=output_dir, help="directory for report.md, its figures and the augmented model")
    p.add_argument("--model-out", type=output_file, help="path of the augmented model (default DIR/<model>+<effect>.yaml)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--effects", type=names, help="comma-separated catalogue effects to consider (default: all)")
    p.add_argument("--max-rounds", type=integer(1), default=3, help="effects added at most (default 3)")
    p.add_argument("--min-improvement", type=number(0, 1, hi_open=True), default=0.10,
                   help="relative held-out gap reduction a candidate must reach (default 0.10)")
    p.add_argument("--min-gain", type=kelvin, default=0.05, help="and absolute reduction, K (default 0.05)")
    p.add_argument("--train-fraction", type=number(0, 1, lo_open=True, hi_open=True), default=2 / 3,
                   help="fitted share of the run (default 2/3)")
    p.add_argument("--fit-step", type=positive_s, default=5.0, help="step of the decimated fitting window, s (default 5)")
    p.add_argument("--no-report", action="store_true", help="with --out: write the model only, no report")
    p.add_argument("--list-effects", action="store_true", help="list the effect catalogue and the model's targets")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_set_arg(p)
    p.set_defaults(func=run)


def list_effects(args: argparse.Namespace) -> int:
    from ..discovery import effects as E
    from ..discovery import hidden

    raw = hidden.read_document(args.model)
    build = hidden.builder(args.model, args.data_dir)
    ctx = E.context(raw, build(raw), None, build)
    for name, eff in E.CATALOGUE.items():
        tg = E.targets(ctx, eff)
        params = ", ".join(f"{p.short} [{p.unit}] default {p.default:g}" + ("" if p.primary else " (shape)") for p in eff.params)
        if not tg:
            where = f"not placeable: {E.unplaceable_reason(ctx, eff)}"
        elif tg == [None]:
            where = E.placement(ctx, eff) or "needs no target"
        else:
            where = f"{len(tg)} targets: " + ", ".join(map(str, tg))
        print(f"{name}: {eff.doc}\n    parameters: {params}\n    {where}")
    return 0


def _run_header(path: str) -> list[str]:
    """The comment lines at the top of a run CSV (how it was made), as shell comments."""
    out = []
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:  # a Windows-1252 run too
            for line in fh:
                if not line.startswith("#"):
                    break
                out.append("# " + line[1:].strip())
    except OSError:
        return []
    return (["# the run (its header):"] + out) if out else []


def run(args: argparse.Namespace) -> int:
    if args.list_effects:
        return list_effects(args)
    if not args.run:
        raise UsageError("--run is required (or --list-effects)")
    if args.out and not args.no_report and (why := missing("matplotlib")):  # before the work, not after it
        raise UsageError(f"--out {args.out}: the report {why.removeprefix('this ')}; or --no-report for the model alone")
    from ..discovery import effects as E
    from ..discovery import hidden, workflow

    raw = hidden.read_document(args.model)
    build = hidden.builder(args.model, args.data_dir)
    for k, v in parse_sets(build(raw), args.set).items():  # as if the model file said so
        raw["parameters"][k]["value"] = v
    sensors = [s.strip() for s in args.sensors.split(",") if s.strip()] if args.sensors else None
    model = build(raw)
    got = read_checked_runs(args.run, args.format, model, sensors, args.config)
    if len(got) > 1:
        raise RunError(f"{args.run}: {len(got)} runs (stretches of traffic between silences), discover takes one: "
                       "write them to run CSVs with thermal-edge export and give it one")
    ((rec, summary),) = got
    require_finite_prediction(model, rec)
    if not args.json:
        print(summary, flush=True)
    opt = workflow.Options(
        sensors=sensors,
        effects=[e.strip() for e in args.effects.split(",") if e.strip()] if args.effects else None,
        max_rounds=args.max_rounds, min_improvement=args.min_improvement, min_gain_k=args.min_gain,
        train_frac=args.train_fraction, fit_step_s=args.fit_step,
    )
    for e in opt.effects or ():
        E.get(e)
    log = None if (args.quiet or args.json) else (lambda m: print(m, file=sys.stderr, flush=True))
    disc = workflow.discover(raw, rec, build, opt, log=log)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        if disc.added:
            stem = Path(args.model).stem
            tag = "+".join(r.fit.label.replace(":", "-") for r in disc.added)
            disc.model_out = workflow.write_model(disc, args.model_out or out / f"{stem}+{tag}.yaml", args.model)
        if not args.no_report:
            from ..discovery import report

            cmd = ["thermal-edge", "discover", "--model", args.model, "--run", args.run]
            if args.format != "csv":
                cmd += ["--format", args.format]
            if args.format == CAN_FORMAT:
                cmd += ["--config", args.config]
            if args.sensors:
                cmd += ["--sensors", args.sensors]
            cmd += ["--out", args.out]
            header = _run_header(args.run) if args.format != CAN_FORMAT else []  # a CAN log has no comment lines
            disc.report = report.write(disc, out, header + [shlex.join(cmd)])
    elif args.model_out and disc.added:
        disc.model_out = workflow.write_model(disc, args.model_out, args.model)
    d = disc.as_dict()
    if args.json:
        print(json.dumps(d, indent=2, default=float))
        return 0
    print(f"{disc.model_name} on {args.run}: {d['verdict']}")
    print(f"held-out gap over {', '.join(disc.data.sensors)}: {disc.gap_before:.3f} K -> {disc.gap_after:.3f} K"
          f" (nominal parameters {disc.nominal.gap:.3f} K, noise floor {disc.noise_k:.3f} K), {disc.wall_s:.1f} s")
    print(f"{'sensor':<18}{'before K':>10}{'after K':>10}")
    for s in disc.data.sensors:
        print(f"{s:<18}{d['per_sensor_before'][s]:>10.3f}{d['per_sensor_after'][s]:>10.3f}")
    for r in disc.added:
        vals = ", ".join(f"{k} = {v:.4g}" for k, v in disc.final.values(r.fit.effect_params).items())
        print(f"added {r.fit.label}: {vals}")
    cmp = d["comparison"]
    if cmp:
        print(f"runner-up {cmp['runner_up']}: held-out gap {cmp['gap_runner_up_k']:.3f} K against {cmp['gap_winner_k']:.3f} K"
              f" (difference {cmp['gap_runner_up_k'] - cmp['gap_winner_k']:+.3f} ± {cmp['se_diff_k']:.3f} K)"
              + ("; this run cannot separate them" if cmp["ambiguous"] else "")
              + (f"; decided by held-out data at {cmp['decided_by']}" if cmp["decided_by"] else ""))
        if cmp["separating_condition"]:
            sep = cmp["separating_condition"]
            print(f"separating condition: {sep['point']} ({sep['sensor']}: {sep['winner_c']:.1f} vs {sep['runner_up_c']:.1f} °C)")
            if not sep["sensors_separate"] and sep["node_separates"]:
                print(f"  no sensor of this run separates them there ({sep['diff_k']:.2f} K apart); a sensor on "
                      f"{sep['node']} would ({sep['node_winner_c']:.1f} vs {sep['node_runner_up_c']:.1f} °C)")
    no_gap = disc.gap is not None and disc.gap.status == "none"
    if disc.signature is not None and not no_gap:  # the shape of noise is no trend to act on
        print(f"the residual {disc.signature.describe()} (held-out, reading - model)")
    for n in disc.not_placeable:
        fits = disc.signature is not None and disc.signature.fits(n.effect.explains)
        print(f"not placeable: {n.effect.name} ({n.reason})" + ("; it would fit the residual's signature" if fits else ""))
    g = d["gap_detail"]
    if g and g["worst_sensor"]:
        print(f"unexplained gap {g['gap_k']:.3f} K ({g['ratio']:.0f}x the noise floor), largest on {g['worst_sensor']}; "
              f"when: {g['when']}; nearest candidates: "
              + (", ".join(f"{n['effect']} ({n['heldout_gap_k']:.3f} K)" for n in g["nearest"]) or "none"))
    if disc.model_out:
        print(f"wrote {disc.model_out}")
    if disc.report:
        print(f"wrote {disc.report}")
    return 0
