"""Discretisation of ``C dT/dt = A T + W w`` with inputs held over a step, and its exact derivatives.

``T[k+1] = Φ T[k] + Γ w[k]``. Both methods share ``Γ = (Φ − I) A⁻¹ W`` (exact for inputs held over
the step, for ZOH and for explicit Euler with sub-steps alike) and its derivative
``dΓ = dΦ H + (Φ − I) A⁻¹ (dW − dA H)`` with ``H = A⁻¹ W``. They differ in ``Φ``:

* ``zoh``: ``Φ = exp(C⁻¹A Δt)``, computed in the eigenbasis of the symmetric
  ``Ã = C^-½ A C^-½`` (``C⁻¹A`` is similar to it), and ``dΦ`` by the Daleckii–Krein formula
  (divided differences of ``exp`` on the eigenvalues) — exact at any step.
* ``euler`` (the paper's choice): ``Φ = (I + h C⁻¹A)^m`` with ``m`` sub-steps of ``h = Δt/m``.
  Stable only if the spectral radius of ``I + h C⁻¹A`` is below 1; otherwise
  :class:`UnstableDiscretisation` says which step would be stable.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .network import Continuous


class UnstableDiscretisation(ValueError):
    """Explicit Euler would diverge at the requested step."""


class NotPassive(ValueError):
    """The network's system matrix is not negative definite (a node not tied to any boundary, or a
    non-passive T-model)."""


@dataclass
class Discrete:
    """``Φ`` (K, n, n), ``Γ`` (K, n, m) and, if asked, ``dΦ`` (K, p, n, n), ``dΓ`` (K, p, n, m)."""

    Phi: np.ndarray
    Gam: np.ndarray
    dPhi: np.ndarray | None = None
    dGam: np.ndarray | None = None
    substeps: int = 1


def _eig(cont: Continuous) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    s = np.sqrt(cont.c)
    At = cont.A / np.outer(s, s)
    lam, Qm = np.linalg.eigh(At)
    if np.any(lam >= 0):
        worst = float(lam.max())
        raise NotPassive(
            f"system matrix has a non-negative eigenvalue ({worst:.3g} 1/s): some node is not tied to a "
            "boundary through positive conductances"
        )
    return s, At, lam, Qm


def sandwich(left: np.ndarray, mid: np.ndarray, right: np.ndarray) -> np.ndarray:
    """``left @ mid[:, j] @ right`` for every ``j``: (K, n, n), (K, p, n, n), (K, n, n) -> (K, p, n, n).

    Done as two products per operating point over all ``p`` matrices at once (stacked side by
    side, then on top of each other) rather than ``2p`` small ones.
    """
    K, p, n, _ = mid.shape
    a = left @ mid.transpose(0, 2, 1, 3).reshape(K, n, p * n)  # [left M_1, left M_2, ...]
    a = a.reshape(K, n, p, n).transpose(0, 2, 1, 3).reshape(K, p * n, n)
    return (a @ right).reshape(K, p, n, n)


def euler_substeps(lam: np.ndarray, dt: float, max_substep: float | None) -> int:
    """Number of Euler sub-steps: ``ceil(dt / max_substep)``; refuses if that is unstable.

    ``lam`` are the eigenvalues (1/s, negative) of ``C⁻¹A`` over all operating points.
    """
    m = 1 if max_substep is None else max(1, math.ceil(dt / max_substep - 1e-9))
    h = dt / m
    rho = float(np.max(np.abs(1.0 + h * lam)))
    if rho >= 1.0:
        h_max = 2.0 / float(-lam.min())
        raise UnstableDiscretisation(
            f"explicit Euler is unstable: spectral radius {rho:.3g} of I + h·C⁻¹A at h = {h:g} s "
            f"(stable only for h < {h_max:.3g} s); use method zoh, or a sub-step below {h_max:.3g} s"
        )
    return m


def discretise(cont: Continuous, dt: float, method: str = "zoh", max_substep: float | None = None) -> Discrete:
    """Discretise a batch of continuous systems with step ``dt`` (s); derivatives if ``cont`` has them."""
    s, At, lam, Qm = _eig(cont)
    K, n, _ = cont.A.shape
    eye = np.eye(n)
    with_d = cont.dA is not None
    if with_d:
        r = cont.dc / (2.0 * cont.c)  # ds/s per parameter, (p, n)
        dAt = cont.dA / np.outer(s, s) - At[:, None] * (r[None, :, :, None] + r[None, :, None, :])
    if method == "zoh":
        x = lam * dt
        # Φ − I from expm1 so that slow modes (Φ ≈ I) keep their digits in Γ = (Φ − I) H
        Em1 = (Qm * np.expm1(x)[:, None, :]) @ np.swapaxes(Qm, -1, -2)
        PmI = Em1 / s[:, None] * s[None, :]
        Phi = PmI + eye
        m = 1
        if with_d:
            # divided differences of exp(λ dt) w.r.t. λ, (e^a − e^b)/(a − b) · dt, written as
            # e^max(a,b) · (1 − e^−|a−b|)/|a−b| so that neither overflows nor cancels
            ad = np.abs(x[:, :, None] - x[:, None, :])
            small = ad < 1e-10
            ratio = np.where(small, 1.0 - ad / 2.0, -np.expm1(-ad) / np.where(small, 1.0, ad))
            Dd = dt * np.exp(np.maximum(x[:, :, None], x[:, None, :])) * ratio
            Qt = np.swapaxes(Qm, -1, -2)
            dE = sandwich(Qm, sandwich(Qt, dAt, Qm) * Dd[:, None], Qt)
            dPhi = -r[None, :, :, None] * Phi[:, None] + dE / s[:, None] * s[None, :] + Phi[:, None] * r[None, :, None, :]
    elif method == "euler":
        m = euler_substeps(lam, dt, max_substep)
        h = dt / m
        F = cont.A / cont.c[:, None]
        Phi1 = eye + h * F
        PmI = h * F
        for _ in range(m - 1):  # Φ1^(k+1) − I = Φ1 (Φ1^k − I) + (Φ1 − I), without cancellation
            PmI = Phi1 @ PmI + h * F
        Phi = PmI + eye
        if with_d:
            dF = (cont.dA - cont.dc[None, :, :, None] * F[:, None]) / cont.c[None, None, :, None]
            dPhi1 = h * dF
            if m == 1:
                dPhi = dPhi1
            else:
                pows = [np.broadcast_to(eye, Phi1.shape)]
                for _ in range(m - 1):
                    pows.append(pows[-1] @ Phi1)
                dPhi = sum(pows[i][:, None] @ dPhi1 @ pows[m - 1 - i][:, None] for i in range(m))
    else:
        raise ValueError(f"unknown discretisation method {method!r} (zoh, euler)")
    H = np.linalg.solve(cont.A, cont.W)
    Gam = PmI @ H
    out = Discrete(Phi=Phi, Gam=Gam, substeps=m)
    if with_d:
        # one factorisation per operating point for all parameters: stack the right-hand sides
        rhs = cont.dW - cont.dA @ H[:, None]  # (K, p, n, m)
        p_, m_ = rhs.shape[1], rhs.shape[3]
        dH = np.linalg.solve(cont.A, rhs.transpose(0, 2, 1, 3).reshape(K, n, p_ * m_))
        dH = dH.reshape(K, n, p_, m_).transpose(0, 2, 1, 3)
        out.dPhi = dPhi
        out.dGam = dPhi @ H[:, None] + PmI[:, None] @ dH
    return out
