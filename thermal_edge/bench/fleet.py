"""``thermal-edge bench fleet``: the fleet's cost on Dask and its outlier screen's hits.

A simulated fleet (:mod:`thermal_edge.sim.fleet`) of pm10kw machines, each 3 h of the varied drive
cycle at 1 Hz, is written by the cluster itself. Then:

* the same ``speed_machines`` machines are calibrated on a local cluster of 1 worker process and
  of 2 (both started and warmed before the clock starts, taking turns for ``rounds`` rounds):
  the per-machine cost (wall with one worker, and CPU) and the speed-up of the second worker;
* the whole fleet is calibrated and screened with 2 workers: hits (faulty machines named with the
  faulty parameter), misses and false alarms, against the fleet's manifest (which only the bench
  and the tests read);
* the projection to a fleet of ``project_machines`` machines × one day at 1 Hz on clusters of
  several sizes, from the measured CPU time per machine scaled by the samples (the calibration's
  cost is linear in the run's length); the machines' tasks are independent.

The machine's load average is reported: other work on the machine lowers the speed-up.
"""
from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..fleet.calibrate import calibrate_machine
from ..fleet.cluster import connect, map_machines
from ..fleet.runs import find_machines
from ..fleet.screen import THRESHOLD, screen
from ..fleet.task import cached_model, warm
from ..lptn import load_model
from ..shipped import config_path
from ..sim.cycles import load_cycle
from ..sim.fleet import FAULTY, plan_fleet, read_manifest, write_machine, write_manifest
from ..text_table import table
from .common import Progress, no_progress

#: the parameters the bench's fleet is calibrated on: those pm10kw's three sensors pin down
#: (with the winding conductivities free as well, r_ins_sw's σ exceeds 100 %)
FLEET_PARAMS = ("c_p_sw", "c_p_ew", "r_ins_sw", "r_ins_ew", "R_e_hous", "R_e_cap", "c_p_hous", "r_c_hous")
MODEL = "machines/pm10kw.yaml"
CYCLE = "cycles/varied_drive.yaml"
#: cores of the clusters in the projection
CLUSTER_CORES = (8, 64, 256)
DAY_S = 86400.0
#: defaults: machines of the fleet, machines timed with 1 and 2 workers, rounds of the timing
MACHINES, SPEED_MACHINES, ROUNDS = 200, 20, 2


def _write(spec: Any, model_path: str, cycle_path: str, out_dir: str, duration_s: float) -> str:
    return write_machine(cached_model(model_path, None), load_cycle(cycle_path), spec, out_dir, duration_s)


def make_fleet(client: Any, out: Path, machines: int, faulty: int, seed: int, duration_s: float,
               progress: Progress = no_progress) -> None:
    """Write a simulated fleet into ``out``, one machine per task on ``client``; ``progress`` counts
    the machines written."""
    from distributed import as_completed

    model_path, cycle_path = str(config_path(MODEL)), str(config_path(CYCLE))
    specs = plan_fleet(load_model(model_path), machines, faulty, seed)
    out.mkdir(parents=True, exist_ok=True)
    futures = client.map(_write, specs, model_path=model_path, cycle_path=cycle_path, out_dir=str(out),
                         duration_s=duration_s, pure=False)
    for k, fut in enumerate(as_completed(futures), 1):
        fut.result()
        progress("write the fleet", k, len(specs), "machine")
    write_manifest(out, model_path, cycle_path, specs, duration_s, seed)


def _calibrate(client: Any, machines: Sequence[Any], stage: str,
               progress: Progress) -> tuple[float, list[dict[str, Any]]]:
    model_path = str(config_path(MODEL))
    client.run(warm, model_path, None)
    t0 = time.perf_counter()
    per = map_machines(client, calibrate_machine, machines, progress=False, model_path=model_path,
                       params=list(FLEET_PARAMS), finished=lambda k: progress(stage, k, len(machines), "machine"))
    return time.perf_counter() - t0, [r for rows in per for r in rows]


