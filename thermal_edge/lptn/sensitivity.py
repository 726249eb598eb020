"""Forward sensitivities ``S_k = ∂T_k/∂θ`` of a simulated run (paper eqs. 35–37).

``S[k+1] = M_k S[k] + X_k`` with the transition ``M_k = Φ + Γ_P ∂P/∂T`` of the simulation and
the forcing ``X_k = dΦ T_k + dΓ w_k + Γ_P ∂P/∂θ``. Two exact ways, chosen per run of steps:

* **Held inputs.** Over a run where every input is the same (a drive cycle's segment, a test
  bench's set point) and the losses are affine in temperature, ``M`` is constant and similar to
  a symmetric matrix (``Φ`` is, and the copper-loss feedback adds ``diag(phi) Qᵀ C⁻¹ Δ Q`` in its
  modal basis), so ``M = W diag(μ) W⁻¹`` with real ``μ``. The temperatures follow
  ``ξ_i = ξ∞ + μ^i δ`` in that basis and the forcing is affine in them, so the whole run has the
  closed form ``σ_k = μ^k σ_0 + Σ_b G_b DD_k(μ, μ_b)`` with the divided differences
  ``DD_k(x, y) = Σ_{i<k} x^(k−1−i) y^i = (x^k − y^k)/(x − y)``. Separating the terms of
  well-apart eigenvalue pairs, the chosen rows of ``S`` at every step of the run are one product
  of the powers ``μ^k`` with per-mode coefficients: about ``2·n·rows·p`` flops a step instead of
  the ``4·n²·p`` of forcing and recursion. Close pairs keep their divided differences.
* **Step by step** otherwise: the forcing for a block of steps as products per operating point
  (in the modal basis of :class:`~thermal_edge.lptn.discretise.Discrete`), then the recursion.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from .discretise import Discrete

#: shortest run of held inputs worth the closed form (its set-up costs about 100 steps)
MIN_HELD = 64
#: eigenvalue pairs closer than this keep their divided differences (cancellation otherwise)
CLOSE = 1e-3
BLOCK = 512  # time steps per block of the step-by-step forcing

#: losses (B, nl) and ∂P/∂θ (B, nl, p) at temperatures (B, n) with the inputs of one step
LossAt = Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]


def divided_powers(x: np.ndarray, y: np.ndarray, k: np.ndarray) -> np.ndarray:
    """``DD_k(x, y) = Σ_{i<k} x^(k−1−i) y^i`` for positive ``x``, ``y`` (broadcast), without cancellation.

    >>> float(divided_powers(np.array(0.5), np.array(0.25), np.array(3)))
    0.4375
    >>> float(divided_powers(np.array(0.5), np.array(0.5), np.array(3)))
    0.75
    """
    a, b = np.log(x), np.log(y)
    top = np.maximum(a, b)
    d = np.abs(a - b)
    same = d < 1e-300
    ratio = np.where(same, k, np.expm1(-k * d) / np.expm1(-np.where(same, 1.0, d)))
    with np.errstate(under="ignore"):
        return np.exp((k - 1) * top) * ratio


class Sensitivities:
    """The sensitivity recursion of one simulated run.

    Parameters
    ----------
    disc : Discrete
        Discretisation with modal derivatives at every operating point.
    ops : ndarray (N-1,)
        Operating point of each step.
    mats, mi : list of ndarray, list of int
        Distinct transition matrices ``M`` and each step's index into them.
    T : ndarray (N, n)
        Simulated temperatures, °C.
    w : ndarray (N, m)
        Inputs of ``Γ`` at each sample (boundary temperatures, losses at ``T``).
    dPdth : ndarray (N, nl, p)
        ``∂P/∂θ`` along the run, W per parameter unit.
    nb : int
        Number of boundary inputs (the first columns of ``w``).
    """

    def __init__(self, disc: Discrete, ops: np.ndarray, mats: list[np.ndarray], mi: list[int], T: np.ndarray,
                 w: np.ndarray, dPdth: np.ndarray, nb: int) -> None:
        assert disc.dPhit is not None and disc.dGamt is not None and disc.Q is not None and disc.s is not None
        self.d, self.ops, self.mats, self.mi = disc, ops, mats, mi
        self.T, self.w, self.dPdth, self.nb = T, w, dPdth, nb
        self.n, self.p = T.shape[1], disc.dPhit.shape[1]
        self._stacked: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    # -- the forcing, in the modal basis of an operating point ------------------------------
    def _stack(self, o: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if o not in self._stacked:
            d, n, p = self.d, self.n, self.p
            assert d.dPhit is not None and d.Q is not None and d.s is not None
            GPt = d.Q[o].T @ (d.s[:, None] * d.Gam[o][:, self.nb:])  # V⁻¹ Γ_P
            self._stacked[o] = (d.dPhit[o].reshape(p * n, n).T, GPt, np.swapaxes(d.Zh[o], 0, 1))
        return self._stacked[o]

    def forcing(self, o: int, T: np.ndarray, w: np.ndarray, dPdth: np.ndarray) -> np.ndarray:
        """``V⁻¹ X`` (B, n, p) at operating point ``o`` for temperatures ``T`` (B, n), inputs ``w``.

        ``dΦ T + dΓ w = V (dPhit (V⁻¹ T + Ht w) − phi ∘ Zh (dg ∘ Yt w))`` (see
        :class:`~thermal_edge.lptn.discretise.Discrete`).
        """
        d = self.d
        assert d.Q is not None and d.s is not None and d.Ht is not None and d.Yt is not None and d.dg is not None
        dPhiT, GPt, ZhT = self._stack(o)
        y = (T * d.s) @ d.Q[o] + w @ d.Ht[o].T
        X = (y @ dPhiT).reshape(len(T), self.p, self.n)
        X -= d.phi[o] * (((w @ d.Yt[o].T)[:, None, :] * d.dg[o]) @ ZhT)
        X = X.swapaxes(1, 2)
        if np.any(dPdth):
            X += GPt @ dPdth
        return X

    # -- runs ---------------------------------------------------------------------------------
    def run(self, held: np.ndarray, loss_at: LossAt | None, rows: np.ndarray | None) -> np.ndarray:
        """``S`` (N, rows, p) (all nodes when ``rows`` is None).

        ``held[k]`` is True where the inputs of step ``k`` equal those of step ``k − 1``;
        ``loss_at`` (None: no closed form) evaluates the losses at any temperatures.
        """
        N = self.T.shape[0]
        steps = N - 1
        keep = np.arange(self.n) if rows is None else np.asarray(rows, dtype=int)
        S = np.zeros((N, len(keep), self.p))
        s = np.zeros((self.n, self.p))
        starts = np.nonzero(~held[:steps])[0] if steps > 0 else np.zeros(0, dtype=int)
        bounds = list(starts) + [steps]
        pending = 0  # first step not yet propagated
        for a, b in zip(bounds[:-1], bounds[1:]):
            if loss_at is None or b - a < MIN_HELD:
                continue
            if pending < a:
                s = self._steps(pending, a, s, S, keep)
                pending = a
            closed = self._held_run(a, b, s, loss_at, keep)
            if closed is not None:
                S[a + 1: b + 1], s = closed
                pending = b
        if pending < steps:
            self._steps(pending, steps, s, S, keep)
        return S

    def _steps(self, a: int, b: int, s: np.ndarray, S: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Steps ``a .. b−1`` one by one from ``S[a] = s`` (all nodes); fills ``S[a+1 .. b]``."""
        d = self.d
        assert d.Q is not None and d.s is not None
        mats, mi, ops = self.mats, self.mi, self.ops
        full = len(keep) == self.n and np.array_equal(keep, np.arange(self.n))
        for c in range(a, b, BLOCK):
            e = min(c + BLOCK, b)
            X = np.empty((e - c, self.n, self.p))
            ob = ops[c:e]
            for o in np.unique(ob):
                sel = np.nonzero(ob == o)[0]
                Xt = self.forcing(o, self.T[c + sel], self.w[c + sel], self.dPdth[c + sel])
                X[sel] = np.matmul(d.Q[o] / d.s[:, None], Xt)  # back to node coordinates
            for k in range(c, e):
                s = mats[mi[k]] @ s
                s += X[k - c]
                if full:
                    S[k + 1] = s
                else:
                    S[k + 1] = s[keep]
        return s

    def _held_run(self, a: int, b: int, s0: np.ndarray, loss_at: LossAt,
                  keep: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Closed form over the held run of steps ``a .. b−1`` (see the module docstring).

        Returns the chosen rows of ``S[a+1 .. b]`` and the full ``S[b]``, or None where the
        closed form does not apply (transition not symmetrisable, an eigenvalue outside (0, 1)).
        """
        d, n = self.d, self.n
        assert d.Q is not None and d.s is not None and d.phi is not None
        o = int(self.ops[a])
        Q, sv, ph = d.Q[o], d.s, d.phi[o]
        V, Vi = Q / sv[:, None], Q.T * sv  # modal basis of Φ and its inverse
        Mt = Vi @ self.mats[self.mi[a]] @ V
        r = np.sqrt(ph)
        Sym = Mt * r[None, :] / r[:, None]
        if np.max(np.abs(Sym - Sym.T)) > 1e-9 * np.max(np.abs(Sym)):
            return None  # a loss law couples nodes: the closed-loop transition is not symmetric
        mu, Q2 = np.linalg.eigh((Sym + Sym.T) / 2.0)
        if mu.min() < -1e-12 or mu.max() >= 1.0:
            return None
        # modes far faster than the step (e^(λ dt) below round-off) are zero after one step
        mu = np.maximum(mu, 1e-300)
        Wt, Wti = r[:, None] * Q2, Q2.T / r[None, :]  # modal -> closed-loop modes ξ, and back
        Om, Xi = V @ Wt, Wti @ Vi  # ξ -> node temperatures, node temperatures -> ξ
        # the forcing is affine in T: probe it at T = 0 and at each closed-loop mode
        probes = np.vstack([np.zeros(n), Om.T])
        P, dPdth = loss_at(a, probes)
        wp = np.concatenate([np.broadcast_to(self.w[a, : self.nb], (n + 1, self.nb)), P], axis=1)
        Xp = np.einsum("ab,kbp->kap", Wti, self.forcing(o, probes, wp, dPdth))
        bbar = Xp[0]
        F = np.moveaxis(Xp[1:] - bbar, 0, 1)  # F[a, b, j]: ξ_b -> forcing of mode a
        # temperatures in ξ: ξ_i = ξ∞ + μ^i δ
        f = Xi @ (d.Gam[o] @ wp[0])
        xinf = f / (1.0 - mu)
        delta = Xi @ self.T[a] - xinf
        G = np.empty((n, n + 1, self.p))
        G[:, :n] = F * delta[None, :, None]
        G[:, n] = np.einsum("abj,b->aj", F, xinf) + bbar  # the constant part, a mode with μ = 1
        mue = np.append(mu, 1.0)
        sig0 = Xi @ s0
        C = Om[keep]  # ξ -> chosen rows
        nr, p, L = len(keep), self.p, b - a
        gap = np.abs(mu[:, None] - mue[None, :])
        close = gap < CLOSE
        R = np.where(close, 0.0, 1.0 / np.where(close, 1.0, mu[:, None] - mue[None, :]))
        GR = G * R[:, :, None]
        coef = np.zeros((n + 1, nr, p))
        coef[:n] += C.T[:, :, None] * (GR.sum(axis=1) + sig0)[:, None, :]
        coef -= np.einsum("ca,abj->bcj", C, GR)
        k = np.arange(1, L + 1, dtype=float)[:, None]
        with np.errstate(under="ignore"):
            out = np.exp(k * np.log(mue)[None, :]) @ coef.reshape(n + 1, nr * p)
        ia, ib = np.nonzero(close)
        if len(ia):
            coefc = C.T[ia][:, :, None] * G[ia, ib][:, None, :]  # (pairs, nr, p)
            out += divided_powers(mu[ia][None, :], mue[ib][None, :], k) @ coefc.reshape(len(ia), nr * p)
        # the full state at the end of the run
        with np.errstate(under="ignore"):
            sigL = mu[:, None] ** L * sig0 + np.einsum("abj,ab->aj", G, divided_powers(mu[:, None], mue[None, :], float(L)))
        return out.reshape(L, nr, p), Om @ sigL


def held_steps(env: dict[str, object], steps: int) -> np.ndarray:
    """``held[k]``: every input series of ``env`` has the same value at step ``k`` as at ``k − 1``."""
    held = np.ones(steps, dtype=bool)
    if steps:
        held[0] = False
    for v in env.values():
        a = np.asarray(v)
        if a.ndim == 1 and len(a) > steps >= 2:
            held[1:] &= a[1:steps] == a[: steps - 1]
    return held

