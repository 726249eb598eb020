"""Recorded runs: the run CSV of ``DESIGN.md`` §5 and the Paderborn data set's CSV.

A run is one row per sample: column ``t`` (s), input columns (``speed_rpm``, ``i_d``, ``i_q``,
``i_rms``, ``torque_nm``, ``ambient_c``, ``coolant_c``, …) and one column per sensor named as the
machine model names it. NaN means "not measured".

The Paderborn files (``--format paderborn``) have no units in their names, currents as d/q
amplitudes and, in the subset we read, no time column: the adapter renames the columns, adds
``i_rms = sqrt(i_d² + i_q²)/sqrt(2)`` and takes ``t`` from a ``t`` column when there is one, else
2.5 s × row.
"""
from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

FORMATS = ("csv", "paderborn")
PADERBORN_ROW_S = 2.5
PADERBORN_COLUMNS = {
    "motor_speed": "speed_rpm",
    "torque": "torque_nm",
    "ambient": "ambient_c",
    "coolant": "coolant_c",
    "u_d": "u_d_v",
    "u_q": "u_q_v",
}


class RunError(ValueError):
    """A run file that cannot be read; the message names the file (and row or column)."""


@dataclass
class Run:
    """A recorded or simulated run: sample times and named columns of equal length."""

    t: np.ndarray
    columns: dict[str, np.ndarray]
    source: str = ""
    meta: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def dt(self) -> float:
        """The (uniform) sample period, s; raises :class:`RunError` if the spacing varies."""
        if len(self.t) < 2:
            return 1.0
        d = np.diff(self.t)
        dt = float(np.median(d))
        if not np.allclose(d, dt, rtol=1e-6, atol=1e-6):
            raise RunError(f"{self.source}: sample times are not uniformly spaced (median {dt:g} s)")
        return dt

    def column(self, name: str) -> np.ndarray:
        try:
            return self.columns[name]
        except KeyError:
            raise RunError(f"{self.source}: no column {name!r} (has: {', '.join(self.columns)})") from None

    def slice(self, start: int, stop: int) -> "Run":
        """Samples ``start:stop`` as a new run (views, not copies)."""
        return Run(self.t[start:stop], {k: v[start:stop] for k, v in self.columns.items()}, self.source, dict(self.meta))


def read_run(path: str | os.PathLike[str], fmt: str = "csv") -> Run:
    """Read a run file.

    Parameters
    ----------
    path : path-like
        CSV file.
    fmt : {"csv", "paderborn"}
        ``csv``: our run format (needs a ``t`` column). ``paderborn``: the Paderborn data set.
    """
    path = Path(path)
    if fmt not in FORMATS:
        raise RunError(f"{path}: unknown format {fmt!r} (known: {', '.join(FORMATS)})")
    try:
        with open(path, newline="") as fh:
            rows = [r for r in csv.reader(line for line in fh if not line.startswith("#")) if r]
    except OSError as exc:
        raise RunError(f"{path}: cannot read: {exc.strerror}") from None
    if len(rows) < 2:
        raise RunError(f"{path}: no data rows")
    header = [h.strip() for h in rows[0]]
    try:
        data = np.array([[float(v) if v.strip() not in ("", "nan", "NaN") else math.nan for v in r] for r in rows[1:]])
    except ValueError as exc:
        raise RunError(f"{path}: not a number: {exc}") from None
    if data.ndim != 2 or data.shape[1] != len(header):
        raise RunError(f"{path}: rows do not all have {len(header)} columns")
    cols = {h: data[:, i].copy() for i, h in enumerate(header)}
    if fmt == "paderborn":
        return _paderborn(cols, str(path))
    if "t" not in cols:
        raise RunError(f"{path}: no column 't' (seconds); for the Paderborn data use --format paderborn")
    t = cols.pop("t")
    return Run(t, cols, str(path))


def _paderborn(cols: dict[str, np.ndarray], source: str) -> Run:
    n = len(next(iter(cols.values())))
    t = cols.pop("t") if "t" in cols else np.arange(n) * PADERBORN_ROW_S
    out = {PADERBORN_COLUMNS.get(k, k): v for k, v in cols.items()}
    if "i_d" in out and "i_q" in out:
        out["i_rms"] = np.hypot(out["i_d"], out["i_q"]) / math.sqrt(2.0)  # amplitude -> RMS
    return Run(t, out, source, {"format": "paderborn"})


def write_run(path: str | os.PathLike[str], run: Run, comment: str = "") -> None:
    """Write a run in our CSV format (``t`` first; NaN for missing values)."""
    path = Path(path)
    names = list(run.columns)
    data = np.column_stack([run.t] + [run.columns[k] for k in names])
    with open(path, "w", newline="") as fh:
        for line in comment.splitlines():
            fh.write(f"# {line}\n")
        w = csv.writer(fh)
        w.writerow(["t"] + names)
        for row in data:
            w.writerow([f"{v:.6g}" if np.isfinite(v) else "nan" for v in row])
