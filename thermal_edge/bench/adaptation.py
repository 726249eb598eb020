"""``thermal-edge bench adaptation``: the service's online adaptation in closed loop on the
simulated machine, scenario by scenario.

Each scenario runs the service's own :class:`~thermal_edge.service.engine.ThermalEngine`
(``config/edge.yaml``, frame clock, adapter worker in the tick) against the inverter emulator's
plant, which obeys the limits the engine sends (the closed loop of :mod:`.protection`, stepped
directly: faster than real time by the model's speed). The plant is the service's model file
with its nominal parameters; the service's model starts where the scenario says.

Scenarios:

* ``demo``: what ``thermal-edge demo`` runs: the model off by the paper's Table 4, the overload
  cycle, derating active for long stretches;
* ``quasi_steady``: Table 4 start, 20 min at the rated point, then a demand above what the machine
  can carry: the limits hold it at a derated, quasi-steady point near the hot spot's limit;
* ``cold_light``: Table 4 start, a cold machine at 600 rpm / 70 Nm for 3 h (the paper's E1 duty):
  it never comes near a limit;
* ``varied``: Table 4 start, the varied drive cycle of ``bench paper`` E2 (closed loop: the limits
  never bind on it);
* ``at_plant``: the model starts at the plant's own parameters on the overload cycle: nothing to
  learn, so nothing may be promoted.

Figures per scenario: the open-loop prediction error (``TE_PredErrRms``: the RMS over the last
adaptation period of the prediction the engine runs open loop beside the observer, never
corrected by the readings) over time and at the end; every promotion, with the open-loop error of
the next hour predicted from the observer's state at the promotion with the parameters before and
after it; the refusals counted by their reason; the final parameters against the plant's, with
how closely the scenario's data pins each down (relative 1σ from the Fisher information at the
plant's parameters, the residuals' correlation in time counted: the *marginal* 1σ, every other
adaptable parameter free, from the full covariance; beside it, for contrast, the *conditional*
1σ with the others held at their values, which no estimator that has to find them too can
reach); the time from which the open-loop error stays within 1 K.
"""
from __future__ import annotations

import math
import re
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..shipped import config_path
from .protection import PLANT_DT_S, T0, Case, ThermalEdgePolicy, closed_loop, edge_config, emulator_for

__all__ = ["SCENARIOS", "AdaptationBench", "Promotion", "Scenario", "ScenarioResult", "run", "run_scenario"]

#: a parameter counts as identifiable in a scenario when its data pins it down to this relative 1σ
#: (marginal: every other adaptable parameter free)
IDENTIFIABLE_REL_STD = 0.02
#: how far the final identifiable parameters may be from the plant's (relative)
PARAM_TOLERANCE = 0.10
#: the open-loop error a learned model must reach (K)
WITHIN_K = 1.0
#: the horizon over which a promotion must not make the prediction worse, s
NEXT_S = 3600.0
#: the open-loop error is sampled this often, s
SAMPLE_S = 60.0


@dataclass(frozen=True)
class Scenario:
    """A closed-loop scenario: the cycle, where the service's model starts, how long."""

    name: str
    cycle: str  # a shipped cycle's file name, or "quasi_steady" (built here)
    table4: bool = True  # the service's model starts off by Table 4; False: at the plant's parameters
    duration_s: float = 10800.0
    doc: str = ""


SCENARIOS: dict[str, Scenario] = {s.name: s for s in (
    Scenario("demo", "overload.yaml", doc="Table 4 start, overload cycle, derating active (the demo)"),
    Scenario("quasi_steady", "quasi_steady", doc="Table 4 start, held at a derated point near the limit"),
    Scenario("cold_light", "paper_600rpm_70nm.yaml", doc="Table 4 start, cold, 600 rpm / 70 Nm: never near a limit"),
    Scenario("varied", "varied_drive.yaml", doc="Table 4 start, the varied drive cycle (E2)"),
    Scenario("at_plant", "overload.yaml", table4=False, doc="model at the plant's parameters: nothing to learn"),
)}


