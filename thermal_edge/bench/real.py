"""``bench real``: online adaptation on the real Paderborn machine (``run_a.csv``), judged on
every target, from the published parameters and from wrong starts.

The adapter learns from ``stator_winding`` and ``stator_yoke`` only (the production sensors);
``pm`` and ``stator_tooth`` are scored though never seen. Each start is a model file whose
parameters are wrong (the wrong values are also the adapter's prior, as a user's model would
be): stator-side parameters off by 30–60 %, one at a time and together, and one start in which
a parameter the sensors cannot identify (the magnet capacity) is wrong. Per start and target:
the online trace, the same with the starting parameters fixed, the observer, and its 95 % band
coverage; the joint EKF from the same start (its final parameters judged open loop over the run,
as the paper's Fig. 12 compares them), the median adaptation step time, and how closely the
whole run pins down each final parameter (its relative σ, the residuals' correlation in time
counted: :mod:`thermal_edge.estimation.uncertainty`).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..data import Run, read_run
from ..estimation.adapter import AdapterConfig
from ..estimation.ekf import run_ekf
from ..estimation.online import online_report
from ..estimation.predict import initial_from_run, model_inputs, open_loop
from ..lptn import Model, load_model
from ..shipped import config_path
from .common import Progress, no_progress, paderborn_dir, sample_counter

SENSORS = ("stator_winding", "stator_yoke")
#: starts: parameter -> factor on the published value
STARTS: dict[str, dict[str, float]] = {
    "published": {},
    "R_c_sy_x1.5": {"R_c_sy": 1.5},
    "C_sw_x0.6": {"C_sw": 0.6},
    "R_sy_sw_x1.6": {"R_sy_sw": 1.6},
    "R_c_sy_x0.6": {"R_c_sy": 0.6},
    "R_sy_sw_x0.7": {"R_sy_sw": 0.7},
    "C_sy_x1.4": {"C_sy": 1.4},
    "stator_together": {"R_c_sy": 1.5, "C_sw": 0.71, "R_sy_sw": 0.7, "C_sy": 1.4},
    "unidentifiable_C_pm_x1.5": {"C_pm": 1.5},
}


def adapter_config() -> AdapterConfig:
    """The adapter as the bench runs it: 2.5 s rows, 8 per optimiser step (20 s)."""
    return AdapterConfig(sensors=SENSORS, decimate=8)


def one_start(base: Model, run: Run, factors: Mapping[str, float], sets: Mapping[str, float],
              progress: Callable[[int], object] | None = None) -> dict[str, object]:
    """Every figure of one start (see the module docstring); ``progress`` as
    :func:`~thermal_edge.estimation.online.online_report`'s (twice the run's samples)."""
    nominal = dict(zip(base.parameter_names, base.nominal()))
    model = base.with_parameters({k: nominal[k] * f for k, f in factors.items()})
    rep = online_report(model, run, adapter_config(), progress=progress)
    out: dict[str, object] = {"factors": dict(factors)}
    ek = run_ekf(model, model_inputs(model, run), {s: run.columns[s] for s in SENSORS}, run.dt,
                 initial_from_run(model, run), update_s=60.0)
    _, ek_scores = open_loop(model, run, theta=ek.theta)
    for s, v in rep["targets"].items():
        i = model.node_index(model.sensors[s])
        y = run.columns[s]
        ok = np.isfinite(y)
        out[s] = {**v, "ekf_open_loop_mse": ek_scores.mse[s], "ekf_filtered_mse": float(np.mean((ek.T[ok, i] - y[ok]) ** 2))}
    final = rep["final_params"]
    out["final_params"] = final
    reference = {**nominal, **sets}
    out["final_vs_published_pct"] = {k: 100.0 * (v / reference[k] - 1.0) for k, v in final.items()}
    # how closely the whole run pins each final value down, its residuals' correlation counted:
    # a parameter is identifiable to within 10 % only where this is well under 10 %
    unc = rep["result"].adapter.current_uncertainty()
    out["final_rel_std_pct"] = {n: 100.0 * float(r) for n, r in zip(unc.names, unc.rel_std)}
    out["autocorrelation_samples"] = unc.tau
    out["ekf_params_vs_published_pct"] = {k: 100.0 * (float(ek.theta[model.parameter_index([k])[0]]) / reference[k] - 1.0)
                                          for k in ek.names}
    out["mean"] = rep["mean"]
    ds = rep["decisions"]
    out["decisions"] = len(ds)
    out["promoted"] = sum(1 for d in ds if d.accepted)
    out["adapt_step_median_s"] = rep["adapt_step_median_s"]
    out["ekf_wall_s"] = ek.wall_s
    return out


@dataclass
class RealResult:
    """``bench real``: each start's figures by name (:func:`one_start`), or why it was skipped."""

    run: str = ""  #: the run file
    adapted_from: list[str] = field(default_factory=list)  #: the sensors the adapter learns from
    starts: dict[str, dict[str, Any]] = field(default_factory=dict)
    skipped: str | None = None  #: why nothing ran (the data are absent)


def run(data_dir: Path | None = None, starts: Mapping[str, Mapping[str, float]] | None = None,
        sets: Mapping[str, float] | None = None, progress: Progress = no_progress) -> RealResult:
    """All starts; :attr:`RealResult.skipped` says why when the data is absent. ``sets`` overrides parameters of
    the published model first (``--set``; the command names a bad one, here an unknown name or a
    value outside its bounds raises :class:`~thermal_edge.lptn.ParameterError`). ``progress``
    counts the samples replayed, one stage per start. ``data_dir``: the Paderborn data (default
    :func:`~.common.paderborn_dir`)."""
    data_dir = paderborn_dir(data_dir)
    path = data_dir / "run_a.csv"
    if not path.exists():
        return RealResult(skipped=f"{path} not found")
    base = load_model(config_path("machines", "paderborn4.yaml"), data_dir=data_dir)
    sets = dict(sets or {})
    if sets:  # with_parameters refuses an unknown name or a value outside the bounds
        base = base.with_parameters(sets)
    run_ = read_run(path, "paderborn")
    chosen = starts or STARTS
    res = {name: one_start(base, run_, f, sets,
                           sample_counter(progress, f"start {k + 1} of {len(chosen)} ({name})", 2 * len(run_)))
           for k, (name, f) in enumerate(chosen.items())}
    return RealResult(str(path), list(SENSORS), res)
