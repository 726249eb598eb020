"""The discovery workflow: refit, residual analysis, score test, full fits, held-out ranking, repeat.

One *round* on the current model:

1. **Refit** the fitted parameters (the model's adaptable ones plus the parameters of effects
   added in earlier rounds) on the training part of the run, so that what remains is structural.
   Every fit is pulled toward the nominal values within the parameters' stated spread
   (``Options.prior_weight``), so that a refit does not absorb an effect beyond what the model
   file allows.
2. **Residual analysis** of the refitted model over the whole run (:mod:`.residuals`).
3. **Score test** of every applicable catalogue candidate at zero effect with the refitted
   parameters (:func:`.fitting.score_test`), and a *screen* of the candidates against the
   residual of the model at its nominal (file) values: a refit can mimic an effect well enough
   that the local test at the refit no longer sees it (a 5-minute sensor lag absorbed by a
   larger winding capacity); the screen catches those.
4. **Full fits** of the best few (``n_fit`` from the test, ``n_screen`` more from the screen,
   at most two per effect name), each with the fitted parameters, from the refit (test) or the
   nominal values (screen); and a *control*: the refit continued with the same budget.
5. **Ranking** on the held-out part (the last third): held-out RMS gap over the sensors and the
   BIC ``N ln(MSE) + k ln(N)`` (``N`` the held-out samples on the fitting grid, ``k`` the
   effect's parameters), which prefers the simpler of two candidates that predict alike. A
   candidate is accepted when it lowers the BIC and the held-out gap by at least
   ``min_improvement`` (default 10 %) and ``min_gain_k`` (default 0.05 K) against the better of
   refit and control, or removes ``min_share_above_noise`` (50 %) and ``min_gain_k`` of the
   gap above the sensor noise floor (``sqrt(gap² − noise²)``: where the refit imitates the
   effect, little is left above the noise, and 10 % of the whole gap may be more than that).
   (Thermal residuals are strongly correlated in time, so no sample-count
   based test is honest about significance; the two thresholds are the practical guard, and
   data without a missing effect must end with "no missing effect found".)
6. The winner is compared with the runner-up (:mod:`.judge`): when the runner-up explains the
   held-out residual nearly as well (within the uncertainty of the held-out gap), held-out
   samples from an operating region the training part lacks decide where there are enough,
   and may swap the two; otherwise the pair is reported as confusable, with the evidence that
   separates them and the steady operating point that would.
7. The winner is added (its fitted parameters become model parameters) and the next round
   starts from it, until no candidate is accepted or ``max_rounds`` is reached. With no
   winner in the first round the verdict is "no missing effect found", and the gap is judged
   against the sensor noise floor: "no gap" or "a gap the catalogue does not explain".
"""
from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data import Run
from ..lptn import Model
from . import effects as E
from . import fitting as F
from . import judge as J
from . import residuals as R
from . import signature as S
from . import yamlpatch


@dataclass
class Options:
    sensors: Sequence[str] | None = None
    train_frac: float = 2 / 3
    fit_step_s: float = 5.0
    max_rounds: int = 3
    n_fit: int = 3
    n_screen: int = 2
    min_improvement: float = 0.10
    min_gain_k: float = 0.05
    #: or: the share of the gap above the noise floor a candidate removes (with ``min_gain_k`` of it);
    #: a refit that imitates an effect leaves a gap near the noise floor, where 10 % of the whole gap
    #: can be more than there is to remove
    min_share_above_noise: float = 0.5
    effects: Sequence[str] | None = None
    #: MAP pull of every fit (refit, control, candidates) toward the nominal values: a parameter one
    #: spread (its ``spread``, σ of log θ) away costs this many K² of training mean squared error.
    #: Without it the refit absorbs part of a missing effect into the adaptable parameters beyond
    #: their stated spread (on the real Paderborn run the copper coefficient was then fitted as a
    #: loss scale, 54 % of the opened gap closed; with 0.3: 83 %). Effect parameters carry a wide
    #: spread (a quarter of their log range), so the pull on them is weak.
    prior_weight: float = 0.3
    refit_iter: int = 20
    fit_iter: int = 12


