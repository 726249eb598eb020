"""``thermal-edge simulate``: run the simulated machine over a drive cycle and write the run.

``--effect NAME[:TARGET][=PARAM=VALUE,...]`` (repeatable) gives the plant a catalogue effect the
model file lacks, on top of what the model already has, so that data with a hidden effect can
be made at will (``thermal-edge discover`` should then find it). Unset parameters take the
effect's default magnitude, raised (doubled, up to 8 times) where needed until the plant
differs from the model by at least 1 K RMS on some sensor over the cycle. Speeds and currents in
the effect laws are relative to the cycle's reference point (95th percentiles, two significant digits): ``s = |n| / n_ref``.
"""
from __future__ import annotations

import argparse
import shlex
from pathlib import Path

import numpy as np

from ..data import Run, write_run
from ..discovery import effects as E
from ..discovery import hidden
from ..errors import UsageError
from ..lptn import DEFAULT_COLUMNS, Model, NodeRole, Role
from ..sim.cycles import SPEED, cycle_run, load_cycle, samples
from ..sim.inverter import write_log
from ..sim.plant import simulate_plant
from ..sim.pmsm import Pmsm
from .common import add_model_args, add_set_arg, parse_sets
from .fleet import add_simulate_args, simulate_fleet
from .options import MAX_EPOCH_S, frame_period_s, integer, kelvin, number, output_path, positive_s
from .progress import bar
from .runs import require_finite

#: Samples a simulation of a run CSV may have: 11.6 days at 1 s. The 39-node machine's simulation
#: keeps about 2 kB a sample (measured: 330 MB for 1e5 samples), so this is about 2 GB.
MAX_SIMULATED_SAMPLES = 1_000_000


