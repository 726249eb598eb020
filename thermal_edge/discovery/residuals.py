"""Residual analysis: where, when and under which operating conditions model and sensors disagree.

For each sensor the residual ``e = prediction − reading`` (K) is set against the operating
variables of the run: speed, current², (speed·current)², the sensor's own reading and its rise
over ambient, the other sensors' readings, the boundary temperatures, the sensor's rate of change
dT/dt (K/min, smoothed over a minute) and the time since start. How much of the residual a
variable explains is its *correlation ratio* η² (share of the residual variance explained by the
means in 8 quantile bins of the variable; 0 = unrelated, 1 = a function of it); the sign of the
Pearson correlation says in which direction. The run is also cut into regimes (standstill /
low / high speed; light / loaded; heating / steady / cooling) with the residual's bias and RMS
in each.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..data import Run
from ..lptn.vocabulary import Role

LABELS = {
    "speed": "speed (rpm)",
    "current2": "current² (A²)",
    "speed_current2": "(speed·current)² (rpm·A)²",
    "temperature": "own reading (°C)",
    "rise": "own reading − ambient (K)",
    "dTdt": "own dT/dt (K/min)",
    "time": "time since start (h)",
}


def label(var: str) -> str:
    if var.startswith("T:"):
        return f"reading of {var[2:]} (°C)"
    if var.startswith("U:"):
        return f"boundary {var[2:]} (°C)"
    return LABELS.get(var, var)


def _smooth(x: np.ndarray, n: int) -> np.ndarray:
    if n <= 1:
        return x
    k = np.ones(n) / n
    xp = np.pad(x, (n // 2, n - 1 - n // 2), mode="edge")
    return np.convolve(xp, k, mode="valid")


def _role_column(run: Run, roles: Mapping[Role, str], role: Role) -> np.ndarray | None:
    name = roles.get(role)
    return run.columns.get(name) if name is not None else None


def variables(run: Run, sensors: Sequence[str], boundaries: Mapping[str, str],
              roles: Mapping[Role, str]) -> dict[str, dict[str, np.ndarray]]:
    """Operating variables per sensor: ``{sensor: {var: series}}`` (shared ones repeated);
    ``roles`` maps input roles to the run's columns."""
    cols = run.columns
    N = len(run)
    dt = run.dt
    shared: dict[str, np.ndarray] = {"time": (run.t - run.t[0]) / 3600.0}
    speed, current = _role_column(run, roles, Role.SPEED), _role_column(run, roles, Role.CURRENT)
    if speed is not None:
        shared["speed"] = np.abs(speed)
    if current is not None:
        shared["current2"] = current ** 2
        if speed is not None:
            shared["speed_current2"] = (np.abs(speed) * current) ** 2
    for b, c in boundaries.items():
        if c in cols:
            shared[f"U:{b}"] = cols[c]
    amb_col = roles.get(Role.AMBIENT, next(iter(boundaries.values()), None))
    w = max(1, int(round(60.0 / dt)))
    out: dict[str, dict[str, np.ndarray]] = {}
    for s in sensors:
        y = cols[s]
        yf = np.where(np.isfinite(y), y, np.nan)
        v = dict(shared)
        v["temperature"] = yf
        if amb_col is not None and amb_col in cols:
            v["rise"] = yf - cols[amb_col]
        ys = _smooth(np.nan_to_num(yf, nan=float(np.nanmean(yf))), w)
        v["dTdt"] = np.gradient(ys, dt) * 60.0 if N > 1 else np.zeros(N)
        for o in sensors:
            if o != s:
                v[f"T:{o}"] = cols[o]
        out[s] = v
    return out


def eta2(e: np.ndarray, x: np.ndarray, bins: int = 8) -> float:
    """Correlation ratio: share of var(e) explained by the bin means of ``e`` over quantile bins of ``x``."""
    ok = np.isfinite(e) & np.isfinite(x)
    e, x = e[ok], x[ok]
    if len(e) < 2 * bins or np.var(e) <= 0 or np.ptp(x) <= 0:
        return 0.0
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    if len(edges) < 2:
        return 0.0
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    m = e.mean()
    between = 0.0
    for b in range(len(edges) - 1):
        sel = idx == b
        if sel.any():
            between += sel.sum() * (e[sel].mean() - m) ** 2
    return float(between / (len(e) * np.var(e)))


