"""Uncertainty at an estimate: parameter covariance from the Fisher information, identifiability,
and a 95 % band on every node's prediction (the unmeasured magnets and hot spot included).

With residual variance ``s²`` and sensitivities ``J`` (log-parameters), the covariance of the
log-parameters is ``s² (Jᵀ W̃ J + prior)⁻¹`` with ``W̃`` the sample weights scaled to mean one.
A node's prediction variance is ``S_k Cov S_kᵀ``. The residuals of a thermal model are correlated
in time, so these bands are a lower bound on the real uncertainty; they say which parameters and
nodes the sensors at hand can pin down, not how far off the model is structurally.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..settings import AdapterConfig
from .objective import Evaluation, Objective

Z95 = 1.959963984540054
#: The one identifiability threshold: a parameter is identifiable when the window pins it down to
#: this relative standard deviation (σ of log θ). Stated with the adapter's settings
#: (``adaptation.max_rel_std``), which a configuration may change for the service: the adapter
#: passes its configured value wherever it judges identifiability.
MAX_REL_STD: float = AdapterConfig.max_rel_std


@dataclass
class Uncertainty:
    names: tuple[str, ...]
    cov: np.ndarray  # log-parameter covariance
    sigma2: float  # residual variance, K²
    identifiable: np.ndarray  # bool per parameter

    @property
    def rel_std(self) -> np.ndarray:
        """Relative standard deviation of each parameter (std of log θ)."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def node_band(self, S: np.ndarray) -> np.ndarray:
        """Half-width (K) of the 95 % band of node predictions from log-parameter sensitivities
        ``S`` (N, n, p) — or (n, p) for one sample."""
        var = np.einsum("...np,pq,...nq->...n", S, self.cov, S)
        return Z95 * np.sqrt(np.clip(var, 0.0, None))

    def as_dict(self) -> dict[str, object]:
        return {
            "sigma_k": float(np.sqrt(self.sigma2)),
            "rel_std": dict(zip(self.names, map(float, self.rel_std))),
            "identifiable": [n for n, ok in zip(self.names, self.identifiable) if ok],
        }


def estimate_uncertainty(obj: Objective, ev: Evaluation, max_rel_std: float = MAX_REL_STD) -> Uncertainty:
    """Covariance of the estimate at the evaluation ``ev`` of ``obj`` (with derivatives).

    A parameter is *identifiable* when its relative standard deviation is below ``max_rel_std``
    (default :data:`MAX_REL_STD`).
    """
    w = obj.w
    scale = w.size / max(float(w.sum()), 1e-300) if w.sum() > 0 else 1.0
    wt = w * scale  # weights with mean one over the samples
    n_obs = int(np.count_nonzero(wt))
    p = ev.jac.shape[2]
    r = ev.residuals
    sigma2 = float(np.sum(wt * r * r) / max(n_obs - p, 1))
    Jw = (np.sqrt(wt)[:, :, None] * ev.jac).reshape(-1, p)
    info = Jw.T @ Jw
    if obj.prior_weight:
        info = info + np.diag(obj.prior_weight * scale / obj.sigma**2)  # the prior, in the same units
    cov = sigma2 * np.linalg.pinv(info, rcond=1e-12)
    rel = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return Uncertainty(obj.space.names, cov, sigma2, rel < max_rel_std)
