"""Finding the fleet's machines and their runs from paths and globs.

A path (or a glob's match) that is a directory is one machine: its id is the directory's name and
its runs are the run CSVs and the CAN logs in it (``*.csv``; ``*.log``, ``*.asc``, ``*.blf``,
``*.trc``, gzipped or not: :mod:`thermal_edge.service.logruns`). A file is one machine's run: the machine id is the
file's name without its suffixes, or with ``id_column`` the value of that column in the file (a
run CSV; then several files of one machine are grouped, and the column must hold one value per
file). The run files themselves are read by the worker that processes the machine, not here.
"""
from __future__ import annotations

import csv
import glob
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..bus.logs import GZIP_SUFFIXES
from ..data import RunError
from ..service.logruns import CAN_LOG_SUFFIXES, is_can_log

#: run files in a machine's directory: run CSVs and CAN logs (gzipped too)
RUN_GLOBS = ("*.csv", *(f"*{s}" for s in CAN_LOG_SUFFIXES), *(f"*{s}.gz" for s in CAN_LOG_SUFFIXES if s in GZIP_SUFFIXES))


@dataclass(frozen=True)
class Machine:
    """One machine of the fleet: its id and its run files."""

    id: str
    runs: tuple[str, ...]


def _expand(source: str) -> list[Path]:
    if glob.has_magic(source):
        hits = sorted(glob.glob(source, recursive=True))
        if not hits:
            raise FileNotFoundError(f"{source}: no file or directory matches")
        return [Path(h) for h in hits]
    p = Path(source)
    if not p.exists():
        raise FileNotFoundError(f"{source}: no such file or directory")
    return [p]


def column_id(path: str | Path, column: str) -> str:
    """The machine id in ``column`` of a run file's first data row (integral values without ``.0``).

    Raises
    ------
    RunError
        If the file has no such column or no data row, or is a CAN log (whose machine is its name).
    """
    if is_can_log(path):
        raise RunError(f"{path}: a CAN log has no columns: its machine id is its file or directory name, not {column!r}")
    with open(path, newline="") as fh:
        rows = csv.reader(line for line in fh if not line.startswith("#"))
        header = [h.strip() for h in next(rows, [])]
        first = next(rows, None)
    if column not in header:
        raise RunError(f"{path}: no machine id column {column!r}")
    if first is None:
        raise RunError(f"{path}: no data rows")
    return format_id(first[header.index(column)])


def format_id(raw: str | float) -> str:
    """A machine id from a column value: ``12.0`` -> ``12``; text stays as it is."""
    try:
        x = float(raw)
    except ValueError:
        return str(raw).strip()
    return str(int(x)) if math.isfinite(x) and x == int(x) else f"{x:g}"


def find_machines(sources: Sequence[str], id_column: str | None = None) -> list[Machine]:
    """The machines under ``sources`` (paths or globs), sorted by id.

    Raises
    ------
    FileNotFoundError
        A source that matches nothing, or a directory without run files.
    KeyError
        Two different sources that give one machine id (without ``id_column``).
    """
    runs: dict[str, list[str]] = {}
    origin: dict[str, str] = {}
    for source in sources:
        for path in _expand(source):
            if path.is_dir():
                files = sorted({str(f) for g in RUN_GLOBS for f in path.glob(g)})
                if not files:
                    raise FileNotFoundError(f"{path}: directory has no *.csv run files and no CAN logs "
                                            f"({', '.join(RUN_GLOBS[1:])})")
                mid = path.name
            else:
                files = [str(path)]
                mid = column_id(path, id_column) if id_column else path.name.split(".")[0]
            if mid in runs and not id_column and origin[mid] != str(path):
                raise KeyError(f"machine id {mid!r} from both {origin[mid]} and {path}: "
                               "give one directory per machine or --id-column")
            origin.setdefault(mid, str(path))
            runs.setdefault(mid, [])
            runs[mid] += [f for f in files if f not in runs[mid]]
    return [Machine(m, tuple(runs[m])) for m in sorted(runs)]
