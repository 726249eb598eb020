"""``thermal-edge replay``: run the model over a recorded run and score every sensor.

Open loop (``--no-adapt``, the default) predicts the whole run from its measured initial state.
With ``--adapt`` the observer and the online adapter run over the run as the service would,
learning only from ``--sensors``, and every sensor in the file is scored (the unseen ones too):
the online trace, the same with the parameters fixed, the observer and its 95 % band coverage.
``--set NAME=VALUE`` replaces a parameter's value (within the model's bounds) before anything runs.
A CSV run is checked and summarised (sample period, duration, columns used and ignored, ranges)
before the model runs. ``--plot FILE.png`` draws measured against predicted against the
observer's 95 % band per sensor, speed and current below, adaptation decisions marked (needs
matplotlib: the ``report`` extra); ``--out FILE.csv|.parquet`` writes the same per sample
(Parquet needs pyarrow).
A CAN log (``--format can``; old name ``candump``: ``.log`` candump -L, ``.asc``, ``.blf``,
``.trc``, ``.mf4``, ``.csv``, by suffix) goes through the service's own pipeline with the service
configuration ``--config`` (frame timestamps as the clock, the service's observer and adapter) and
is summarised; ``--plot`` draws the service's estimates per tick (its observer's 95 % band, its
open-loop prediction, the readings; the current limit it sent below) and ``--out`` writes them,
with the inputs, the limit, the state and the derating reason of every tick. The model's inputs
and readings alone, as a run CSV: ``thermal-edge export``.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..data import FORMATS, Run, RunError, write_run
from ..errors import UsageError
from ..estimation.adapter import AdapterConfig
from ..estimation.online import OnlineResult, online_report, run_online
from ..estimation.predict import Scores, open_loop
from ..estimation.uncertainty import Z95
from ..lptn import Model
from ..lptn.vocabulary import Role
from ..plots import missing
from ..service.flux_input import OUTCOMES
from ..service.replay import ReplayResult, format_summary, replay_log, summarise
from ..shipped import config_path
from .common import add_model_args, add_set_arg, model_from_args, model_with_sets, parse_sets, split_sets
from .options import integer, kelvin, names, output_file, positive_s
from .progress import bar
from .runs import read_checked, require_finite, require_finite_prediction

#: ``--out`` suffixes and the module each needs (None: none beyond the core).
EXPORTS = {".csv": None, ".parquet": "pyarrow"}
#: ``--plot`` suffixes matplotlib writes.
PLOTS = (".png", ".svg", ".pdf")


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("replay", help="replay a recorded run through the model", description=__doc__)
    add_model_args(p, required=False, discretisation=True)
    p.add_argument("--run", required=True, help="recorded run, or a CAN log with --format can")
    p.add_argument("--format", default="csv", choices=(*FORMATS, "can", "candump"),
                   help="run file format (default csv); can (old name: candump): a CAN log of any format by its suffix")
    p.add_argument("--config", default=str(config_path("edge.yaml")),
                   help="can: the service configuration to replay with (default: the packaged example)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--no-adapt", dest="adapt", action="store_false", help="open-loop prediction (default)")
    mode.add_argument("--adapt", dest="adapt", action="store_true", help="run the online adapter over the run")
    p.add_argument("--sensors", type=names,
                   help="with --adapt: comma-separated sensors the adapter may learn from (default: all)")
    p.add_argument("--period", type=positive_s, default=AdapterConfig.period_s, help="with --adapt: adaptation period, s")
    p.add_argument("--threshold", type=kelvin, default=AdapterConfig.threshold_k,
                   help="with --adapt: adaptation threshold, K RMS")
    p.add_argument("--decimate", type=integer(1), default=AdapterConfig.decimate, help="with --adapt: samples per optimiser step")
    p.add_argument("--plot", type=output_file, metavar="FILE.png",
                   help="figure: measured, predicted and the observer's band per sensor")
    p.add_argument("--out", type=output_file, metavar="FILE.csv",
                   help="per-sample (can: per-tick) estimates, predictions and bands (.csv or .parquet)")
    add_set_arg(p)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run, adapt=False)


def _check_outputs(args: argparse.Namespace) -> str | None:
    """One line if ``--plot``/``--out`` cannot be written (suffix, missing extra), checked before any work."""
    if args.plot:
        if Path(args.plot).suffix.lower() not in PLOTS:
            return f"--plot {args.plot}: the suffix must be one of {', '.join(PLOTS)}"
        if (why := missing("matplotlib")):
            return f"--plot: {why}"
    if args.out:
        suffix = Path(args.out).suffix.lower()
        if suffix not in EXPORTS:
            return f"--out {args.out}: the suffix must be one of {', '.join(EXPORTS)}"
        if (extra := EXPORTS[suffix]) and (why := missing(extra)):
            return f"--out {args.out}: {why}"
    return None


#: options of the model run over a CSV run, with their defaults: a CAN log is replayed by the
#: service itself, whose observer and adapter the configuration sets (``observer:``, ``adaptation:``)
CSV_ONLY = {"adapt": False, "sensors": None, "period": AdapterConfig.period_s, "threshold": AdapterConfig.threshold_k,
            "decimate": AdapterConfig.decimate, "method": None, "max_substep": None, "data_dir": None}


def _refuse_csv_options(args: argparse.Namespace) -> None:
    """A CAN log is replayed as the service runs: an option of the CSV replay given with it would
    be ignored without a word, so it is refused."""
    given = [k for k, default in CSV_ONLY.items() if getattr(args, k, default) != default]
    if given:
        opt = "--" + given[0].replace("_", "-")
        raise UsageError(f"{opt}: not for a CAN log (--format can): the service replays it as its configuration "
                         f"{args.config} says (adaptation: and observer:); {opt} is for a CSV run")


#: options of the online adapter, with their defaults: without ``--adapt`` no adapter runs
ADAPT_ONLY = {"sensors": None, "threshold": AdapterConfig.threshold_k, "decimate": AdapterConfig.decimate,
              "period": AdapterConfig.period_s}


def _refuse_adapter_options(args: argparse.Namespace) -> None:
    """An adapter's option given to an open-loop replay of a CSV run would be ignored without a
    word, so it is refused."""
    given = [k for k, default in ADAPT_ONLY.items() if getattr(args, k) != default]
    if given:
        raise UsageError(f"--{given[0]}: only with --adapt (the open-loop replay runs no adapter)")


def run(args: argparse.Namespace) -> int:
    if (why := _check_outputs(args)):
        print(f"thermal-edge replay: error: {why}", file=sys.stderr)
        return 2
    if args.format in ("can", "candump"):
        _refuse_csv_options(args)
        ticks = bool(args.plot or args.out)  # the summary alone keeps nothing per tick: memory flat in the log's length
        replayed, service_model = replay_log(args.run, args.config, args.model, sets=split_sets(args.set),
                                             keep_outputs=ticks, per_tick=ticks)
        summary = summarise(args.run, replayed, service_model)
        if (args.plot or args.out) and replayed.totals.ticks < 2:
            raise RunError(f"{args.run}: {replayed.totals.ticks} ticks: nothing to plot or write")
        print(json.dumps(summary, indent=2, default=float) if args.json else format_summary(summary))
        if args.plot or args.out:
            _service_outputs(args, service_model, replayed)
        return 0
    if not args.model:
        raise UsageError("--model is required for CSV runs")
    if not args.adapt:
        _refuse_adapter_options(args)
    model = model_with_sets(model_from_args(args), args.set)
    sensors = tuple(s.strip() for s in args.sensors.split(",") if s.strip()) if args.sensors else None
    rec, data = read_checked(args.run, args.format, model, sensors if args.adapt else None)
    out: dict[str, Any] = {"model": model.name, "run": args.run, "samples": len(rec), "adapt": bool(args.adapt),
                           "data": data}
    if not args.json:
        print(data)
    if args.set:
        out["set"] = parse_sets(model, args.set)
    cfg = AdapterConfig(period_s=args.period, threshold_k=args.threshold, decimate=args.decimate, sensors=sensors)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # refused below, by node and sample
        if not args.adapt:
            traj, scores = open_loop(model, rec, method=args.method, max_substep=args.max_substep)
            require_finite(model, rec, traj.T, "the open-loop prediction")
            if args.plot or args.out:
                with bar(len(rec), "replay: observer", "sample") as pb:
                    obs = run_online(model, rec, replace(cfg, threshold_k=np.inf), progress=pb.update)
                _outputs(args, model, rec, traj.T, obs)
            return _print_open_loop(args, model, rec, scores, out)
        require_finite_prediction(model, rec)  # the adapter's fits would fail on it without saying why
        with bar(2 * len(rec), "replay: fixed, then adapting", "sample") as pb:
            rep = online_report(model, rec, cfg, progress=pb.update)
        res = rep["result"]
        require_finite(model, rec, res.T, "the online trace")
        require_finite(model, rec, res.estimate, "the observer's estimate")
        _, final = open_loop(model, rec, theta=res.theta, method=args.method, max_substep=args.max_substep)
        if args.plot or args.out:
            _outputs(args, model, rec, res.T, res)
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
          "parameters never changed; observer: its live estimate; coverage: readings inside its 95 % band (the node "
          "temperature's band: a reading's own noise is not in it, so a measured sensor's coverage can be below 0.95)")
    print(f"{'target':<18}{'seen':>5}{'mse K²':>9}{'fixed K²':>10}{'observer K²':>13}{'coverage':>10}")
    for s, v in rep["targets"].items():
        print(f"{s:<18}{'yes' if v['seen'] else 'no':>5}{v['mse']:>9.3f}{v['fixed_mse']:>10.3f}"
              f"{v['observer_mse']:>13.3f}{v['band_coverage']:>10.3f}")
    m = rep["mean"]
    print(f"{'mean':<18}{'':>5}{m['mse']:>9.3f}{m['fixed_mse']:>10.3f}{m['observer_mse']:>13.3f}")
    ds = out["decisions"]
    print(f"{len(ds)} decisions, {sum(1 for d in ds if d['accepted'])} challengers promoted; "
          + (f"median adaptation step {rep['adapt_step_median_s']:.3f} s; " if math.isfinite(rep["adapt_step_median_s"])
             else "no adaptation step ran; ")
          + "final parameters: "
          + ", ".join(f"{k}={v:.4g}" for k, v in rep["final_params"].items()))
    return 0


def _print_open_loop(args: argparse.Namespace, model: Model, rec: Run, scores: Scores, out: dict[str, Any]) -> int:
    out.update(scores.as_dict())
    if args.json:
        print(json.dumps(out, indent=2, default=float))
        return 0
    print(f"{model.name} on {args.run}: {len(rec)} samples, open loop")
    print(f"{'sensor':<18}{'MSE K²':>10}{'RMS K':>10}{'max |e| K':>11}")
    for s in scores.mse:
        if math.isfinite(scores.mse[s]):
            print(f"{s:<18}{scores.mse[s]:>10.3f}{scores.rms[s]:>10.3f}{scores.max_abs[s]:>11.3f}")
        else:  # a column with no reading: nothing to compare the prediction with
            print(f"{s:<18}{'not measured':>31}")
    mean = scores.mean_mse
    print(f"{'mean':<18}{mean:>10.3f}" if math.isfinite(mean) else f"{'mean':<18}{'no sensor measured':>31}")
    return 0


def per_sample(model: Model, rec: Run, predicted: np.ndarray, obs: OnlineResult) -> dict[str, np.ndarray]:
    """The per-sample table of ``--out``: the model's inputs as recorded; per sensor in the run
    ``<s>_measured``, ``<s>_predicted``, ``<s>_observer``, ``<s>_band_low``, ``<s>_band_high``
    (degC, the band the observer's 95 % interval); the same but measured for each limited node
    (``<limit>_…``); ``adaptation`` (0 no decision, 1 a triggered decision, 2 a promoted
    challenger) and, with ``--adapt``, each adaptable parameter's value in use (``param_<name>``).

    Parameters
    ----------
    predicted : ndarray (N, n)
        The prediction scored (open loop, or the online trace with ``--adapt``), degC.
    obs : OnlineResult
        The observer run over the same samples (its ``estimate`` and ``sigma``).
    """
    cols: dict[str, np.ndarray] = {c: rec.columns[c] for c in model.inputs}

    def node(prefix: str, i: int) -> None:
        half = Z95 * obs.sigma[:, i]
        cols[f"{prefix}_predicted"] = predicted[:, i]
        cols[f"{prefix}_observer"] = obs.estimate[:, i]
        cols[f"{prefix}_band_low"] = obs.estimate[:, i] - half
        cols[f"{prefix}_band_high"] = obs.estimate[:, i] + half

    for s, n in model.sensors.items():
        if s in rec.columns:
            cols[f"{s}_measured"] = rec.columns[s]
            node(s, model.node_index(n))
    for lim in model.limits:
        node(lim.name, model.node_index(lim.node))
    flag = np.zeros(len(rec))
    for d in obs.decisions:
        if d.triggered:
            flag[int(np.searchsorted(rec.t, d.t))] = 2.0 if d.accepted else 1.0
    cols["adaptation"] = flag
    if np.isfinite(obs.adapter.config.threshold_k):
        cols.update({f"param_{p}": v for p, v in obs.param_trace.items()})
    return cols


def _outputs(args: argparse.Namespace, model: Model, rec: Run, predicted: np.ndarray, obs: OnlineResult) -> None:
    cols = per_sample(model, rec, predicted, obs)
    if args.out:
        if Path(args.out).suffix.lower() == ".parquet":
            import pyarrow as pa
            import pyarrow.parquet as pq

            pq.write_table(pa.table({"t": rec.t, **cols}), args.out)
        else:
            write_run(args.out, Run(rec.t, cols, args.out),
                      comment=f"thermal-edge replay of {args.run} with model {model.name}")
        print(f"wrote {args.out}: {len(rec)} samples, {len(cols) + 1} columns", file=sys.stderr)
    if args.plot:
        from ..plots.replay import replay_figure

        sensors = {s: {k: cols[f"{s}_{k}"] for k in ("measured", "predicted", "observer", "band_low", "band_high")}
                   for s in model.sensors if f"{s}_measured" in cols}
        speed, current = model.find_input(Role.SPEED), model.find_input(Role.CURRENT)
        mode = "online adaptation" if args.adapt else "open loop"
        replay_figure(args.plot, f"{model.name} on {Path(args.run).name}, {mode}", rec.t, sensors,
                      rec.columns[speed] if speed else None, rec.columns[current] if current else None,
                      [(d.t, d.accepted) for d in obs.decisions if d.triggered])
        print(f"wrote {args.plot}", file=sys.stderr)


def per_tick(model: Model, res: ReplayResult) -> dict[str, np.ndarray]:
    """The per-tick table of ``replay --format can --out``: what the service computed each tick.

    The model's inputs as the tick accumulated them; per sensor ``<s>_measured`` (the reading the
    tick used, NaN if none), ``<s>_predicted`` (the service's open-loop prediction),
    ``<s>_observer`` (its observer's estimate) and ``<s>_band_low``/``<s>_band_high`` (the
    observer's 95 % interval), degC; the same but measured for each limited node (``<limit>_…``),
    whose band is the observer's at ``derating.band_z`` and which also gets ``<limit>_upper``: the
    upper band the tick derated on and sent (:class:`.derating.NodeBand` ``upper_c``, in
    ``TE_T_HotSpotUpper``/``TE_T_MagnetUpper`` for the transmitted nodes; the readings of a sensor
    that bounds the node from below where they are above ``_band_high``); ``current_limit_a`` (the
    limit sent, A rms), ``state`` and ``reason`` (the codes of ``TE_State`` and the derating
    reason, DBC value tables); ``adaptation`` (0 no decision, 1 a triggered decision, 2 accepted
    parameters). With the voltage input (``flux.calibration``): ``flux_outcome`` (the index of the
    tick's outcome in :data:`.flux_input.OUTCOMES`: 0 used, 1 disagreement, 2 stale, 3 implausible,
    4 uninformative, 5 transient, 6 low_speed; NaN for a tick without an estimate), ``flux_magnet``
    (the magnet temperature the voltages imply, degC) and ``flux_sigma`` (its σ, K; inf where
    uninformative).

    Parameters
    ----------
    model : Model
        The model the service ran.
    res : ReplayResult
        A replay with its outputs kept.
    """
    outs = res.outputs
    cols: dict[str, np.ndarray] = {c: np.array([o.inputs.get(c, np.nan) for o in outs]) for c in model.inputs}

    def node(prefix: str, i: int) -> None:
        half = Z95 * res.sigma[:, i]
        cols[f"{prefix}_predicted"] = res.prediction[:, i]
        cols[f"{prefix}_observer"] = res.estimate[:, i]
        cols[f"{prefix}_band_low"] = res.estimate[:, i] - half
        cols[f"{prefix}_band_high"] = res.estimate[:, i] + half

    for s, n in model.sensors.items():
        if any(s in o.measured for o in outs):
            cols[f"{s}_measured"] = np.array([o.measured.get(s, np.nan) for o in outs])
            node(s, model.node_index(n))
    for lim in model.limits:
        node(lim.name, model.node_index(lim.node))
        # the tick's own band (the service's z, the bounding sensors' floor), not one derived here
        bands = [next((b for b in o.bands if b.name == lim.name), None) for o in outs]
        cols[f"{lim.name}_band_low"] = np.array([b.observer_lower_c if b else np.nan for b in bands])
        cols[f"{lim.name}_band_high"] = np.array([b.observer_upper_c if b else np.nan for b in bands])
        cols[f"{lim.name}_upper"] = np.array([b.upper_c if b else np.nan for b in bands])
    cols["current_limit_a"] = np.asarray(res.current_limit_a, dtype=float)
    cols["state"] = np.asarray(res.state, dtype=float)
    cols["reason"] = np.asarray(res.reason, dtype=float)
    flag = np.zeros(len(outs))
    for d in res.decisions:
        if d.get("triggered"):
            k = min(int(np.searchsorted(res.t, float(d["t"]))), len(outs) - 1)
            flag[k] = 2.0 if d.get("accepted") else 1.0
    cols["adaptation"] = flag
    if res.flux is not None:
        ticks = [o.flux for o in outs]
        cols["flux_outcome"] = np.array([OUTCOMES.index(f.outcome) if f else np.nan for f in ticks])
        cols["flux_magnet"] = np.array([f.estimate_c if f else np.nan for f in ticks])
        cols["flux_sigma"] = np.array([f.sigma_k if f else np.nan for f in ticks])
    return cols


def _service_outputs(args: argparse.Namespace, model: Model, res: ReplayResult) -> None:
    """``--out`` and ``--plot`` of a CAN log's replay: the service's ticks, time from the first tick."""
    cols = per_tick(model, res)
    t = res.t - res.t[0]
    if args.out:
        if Path(args.out).suffix.lower() == ".parquet":
            import pyarrow as pa
            import pyarrow.parquet as pq

            pq.write_table(pa.table({"t": t, **cols}), args.out)
        else:
            write_run(args.out, Run(t, cols, args.out),
                      comment=f"thermal-edge replay of the CAN log {args.run} with model {model.name} and "
                              f"{args.config}\nt: s from the first tick at {res.t[0]:.6f} s since the epoch")
        print(f"wrote {args.out}: {len(t)} ticks, {len(cols) + 1} columns", file=sys.stderr)
    if args.plot:
        from ..plots.replay import replay_figure

        sensors = {s: {k: cols[f"{s}_{k}"] for k in ("measured", "predicted", "observer", "band_low", "band_high")}
                   for s in model.sensors if f"{s}_measured" in cols}
        speed, current = model.find_input(Role.SPEED), model.find_input(Role.CURRENT)
        decisions = [(float(d["t"]) - res.t[0], bool(d.get("accepted"))) for d in res.decisions if d.get("triggered")]
        replay_figure(args.plot, f"{model.name} on {Path(args.run).name}, the service's replay", t, sensors,
                      cols[speed] if speed else None, cols[current] if current else None, decisions)
        print(f"wrote {args.plot}", file=sys.stderr)
