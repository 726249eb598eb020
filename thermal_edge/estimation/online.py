"""Running the online adapter over a recorded run, as the service would.

At each sample the adaptive model predicts open-loop with the parameters accepted so far; every
``period_s`` the adapter decides on the history up to that sample; after a decision the model's
state is re-derived by simulating the history window with the (possibly new) parameters, and the
prediction of the next period continues from there (the paper's §5.1: at ``k·Ts`` estimate from
data ``0…k·Ts``, then predict ``k·Ts…(k+1)·Ts``). Between decisions the prediction is simulated
a period at a time.
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
    meas = {s: run.column(s) for s in ad.sensors}
    N, n = len(run), len(model.nodes)
    T = np.empty((N, n))
    x = initial_from_run(model, run, ad.theta) if T0 is None else np.asarray(T0, dtype=float)
    trace = {p: np.empty(N) for p in ad.params}
    pidx = model.parameter_index(ad.params)
    t = run.t
    k0 = 0
    while k0 < N:
        # the next sample at which a decision falls due (or the end of the run)
        due = np.nonzero(t[k0:] - t[0] >= (len(ad.decisions) + 1) * config.period_s - 1e-9)[0]
        k1 = k0 + int(due[0]) if len(due) else N - 1
        chunk = ad.sim.simulate(ad.theta, {c: v[k0:k1 + 1] for c, v in inputs.items()}, dt, x).T
        T[k0:k1 + 1] = chunk
        for k in range(k0, k1 + 1):
            ad.record(float(t[k]), {c: float(v[k]) for c, v in inputs.items()}, {s: float(v[k]) for s, v in meas.items()}, T[k])
        for p, i in zip(ad.params, pidx):
            trace[p][k0:k1 + 1] = ad.theta[i]
        if ad.due(float(t[k1])):
            before = ad.version
            ad.decide(float(t[k1]))
            if ad.version != before:
                # the state consistent with the accepted parameters: re-simulate the window
                win = ad._window(float(t[k1]) - config.window_s)
                T[k1] = ad.sim.simulate(ad.theta, win.inputs, win.dt, win.T0).T[-1]
                for p, i in zip(ad.params, pidx):
                    trace[p][k1] = ad.theta[i]
        x = T[k1]
        if k1 == N - 1:
            break
        # continue from sample k1 (its inputs drive the step to k1 + 1)
        nxt = ad.sim.simulate(ad.theta, {c: v[k1:k1 + 2] for c, v in inputs.items()}, dt, x).T[-1]
        x = nxt
        k0 = k1 + 1
    return OnlineResult(T, ad.decisions, ad.theta.copy(), ad, trace)