@dataclass
class FleetResult:
    """``bench fleet``: cost, speed-up, memory and the outlier screen's hits (times in s, memory in MB)."""

    machines: int
    speed_machines: int  #: machines timed with 1 and with 2 workers
    samples_per_machine: int
    params: list[str]  #: the parameters fitted per machine
    per_machine_s: float
    per_machine_cpu_s: float
    wall_1_worker_s: list[float]  #: by round
    wall_2_workers_s: list[float]
    speedup_2_workers: float  #: median of the rounds' ratios
    speedup_rounds: list[float]
    wall_fleet_2_workers_s: float
    make_fleet_s: float
    peak_worker_mb: float
    errors: int  #: machines not processed
    faulty_total: int
    faulty_found: int  #: found with the right parameter
    faulty_wrong_parameter: int
    false_alarms: int
    max_healthy_z: float
    min_faulty_z: float
    threshold: float
    outliers: list[dict[str, Any]]
    spread: list[dict[str, Any]]
    load_avg_start: list[float]
    load_avg_end: list[float]
    projection: dict[str, Any]


def run(machines: int = MACHINES, faulty: int = FAULTY, speed_machines: int = SPEED_MACHINES, rounds: int = ROUNDS,
        hours: float = 3.0, seed: int = 0, threshold: float = THRESHOLD, project_machines: int = 10_000,
        cluster_cores: Sequence[int] = CLUSTER_CORES, workdir: str | None = None,
        progress: Progress = no_progress) -> FleetResult:
    """Run the fleet benchmark; see the module docstring. Times in s, memory in MB; ``progress``
    counts the machines of each part.

    The 1-worker and 2-worker clusters run side by side and take turns on the same machines for
    ``rounds`` rounds, so that a change of the shared machine's load falls on both alike; the
    speed-up is the median of the rounds' ratios.
    """
    load_start = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="te-fleet-", dir=workdir) as tmp:
        out = Path(tmp) / "fleet"
        t0 = time.perf_counter()
        with connect(workers=2) as client:
            make_fleet(client, out, machines, faulty, seed, hours * 3600.0, progress)
        make_s = time.perf_counter() - t0
        fleet = find_machines([str(out / "*.csv")])
        subset = fleet[:speed_machines]
        t1s, t2s, cpu = [], [], []
        with connect(workers=1) as one, connect(workers=2) as two:
            for k in range(1, rounds + 1):
                t1, rows1 = _calibrate(one, subset, f"round {k} of {rounds}, 1 worker", progress)
                t2, _ = _calibrate(two, subset, f"round {k} of {rounds}, 2 workers", progress)
                t1s.append(t1)
                t2s.append(t2)
                cpu += [r["cpu_s"] for r in rows1 if r["kind"] == "parameter" and r["name"] == FLEET_PARAMS[0]]
            t_all, rows = _calibrate(two, fleet, "whole fleet, 2 workers", progress)
        manifest = read_manifest(out)
    load_end = os.getloadavg()
    spreads, outliers = screen(rows, threshold)
    truth = {m["id"]: m["fault"] for m in manifest["machines"]}
    hits = [o for o in outliers if truth.get(o.machine) and truth[o.machine]["parameter"] == o.parameter]
    wrong = [o for o in outliers if truth.get(o.machine) and truth[o.machine]["parameter"] != o.parameter]
    false = [o for o in outliers if not truth.get(o.machine)]
    samples = max(r["samples"] or 0 for r in rows if r["kind"] == "parameter")
    per_machine_s = statistics.median(t1s) / len(subset)
    per_machine_cpu_s = statistics.median(cpu)
    speedup = statistics.median(a / b for a, b in zip(t1s, t2s))
    day_s = per_machine_cpu_s * DAY_S / samples  # one machine-day at 1 Hz on a core of its own
    projection = [{"cores": c, "hours": project_machines * day_s / c / 3600.0} for c in cluster_cores]
    return FleetResult(
        machines=len(fleet),
        speed_machines=len(subset),
        samples_per_machine=samples,
        params=list(FLEET_PARAMS),
        per_machine_s=per_machine_s,
        per_machine_cpu_s=per_machine_cpu_s,
        wall_1_worker_s=t1s,
        wall_2_workers_s=t2s,
        speedup_2_workers=speedup,
        speedup_rounds=[a / b for a, b in zip(t1s, t2s)],
        wall_fleet_2_workers_s=t_all,
        make_fleet_s=make_s,
        peak_worker_mb=max(r["worker_peak_mb"] for r in rows),
        errors=sum(r["kind"] == "error" for r in rows),
        faulty_total=sum(1 for f in truth.values() if f),
        faulty_found=len(hits),
        faulty_wrong_parameter=len(wrong),
        false_alarms=len(false),
        max_healthy_z=max(abs(r["z"]) for r in rows if r["kind"] == "parameter" and not truth.get(r["machine"])),
        min_faulty_z=min((abs(o.z) for o in hits), default=float("nan")),
        threshold=threshold,
        outliers=[{"machine": o.machine, "parameter": o.parameter, "z": o.z, "ratio": o.ratio,
                   "fault": (truth.get(o.machine) or {}).get("kind")} for o in outliers],
        spread=[{"parameter": s.parameter, "median": s.median, "spread_rel": s.spread_rel,
                 "identifiable": s.identifiable} for s in spreads],
        load_avg_start=list(load_start),
        load_avg_end=list(load_end),
        projection={"machines": project_machines, "day_s": DAY_S, "machine_day_core_s": day_s,
                    "clusters": projection},
    )


