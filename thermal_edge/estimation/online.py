"""Running the online adapter over a recorded run, as the service would.

An observer (:class:`~thermal_edge.estimation.observer.Observer`, the adapter's sensors only)
follows the run with the parameters in use; its estimate is what the adapter records. Its bands
carry the parameters' declared spread (:mod:`.observer`). Every
``period_s`` the adapter decides on the history up to that sample. The *online trace* is scored
as the paper does (§5.1): at each decision the parameters then in use predict the next period
open loop from the observer's state at that sample.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..data import Run
from ..lptn import Model
from .adapter import AdapterConfig, Decision, OnlineAdapter
from .observer import Observer
from .predict import initial_from_run, model_inputs
from .uncertainty import Z95


@dataclass
class OnlineResult:
    T: np.ndarray  # (N, n) the online trace, °C
    estimate: np.ndarray  # (N, n) the observer's estimate from the adapter's sensors, °C
    sigma: np.ndarray  # (N, n) its standard deviation (state and parameter uncertainty), K
    decisions: list[Decision]
    theta: np.ndarray  # final parameters
    adapter: OnlineAdapter
    param_trace: dict[str, np.ndarray]  # adaptable parameter values over time (N,)


def run_online(model: Model, run: Run, config: AdapterConfig, theta0: np.ndarray | None = None,
               T0: np.ndarray | None = None, progress: Callable[[int], object] | None = None) -> OnlineResult:
    """Replay ``run`` through the observer and the online adapter (only the configured sensors
    are seen).

    Parameters
    ----------
    theta0 : ndarray, optional
        Starting parameters (default: the model's nominal values, also the adapter's prior).
    T0 : ndarray, optional
        Initial state, °C (default: from the first row's readings).
    progress : callable, optional
        Called with 1 after every sample (a progress bar's ``update``).
    """
    dt = run.dt
    ad = OnlineAdapter(model, config, dt, theta0)
    inputs = model_inputs(model, run)
    meas = {s: run.column(s) for s in ad.sensors}
    N, n = len(run), len(model.nodes)
    T = np.empty((N, n))
    est = np.empty((N, n))
    sig = np.empty((N, n))
    x0 = initial_from_run(model, run, ad.theta) if T0 is None else np.asarray(T0, dtype=float)
    obs = Observer(model, x0, ad.theta, dt)
    trace = {p: np.empty(N) for p in ad.params}
    pidx = model.parameter_index(ad.params)
    t = run.t
    seg = 0  # the sample the current open-loop period starts from
    for k in range(N):
        u = {c: float(v[k]) for c, v in inputs.items()}
        if k:
            obs.predict({c: float(v[k - 1]) for c, v in inputs.items()})
        y = {s: float(v[k]) for s, v in meas.items()}
        obs.update(y)
        est[k], sig[k] = obs.T, obs.std()
        if k == 0:
            T[0] = obs.T
        ad.record(float(t[k]), u, y, obs.T)
        due = ad.due(float(t[k]))
        if due or k == N - 1:
            if k > seg:
                T[seg + 1:k + 1] = ad.sim.simulate(ad.theta, {c: v[seg:k + 1] for c, v in inputs.items()}, dt,
                                                   est[seg]).T[1:]
            seg = k
        if due:
            before = ad.version
            ad.decide(float(t[k]))
            if ad.version != before:
                obs.set_parameters(ad.theta)
                if ad.promoted_state is not None and ad.promoted_state[0] == float(t[k]):
                    obs.T = ad.promoted_state[1].copy()  # the estimate the promoted parameters were judged from
        for p, i in zip(ad.params, pidx):  # in use from this sample on (a decision here included)
            trace[p][k] = ad.theta[i]
        if progress is not None:
            progress(1)

    return OnlineResult(T, est, sig, ad.decisions, ad.theta.copy(), ad, trace)


def online_report(model: Model, run: Run, config: AdapterConfig, theta0: np.ndarray | None = None,
                  progress: Callable[[int], object] | None = None) -> dict[str, Any]:
    """What a user needs to judge online adaptation on a recorded run, per target (every sensor
    column of the run, seen by the adapter or not).

    Per target: ``mse`` the online trace (K², see :func:`run_online`), ``fixed_mse`` the same
    with the starting parameters never changed, ``observer_mse`` the observer's estimate from the
    adapter's sensors only (K²), ``fixed_observer_mse`` the same observer with the starting
    parameters, ``band_coverage`` the share of samples whose reading lies inside the 95 % band of
    that estimate (NaN readings not counted), ``seen`` whether the adapter learns from it. Also
    ``final_params`` (the adaptable parameters at the end), ``mean`` (the four figures averaged
    over the targets), the decisions and the median time of an adaptation step (s). ``progress``
    as :func:`run_online`'s, for both runs (twice the samples in all).
    """
    fixed = run_online(model, run, replace(config, threshold_k=np.inf), theta0, progress=progress)
    res = run_online(model, run, config, theta0, progress=progress)
    targets: dict[str, dict[str, object]] = {}
    for s, node in model.sensors.items():
        if s not in run.columns:
            continue
        i = model.node_index(node)
        y = run.columns[s]
        ok = np.isfinite(y)
        targets[s] = {
            "mse": float(np.mean((res.T[ok, i] - y[ok]) ** 2)),
            "fixed_mse": float(np.mean((fixed.T[ok, i] - y[ok]) ** 2)),
            "observer_mse": float(np.mean((res.estimate[ok, i] - y[ok]) ** 2)),
            "fixed_observer_mse": float(np.mean((fixed.estimate[ok, i] - y[ok]) ** 2)),
            "band_coverage": band_coverage(res.estimate[ok, i], res.sigma[ok, i], y[ok]),
            "seen": s in res.adapter.sensors,
        }
    keys = ("mse", "fixed_mse", "observer_mse", "fixed_observer_mse")
    steps = [d.duration_s for d in res.decisions if d.evaluations]
    return {
        "targets": targets,
        "mean": {k: float(np.mean([v[k] for v in targets.values()])) for k in keys},
        "final_params": res.adapter.params_dict(),
        "decisions": res.decisions,
        "adapt_step_median_s": float(np.median(steps)) if steps else float("nan"),
        "result": res,
    }


def band_coverage(estimate: np.ndarray, sigma: np.ndarray, measured: np.ndarray) -> float:
    """Share of samples whose reading lies within the 95 % band ``estimate ± Z95 σ`` (NaN readings
    not counted)."""
    ok = np.isfinite(measured)
    return float(np.mean(np.abs(measured[ok] - estimate[ok]) <= Z95 * sigma[ok])) if ok.any() else float("nan")
