"""Fitting pieces of the discovery workflow: windows, refit, score test, candidate fits, held-out scores.

* :func:`prepare` splits a run into a training part (default the first 2/3) and a held-out part,
  and decimates the training window for the optimiser (5 s steps by default, fewer if the
  model's fastest mode needs it).
* :func:`refit` fits parameters (log-scaled, bounded) by Gauss-Newton on the training window,
  reusing :class:`thermal_edge.estimation.objective.Objective` and
  :func:`thermal_edge.estimation.gauss_newton.fit_gauss_newton`.
* :func:`score_test` is the Lagrange-multiplier (score) test of every candidate at zero effect:
  with residuals ``r`` of the refitted model and sensitivities ``J = [J_b, J_e]`` (base
  parameters in logs, effect parameters linear at their zero-effect value) the efficient score
  and information are ``g* = J_eᵀr − H_eb H_bb⁻¹ J_bᵀr`` and ``I* = H_ee − H_eb H_bb⁻¹ H_be``
  (``H = JᵀJ``), and ``g*ᵀ I*⁻¹ g*`` is the drop of the residual sum of squares a joint
  Gauss-Newton step would give. Effect parameters are one-sided (an effect adds, never
  removes: a step of the wrong sign scores zero) unless marked two-sided; a step beyond a
  parameter's bounds is shortened onto them. Many candidates share one simulation: they
  are added together at zero effect (which leaves the model unchanged) and differentiated at once.
* :func:`heldout` simulates the whole run at its own sample rate and scores each part.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..data import Run, RunError
from ..estimation.common import ParamSpace, Window, decimate, window_from_arrays
from ..estimation.gauss_newton import fit_gauss_newton
from ..estimation.objective import Objective
from ..estimation.predict import model_inputs
from ..lptn import Model, Network, Role, Simulator, initial_state
from . import effects as E


@dataclass
class Data:
    """A run prepared for discovery."""

    run: Run
    sensors: list[str]
    split: int  # first held-out sample
    factor: int  # decimation of the training window
    refs: dict[str, float]
    #: the model's input column of each role it declares (speed, current, ambient …)
    roles: dict[Role, str] = field(default_factory=dict)

    @property
    def dt(self) -> float:
        return self.run.dt

    def column(self, role: Role) -> np.ndarray | None:
        """The run's column of an input role (None when the model or the run has none)."""
        name = self.roles.get(role)
        return self.run.columns.get(name) if name is not None else None


def stiff_factor(model: Model, run: Run, theta: np.ndarray | None = None, limit: float = 600.0) -> int:
    """Largest decimation factor with ``|λ_max| · Δt < limit`` at the run's fastest operating point."""
    net = Network(model)
    theta = model.nominal() if theta is None else theta
    cols = model_inputs(model, run)
    speed = model.find_input(Role.SPEED)
    op = {}
    for k in net.matrix_inputs:
        v = np.asarray(cols[k], float)
        op[k] = np.array([np.nanmax(np.abs(v)) if k == speed else np.nanmedian(v)])
    cont = net.continuous(theta, op, K=1)
    lam = np.linalg.eigvals(cont.A[0] / cont.c[:, None])
    fastest = float(np.max(np.abs(lam.real)))
    return max(1, int(limit / (fastest * run.dt)))


#: samples below which a run cannot be split into a fit and a check of any use
MIN_SAMPLES = 30


