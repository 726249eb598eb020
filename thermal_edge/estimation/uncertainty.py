"""Uncertainty at an estimate: parameter covariance from the Fisher information, identifiability,
and a 95 % band on every node's prediction (the unmeasured magnets and hot spot included).

With residual variance ``s²`` and sensitivities ``J`` (log-parameters), the covariance of the
log-parameters is ``s² (Jᵀ W̃ J / τ + prior)⁻¹`` with ``W̃`` the sample weights scaled to mean
one and ``τ`` the residuals' integrated autocorrelation time in samples
(:func:`integrated_autocorrelation`). The residuals of a model that is not the machine are
correlated in time, so ``n`` samples carry the information of about ``n / τ`` independent ones
(the Paderborn run, published parameters, 20 s steps: τ ≈ 25 over the whole run, every σ ×5).
The correction assumes the sensitivities change slowly against the correlation time, as a
thermal network's do. A node's prediction variance is ``S_k Cov S_kᵀ``.

*Identifiable* is a different question, the adapter's gate: whether the window's excitation and
sensors separate a parameter, judged on the information as if the residuals were independent
(``τ = 1``). Judged with ``τ``, a wrong start (whose residuals are its error, correlated over
the whole window) would look uninformative exactly when it most needs adapting: on the
Paderborn run a start with ``R_c_sy`` ×0.6 never adapted, and ``bench paper`` E2's held-out RMS
rose from 0.105 to 0.131 K. So a parameter can be identifiable and still have a wide band.
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
#: Residual degrees of freedom (observations, samples x sensors, beyond the number of fitted
#: parameters) below which no parameter is identifiable: a fit with nearly as many parameters as
#: observations matches them whatever the parameters are, and its residual variance, hence every
#: standard deviation, comes out near zero (two samples "pinned" three parameters to ±0.02 %).
MIN_RESIDUAL_DOF = 20


@dataclass
class Uncertainty:
    names: tuple[str, ...]
    cov: np.ndarray  # log-parameter covariance
    sigma2: float  # residual variance, K²
    identifiable: np.ndarray  # bool per parameter: ``rel_std_independent`` below the gate's limit
    tau: float  # the residuals' integrated autocorrelation time, samples (the information is divided by it)
    rel_std_independent: np.ndarray  # σ of log θ as if the residuals were independent (the gate's)
    #: bool per parameter: moved by a direction the data carry no information on (σ infinite)
    unresolved: np.ndarray | None = None

    @property
    def rel_std(self) -> np.ndarray:
        """Relative standard deviation of each parameter (std of log θ; inf where :attr:`unresolved`)."""
        std = np.sqrt(np.clip(np.diag(self.cov), 0.0, None))
        return std if self.unresolved is None else np.where(self.unresolved, np.inf, std)

    def node_band(self, S: np.ndarray) -> np.ndarray:
        """Half-width (K) of the 95 % band of node predictions from log-parameter sensitivities
        ``S`` (N, n, p) — or (n, p) for one sample."""
        var = np.einsum("...np,pq,...nq->...n", S, self.cov, S)
        return Z95 * np.sqrt(np.clip(var, 0.0, None))

    def as_dict(self) -> dict[str, object]:
        return {
            "sigma_k": float(np.sqrt(self.sigma2)),
            "autocorrelation_samples": float(self.tau),
            "rel_std": dict(zip(self.names, map(float, self.rel_std))),
            "rel_std_independent": dict(zip(self.names, map(float, self.rel_std_independent))),
            "identifiable": [n for n, ok in zip(self.names, self.identifiable) if ok],
        }


def estimate_uncertainty(obj: Objective, ev: Evaluation, max_rel_std: float = MAX_REL_STD) -> Uncertainty:
    """Covariance of the estimate at the evaluation ``ev`` of ``obj`` (with derivatives), the
    residuals' correlation in time counted.

    A parameter is *identifiable* when its relative standard deviation, from the information as
    if the residuals were independent, is below ``max_rel_std`` (default :data:`MAX_REL_STD`),
    and the window has at least :data:`MIN_RESIDUAL_DOF` observations more than parameters.
    """
    w = obj.w
    scale = w.size / max(float(w.sum()), 1e-300) if w.sum() > 0 else 1.0
    wt = w * scale  # weights with mean one over the samples
    n_obs = int(np.count_nonzero(wt))
    p = ev.jac.shape[2]
    r = ev.residuals
    dof = n_obs - p - obj.nuisance  # the start's offsets fitted alongside take theirs too
    sigma2 = float(np.sum(wt * r * r) / max(dof, 1))
    tau = integrated_autocorrelation(r, wt > 0)
    Jw = (np.sqrt(wt)[:, :, None] * ev.jac).reshape(-1, p)
    data = Jw.T @ Jw
    prior = np.diag(obj.prior_weight * scale / obj.sigma**2) if obj.prior_weight else np.zeros((p, p))  # same units
    cov, unresolved = information_inverse(data / tau + prior)
    white, _ = information_inverse(data + prior)
    gate = np.where(unresolved, np.inf, np.sqrt(np.clip(sigma2 * np.diag(white), 0.0, None)))
    enough = dof >= MIN_RESIDUAL_DOF
    return Uncertainty(obj.space.names, sigma2 * cov, sigma2, (gate < max_rel_std) & enough, tau, gate, unresolved)


#: an eigenvalue of the information below this fraction of the largest is none: its direction is
#: not seen in the data (round-off of the exact zero of parameters that only act together)
INFO_RCOND = 1e-12


def information_inverse(info: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of an information matrix (p, p) on the directions the data see, and which
    parameters a direction they do not see moves (bool, p).

    A direction with no information (parameters that act only together, such as a capacity, a
    conductance and a loss scaled alike, or a parameter no output depends on) has an infinite
    variance, not the zero a pseudo-inverse gives it: its parameters are marked. The inverse
    itself is the pseudo-inverse, so the prediction's variance (to which such a direction adds
    nothing) stays finite.
    """
    lam, V = np.linalg.eigh(0.5 * (info + info.T))
    top = float(lam.max()) if lam.size else 0.0
    seen = lam > INFO_RCOND * top if top > 0 else np.zeros(lam.shape, dtype=bool)
    inv = (V[:, seen] / lam[seen]) @ V[:, seen].T
    # a parameter is moved by an unseen direction when it has a share of it beyond round-off
    unresolved = np.any(np.abs(V[:, ~seen]) > 1e-6, axis=1) if (~seen).any() else np.zeros(len(lam), dtype=bool)
    return inv, unresolved


