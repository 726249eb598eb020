"""``thermal-edge bench``: benchmarks that print tables side by side with their baselines."""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from typing import Any

from ..bench import jacobian, paper
from ..lptn.chain import MIN_NODES
from ..text_table import table
from .bench_page import check_path, with_page
from .common import add_set_arg, check_sets, split_sets
from .options import integer, number, positive_s
from .progress import StageBars

#: Hours of a simulated drive cycle a benchmark runs (a minute to a month).
HOURS = number(1 / 60, 24 * 31, unit="h")


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("bench", help="run a benchmark", description=__doc__)
    which = p.add_subparsers(dest="bench", required=True, metavar="BENCH")
    j = which.add_parser("jacobian",
                         help="analytic vs forward-difference Jacobian (39 nodes, 14 parameters, --hours of a drive cycle)")
    j.add_argument("--repeat", type=integer(1), default=7,
                   help="timed rounds (medians reported; the speed-up is the median of the rounds' ratios)")
    j.add_argument("--hours", type=HOURS, default=3.0, help="hours of the drive cycle at 1 Hz (default 3)")
    j.add_argument("--json", action="store_true", help="print one JSON object")
    j.set_defaults(func=run_jacobian)
    pp = which.add_parser("paper", help="the paper's experiments E1-E3, every method side by side")
    pp.add_argument("--json", action="store_true", help="print one JSON object")
    add_data_dir_arg(pp)
    pp.set_defaults(func=run_paper)
    sv = which.add_parser("service", help="edge service: tick p50/p99 (idle, adapting), max lossless frame rate, RSS over 24 h")
    sv.add_argument("--hours", type=HOURS, default=24.0, help="simulated hours of the memory run (default 24)")
    sv.add_argument("--ticks", type=integer(1), default=600, help="ticks timed per tick benchmark (default 600)")
    sv.add_argument("--fps-seconds", type=positive_s, default=4.0, help="seconds sent at each frame rate (default 4)")
    sv.add_argument("--json", action="store_true", help="print one JSON object")
    sv.set_defaults(func=run_service)
    pr = which.add_parser("protection", help="closed loop on the simulated machine: headroom delivered and overheating of "
                                             "thermal_edge without and with the voltage frame, a PT100 derate, I2t and "
                                             "the oracle, per plant case")
    pr.add_argument("--case", action="append", default=None, metavar="NAME",
                    help="run only this plant case (repeatable; default all: nominal, r_hous_plus30, sigma_cu_minus25, "
                         "h_sh1_minus30, ambient_40, warm_restart, warm_restart_rotor, electrical_wrong)")
    pr.add_argument("--plant", action="append", default=[], metavar="NAME=VALUE",
                    help="add the case 'custom': the plant's parameter or constant NAME at VALUE (absolute) or changed "
                         "by VALUE%% (e.g. R_e_hous=+30%%); repeatable")
    pr.add_argument("--duration", type=positive_s, default=None, help="simulated seconds of the cycle (default: all of it, 2 h)")
    pr.add_argument("--cycle", default=None, help="drive cycle: a file or a packaged name (default: the packaged protection)")
    pr.add_argument("--jobs", type=integer(1), default=2, help="cases run in parallel processes (default 2)")
    pr.add_argument("--json", action="store_true", help="print one JSON object")
    pr.set_defaults(func=run_protection)
    rl = which.add_parser("real", help="online adaptation on the real Paderborn machine from the published and wrong starts")
    rl.add_argument("--json", action="store_true", help="print one JSON object")
    add_data_dir_arg(rl)
    add_set_arg(rl)
    rl.set_defaults(func=run_real)
    mg = which.add_parser("magnet", help="magnet temperature from the inverter's voltages on the real Paderborn machine: "
                                         "commissioned on the first part, scored on the rest against the LPTN")
    mg.add_argument("--fit-minutes", type=float, action="append", default=None, metavar="MIN",
                    help="commissioning part, minutes from the start (repeatable; default 20, 30 and 60)")
    mg.add_argument("--json", action="store_true", help="print one JSON object")
    add_data_dir_arg(mg)
    mg.set_defaults(func=run_magnet)
    ad = which.add_parser("adaptation", help="online adaptation in closed loop on the simulated machine: the open-loop "
                                             "error over time, promotions and refusals, final parameters, per scenario")
    ad.add_argument("--scenario", action="append", default=None, metavar="NAME",
                    help="run only this scenario (repeatable; default all: demo, quasi_steady, cold_light, varied, at_plant)")
    ad.add_argument("--duration", type=float, default=None, help="simulated seconds per scenario (default 3 h)")
    ad.add_argument("--json", action="store_true", help="print one JSON object")
    ad.set_defaults(func=run_adaptation)
    ld = which.add_parser("ladder", help="one online adaptation step against the model size (generated chain models, "
                                         "40-320 nodes): the dense and the reduced-order path, error bound and error")
    ld.add_argument("--nodes", type=integer(MIN_NODES, 2000), action="append", default=None, metavar="N",
                    help="a model size (repeatable; default 40, 80, 160 and 320 nodes)")
    ld.add_argument("--repeat", type=integer(1), default=3,
                    help="timed rounds per size (medians reported; the ratio is the median of the rounds' ratios)")
    ld.add_argument("--hours", type=HOURS, default=3.0, help="hours of the drive cycle: the adapter's window (default 3)")
    ld.add_argument("--json", action="store_true", help="print one JSON object")
    ld.set_defaults(func=run_ladder)
    from ..bench.fleet import MACHINES, ROUNDS, SPEED_MACHINES

    fl = which.add_parser("fleet", help="fleet on Dask: per-machine cost, 1 vs 2 workers, memory, outlier screen hits")
    fl.add_argument("--machines", type=integer(1), default=MACHINES, help=f"simulated machines (default {MACHINES})")
    fl.add_argument("--speed-machines", type=integer(1), default=SPEED_MACHINES,
                    help=f"machines timed with 1 and with 2 workers (default {SPEED_MACHINES})")
    fl.add_argument("--rounds", type=integer(1), default=ROUNDS,
                    help=f"rounds of 1 and 2 workers taking turns (default {ROUNDS})")
    fl.add_argument("--json", action="store_true", help="print one JSON object")
    fl.set_defaults(func=run_fleet)
    for name, parser in which.choices.items():  # every bench can write what it prints as a page of the manual
        parser.add_argument("--markdown", metavar="PATH", default=None,
                            help="also write what the bench prints to this Markdown page, stamped with the commit "
                                 "(or package version), host and date (the manual's docs/benchmarks/ pages)")
        parser.set_defaults(bench_func=parser.get_default("func"), bench_title=f"Benchmark: {name}",
                            bench_help=parser.description or "", func=run_bench)


