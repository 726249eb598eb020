"""Gauss-Newton / trust region (scipy ``least_squares``, ``trf``) with the analytic residual Jacobian.

``scipy.optimize`` is imported when a fit runs, not with this module (see :mod:`.sqp`).
"""
from __future__ import annotations

import time

import numpy as np

from .blas import one_blas_thread
from .common import FitResult
from .objective import Objective


def fit_gauss_newton(obj: Objective, max_iter: int = 10) -> FitResult:
    """Minimise ``obj`` as a bounded nonlinear least-squares problem in log-parameters.

    Parameters
    ----------
    max_iter : int
        Cap on function evaluations (each gives residuals and their Jacobian).
    """
    from scipy.optimize import least_squares

    space = obj.space
    phi0 = np.log(space.values())
    lo, hi = np.log(space.lower), np.log(space.upper)
    with one_blas_thread():
        t0 = time.perf_counter()
        f0 = obj.evaluate(phi0).value  # with the Jacobian least_squares asks for first: one simulation
        ev0 = obj.evaluations
        res = least_squares(obj.residual_vector, np.clip(phi0, lo, hi), jac=obj.residual_jacobian, bounds=(lo, hi),
                            method="trf", max_nfev=max_iter, x_scale="jac")
        phi = res.x if obj.value(res.x) <= f0 else phi0
        after = obj.value(phi)
        wall = time.perf_counter() - t0
    return FitResult("gauss_newton", space.names, np.exp(phi), f0, after, int(res.nfev), obj.evaluations - ev0, wall,
                     str(res.message))
