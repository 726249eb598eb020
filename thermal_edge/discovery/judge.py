"""How sure the verdict is: winner against runner-up, and a gap nobody explains against no gap.

Three questions the ranking by held-out gap alone does not answer:

* **Is the runner-up nearly as good?** The held-out gaps of two fits come with an uncertainty:
  the per-sample squared error (mean over the sensors) is averaged over ``N_BLOCKS`` contiguous
  blocks of the held-out part (thermal residuals are correlated over minutes, single samples are
  not independent), and the spread of the block means of the *difference* between the two fits
  gives the standard error of that difference (:func:`compare`). Two effects are *confusable*
  when their held-out gaps differ by less than ``Z_SEPARATE`` standard errors, or when the
  runner-up achieves at least ``CLOSE_SHARE`` of the winner's reduction of the gap (two
  predictions so alike that even a "significant" difference is far below what matters).
* **Can data decide?** Where the held-out part reaches an operating region the training part
  never saw (speed, current or ambient outside the training range), the two fits are compared
  there alone: that is data neither was fitted to, in conditions where their forms disagree. A
  difference beyond ``Z_SEPARATE`` standard errors decides (:func:`novel_region`).
* **What would tell them apart?** Each fit's *predicted residual* (its prediction minus the
  refitted model's: what the effect says the refit got wrong) is set against speed, current,
  ambient and time (:func:`evidence`); and both fitted models are run to steady state on a grid
  of operating points up to and beyond the run's (:func:`separating_point`): the point where
  their sensor temperatures differ most, with both models keeping every limited node below its
  warning temperature (a run one can do without derating), is the test to run next.

The gap itself is judged against the sensor noise floor (:func:`gap_status`): within
``NO_GAP_FACTOR`` noise floors (plus the smallest gain discovery accepts) there is nothing to
explain; above it, a gap no catalogue effect removes is reported with its size, where and when
it occurs and the nearest candidates.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..data import Run
from ..lptn import Model, Role, steady_state
from . import fitting as F
from .residuals import SensorResiduals

N_BLOCKS = 10  # contiguous blocks of the held-out part for the standard errors
Z_SEPARATE = 2.0  # standard errors that separate two gaps
CLOSE_SHARE = 0.9  # the runner-up achieves this share of the winner's gap reduction: confusable
NO_GAP_FACTOR = 2.0  # a gap within this many noise floors (+ min gain) is no gap
NOVEL_MIN = 30  # held-out samples outside the training range needed to decide by them


def above_noise(gap_k: float, noise_k: float) -> float:
    """The part of a held-out gap above the sensor noise floor, K: ``sqrt(max(gap² − noise², 0))``
    (noise adds to the squared gap; no model removes it)."""
    return math.sqrt(max(gap_k**2 - noise_k**2, 0.0)) if np.isfinite(gap_k) else float("nan")


def sample_loss(fit: F.Fit, data: F.Data) -> np.ndarray:
    """Squared error per sample, mean over the sensors (K², NaN where no sensor reads)."""
    assert fit.traj_T is not None
    Y = np.column_stack([data.run.columns[s] for s in data.sensors])
    e2 = (fit.traj_T - Y) ** 2
    with np.errstate(invalid="ignore"):
        return np.nanmean(np.where(np.isfinite(e2), e2, np.nan), axis=1)


def _block_means(x: np.ndarray, n_blocks: int) -> np.ndarray:
    parts = [p[np.isfinite(p)] for p in np.array_split(x, n_blocks) if np.isfinite(p).any()]
    return np.array([p.mean() for p in parts])


def gap_se(fit: F.Fit, data: F.Data) -> float:
    """Standard error (K) of a fit's held-out gap, from block means of its squared error."""
    b = _block_means(sample_loss(fit, data)[data.split:], N_BLOCKS)
    if len(b) < 2 or not np.isfinite(fit.gap) or fit.gap <= 0:
        return float("nan")
    return float(np.std(b, ddof=1) / math.sqrt(len(b)) / (2 * fit.gap))