@dataclass
class Ranked:
    fit: F.Fit
    source: str  # test | screen | control
    score: float  # fraction of the training residual the score test/screen predicts
    improvement: float  # relative held-out gap reduction vs the round's reference
    criterion: float  # BIC-like, lower is better
    delta_criterion: float
    accepted: bool
    k: int
    improvement_above_noise: float = float("nan")  # relative reduction of the gap above the noise floor


@dataclass
class Round:
    index: int
    base: F.Fit
    analysis: R.Analysis
    scores: list[F.Score]
    screen: list[F.Score]
    ranked: list[Ranked]
    reference_gap: float
    n_eff: float
    winner: Ranked | None = None
    wall_s: float = 0.0
    runner_up: Ranked | None = None  # the best other candidate by held-out gap
    comparison: J.Comparison | None = None  # winner against runner-up (both must explain something)
    evidence: list[J.Evidence] = field(default_factory=list)
    point: J.Point | None = None  # steady operating point that separates winner and runner-up
    #: every other candidate the winner cannot be separated from on this run (the runner-up first)
    confusable: list[Ranked] = field(default_factory=list)


@dataclass
class Discovery:
    model_name: str
    source: str
    data: F.Data
    nominal: F.Fit
    rounds: list[Round]
    final: F.Fit
    raw0: dict[str, Any]
    wall_s: float = 0.0
    model_out: str | None = None
    report: str | None = None
    notes: list[str] = field(default_factory=list)
    noise_k: float = 0.0
    final_analysis: R.Analysis | None = None
    options: Options = field(default_factory=Options)
    gap: J.GapStatus | None = None
    #: catalogue effects the model cannot express (no node of the roles they act on, ...)
    not_placeable: list[E.NotPlaceable] = field(default_factory=list)
    #: how the first round's held-out residual depends on speed, current and ambient
    signature: S.Signature | None = None

    @property
    def runner_up(self) -> Ranked | None:
        return self.rounds[0].runner_up if self.rounds else None

    @property
    def ambiguous(self) -> bool:
        c = self.rounds[0].comparison if self.rounds else None
        return bool(self.named is not None and c is not None and c.ambiguous)

    @property
    def confusable(self) -> list[Ranked]:
        """The candidates the named effect cannot be separated from (empty when it is clear)."""
        return self.rounds[0].confusable if self.ambiguous else []

    @property
    def unexpressed(self) -> list[E.NotPlaceable]:
        """Effects the model cannot express whose predicted signature is the residual's: the
        answer may be "none of the candidates"."""
        sig = self.signature
        if sig is None or (self.gap is not None and self.gap.status == "none"):
            return []
        return [n for n in self.not_placeable if sig.fits(n.effect.explains)]

    @property
    def verdict(self) -> str:
        named, g = self.named, self.gap
        if named is not None:
            v = f"missing effect: {named.fit.label}"
            if self.confusable:
                v += "".join(f" or {r.fit.label}" for r in self.confusable) + " (this run cannot separate them)"
            if g is not None and g.status == "partly explained":
                v += f"; a gap of {g.gap_k:.3f} K remains that the catalogue does not explain"
            return v + self._unexpressed_clause("would fit it too")
        if g is not None and g.status == "unexplained":
            return (f"no missing effect found: a gap of {g.gap_k:.3f} K ({g.ratio:.0f}x the noise floor) "
                    "that the catalogue does not explain" + self._unexpressed_clause("would fit its signature"))
        return "no missing effect found: no gap (within the noise floor)"

    def _unexpressed_clause(self, what: str) -> str:
        un = self.unexpressed
        if not un or self.signature is None:
            return ""
        names = " or ".join(n.effect.name for n in un)
        return f"; but {names}, which this model cannot express, {what} (the residual {self.signature.describe()})"

    @property
    def added(self) -> list[Ranked]:
        return [r.winner for r in self.rounds if r.winner is not None]

    @property
    def named(self) -> Ranked | None:
        return self.added[0] if self.added else None

    @property
    def gap_before(self) -> float:
        return self.rounds[0].base.gap

    @property
    def gap_after(self) -> float:
        return self.final.gap

    def as_dict(self) -> dict[str, Any]:
        named = self.named
        first = self.rounds[0]
        cand = []
        ranked = {r.fit.label: r for r in first.ranked}
        for s in first.scores:
            r = ranked.get(s.cand.label)
            cand.append({
                "name": s.cand.effect.name, "target": s.cand.target, "score": s.fraction,
                "improvement": None if r is None else r.improvement,
                "heldout_gap_k": None if r is None else r.fit.gap, "note": s.note,
            })
        for r in first.ranked:  # screen-only fits
            if r.source == "screen" and r.fit.label not in {s.cand.label for s in first.scores}:
                cand.append({"name": r.fit.label, "target": None, "score": r.score, "improvement": r.improvement,
                             "heldout_gap_k": r.fit.gap, "note": "screen"})
        nm, tg = (named.fit.label.split(":", 1) + [None])[:2] if named else (None, None)
        return {
            "model": self.model_name,
            "run": self.source,
            "sensors": self.data.sensors,
            "named_effect": nm,
            "target": tg,
            "effects_added": [{"effect": r.fit.label, "params": self.final.values(r.fit.effect_params),
                               "gap_k": r.fit.gap, "improvement": r.improvement} for r in self.added],
            "verdict": self.verdict,
            "runner_up": self.runner_up.fit.label if self.runner_up else None,
            "ambiguous": self.ambiguous,
            "confusable": [r.fit.label for r in self.confusable],
            "not_placeable": [{"effect": n.effect.name, "reason": n.reason, "explains": n.effect.explains,
                               "fits_signature": None if self.signature is None else self.signature.fits(n.effect.explains)}
                              for n in self.not_placeable],
            "signature": None if self.signature is None else self.signature.as_dict(),
            "gap_noise_floor": self.noise_k,
            "gap_status": self.gap.status if self.gap else None,
            "gap_detail": self._gap_dict(),
            "comparison": self._comparison_dict(),
            "gap_before": self.gap_before,
            "gap_after": self.gap_after,
            "gap_nominal": self.nominal.gap,
            "noise_floor_k": self.noise_k,
            "gap_above_noise_before": J.above_noise(self.gap_before, self.noise_k),
            "gap_above_noise_after": J.above_noise(self.gap_after, self.noise_k),
            "shrink": 1.0 - self.gap_after / self.gap_before if self.gap_before > 0 else 0.0,
            "per_sensor_before": {s: math.sqrt(v) for s, v in first.base.heldout_mse.items()},
            "per_sensor_after": {s: math.sqrt(v) for s, v in self.final.heldout_mse.items()},
            "candidates": cand,
            "rounds": [
                {"round": r.index, "reference_gap_k": r.reference_gap, "n_eff": r.n_eff,
                 "fits": [{"effect": x.fit.label, "source": x.source, "heldout_gap_k": x.fit.gap,
                           "improvement": x.improvement, "delta_criterion": x.delta_criterion,
                           "accepted": x.accepted, "message": x.fit.message} for x in r.ranked],
                 "winner": r.winner.fit.label if r.winner else None, "wall_s": r.wall_s}
                for r in self.rounds
            ],
            "refs": self.data.refs,
            "model_out": self.model_out,
            "report": self.report,
            "wall_s": self.wall_s,
            "notes": self.notes,
        }


    def _gap_dict(self) -> dict[str, object] | None:
        g = self.gap
        if g is None:
            return None
        return {"gap_k": g.gap_k, "noise_floor_k": g.noise_k, "threshold_k": g.threshold_k, "ratio": g.ratio,
                "worst_sensor": g.worst_sensor or None, "where": g.where, "when": g.when or None,
                "nearest": [{"effect": n, "heldout_gap_k": v, "improvement": i} for n, v, i in g.nearest]}

    def _comparison_dict(self) -> dict[str, object] | None:
        rd = self.rounds[0] if self.rounds else None
        c = rd.comparison if rd else None
        if rd is None or c is None:
            return None
        p = rd.point
        return {
            "winner": c.a, "runner_up": c.b, "gap_winner_k": c.gap_a, "gap_runner_up_k": c.gap_b,
            "se_diff_k": c.se_diff, "share_of_reduction": c.share, "ambiguous": c.ambiguous,
            "decided_by": c.decided_by or None,
            "evidence": [{"variable": e.variable, "sensor": e.sensor, "centers": e.centers, "winner": e.a,
                          "runner_up": e.b} for e in rd.evidence],
            "separating_condition": None if p is None else {
                "point": p.describe(), "inputs": p.inputs, "sensor": p.sensor, "winner_c": p.t_a,
                "runner_up_c": p.t_b, "diff_k": p.diff, "in_run": p.in_run,
                "node": p.node or None, "node_winner_c": p.node_a, "node_runner_up_c": p.node_b,
                "sensors_separate": p.sensors_separate(self.noise_k), "node_separates": p.node_separates(self.noise_k)},
        }


