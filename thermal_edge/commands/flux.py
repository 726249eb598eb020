"""``thermal-edge flux``: commission the magnet-temperature estimate from the inverter's dq
voltages on a recorded run with a measured magnet temperature, and score a commissioned estimate
on another run.

``flux calibrate RUN --out FLUX.json`` fits the electrical parameters (``R_s`` at 20 °C, the
inverter's voltage error, ``ψ_PM`` and its temperature coefficient, ``L_d`` and ``L_q`` over the
current) and the variance table, and prints them with the region where the estimate is
informative. ``flux score FLUX.json RUN`` prints the estimate's error on a run where it is
informative.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from ..data import FORMATS, read_run
from ..errors import UsageError
from ..estimation.flux import PARAMS, UNITS, Electrical, FluxError, FluxModel, fit_flux_model
from ..lptn import Role
from ..text_table import table
from .options import integer, number, output_file

COLUMNS = {"u_d": "u_d_v", "u_q": "u_q_v", "current_d": Role.CURRENT_D.default_column, "current_q": Role.CURRENT_Q.default_column,
           "speed": Role.SPEED.default_column, "winding": "stator_winding"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("flux", help="commission the magnet-temperature estimate from the inverter's voltages",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    which = p.add_subparsers(dest="flux", required=True, metavar="ACTION")
    c = which.add_parser("calibrate", help="fit the electrical parameters and the variance table on a recorded run")
    c.add_argument("run", help="recorded run (CSV) with dq voltages and currents, speed, winding and magnet temperature")
    c.add_argument("--out", required=True, type=output_file, help="write the commissioned estimate here (JSON)")
    c.add_argument("--pole-pairs", type=integer(1, 100), required=True, help="pole pairs of the machine")
    c.add_argument("--prior", action="append", default=[], metavar="NAME=MEAN,SIGMA",
                   help=f"a parameter's prior ({', '.join(f'{k} [{UNITS[k]}]' for k in PARAMS)}); repeatable")
    c.add_argument("--minutes", type=number(0, lo_open=True, unit="min"), default=None,
                   help="use only the run's first MIN minutes")
    c.add_argument("--speed-min", type=number(0, 20000, unit="rpm"), default=500.0,
                   help="samples slower than this are not used (rpm, default 500)")
    _common(c)
    s = which.add_parser("score", help="the commissioned estimate's error on a run (where informative)")
    s.add_argument("flux_file", help="a file written by flux calibrate")
    s.add_argument("run", help="recorded run (CSV) with the same columns")
    s.add_argument("--from-minute", type=number(0, unit="min"), default=0.0, help="score from this minute on (default 0)")
    _common(s)
    p.set_defaults(func=main)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--format", choices=FORMATS, default="csv", help="run format (default csv; paderborn for the data set)")
    p.add_argument("--magnet-column", default="pm", help="measured magnet temperature column (default pm)")
    for k, v in COLUMNS.items():
        p.add_argument(f"--{k.replace('_', '-')}-column", default=v, help=f"column of {k} (default {v})")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _priors(items: list[str]) -> dict[str, tuple[float, float]]:
    out = {}
    for it in items:
        name, _, val = it.partition("=")
        parts = val.split(",")
        try:
            mean, sigma = float(parts[0]), float(parts[1])
        except (ValueError, IndexError):
            raise UsageError(f"--prior {it}: expected NAME=MEAN,SIGMA (e.g. r20=0.015,0.005)") from None
        if name not in PARAMS:
            raise UsageError(f"--prior {it}: unknown parameter {name!r} (known: {', '.join(PARAMS)})")
        if not (math.isfinite(mean) and math.isfinite(sigma) and sigma > 0):
            raise UsageError(f"--prior {it}: MEAN finite and SIGMA > 0")
        out[name] = (mean, sigma)
    return out


def _electrical(args: argparse.Namespace, columns: dict[str, np.ndarray]) -> Electrical:
    try:
        return Electrical.of(columns, *(getattr(args, f"{k}_column") for k in COLUMNS))
    except FluxError as exc:  # a missing column: name the run it is missing from
        raise FluxError(f"{args.run}: {exc}") from None


def main(args: argparse.Namespace) -> int:
    run = read_run(args.run, args.format)
    if args.magnet_column not in run.columns:
        raise FluxError(f"{args.run}: no magnet temperature column {args.magnet_column!r}")
    e = _electrical(args, run.columns)
    tm = run.columns[args.magnet_column]
    if args.flux == "calibrate":
        n = len(run) if args.minutes is None else int(round(args.minutes * 60.0 / run.dt))
        if n < 2:
            raise UsageError(f"--minutes {args.minutes:g}: fewer than two samples")
        head = Electrical(*(np.asarray(a)[:n] for a in (e.u_d, e.u_q, e.i_d, e.i_q, e.speed_rpm, e.winding_c)))
        m = fit_flux_model(head, tm[:n], args.pole_pairs, run.dt, priors=_priors(args.prior), speed_min_rpm=args.speed_min)
        Path(args.out).write_text(json.dumps(m.as_dict(), indent=1) + "\n")
        speed = float(np.median(np.abs(e.speed_rpm[:n][np.abs(e.speed_rpm[:n]) >= args.speed_min])))
        if args.json:
            print(json.dumps({**m.as_dict(), "tempco_pct_per_k": 100.0 * m.tempco_per_k,
                              "sigma_table_k": m.sigma_table(speed)}, indent=2))
            return 0
        print(f"{args.run}: {int(m.fit_info['samples'])} steady samples at {args.speed_min:g} rpm and up; "
              f"written to {args.out}")
        print(table(["parameter", "value", "posterior sigma", "unit"],
                    [[k, f"{m.params[k]:.6g}", f"{m.sigma[k]:.3g}", UNITS[k]] for k in PARAMS]))
        print(f"magnet temperature coefficient of the flux linkage: {100.0 * m.tempco_per_k:+.3f} %/K")
        sig = ", ".join(f"{k} {v:.2f} K" for k, v in m.sigma_table(speed).items())
        print(f"informative from {m.speed_min_rpm:.0f} rpm, at these currents only (sigma at {speed:.0f} rpm): {sig}; "
              f"errors correlated over {m.tau_s:.0f} s")
        return 0
    try:
        m = FluxModel.from_dict(json.loads(Path(args.flux_file).read_text(encoding="utf-8")))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, FluxError, TypeError, ValueError, AttributeError) as exc:
        # a file of another program, or edited by hand: its entries are the user's input
        raise UsageError(f"{args.flux_file}: not a file written by flux calibrate ({exc})") from None
    T, s, ok = m.estimate(e)
    ok &= (run.t - run.t[0]) >= args.from_minute * 60.0
    ok &= np.isfinite(tm)
    err = T[ok] - tm[ok]
    r = {"informative_share": float(ok.mean()), "rms_k": float(np.sqrt(np.mean(err**2))) if ok.any() else float("nan"),
         "coverage": float(np.mean(np.abs(err) <= 1.96 * s[ok])) if ok.any() else float("nan")}
    if args.json:
        print(json.dumps(r))
        return 0
    print(f"{args.run}: informative on {100 * r['informative_share']:.0f} % of the samples; there RMS "
          f"{r['rms_k']:.2f} K, 95 % band covers {100 * r['coverage']:.0f} %")
    return 0