@dataclass
class Comparison:
    """Winner A against runner-up B on the held-out part."""

    a: str
    b: str
    gap_a: float
    gap_b: float
    se_diff: float  # K: standard error of gap_b - gap_a
    share: float  # of the winner's reduction of the held-out gap, the share the runner-up achieves
    ambiguous: bool
    decided_by: str = ""  # the operating region that decided, when one did
    novel_gap_a: float = float("nan")
    novel_gap_b: float = float("nan")
    novel_se: float = float("nan")
    swapped: bool = False  # the runner-up by the full held-out gap won the novel region

    @property
    def z(self) -> float:
        d = self.gap_b - self.gap_a
        return d / self.se_diff if self.se_diff > 0 else float("inf")


def _diff_se(la: np.ndarray, lb: np.ndarray) -> tuple[float, float]:
    """(gap_b - gap_a, its standard error) from the per-sample losses of the compared samples."""
    bm = _block_means(lb - la, N_BLOCKS)
    ga, gb = math.sqrt(np.nanmean(la)), math.sqrt(np.nanmean(lb))
    se = float(np.std(bm, ddof=1) / math.sqrt(len(bm)) / max(ga + gb, 1e-12)) if len(bm) >= 2 else float("nan")
    return gb - ga, se


def compare(a: F.Fit, b: F.Fit, reference_gap: float, data: F.Data) -> Comparison:
    """Compare two fits on the held-out part (see the module docstring for the rule)."""
    la, lb = sample_loss(a, data)[data.split:], sample_loss(b, data)[data.split:]
    d, se = _diff_se(la, lb)
    ra, rb = reference_gap - a.gap, reference_gap - b.gap
    share = rb / ra if ra > 0 else 0.0
    close = bool((np.isfinite(se) and d < Z_SEPARATE * se) or share >= CLOSE_SHARE)
    return Comparison(a.label, b.label, a.gap, b.gap, se, share, close)


def novel_region(data: F.Data, boundaries: dict[str, str]) -> tuple[np.ndarray, str]:
    """Held-out samples outside the training range of speed, current or a boundary temperature
    (beyond 5 % of the training span), and a description of that region."""
    run, split = data.run, data.split
    speed = data.column(Role.SPEED)
    cols = {"speed (rpm)": np.abs(speed) if speed is not None else None, "current (A)": data.column(Role.CURRENT)}
    for b, c in boundaries.items():
        cols[f"{b} (°C)"] = run.columns.get(c)
    mask = np.zeros(len(run) - split, bool)
    parts = []
    for name, x in cols.items():
        if x is None:
            continue
        tr, ho = x[:split], x[split:]
        lo, hi = float(np.nanmin(tr)), float(np.nanmax(tr))
        tol = 0.05 * max(hi - lo, 1e-9)
        above, below = ho > hi + tol, ho < lo - tol
        if above.any():
            parts.append(f"{name} above {hi:.4g} (up to {float(np.nanmax(ho)):.4g})")
        if below.any():
            parts.append(f"{name} below {lo:.4g} (down to {float(np.nanmin(ho)):.4g})")
        mask |= above | below
    return mask, "; ".join(parts)


def decide_novel(cmp: Comparison, a: F.Fit, b: F.Fit, data: F.Data, boundaries: dict[str, str]) -> Comparison:
    """Let held-out data from an operating region the training part lacks decide a confusable pair."""
    mask, desc = novel_region(data, boundaries)
    if mask.sum() < NOVEL_MIN:
        return cmp
    la, lb = sample_loss(a, data)[data.split:][mask], sample_loss(b, data)[data.split:][mask]
    d, se = _diff_se(la, lb)
    cmp.novel_gap_a, cmp.novel_gap_b, cmp.novel_se = math.sqrt(np.nanmean(la)), math.sqrt(np.nanmean(lb)), se
    if np.isfinite(se) and abs(d) > Z_SEPARATE * se:
        cmp.decided_by = desc
        cmp.ambiguous = False
        cmp.swapped = d < 0
    return cmp