@dataclass
class Promotion:
    """A promoted challenger and what it did to the next hour's open-loop prediction (RMS, K,
    seen sensors, from the observer's state at the promotion)."""

    t_s: float
    next_before_k: float
    next_after_k: float
    next_span_s: float

    @property
    def harmed(self) -> bool:
        return self.next_after_k > self.next_before_k


@dataclass
class ScenarioResult:
    """Every figure of one scenario (times in s from the start, errors in K)."""

    name: str
    doc: str
    learn: bool  # the plant differs from the model's start
    pred_err_k: list[tuple[float, float]]  # (t, TE_PredErrRms) every SAMPLE_S
    final_pred_err_k: float
    within_1k_from_s: float  # from when the open-loop error stays <= WITHIN_K (NaN: it does not at the end)
    promotions: list[Promotion]
    decisions: int
    outcomes: dict[str, int]  # decisions by kind of reason
    refusals: list[tuple[float, str]]  # (t, reason) of every challenger dropped
    final: dict[str, float]
    plant: dict[str, float]
    start: dict[str, float]
    rel_std: dict[str, float]  # what the scenario's data allows (marginal 1σ, relative) at the plant's parameters
    rel_std_fixed: dict[str, float]  # the same with every other parameter held (conditional 1σ, relative)
    peak_hot_spot_c: float
    derated_s: float  # plant time with the limits reduced (derating active)
    wall_s: float

    @property
    def identifiable(self) -> list[str]:
        return [k for k, v in self.rel_std.items() if v <= IDENTIFIABLE_REL_STD]

    @property
    def param_errors_pct(self) -> dict[str, float]:
        return {k: 100.0 * (v / self.plant[k] - 1.0) for k, v in self.final.items()}

    @property
    def passed(self) -> bool:
        """Learned where there was something to learn; nothing promoted where there was not."""
        if not self.learn:
            return not self.promotions
        close = all(abs(self.param_errors_pct[k]) <= 100 * PARAM_TOLERANCE for k in self.identifiable)
        return self.final_pred_err_k <= WITHIN_K and close and not any(p.harmed for p in self.promotions)


@dataclass
class AdaptationBench:
    """All scenarios."""

    scenarios: dict[str, ScenarioResult] = field(default_factory=dict)
    wall_s: float = 0.0

    @property
    def passed(self) -> bool:
        return all(r.passed for r in self.scenarios.values())


def _cycle_file(scenario: Scenario, tmp: Path) -> Path:
    if scenario.cycle != "quasi_steady":
        return config_path("cycles", scenario.cycle)
    import yaml

    from ..lptn import DEFAULT_COLUMNS, Role

    col = DEFAULT_COLUMNS
    path = tmp / "quasi_steady.yaml"
    path.write_text(yaml.safe_dump({"name": "quasi_steady", "dt_s": 1.0, col[Role.AMBIENT]: 25.0, "segments": [
        {"duration_s": 1200.0, col[Role.SPEED]: 900.0, col[Role.TORQUE]: 106.0},
        {"duration_s": scenario.duration_s, col[Role.SPEED]: 900.0, col[Role.TORQUE]: 160.0, "ramp_s": 10.0}]}))
    return path


def _outcome(reason: str) -> str:
    """A decision's reason -> its kind (the first clause, numbers and sensors left out)."""
    head = reason.split(";")[0].strip()
    head = re.sub(r" on the .*", "", head)
    return head or "none"


class _Recorder:
    """The samples the engine hands its adapter (time, inputs, readings, observer state)."""

    def __init__(self, record: Callable[..., None]) -> None:
        self.inner = record
        self.t: list[float] = []
        self.u: list[dict[str, float]] = []
        self.y: list[dict[str, float]] = []
        self.x: list[np.ndarray] = []

    def __call__(self, t: float, inputs: dict[str, float], measured: Mapping[str, float], state: np.ndarray) -> None:
        self.t.append(float(t))
        self.u.append(dict(inputs))
        self.y.append(dict(measured))
        self.x.append(np.array(state, dtype=float))
        self.inner(t, inputs, measured, state)


