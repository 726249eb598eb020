"""The residual's signature: how what the model misses depends on speed, current and ambient.

Ranking candidates by their held-out gap says which effect fits best; it does not say whether the
residual has the *shape* an effect predicts, nor whether an effect the model cannot express would
fit it as well. The signature answers that from the run itself, on the held-out part:

* the change of the residual across the run's speed range **at constant current** (the slope of
  the residual on speed within quantile bins of the current, averaged with the bins' weights),
* the change across the current range (current², as the copper loss) at constant speed, and
* the change across the ambient range (at the run's operating points as they are).

A machine answers a change of its operating point with a lag (its thermal time constants), so
the variables are seen through a first-order lag: of the lags in :data:`LAGS_S` the one whose
joint least-squares fit of the residual on the three lagged variables leaves the least residual
variance is used, and stated.

Each change is the slope times the variable's 5–95 % range (K), so that the three read on one
scale; its standard error comes from a block jackknife over contiguous blocks of the held-out
part (thermal residuals are correlated over minutes: single samples are not independent). The
same numbers are computed for each candidate's *correction* (its prediction minus the refitted
model's): a candidate whose correction has the residual's signature explains its shape, one that
does not only lowers its size.

Sign: the residual here is ``reading − refitted model`` (what is missing, positive when the
machine runs warmer than the model), so that a candidate's correction and the residual agree in
sign when the candidate is right.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from ..lptn.vocabulary import Role
from . import fitting as F

VARIABLES = ("speed", "current", "ambient")
HELD = {"speed": "current", "current": "speed", "ambient": ""}
N_BLOCKS = 10  # contiguous blocks of the held-out part for the jackknife
BINS = 4  # quantile bins of the variable held constant
SHARE = 0.3  # a variable is part of the signature when its change is this share of the largest
Z = 2.0  # ... and this many standard errors from zero
LAGS_S = (0.0, 300.0, 900.0, 1800.0, 3600.0)  # first-order lags tried for the operating variables, s

#: which signature an effect's explained variable predicts (None: not judged from these three)
PREDICTS: dict[str, frozenset[str] | None] = {
    "speed": frozenset({"speed"}),
    "current2": frozenset({"current"}),
    "speed_current2": frozenset({"speed", "current"}),
    "ambient": frozenset({"ambient"}),
}


@dataclass
class Dependence:
    """The residual's change across one variable's range, the other variable held (K)."""

    variable: str
    held: str  # the variable held constant ("" for none)
    change_k: float
    se_k: float
    corrections: dict[str, float] = field(default_factory=dict)  # candidate label -> its correction's change, K

    @property
    def significant(self) -> bool:
        return bool(np.isfinite(self.change_k) and np.isfinite(self.se_k) and abs(self.change_k) > Z * self.se_k)


@dataclass
class Signature:
    """The residual's dependences and the variables it follows."""

    dependences: list[Dependence]
    follows: frozenset[str]  # the variables the residual clearly follows
    lag_s: float = 0.0  # the first-order lag the variables are seen through

    def describe(self) -> str:
        """``"grows with speed, not with current or ambient"`` (or ``"follows none of speed, current,
        ambient"``)."""
        judged = [d.variable for d in self.dependences if np.isfinite(d.change_k)]
        on = [v for v in judged if v in self.follows]
        off = [v for v in judged if v not in self.follows]
        if not on:
            return f"follows none of {', '.join(judged)}" if judged else "cannot be judged on this run"
        verbs = []
        for v in on:
            d = next(x for x in self.dependences if x.variable == v)
            held = f" at constant {d.held}" if d.held else ""
            verbs.append(f"{'grows' if d.change_k > 0 else 'falls'} with {v}{held}")
        return ", ".join(verbs) + (f"; not with {' or '.join(off)}" if off else "")

    def fits(self, explains: str) -> bool | None:
        """Whether an effect that follows ``explains`` (its explained variable) has this signature;
        None when the signature's three variables cannot judge it."""
        want = PREDICTS.get(explains)
        if want is None:
            return None
        return bool(self.follows) and want == self.follows

    def as_dict(self) -> dict[str, object]:
        return {
            "follows": sorted(self.follows), "describe": self.describe(), "lag_s": self.lag_s,
            "dependences": [{"variable": d.variable, "held_constant": d.held or None, "residual_change_k": d.change_k,
                             "se_k": d.se_k, "corrections_k": d.corrections} for d in self.dependences],
        }