def prepare(model: Model, run: Run, sensors: Sequence[str] | None = None, train_frac: float = 2 / 3,
            fit_step_s: float = 5.0) -> Data:
    """Split and decimation of a run for a model (sensors: those of the model the run has).

    Raises
    ------
    RunError
        Sensors the model lacks, no measured sample of a sensor, fewer than :data:`MIN_SAMPLES` samples.
    """
    have = [s for s in model.sensors if s in run.columns and np.isfinite(run.columns[s]).any()]
    if sensors:
        unknown = [s for s in sensors if s not in model.sensors]
        if unknown:
            raise RunError(f"{run.source}: --sensors: model {model.name} has no sensor(s) {', '.join(unknown)} "
                           f"(has: {', '.join(model.sensors)})")
        absent = [s for s in sensors if s not in have]
        if absent:
            raise RunError(f"{run.source}: no measured sample of sensor(s) {', '.join(absent)}")
        have = list(sensors)
    if not have:
        raise RunError(f"{run.source}: none of the sensors of model {model.name} ({', '.join(model.sensors)}) "
                       "has a measured sample in the run")
    N = len(run)
    if N < MIN_SAMPLES:
        raise RunError(f"{run.source}: {N} samples are too few for discovery (at least {MIN_SAMPLES})")
    split = int(round(N * train_frac))
    factor = max(1, int(round(fit_step_s / run.dt)))
    factor = min(factor, stiff_factor(model, run))
    roles = {role: name for name, role in model.input_roles.items()}
    return Data(run, have, split, factor, E.references(model, run.columns), roles)


_SIMS: dict[int, tuple[Model, Simulator]] = {}


def simulator(model: Model) -> Simulator:
    """A cached :class:`Simulator` per model object (its network is built once)."""
    hit = _SIMS.get(id(model))
    if hit is None or hit[0] is not model:
        if len(_SIMS) > 64:
            _SIMS.clear()
        hit = (model, Simulator(model))
        _SIMS[id(model)] = hit
    return hit[1]


def initial(model: Model, run: Run, theta: np.ndarray, k: int = 0) -> np.ndarray:
    """Node temperatures at sample ``k``: measured nodes from the sensors, the others from the
    steady state given them with the heat flows the laws give at rest
    (:func:`thermal_edge.lptn.initial_state`): an effect such as a warmer ambient then starts the
    unmeasured nodes where the machine has them."""
    inp = {c: float(v[k]) for c, v in model_inputs(model, run).items()}
    meas = {s: float(run.columns[s][k]) for s in model.sensors if s in run.columns}
    return initial_state(model, inp, meas, theta, net=simulator(model).net, rest_inputs=model.at_rest(inp))


def train_window(model: Model, data: Data, theta: np.ndarray) -> Window:
    run = data.run.slice(0, data.split)
    meas = {s: run.columns[s] for s in data.sensors}
    W = window_from_arrays(model, model_inputs(model, run), meas, initial(model, data.run, theta), data.dt, run.t)
    return decimate(W, data.factor)


@dataclass
class Fit:
    """A fitted model: its document, parameters and scores."""

    label: str
    raw: dict[str, Any]
    model: Model
    theta: np.ndarray
    names: tuple[str, ...]  # fitted parameters
    effect_params: list[str] = field(default_factory=list)
    edits: list[E.Edit] = field(default_factory=list)
    train_mse: dict[str, float] = field(default_factory=dict)
    heldout_mse: dict[str, float] = field(default_factory=dict)
    traj_T: np.ndarray | None = None  # sensor predictions over the whole run (N, ns)
    message: str = ""

    @property
    def gap(self) -> float:
        """Held-out RMS over the sensors (root of the mean MSE), K."""
        v = [x for x in self.heldout_mse.values() if np.isfinite(x)]
        return float(math.sqrt(np.mean(v))) if v else float("nan")

    @property
    def train_gap(self) -> float:
        v = [x for x in self.train_mse.values() if np.isfinite(x)]
        return float(math.sqrt(np.mean(v))) if v else float("nan")

    def values(self, names: Sequence[str]) -> dict[str, float]:
        idx = self.model.parameter_index(list(names))
        return {n: float(self.theta[i]) for n, i in zip(names, idx)}