@dataclass
class Evidence:
    """The predicted residuals of two fits against one operating variable (binned means, K)."""

    variable: str
    centers: list[float]
    a: list[float]
    b: list[float]
    sensor: str

    @property
    def max_diff(self) -> tuple[float, float]:
        """(bin centre, |a − b|) where the two differ most."""
        if not self.centers:
            return float("nan"), 0.0
        d = np.abs(np.array(self.a) - np.array(self.b))
        i = int(np.argmax(d))
        return self.centers[i], float(d[i])


EVIDENCE_VARS = ("speed (rpm)", "current (A)", "ambient (°C)", "time (h)")


def evidence(base: F.Fit, a: F.Fit, b: F.Fit, data: F.Data, boundaries: dict[str, str], bins: int = 10) -> list[Evidence]:
    """Each fit's predicted residual (refit prediction minus the fit's) against speed, current,
    ambient and time, in quantile bins, on the sensor where the two differ most."""
    assert base.traj_T is not None and a.traj_T is not None and b.traj_T is not None
    pa, pb = base.traj_T - a.traj_T, base.traj_T - b.traj_T
    j = int(np.nanargmax(np.nanmean((pa - pb) ** 2, axis=0)))
    run = data.run
    amb = data.roles.get(Role.AMBIENT, next(iter(boundaries.values()), None))
    speed = data.column(Role.SPEED)
    xs = {"speed (rpm)": np.abs(speed) if speed is not None else None,
          "current (A)": data.column(Role.CURRENT),
          "ambient (°C)": run.columns.get(amb) if amb else None,
          "time (h)": (run.t - run.t[0]) / 3600.0}
    out = []
    for name in EVIDENCE_VARS:
        x = xs[name]
        if x is None:
            continue
        ok = np.isfinite(x) & np.isfinite(pa[:, j]) & np.isfinite(pb[:, j])
        edges = np.unique(np.quantile(x[ok], np.linspace(0, 1, bins + 1)))
        if len(edges) < 2:
            continue
        idx = np.clip(np.searchsorted(edges, x[ok], side="right") - 1, 0, len(edges) - 2)
        c, ya, yb = [], [], []
        for k in range(len(edges) - 1):
            sel = idx == k
            if sel.any():
                c.append(float(x[ok][sel].mean()))
                ya.append(float(pa[ok, j][sel].mean()))
                yb.append(float(pb[ok, j][sel].mean()))
        out.append(Evidence(name, c, ya, yb, data.sensors[j]))
    return out


#: two fitted models are told apart at a sensor where they differ by this many noise floors
SEPARATES_NOISE = 3.0


@dataclass
class Point:
    """A steady operating point where two fitted models disagree most."""

    inputs: dict[str, float]
    sensor: str
    t_a: float
    t_b: float
    in_run: bool  # the run held steady near this point
    roles: dict[str, Role] = field(default_factory=dict)  # input name -> role (for the description)
    #: the node of both models where they differ most at this point, and its two temperatures (°C):
    #: where a sensor would separate them when no sensor of the run does
    node: str = ""
    node_a: float = float("nan")
    node_b: float = float("nan")

    @property
    def node_diff(self) -> float:
        return abs(self.node_a - self.node_b)

    def sensors_separate(self, noise_k: float) -> bool:
        """A test run at this point tells the two models apart with the run's sensors: they differ
        by :data:`SEPARATES_NOISE` noise floors (``noise_k``, K) or more."""
        return self.diff >= SEPARATES_NOISE * noise_k

    def node_separates(self, noise_k: float) -> bool:
        """A sensor on :attr:`node` would tell them apart (by the same rule)."""
        return bool(self.node) and self.node_diff >= SEPARATES_NOISE * noise_k

    @property
    def diff(self) -> float:
        return abs(self.t_a - self.t_b)

    def describe(self) -> str:
        by_role = {self.roles[k]: v for k, v in self.inputs.items() if k in self.roles}
        parts = []
        if Role.SPEED in by_role:
            parts.append(f"{by_role[Role.SPEED]:.0f} rpm")
        if Role.CURRENT in by_role:
            parts.append(f"{by_role[Role.CURRENT]:.0f} A")
        parts += [f"{r.value} {v:.0f} °C" for r, v in by_role.items() if r.is_temperature]
        return "steady " + ", ".join(parts)