def _n_eff(res: np.ndarray, split: int, factor: int) -> float:
    """Held-out samples on the fitting grid (the BIC's N)."""
    return float(max(5, len(res[split::max(factor, 1)])))


def _criterion(gap: float, k: int, n_eff: float) -> float:
    return n_eff * math.log(max(gap, 1e-12) ** 2) + k * math.log(n_eff)


def _select(scores: Sequence[F.Score], n: int, taken: set[str], per_effect: dict[str, int]) -> list[F.Score]:
    out: list[F.Score] = []
    for s in scores:
        if len(out) >= n:
            break
        if s.score <= 0 or s.cand.label in taken or per_effect.get(s.cand.effect.name, 0) >= 2:
            continue
        out.append(s)
        taken.add(s.cand.label)
        per_effect[s.cand.effect.name] = per_effect.get(s.cand.effect.name, 0) + 1
    return out


def discover(raw: dict[str, Any], run: Run, build: Callable[[dict[str, Any]], Model], options: Options | None = None,
             log: Callable[[str], None] | None = None) -> Discovery:
    """Run the workflow on a model document and a run (see the module docstring)."""
    opt = options or Options()
    say = log or (lambda msg: None)
    t0 = time.perf_counter()
    model0 = build(raw)
    data = F.prepare(model0, run, opt.sensors, opt.train_frac, opt.fit_step_s)
    say(f"{model0.name}: {len(run)} samples at {run.dt:g} s, sensors {', '.join(data.sensors)}; fitting on the "
        f"first {data.split} samples at {data.dt * data.factor:g} s, held out the last {len(run) - data.split}")
    nominal = F.Fit("nominal", raw, model0, model0.nominal(), ())
    nominal.train_mse, nominal.heldout_mse, nominal.traj_T = F.heldout(model0, nominal.theta, data)
    noise = noise_floor(run, data.sensors, data.split)
    fit_names = list(model0.adaptable)
    prior = {n: float(v) for n, v in zip(model0.parameter_names, model0.nominal())}
    theta = F.refit(model0, model0.nominal(), fit_names, data, max_iter=opt.refit_iter, prior=prior,
                    prior_weight=opt.prior_weight)
    base = F.Fit("refit", raw, model0, theta, tuple(fit_names))
    base.train_mse, base.heldout_mse, base.traj_T = F.heldout(model0, theta, data)
    say(f"held-out gap: nominal {nominal.gap:.3f} K, refitted ({len(fit_names)} parameters) {base.gap:.3f} K")
    rounds: list[Round] = []
    not_placeable: list[E.NotPlaceable] = []
    sig: S.Signature | None = None
    cur_raw, cur_nominal = raw, nominal
    added_labels: set[str] = set()
    for k in range(1, opt.max_rounds + 1):
        tr = time.perf_counter()
        assert base.traj_T is not None
        analysis = R.analyse(run, data.sensors, base.traj_T, data.split, base.model.boundaries, data.refs, data.roles)
        ctx = E.context(cur_raw, base.model, data.refs, build)
        cands = [c for c in E.applicable(ctx, opt.effects) if c.label not in added_labels]
        scores = F.score_test(cur_raw, base, cands, data, build, fit_names)
        screen = F.score_test(cur_raw, cur_nominal, cands, data, build, [])
        later = 1 if k > 1 else 0  # fewer full fits once an effect has been added
        taken: set[str] = set()
        picks = [(s, "test") for s in _select(scores, max(1, opt.n_fit - later), taken, {})]
        # the screen's best is fitted from the nominal values even when the test picked it too (a
        # refit that mimics an effect can hold that effect's fit in a worse basin); the others
        # of the screen only when the test did not
        top = _select(screen, 1, set(), {})
        picks += [(s, "screen") for s in top]
        taken |= {s.cand.label for s in top}
        picks += [(s, "screen") for s in _select(screen, max(1, opt.n_screen - later) - len(top), taken, {})]
        say(f"round {k}: {len(cands)} candidates scored; full fits: " + ", ".join(f"{s.cand.label} ({src})" for s, src in picks))
        n_eff = _n_eff(analysis.residual, data.split, data.factor)
        ranked: list[Ranked] = []
        ref_gap = base.gap
        if k == 1:
            # control: the refit continued with the same budget as a candidate's fit (later
            # rounds start from a model that was refitted after the winner was added)
            control = F.Fit("control (refit continued)", cur_raw, base.model, base.theta, base.names)
            control.theta = F.refit(base.model, base.theta, fit_names, data, max_iter=opt.fit_iter, prior=prior,
                                    prior_weight=opt.prior_weight)
            control.train_mse, control.heldout_mse, control.traj_T = F.heldout(base.model, control.theta, data)
            if np.isfinite(control.gap):
                ref_gap = min(base.gap, control.gap)
            ranked.append(Ranked(control, "control", 0.0, 1 - control.gap / base.gap, _criterion(control.gap, 0, n_eff),
                                 _criterion(control.gap, 0, n_eff) - _criterion(ref_gap, 0, n_eff), False, 0))
        ref_crit = _criterion(ref_gap, 0, n_eff)
        for s, src in picks:
            start = base if src == "test" else cur_nominal
            f = F.fit_candidate(cur_raw, s.cand, s.step, start, fit_names, data, build, max_iter=opt.fit_iter,
                                prior=prior, prior_weight=opt.prior_weight)
            kpar = len(s.cand.effect.params)
            crit = _criterion(f.gap, kpar, n_eff)
            imp = 1 - f.gap / ref_gap if ref_gap > 0 and np.isfinite(f.gap) else float("nan")
            s_ref, s_fit = J.above_noise(ref_gap, noise), J.above_noise(f.gap, noise)
            imp_n = 1 - s_fit / s_ref if s_ref > 0 and np.isfinite(s_fit) else float("nan")
            whole = bool(np.isfinite(imp) and imp >= opt.min_improvement and ref_gap - f.gap >= opt.min_gain_k)
            above = bool(np.isfinite(imp_n) and imp_n >= opt.min_share_above_noise and s_ref - s_fit >= opt.min_gain_k)
            ok = bool((whole or above) and crit < ref_crit and not f.message)
            say(f"  {s.cand.label:<42} ({src}) held-out gap {f.gap:.3f} K ({imp:+.0%})" + ("  accepted" if ok else "") +
                (f"  [{f.message}]" if f.message else ""))
            twin = next((r for r in ranked if r.fit.label == f.label), None)
            if twin is not None:  # fitted from both starts: keep the better fit of the training part
                if f.train_gap < twin.fit.train_gap:
                    ranked.remove(twin)
                else:
                    continue
            ranked.append(Ranked(f, src, s.fraction, imp, crit, crit - ref_crit, ok, kpar, imp_n))
        ranked.sort(key=lambda r: (not r.accepted, r.criterion))
        rd = Round(k, base, analysis, scores, screen, ranked, ref_gap, n_eff)
        if k == 1:
            not_placeable = E.not_placeable(ctx, opt.effects)
            sig = S.signature(base, data, {r.fit.label: r.fit for r in ranked if r.source != "control"})
        best = ranked[0] if ranked and ranked[0].accepted else None
        best = _runner_up(rd, best, data, opt, say)
        rd.winner = best
        rd.wall_s = time.perf_counter() - tr
        rounds.append(rd)
        if best is None:
            say(f"round {k}: no candidate improves the held-out gap by {opt.min_improvement:.0%} and {opt.min_gain_k:g} K")
            break
        added_labels.add(best.fit.label)
        cur_raw = best.fit.raw
        fit_names = list(best.fit.names)
        prior.update(best.fit.values(best.fit.effect_params))
        # refit the augmented model (the winner's fit continued): the next round's base
        base = _polish(best.fit, fit_names, data, opt, prior)
        say(f"round {k}: adding {best.fit.label}; refitted, held-out gap {ref_gap:.3f} -> {base.gap:.3f} K")
        cur_nominal = F.Fit("nominal", cur_raw, base.model, base.model.nominal(), ())
    final = base
    disc = Discovery(model0.name, run.source, data, nominal, rounds, final, raw, options=opt,
                     not_placeable=not_placeable, signature=sig)
    disc.noise_k = noise
    assert final.traj_T is not None
    disc.final_analysis = R.analyse(run, data.sensors, final.traj_T, data.split, final.model.boundaries, data.refs,
                                      data.roles)
    last = rounds[-1]
    nearest = [(r.fit.label, r.fit.gap, r.improvement) for r in sorted(
        (r for r in last.ranked if r.source != "control" and np.isfinite(r.fit.gap)), key=lambda r: r.fit.gap)[:3]]
    disc.gap = J.gap_status(final.gap, disc.noise_k, opt.min_gain_k, disc.named is not None,
                            disc.final_analysis.residual[data.split:], (run.t[data.split:] - run.t[0]) / 3600.0,
                            disc.final_analysis.sensors, nearest)
    say(f"verdict: {disc.verdict}")
    disc.wall_s = time.perf_counter() - t0
    return disc


