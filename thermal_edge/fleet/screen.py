"""``fleet screen``: the fleet's parameter distribution and the machines that stand out.

Per parameter, in logs (the calibration's own scale: its uncertainty is the σ of ``log θ``), the
fleet's robust centre is the median ``m`` and its spread the scaled median absolute deviation
``s = 1.4826 MAD`` (the σ of a normal distribution). A machine's distance combines that spread
with its own estimate's uncertainty ``σ_i``::

    z_i = (log θ_i − m) / sqrt(s² + σ_i²)

so a parameter the machine's runs cannot pin down (large ``σ_i``) never makes it look odd, and
a few faulty machines do not widen the yardstick they are measured with. A machine is an outlier
when ``|z|`` of some parameter exceeds the threshold; it is named with the parameter of the
largest ``|z|``.
"""
from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: |z| above which a machine stands out
THRESHOLD = 5.0
#: MAD -> σ of a normal distribution
MAD_SCALE = 1.482602218505602


@dataclass(frozen=True)
class Outlier:
    """A machine that stands out, by the parameter that makes it odd."""

    machine: str
    parameter: str
    z: float
    value: float
    fleet_median: float
    rel_std: float

    @property
    def ratio(self) -> float:
        """The machine's value over the fleet's median."""
        return self.value / self.fleet_median


@dataclass(frozen=True)
class Spread:
    """The fleet's distribution of one parameter (values in the parameter's unit)."""

    parameter: str
    machines: int
    nominal: float
    median: float
    spread_rel: float  # 1.4826 MAD of log θ: the fleet's relative spread, robust
    p05: float
    p95: float
    identifiable: int  # machines whose runs pin the parameter down


def robust_z(log_values: np.ndarray, log_std: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``z`` of every value, the median and the scaled MAD of ``log_values``.

    >>> z, m, s = robust_z(np.log([1.0, 1.0, 1.1, 0.9, 3.0]), np.zeros(5))
    >>> round(float(z[-1]), 1), round(float(np.exp(m)), 2)
    (7.8, 1.0)
    """
    m = float(np.median(log_values))
    s = MAD_SCALE * float(np.median(np.abs(log_values - m)))
    den = np.sqrt(s**2 + np.nan_to_num(log_std, nan=math.inf) ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(den > 0, (log_values - m) / den, 0.0)
    return z, m, s


def _groups(rows: Sequence[dict[str, Any]]) -> Iterator[tuple[str, list[dict[str, Any]], np.ndarray, np.ndarray]]:
    """Per parameter: its rows, log values and σ of log values (unknown σ: infinite)."""
    params = [r for r in rows if r["kind"] == "parameter" and r["value"] is not None and r["value"] > 0]
    for name in dict.fromkeys(r["name"] for r in params):
        group = [r for r in params if r["name"] == name]
        sd = np.array([math.inf if r["rel_std"] is None else r["rel_std"] for r in group], dtype=float)
        yield name, group, np.log([r["value"] for r in group]), sd


def _spread(name: str, group: list[dict[str, Any]], x: np.ndarray, m: float, s: float) -> Spread:
    vals = np.exp(x)
    nominal = group[0]["nominal"]
    return Spread(name, len(group), math.nan if nominal is None else float(nominal), float(np.exp(m)), s,
                  float(np.percentile(vals, 5)), float(np.percentile(vals, 95)), sum(bool(r["identifiable"]) for r in group))


def distribution(rows: Sequence[dict[str, Any]]) -> list[Spread]:
    """The fleet's distribution of every parameter in calibration rows (``kind = parameter``)."""
    out = []
    for name, group, x, sd in _groups(rows):
        _, m, s = robust_z(x, sd)
        out.append(_spread(name, group, x, m, s))
    return out


def screen(rows: Sequence[dict[str, Any]], threshold: float = THRESHOLD) -> tuple[list[Spread], list[Outlier]]:
    """Screen calibration rows (``kind = parameter``): set their ``z`` and ``outlier`` in place.

    Returns the fleet's distribution per parameter and the outliers (one per machine, by
    decreasing ``|z|``).
    """
    spreads: list[Spread] = []
    best: dict[str, tuple[float, dict[str, Any]]] = {}
    for name, group, x, sd in _groups(rows):
        z, m, s = robust_z(x, sd)
        for r, zi in zip(group, z):
            r["z"], r["outlier"] = float(zi), bool(abs(zi) > threshold)
            if abs(zi) > threshold and abs(zi) > best.get(r["machine"], (0.0, r))[0]:
                best[r["machine"]] = (abs(float(zi)), r)
        spreads.append(_spread(name, group, x, m, s))
    med = {sp.parameter: sp.median for sp in spreads}
    outliers = [Outlier(r["machine"], r["name"], float(r["z"]), float(r["value"]), med[r["name"]],
                        math.nan if r["rel_std"] is None else float(r["rel_std"])) for _, r in best.values()]
    outliers.sort(key=lambda o: -abs(o.z))
    return spreads, outliers
