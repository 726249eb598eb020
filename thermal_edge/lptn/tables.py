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
    with open(path, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r]
    if kind == "curve":
        data = np.array([[float(v) for v in r[:2]] for r in rows[1:]])
        order = np.argsort(data[:, 0])
        return Lookup(name, (data[order, 0],), data[order, 1], method)
    if kind == "grid2d":
        cols = np.array([float(v) for v in rows[0][1:]])
        body = np.array([[float(v) for v in r] for r in rows[1:]])
        return Lookup(name, (body[:, 0], cols), body[:, 1:], method)
    raise ValueError(f"unknown table kind {kind!r} (curve, grid2d)")
