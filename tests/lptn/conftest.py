"""Shared fixtures for the LPTN maths tests.

Models:
* ``tiny``: the small arc model of the test brief (two arcs, one lumped node, one boundary),
  built from a dict with :func:`thermal_edge.lptn.loader.build_model`.
* ``paderborn4``: ``config/machines/paderborn4.yaml`` with the measured tables of
  ``../shared/data/paderborn`` (skipped visibly when that directory is absent).
* ``pm10kw``: ``config/machines/pm10kw.yaml`` (skipped visibly when the file is absent).

Independent reference computations (Laplacian assembly, continuous right-hand side) live in
``lptn_ref.py`` next to this file; they never call ``Network.continuous`` or ``discretise``.
"""
from __future__ import annotations

import os

# The batched small eigen-decompositions and products of these tests are ~100x slower when
# OpenBLAS spreads them over threads on a busy 2-core machine (measured: eigh of 40 39x39
# matrices 5 ms single-threaded, 0.35-0.65 s with 2 threads under load). Must be set before
# numpy is first imported; an explicit setting in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest
from lptn_ref import PADERBORN_DIR, PADERBORN_YAML, PM10KW_YAML, require_paderborn, require_pm10kw, tiny_plus_raw, tiny_raw

from thermal_edge.lptn import load_model
from thermal_edge.lptn.loader import build_model


@pytest.fixture
def tiny_model():
    return build_model(tiny_raw(), fname="tiny.yaml")


@pytest.fixture
def tiny_plus_model():
    return build_model(tiny_plus_raw(), fname="tiny_plus.yaml")


@pytest.fixture(scope="session")
def paderborn_model():
    d = require_paderborn()
    return load_model(PADERBORN_YAML, data_dir=d)


@pytest.fixture(scope="session")
def paderborn_run():
    from thermal_edge.data import read_run

    d = require_paderborn()
    return read_run(d / "run_a.csv", "paderborn")


@pytest.fixture(scope="session")
def pm10kw_model():
    path = require_pm10kw()
    data_dir = PADERBORN_DIR if PADERBORN_DIR.is_dir() else None
    try:
        return load_model(path, data_dir=data_dir)
    except Exception as exc:  # being written right now: a broken file is a visible skip, not an error
        pytest.skip(f"{path.name} does not load yet: {exc}")


def pytest_report_header(config):  # visible in the run header: what data the suite found
    return [
        f"lptn: paderborn data {'found' if PADERBORN_DIR.is_dir() else 'ABSENT'} at {PADERBORN_DIR}",
        f"lptn: pm10kw.yaml {'found' if PM10KW_YAML.exists() else 'ABSENT'}",
    ]

