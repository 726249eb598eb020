"""``bench magnet``: the magnet temperature from the inverter's voltages on the real Paderborn
machine (``run_a.csv``), the flux-linkage model commissioned on the first part of the run only
and scored on the rest, side by side with the published 4-node LPTN (open loop, and its observer
from the stator sensors) and their fusion.

The stator targets are scored on the estimate; the two the observer reads also on its prediction
before each reading. The estimate after a reading is partly that reading: the better the
prediction, the less the filter copies its sensor, so the estimate's mean square distance from the
sensor it has just read can grow while its prediction improves (for a Kalman filter with prior
variance ``P`` and sensor noise variance ``r``, both K²: ``r² / (P + r)``, rising as ``P`` falls).
The prediction is the score that a better model lowers.

The run is two operating points at 5,500 rpm: about 70 min at 64 Nm (|i| ≈ 200–215 A, deep field
weakening), then zero torque (|i| ≈ 95–108 A). A commissioning part cut from the first hour only
ever sees the loaded point, so the flux estimate is informative on the loaded rest and flagged
uninformative in the cool-down (the current is outside what commissioning saw): there the fused
estimate is the observer's. The second fusion uses the cool-down's estimate for its changes only
(:class:`~thermal_edge.estimation.fusion.FluxObserver`, anchored at the load step where the magnet
cannot jump): its figures stand beside the first's.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..data import Run, read_run
from ..estimation.flux import PARAMS, Electrical, FluxModel, fit_flux_model
from ..estimation.fusion import FusedRun, run_fused
from ..estimation.online import band_coverage
from ..estimation.predict import open_loop
from ..lptn import Model, load_model
from ..shipped import config_path
from .common import Progress, no_progress, paderborn_dir

SENSORS = ("stator_winding", "stator_yoke")
#: pole pairs of the Paderborn machine (a wrong value scales ψ and L together: same temperatures)
POLE_PAIRS = 4
#: commissioning parts, minutes from the start
FIT_MINUTES = (20.0, 30.0, 60.0)
#: priors of the commissioning fit for this machine: a copper resistance of a 50 kW machine's
#: order, and ψ from the back-EMF the run shows at its start (u_q/ω_el at 1,266 rpm, i ≈ 0: 0.117 Wb)
PRIORS = {"r20": (0.015, 0.005), "psi20": (0.1, 0.03)}
#: a deliberately wrong calibration: the inductances 20 % off, the voltage error doubled
WRONG = {"ld0": 1.2, "ld1": 1.2, "lq0": 1.2, "lq1": 1.2, "v_err": 2.0}
#: the published LPTN's magnet MSE on run_a, open loop, K² (the paper's figure)
PUBLISHED_LPTN_MSE = 4.05


def _head(e: Electrical, n: int) -> Electrical:
    return Electrical(e.u_d[:n], e.u_q[:n], e.i_d[:n], e.i_q[:n], e.speed_rpm[:n], e.winding_c[:n])


@dataclass
class MagnetResult:
    """The bench's figures: per commissioning length (minutes, as text) the figures of
    :func:`run`; ``skipped`` says why nothing ran (no data)."""

    run: str = ""
    pole_pairs: int = 0
    priors: dict[str, Any] = field(default_factory=dict)
    parts: dict[str, dict[str, Any]] = field(default_factory=dict)
    published_lptn_mse: float = float("nan")
    skipped: str | None = None


def run(data_dir: Path | None = None, fit_minutes: tuple[float, ...] = FIT_MINUTES,
        progress: Progress = no_progress) -> MagnetResult:
    """Every figure per commissioning length; ``skipped`` set when the data is absent."""
    data_dir = paderborn_dir(data_dir)
    path = data_dir / "run_a.csv"
    if not path.exists():
        return MagnetResult(skipped=f"{path} not found")
    model = load_model(config_path("machines", "paderborn4.yaml"), data_dir=data_dir)
    run_ = read_run(path, "paderborn")
    e = Electrical.of(run_.columns)
    tm = run_.columns["pm"]
    node = model.sensors["pm"]
    i = model.node_index(node)
    traj, _ = open_loop(model, run_)
    progress("observer", 0, 1 + len(fit_minutes), "run")
    base = run_fused(model, run_, SENSORS, None, node)
    parts: dict[str, dict[str, Any]] = {}
    for k, minutes in enumerate(fit_minutes):
        progress("fused", k + 1, 1 + len(fit_minutes), "run")
        n = int(round(minutes * 60.0 / run_.dt))
        fm = fit_flux_model(_head(e, n), tm[:n], POLE_PAIRS, run_.dt, priors=PRIORS)
        fu = run_fused(model, run_, SENSORS, fm, node, electrical=e, flux_from=n)
        fx = run_fused(model, run_, SENSORS, fm, node, electrical=e, flux_from=n, extrapolate=True)
        rest = np.arange(len(run_)) >= n
        ok = rest & np.isfinite(fu.flux_sigma)
        y = tm[rest]
        parts[f"{minutes:g}"] = {
            "fit_samples": n, "scored_samples": int(rest.sum()),
            "params": fm.params, "param_sigma": fm.sigma, "tempco_pct_per_k": 100.0 * fm.tempco_per_k,
            "sigma_table_k": fm.sigma_table(float(np.median(np.abs(e.speed_rpm[:n])))),
            "speed_min_rpm": fm.speed_min_rpm, "tau_s": fm.tau_s,
            "informative_share": float(ok.sum() / rest.sum()),
            "flux_rms_k": float(np.sqrt(np.mean((fu.flux_c[ok] - tm[ok]) ** 2))) if ok.any() else float("nan"),
            "flux_coverage": band_coverage(fu.flux_c[ok], fu.flux_sigma[ok], tm[ok]) if ok.any() else float("nan"),
            "open_loop_mse": mse_of(traj.node(node), tm, rest),
            "observer_mse": mse_of(base.estimate[:, i], tm, rest),
            "fused_mse": mse_of(fu.estimate[:, i], tm, rest),
            "observer_coverage": band_coverage(base.estimate[rest, i], base.sigma[rest, i], y),
            "fused_coverage": band_coverage(fu.estimate[rest, i], fu.sigma[rest, i], y),
            "observer_mse_informative": float(np.mean((base.estimate[ok, i] - tm[ok]) ** 2)) if ok.any() else float("nan"),
            "fused_mse_informative": float(np.mean((fu.estimate[ok, i] - tm[ok]) ** 2)) if ok.any() else float("nan"),
            "used": int(fu.used.sum()), "refused": fu.refused,
            "extrapolated": {"fused_mse": mse_of(fx.estimate[:, i], tm, rest),
                             "fused_coverage": band_coverage(fx.estimate[rest, i], fx.sigma[rest, i], y),
                             "used": int(fx.used.sum()), "refused": fx.refused,
                             "relative": int(fx.relative.sum()) if fx.relative is not None else 0,
                             "stator_mse": {s: mse_of(fx.estimate[:, model.node_index(model.sensors[s])], run_.columns[s],
                                                      rest)
                                            for s in ("stator_winding", "stator_yoke", "stator_tooth")
                                            if s in run_.columns},
                             # the sensors the observer reads, by its prediction before each reading
                             "stator_prediction_mse": {
                                 s: {"observer": mse_of(_prediction(base)[:, model.node_index(model.sensors[s])],
                                                        run_.columns[s], rest),
                                     "fused": mse_of(_prediction(fx)[:, model.node_index(model.sensors[s])],
                                                     run_.columns[s], rest)}
                                 for s in SENSORS}},
            "wrong": wrong_calibration(model, run_, fm, node, e, n, rest),
            "stator_mse": {s: {"observer": mse_of(base.estimate[:, model.node_index(model.sensors[s])], run_.columns[s], rest),
                               "fused": mse_of(fu.estimate[:, model.node_index(model.sensors[s])], run_.columns[s], rest)}
                           for s in ("stator_winding", "stator_yoke", "stator_tooth") if s in run_.columns},
        }
    progress("fused", 1 + len(fit_minutes), 1 + len(fit_minutes), "run")
    return MagnetResult(str(path), POLE_PAIRS, dict(PRIORS), parts, PUBLISHED_LPTN_MSE)


def wrong_calibration(model: Model, run_: Run, fm: FluxModel, node: str, e: Electrical, n: int,
                      rest: np.ndarray) -> dict[str, float]:
    """The fused run with :data:`WRONG` applied to the commissioned model: how often the
    disagreement check refuses, and the magnet's MSE and band coverage on the rest."""
    bad = replace(fm, params={k: v * WRONG.get(k, 1.0) for k, v in fm.params.items()},
                  cv_params=[[v * WRONG.get(k, 1.0) for k, v in zip(PARAMS, row)] for row in fm.cv_params])
    fu = run_fused(model, run_, SENSORS, bad, node, electrical=e, flux_from=n)
    fx = run_fused(model, run_, SENSORS, bad, node, electrical=e, flux_from=n, extrapolate=True)
    i = model.node_index(node)
    tm = run_.columns["pm"]
    return {"used": int(fu.used.sum()), "refused": fu.refused, "fused_mse": mse_of(fu.estimate[:, i], tm, rest),
            "fused_coverage": band_coverage(fu.estimate[rest, i], fu.sigma[rest, i], tm[rest]),
            "flux_rms_k": float(np.sqrt(np.mean((fu.flux_c[rest] - tm[rest]) ** 2))),
            "extrapolated_used": int(fx.used.sum()), "extrapolated_fused_mse": mse_of(fx.estimate[:, i], tm, rest)}


def _prediction(fr: FusedRun) -> np.ndarray:
    assert fr.prediction is not None  # run_fused always records it
    return fr.prediction


def mse_of(x: np.ndarray, y: np.ndarray, mask: np.ndarray) -> float:
    """Mean square error of ``x`` against ``y`` over ``mask`` (NaN readings skipped), K²."""
    ok = mask & np.isfinite(y)
    return float(np.mean((x[ok] - y[ok]) ** 2))

