"""Measured lookup tables (loss maps, drag curves) callable from laws.

Two CSV layouts are read: ``curve`` (first column x, second column y, one header row) and
``grid2d`` (header row: a label then the column axis; each following row: the row-axis value
then the values). Look-up is ``nearest`` (snap to the grid, as the Paderborn reference does) or
``linear``; arguments outside the grid are clamped to its edge.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Lookup:
    """A 1-D or 2-D table. Call it with numpy arrays; it broadcasts."""

    name: str
    axes: tuple[np.ndarray, ...]
    values: np.ndarray
    method: str = "nearest"

    @property
    def arity(self) -> int:
        return len(self.axes)

    def __call__(self, *args: object) -> np.ndarray:
        coords = [np.asarray(a, dtype=float) for a in args]
        shape = np.broadcast_shapes(*[c.shape for c in coords])
        coords = [np.broadcast_to(c, shape) for c in coords]
        if self.method == "nearest":
            idx = tuple(_nearest(ax, c) for ax, c in zip(self.axes, coords))
            picked: np.ndarray = self.values[idx]
            return picked
        if len(self.axes) == 1:
            return np.asarray(np.interp(coords[0], self.axes[0], self.values))
        from scipy.interpolate import RegularGridInterpolator

        interp = RegularGridInterpolator(self.axes, self.values, bounds_error=False, fill_value=None)
        pts = np.stack([np.clip(c, ax[0], ax[-1]) for ax, c in zip(self.axes, coords)], axis=-1)
        return np.asarray(interp(pts))


def _nearest(axis: np.ndarray, x: np.ndarray) -> np.ndarray:
    i = np.clip(np.searchsorted(axis, x), 1, len(axis) - 1)
    left = axis[i - 1]
    return np.where(np.abs(x - left) <= np.abs(axis[i] - x), i - 1, i)


def load_table(name: str, path: Path, kind: str, method: str = "nearest") -> Lookup:
    """Read a table file.

    Parameters
    ----------
    name : str
        Name the laws call it by.
    path : Path
        CSV file.
    kind : {"curve", "grid2d"}
        File layout (module docstring).
    method : {"nearest", "linear"}
        Look-up between grid points.
    """
    if kind not in ("curve", "grid2d"):
        raise ValueError(f"unknown table kind {kind!r} (curve, grid2d)")
    if method not in ("nearest", "linear"):
        raise ValueError(f"unknown lookup {method!r} (nearest, linear)")
    with open(path, newline="") as fh:
        rows = [(n, r) for n, r in enumerate(csv.reader(fh), start=1) if r]
    if len(rows) < 3:
        raise ValueError(f"{len(rows)} non-empty lines: a header and at least two rows are needed")
    head_line, head = rows[0]
    width = 2 if kind == "curve" else len(head)
    body = np.array([_numbers(n, r, width) for n, r in rows[1:]])
    if kind == "curve":  # rows in any order: sorted by x, which must not repeat
        order = np.argsort(body[:, 0], kind="stable")
        _increasing(body[order, 0], [rows[1:][i][0] for i in order], "x")
        return Lookup(name, (body[order, 0],), body[order, 1], method)
    cols = np.array(_numbers(head_line, ["0", *head[1:]], width)[1:])
    _increasing(cols, [head_line] * len(cols), "column axis")
    _increasing(body[:, 0], [n for n, _ in rows[1:]], "row axis")
    return Lookup(name, (body[:, 0], cols), body[:, 1:], method)


def _numbers(line: int, row: list[str], width: int) -> list[float]:
    """The finite numbers of one row of ``width`` values; ValueError naming the line otherwise."""
    if len(row) != width:
        raise ValueError(f"line {line}: {len(row)} values, the header has {width}")
    out = []
    for v in row:
        try:
            x = float(v)
        except ValueError:
            raise ValueError(f"line {line}: {v.strip()!r} is not a number") from None
        if not np.isfinite(x):
            raise ValueError(f"line {line}: {v.strip()!r} is not a finite number")
        out.append(x)
    return out


def _increasing(axis: np.ndarray, lines: list[int], what: str) -> None:
    """An axis the look-up searches must rise strictly (a value twice, or a grid's axis out of
    order, would pick the wrong entry); ValueError naming the line where it does not."""
    bad = np.nonzero(np.diff(axis) <= 0)[0]
    if len(bad):
        i = int(bad[0]) + 1
        raise ValueError(f"line {lines[i]}: the {what} does not rise ({axis[i - 1]:g} then {axis[i]:g})")
