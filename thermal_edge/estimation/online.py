"""Running the online adapter over a recorded run, as the service would.

At each sample the adaptive model predicts open-loop with the parameters accepted so far; every
``period_s`` the adapter decides on the history up to that sample; after a decision the model's
state is re-derived by simulating the history window with the (possibly new) parameters, and the
prediction of the next period continues from there (the paper's §5.1: at ``k·Ts`` estimate from
data ``0…k·Ts``, then predict ``k·Ts…(k+1)·Ts``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data import Run
from ..lptn import Model
from .adapter import AdapterConfig, Decision, OnlineAdapter
from .predict import initial_from_run, model_inputs


@dataclass
class OnlineResult:
    T: np.ndarray  # (N, n) the adaptive model's prediction at each sample, °C
    decisions: list[Decision]
    theta: np.ndarray  # final parameters
    adapter: OnlineAdapter
    param_trace: dict[str, np.ndarray]  # adaptable parameter values over time (N,)


def run_online(model: Model, run: Run, config: AdapterConfig, theta0: np.ndarray | None = None,
               T0: np.ndarray | None = None) -> OnlineResult:
    """Replay ``run`` through the online adapter (only the configured sensors are seen)."""
    dt = run.dt
    ad = OnlineAdapter(model, config, dt, theta0)
    inputs = model_inputs(model, run)
    sensors = [s for s in ad.sensors]
    meas = {s: run.column(s) for s in sensors}
    N = len(run)
    n = len(model.nodes)
    T = np.empty((N, n))
    x = initial_from_run(model, run, ad.theta) if T0 is None else np.asarray(T0, dtype=float)
    trace = {p: np.empty(N) for p in ad.params}
    pidx = model.parameter_index(ad.params)
    from ..lptn import Stepper

    stepper = Stepper(model, ad.theta, dt)
    for k in range(N):
        T[k] = x
        u = {c: float(v[k]) for c, v in inputs.items()}
        y = {s: float(v[k]) for s, v in meas.items()}
        ad.record(float(run.t[k]), u, y, x)
        if ad.due(float(run.t[k])):
            before = ad.version
            ad.decide(float(run.t[k]))
            if ad.version != before:
                stepper.set_parameters(ad.theta)
                # the state consistent with the accepted parameters: re-simulate the window
                win = ad._window(float(run.t[k]) - config.window_s)
                x = ad.sim.simulate(ad.theta, win.inputs, win.dt, win.T0).T[-1]
                T[k] = x
        for p, i in zip(ad.params, pidx):
            trace[p][k] = ad.theta[i]
        if k + 1 < N:
            x, _ = stepper.step(x, u)
    return OnlineResult(T, ad.decisions, ad.theta.copy(), ad, trace)