def _runner_up(rd: Round, best: Ranked | None, data: F.Data, opt: Options,
               say: Callable[[str], None]) -> Ranked | None:
    """Name the runner-up of a round; when both explain the residual, compare them (held-out gap
    with its uncertainty, then held-out data from an operating region the training part lacks,
    which may swap them), and gather the evidence that separates them. Returns the winner."""
    fits = sorted((r for r in rd.ranked if r.source != "control" and np.isfinite(r.fit.gap) and not r.fit.message),
                  key=lambda r: r.fit.gap)
    if best is None:
        rd.runner_up = fits[0] if fits else None
        return None
    others = [r for r in fits if r.fit.label != best.fit.label]
    ru = others[0] if others else None
    rd.runner_up = ru
    if ru is None or not _explains(ru, opt):
        return best  # the runner-up does not explain the residual: nothing to confuse
    bounds = dict(rd.base.model.boundaries)
    cmp = J.compare(best.fit, ru.fit, rd.reference_gap, data)
    if cmp.ambiguous:
        cmp = J.decide_novel(cmp, best.fit, ru.fit, data, bounds)
        if cmp.swapped and ru.accepted:
            decided = cmp.decided_by
            best, ru = ru, best
            rd.runner_up = ru
            cmp = J.compare(best.fit, ru.fit, rd.reference_gap, data)
            cmp.decided_by, cmp.ambiguous = decided, False
    rd.comparison = cmp
    if cmp.ambiguous:
        rd.confusable = [ru] + [r for r in others[1:] if _explains(r, opt) and
                                J.compare(best.fit, r.fit, rd.reference_gap, data).ambiguous]
    rd.evidence = J.evidence(rd.base, best.fit, ru.fit, data, bounds)
    rd.point = J.separating_point(best.fit, ru.fit, data)
    say(f"round {rd.index}: runner-up {ru.fit.label} (held-out gap {ru.fit.gap:.3f} K vs {best.fit.gap:.3f} K, "
        f"difference {cmp.gap_b - cmp.gap_a:.3f} ± {cmp.se_diff:.3f} K)" +
        ("; cannot be separated on this run" if cmp.ambiguous else "") +
        (f"; decided by held-out data at {cmp.decided_by}" if cmp.decided_by else ""))
    return best