def _open_loop_rms(sim: Any, model: Any, theta: np.ndarray, rec: _Recorder, k0: int, k1: int, sensors: list[str],
                   scored_from: int | None = None) -> float:
    """RMS error (K, ``sensors``) of the open loop from the recorded state at sample ``k0`` over
    the samples up to ``k1`` (excluded), scored after ``scored_from`` (default ``k0``)."""
    inputs = {c: np.array([rec.u[k][c] for k in range(k0, k1)]) for c in model.inputs}
    traj = sim.simulate(theta, inputs, rec.t[1] - rec.t[0], rec.x[k0])
    skip = 1 + max((scored_from if scored_from is not None else k0) - k0, 0)
    err = []
    for s in sensors:
        row = model.node_index(model.sensors[s])
        y = np.array([rec.y[k].get(s, math.nan) for k in range(k0, k1)])
        e = traj.T[skip:, row] - y[skip:] if len(y) > skip else np.zeros(0)
        err.append(e[np.isfinite(e)])
    e = np.concatenate(err) if err else np.zeros(0)
    return float(np.sqrt(np.mean(e**2))) if len(e) else math.nan


def _rel_std(model: Any, rec: _Recorder, sensors: list[str], decimate_by: int,
             max_rel_std: float) -> tuple[dict[str, float], dict[str, float]]:
    """Relative 1σ of each adaptable parameter that the recorded data allows at the plant's
    parameters: marginal (all the others free: the diagonal of the covariance) and conditional
    (the others held: one over the diagonal of the information)."""
    from ..estimation.common import ParamSpace, decimate, window_from_arrays
    from ..estimation.objective import Objective
    from ..estimation.uncertainty import estimate_uncertainty
    from ..lptn import Simulator

    inputs = {c: np.array([u[c] for u in rec.u]) for c in model.inputs}
    meas = {s: np.array([y.get(s, math.nan) for y in rec.y]) for s in sensors}
    win = decimate(window_from_arrays(model, inputs, meas, rec.x[0], rec.t[1] - rec.t[0], np.array(rec.t)), decimate_by)
    names = tuple(model.adaptable)
    obj = Objective(Simulator(model), ParamSpace(model, names, model.nominal()), win, sensors)
    ev = obj.evaluate(np.log(obj.space.values()))
    unc = estimate_uncertainty(obj, ev, max_rel_std)
    info = np.linalg.pinv(unc.cov, rcond=1e-15)
    fixed = 1.0 / np.sqrt(np.clip(np.diag(info), 1e-300, None))
    return ({n: float(r) for n, r in zip(unc.names, unc.rel_std)}, {n: float(r) for n, r in zip(unc.names, fixed)})