def separating_point(a: F.Fit, b: F.Fit, data: F.Data) -> Point | None:
    """Steady operating point (grid over speed, current and ambient, up to beyond the run's
    range) where the two fitted models' sensor temperatures differ most, with the node (of both
    models) where they differ most at that point. Only points a test run may hold: no current at
    standstill, every limited node :data:`TEST_MARGIN_K` below its warning temperature."""
    run, model = data.run, a.model
    cols = run.columns
    speed_c, current_c, torque_c, amb_c = (model.find_input(r) for r in (Role.SPEED, Role.CURRENT, Role.TORQUE,
                                                                       Role.AMBIENT))
    med = {c: float(np.nanmedian(cols[c])) for c in model.inputs if c in cols}
    speeds = [0.0]
    if speed_c is not None:
        top = float(np.nanmax(np.abs(cols[speed_c])))
        speeds = sorted({0.0, round(top / 2, -1), round(top, -1)})
    currents = [0.0]
    if current_c is not None:
        top = float(np.nanmax(np.abs(cols[current_c])))
        currents = sorted({round(top * f, 1) for f in (0.0, 0.25, 0.5, 0.75, 1.0)})
    ratio = 0.0
    if torque_c is not None and current_c is not None and torque_c in cols:
        i, tq = np.abs(cols[current_c]), cols[torque_c]
        ok = i > 0.2 * max(float(np.nanmax(i)), 1e-9)
        ratio = float(np.nanmedian(tq[ok] / i[ok])) if ok.any() else 0.0
    ambients = [med.get(amb_c, 25.0)] if amb_c else [0.0]
    if amb_c and amb_c in cols:
        ambients = sorted({round(float(np.nanmin(cols[amb_c]))), round(float(np.nanmax(cols[amb_c]))) + 15})
    best: Point | None = None
    steady: tuple[np.ndarray, np.ndarray] | None = None  # both models' node temperatures at ``best``
    for n in speeds:
        for i in currents:
            if speed_c is not None and n == 0.0 and i > 0.0:
                # a locked rotor: the phase currents are DC, the phase at the peak carries twice the
                # mean copper loss in its coils, which a model fed the RMS current does not see (and
                # drives forbid stalling at rated current): no test run to recommend
                continue
            for ta in ambients:
                inp = dict(med)
                inp.update({c: v for c, v in ((speed_c, n), (current_c, i), (torque_c, ratio * i)) if c is not None})
                if amb_c:
                    inp[amb_c] = ta
                inp = {k: v for k, v in inp.items() if k in model.inputs}
                try:
                    Ta, _ = steady_state(a.model, inp, a.theta)
                    Tb, _ = steady_state(b.model, inp, b.theta)
                except (ValueError, ArithmeticError, np.linalg.LinAlgError):
                    continue
                if not (_admissible(a.model, Ta) and _admissible(b.model, Tb)):
                    continue
                for s in data.sensors:
                    va = float(Ta[a.model.node_index(a.model.sensors[s])])
                    vb = float(Tb[b.model.node_index(b.model.sensors[s])])
                    if np.isfinite(va) and np.isfinite(vb) and (best is None or abs(va - vb) > best.diff):
                        best = Point(inp, s, va, vb, _near(run, inp, [speed_c, current_c]), dict(model.input_roles))
                        steady = (Ta, Tb)
    if best is not None and steady is not None:
        common = [x for x in a.model.nodes if x in b.model.nodes]
        d = [abs(float(steady[0][a.model.node_index(x)] - steady[1][b.model.node_index(x)])) for x in common]
        if common:
            x = common[int(np.argmax(d))]
            best.node = x
            best.node_a = float(steady[0][a.model.node_index(x)])
            best.node_b = float(steady[1][b.model.node_index(x)])
    return best