def _explains(r: Ranked, opt: Options) -> bool:
    """A candidate removes enough of the gap to be an explanation at all."""
    return bool(r.improvement >= opt.min_improvement or r.improvement_above_noise >= opt.min_share_above_noise)


def _polish(fit: F.Fit, names: Sequence[str], data: F.Data, opt: Options, prior: dict[str, float]) -> F.Fit:
    out = F.Fit(fit.label, fit.raw, fit.model, fit.theta, tuple(names), fit.effect_params, fit.edits)
    try:
        out.theta = F.refit(fit.model, fit.theta, names, data, max_iter=opt.fit_iter, prior=prior,
                            prior_weight=opt.prior_weight)
    except (ValueError, np.linalg.LinAlgError):
        return fit
    out.train_mse, out.heldout_mse, out.traj_T = F.heldout(fit.model, out.theta, data)
    idx = {p.name: i for i, p in enumerate(fit.model.parameters)}
    for n in fit.effect_params:
        spec = out.raw["parameters"][n]
        spec["value"] = float(f"{float(out.theta[idx[n]]):.6g}")
        spec["min"] = min(spec["min"], spec["value"])
        spec["max"] = max(spec["max"], spec["value"])
    return out


def noise_floor(run: Run, sensors: Sequence[str], split: int) -> float:
    """Sensor noise estimate (K, RMS over the sensors) from the robust spread of first differences."""
    v = []
    for s in sensors:
        d = np.diff(run.columns[s][split:])
        d = d[np.isfinite(d)]
        if len(d) > 10:
            mad = float(np.median(np.abs(d - np.median(d))))
            sd = mad / 0.6745 if mad > 0 else float(np.std(d))
            v.append((sd / math.sqrt(2.0)) ** 2)
    return float(math.sqrt(np.mean(v))) if v else 0.0


