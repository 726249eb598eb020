"""Benchmarks that need a checkout of the repository (``make bench-faults``, ``make bench-discovery``).

They drive the installed package from outside: processes started from the source tree, the
shipped systemd unit under ``deploy/``, test models under ``tests/``, data beside the checkout.
What runs from an installed package alone is ``thermal-edge bench``.
"""
from __future__ import annotations

from pathlib import Path

#: the checkout this directory belongs to
ROOT = Path(__file__).resolve().parents[1]