def _effects_help() -> str:
    lines = ["effects (--effect NAME[:TARGET][=PARAM=VALUE,...]; defaults in brackets):"]
    for name, eff in E.CATALOGUE.items():
        tgt = {"none": "", "group": ":<conductance group>", "edge": ":<conductance>", "sensor": ":<sensor>",
               "boundary": "[:<boundary>]"}[eff.target_kind]
        ps = ",".join(f"{p.short}={p.default:g}" + ("x" if eff.scale_by_target else "") for p in eff.params)
        lines.append(f"  {name}{tgt}  [{ps}]")
        lines.append(f"      {eff.doc}; " + "; ".join(f"{p.short} ({p.unit}): {p.doc}" for p in eff.params))
    lines += [
        "  A conductance group is named by the parameters its law uses (pm10kw: R_e_hous = housing to",
        "  ambient, h_gap0+h_gap1 = air gap), else by its two ends (st-pm); a conductance by its ends",
        "  (housing_6-yoke_1); contact_resistance's R default is 2x the path's nominal resistance.",
        "  Unset magnitudes are raised (doubled, up to 8x) until the plant differs from the model by",
        "  at least 1 K RMS on some sensor over the cycle; the run's header comment records the values.",
        "  List a model's targets: thermal-edge discover --model M --list-effects",
        "examples:",
        "  --effect copper_temperature            --effect speed_convection:R_e_hous=k=0.8,m=1.2",
        "  --effect sensor_lag:end_winding=tau=120 --effect ambient_offset=dT=3",
    ]
    return "\n".join(lines)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("simulate", help="simulate the machine over a drive cycle", description=__doc__,
                       epilog=_effects_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    add_model_args(p)
    p.add_argument("--cycle", required=True,
                   help="drive cycle: a file, or the name of a packaged one (varied_drive, overload, ...)")
    p.add_argument("--out", required=True, type=output_path, help="output file: run CSV, or a CAN log with --format can")
    p.add_argument("--format", choices=("csv", "can", "candump"), default="csv",
                   help="csv: run CSV (default); can (old name: candump): the inverter's CAN frames as a log in "
                        "the format of --out's suffix: .log (candump -L, decodable with python -m cantools decode "
                        "dbc/thermal_edge.dbc), .asc, .blf, .trc, .mf4, .csv; .gz compresses the text formats")
    p.add_argument("--config", metavar="EDGE_YAML", default=None,
                   help="can: put the model's sensors into the inverter's PT100 signals (INV_StatorTemps) as this "
                        "service configuration maps them (signals.sensors); default: the packaged model's names")
    p.add_argument("--current-period", type=frame_period_s, default=0.01,
                   help="can: INV_Currents/INV_Mechanics period, s (default 0.01 as the DBC)")
    p.add_argument("--temperature-period", type=frame_period_s, default=0.1,
                   help="can: INV_StatorTemps/INV_AmbientTemps period, s (default 0.1)")
    p.add_argument("--t0", type=number(0, MAX_EPOCH_S, unit="s"), default=1.7e9,
                   help="can: timestamp of the first frame, s since the epoch")
    p.add_argument("--duration", type=positive_s, help="override the cycle's duration, s")
    add_set_arg(p, "--param")
    p.add_argument("--effect", action="append", default=[], metavar="NAME[:TARGET][=PARAM=VALUE,...]",
                   help="hide a catalogue effect in the plant (repeatable; list below)")
    p.add_argument("--noise", type=kelvin, default=0.1, help="PT100 noise sigma, K (default 0.1)")
    p.add_argument("--resolution", type=kelvin, default=0.1, help="PT100 quantisation, K (default 0.1)")
    p.add_argument("--seed", type=integer(0), default=0)
    add_simulate_args(p)
    p.add_argument("--all-nodes", action="store_true", help="also write every node's true temperature (T_<node>)")
    p.add_argument("--voltages", action="store_true",
                   help="also write the inverter's dq voltage references (u_d_v, u_q_v; V peak) from the simulated "
                        "machine's electrical side at the plant's true winding and magnet temperatures, and the magnet's "
                        "true temperature as pm (a test bench's rotor telemetry): a run for thermal-edge flux calibrate; "
                        "with --format can the INV_Voltages frames")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.fleet is not None:
        return simulate_fleet(args)
    if Path(args.out).is_dir():
        raise UsageError(f"--out {args.out}: a directory; give a file name (a directory is written with --fleet only)")
    if args.format in ("can", "candump"):
        return run_can_log(args)
    if Path(args.out).suffix.lower() != ".csv":  # what is written is a run CSV, whatever the name says
        raise UsageError(f"--out {args.out}: a run is written as CSV: give a .csv file name "
                         "(or --format can for a CAN log in the format of the suffix)")
    raw = hidden.read_document(args.model)
    build = hidden.builder(args.model, args.data_dir)
    model = build(raw)
    cycle = load_cycle(args.cycle)
    kt = model.drive.get("kt_nm_per_arms")
    if kt is None:
        raise UsageError(f"--model {args.model}: drive.kt_nm_per_arms is missing: cannot turn the cycle's torque into current")
    n = samples(cycle.duration_s if args.duration is None else args.duration, cycle.dt_s)
    if n > MAX_SIMULATED_SAMPLES:
        raise UsageError(f"--duration {args.duration if args.duration is not None else cycle.duration_s:g} s: {n:.3g} "
                         f"samples at the cycle's {cycle.dt_s:g} s steps, more than {MAX_SIMULATED_SAMPLES:.0e} (the "
                         "simulation keeps about 2 kB a sample; a shorter --duration or a longer dt_s in the cycle)")
    inputs = cycle_run(cycle, kt, args.duration)
    cmd = ["thermal-edge", "simulate", "--model", args.model, "--cycle", args.cycle]
    for e in args.effect:
        cmd += ["--effect", e]
    for item in args.set:
        cmd += ["--set", item]
    if args.duration is not None:
        cmd += ["--duration", f"{args.duration:g}"]
    if args.noise != 0.1:
        cmd += ["--noise", f"{args.noise:g}"]
    if args.resolution != 0.1:
        cmd += ["--resolution", f"{args.resolution:g}"]
    cmd += ["--seed", str(args.seed), "--out", args.out]
    comment = shlex.join(cmd)
    plant = model
    if args.effect:
        refs = E.references(model, inputs.columns)
        doc, resolved = hidden.plant_document(raw, args.effect, refs, build, inputs=inputs)
        plant = build(doc)
        desc = hidden.describe(resolved, refs)
        with np.errstate(over="ignore", invalid="ignore"):  # an absurd magnitude: refused below, by node and sample
            gap = hidden.sensor_gap(model, plant, inputs)
        if gap < hidden.MIN_GAP_K:  # even at its magnitude's bound: nothing for discover to find
            desc += (f"\nnote: the hidden effects move the sensors by at most {gap:.2f} K RMS (without noise, "
                     f"below {hidden.MIN_GAP_K:g} K): no sensor of the model may see them")
        comment += f"\n{desc}"
        print(desc)
    with np.errstate(over="ignore", invalid="ignore"):  # refused below, by node and sample
        res = simulate_plant(plant, inputs, parse_sets(model, args.set), noise_k=args.noise, resolution_k=args.resolution,
                             seed=args.seed, all_nodes=args.all_nodes or args.voltages)
    require_finite(plant, inputs, res.truth.T, "the simulated plant" + (" (with --effect)" if args.effect else ""))
    if args.voltages:
        pm = add_voltages(plant, res.run, args.seed, keep_nodes=args.all_nodes)
        comment += f"\nvoltages: {pm.describe()}"
    write_run(args.out, res.run, comment=comment)
    hot = {lim.name: float(res.truth.node(lim.node).max()) for lim in plant.limits}
    print(f"wrote {args.out}: {len(res.run)} samples at {cycle.dt_s:g} s; " +
          ("peak " + ", ".join(f"{k} {v:.1f} °C" for k, v in hot.items()) if hot else "the model declares no limits"))
    return 0


def run_can_log(args: argparse.Namespace) -> int:
    """The inverter's frames of a simulated run (open loop: no service answers) as a CAN log."""
    if args.effect:
        raise UsageError("--effect is not supported with --format can (the emulator plays the model file)")
    from ..lptn import load_model

    model = load_model(args.model, data_dir=args.data_dir)
    sets = parse_sets(model, args.set)
    sensor_signals = _sensor_signals(args.config, model)
    total = round(args.duration if args.duration is not None else load_cycle(args.cycle).duration_s)
    with bar(total, "simulate: CAN log", "s") as pb:
        def progress(elapsed_s: float) -> None:  # whole simulated seconds: a readable count
            if int(elapsed_s) > pb.n:
                pb.update(int(elapsed_s) - pb.n)

        st = write_log(args.model, args.cycle, args.out, params=sets, duration_s=args.duration,
                       noise_k=args.noise, resolution_k=args.resolution, seed=args.seed, t0=args.t0,
                       current_period_s=args.current_period, temperature_period_s=args.temperature_period,
                       progress=progress, pmsm=voltage_machine(model) if args.voltages else None,
                       sensor_signals=sensor_signals)
    peaks = ", ".join(f"{k} {v:.1f} °C" for k, v in st.true_max_c.items())
    print(f"wrote {args.out}: {sum(st.frames_sent.values())} frames over {st.sim_seconds:g} s; peak {peaks}")
    return 0


def _sensor_signals(config: str | None, model: Model) -> dict[str, str]:
    """The PT100 signals of the simulated inverter's INV_StatorTemps -> the model's sensors: as the
    configuration ``config`` maps them, else by the packaged model's names; a note on stdout names
    the model's sensors the log will not carry."""
    from ..sim.inverter import DEFAULT_SENSOR_SIGNALS, STATOR_FRAME, mapped_sensor_signals

    if config is None:
        mapping = dict(DEFAULT_SENSOR_SIGNALS)
    else:
        from ..config import load_config

        mapping = mapped_sensor_signals(load_config(config).sensors)
    unsent = [s for s in model.sensors if s not in mapping.values()]
    if unsent:
        print(f"note: the log carries no reading of {', '.join(unsent)}: the simulated inverter sends "
              f"{STATOR_FRAME}'s {', '.join(DEFAULT_SENSOR_SIGNALS)}" +
              (" as the configuration maps them" if config else "; --config EDGE_YAML maps the model's sensors onto them"))
    return mapping


def voltage_machine(model: Model) -> Pmsm:
    """The simulated electrical machine of ``model``: the package's, with the flux linkage of the
    model's torque constant (a model file holds no electrical data), said on stdout."""
    pm = Pmsm.with_kt(model.drive.get("kt_nm_per_arms"))
    print(f"voltages: the simulated machine has {pm.describe()}"
          + ("" if pm == Pmsm() else f" (the flux linkage from model {model.name}'s drive.kt_nm_per_arms, the rest "
                                      "the package's machine's)"))
    return pm


def add_voltages(model: Model, run: Run, seed: int, keep_nodes: bool) -> Pmsm:
    """Add ``u_d_v``, ``u_q_v`` (V peak, :func:`voltage_machine`) and ``pm`` (the mean true
    temperature of the model's magnet nodes, °C) to a simulated ``run`` that has every node's
    ``T_<node>``; the ``T_`` columns go unless ``keep_nodes``. Returns the machine used.

    The stator resistance is at the mean true temperature of the winding nodes: the copper the
    current flows through, not one sensor's reading."""
    def mean_of(role: NodeRole) -> np.ndarray:
        names = [n for n, r in model.node_roles.items() if r is role]
        if not names:
            raise UsageError(f"--voltages: model {model.name} declares no node with role {role.value}")
        return np.mean([np.asarray(run.columns[f"T_{n}"], dtype=float) for n in names], axis=0)

    c = run.columns
    winding, magnet = mean_of(NodeRole.WINDING), mean_of(NodeRole.MAGNET)
    pm = voltage_machine(model)
    u_d, u_q = pm.voltages(c[DEFAULT_COLUMNS[Role.CURRENT_D]], c[DEFAULT_COLUMNS[Role.CURRENT_Q]], c[SPEED],
                           winding, magnet, seed)
    if not keep_nodes:
        for k in [k for k in c if k.startswith("T_")]:
            del c[k]
    c["u_d_v"], c["u_q_v"], c["pm"] = u_d, u_q, magnet
    return pm