#: K: a recommended test run keeps every limited node at least this far below its warning
#: temperature in both fitted models (the models differ there, so neither is known to be right)
TEST_MARGIN_K = 10.0


def _admissible(model: Model, T: np.ndarray) -> bool:
    """Every limited node :data:`TEST_MARGIN_K` below its warning temperature (and every node finite)."""
    if not np.all(np.isfinite(T)):
        return False
    return all(float(T[model.node_index(lim.node)]) < lim.warn_c - TEST_MARGIN_K for lim in model.limits)


def _near(run: Run, inp: dict[str, float], columns: Sequence[str | None]) -> bool:
    """The run spent at least 10 minutes within 10 % of the point's values of ``columns`` (its
    speed and current)."""
    ok = np.ones(len(run), bool)
    for c in columns:
        if c is not None and c in inp and c in run.columns:
            x = np.abs(run.columns[c])
            ok &= np.abs(x - inp[c]) <= 0.1 * max(float(np.nanmax(x)), 1e-9)
    return bool(ok.sum() * run.dt >= 600.0)


@dataclass
class GapStatus:
    """The gap judged against the noise floor: ``none`` (nothing to explain), ``explained``,
    ``partly explained`` (effects added, a gap remains) or ``unexplained``."""

    status: str
    gap_k: float
    noise_k: float
    threshold_k: float
    worst_sensor: str = ""
    worst_rms_k: float = float("nan")
    where: list[str] = field(default_factory=list)  # regimes with the largest residual
    when: str = ""  # the stretch of the run with the largest residual
    nearest: list[tuple[str, float, float]] = field(default_factory=list)  # (candidate, gap K, improvement)

    @property
    def ratio(self) -> float:
        return self.gap_k / self.noise_k if self.noise_k > 0 else float("inf")


def gap_status(gap_k: float, noise_k: float, min_gain_k: float, named: bool, residual: np.ndarray, t_h: np.ndarray,
               analysis_sensors: Sequence[SensorResiduals], nearest: Sequence[tuple[str, float, float]]) -> GapStatus:
    """Judge the final held-out gap against the noise floor and locate what remains.

    ``residual`` (N, ns) and ``t_h`` (hours since the start of the run) cover the held-out part.
    """
    thr = NO_GAP_FACTOR * noise_k + min_gain_k
    if gap_k <= thr:
        return GapStatus("explained" if named else "none", gap_k, noise_k, thr)
    st = GapStatus("partly explained" if named else "unexplained", gap_k, noise_k, thr, nearest=list(nearest))
    worst = max(analysis_sensors, key=lambda s: s.rms_heldout if np.isfinite(s.rms_heldout) else -1)
    st.worst_sensor, st.worst_rms_k = worst.sensor, worst.rms_heldout
    regs = sorted(worst.regimes, key=lambda r: -r[4])
    st.where = [f"{rg} ({ax}, {sh:.0%} of the run): RMS {rm:.2f} K, bias {b:+.2f} K" for ax, rg, sh, b, rm in regs[:3]]
    e2 = np.nanmean(residual**2, axis=1)
    w = max(1, len(e2) // 10)
    roll = np.convolve(np.nan_to_num(e2), np.ones(w) / w, mode="valid")
    k = int(np.argmax(roll))
    h0, h1 = t_h[k], t_h[k + w - 1]
    st.when = f"{h0:.2f}–{h1:.2f} h after the start (RMS {math.sqrt(roll[k]):.2f} K over the sensors)"
    return st