def run_scenario(scenario: Scenario, config_file: Path | None = None,
                 progress: Callable[[float, float], object] | None = None) -> ScenarioResult:
    """One scenario, closed loop (see the module docstring); ``progress(done_s, total_s)`` every
    simulated minute."""
    from ..lptn import Simulator
    from ..service.engine import load_service_model
    from ..sim.inverter import table4_parameters

    w0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="te-bench-adaptation-") as tmp:
        cfg = edge_config(Path(tmp), config_file)
        plant = load_service_model(cfg)
        start_values = table4_parameters(plant) if scenario.table4 else {}
        if start_values:
            cfg = replace(cfg, model=replace(cfg.model, parameters={**cfg.model.parameters, **start_values}))
        kt = float(cfg.kt(plant))
        emu = emulator_for(plant, _cycle_file(scenario, Path(tmp)), Case(scenario.name), scenario.duration_s)
        pol = ThermalEdgePolicy(emu, cfg.derating.max_current_a, cfg.derating.max_torque_nm, cfg)
        eng = pol.engine
        rec = _Recorder(eng.adaptation.record)
        eng.adaptation.record = rec  # type: ignore[method-assign]  # the bench sees what the adapter sees
        hs = next(lim for lim in plant.limits if lim.name == cfg.transmit.hot_spot_limit)
        hs_row = plant.node_index(hs.node)
        samples: list[tuple[float, float]] = []
        peak = [-math.inf]
        derated = [0.0]
        next_sample = [SAMPLE_S]

        def observe(emu_: Any, pol_: Any) -> None:
            peak[0] = max(peak[0], float(emu_.plant.T[hs_row]))
            out = pol_.last_out
            if out is None:
                return
            if out.limits.active:
                derated[0] += PLANT_DT_S
            el = out.t - T0
            if el + 1e-9 >= next_sample[0]:
                samples.append((el, float(out.pred_err_rms)))
                next_sample[0] += SAMPLE_S
                if progress is not None:
                    progress(el, scenario.duration_s)

        try:
            closed_loop(emu, pol, kt, [], observe=observe)
            out = pol.last_out
            final_err = float(out.pred_err_rms) if out is not None else math.nan
            decisions = eng.adaptation.decisions
            final = eng.adaptation.values()
        finally:
            pol.close()
        model0 = load_service_model(cfg)  # the service's starting model
        names = list(final)
        nominal = dict(zip(plant.parameter_names, plant.nominal()))
        start = dict(zip(model0.parameter_names, model0.nominal()))
        sensors = list(cfg.adaptation.adapter.sensors or [s for s in plant.sensors if s in cfg.sensors])
        # promotions: the next hour with the parameters before and after, from the observer's state then
        sim = Simulator(model0)
        theta = model0.nominal()
        idx = {n: i for i, n in enumerate(model0.parameter_names)}
        t_arr = np.array(rec.t)
        applied = cfg.adaptation.apply_delay_ticks  # ticks from a decision's request to its result in use
        tick_s = float(t_arr[1] - t_arr[0]) if len(t_arr) > 1 else 1.0
        promotions: list[Promotion] = []
        refusals: list[tuple[float, str]] = []
        outcomes: dict[str, int] = {}
        for d in decisions:
            kind = _outcome(str(d.get("reason", "")))
            outcomes[kind] = outcomes.get(kind, 0) + 1
            if "dropped" in str(d.get("reason", "")):
                refusals.append((float(d["t"]) - T0, str(d["reason"]).split(";")[0]))
            if not d.get("accepted"):
                continue
            after = theta.copy()
            for k, v in (d.get("params") or {}).items():
                after[idx[k]] = float(v)
            # before: from the observer's state at the decision; after: from the state the service
            # continued from once the promotion was applied (the promoted parameters' own estimate)
            k0 = int(np.searchsorted(t_arr, float(d["t"])))
            ka = int(np.searchsorted(t_arr, float(d["t"]) + (applied + 1) * tick_s))
            k1 = int(np.searchsorted(t_arr, float(d["t"]) + NEXT_S))
            if k1 - ka > 1:
                promotions.append(Promotion(float(d["t"]) - T0, _open_loop_rms(sim, model0, theta, rec, k0, k1, sensors, ka),
                                            _open_loop_rms(sim, model0, after, rec, ka, k1, sensors), t_arr[k1 - 1] - t_arr[ka]))
            else:
                promotions.append(Promotion(float(d["t"]) - T0, math.nan, math.nan, 0.0))
            theta = after
        ad = cfg.adaptation.adapter
        rel, rel_fixed = _rel_std(plant, rec, sensors, ad.decimate, ad.max_rel_std)
    within = math.nan
    if samples and samples[-1][1] <= WITHIN_K:
        within = 0.0
        for t_s, e in samples:
            if not e <= WITHIN_K:
                within = t_s + SAMPLE_S
    return ScenarioResult(
        name=scenario.name, doc=scenario.doc, learn=bool(start_values), pred_err_k=samples, final_pred_err_k=final_err,
        within_1k_from_s=within, promotions=promotions, decisions=len(decisions), outcomes=outcomes, refusals=refusals,
        final=final, plant={n: float(nominal[n]) for n in names}, start={n: float(start[n]) for n in names},
        rel_std={n: rel[n] for n in names if n in rel}, rel_std_fixed={n: rel_fixed[n] for n in names if n in rel_fixed},
        peak_hot_spot_c=peak[0], derated_s=derated[0],
        wall_s=time.perf_counter() - w0,
    )


