"""What every fleet task does on its worker: load the model once per process, read one machine's
runs (run CSVs and CAN logs), and stamp the machine's rows with its wall time and the worker's peak
memory.

A machine that cannot be processed (a broken run, a failed fit) gives one ``error`` row naming
the machine, its files and the error, instead of failing the whole fleet's job.
"""
from __future__ import annotations

import functools
import resource
import time
from collections.abc import Callable
from typing import Any

from ..config import EdgeConfig, load_config
from ..data import Run, read_run
from ..lptn import Model, load_model
from ..service.logruns import is_can_log, read_log_runs
from ..shipped import config_path
from .results import row
from .runs import Machine, format_id


@functools.lru_cache(maxsize=4)
def cached_model(model_path: str, data_dir: str | None) -> Model:
    """The machine model, loaded once per worker process."""
    return load_model(model_path, data_dir=data_dir)


@functools.lru_cache(maxsize=4)
def can_config(path: str | None) -> EdgeConfig:
    """The service configuration that decodes the CAN logs (default: the shipped ``edge.yaml``),
    loaded once per worker process."""
    return load_config(path if path is not None else config_path("edge.yaml"))


def warm(model_path: str, data_dir: str | None) -> str:
    """Load the model into this worker's cache (``client.run``) so timing starts warm; its name."""
    return cached_model(model_path, data_dir).name


def read_machine_runs(machine: Machine, fmt: str, id_column: str | None, can_config_path: str | None = None) -> list[Run]:
    """The machine's runs; with ``id_column`` every row of its run CSVs must carry the machine's id.

    Parameters
    ----------
    fmt : str
        Format of the run CSVs (:data:`thermal_edge.data.FORMATS`).
    can_config_path : str, optional
        Service configuration whose ``signals:`` decode the CAN logs (default: the shipped one);
        a CAN log gives a run per stretch of traffic (:func:`thermal_edge.service.logruns.log_runs`).
    """
    runs: list[Run] = []
    for path in machine.runs:
        if is_can_log(path):  # its machine is its file or directory name
            runs += read_log_runs(path, can_config(can_config_path))
            continue
        run = read_run(path, fmt)
        if id_column:
            ids = {format_id(v) for v in run.column(id_column)}
            if ids != {machine.id}:
                raise KeyError(f"{run.source}: column {id_column} holds {', '.join(sorted(ids))}, expected only {machine.id}")
        runs.append(run)
    return runs


def peak_mb() -> float:
    """Peak resident memory of this process so far, MB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_machine(job: Callable[[], list[dict[str, Any]]], machine: Machine) -> list[dict[str, Any]]:
    """Run one machine's job; every row gets the task's wall and CPU time and the worker's peak memory."""
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        rows = job()
    except Exception as exc:  # one machine's failure must not end the fleet's job; it is reported
        text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)  # not KeyError's repr quotes
        msg = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
        rows = [row(machine=machine.id, kind="error", name=type(exc).__name__, message=msg, runs=";".join(machine.runs))]
    wall, cpu, mb = time.perf_counter() - t0, time.process_time() - c0, peak_mb()
    for r in rows:
        r["wall_s"], r["cpu_s"], r["worker_peak_mb"] = wall, cpu, mb
    return rows