def refit(model: Model, theta: np.ndarray, names: Sequence[str], data: Data, max_iter: int = 15,
          prior: Mapping[str, float] | None = None, prior_weight: float = 0.0) -> np.ndarray:
    """Gauss-Newton fit of ``names`` (log-scaled, within bounds) on the decimated training window.

    ``prior`` (name -> value, default the model's nominal values) and ``prior_weight`` give the
    MAP penalty of :class:`~thermal_edge.estimation.objective.Objective`: a weak pull that keeps
    parameters the sensors cannot see from wandering to their bounds.
    """
    if not names:
        return theta
    lo, hi = model.bounds()
    idx = model.parameter_index(list(names))
    th = theta.copy()
    th[idx] = np.clip(th[idx], lo[idx] * (1 + 1e-9), hi[idx] * (1 - 1e-9))
    nominal = model.nominal()
    pv = np.array([float((prior or {}).get(n, nominal[i])) for n, i in zip(names, idx)])
    pv = np.clip(pv, lo[idx] * (1 + 1e-9), hi[idx] * (1 - 1e-9))
    space = ParamSpace(model, tuple(names), th, pv)
    W = train_window(model, data, th)
    obj = Objective(simulator(model), space, W, sensors=data.sensors, weighting="uniform", prior_weight=prior_weight)
    res = fit_gauss_newton(obj, max_iter=max_iter)
    out = th.copy()
    out[idx] = res.values
    return out


def heldout(model: Model, theta: np.ndarray, data: Data) -> tuple[dict[str, float], dict[str, float], np.ndarray]:
    """Training and held-out MSE per sensor (K²) of an open-loop run from the first sample, and
    the sensor predictions (N, ns)."""
    run = data.run
    traj = simulator(model).simulate(theta, model_inputs(model, run), data.dt, initial(model, run, theta))
    pred = np.column_stack([traj.node(model.sensors[s]) for s in data.sensors])
    tr, ho = {}, {}
    for j, s in enumerate(data.sensors):
        e = pred[:, j] - run.columns[s]
        a, b = e[: data.split], e[data.split:]
        tr[s] = float(np.nanmean(a**2)) if np.isfinite(a).any() else float("nan")
        ho[s] = float(np.nanmean(b**2)) if np.isfinite(b).any() else float("nan")
    return tr, ho, pred


# ------------------------------------------------------------------------------------------
# score test

@dataclass
class Score:
    cand: E.Candidate
    score: float  # predicted drop of the training residual sum of squares, K² (per sample mean)
    fraction: float  # of the training residual sum of squares
    step: dict[str, float]  # zero-effect value + Gauss-Newton step of the primary parameters
    note: str = ""


def _solve_bounded(g: np.ndarray, I: np.ndarray, lo: np.ndarray, hi: np.ndarray, signed: np.ndarray) -> tuple[float, np.ndarray]:
    """Best decrease ``2 gᵀδ − δᵀIδ`` over ``lo ≤ δ ≤ hi`` (``g`` the descent direction).

    Small problems (1–3 parameters): every subset of free parameters is solved with the others
    at zero; one-sided parameters (``signed`` False, ``lo`` = 0) must come out positive; a step
    beyond the bounds is shortened onto them (the linearisation would not hold beyond).
    """
    p = len(g)
    best, best_d = 0.0, np.zeros(p)
    for k in range(1, p + 1):
        for sub in itertools.combinations(range(p), k):
            s = list(sub)
            Is = I[np.ix_(s, s)]
            try:
                d = np.linalg.solve(Is, g[s])
            except np.linalg.LinAlgError:
                continue
            if np.any((d <= 0) & ~signed[s]):
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                lim = np.where(d > 0, hi[s] / d, np.where(d < 0, lo[s] / d, np.inf))
            t = float(np.min(lim)) if len(lim) else 1.0
            if t < 1.0:
                d = d * t
            val = float(2 * g[s] @ d - d @ Is @ d)
            if val > best:
                best, best_d = val, np.zeros(p)
                best_d[s] = d
    return best, best_d


def _chunks(cands: Sequence[E.Candidate], size: int) -> list[list[E.Candidate]]:
    # effects that read laws from the built model come first in every chunk; effects that move
    # a sensor onto a new node, and laws not affine in T (simulated step by step), get chunks of their own
    lags = [c for c in cands if c.effect.moves_sensor]
    nonaffine = [c for c in cands if c.effect.nonaffine and not c.effect.moves_sensor]
    rest = sorted((c for c in cands if not (c.effect.moves_sensor or c.effect.nonaffine)),
                  key=lambda c: not c.effect.reads_built_model)
    out: list[list[E.Candidate]] = []
    for group in (rest, lags, nonaffine):
        cur: list[E.Candidate] = []
        n_p = 0
        for c in group:
            k = sum(p.primary for p in c.effect.params)
            if cur and n_p + k > size:
                out.append(cur)
                cur, n_p = [], 0
            cur.append(c)
            n_p += k
        if cur:
            out.append(cur)
    return out


