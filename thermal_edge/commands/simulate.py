"""``thermal-edge simulate``: run the simulated machine over a drive cycle and write the run."""
from __future__ import annotations

import argparse

from ..data import write_run
from ..sim.cycles import cycle_run, load_cycle
from ..sim.plant import simulate_plant
from .common import add_model_args, model_from_args


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("simulate", help="simulate the machine over a drive cycle", description=__doc__)
    add_model_args(p)
    p.add_argument("--cycle", required=True, help="drive cycle file (config/cycles/*.yaml)")
    p.add_argument("--out", required=True, help="output run CSV")
    p.add_argument("--duration", type=float, help="override the cycle's duration, s")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="plant parameter (repeatable)")
    p.add_argument("--noise", type=float, default=0.1, help="PT100 noise sigma, K (default 0.1)")
    p.add_argument("--resolution", type=float, default=0.1, help="PT100 quantisation, K (default 0.1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--all-nodes", action="store_true", help="also write every node's true temperature (T_<node>)")
    p.set_defaults(func=run)


def parse_params(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise KeyError(f"--param {item!r}: expected NAME=VALUE")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise KeyError(f"--param {item!r}: {value!r} is not a number") from None
    return out


def run(args: argparse.Namespace) -> int:
    model = model_from_args(args)
    cycle = load_cycle(args.cycle)
    kt = model.drive.get("kt_nm_per_arms")
    if kt is None:
        raise KeyError(f"model {model.name} has no drive.kt_nm_per_arms: cannot turn torque into current")
    inputs = cycle_run(cycle, kt, args.duration)
    res = simulate_plant(model, inputs, parse_params(args.param), noise_k=args.noise, resolution_k=args.resolution,
                         seed=args.seed, all_nodes=args.all_nodes)
    write_run(args.out, res.run, comment=f"thermal-edge simulate --model {args.model} --cycle {args.cycle}")
    hot = {lim.name: float(res.truth.node(lim.node).max()) for lim in model.limits}
    print(f"wrote {args.out}: {len(res.run)} samples at {cycle.dt_s:g} s; peak " +
          ", ".join(f"{k} {v:.1f} °C" for k, v in hot.items()))
    return 0
