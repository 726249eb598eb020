"""``thermal-edge bench``: benchmarks that print tables side by side with their baselines."""
from __future__ import annotations

import argparse
import json

from ..bench import jacobian, paper
from ..text_table import table
from .common import add_set_arg, check_sets, split_sets
from .progress import StageBars


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("bench", help="run a benchmark", description=__doc__)
    which = p.add_subparsers(dest="bench", required=True, metavar="BENCH")
    j = which.add_parser("jacobian", help="analytic vs forward-difference Jacobian (39 nodes, 14 parameters, --hours of a drive cycle)")
    j.add_argument("--repeat", type=int, default=7, help="timed rounds (medians reported; the speed-up is the median of the rounds' ratios)")
    j.add_argument("--hours", type=float, default=3.0, help="hours of the drive cycle at 1 Hz (default 3)")
    j.add_argument("--json", action="store_true", help="print one JSON object")
    j.set_defaults(func=run_jacobian)
    pp = which.add_parser("paper", help="the paper's experiments E1-E3, every method side by side")
    pp.add_argument("--json", action="store_true", help="print one JSON object")
    add_data_dir_arg(pp)
    pp.set_defaults(func=run_paper)
    sv = which.add_parser("service", help="edge service: tick p50/p99 (idle, adapting), max lossless frame rate, RSS over 24 h")
    sv.add_argument("--hours", type=float, default=24.0, help="simulated hours of the memory run (default 24)")
    sv.add_argument("--ticks", type=int, default=600, help="ticks timed per tick benchmark (default 600)")
    sv.add_argument("--fps-seconds", type=float, default=4.0, help="seconds sent at each frame rate (default 4)")
    sv.add_argument("--json", action="store_true", help="print one JSON object")
    sv.set_defaults(func=run_service)
    fa = which.add_parser("faults", help="the service as a black box against 100+ fault cases: what it did, frames or "
                                         "state lost, unsafe events")
    fa.add_argument("--full", action="store_true", help="full lengths and counts (200 SIGKILLs, 60 s at 8,000 frames/s, "
                                                        "a 7-day soak, ...); default: the short form")
    fa.add_argument("--only", action="append", default=None, metavar="GROUP", help="run only this group (repeatable)")
    fa.add_argument("--json", action="store_true", help="print one JSON object")
    fa.set_defaults(func=run_faults)
    pr = which.add_parser("protection", help="closed loop on the simulated machine: headroom delivered and overheating of "
                                             "thermal_edge, a PT100 derate, I2t and the oracle, per plant case")
    pr.add_argument("--case", action="append", default=None, metavar="NAME",
                    help="run only this plant case (repeatable; default all: nominal, r_hous_plus30, sigma_cu_minus25, "
                         "h_sh1_minus30, ambient_40, warm_restart)")
    pr.add_argument("--plant", action="append", default=[], metavar="NAME=VALUE",
                    help="add the case 'custom': the plant's parameter or constant NAME at VALUE (absolute) or changed "
                         "by VALUE%% (e.g. R_e_hous=+30%%); repeatable")
    pr.add_argument("--duration", type=float, default=None, help="simulated seconds of the cycle (default: all of it, 2 h)")
    pr.add_argument("--cycle", default=None, help="drive cycle: a file or a packaged name (default: the packaged protection)")
    pr.add_argument("--jobs", type=int, default=2, help="cases run in parallel processes (default 2)")
    pr.add_argument("--json", action="store_true", help="print one JSON object")
    pr.set_defaults(func=run_protection)
    rl = which.add_parser("real", help="online adaptation on the real Paderborn machine from the published and wrong starts")
    rl.add_argument("--json", action="store_true", help="print one JSON object")
    add_data_dir_arg(rl)
    add_set_arg(rl)
    rl.set_defaults(func=run_real)
    from ..bench.fleet import MACHINES, ROUNDS, SPEED_MACHINES

    fl = which.add_parser("fleet", help="fleet on Dask: per-machine cost, 1 vs 2 workers, memory, outlier screen hits")
    fl.add_argument("--machines", type=int, default=MACHINES, help=f"simulated machines (default {MACHINES})")
    fl.add_argument("--speed-machines", type=int, default=SPEED_MACHINES,
                    help=f"machines timed with 1 and with 2 workers (default {SPEED_MACHINES})")
    fl.add_argument("--rounds", type=int, default=ROUNDS, help=f"rounds of 1 and 2 workers taking turns (default {ROUNDS})")
    fl.add_argument("--json", action="store_true", help="print one JSON object")
    fl.set_defaults(func=run_fleet)


