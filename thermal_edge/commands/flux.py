"""``thermal-edge flux``: commission the magnet-temperature estimate from the inverter's dq
voltages on a recorded run with a measured magnet temperature, and score a commissioned estimate
on another run.

``flux calibrate RUN --out FLUX.json`` fits the electrical parameters (``R_s`` at 20 °C, the
inverter's voltage error, ``ψ_PM`` and its temperature coefficient, ``L_d`` and ``L_q`` over the
current) and the variance table, and prints them with the region where the estimate is
informative. It refuses a run whose voltages are plausible only in another unit and a fit the
service would refuse to read, and warns when the run cannot pin the temperature coefficient down.
``flux score FLUX.json RUN`` prints the estimate's error on a run where it is informative.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from ..data import FORMATS, Run, read_run
from ..errors import UsageError
from ..estimation.flux import PARAMS, UNITS, Electrical, FluxError, FluxModel, fit_flux_model, steady
from ..lptn import Model, ModelError, NodeRole, Role, load_model
from ..lptn.vocabulary import TEMPERATURE, OtherUnit, Plausible
from ..text_table import table
from .options import integer, number, output_file

COLUMNS = {"u_d": "u_d_v", "u_q": "u_q_v", "current_d": Role.CURRENT_D.default_column, "current_q": Role.CURRENT_Q.default_column,
           "speed": Role.SPEED.default_column, "winding": "stator_winding"}
#: The magnitude ``|u|`` of the dq voltages a PM machine runs at when turning at speed, V peak (95th
#: percentile of the run's samples used): from a small drive's volt to a medium-voltage machine's kV.
VOLTAGE = Plausible("V", 1.0, 5000.0, (OtherUnit("kV", 1e3), OtherUnit("mV", 1e-3)), what="dq voltage magnitude")
#: The electrical power of the dq quantities (``1.5 (u_d i_d + u_q i_q)``, amplitude-invariant)
#: lies within this factor of the shaft power (torque x speed) on any machine and convention
#: (efficiency, RMS for peak); a unit error of the voltages is a factor 1000.
POWER_FACTOR_MAX = 30.0
#: The shaft power a sample needs for the power comparison, as a share of the run's 95th percentile.
POWER_SHARE_MIN = 0.2
#: A run whose magnet temperature spans less than this (5th to 95th percentile of the samples used),
#: K, cannot separate the temperature coefficient from the other parameters.
MAGNET_SPAN_MIN_K = 10.0
#: The temperature coefficient counts as identified when its σ (posterior, or the spread of the
#: forward cross-validation's fits, the larger) is at most this share of it.
BETA_REL_SIGMA_MAX = 0.3
HINT = ("are u_d and u_q swapped (--u-d-column, --u-q-column), or a voltage's or current's sign reversed, "
        "or --pole-pairs or --magnet-column wrong?")


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
    c.add_argument("--model", default=None,
                   help="the machine's model (a file, or a packaged name): a warning when --magnet-column is its "
                        "sensor on a node that is not a magnet (default: checked against the packaged models)")
    c.add_argument("--torque-column", default=Role.TORQUE.default_column,
                   help=f"shaft torque (Nm), when the run has it: the voltages' unit is checked against the shaft "
                        f"power (default {Role.TORQUE.default_column})")
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


#: the parameters that are positive whatever the machine (the others may take either sign)
POSITIVE = ("r20", "psi20", "ld0", "lq0")


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
        if name in POSITIVE and not mean > 0:  # a resistance, a flux linkage, an inductance
            raise UsageError(f"--prior {it}: {name} is positive ({UNITS[name]}), got a MEAN of {mean:g}")
        out[name] = (mean, sigma)
    return out


def _electrical(args: argparse.Namespace, columns: dict[str, np.ndarray]) -> Electrical:
    try:
        return Electrical.of(columns, *(getattr(args, f"{k}_column") for k in COLUMNS))
    except FluxError as exc:  # a missing column: name the run it is missing from
        raise FluxError(f"{args.run}: {exc}") from None


def load(path: str) -> FluxModel:
    """The flux model in the JSON file ``path``; :class:`FluxError` names the file and the entry."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FluxError(f"{path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from None
    if not text.strip():
        raise FluxError(f"{path}: empty, not a file written by flux calibrate")
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise FluxError(f"{path}: not a file written by flux calibrate (not JSON: {exc.msg}, line {exc.lineno})") from None
    try:
        return FluxModel.from_dict(d)
    except FluxError as exc:
        raise FluxError(f"{path}: {exc}") from None


def used_samples(e: Electrical, speed_min_rpm: float) -> np.ndarray:
    """Samples fast enough and steady, with finite voltages (those the fit speaks for)."""
    return (np.abs(e.speed_rpm) >= speed_min_rpm) & steady(e.speed_rpm) & np.isfinite(e.u_d) & np.isfinite(e.u_q)


def check_voltage_unit(e: Electrical, use: np.ndarray, torque_nm: np.ndarray | None, where: str) -> None:
    """Refuse voltages plausible only in another unit (:class:`FluxError` naming ``where``, the
    columns): their magnitude at speed against :data:`VOLTAGE`, and, with the shaft torque, the
    electrical power against the shaft power (within :data:`POWER_FACTOR_MAX`)."""
    if not use.any():
        return
    u = float(np.percentile(np.hypot(e.u_d[use], e.u_q[use]), 95.0))
    why = VOLTAGE.problem(u)
    if why is not None:
        raise FluxError(f"{where}: |u| at speed (95th percentile) {why}")
    if torque_nm is None:
        return
    p_el = 1.5 * (e.u_d * e.i_d + e.u_q * e.i_q)
    p_m = torque_nm * e.speed_rpm * (2.0 * np.pi / 60.0)
    ok = use & np.isfinite(p_el) & np.isfinite(p_m)
    if not ok.any():
        return
    big = ok & (np.abs(p_m) >= POWER_SHARE_MIN * np.percentile(np.abs(p_m[ok]), 95.0)) & (np.abs(p_m) > 0)
    if big.sum() < 10:
        return
    r = float(np.median(np.abs(p_el[big] / p_m[big])))
    if not 1.0 / POWER_FACTOR_MAX <= r <= POWER_FACTOR_MAX:
        unit = "kV" if r < 1.0 else "mV"
        raise FluxError(f"{where}: the electrical power 1.5 (u_d i_d + u_q i_q) is {r:.3g} times the shaft power "
                        f"(torque x speed): the voltages look like {unit}; give them in V")


def magnet_column_warning(column: str, model: Model | None) -> str | None:
    """Why ``column`` is unlikely to be the magnet's temperature: it is the sensor of a node whose
    role is not the magnet's in ``model`` (default: in the packaged models that load without
    external files), None when nothing says so."""
    from ..shipped import config_path, names

    models: list[Model] = [model] if model is not None else []
    if model is None:
        for name in names("machines"):
            try:
                models.append(load_model(config_path("machines", f"{name}.yaml")))
            except ModelError:  # a packaged model that needs external tables: nothing to compare with
                continue
    for m in models:
        node = m.sensors.get(column)
        role = m.node_roles.get(node) if node is not None else None
        if role is not None and role is not NodeRole.MAGNET:
            return (f"--magnet-column {column}: in model {m.name}, {column} is the sensor of node {node} (role "
                    f"{role.value}), not of a magnet: the fit would take its temperature for the magnet's")
    return None


def identification_warning(m: FluxModel, magnet_c: np.ndarray) -> str | None:
    """Why the run cannot give the temperature coefficient (a narrow magnet span, or ``β``'s σ
    comparable to it), None when it can."""
    lo, hi = (float(x) for x in np.percentile(magnet_c, [5.0, 95.0]))
    beta = m.params["beta"]
    s = max(m.sigma.get("beta", 0.0), m.beta_spread)
    why = []
    if hi - lo < MAGNET_SPAN_MIN_K:
        why.append(f"the magnet spans only {hi - lo:.1f} K ({lo:.1f} to {hi:.1f} degC, 5th to 95th percentile; "
                   f"at least {MAGNET_SPAN_MIN_K:g} K needed)")
    if s > BETA_REL_SIGMA_MAX * abs(beta):
        why.append(f"beta's sigma {s:.3g} Wb/K is {100 * s / abs(beta):.0f} % of beta")
    if not why:
        return None
    return ("the temperature coefficient is not identified: " + " and ".join(why) +
            "; the estimate is unreliable away from the temperatures seen: commission on a run that heats the magnet")


#: the unit each column the flux commands read must be in, judged as a run's columns are everywhere
#: (a whole column plausible only in kelvin or mA is refused naming that unit)
_COLUMN_UNITS = {"current_d": Role.CURRENT_D.plausible, "current_q": Role.CURRENT_Q.plausible,
                 "speed": Role.SPEED.plausible, "winding": TEMPERATURE, "magnet": TEMPERATURE}


def check_column_units(args: argparse.Namespace, run: Run) -> None:
    """Refuse a column of ``run`` in another unit (winding or magnet in kelvin, currents in mA):
    the winding's temperature sets the stator resistance and the magnet's the flux linkage's
    slope, so either one off by 273 K gives a calibration that is wrong throughout."""
    for key, plausible in _COLUMN_UNITS.items():
        column = getattr(args, f"{key}_column")
        x = run.columns.get(column)
        found = plausible.series_problem(np.asarray(x, dtype=float)) if x is not None else None
        if found is not None:
            k, why = found
            where = "" if k is None else f" (sample {k + 1}, t = {run.t[k]:g} s)"
            raise FluxError(f"{args.run}: column {column!r}{where}: {why}")


def main(args: argparse.Namespace) -> int:
    run = read_run(args.run, args.format)
    if args.magnet_column not in run.columns:
        raise FluxError(f"{args.run}: no magnet temperature column {args.magnet_column!r}")
    check_column_units(args, run)
    e = _electrical(args, run.columns)
    tm = run.columns[args.magnet_column]
    if args.flux == "calibrate":
        return _calibrate(args, run, e, tm)
    m = load(args.flux_file)
    T, s, ok = m.estimate(e)
    ok &= (run.t - run.t[0]) >= args.from_minute * 60.0
    ok &= np.isfinite(tm)
    if not ok.any():
        raise FluxError(f"{args.run}: {args.flux_file} is informative on none of the samples (speed below "
                        f"{m.speed_min_rpm:.0f} rpm, currents outside its bins, or sigma above {m.sigma_max_k:g} K): "
                        "nothing to score")
    err = T[ok] - tm[ok]
    r = {"informative_share": float(ok.mean()), "rms_k": float(np.sqrt(np.mean(err**2))),
         "coverage": float(np.mean(np.abs(err) <= 1.96 * s[ok]))}
    if not all(math.isfinite(v) for v in r.values()):
        raise FluxError(f"{args.run}: the estimate of {args.flux_file} is not finite where informative (RMS "
                        f"{r['rms_k']}): a calibration for another machine or columns in another unit?")
    if args.json:
        print(json.dumps(r))
        return 0
    print(f"{args.run}: informative on {100 * r['informative_share']:.0f} % of the samples; there RMS "
          f"{r['rms_k']:.2f} K, 95 % band covers {100 * r['coverage']:.0f} %")
    return 0


def _calibrate(args: argparse.Namespace, run: Run, e: Electrical, tm: np.ndarray) -> int:
    """``flux calibrate``: fit, check as the service reads it, write, print."""
    dt = float(run.dt)
    n = len(tm) if args.minutes is None else int(round(args.minutes * 60.0 / dt))
    if n < 2:
        raise UsageError(f"--minutes {args.minutes:g}: fewer than two samples")
    head = Electrical(*(np.asarray(a)[:n] for a in (e.u_d, e.u_q, e.i_d, e.i_q, e.speed_rpm, e.winding_c)))
    tm = np.asarray(tm, dtype=float)[:n]
    columns = run.columns
    torque = np.asarray(columns[args.torque_column], dtype=float)[:n] if args.torque_column in columns else None
    use = used_samples(head, args.speed_min)
    check_voltage_unit(head, use, torque, f"{args.run}: columns {args.u_d_column}, {args.u_q_column}")
    warnings = []
    model = None
    if args.model is not None:
        model = load_model(args.model)
    if args.magnet_column == args.winding_column:
        raise UsageError(f"--magnet-column {args.magnet_column}: the same column as --winding-column")
    column_note = magnet_column_warning(args.magnet_column, model)
    if column_note:
        warnings.append(column_note)
    hint = column_note or HINT  # a refused fit on a column of another node: that is the likely cause
    try:
        m = fit_flux_model(head, tm, args.pole_pairs, dt, priors=_priors(args.prior), speed_min_rpm=args.speed_min)
        # what the service reads, checked by the reader itself: a fit it would refuse is not written
        m = FluxModel.from_dict(json.loads(json.dumps(m.as_dict())))
    except FluxError as exc:
        if str(exc).startswith("only "):  # too few samples: nothing fitted, no hint to give
            raise FluxError(f"{args.run}: {exc}") from None
        raise FluxError(f"{args.run}: the fit is no magnet's: {exc}; {hint}") from None
    speed = float(np.median(np.abs(head.speed_rpm[use]))) if use.any() else float(np.median(np.abs(head.speed_rpm)))
    table_k = m.sigma_table(speed)
    if not any(v <= m.sigma_max_k for v in table_k.values()):
        raise FluxError(f"{args.run}: the fit's sigma at {speed:.0f} rpm is {min(table_k.values()):.3g} K at best, above "
                        f"{m.sigma_max_k:g} K: the estimate would never be used; {hint}")
    seen = tm[use & np.isfinite(tm)] if (use & np.isfinite(tm)).any() else tm[np.isfinite(tm)]
    w = identification_warning(m, seen)
    if w:
        warnings.append(w)
    Path(args.out).write_text(json.dumps(m.as_dict(), indent=1) + "\n")
    lo, hi = float(np.min(seen)), float(np.max(seen))
    for w in warnings:
        print(f"thermal-edge flux calibrate: warning: {w}", file=sys.stderr)
    if args.json:
        print(json.dumps({**m.as_dict(), "tempco_pct_per_k": 100.0 * m.tempco_per_k, "sigma_table_k": table_k,
                          "magnet_seen_c": [lo, hi], "warnings": warnings}, indent=2))
        return 0
    print(f"{args.run}: {int(m.fit_info['samples'])} steady samples at {args.speed_min:g} rpm and up; "
          f"written to {args.out}")
    print(table(["parameter", "value", "posterior sigma", "unit"],
                [[k, f"{m.params[k]:.6g}", f"{m.sigma[k]:.3g}", UNITS[k]] for k in PARAMS]))
    print(f"magnet temperature coefficient of the flux linkage: {100.0 * m.tempco_per_k:+.3f} %/K")
    sig = ", ".join(f"{k} {v:.2f} K" for k, v in table_k.items())
    print(f"informative from {m.speed_min_rpm:.0f} rpm, at these currents only (sigma at {speed:.0f} rpm): {sig}; "
          f"errors correlated over {m.tau_s:.0f} s")
    print(f"these sigmas hold at the magnet temperatures of the run ({lo:.1f} to {hi:.1f} degC); away from them the "
          "service adds the temperature coefficient's uncertainty")
    return 0