def format_result(r: FleetResult) -> str:
    """The benchmark's tables as text."""
    p = r.projection
    lines = [
        f"fleet of {r.machines} simulated pm10kw machines, {r.samples_per_machine} samples (1 Hz) each; "
        f"{len(r.params)} parameters fitted per machine; load average {r.load_avg_start[0]:.1f} at the start, "
        f"{r.load_avg_end[0]:.1f} at the end (2 cores)",
        table(["measure", "value"], [
            ["per machine, 1 worker: wall (s)", r.per_machine_s],
            ["per machine: CPU (s)", r.per_machine_cpu_s],
            [f"{r.speed_machines} machines, 1 worker (s), by round", ", ".join(f"{t:.1f}" for t in r.wall_1_worker_s)],
            [f"{r.speed_machines} machines, 2 workers (s), by round", ", ".join(f"{t:.1f}" for t in r.wall_2_workers_s)],
            ["speed-up of 2 workers (median of the rounds)", r.speedup_2_workers],
            [f"{r.machines} machines, 2 workers (s)", r.wall_fleet_2_workers_s],
            ["peak worker RSS (MB)", r.peak_worker_mb],
            ["machines not processed", r.errors],
            [f"faulty found, right parameter (|z| > {r.threshold:g})", f"{r.faulty_found} of {r.faulty_total}"],
            ["faulty named with another parameter", r.faulty_wrong_parameter],
            ["false alarms (healthy machines)", r.false_alarms],
            ["largest |z| of a healthy machine", r.max_healthy_z],
            ["smallest |z| of a faulty machine found", r.min_faulty_z],
        ]),
        table(["machine", "parameter", "z", "x fleet median", "true fault"],
              [[o["machine"], o["parameter"], o["z"], o["ratio"], o["fault"] or "-"] for o in r.outliers]),
        f"projection: {p['machines']} machines x 1 day at 1 Hz, {p['machine_day_core_s']:.1f} core-s per machine-day "
        "(the per-machine CPU time scaled by the samples; the tasks are independent)",
        table(["cluster cores", "hours"], [[c["cores"], c["hours"]] for c in p["clusters"]]),
    ]
    return "\n\n".join(lines)