def add_data_dir_arg(p: argparse.ArgumentParser) -> None:
    """``--data-dir``: the Paderborn data set (the bench's real-machine part is skipped without it)."""
    from ..bench.common import DATA_DIR_ENV, PADERBORN_DEFAULT

    p.add_argument("--data-dir", default=None,
                   help=f"Paderborn data set directory (run_a.csv and the paderborn4 tables; default ${DATA_DIR_ENV}, "
                        f"else {PADERBORN_DEFAULT} from the working directory; skipped when absent)")


def run_jacobian(args: argparse.Namespace) -> int:
    with StageBars("bench jacobian") as progress:
        r = jacobian.run(repeat=args.repeat, hours=args.hours, progress=progress)
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(f"Jacobian of {r['nodes']} nodes x {r['params']} parameters over {r['samples']} samples "
          f"({r['operating_points']} distinct speeds, inputs held on {r['held_steps']} of "
          f"{r['samples'] - 1} steps); median of {args.repeat}")
    print(table(
        ["method", "wall s", "vs analytic"],
        [
            ["analytic (sim + sensitivities)", r["analytic_s"], "1.0x"],
            ["analytic, every step stepped", r["analytic_stepped_s"], f"{r['analytic_stepped_s'] / r['analytic_s']:.1f}x slower"],
            ["forward differences (p+1 sims)", r["numerical_s"], f"{r['speedup']:.1f}x slower"],
            ["one simulation", r["simulation_s"], f"{r['simulation_s'] / r['analytic_s']:.2f}x"],
            ["arithmetic limit (BLAS rate)", r["arith_limit_s"], f"{r['arith_limit_s'] / r['analytic_s']:.2f}x"],
        ],
    ))
    rounds = ", ".join(f"{x:.2f}" for x in r["speedup_rounds"])
    print(f"speed-up, median of the rounds' ratios: {r['speedup']:.2f}x (rounds: {rounds}; ratio of the medians "
          f"{r['speedup_of_medians']:.2f}x)")
    print(f"max relative error vs central differences: {r['max_rel_err']:.2e}; "
          f"closed form vs stepped: {r['closed_vs_stepped_max_rel']:.1e} of the largest entry")
    v = r["varying"]
    print(f"\nInputs that vary every sample: relative noise {v['noise']:g} on current and speed, speed binned to "
          f"{v['speed_bin_rpm']:g} rpm ({v['operating_points']} operating points; binning changes the sensor "
          f"temperatures by at most {v['binning_max_err_k']:.2g} K over the first hour); median of {args.repeat}")
    print(table(
        ["method", "wall s", "vs analytic"],
        [
            ["analytic (sim + sensitivities)", v["analytic_s"], "1.0x"],
            ["analytic, every step stepped", v["analytic_stepped_s"], f"{v['speedup_vs_stepped']:.1f}x slower"],
            ["forward differences (p+1 sims)", v["numerical_s"], f"{v['speedup_vs_forward']:.1f}x slower"],
            ["one simulation", v["simulation_s"], f"{v['simulation_s'] / v['analytic_s']:.2f}x"],
            ["one simulation, stepped", v["simulation_stepped_s"], f"{v['simulation_stepped_s'] / v['analytic_s']:.2f}x"],
            ["arithmetic limit (BLAS rate)", v["arith_limit_s"], f"{v['arith_limit_s'] / v['analytic_s']:.2f}x"],
        ],
    ))
    print(f"analytic / arithmetic limit: {v['analytic_over_limit']:.1f}x; simulation vectorised vs stepped: "
          f"{v['simulation_speedup']:.1f}x faster; agreement with the stepped recursion: sensitivities "
          f"{v['vectorised_vs_stepped_max_rel']:.1e}, temperatures {v['simulation_vs_stepped_max_rel']:.1e} of the largest entry")
    return 0