def _jacobian(model: Model, theta: np.ndarray, wrt: Sequence[str], data: Data,
              log_cols: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (flattened), Jacobian (flattened rows × wrt) and the mask on the training window."""
    W = train_window(model, data, theta)
    rows = [model.sensors[s] for s in data.sensors]
    traj = simulator(model).simulate(theta, W.inputs, W.dt, W.T0, wrt=list(wrt), rows=rows)
    Y = np.column_stack([W.measured[s] for s in data.sensors])
    mask = np.isfinite(Y)
    pred = traj.T[:, [model.node_index(r) for r in rows]]
    r = np.where(mask, pred - np.where(mask, Y, 0.0), 0.0).reshape(-1)
    assert traj.S is not None
    S = traj.S * mask[:, :, None]
    if log_cols:
        idx = model.parameter_index(list(wrt[:log_cols]))
        S[:, :, :log_cols] *= theta[idx]
    return r, S.reshape(-1, len(wrt)), mask


_CHUNKS: dict[tuple[Any, ...], tuple[Any, list[list[str]], Model]] = {}


def score_test(raw: Mapping[str, Any], base: Fit, cands: Sequence[E.Candidate], data: Data,
               build: Callable[[dict[str, Any]], Model], base_names: Sequence[str], chunk: int = 48) -> list[Score]:
    """Score test of every candidate at zero effect, with the refitted base parameters.

    The residuals and base sensitivities come from the base model; each candidate's
    sensitivities from a model with a chunk of candidates added at zero effect.
    """
    out: list[Score] = []
    if base_names:
        r, Jb, mask = _jacobian(base.model, base.theta, list(base_names), data, log_cols=len(base_names))
    else:  # no projection: the effect alone against the residual (a screen, not a test)
        r, _, mask = _jacobian(base.model, base.theta, base.model.parameter_names[:1], data)
        Jb = np.zeros((len(r), 0))
    n_obs = max(int(mask.sum()), 1)
    rss = float(r @ r)
    nb = len(base_names)
    Hbb = Jb.T @ Jb
    Hbb_reg = Hbb + np.eye(nb) * 1e-10 * (np.trace(Hbb) / max(nb, 1) + 1e-30)
    gb = Jb.T @ r
    base_vals = base.values([p.name for p in base.model.parameters])
    ctx0 = E.context(raw, base.model, data.refs)
    for group in _chunks(cands, chunk):
        key = (id(raw), tuple(c.label for c in group), tuple(sorted(data.refs.items())))
        hit = _CHUNKS.get(key)
        if hit is None or hit[0] is not raw:  # the test and the screen share the chunk models
            if len(_CHUNKS) > 32:
                _CHUNKS.clear()
            doc, pnames, _ = E.augment(raw, [(c, None) for c in group], data.refs, build, model=base.model)
            hit = (raw, pnames, build(doc))
            _CHUNKS[key] = hit
        _, pnames, model = hit
        theta = model.nominal()
        idx = {p.name: i for i, p in enumerate(model.parameters)}
        for n, v in base_vals.items():
            theta[idx[n]] = v
        prim: list[list[str]] = []
        for c, names in zip(group, pnames):
            sc = E.scale(ctx0, c)
            pl = []
            for p, n in zip(c.effect.params, names):
                theta[idx[n]] = p.null * sc if p.primary else p.nominal
                if p.primary:
                    pl.append(n)
            prim.append(pl)
        wrt = [n for pl in prim for n in pl]
        try:
            _, J, _ = _jacobian(model, theta, wrt, data)
        except (ValueError, np.linalg.LinAlgError) as exc:
            out.extend(Score(c, 0.0, 0.0, {}, f"simulation failed: {exc}") for c in group)
            continue
        col = 0
        for c, pl in zip(group, prim):
            k = len(pl)
            Je = J[:, col: col + k]
            col += k
            if not np.all(np.isfinite(Je)):
                out.append(Score(c, 0.0, 0.0, {}, "sensitivity not finite"))
                continue
            Heb = Je.T @ Jb
            g = -(Je.T @ r - Heb @ np.linalg.solve(Hbb_reg, gb)) if nb else -(Je.T @ r)
            I = Je.T @ Je - Heb @ np.linalg.solve(Hbb_reg, Heb.T) if nb else Je.T @ Je
            raw_info = np.diag(Je.T @ Je)
            if np.all(raw_info <= 1e-300):
                out.append(Score(c, 0.0, 0.0, {}, "no sensitivity at the sensors"))
                continue
            if np.any(np.diag(I) <= 1e-6 * raw_info):
                out.append(Score(c, 0.0, 0.0, {}, "indistinguishable from the adaptable parameters"))
                continue
            sc = E.scale(ctx0, c)
            ps = [p for p in c.effect.params if p.primary]
            hi = np.array([(p.upper - p.null) * sc for p in ps])
            lo = np.array([(p.lower - p.null) * sc if p.two_sided else 0.0 for p in ps])
            val, d = _solve_bounded(g, I, lo, hi, np.array([p.two_sided for p in ps]))
            note = "" if val > 0 else "would need a negative effect"
            step = {p.short: p.null * sc + float(dv) for p, dv in zip(ps, d)}
            out.append(Score(c, val / n_obs, val / rss if rss > 0 else 0.0, step, note))
    out.sort(key=lambda s: -s.score)
    return out


def fit_candidate(raw: Mapping[str, Any], cand: E.Candidate, start: Mapping[str, float], base: Fit,
                  fit_names: Sequence[str], data: Data, build: Callable[[dict[str, Any]], Model],
                  max_iter: int = 12, prior: Mapping[str, float] | None = None, prior_weight: float = 0.0) -> Fit:
    """Add a candidate with start values (short name -> value), refit it with ``fit_names``, score it.

    The base parameters start from ``base`` and are pulled toward ``prior`` (default nominal);
    the effect's parameters are pulled (weakly) toward their start values.
    """
    sc = E.scale(E.context(raw, base.model, data.refs), cand)
    values = {}
    for p in cand.effect.params:
        lo, hi = p.lower * (sc if p.primary else 1.0), p.upper * (sc if p.primary else 1.0)
        v = start.get(p.short, p.nominal)
        values[p.short] = float(np.clip(v, lo * 2.0, hi / 2.0)) if p.primary else float(v)
    doc, pnames, edits = E.augment(raw, [(cand, values)], data.refs, build, model=base.model)
    model = build(doc)
    theta = model.nominal()
    idx = {p.name: i for i, p in enumerate(model.parameters)}
    for n, v in base.values([p.name for p in base.model.parameters]).items():
        theta[idx[n]] = v
    names = list(fit_names) + list(pnames[0])
    pri = dict(prior or {})
    pri.update({n: theta[idx[n]] for n in pnames[0]})
    fit = Fit(cand.label, doc, model, theta, tuple(names), list(pnames[0]), edits)
    try:
        fit.theta = refit(model, theta, names, data, max_iter=max_iter, prior=pri, prior_weight=prior_weight)
    except (ValueError, np.linalg.LinAlgError, FloatingPointError) as exc:
        fit.message = f"fit failed: {exc}"
    # write the fitted values into the document
    for n in pnames[0]:
        spec = doc["parameters"][n]
        v = float(fit.theta[idx[n]])
        spec["value"] = float(f"{v:.6g}")
        spec["min"] = min(spec["min"], spec["value"])
        spec["max"] = max(spec["max"], spec["value"])
    try:
        fit.train_mse, fit.heldout_mse, fit.traj_T = heldout(model, fit.theta, data)
    except (ValueError, np.linalg.LinAlgError) as exc:
        fit.message = f"simulation failed: {exc}"
        fit.heldout_mse = {s: float("nan") for s in data.sensors}
    return fit
