"""``thermal-edge demo``: the 10 kW machine over a drive cycle, printing its hot spots."""
from __future__ import annotations

import argparse

from ..bench.common import config_path
from ..lptn import load_model
from ..sim.cycles import cycle_run, load_cycle
from ..sim.plant import simulate_plant


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("demo", help="simulate the 10 kW machine over a drive cycle", description=__doc__)
    p.add_argument("--model", default=str(config_path("machines", "pm10kw.yaml")))
    p.add_argument("--cycle", default=str(config_path("cycles", "varied_drive.yaml")))
    p.add_argument("--every", type=float, default=600.0, help="print interval, s")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    model = load_model(args.model)
    cycle = load_cycle(args.cycle)
    res = simulate_plant(model, cycle_run(cycle, model.drive["kt_nm_per_arms"]), noise_k=0.0, resolution_k=0.0)
    t = res.run.t
    cols = res.run.columns
    step = max(1, int(round(args.every / cycle.dt_s)))
    names = [lim.name for lim in model.limits]
    print(f"{model.name} over {cycle.name} ({cycle.duration_s / 3600:.1f} h)")
    print(f"{'t min':>7}{'rpm':>7}{'Nm':>7}" + "".join(f"{n + ' °C':>14}" for n in names))
    for k in range(0, len(t), step):
        temps = "".join(f"{res.truth.node(lim.node)[k]:>14.1f}" for lim in model.limits)
        print(f"{t[k] / 60:>7.0f}{cols['speed_rpm'][k]:>7.0f}{cols['torque_nm'][k]:>7.0f}{temps}")
    peaks = ", ".join(f"{lim.name} {res.truth.node(lim.node).max():.1f} °C (max {lim.max_c:g})" for lim in model.limits)
    print(f"peaks: {peaks}")
    return 0