def run_paper(args: argparse.Namespace) -> int:
    with StageBars("bench paper") as progress:
        r = paper.run(progress=progress, data_dir=args.data_dir)
    if args.json:
        print(json.dumps(r, indent=2, default=float))
        return 0
    print(r["headline"] + "\n")
    e1 = r["e1"]
    print("E1 (paper Figs. 9-10): only R_e_hous adapted, 600 rpm / 70 Nm, 3 h")
    print(table(
        ["", "R_e_hous K/W", "error %", "RMS last hour K"],
        [
            ["plant (true)", e1["r_e_hous_true"], "", ""],
            ["model start / fixed", e1["r_e_hous_start"], 100 * (6.1 - e1["r_e_hous_true"]) / e1["r_e_hous_true"],
             e1["rms_last_hour_fixed_k"]],
            ["adapted (this run)", e1["r_e_hous_final"], e1["r_e_hous_err_pct"], e1["rms_last_hour_k"]],
            ["paper", 8.96, -2.5, ""],
        ],
    ))
    print("R_e_hous over time: " + ", ".join(f"{p['t_s'] / 60:.0f} min {p['r_e_hous']:.3f}" for p in e1["trajectory"]))
    e2 = r["e2"]
    print(f"\nE2 (paper Table 4/5, Fig. 11): 14 parameters, Table 4 start; held-out RMS at the start "
          f"{e2['heldout_rms_start_k']:.2f} K, with the plant's own parameters {e2['heldout_rms_true_params_k']:.3f} K")
    print(table(
        ["method", "wall s", "held-out RMS K"],
        [[m["label"], m["wall_s"], m["heldout_rms_k"]] for m in e2["methods"].values()]
        + [["paper: proposed / numerical / EKF", "107 / 459 / -", "1.6 / 7.6 / 11.9"]],
    ))
    print(f"numerical SQP / analytic SQP (same data, same cap): {e2['numerical_over_analytic_whole_data']:.1f}x; "
          f"numerical / proposed online total: {e2['numerical_over_proposed']:.1f}x (paper 4.3x)")
    print(f"one online adaptation step (14 parameters, 3 h window): median {r['adapt_step_median_s']:.3f} s")
    e3 = r["e3"]
    print("\nE3 (Paderborn run_a, adapted from stator_winding + stator_yoke only)")
    if "skipped" in e3:
        print(f"skipped: {e3['skipped']}")
        return 0
    print(table(
        ["target", "fixed MSE K²", "adapted MSE K²", "online trace MSE K²", "seen by adapter"],
        [[s, e3["fixed"]["mse"][s], e3["adapted"]["mse"][s], e3["online_trace"]["mse"][s],
          "yes" if s in e3["adapted_from"] else "no"] for s in e3["fixed"]["mse"]],
    ))
    return 0


def run_service(args: argparse.Namespace) -> int:
    from ..bench import service

    with StageBars("bench service") as progress:
        r = service.run(hours=args.hours, ticks=args.ticks, fps_seconds=args.fps_seconds, progress=progress)
    if args.json:
        print(json.dumps(r, indent=2, default=float))
        return 0
    t = r["targets"]
    print(f"edge service, pm10kw (39 nodes), 1 Hz tick; {r['ticks_measured']} ticks timed per row")
    print(table(
        ["measure", "value", "target"],
        [
            ["tick p50, adapter idle (ms)", r["tick_p50_ms"], ""],
            ["tick p99, adapter idle (ms)", r["tick_p99_ms"], ""],
            ["tick p50, adaptation running (ms)", r["tick_p50_adapting_ms"], ""],
            ["tick p99, adaptation running (ms)", r["tick_p99_adapting_ms"], f"<= {t['tick_p99_adapting_ms']:g}"],
            ["max lossless inbound frames/s (udp_multicast)", r["max_lossless_fps"], f">= {t['max_lossless_fps']}"],
            [f"RSS after {r['memory_run_hours']:g} h accelerated (MB)", r["rss_mb"], f"<= {t['rss_mb']:g}, flat"],
            ["RSS growth after the first hour (MB)", r["rss_growth_mb"], "~0"],
        ],
    ))
    print("RSS by simulated hour: " + ", ".join(f"{h:g} h {m:.0f} MB" for h, m in r["rss_samples"]))
    return 0


def run_fleet(args: argparse.Namespace) -> int:
    from ..bench import fleet
    from ..fleet import MissingExtra

    try:
        with StageBars("bench fleet") as progress:
            r = fleet.run(machines=args.machines, speed_machines=args.speed_machines, rounds=args.rounds,
                          progress=progress)
    except MissingExtra as exc:
        print(f"thermal-edge bench fleet: error: {exc}")
        return 2
    if args.json:
        print(json.dumps(r, indent=2, default=float))
        return 0
    print(fleet.format_result(r))
    return 0


