"""The fleet's result table: one row per machine and parameter (``kind = parameter``), per machine
and sensor (``kind = sensor``), or per machine that could not be processed (``kind = error``).

Columns that do not apply to a row's kind are null. Written as Parquet with pyarrow.
"""
from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any

#: column -> pyarrow type name; the order is the table's
COLUMNS: dict[str, str] = {
    "machine": "string",
    "kind": "string",  # parameter | sensor | error
    "name": "string",  # parameter or sensor name
    "value": "float64",  # parameter: fitted value (its unit); sensor: RMS error, K
    "nominal": "float64",  # parameter: the design's (start) value
    "rel_std": "float64",  # parameter: 1σ of log θ (Fisher information, the residuals' correlation counted)
    "identifiable": "bool",  # parameter: 1σ as if the residuals were independent below the calibration's limit
    "mse_k2": "float64",  # sensor: mean squared error, K²
    "rms_k": "float64",  # sensor: RMS error, K
    "max_abs_k": "float64",  # sensor: largest absolute error, K
    "residual_k": "float64",  # the machine's residual σ of the fit (parameter rows), K
    "objective": "float64",  # the machine's final objective (parameter rows), K²
    "samples": "int64",  # samples of the machine's runs
    "runs": "string",  # the machine's run files, ';'-separated
    "wall_s": "float64",  # wall time of the machine's task, s
    "cpu_s": "float64",  # CPU time of the machine's task, s (the cost on a core of its own)
    "worker_peak_mb": "float64",  # peak RSS of the worker process after the task, MB
    "z": "float64",  # screen: robust distance from the fleet's centre
    "outlier": "bool",  # screen: the machine stands out on this parameter
    "message": "string",  # error rows: what went wrong
}


def row(**values: Any) -> dict[str, Any]:
    """A table row: every column, ``None`` where not given.

    Raises
    ------
    KeyError
        For a column the table does not have.
    """
    unknown = set(values) - set(COLUMNS)
    if unknown:
        raise KeyError(f"no result column {sorted(unknown)[0]!r}")
    return {c: values.get(c) for c in COLUMNS}


def write_table(path: str | os.PathLike[str], rows: Iterable[dict[str, Any]]) -> None:
    """Write rows (from :func:`row`) as one Parquet file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = pa.schema([(c, pa.type_for_alias(t)) for c, t in COLUMNS.items()])
    pq.write_table(pa.Table.from_pylist([row(**r) for r in rows], schema=schema), str(path))


def read_table(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """The rows of a table written by :func:`write_table` (missing columns as ``None``).

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    KeyError
        If the file is not a Parquet table with ``machine``, ``kind`` and ``name`` columns.
    """
    import pyarrow.parquet as pq

    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such result table")
    try:
        rows = pq.read_table(str(path)).to_pylist()
    except Exception as exc:  # pyarrow raises several types for a file that is not Parquet
        raise KeyError(f"{path}: not a Parquet table: {exc}") from None
    if rows and not {"machine", "kind", "name"} <= set(rows[0]):
        raise KeyError(f"{path}: not a fleet result table (needs machine, kind, name columns)")
    return [{c: r.get(c) for c in COLUMNS} for r in rows]
