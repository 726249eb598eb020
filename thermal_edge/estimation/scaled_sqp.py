"""The online adapter's SQP: SLSQP whose first quasi-Newton matrix is the window's Gauss-Newton
Hessian, damped in the directions the window does not pin down.

SLSQP starts its BFGS matrix from the identity, so its first iterations are gradient steps in
log-parameters. The adaptable parameters of a thermal network are pinned down by a window to
very different degrees (the demo's 3 h closed-loop window, 1σ all parameters free: ``R_e_hous``
0.3 %, ``r_c_hous`` 1.6 %, ``k_c_sw`` 800 %), and they are correlated (``r_c_hous`` with ``k_r_sw``
0.8): gradient steps capped at three iterations per decision stop across the narrow valleys of
such a problem. On the demo's closed loop the adapter ended with ``r_c_hous`` 12.9 % above the
plant's value, 8σ from what its window said, where the window's own optimum (the same objective,
prior included, run to convergence) was within 1.1 %.

Here SLSQP runs in the variables ``z`` with ``φ = φ₀ + M z`` and ``M = (H + λ I)^{-1/2}``
(``H`` the Gauss-Newton Hessian of the objective at ``φ₀``, prior included): its identity in
``z`` is ``H + λ I`` in ``φ``, so its first step is a Levenberg-Marquardt step and three
iterations reach close to the window's optimum in the directions the window pins down. The
bounds become linear constraints on ``z``.

``λ`` is the information that pins a direction to :data:`STEP_REL_STD` (relative 1σ), counted
as :mod:`.uncertainty` counts it (the residual variance and the residuals' autocorrelation time):
directions the window pins more tightly take Gauss-Newton steps, looser ones short gradient
steps. Without the damping (``λ = 0``) every fit converges to its own window's optimum, which for
the first windows (30-40 min of one duty) lies far off in the directions they do not separate:
measured on ``thermal-edge bench adaptation``, the demo ended at 1.43 K open-loop error and the
cold light duty at 1.44 K (0.12 and 0.13 K with plain SLSQP), the challengers fitted later on
the longer windows being refused one after the other.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.optimize import minimize

from .common import FitResult
from .objective import Evaluation, Objective
from .uncertainty import estimate_uncertainty

#: relative 1σ (σ of log θ) above which a direction of the window's Fisher information is damped
#: (``bench adaptation``: 0.03 slowed the learning at the limit, quasi-steady duty ending at
#: 0.46 K; 0.1 learned every scenario)
STEP_REL_STD = 0.1


def damping(obj: Objective, ev: Evaluation, step_rel_std: float = STEP_REL_STD) -> float:
    """The damping ``λ`` (objective units per unit log-parameter squared) at which a direction of
    the Gauss-Newton Hessian of ``ev`` (an evaluation of ``obj`` with derivatives) is pinned down
    to ``step_rel_std`` (relative 1σ).

    With weights ``w`` (sum over the samples 1) rescaled to mean one by ``s = size / Σ w``, the
    covariance of the log-parameters is ``2 σ² τ / s · H⁻¹`` (:func:`.uncertainty.estimate_uncertainty`:
    ``σ²`` the residual variance, ``τ`` the residuals' integrated autocorrelation time), so the
    direction with eigenvalue ``h`` has variance ``2 σ² τ / (s h)``.
    """
    w = obj.w
    scale = w.size / max(float(w.sum()), 1e-300)
    unc = estimate_uncertainty(obj, ev)
    return 2.0 * unc.sigma2 * unc.tau / (scale * step_rel_std**2)


def scaling(hess: np.ndarray, lam: float) -> np.ndarray:
    """``(H + λ I)^{-1/2}`` of a symmetric positive semi-definite ``hess`` (negative eigenvalues
    from rounding count as zero); ``λ`` is floored at 1e-12 of the largest eigenvalue so that a
    direction of no information still maps to a finite step."""
    w, V = np.linalg.eigh(0.5 * (hess + hess.T))
    w = np.clip(w, 0.0, None)
    w = w + max(lam, 1e-12 * max(float(w.max()), 1e-300))
    return (V / np.sqrt(w)) @ V.T


def fit_scaled_sqp(obj: Objective, max_iter: int = 3, step_rel_std: float = STEP_REL_STD) -> FitResult:
    """Minimise ``obj`` within its bounds with SLSQP started from the damped Gauss-Newton Hessian
    (see the module docstring), analytic gradient.

    Parameters
    ----------
    obj : Objective
        The objective over the parameters to fit (log-parameters, bounded).
    max_iter : int
        SQP iteration cap (the paper: 3 per adaptation).
    step_rel_std : float
        Relative 1σ above which a direction is damped (:data:`STEP_REL_STD`).

    Returns
    -------
    FitResult
        Method ``"sqp-scaled"``; the starting values when no iterate improved the objective.
    """
    space = obj.space
    lo, hi = np.log(space.lower), np.log(space.upper)
    phi0 = np.clip(np.log(space.values()), lo, hi)
    t0 = time.perf_counter()
    ev0 = obj.evaluations
    ev = obj.evaluate(phi0)
    f0 = ev.value
    M = scaling(ev.hess, damping(obj, ev, step_rel_std))
    A = np.vstack([M, -M])
    slack = np.concatenate([phi0 - lo, hi - phi0])  # lo <= φ0 + M z <= hi as A z + slack >= 0
    res = minimize(lambda z: obj.value(phi0 + M @ z), np.zeros(len(phi0)), jac=lambda z: M.T @ obj.grad(phi0 + M @ z),
                   method="SLSQP", constraints=[{"type": "ineq", "fun": lambda z: slack + A @ z, "jac": lambda z: A}],
                   options={"maxiter": max_iter, "ftol": 1e-12})
    phi = np.clip(phi0 + M @ res.x, lo, hi)  # the constraints hold to SLSQP's tolerance only
    if not obj.value(phi) <= f0:  # SLSQP may stop on a worse point at the cap
        phi = phi0
    return FitResult("sqp-scaled", space.names, np.exp(phi), f0, obj.value(phi), int(res.nit),
                     obj.evaluations - ev0, time.perf_counter() - t0, str(res.message))