def run_real(args: argparse.Namespace) -> int:
    from ..bench import real
    from ..bench.common import paderborn_dir
    from ..lptn import load_model
    from ..shipped import config_path
    from .runs import read_checked

    data_dir = paderborn_dir(args.data_dir)
    path = data_dir / "run_a.csv"
    sets = split_sets(args.set)
    if path.exists():  # the bench's own data: checked and summarised as every offline run is
        model = load_model(config_path("machines", "paderborn4.yaml"), data_dir=data_dir)
        sets = check_sets(model, sets)
        summary = read_checked(str(path), "paderborn", model, real.SENSORS)[1]
        if not args.json:
            print(summary, flush=True)
    with StageBars("bench real") as progress:
        r = real.run(data_dir, sets=sets, progress=progress)
    if args.json:
        print(json.dumps(r, indent=2, default=float))
        return 0
    if "skipped" in r:
        print(f"bench real skipped: {r['skipped']}")
        return 0
    print(f"Paderborn {r['run']}, adapted from {' + '.join(r['adapted_from'])} only; MSE K² per target "
          "(trace: each period predicted open loop from the observer's state; fixed: the same, parameters never "
          "changed; observer: live estimate; coverage: readings inside its 95 % band; EKF: its final parameters open loop)")
    for name, st in r["starts"].items():
        f = ", ".join(f"{k} x{v:g}" for k, v in st["factors"].items()) or "published parameters"
        print(f"\n{name} ({f}): {st['promoted']} challengers promoted; adaptation step median "
              f"{st['adapt_step_median_s']:.3f} s")
        targets = [k for k, v in st.items() if isinstance(v, dict) and "seen" in v]
        print(table(
            ["target", "seen", "fixed", "trace", "observer", "fixed observer", "coverage", "EKF open loop"],
            [[t, "yes" if st[t]["seen"] else "no", st[t]["fixed_mse"], st[t]["mse"], st[t]["observer_mse"],
              st[t]["fixed_observer_mse"], st[t]["band_coverage"], st[t]["ekf_open_loop_mse"]] for t in targets]
            + [["mean", "", st["mean"]["fixed_mse"], st["mean"]["mse"], st["mean"]["observer_mse"],
                st["mean"]["fixed_observer_mse"], "", ""]],
        ))
        sd = st["final_rel_std_pct"]
        print("final vs published (± 1σ the run allows): "
              + ", ".join(f"{k} {v:+.1f} % (±{sd[k]:.1f} %)" for k, v in st["final_vs_published_pct"].items())
              + "; EKF: " + ", ".join(f"{k} {v:+.1f} %" for k, v in st["ekf_params_vs_published_pct"].items()))
    return 0


def run_protection(args: argparse.Namespace) -> int:
    import sys
    from pathlib import Path

    from ..bench import protection

    try:
        cases = [protection.CASES[c] for c in (args.case or ([] if args.plant else list(protection.CASES)))]
        if args.plant:
            cases.append(protection.parse_plant_changes(args.plant))
    except KeyError as exc:
        print(f"thermal-edge bench protection: error: unknown case {exc} (known: {', '.join(protection.CASES)})", file=sys.stderr)
        return 2
    except ValueError as exc:
        print(f"thermal-edge bench protection: error: {exc}", file=sys.stderr)
        return 2
    try:
        r = protection.run(cases, cycle=Path(args.cycle) if args.cycle else None, duration_s=args.duration, jobs=args.jobs)
    except ValueError as exc:  # a --plant name the model does not have, a bad cycle
        print(f"thermal-edge bench protection: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(r, indent=2, default=float))
        return 0
    dur = "" if r["duration_s"] is None else f" (first {r['duration_s']:g} s)"
    mx = ", ".join(f"{k} {v:g} degC" for k, v in r["max_c"].items())
    print(f"closed loop on the simulated machine, cycle {Path(r['cycle']).stem}{dur}; "
          f"reaction time {r['reaction_time_s']:g} s; max: {mx}")
    print(table(protection.TABLE_HEADERS, protection.table_rows(r)))
    print(f"thermal_edge: min share of the oracle {r['min_oracle_share_pct']:.1f} % (target >= 90), "
          f"seconds over max {r['total_seconds_over_max']:g} (target 0)")
    for line in protection.verdicts(r):
        print(line)
    return 0


def run_faults(args: argparse.Namespace) -> int:
    from ..bench import faults

    r = faults.run(full=args.full, only=args.only)
    if args.json:
        print(json.dumps(r, indent=2, default=float))
        return 0
    print(faults.report_table(r))
    return 0
