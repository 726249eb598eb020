"""The Dask cluster the fleet runs on: an embedded ``LocalCluster`` (one single-threaded worker
process per core, everything on 127.0.0.1) or a running scheduler (``--scheduler tcp://HOST:8786``),
and the fan-out of one task per machine with a progress bar.
"""
from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TextIO

from . import require_fleet_extra
from .runs import Machine


def default_workers() -> int:
    """One worker process per core this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@contextmanager
def connect(scheduler: str | None = None, workers: int | None = None, log: TextIO = sys.stderr,
            wait_s: float = 60.0) -> Iterator[Any]:
    """A ``distributed.Client``: to ``scheduler``, or to a new ``LocalCluster`` of ``workers`` processes.

    Parameters
    ----------
    scheduler : str, optional
        Address of a running scheduler (``tcp://HOST:8786``); with ``workers`` the client waits
        (up to ``wait_s`` s) until that many workers have joined.
    workers : int, optional
        Worker processes of the local cluster (default: one per core).
    log : text stream
        Where the cluster and its dashboard address are announced.

    Raises
    ------
    MissingExtra
        Dask or pyarrow is not installed.
    OSError
        The scheduler cannot be reached.
    """
    require_fleet_extra()
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise OSError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        try:
            if workers:
                client.wait_for_workers(workers, timeout=wait_s)
            n = len(client.scheduler_info().get("workers", {}))
            log.write(f"fleet: Dask scheduler {scheduler}, {n} workers; dashboard {client.dashboard_link}\n")
            yield client
        finally:
            client.close()
        return
    bokeh = importlib.util.find_spec("bokeh") is not None
    n = workers or default_workers()
    # A task is one machine's numpy work: one thread per worker process; no memory limit, as the
    # worker's spilling and pausing are for large data, not for a few rows per machine. The
    # scheduler's HTTP server (the dashboard with bokeh, else only health and metrics) listens on
    # a free port of 127.0.0.1, never on all interfaces.
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", memory_limit=0) as cluster, \
            Client(cluster) as client:
        dash = client.dashboard_link if bokeh else "off (pip install bokeh to get it)"
        log.write(f"fleet: LocalCluster of {n} worker processes at {cluster.scheduler_address}; dashboard {dash}\n")
        yield client


def map_machines(client: Any, fn: Callable[..., list[dict[str, Any]]], machines: Sequence[Machine],
                 *per_machine: Sequence[Any], progress: bool = True, desc: str = "machines",
                 finished: Callable[[int], object] | None = None, **kwargs: Any) -> list[list[dict[str, Any]]]:
    """``fn(machine, *per_machine[i], **kwargs)`` as one Dask task per machine; the results in the
    machines' order.

    ``per_machine`` are sequences of one value per machine; ``progress`` shows a bar on a terminal
    (``tqdm`` on stderr) as the tasks complete; ``finished(count)`` is told the same count (a
    caller that draws its own progress).
    """
    from distributed import as_completed
    from tqdm import tqdm

    futures = client.map(fn, list(machines), *map(list, per_machine), pure=False, **kwargs)
    index = {f.key: i for i, f in enumerate(futures)}
    out: list[list[dict[str, Any]]] = [[] for _ in machines]
    with tqdm(total=len(futures), desc=desc, unit="machine", disable=None if progress else True,
              file=sys.stderr) as bar:
        for done, fut in enumerate(as_completed(futures), 1):
            out[index[fut.key]] = fut.result()
            bar.update(1)
            if finished is not None:
                finished(done)
    return out
