"""``thermal-edge simulate … --format candump``: the inverter frames of a simulated run as a
``candump -L`` log (decodable with ``python -m cantools decode dbc/thermal_edge.dbc``).

This module extends the ``simulate`` sub-command registered by :mod:`.simulate` with
``--format {csv,candump}`` (and two frame-period options) without changing it; registered after
it in ``COMMANDS``. The frames come from :func:`thermal_edge.sim.inverter.write_candump`
(open loop: no service answers), timestamps in simulated time from ``--t0``.
"""
from __future__ import annotations

import argparse

from ..sim.inverter import write_candump


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.choices.get("simulate")
    if p is None or any(a.dest == "format" for a in p._actions):
        return  # no simulate command, or it already has --format
    p.add_argument("--format", choices=("csv", "candump"), default="csv",
                   help="csv: run CSV (default); candump: the inverter's CAN frames as a candump -L log")
    p.add_argument("--current-period", type=float, default=0.01,
                   help="candump: INV_Currents/INV_Mechanics period, s (default 0.01 as the DBC)")
    p.add_argument("--temperature-period", type=float, default=0.1,
                   help="candump: INV_StatorTemps/INV_AmbientTemps period, s (default 0.1)")
    p.add_argument("--t0", type=float, default=1.7e9, help="candump: timestamp of the first frame, s since the epoch")
    csv_func = p.get_default("func")

    def func(args: argparse.Namespace) -> int:
        if args.format != "candump":
            return int(csv_func(args) or 0)
        return run_candump(args)

    p.set_defaults(func=func)


def run_candump(args: argparse.Namespace) -> int:
    from .simulate import parse_params

    s = write_candump(args.model, args.cycle, args.out, params=parse_params(args.param), duration_s=args.duration,
                      noise_k=args.noise, resolution_k=args.resolution, seed=args.seed, t0=args.t0,
                      current_period_s=args.current_period, temperature_period_s=args.temperature_period)
    n = sum(s.frames_sent.values())
    peaks = ", ".join(f"{k} {v:.1f} °C" for k, v in s.true_max_c.items())
    print(f"wrote {args.out}: {n} frames over {s.sim_seconds:g} s (candump -L); peak {peaks}")
    return 0