def _corr(e: np.ndarray, x: np.ndarray) -> float:
    ok = np.isfinite(e) & np.isfinite(x)
    if ok.sum() < 3 or np.std(e[ok]) == 0 or np.std(x[ok]) == 0:
        return 0.0
    return float(np.corrcoef(e[ok], x[ok])[0, 1])


@dataclass
class SensorResiduals:
    sensor: str
    rms_train: float
    rms_heldout: float
    bias: float
    drivers: list[tuple[str, float, float]]  # (variable, eta², pearson r), strongest first
    regimes: list[tuple[str, str, float, float, float]]  # (axis, regime, share, bias, rms)


@dataclass
class Analysis:
    sensors: list[SensorResiduals]
    residual: np.ndarray  # (N, ns)
    vars: dict[str, dict[str, np.ndarray]] = field(repr=False, default_factory=dict)

    def worst(self) -> SensorResiduals:
        return max(self.sensors, key=lambda s: s.rms_heldout if np.isfinite(s.rms_heldout) else -1)

    def as_dict(self) -> dict[str, object]:
        return {
            s.sensor: {
                "rms_train_k": s.rms_train, "rms_heldout_k": s.rms_heldout, "bias_k": s.bias,
                "drivers": [{"variable": v, "eta2": a, "r": r} for v, a, r in s.drivers[:5]],
                "regimes": [{"axis": ax, "regime": rg, "share": sh, "bias_k": b, "rms_k": rm} for ax, rg, sh, b, rm in s.regimes],
            }
            for s in self.sensors
        }


def regimes(run: Run, refs: Mapping[str, float], sensors: Sequence[str],
            roles: Mapping[Role, str]) -> dict[str, dict[str, np.ndarray]]:
    """Boolean masks of the regimes along three axes: speed, load and thermal state."""
    cols = run.columns
    N = len(run)
    out: dict[str, dict[str, np.ndarray]] = {}
    speed, current = _role_column(run, roles, Role.SPEED), _role_column(run, roles, Role.CURRENT)
    if speed is not None:
        n = np.abs(speed) / refs.get("n_ref", 1.0)
        out["speed"] = {"standstill": n < 0.05, "low speed": (n >= 0.05) & (n < 0.6), "high speed": n >= 0.6}
    if current is not None:
        i = current / refs.get("i_ref", 1.0)
        out["load"] = {"light": i < 0.4, "loaded": i >= 0.4}
    w = max(1, int(round(60.0 / run.dt)))
    ys = [np.nan_to_num(cols[s], nan=float(np.nanmean(cols[s]))) for s in sensors]
    rate = np.max(np.abs(np.array([np.gradient(_smooth(y, w), run.dt) * 60.0 for y in ys])), axis=0) if N > 1 else np.zeros(N)
    sgn = np.mean(np.array([np.gradient(_smooth(y, w), run.dt) for y in ys]), axis=0) if N > 1 else np.zeros(N)
    fast = rate > 0.1  # K/min
    out["thermal"] = {"heating": fast & (sgn > 0), "steady": ~fast, "cooling": fast & (sgn <= 0)}
    return out


def analyse(run: Run, sensors: Sequence[str], pred: np.ndarray, split: int, boundaries: Mapping[str, str],
            refs: Mapping[str, float], roles: Mapping[Role, str]) -> Analysis:
    """Residual analysis of predictions ``pred`` (N, ns) against the run's sensor columns
    (``roles``: the run's column of each input role, :attr:`.fitting.Data.roles`)."""
    V = variables(run, sensors, boundaries, roles)
    R = regimes(run, refs, sensors, roles)
    res = np.column_stack([pred[:, j] - run.columns[s] for j, s in enumerate(sensors)])
    out = []
    for j, s in enumerate(sensors):
        e = res[:, j]
        drivers = sorted(((k, eta2(e, x), _corr(e, x)) for k, x in V[s].items()), key=lambda t: -t[1])
        regs = []
        for axis, masks in R.items():
            for name, m in masks.items():
                ok = m & np.isfinite(e)
                if ok.sum() == 0:
                    continue
                regs.append((axis, name, float(ok.mean()), float(np.mean(e[ok])), float(np.sqrt(np.mean(e[ok] ** 2)))))
        a, b = e[:split], e[split:]
        out.append(SensorResiduals(
            s, float(np.sqrt(np.nanmean(a**2))), float(np.sqrt(np.nanmean(b**2))) if np.isfinite(b).any() else float("nan"),
            float(np.nanmean(e)), drivers, regs))
    return Analysis(out, res, V)