def run_bench(args: argparse.Namespace) -> int:
    """Run the chosen bench; with ``--markdown`` also write its output as a page."""
    if args.markdown is None:
        return int(args.bench_func(args))
    path = check_path(args.markdown)
    argv = [a for a in sys.argv[1:] if a != "--debug"]  # the command as typed, when this process runs it
    shown = argv if argv[:2] == ["bench", args.bench] else ["bench", args.bench]
    command = "thermal-edge " + " ".join(_drop_option(shown, "--markdown"))
    return with_page(args.bench_func, args.bench_title, command, path, args)


def _drop_option(argv: list[str], option: str) -> list[str]:
    """``argv`` without ``option`` and its value (``--opt V`` or ``--opt=V``)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == option:
            skip = True
        elif not a.startswith(option + "="):
            out.append(a)
    return out


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
        print(json.dumps(asdict(r), indent=2))
        return 0
    print(f"Jacobian of {r.nodes} nodes x {r.params} parameters over {r.samples} samples "
          f"({r.operating_points} distinct speeds, inputs held on {r.held_steps} of "
          f"{r.samples - 1} steps); median of {args.repeat}")
    print(table(
        ["method", "wall s", "vs analytic"],
        [
            ["analytic (sim + sensitivities)", r.analytic_s, "1.0x"],
            ["analytic, every step stepped", r.analytic_stepped_s, f"{r.analytic_stepped_s / r.analytic_s:.1f}x slower"],
            ["forward differences (p+1 sims)", r.numerical_s, f"{r.speedup:.1f}x slower"],
            ["one simulation", r.simulation_s, f"{r.simulation_s / r.analytic_s:.2f}x"],
            ["arithmetic limit (BLAS rate)", r.arith_limit_s, f"{r.arith_limit_s / r.analytic_s:.2f}x"],
            ["  the same, output array reused", r.arith_limit_reused_s, f"{r.arith_limit_reused_s / r.analytic_s:.2f}x"],
        ],
    ))
    rounds = ", ".join(f"{x:.2f}" for x in r.speedup_rounds)
    print(f"speed-up, median of the rounds' ratios: {r.speedup:.2f}x (rounds: {rounds}; ratio of the medians "
          f"{r.speedup_of_medians:.2f}x)")
    print(f"max relative error vs central differences: {r.max_rel_err:.2e}; "
          f"closed form vs stepped: {r.closed_vs_stepped_max_rel:.1e} of the largest entry")
    v = r.varying
    print(f"\nInputs that vary every sample: relative noise {v['noise']:g} on current and speed, speed binned to "
          f"{v['speed_bin_rpm']:g} rpm ({v['operating_points']} operating points; binning changes the sensor "
          f"temperatures by at most {v['binning_max_err_k']:.2g} K over the first hour); median of {args.repeat}, "
          "wall clock and CPU time")
    x = lambda w, c: f"{w:.2f}x (CPU {c:.2f}x)"  # noqa: E731
    print(table(
        ["", "new: vectorised s", "old: stepped s", "old / new"],
        [
            ["analytic Jacobian (sim + sensitivities)", v["analytic_s"], v["analytic_stepped_s"],
             x(v["speedup_vs_stepped"], v["cpu_speedup_vs_stepped"])],
            ["  CPU s", v["analytic_cpu_s"], v["analytic_stepped_cpu_s"], ""],
            ["one simulation", v["simulation_s"], v["simulation_stepped_s"],
             x(v["simulation_speedup"], v["cpu_simulation_speedup"])],
            ["  CPU s", v["simulation_cpu_s"], v["simulation_stepped_cpu_s"], ""],
            ["forward differences (p+1 sims)", v["numerical_s"], "", ""],
            ["forward differences / analytic", x(v["speedup_vs_forward"], v["cpu_speedup_vs_forward"]),
             x(v["stepped_speedup_vs_forward"], v["cpu_stepped_speedup_vs_forward"]), ""],
            ["  its bound, (p+1) x simulation / analytic", x(v["forward_bound"], v["cpu_forward_bound"]),
             x(v["stepped_forward_bound"], v["cpu_stepped_forward_bound"]), ""],
            ["arithmetic limit (BLAS rate)", v["arith_limit_s"], "", ""],
            ["analytic / arithmetic limit", x(v["analytic_over_limit"], v["cpu_analytic_over_limit"]),
             x(v["stepped_over_limit"], v["cpu_stepped_over_limit"]), ""],
            ["  sensitivities alone (analytic - simulation) / limit",
             x(v["sensitivities_over_limit"], v["cpu_sensitivities_over_limit"]),
             x(v["stepped_sensitivities_over_limit"], v["cpu_stepped_sensitivities_over_limit"]), ""],
            ["arithmetic limit, output array reused", v["arith_limit_reused_s"], "", ""],
            ["analytic / that limit", x(v["analytic_over_reused_limit"], v["cpu_analytic_over_reused_limit"]), "", ""],
        ],
    ))
    print("ratios: medians of the rounds' paired ratios; agreement of new with old: sensitivities "
          f"{v['vectorised_vs_stepped_max_rel']:.1e}, temperatures {v['simulation_vs_stepped_max_rel']:.1e} of the largest entry")
    w = r.sweep
    print(f"\nA speed that sweeps continuously (+-{w['amplitude_rpm']:g} rpm around the cycle's, 1 rpm resolution, "
          f"noisy current): {w['operating_points']} operating points; peak memory (tracemalloc) and wall time of one call")
    print(table(
        ["", "all operating points at once", f"chunks of <= {w['max_operating_points']}"],
        [
            ["simulation: peak MB", w["whole_simulation_peak_mb"], w["chunked_simulation_peak_mb"]],
            ["  wall s", w["whole_simulation_s"], w["chunked_simulation_s"]],
            ["Jacobian: peak MB", w["whole_jacobian_peak_mb"], w["chunked_jacobian_peak_mb"]],
            ["  wall s", w["whole_jacobian_s"], w["chunked_jacobian_s"]],
        ],
    ))
    print(f"agreement of chunks with one piece: temperatures {w['temperatures_max_rel']:.1e}, sensitivities "
          f"{w['sensitivities_max_rel']:.1e} of the largest entry")
    return 0


def run_ladder(args: argparse.Namespace) -> int:
    from ..bench import ladder

    sizes = tuple(args.nodes or ladder.SIZES)
    with StageBars("bench ladder") as progress:
        r = ladder.run(sizes=sizes, repeat=args.repeat, hours=args.hours, progress=progress)
    if args.json:
        print(json.dumps(asdict(r), indent=2, default=float))
        return 0
    print(f"one online adaptation step (screening + SQP, {r.params} adaptable parameters, a {r.hours:g} h window "
          f"decimated by {r.decimate}) on generated chain models; dense: the exact simulator, reduced: the "
          f"Galerkin-reduced model; median of {r.repeat}")
    print(table(ladder.HEADERS, ladder.table_rows(r)))
    big = r.largest
    verdict = "meets" if big.reduced_s <= r.target_s else "misses"
    print(f"{big.nodes} nodes: reduced step {big.reduced_s:.3f} s ({verdict} the {r.target_s:g} s target), "
          f"dense {big.dense_s:.2f} s; rounds dense " + ", ".join(f"{x:.2f}" for x in big.dense_runs_s)
          + "; reduced " + ", ".join(f"{x:.3f}" for x in big.reduced_runs_s))
    print("error bound: at the reference (nominal parameters, standstill) over the window's inputs, losses taken "
          "as inputs; measured: largest sensor error against the dense model over the optimiser's window at the "
          "nominal parameters; fit difference: the two paths' fitted parameters, largest relative difference")
    print("reduced bases built once per model (optimiser's step and 1 s): "
          + ", ".join(f"{x.nodes} nodes {x.basis_s:.2f} s" for x in r.rows))
    return 0


def run_paper(args: argparse.Namespace) -> int:
    with StageBars("bench paper") as progress:
        r = paper.run(progress=progress, data_dir=args.data_dir)
    if args.json:
        print(json.dumps(asdict(r), indent=2, default=float))
        return 0
    print(r.headline + "\n")
    e1 = r.e1
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
    e2 = r.e2
    print(f"\nE2 (paper Table 4/5, Fig. 11): 14 parameters, Table 4 start; held-out RMS at the start "
          f"{e2['heldout_rms_start_k']:.2f} K, with the plant's own parameters {e2['heldout_rms_true_params_k']:.3f} K")
    print(table(
        ["method", "wall s", "held-out RMS K"],
        [[m["label"], m["wall_s"], m["heldout_rms_k"]] for m in e2["methods"].values()]
        + [["paper: proposed / numerical / EKF", "107 / 459 / -", "1.6 / 7.6 / 11.9"]],
    ))
    print(f"numerical SQP / analytic SQP (same data, same cap): {e2['numerical_over_analytic_whole_data']:.1f}x; "
          f"numerical / proposed online total: {e2['numerical_over_proposed']:.1f}x (paper 4.3x)")
    print(f"one online adaptation step (14 parameters, 3 h window): median {r.adapt_step_median_s:.3f} s")
    e3 = r.e3
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
        print(json.dumps(asdict(r), indent=2, default=float))
        return 0
    t = r.targets
    print(f"edge service, pm10kw (39 nodes), 1 Hz tick; {r.ticks_measured} ticks timed per row")
    print(table(
        ["measure", "value", "target"],
        [
            ["tick p50, adapter idle (ms)", r.tick_p50_ms, ""],
            ["tick p99, adapter idle (ms)", r.tick_p99_ms, ""],
            ["tick p50, adaptation running (ms)", r.tick_p50_adapting_ms, ""],
            ["tick p99, adaptation running (ms)", r.tick_p99_adapting_ms, f"<= {t['tick_p99_adapting_ms']:g}"],
            ["max lossless inbound frames/s (udp_multicast)", r.max_lossless_fps, f">= {t['max_lossless_fps']}"],
            ["service process RSS when ready (MB)", r.rss_at_start_mb, ""],
            [f"service process RSS after {r.memory_run_hours:g} h accelerated (MB)", r.rss_mb, f"<= {t['rss_mb']:g}, flat"],
            ["service process peak RSS over the run, VmHWM (MB)", r.hwm_mb, f"<= {t['rss_mb']:g}"],
            ["RSS growth after the first hour (MB)", r.rss_growth_mb, "~0"],
        ],
    ))
    print(f"memory run: thermal-edge run in its own process, adaptation on ({r.memory_run_adaptations[0]} accepted of "
          f"{r.memory_run_adaptations[1]} decisions), {r.memory_run_wall_s:.0f} s wall")
    marks = [h for h in (1.0, 4.0, 8.0) if h < r.memory_run_hours] + [r.memory_run_hours]
    at = dict.fromkeys(min(r.rss_samples, key=lambda s: abs(s[0] - h)) for h in marks)  # the samples nearest
    print(table(["simulated hour", "RSS MB", "peak (VmHWM) MB"], [[f"{h:g}", m, p] for h, m, p in at]))
    print("service RSS / peak by simulated hour: " + ", ".join(f"{h:g} h {m:.0f}/{p:.0f} MB" for h, m, p in r.rss_samples))
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
        print(json.dumps(asdict(r), indent=2, default=float))
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
        print(json.dumps(asdict(r), indent=2, default=float))
        return 0
    if r.skipped is not None:
        print(f"bench real skipped: {r.skipped}")
        return 0
    print(f"Paderborn {r.run}, adapted from {' + '.join(r.adapted_from)} only; MSE K² per target "
          "(trace: each period predicted open loop from the observer's state; fixed: the same, parameters never "
          "changed; observer: live estimate; coverage: readings inside its 95 % band; EKF: its final parameters open loop)")
    for name, st in r.starts.items():
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


def run_magnet(args: argparse.Namespace) -> int:
    from ..bench import magnet
    from ..errors import UsageError

    minutes = tuple(args.fit_minutes or magnet.FIT_MINUTES)
    bad = [m for m in minutes if not 5.0 <= m <= 100.0]
    if bad:
        raise UsageError(f"--fit-minutes {bad[0]:g}: between 5 and 100 (the run is 125 min; the rest is scored)")
    with StageBars("bench magnet") as progress:
        r = magnet.run(args.data_dir, fit_minutes=minutes, progress=progress)
    if args.json:
        print(json.dumps({k: v for k, v in asdict(r).items() if v is not None or k != "skipped"}, indent=2, default=float))
        return 0
    if r.skipped is not None:
        print(f"bench magnet skipped: {r.skipped}")
        return 0
    parts: dict[str, Any] = r.parts
    print(f"Paderborn {r.run}: magnet temperature from the inverter's voltages (p = {r.pole_pairs}), "
          "commissioned on the first MIN minutes, scored on the rest; observer: the LPTN with "
          "stator_winding + stator_yoke; published LPTN open loop on the whole run: "
          f"{r.published_lptn_mse:g} K2")
    print(table(
        ["commissioned on", "informative", "flux RMS K", "flux cover", "LPTN open loop MSE", "observer MSE",
         "fused MSE", "observer cover", "fused cover", "used", "refused"],
        [[f"{m} min", f"{p['informative_share'] * 100:.0f} %", p["flux_rms_k"], p["flux_coverage"], p["open_loop_mse"],
          p["observer_mse"], p["fused_mse"], p["observer_coverage"], p["fused_coverage"], p["used"], p["refused"]]
         for m, p in parts.items()],
    ))
    print("MSE in K2 over the scored rest; cover: share of readings inside the 95 % band; flux: where informative; "
          "fused: the commissioned operating points only (flux.extrapolate: false)")
    print(table(
        ["commissioned on, unseen currents by their changes (the service's default)", "fused MSE", "fused cover", "used",
         "of them relative", "refused", "stator MSE observer -> fused (winding, yoke, tooth)",
         "read sensors' prediction MSE observer -> fused (winding, yoke)"],
        [[f"{m} min", p["extrapolated"]["fused_mse"], p["extrapolated"]["fused_coverage"], p["extrapolated"]["used"],
          p["extrapolated"]["relative"], p["extrapolated"]["refused"],
          ", ".join(f"{p['stator_mse'][s]['observer']:.4g} -> {v:.4g}" for s, v in p["extrapolated"]["stator_mse"].items()),
          ", ".join(f"{v['observer']:.4g} -> {v['fused']:.4g}"
                    for v in p["extrapolated"].get("stator_prediction_mse", {}).values())]
         for m, p in parts.items()],
    ))
    for m, p in parts.items():
        x = p["extrapolated"]
        worse = [f"{s} ({v - p['stator_mse'][s]['observer']:+.1e} K2)" for s, v in x["stator_mse"].items()
                 if v > p["stator_mse"][s]["observer"]]
        pworse = [f"{s} ({v['fused'] - v['observer']:+.1e} K2)" for s, v in x.get("stator_prediction_mse", {}).items()
                  if v["fused"] > v["observer"]]
        print(f"{m} min, the service's default: fused MSE {x['fused_mse']:.2f} K2 against the LPTN's "
              f"{p['open_loop_mse']:.2f} ({'no worse' if x['fused_mse'] <= p['open_loop_mse'] else 'WORSE'}); "
              f"95 % band covers {100 * x['fused_coverage']:.1f} % "
              f"({'within' if 0.85 <= x['fused_coverage'] <= 0.99 else 'OUTSIDE'} 85-99 %); stator targets worse than "
              f"the observer's: {', '.join(worse) if worse else 'none'}; read sensors predicted worse: "
              f"{', '.join(pworse) if pworse else 'none'}")
    print("stator MSE: of the estimate; prediction: of the estimate before each reading (the estimate after a reading "
          "is partly that reading, and copies it less the better the prediction is)")
    print(table(
        ["commissioned on, then wrong (L x1.2, V_err x2)", "flux RMS K", "fused MSE", "fused cover", "used", "refused",
         "used by changes", "their fused MSE"],
        [[f"{m} min", p["wrong"]["flux_rms_k"], p["wrong"]["fused_mse"], p["wrong"]["fused_coverage"], p["wrong"]["used"],
          p["wrong"]["refused"], p["wrong"]["extrapolated_used"], p["wrong"]["extrapolated_fused_mse"]]
         for m, p in parts.items()],
    ))
    for m, p in parts.items():
        sig = ", ".join(f"{k} {v:.2f} K" for k, v in p["sigma_table_k"].items())
        st = ", ".join(f"{s} {v['observer']:.4g} -> {v['fused']:.4g}" for s, v in p["stator_mse"].items())
        print(f"{m} min: tempco {p['tempco_pct_per_k']:+.3f} %/K, psi20 {p['params']['psi20']:.4f} Wb, "
              f"Ld0 {p['params']['ld0'] * 1e3:.3f} mH, R20 {p['params']['r20'] * 1e3:.1f} mOhm, "
              f"V_err {p['params']['v_err']:+.2f} V; sigma by current at {p['speed_min_rpm']:.0f} rpm and up: {sig}; "
              f"error correlation {p['tau_s']:.0f} s; magnet MSE where informative: observer "
              f"{p['observer_mse_informative']:.2f}, fused {p['fused_mse_informative']:.2f}; stator MSE observer -> fused: {st}")
    return 0


def run_adaptation(args: argparse.Namespace) -> int:
    import dataclasses

    from ..bench import adaptation as ab
    from ..errors import UsageError

    unknown = [n for n in args.scenario or [] if n not in ab.SCENARIOS]
    if unknown:
        raise UsageError(f"--scenario {unknown[0]}: unknown (known: {', '.join(ab.SCENARIOS)})")
    if args.duration is not None and not args.duration >= 600:
        raise UsageError(f"--duration {args.duration:g}: at least 600 s (the adapter needs history to decide on)")
    chosen = [ab.SCENARIOS[n] for n in args.scenario] if args.scenario else list(ab.SCENARIOS.values())
    if args.duration is not None:
        chosen = [dataclasses.replace(s, duration_s=float(args.duration)) for s in chosen]
    with StageBars("bench adaptation") as progress:
        r = ab.run(chosen, progress=lambda name, done, total: progress(f"scenario {name}", done, total, "s"))
    if args.json:
        out = {"wall_s": r.wall_s, "passed": r.passed, "scenarios": {
            k: {**dataclasses.asdict(v), "identifiable": v.identifiable, "param_errors_pct": v.param_errors_pct,
                "passed": v.passed} for k, v in r.scenarios.items()}}
        print(json.dumps(out, indent=2, default=float))
        return 0
    print("online adaptation in closed loop on the simulated machine (config/edge.yaml, frame clock); the plant is "
          "the model file's nominal parameters")
    for sc in r.scenarios.values():
        print(f"  {sc.name}: {sc.doc}")
    print()
    print(table(ab.SUMMARY_HEADERS, ab.summary_rows(r)))
    print(f"\nopen-loop prediction error (TE_PredErrRms, K) over time; pass: final <= {ab.WITHIN_K:g} K, identifiable "
          f"parameters (marginal 1σ <= {100 * ab.IDENTIFIABLE_REL_STD:g} %, all others free) within "
          f"{100 * ab.PARAM_TOLERANCE:g} %, no promotion that makes the next hour worse; at the plant's parameters: no promotion")
    print(table(*ab.error_rows(r)))
    for sc in r.scenarios.values():
        print(f"\n{sc.name}: {sc.decisions} decisions: " + ", ".join(f"{k} {v}" for k, v in sorted(sc.outcomes.items())))
        if sc.promotions:
            print(table(ab.PROMOTION_HEADERS, ab.promotion_rows(sc)))
        for t_s, why in sc.refusals:
            print(f"  {ab.hms(t_s)} {why}")
        print(table(ab.PARAMETER_HEADERS, ab.parameter_rows(sc)))
    print(f"\n{'every scenario passes' if r.passed else 'NOT every scenario passes'} ({r.wall_s:.0f} s)")
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
        print(json.dumps(asdict(r), indent=2, default=float))
        return 0
    dur = "" if r.duration_s is None else f" (first {r.duration_s:g} s)"
    mx = ", ".join(f"{k} {v:g} degC" for k, v in r.max_c.items())
    print(f"closed loop on the simulated machine, cycle {Path(r.cycle).stem}{dur}; "
          f"reaction time {r.reaction_time_s:g} s; max: {mx}")
    print(table(protection.TABLE_HEADERS, protection.table_rows(r)))
    if r.min_oracle_share_pct is not None:
        print(f"thermal_edge: min share of the oracle {r.min_oracle_share_pct:.1f} % (target >= 90), "
              f"seconds over max {r.total_seconds_over_max:g} (target 0)")
    if r.total_seconds_over_max_voltages is not None:
        print(table(protection.SIDE_BY_SIDE_HEADERS, protection.side_by_side_rows(r)))
        share = (f"min share of the oracle {r.min_oracle_share_voltages_pct:.1f} % (target >= 97), "
                 if r.min_oracle_share_voltages_pct is not None else "")
        print(f"thermal_edge with the voltage frame: {share}seconds over max {r.total_seconds_over_max_voltages:g} "
              "(target 0, every case)")
        for name in r.miscalibrated_cases:
            tv = r.cases.get(name, {}).get("thermal_edge_voltages")
            if tv is not None:
                flux = tv.get("flux", {})
                print(f"{name} (the electrical calibration wrong on purpose): {tv['oracle_share_pct']:.1f} % of the oracle, "
                      f"{tv['seconds_over_max']:g} s over max; the disagreement check refused {flux.get('disagreement', 0)} "
                      f"of {sum(flux.values())} ticks")
    for line in protection.verdicts(r):
        print(line)
    return 0

