"""The paper's optimiser: SQP (scipy ``SLSQP``) on the screened parameters with the analytic gradient.

``scipy.optimize`` is imported when a fit runs, not with this module: the service imports the
adapter at start, and a model that fits its machine never runs a fit (``scipy.optimize`` and what
it pulls in are about 15 MB of the service's resident memory).
"""
from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from .blas import one_blas_thread
from .common import FitResult
from .objective import Objective


def fit_sqp(obj: Objective, max_iter: int = 3, gradient: str = "analytic", method_name: str | None = None) -> FitResult:
    """Minimise ``obj`` over its parameter space with SLSQP in log-parameters within bounds.

    Parameters
    ----------
    max_iter : int
        SQP iteration cap (the paper: 3 per adaptation).
    gradient : {"analytic", "numerical"}
        ``analytic``: the forward-sensitivity gradient at the points SLSQP asks it for.
        ``numerical``: scipy's forward differences (one simulation per parameter per gradient;
        the paper's fmincon baseline).

    Notes
    -----
    With the analytic gradient each point SLSQP evaluates is simulated once, and the simulation
    is kept (:meth:`~.objective.Objective.evaluate` with ``keep``): SLSQP asks for the gradient
    at the points its line search accepts (in E2 of ``bench paper`` three of six), and their
    sensitivities then come from that simulation, while a rejected trial point costs a
    simulation only. BLAS runs on one thread (:func:`~.blas.one_blas_thread`).
    """
    from scipy.optimize import minimize

    if gradient not in ("analytic", "numerical"):
        raise ValueError(f"gradient must be analytic or numerical, got {gradient!r}")
    analytic = gradient == "analytic"
    space = obj.space
    phi0 = np.log(space.values())
    with one_blas_thread():
        t0 = time.perf_counter()
        f0 = obj.evaluate(phi0, derivatives=analytic).value
        ev0 = obj.evaluations
        fun: Callable[[np.ndarray], float]
        jac: Callable[[np.ndarray], np.ndarray] | str
        if analytic:
            fun, jac = (lambda phi: obj.evaluate(phi, derivatives=False, keep=True).value), obj.grad
        else:
            fun, jac = obj.value, "2-point"
        res = minimize(fun, phi0, jac=jac, method="SLSQP", bounds=space.log_bounds(),
                       options={"maxiter": max_iter, "ftol": 1e-12})
        phi = res.x if obj.value(res.x) <= f0 else phi0  # SLSQP may stop on a worse point at the cap
        after = obj.value(phi)
        wall = time.perf_counter() - t0
    return FitResult(
        method=method_name or f"sqp-{gradient}",
        names=space.names,
        values=np.exp(phi),
        objective_before=f0,
        objective_after=after,
        iterations=int(res.nit),
        evaluations=obj.evaluations - ev0,
        wall_s=wall,
        message=str(res.message),
    )