def write_model(disc: Discovery, out: str | os.PathLike[str], model_path: str | os.PathLike[str] | None) -> str:
    """Write the augmented model: the original file with the effect lines patched in, one
    effect after the other (each changed line names its effect)."""
    import copy
    import re

    out = Path(out)
    docs = [copy.deepcopy(disc.raw0)] + [copy.deepcopy(r.fit.raw) for r in disc.added]
    labels = [r.fit.label for r in disc.added]
    text = Path(model_path).read_text(encoding="utf-8") if model_path else None
    if "data_dir" in docs[0] and model_path is not None:
        orig = (Path(model_path).resolve().parent / str(docs[0]["data_dir"])).resolve()
        rel = os.path.relpath(orig, out.resolve().parent)
        if rel != docs[0]["data_dir"]:
            for d in docs:
                d["data_dir"] = rel
            if text is not None:
                text = re.sub(r"(?m)^data_dir:.*$", f"data_dir: {rel}   # relative to this file", text, count=1)
    label = " + ".join(labels) or "no effect"
    header = (f"{out.name}: {disc.model_name} + {label}, written by thermal-edge discover\n"
              f"from the run {disc.source}; held-out gap {disc.gap_before:.3f} K -> {disc.gap_after:.3f} K.\n"
              f"Lines marked '# <effect>' were added or changed; everything else is the original file.\n"
              f"The effect's parameters hold their fitted values; the adaptable parameters keep their\n"
              f"nominal values (the refitted ones are in the discovery report).")
    body = None
    if text is not None:
        try:
            t = text
            for old, new, lab in zip(docs, docs[1:], labels):
                t = yamlpatch.patch_text(t, old, new, lab)
            body = "".join(f"# {ln}\n" for ln in header.splitlines()) + t
        except (yamlpatch.PatchError, IndexError, KeyError):
            body = None
    if body is None:
        body = yamlpatch.render(None, docs[0], docs[-1], label, header)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(body, encoding="utf-8")
    return str(out)