def run(scenarios: list[Scenario] | None = None, config_file: Path | None = None,
        progress: Callable[[str, float, float], object] | None = None) -> AdaptationBench:
    """Every scenario (default all of :data:`SCENARIOS`), one after the other;
    ``progress(scenario, done_s, total_s)``."""
    w0 = time.perf_counter()
    res = AdaptationBench()
    for sc in scenarios if scenarios is not None else list(SCENARIOS.values()):
        cb = (lambda done, total, name=sc.name: progress(name, done, total)) if progress is not None else None
        res.scenarios[sc.name] = run_scenario(sc, config_file, cb)
    res.wall_s = time.perf_counter() - w0
    return res


def summary_rows(res: AdaptationBench) -> list[list[object]]:
    """One row per scenario: the final open-loop error, promotions, refusals, parameters, verdict."""
    rows: list[list[object]] = []
    for r in res.scenarios.values():
        ident = r.identifiable
        worst = max((abs(r.param_errors_pct[k]) for k in ident), default=math.nan)
        harmed = sum(p.harmed for p in r.promotions)
        rows.append([r.name, round(r.final_pred_err_k, 2), hms(r.within_1k_from_s), len(r.promotions), harmed,
                     sum(1 for _ in r.refusals), len(ident), round(worst, 1), round(r.peak_hot_spot_c, 1), hms(r.derated_s),
                     round(r.wall_s), "yes" if r.passed else "NO"])
    return rows


SUMMARY_HEADERS = ["scenario", "final err K", "within 1 K from", "promoted", "next hour worse", "dropped",
                   "identifiable", "worst of them %", "peak hot spot °C", "derated for", "wall s", "pass"]


def hms(t: float) -> str:
    if not math.isfinite(t):
        return "never"
    return f"{int(t // 3600)}:{int(t % 3600 // 60):02d}"


def error_rows(res: AdaptationBench, every_s: float = 900.0) -> tuple[list[str], list[list[object]]]:
    """The open-loop error over time: one row every ``every_s``, one column per scenario."""
    names = list(res.scenarios)
    series = {n: dict(res.scenarios[n].pred_err_k) for n in names}
    ends = [max(s) for s in series.values() if s]
    if not ends:
        return ["t"] + names, []
    rows = []
    t = every_s
    while t <= max(ends) + 1e-9:
        row: list[object] = [hms(t)]
        for n in names:
            s = series[n]
            key = min(s, key=lambda k: abs(k - t)) if s else None
            row.append(round(s[key], 2) if key is not None and abs(key - t) < SAMPLE_S else "")
        rows.append(row)
        t += every_s
    return ["t"] + names, rows


def parameter_rows(r: ScenarioResult) -> list[list[object]]:
    """Start, final and plant value of each adaptable parameter, and what the data allows."""
    return [[k, r.start[k], r.final[k], r.plant[k], round(r.param_errors_pct[k], 1), round(100 * r.rel_std.get(k, math.nan), 2),
             round(100 * r.rel_std_fixed.get(k, math.nan), 3), "yes" if k in r.identifiable else "no"] for k in r.final]


PARAMETER_HEADERS = ["parameter", "start", "final", "plant", "final vs plant %", "1σ the data allows %",
                     "1σ if the others were known %", "identifiable"]


def promotion_rows(r: ScenarioResult) -> list[list[object]]:
    return [[hms(p.t_s), round(p.next_before_k, 3), round(p.next_after_k, 3), round(p.next_span_s),
             "WORSE" if p.harmed else "better"] for p in r.promotions]


PROMOTION_HEADERS = ["promoted at", "next hour before K", "after K", "span s", "next hour"]
