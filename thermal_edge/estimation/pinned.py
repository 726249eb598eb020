"""What a history window pins down: the Gauss-Newton step of the estimation objective restricted to
the directions the window determines, and the refinement fit that takes it.

SLSQP starts its quasi-Newton matrix from the identity, so its first iterations are gradient steps
in log-parameters. The adaptable parameters of a thermal network are pinned down by a window to
very different degrees (the demo's 3 h closed-loop window, 1σ with all parameters free:
``R_e_hous`` 0.3 %, ``r_c_hous`` 1.6 %, ``k_c_sw`` 800 %) and they are correlated (``r_c_hous``
with ``k_r_sw`` 0.8): three iterations per decision stop across the narrow valleys of such a
problem. Once the model predicts within the adapter's threshold, no fit is triggered by the error
any more although the window goes on pinning such a parameter ever tighter, away from its value.

The Gauss-Newton step in the pinned directions says how far that is. It is taken only once the
model predicts within the threshold: early, while the model is far from the machine, the first
windows (30-40 min of one duty) do not separate what they are fitted to, and a fit that went to
their optimum in every direction they seemed to pin ended the closed-loop demo at 1.4 K.
"""
from __future__ import annotations

import time

import numpy as np

from .blas import one_blas_thread
from .common import FitResult
from .objective import Evaluation, Objective
from .uncertainty import estimate_uncertainty

__all__ = ["fit_refine", "pinned_step"]


def pinned_step(obj: Objective, ev: Evaluation, step_rel_std: float) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Newton step (log-parameters) restricted to the eigen-directions of the window's
    Gauss-Newton Hessian pinned down to ``step_rel_std`` (relative 1σ, the residuals counted as
    independent as the adapter's gate counts them); zero in every other direction. Also each
    parameter's marginal 1σ (relative, residuals independent).

    With weights ``w`` (sum 1) rescaled to mean one by ``s = size / Σ w``, the covariance of the
    log-parameters is ``2 σ² / s · H⁻¹``, so the eigenvector of ``H`` with eigenvalue ``h`` is
    pinned to ``√(2 σ² / (s h))``.
    """
    w = obj.w
    scale = w.size / max(float(w.sum()), 1e-300)
    unc = estimate_uncertainty(obj, ev)
    h, V = np.linalg.eigh(0.5 * (ev.hess + ev.hess.T))
    pinned = h > 2.0 * unc.sigma2 / (scale * step_rel_std**2)
    if not pinned.any():
        return np.zeros(len(h)), unc.rel_std_independent
    Vp = V[:, pinned]
    return -Vp @ ((Vp.T @ ev.grad) / h[pinned]), unc.rel_std_independent


def fit_refine(obj: Objective, max_iter: int, step_rel_std: float) -> FitResult:
    """The Gauss-Newton step in the directions the window pins down to ``step_rel_std`` (halved
    while it does not lower the objective), then SLSQP from there (``max_iter`` iterations,
    analytic gradient).

    Returns
    -------
    FitResult
        Method ``"sqp-refine"``; the starting values when nothing lowered the objective.
    """
    from scipy.optimize import minimize

    space = obj.space
    lo, hi = np.log(space.lower), np.log(space.upper)
    phi0 = np.clip(np.log(space.values()), lo, hi)
    with one_blas_thread():
        t0 = time.perf_counter()
        ev0 = obj.evaluations
        ev = obj.evaluate(phi0)
        f0 = ev.value
        step, _ = pinned_step(obj, ev, step_rel_std)
        phi1, f1 = phi0, f0
        for frac in (1.0, 0.5, 0.25):  # a nonlinear model: halve a step that does not lower the objective
            if not np.any(step):
                break
            trial = np.clip(phi0 + frac * step, lo, hi)
            f = obj.value(trial)
            if f < f0:
                phi1, f1 = trial, f
                break
        res = minimize(lambda p: obj.evaluate(p).value, phi1, jac=obj.grad, method="SLSQP",
                       bounds=space.log_bounds(), options={"maxiter": max_iter, "ftol": 1e-12})
        x = np.clip(res.x, lo, hi)
        fx = obj.value(x)
        phi, after = (x, fx) if fx <= f1 else (phi1, f1)  # SLSQP may stop on a worse point at the cap
        wall = time.perf_counter() - t0
    return FitResult("sqp-refine", space.names, np.exp(phi), f0, after, int(res.nit), obj.evaluations - ev0, wall,
                     str(res.message))