def integrated_autocorrelation(r: np.ndarray, mask: np.ndarray | None = None, c: float = 5.0) -> float:
    """Integrated autocorrelation time (samples, at least 1) of residuals ``r`` (N, sensors).

    Per sensor ``τ = 1 + 2 Σ_{t=1}^{M} ρ_t`` with ``ρ_t`` the autocorrelation of the centred
    residuals at lag ``t`` and Sokal's window: the smallest ``M ≥ c τ(M)`` (``c`` = 5). Sensors
    are pooled weighted by their residuals' sum of squares, the share of the information each
    carries. Samples outside ``mask`` count as zero residual. A window shorter than about
    ``c τ`` cannot see its own correlation time and gives a lower τ (hence a floor on the
    history before adapting). Anti-correlated residuals give 1: the bound never narrows below
    that of white noise.
    """
    r = np.asarray(r, dtype=float)
    if r.ndim == 1:
        r = r[:, None]
    ok = np.ones(r.shape, dtype=bool) if mask is None else np.broadcast_to(mask, r.shape)
    n = r.shape[0]
    if n < 3:
        return 1.0
    taus, weights = [], []
    for j in range(r.shape[1]):
        m = ok[:, j]
        if m.sum() < 3:
            continue
        x = np.where(m, r[:, j] - r[m, j].mean(), 0.0)
        var = float(x @ x)
        if var <= 0:
            continue
        f = np.fft.rfft(x, 2 * n)  # zero-padded: linear, not circular, correlation
        rho = np.fft.irfft(f * np.conj(f))[:n] / var
        tau_m = 1.0 + 2.0 * np.cumsum(rho[1:])
        lags = np.arange(1, n)
        stop = np.nonzero(lags >= c * tau_m)[0]
        taus.append(float(tau_m[stop[0]] if len(stop) else tau_m[-1]))
        weights.append(float(np.sum(r[m, j] ** 2)))
    if not taus:
        return 1.0
    return max(float(np.average(taus, weights=weights)) if sum(weights) > 0 else float(np.mean(taus)), 1.0)