def conditional_change(e: np.ndarray, x: np.ndarray, z: np.ndarray | None, bins: int = BINS) -> float:
    """Change of ``e`` across the 5–95 % range of ``x`` with ``z`` held: least-squares slopes of ``e``
    on ``x`` within quantile bins of ``z`` (all samples when ``z`` is None), averaged with weights
    ``Σ (x − x̄)²`` (each bin's information on its slope); NaN when ``x`` does not vary."""
    ok = np.isfinite(e) & np.isfinite(x) & (np.isfinite(z) if z is not None else True)
    e, x = e[ok], x[ok]
    if len(x) < 10:
        return float("nan")
    span = float(np.percentile(x, 95) - np.percentile(x, 5))
    if span <= 0:
        return float("nan")
    if z is None:
        groups = [np.ones(len(x), bool)]
    else:
        zz = z[ok]
        edges = np.unique(np.quantile(zz, np.linspace(0, 1, bins + 1)))
        idx = np.clip(np.searchsorted(edges, zz, side="right") - 1, 0, max(len(edges) - 2, 0))
        groups = [idx == k for k in range(max(len(edges) - 1, 1))]
    num = den = 0.0
    for g in groups:
        if g.sum() < 3:
            continue
        xc = x[g] - x[g].mean()
        sxx = float(xc @ xc)
        if sxx <= 1e-12 * span**2 * g.sum():
            continue
        num += float(xc @ (e[g] - e[g].mean()))
        den += sxx
    return num / den * span if den > 0 else float("nan")


def _jackknife(stat: Sequence[float], full: float) -> float:
    v = np.array([s for s in stat if np.isfinite(s)])
    n = len(v)
    if n < 3 or not np.isfinite(full):
        return float("nan")
    return float(math.sqrt((n - 1) / n * np.sum((v - v.mean()) ** 2)))


def _columns(data: F.Data) -> dict[str, np.ndarray | None]:
    speed, current = data.column(Role.SPEED), data.column(Role.CURRENT)
    return {"speed": np.abs(speed) if speed is not None else None,
            "current": current**2 if current is not None else None,
            "ambient": data.column(Role.AMBIENT)}


def lagged(x: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """``x`` through a first-order lag of time constant ``tau_s`` (s), started at its first value."""
    if tau_s <= 0:
        return x
    a = math.exp(-dt_s / tau_s)
    x0 = np.nan_to_num(x, nan=float(np.nanmean(x)) if np.isfinite(x).any() else 0.0)
    y, _ = lfilter([1 - a], [1, -a], x0, zi=[a * x0[0]])
    return np.asarray(y)


def _best_lag(e: np.ndarray, cols: Mapping[str, np.ndarray | None], split: int, dt_s: float) -> float:
    """The lag of :data:`LAGS_S` under which the three variables explain most of the residual."""
    best, best_rss = 0.0, float("inf")
    for tau in LAGS_S:
        X = [np.ones(len(e))] + [lagged(x, dt_s, tau)[split:] for x in cols.values() if x is not None]
        A = np.column_stack(X)
        ok = np.isfinite(e) & np.isfinite(A).all(axis=1)
        if ok.sum() <= A.shape[1]:
            continue
        coef, *_ = np.linalg.lstsq(A[ok], e[ok], rcond=None)
        rss = float(np.sum((e[ok] - A[ok] @ coef) ** 2))
        if rss < best_rss * (1 - 1e-9):
            best, best_rss = tau, rss
    return best


def _missing(traj: np.ndarray, data: F.Data) -> np.ndarray:
    """Reading − prediction, mean over the sensors (K)."""
    Y = np.column_stack([data.run.columns[s] for s in data.sensors])
    with np.errstate(invalid="ignore"):
        return np.nanmean(Y - traj, axis=1)


def signature(base: F.Fit, data: F.Data, candidates: Mapping[str, F.Fit] | None = None) -> Signature:
    """The held-out residual's signature of the refitted model ``base``, and each candidate's
    correction (candidate − refit) on the same scale."""
    assert base.traj_T is not None
    s = data.split
    e = _missing(base.traj_T, data)[s:]
    corr = {label: np.nanmean(f.traj_T - base.traj_T, axis=1)[s:] for label, f in (candidates or {}).items()
            if f.traj_T is not None}
    raw_cols = _columns(data)
    dt = float(np.median(np.diff(data.run.t))) if len(data.run) > 1 else 1.0
    tau = _best_lag(e, raw_cols, s, dt)
    cols = {k: (lagged(x, dt, tau) if x is not None else None) for k, x in raw_cols.items()}
    blocks = np.array_split(np.arange(len(e)), N_BLOCKS)
    deps = []
    for v in VARIABLES:
        x = cols[v]
        if x is None:
            continue
        zname = HELD[v]
        zc = cols.get(zname) if zname else None
        x, zz = x[s:], (zc[s:] if zc is not None else None)
        full = conditional_change(e, x, zz)
        keep = [np.setdiff1d(np.arange(len(e)), b) for b in blocks]
        se = _jackknife([conditional_change(e[k], x[k], zz[k] if zz is not None else None) for k in keep], full)
        d = Dependence(v, zname if zc is not None else "", full, se)
        d.corrections = {label: conditional_change(c, x, zz) for label, c in corr.items()}
        deps.append(d)
    sig = [d for d in deps if d.significant]
    top = max((abs(d.change_k) for d in sig), default=0.0)
    follows = frozenset(d.variable for d in sig if abs(d.change_k) >= SHARE * top)
    return Signature(deps, follows, tau)
