"""The observer over a recorded run with the magnet temperature from the inverter's voltages as a
measurement of the magnet node (:meth:`~thermal_edge.estimation.observer.Observer.update_node`).

The flux estimate's errors are correlated over minutes (an operating point's bias does not average
out from one sample to the next), so each sample's variance is inflated by the number of samples in
the estimate's correlation time (:attr:`~thermal_edge.estimation.flux.FluxModel.tau_s`): a minute of
samples carries about the information of one, not of twenty-four.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..data import Run
from ..lptn import Model
from .flux import Electrical, FluxModel, steady
from .observer import Observer
from .predict import initial_from_run, model_inputs


@dataclass
class FusedRun:
    """Per sample: the observer's estimate (N, n) °C and σ (N, n) K; the flux estimate of the
    magnet (°C), its σ (K, ``inf`` where uninformative) and whether it was used; counts."""

    estimate: np.ndarray
    sigma: np.ndarray
    flux_c: np.ndarray
    flux_sigma: np.ndarray
    used: np.ndarray
    refused: int
    informative: int


def run_fused(model: Model, run: Run, sensors: Sequence[str], flux: FluxModel | None, magnet_node: str | Sequence[str],
              theta: np.ndarray | None = None, electrical: Electrical | None = None, flux_from: int = 0) -> FusedRun:
    """Replay ``run`` through the observer with the stator ``sensors`` and, where ``flux`` is given
    and the operating point informative (and steady), the flux estimate of ``magnet_node`` (or of
    the mean of several magnet nodes: the flux linkage sees all magnets) (from
    sample ``flux_from`` on: a run whose first part commissioned the flux model is scored on the
    rest with only the rest's flux estimates).

    Without ``flux`` this is the observer as the service runs it (no node updates at all).
    """
    dt = run.dt
    inputs = model_inputs(model, run)
    meas = {s: run.column(s) for s in sensors}
    N, n = len(run), len(model.nodes)
    obs = Observer(model, initial_from_run(model, run, theta), theta, dt)
    m = [model.node_index(magnet_node)] if isinstance(magnet_node, str) else [model.node_index(x) for x in magnet_node]
    est, sig = np.empty((N, n)), np.empty((N, n))
    fc, fs = np.full(N, np.nan), np.full(N, np.inf)
    if flux is not None:
        e = electrical if electrical is not None else Electrical.of(run.columns)
        fc, fs, ok = flux.estimate(e)
        ok = ok & steady(e.speed_rpm)
        ok[:flux_from] = False
        fs = np.where(ok, fs, np.inf)
    inflate = max(1.0, (flux.tau_s / dt) if flux is not None else 1.0)
    used = np.zeros(N, dtype=bool)
    for k in range(N):
        if k:
            obs.predict({c: float(v[k - 1]) for c, v in inputs.items()})
        obs.update({s: float(v[k]) for s, v in meas.items()})
        if flux is not None and np.isfinite(fs[k]):
            used[k] = obs.update_node(m, float(fc[k]), float(fs[k]) ** 2, inflate=inflate)
        est[k], sig[k] = obs.T, obs.std()
    return FusedRun(est, sig, fc, fs, used, obs.node_updates_refused, int(np.isfinite(fs).sum()))
