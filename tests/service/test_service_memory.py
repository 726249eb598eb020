"""What the service keeps resident: only the libraries it uses on import, the heap's thresholds
fixed before the model and adapter allocate, and ``bench service`` reading the memory of the
service process itself."""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from thermal_edge.bench.service import memory_run, proc_memory

REPO = Path(__file__).resolve().parents[2]
#: imported by no module the service runs: fits (scipy.optimize, loaded when a fit runs), reports,
#: progress bars, the fleet
NOT_ON_THE_SERVICE_PATH = ("scipy.optimize", "matplotlib", "tqdm", "threadpoolctl", "dask", "pyarrow", "pandas")


def _modules_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport json, sys; print(json.dumps(sorted(sys.modules)))"],
                         cwd=REPO, capture_output=True, text=True, timeout=120, check=True)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def _present(modules: set[str]) -> list[str]:
    return [name for name in NOT_ON_THE_SERVICE_PATH if name in modules]


def test_the_service_path_imports_no_fit_report_or_fleet_library():
    modules = _modules_after("import thermal_edge.cli, thermal_edge.commands.run, thermal_edge.service, "
                             "thermal_edge.estimation.sqp, thermal_edge.estimation.gauss_newton")
    assert "thermal_edge.service" in modules and "thermal_edge.estimation.adapter" in modules
    assert _present(modules) == []
    # the check sees such an import: the offline calibration loads scipy.optimize with its module
    assert _present(_modules_after("import thermal_edge.estimation.calibrate")) == ["scipy.optimize"]


def test_proc_memory_reads_this_process_as_the_kernel_counts_it():
    mine = proc_memory()
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # the same high-water mark, another interface
    assert abs(mine["VmHWM"] - peak_kb * 1024 / 1e6) < 2.0
    assert 0 < mine["VmRSS"] <= mine["VmHWM"] + 1e-9
    assert mine["RssAnon"] + mine["RssFile"] <= mine["VmRSS"] + 1e-9


#: a child that touches ``big`` bytes and prints its own anonymous resident set (kB, its own /proc/self)
CHILD = """
import re, sys
b = bytearray(int(sys.argv[1]))
kb = int(re.search(r"RssAnon:\\s+(\\d+) kB", open("/proc/self/status").read()).group(1))
print(kb, flush=True)
input()
"""


def test_proc_memory_reads_another_process():
    big = 200_000_000  # bytes the child touches
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(big)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True)
    try:
        assert child.stdout is not None
        own_mb = int(child.stdout.readline()) * 1024 / 1e6  # what the child counted itself
        theirs = proc_memory(child.pid)
        assert theirs["RssAnon"] >= big / 1e6
        assert abs(theirs["RssAnon"] - own_mb) < 2.0  # the child's figure, not this process's
    finally:
        child.kill()
        child.wait()
    assert proc_memory(child.pid) == {}  # gone: nothing to read


def test_the_service_keeps_little_of_what_its_start_allocated(tmp_path):
    """The model's and the adapter's temporaries at construction go back to the system: without the
    heap's thresholds fixed first, glibc kept about 30 MB of them resident (measured: RssAnon
    +32 MB across the construction, +8 MB with them)."""
    code = f"""
import asyncio, json
from pathlib import Path
from thermal_edge.bench.service import _config, proc_memory
from thermal_edge.service import EdgeService
cfg = _config(Path({str(tmp_path)!r}), {{"interface": "virtual", "channel": "mem-{os.getpid()}"}}, adapt=True)
before = proc_memory()["RssAnon"]
svc = EdgeService(cfg, serve_metrics=False)
print(json.dumps(proc_memory()["RssAnon"] - before))
"""
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300, check=True)
    grown = json.loads(out.stdout.strip().splitlines()[-1])
    assert grown < 20.0, grown


@pytest.mark.slow
def test_bench_memory_run_measures_the_service_process(udp_ok):
    t = time.monotonic()
    r = memory_run(hours=0.1)
    assert r["service_pid"] != os.getpid()
    assert r["flow_timeouts"] == 0 and r["rx_lost"] == 0
    h, rss, hwm = r["rss_samples"][-1]
    assert h == pytest.approx(0.1, abs=1e-3) and rss == pytest.approx(r["rss_mb"], abs=0.05)
    assert 0 < r["at_start"]["VmRSS"] <= hwm and rss <= hwm
    assert proc_memory(r["service_pid"]) == {}  # the service was stopped
    assert time.monotonic() - t < 600


def test_release_free_heap_gives_freed_arrays_back():
    code = """
import json
import numpy as np
from thermal_edge.bench.service import proc_memory
from thermal_edge.service.memory import limit_heap_retention, release_free_heap
limit_heap_retention()
arrays = [np.ones(12_000) for _ in range(3000)]  # 96 kB each, below the mmap threshold: from the heap
keep = arrays[-1]
del arrays  # freed inside the heap, below the array kept at its top: not trimmed by free()
before = proc_memory()["RssAnon"]
released = release_free_heap()
print(json.dumps([released, before - proc_memory()["RssAnon"]]))
"""
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120, check=True)
    released, dropped_mb = json.loads(out.stdout.strip().splitlines()[-1])
    assert released and dropped_mb > 200.0, dropped_mb  # of the 288 MB freed
