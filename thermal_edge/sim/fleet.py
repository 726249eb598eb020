"""A simulated fleet: N machines of one design with a manufacturing spread, a few of them faulty.

Every machine is the design's model with its adaptable parameters drawn from a log-normal spread
around the nominal values (σ of ``log θ`` = :data:`SPREAD_REL`, truncated at
:data:`SPREAD_TRUNC` σ, so at most ±13 %: well inside the paper's Table 4 variations, which are
the extreme a design's own parameters may be off by). A few machines carry a fault that
multiplies one parameter (:data:`FAULTS`): a degraded housing-to-ambient path (fouled fins,
``R_e_hous`` × 1.5) or aged slot-winding insulation (delaminated liner, ``r_ins_sw`` × 2).

Each machine runs the drive cycle started at its own (seeded) point, with its own ambient offset
and sensor noise, and is written as one run CSV (``<id>.csv``, one machine per file). The truth
(parameters, faults) goes to ``manifest.json`` for tests and benchmarks; the fleet commands never
read it.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data import Run, write_run
from ..lptn import Model
from .cycles import AMBIENT, COOLANT, Cycle, cycle_run
from .plant import simulate_plant

#: manufacturing spread: σ of log θ for every adaptable parameter
SPREAD_REL = 0.05
#: the spread is truncated at this many σ
SPREAD_TRUNC = 2.5
#: fault kind -> (parameter, factor, description)
FAULTS: dict[str, tuple[str, float, str]] = {
    "housing_path": ("R_e_hous", 1.5, "degraded housing-to-ambient path (fouled fins)"),
    "winding_insulation": ("r_ins_sw", 2.0, "aged slot-winding insulation"),
}
#: faulty machines of a fleet, by default
FAULTY = 5
#: a machine's ambient differs from the cycle's by up to this much, K
AMBIENT_OFFSET_K = 3.0
MANIFEST = "manifest.json"


@dataclass
class MachineSpec:
    """One simulated machine: its id, seed, true parameters and fault (if any)."""

    id: str
    seed: int
    params: dict[str, float]
    start_s: float
    ambient_offset_k: float
    fault: dict[str, object] | None = field(default=None)


def plan_fleet(model: Model, n: int, faulty: int = FAULTY, seed: int = 0) -> list[MachineSpec]:
    """Draw ``n`` machines of ``model`` (``faulty`` of them with a fault, kinds alternating).

    Parameters
    ----------
    n : int
        Machines.
    faulty : int
        Machines with a fault (at most ``n``); which ones is drawn from ``seed``.
    seed : int
        Seed of the whole fleet: the same seed gives the same machines.
    """
    if n < 1:
        raise KeyError(f"--fleet {n}: need at least one machine")
    missing = [p for p, _, _ in FAULTS.values() if p not in model.parameter_names]
    if faulty and missing:
        raise KeyError(f"model {model.name} has no parameter(s) {', '.join(missing)} for the fleet's faults")
    rng = np.random.default_rng(seed)
    nominal = dict(zip(model.parameter_names, model.nominal()))
    lo, hi = model.bounds()
    idx = model.parameter_index(model.adaptable)
    width = len(str(n - 1))
    bad = set(rng.choice(n, size=min(faulty, n), replace=False).tolist())
    kinds = list(FAULTS)
    specs, k = [], 0
    for i in range(n):
        z = np.clip(rng.standard_normal(len(idx)), -SPREAD_TRUNC, SPREAD_TRUNC)
        vals = np.clip(model.nominal()[idx] * np.exp(SPREAD_REL * z), lo[idx], hi[idx])
        params = {name: float(v) for name, v in zip(model.adaptable, vals)}
        fault = None
        if i in bad:
            kind = kinds[k % len(kinds)]
            k += 1
            pname, factor, desc = FAULTS[kind]
            j = model.parameter_index([pname])[0]
            params[pname] = float(min(params.get(pname, nominal[pname]) * factor, hi[j]))
            fault = {"kind": kind, "parameter": pname, "factor": factor, "description": desc}
        specs.append(MachineSpec(f"m{i:0{width}d}", int(rng.integers(2**31)), params,
                                 float(rng.uniform(0.0, 1.0)), float(rng.uniform(-1, 1) * AMBIENT_OFFSET_K), fault))
    return specs


def machine_run(model: Model, cycle: Cycle, spec: MachineSpec, duration_s: float,
                noise_k: float = 0.1, resolution_k: float = 0.1) -> Run:
    """The run of one machine: the cycle from the machine's start point for ``duration_s``."""
    kt = model.drive.get("kt_nm_per_arms")
    if kt is None:
        raise KeyError(f"model {model.name} has no drive.kt_nm_per_arms: cannot turn torque into current")
    offset = int(spec.start_s * cycle.duration_s / cycle.dt_s)  # samples into the (repeated) cycle
    n = int(round(duration_s / cycle.dt_s)) + 1
    full = cycle_run(cycle, kt, (offset + n) * cycle.dt_s + cycle.duration_s)
    inp = full.slice(offset, offset + n)
    cols = dict(inp.columns)
    for c in (AMBIENT, COOLANT):
        cols[c] = cols[c] + spec.ambient_offset_k
    inputs = Run(np.arange(n) * cycle.dt_s, cols, f"fleet:{spec.id}")
    return simulate_plant(model, inputs, spec.params, noise_k=noise_k, resolution_k=resolution_k, seed=spec.seed).run


def write_machine(model: Model, cycle: Cycle, spec: MachineSpec, out_dir: str | os.PathLike[str],
                  duration_s: float, noise_k: float = 0.1, resolution_k: float = 0.1) -> str:
    """Simulate one machine and write ``<out_dir>/<id>.csv``; returns the path."""
    path = Path(out_dir) / f"{spec.id}.csv"
    run = machine_run(model, cycle, spec, duration_s, noise_k, resolution_k)
    write_run(path, run, comment=f"machine {spec.id} of a simulated {model.name} fleet, seed {spec.seed}")
    return str(path)


def write_manifest(out_dir: str | os.PathLike[str], model_path: str, cycle_path: str, specs: list[MachineSpec],
                   duration_s: float, seed: int) -> Path:
    """The fleet's truth (parameters, faults) as ``manifest.json``: for tests, never read by ``fleet``."""
    path = Path(out_dir) / MANIFEST
    doc = {
        "model": str(model_path), "cycle": str(cycle_path), "duration_s": duration_s, "seed": seed,
        "spread_rel": SPREAD_REL, "spread_trunc": SPREAD_TRUNC,
        "faults": {k: {"parameter": p, "factor": f, "description": d} for k, (p, f, d) in FAULTS.items()},
        "machines": [asdict(s) for s in specs],
    }
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def read_manifest(out_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """The manifest written by :func:`write_manifest`."""
    return json.loads((Path(out_dir) / MANIFEST).read_text())
