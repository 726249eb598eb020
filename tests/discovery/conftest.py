"""Fixtures of the discovery tests: the 10 kW model document and plant runs with hidden effects.

Runs are simulated from the drive cycles with PT100 noise (0.1 K, 0.1 K quantisation); the
Paderborn cases are skipped visibly when ``../shared/data/paderborn/run_a.csv`` is absent.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest

from benchmarks import discovery as bench
from thermal_edge.discovery import hidden


@pytest.fixture(scope="session")
def pm10kw_raw():
    if not bench.PM10KW.exists():
        pytest.skip(f"{bench.PM10KW} not found")
    return hidden.read_document(bench.PM10KW)


@pytest.fixture(scope="session")
def pm10kw_build():
    return hidden.builder(bench.PM10KW)


@pytest.fixture(scope="session")
def paderborn_run_path():
    if not bench.PADERBORN_RUN.exists():
        pytest.skip(f"Paderborn data not found at {bench.PADERBORN_RUN}")
    return bench.PADERBORN_RUN
