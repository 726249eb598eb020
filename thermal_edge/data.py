"""Recorded runs: the run CSV (``docs/guide/commands.md``) and the Paderborn data set's CSV.

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
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ThermalEdgeError
from .lptn.vocabulary import TEMPERATURE, Plausible, Role
from .yamlfile import SNIFF_BYTES, decode_text

FORMATS = ("csv", "paderborn")
PADERBORN_ROW_S = 2.5
#: the Paderborn data set's columns under the usual names of the model's inputs
PADERBORN_COLUMNS = {
    "motor_speed": Role.SPEED.default_column,
    "torque": Role.TORQUE.default_column,
    "ambient": Role.AMBIENT.default_column,
    "coolant": Role.COOLANT.default_column,
    "u_d": "u_d_v",
    "u_q": "u_q_v",
}


class RunError(ThermalEdgeError, ValueError):
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
        off = np.flatnonzero(~np.isclose(d, dt, rtol=1e-6, atol=1e-6))
        if off.size:
            k = int(off[0]) + 1
            raise RunError(f"{self.source}: column 't', sample {k + 1} (t = {self.t[k]:g} s): sample times are not "
                           f"uniformly spaced (median period {dt:g} s, here {d[k - 1]:g} s)")
        return dt

    def column(self, name: str) -> np.ndarray:
        try:
            return self.columns[name]
        except KeyError:
            raise RunError(f"{self.source}: no column {name!r} (has: {', '.join(self.columns)})") from None

    def slice(self, start: int, stop: int) -> Run:
        """Samples ``start:stop`` as a new run (views, not copies)."""
        return Run(self.t[start:stop], {k: v[start:stop] for k, v in self.columns.items()}, self.source, dict(self.meta))


#: A line of a ``candump -L`` log: ``(1700000000.000000) can0 123#11223344``.
CANDUMP_LINE = re.compile(r"^\s*\(\d+\.\d+\)\s+\S+\s+[0-9A-Fa-f]+#")
#: Separators of other exports, named in the message when a header is one column holding them.
SEPARATORS = {";": "semicolons (';')", "\t": "tabs", "|": "vertical bars ('|')"}
#: Encodings of a run CSV: UTF-8 (the encoding policy of :mod:`thermal_edge.yamlfile`), else
#: Windows-1252, the usual test-bench export with "°C" or "Prüfstand" (it decodes every Latin-1
#: text byte the same way).
FALLBACK_ENCODINGS = ("cp1252",)


def _text(path: Path) -> str:
    try:
        raw = path.read_bytes()
    except IsADirectoryError:
        raise RunError(f"{path}: is a directory, not a run file") from None
    except OSError as exc:
        raise RunError(f"{path}: cannot read: {exc.strerror}") from None
    if b"\x00" in raw[:SNIFF_BYTES] and raw[:2] not in (b"\xff\xfe", b"\xfe\xff"):
        raise RunError(f"{path}: a binary file, not a CSV run (a CAN log? replay reads CAN logs "
                       "with --format can)")
    return decode_text(raw, str(path), RunError, FALLBACK_ENCODINGS)


def _number(v: str, path: Path, line: int, column: str) -> float:
    v = v.strip()
    if v in ("", "nan", "NaN", "NA"):
        return math.nan
    try:
        x = float(v)
    except ValueError:
        hint = " (a decimal comma? the run needs a decimal point)" if re.fullmatch(r"[-+]?\d+,\d+", v) else ""
        raise RunError(f"{path}: line {line}, column {column!r}: not a number: {v!r}{hint}") from None
    if math.isinf(x):
        raise RunError(f"{path}: line {line}, column {column!r}: infinite value {v!r}")
    return x


def read_run(path: str | os.PathLike[str], fmt: str = "csv") -> Run:
    """Read a run file.

    Parameters
    ----------
    path : path-like
        CSV file (UTF-8 or Windows-1252/Latin-1; ``#`` lines are comments).
    fmt : {"csv", "paderborn"}
        ``csv``: our run format (needs a ``t`` column). ``paderborn``: the Paderborn data set.

    Raises
    ------
    RunError
        The file cannot be used; the message names the file, and the line and column where one
        is at fault.
    """
    path = Path(path)
    if fmt not in FORMATS:
        raise RunError(f"{path}: unknown format {fmt!r} (known: {', '.join(FORMATS)})")
    numbered = [(k, line) for k, line in enumerate(_text(path).splitlines(), start=1)
                if line.strip() and not line.startswith("#")]
    rows = list(zip((k for k, _ in numbered), csv.reader(line for _, line in numbered)))
    if not rows:
        raise RunError(f"{path}: empty: no header and no data rows")
    if len(rows) < 2:
        raise RunError(f"{path}: a header but no data rows")
    if CANDUMP_LINE.match(numbered[0][1]):
        raise RunError(f"{path}: line {numbered[0][0]}: a candump -L log, not a CSV run (replay reads it with "
                       "--format can)")
    header = [h.strip() for h in rows[0][1]]
    if len(header) == 1:
        for sep, name in SEPARATORS.items():
            if sep in header[0]:
                raise RunError(f"{path}: line {rows[0][0]}: one column {header[0][:40]!r}: the file is separated by "
                               f"{name}; a run CSV is comma-separated (export it with ',' and a decimal point)")
    dupes = sorted({h for h in header if header.count(h) > 1})
    if dupes:
        raise RunError(f"{path}: line {rows[0][0]}: column(s) {', '.join(map(repr, dupes))} appear more than once")
    data = np.empty((len(rows) - 1, len(header)))
    for i, (line, r) in enumerate(rows[1:]):
        if len(r) != len(header):
            raise RunError(f"{path}: line {line}: {len(r)} values, the header has {len(header)} columns")
        data[i] = [_number(v, path, line, header[j]) for j, v in enumerate(r)]
    cols = {h: data[:, i].copy() for i, h in enumerate(header)}
    if fmt == "paderborn":
        return _paderborn(cols, str(path))
    if "t" not in cols:
        raise RunError(f"{path}: no column 't' (seconds); for the Paderborn data use --format paderborn")
    t = cols.pop("t")
    bad = np.flatnonzero(~np.isfinite(t) | (np.diff(t, prepend=-np.inf) <= 0))
    if bad.size:
        raise RunError(f"{path}: line {rows[1 + int(bad[0])][0]}, column 't': time must be finite and increasing")
    return Run(t, cols, str(path))


def _paderborn(cols: dict[str, np.ndarray], source: str) -> Run:
    n = len(next(iter(cols.values())))
    t = cols.pop("t") if "t" in cols else np.arange(n) * PADERBORN_ROW_S
    out = {PADERBORN_COLUMNS.get(k, k): v for k, v in cols.items()}
    # the data set's own d/q current columns (amplitudes) keep their names: the vocabulary's too
    i_d, i_q = Role.CURRENT_D.default_column, Role.CURRENT_Q.default_column
    if i_d in out and i_q in out:
        out[Role.CURRENT.default_column] = np.hypot(out[i_d], out[i_q]) / math.sqrt(2.0)  # amplitude -> RMS
    return Run(t, out, source, {"format": "paderborn"})


#: Longest plausible sample period of a thermal run, s (a 1 Hz model; a longer one is time in ms).
MAX_SAMPLE_PERIOD_S = 60.0


def check_run(run: Run, temperatures: Sequence[str], inputs: Mapping[str, Role] | None = None) -> None:
    """Refuse a run whose units cannot be right before anything is fitted to it.

    Parameters
    ----------
    run : Run
    temperatures : sequence of str
        The run's columns that hold temperatures in degC (the model's sensors, ``*_c`` inputs).
    inputs : mapping of str to Role, optional
        The run's input columns with their role: each is checked against the role's plausible
        range (:data:`thermal_edge.lptn.vocabulary.PLAUSIBLE`) and must be measured at every
        sample (the model needs every input at every step).

    Raises
    ------
    RunError
        Time not in seconds (a sample period above :data:`MAX_SAMPLE_PERIOD_S`), a column in
        another unit (kelvin, mA: named), a value outside its role's plausible range (a spike, a
        negative RMS current), an input not measured (NaN); the message names the file, the
        column and the sample.
    """
    if len(run) < 2:
        raise RunError(f"{run.source}: {len(run)} sample(s): a run needs at least two")
    dt = float(np.median(np.diff(run.t)))
    if dt > MAX_SAMPLE_PERIOD_S:
        raise RunError(f"{run.source}: column 't': sample period {dt:g} s; is the time in milliseconds? "
                       "(t must be in seconds)")
    checks: dict[str, Plausible] = {name: TEMPERATURE for name in temperatures}
    for name, role in (inputs or {}).items():
        checks[name] = role.plausible
    for name, rule in checks.items():
        x = run.columns.get(name)
        if x is None:
            continue
        if inputs and name in inputs:
            gap = np.flatnonzero(~np.isfinite(x))
            if gap.size:
                k = int(gap[0])
                raise RunError(f"{run.source}: column {name!r}, sample {k + 1} (t = {run.t[k]:g} s): not measured "
                               f"({x[k]:g}) in {gap.size} sample(s); the model needs its input {name!r} at every sample")
        found = rule.series_problem(x)
        if found is None:
            continue
        at, why = found
        if at is None:
            raise RunError(f"{run.source}: column {name!r}: {why}")
        raise RunError(f"{run.source}: column {name!r}, sample {at + 1} (t = {run.t[at]:g} s): {why}")


def describe(run: Run, used: Sequence[str]) -> str:
    """A summary to print before any fit: samples, period, duration, columns used and ignored, ranges.

    Parameters
    ----------
    run : Run
    used : sequence of str
        The columns the command takes (inputs and sensors).
    """
    dur = float(run.t[-1] - run.t[0]) if len(run) else 0.0
    dt = float(np.median(np.diff(run.t))) if len(run) > 1 else math.nan
    ranges = []
    for name in used:
        x = run.columns.get(name)
        if x is not None and np.isfinite(x).any():
            ranges.append(f"{name} {np.nanmin(x):.4g}..{np.nanmax(x):.4g}")
    ignored = [k for k in run.columns if k not in used]
    return (f"{run.source}: {len(run)} samples every {dt:g} s ({dur / 3600:.2f} h); "
            f"used: {', '.join(ranges) or 'none'}; ignored: {', '.join(ignored) or 'none'}")


def write_run(path: str | os.PathLike[str], run: Run, comment: str = "") -> None:
    """Write a run in our CSV format (``t`` first; NaN for missing values)."""
    path = Path(path)
    names = list(run.columns)
    data = np.column_stack([run.t] + [run.columns[k] for k in names])
    with open(path, "w", newline="", encoding="utf-8") as fh:
        for line in comment.splitlines():
            fh.write(f"# {line}\n")
        w = csv.writer(fh)
        w.writerow(["t"] + names)
        for row in data:
            w.writerow([f"{v:.6g}" if np.isfinite(v) else "nan" for v in row])
