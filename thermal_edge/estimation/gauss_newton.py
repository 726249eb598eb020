"""Gauss-Newton / trust region (scipy ``least_squares``, ``trf``) with the analytic residual Jacobian."""
from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares

from .common import FitResult
from .objective import Objective


def fit_gauss_newton(obj: Objective, max_iter: int = 10) -> FitResult:
    """Minimise ``obj`` as a bounded nonlinear least-squares problem in log-parameters.

    Parameters
    ----------
    max_iter : int
        Cap on function evaluations (each gives residuals and their Jacobian).
    """
    space = obj.space
    phi0 = np.log(space.values())
    lo, hi = np.log(space.lower), np.log(space.upper)
    t0 = time.perf_counter()
    f0 = obj.value(phi0)
    ev0 = obj.evaluations
    res = least_squares(obj.residual_vector, np.clip(phi0, lo, hi), jac=obj.residual_jacobian, bounds=(lo, hi),
                        method="trf", max_nfev=max_iter, x_scale="jac")
    phi = res.x if obj.value(res.x) <= f0 else phi0
    return FitResult("gauss_newton", space.names, np.exp(phi), f0, obj.value(phi), int(res.nfev),
                     obj.evaluations - ev0, time.perf_counter() - t0, str(res.message))
