"""Fixtures of the benchmark tests: single-threaded BLAS (a busy 2-core host), and the lptn tests'
independent reference computations on the import path."""
from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "lptn"))
