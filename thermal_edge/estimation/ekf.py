"""The EKF baseline (paper eqs. 42–45): joint estimation of node temperatures and parameters.

State ``L = [T; φ]`` with ``φ = log θ`` a random walk. Prediction by the discrete model,
``T⁺ = Φ(θ) T + Γ(θ) w(T)``, with the Jacobian ``[[Φ + Γ_P ∂P/∂T, ∂T⁺/∂φ], [0, I]]`` where
``∂T⁺/∂φ_j = θ_j (dΦ_j T + dΓ_j w + Γ_P ∂P/∂θ_j)`` comes from the same exact derivatives as the
sensitivities. The measurement update runs every ``update_s`` (the paper: every minute). The
EKF moves states and parameters together, so its parameters are judged open-loop afterwards.
"""
from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..lptn import DiscreteDerivatives, Model, Network, discretise
from ..lptn.losses import LossLaws


@dataclass
class EKFResult:
    theta: np.ndarray  # final full parameter vector
    names: tuple[str, ...]
    trace: np.ndarray  # (updates, p) estimated parameters after each update
    T: np.ndarray  # (N, n) filtered node temperatures
    wall_s: float


def run_ekf(
    model: Model, inputs: Mapping[str, np.ndarray], measured: Mapping[str, np.ndarray], dt: float, T0: np.ndarray,
    theta0: np.ndarray | None = None, names: Sequence[str] | None = None, update_s: float = 60.0,
    r_k: float = 0.1, q_t_k: float = 0.01, q_phi: float = 1e-4, p_t0_k: float = 1.0,
) -> EKFResult:
    """Run the joint EKF over a run.

    Parameters
    ----------
    inputs, measured : mapping
        Model input columns and sensor readings (N,), °C.
    names : sequence of str
        Parameters estimated (default: the model's adaptable ones).
    r_k : float
        Measurement noise σ, K. ``q_t_k``: process noise σ on temperatures per step, K.
        ``q_phi``: random-walk σ of the log-parameters per step. ``p_t0_k``: initial σ of T, K.
    """
    t_start = time.perf_counter()
    names = tuple(names or model.adaptable)
    theta = (model.nominal() if theta0 is None else np.asarray(theta0, dtype=float)).copy()
    idx = model.parameter_index(names)
    lo, hi = (b[idx] for b in model.bounds())
    net = Network(model)
    n, p = len(model.nodes), len(names)
    nb = len(model.boundaries)
    sensors = [s for s in measured if s in model.sensors]
    H = np.zeros((len(sensors), n + p))
    for i, s in enumerate(sensors):
        H[i, model.node_index(model.sensors[s])] = 1.0
    R = np.eye(len(sensors)) * r_k**2
    Q = np.diag(np.concatenate([np.full(n, q_t_k**2), np.full(p, q_phi**2)]))
    sig = (np.log(hi) - np.log(lo)) / 4.0
    Pc = np.diag(np.concatenate([np.full(n, p_t0_k**2), sig**2]))
    N = len(next(iter(inputs.values())))
    every = max(1, int(round(update_s / dt)))
    laws = LossLaws(model)
    cache: dict[tuple[float, ...], tuple[np.ndarray, ...]] = {}
    T = np.asarray(T0, dtype=float).copy()
    out = np.empty((N, n))
    trace = []
    for k in range(N):
        out[k] = T
        if k and k % every == 0:  # measurement update
            y = np.array([measured[s][k] for s in sensors])
            ok = np.isfinite(y)
            if ok.any():
                Hk, Rk = H[ok], R[np.ix_(ok, ok)]
                L = np.concatenate([T, np.log(theta[idx])])
                Sk = Hk @ Pc @ Hk.T + Rk
                Kg = np.linalg.solve(Sk, Hk @ Pc).T
                L = L + Kg @ (y[ok] - Hk @ L)
                Pc = (np.eye(n + p) - Kg @ Hk) @ Pc
                Pc = 0.5 * (Pc + Pc.T)
                T = L[:n]
                theta[idx] = np.exp(np.clip(L[n:], np.log(lo), np.log(hi)))
                cache.clear()
                trace.append(theta[idx].copy())
        if k == N - 1:
            break
        u = {c: float(v[k]) for c, v in inputs.items()}
        key = tuple(u[c] for c in net.matrix_inputs)
        if key not in cache:
            op = {c: np.array([u[c]]) for c in net.matrix_inputs}
            d = discretise(net.continuous(theta, op, K=1, wrt=list(idx)), dt, model.discretisation.method,
                           model.discretisation.max_substep_s)
            assert isinstance(d, DiscreteDerivatives)  # discretised with the derivatives by ``wrt``
            cache[key] = (d.Phi[0], d.Gam[0], d.dPhi[0], d.dGam[0])
        Phi, Gam, dPhi, dGam = cache[key]
        env = net.env(theta, {c: np.asarray(v) for c, v in u.items()})
        P = laws.power(env, T)
        w = np.concatenate([[u[c] for c in model.boundaries.values()], P])
        GP = Gam[:, nb:]
        M = Phi.copy()
        M[:, laws.nodes] += GP @ laws.dT(env, T)
        X = (dPhi @ T + dGam @ w).T + GP @ laws.dtheta(env, T, idx)  # (n, p) per unit θ
        F = np.eye(n + p)
        F[:n, :n] = M
        F[:n, n:] = X * theta[idx][None, :]
        T = Phi @ T + Gam @ w
        Pc = F @ Pc @ F.T + Q
    return EKFResult(theta, names, np.array(trace), out, time.perf_counter() - t_start)
