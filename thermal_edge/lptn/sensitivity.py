"""Forward sensitivities ``S_k = ∂T_k/∂θ`` of a simulated run (paper eqs. 35–37).

``S[k+1] = M_k S[k] + X_k`` with the transition ``M_k = Φ + Γ_P ∂P/∂T`` of the simulation and
the forcing ``X_k = dΦ T_k + dΓ w_k + Γ_P ∂P/∂θ``. Two exact ways, chosen per run of steps:

* **Held inputs.** Over a run where every input is the same (a drive cycle's segment, a test
  bench's set point) and the losses are affine in temperature, ``M`` is constant and similar to
  a symmetric matrix (``Φ`` is, and the copper-loss feedback adds ``diag(phi) Qᵀ C⁻¹ Δ Q`` in its
  modal basis), so ``M = W diag(μ) W⁻¹`` with real ``μ``. The temperatures follow
  ``ξ_i = ξ∞ + μ^i δ`` in that basis and the forcing is affine in them (``dΦ`` acts on every
  node, the losses' part only on the nodes their laws read, found by probing there), so the
  whole run has the closed form ``σ_k = μ^k σ_0 + Σ_b G_b DD_k(μ, μ_b)`` with the divided
  differences ``DD_k(x, y) = Σ_{i<k} x^(k−1−i) y^i = (x^k − y^k)/(x − y)``. Separating the terms
  of well-apart eigenvalue pairs, the chosen rows of ``S`` at every step of the run are one
  product of the powers ``μ^k`` with per-mode coefficients: about ``2·n·rows·p`` flops a step
  instead of the ``4·n²·p`` of forcing and recursion. Close pairs keep their divided
  differences. Runs that meet a set point again share its eigendecomposition and the forcing's
  linear part (``p·n²`` numbers); each run adds only matrix-vector products.
* **Step by step** otherwise: the forcing for a block of steps as products per operating point
  (in the modal basis of :class:`~thermal_edge.lptn.discretise.DiscreteDerivatives`; the Daleckii–Krein
  form row by row at a ramp's operating points), then the recursion.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from .discretise import DiscreteDerivatives

#: shortest run of held inputs worth the closed form (its set-up costs about as much as 60 steps)
MIN_HELD = 64
#: eigenvalue pairs closer than this keep their divided differences: split over the power
#: basis a pair loses about 1e-16/gap of relative accuracy to cancellation
CLOSE = 1e-6
BLOCK = 256  # time steps per block of the step-by-step forcing
#: the powers μ^k of a held run are built in blocks of this many steps, ``μ^(jB + i) = μ^(jB) μ^i``:
#: ``exp`` for one block and the block offsets, one product for the rest
POW_BLOCK = 64
#: floor of the exponents of both factors: their product stays above e^−708 (no subnormals, which
#: would slow the product of the basis with the coefficients), and e^−350 is far below round-off
#: of any term that matters
LOG_FLOOR = -350.0
#: an operating point used by fewer stepped steps than this gets the Daleckii–Krein form vector by
#: vector instead of its dense derivative (a ramp: a new speed every step)
FEW_STEPS = 8

#: a function of steps (B,) and temperatures (B, n) with the inputs of those steps: the losses
#: (B, nl) in W, or ``∂P/∂θ`` (B, nl, p) in W per parameter unit
AtSteps = Callable[[np.ndarray, np.ndarray], np.ndarray]

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
    disc : DiscreteDerivatives
        Discretisation with modal derivatives at every operating point.
    ops : ndarray (N-1,)
        Operating point of each step.
    mats, mi : list of ndarray, list of int
        Distinct transition matrices ``M`` and each step's index into them.
    T : ndarray (N, n)
        Simulated temperatures, °C.
    U : ndarray (N, nb)
        Boundary temperatures, °C.
    P : ndarray (N, nl)
        Losses along the run, W.
    losses, loss_theta : callable
        The losses and ``∂P/∂θ`` at any steps and temperatures (see :data:`AtSteps`).
    loss_nodes : ndarray of int
        The nodes whose temperatures the loss laws read.
    """

    def __init__(self, disc: DiscreteDerivatives, ops: np.ndarray, mats: list[np.ndarray], mi: list[int], T: np.ndarray,
                 U: np.ndarray, P: np.ndarray, losses: AtSteps, loss_theta: AtSteps, loss_nodes: np.ndarray) -> None:
        self.d, self.ops, self.mats, self.mi = disc, ops, mats, mi
        self.T, self.U, self.P, self.nb = T, U, P, U.shape[1]
        self.losses, self.loss_theta, self.loss_nodes = losses, loss_theta, np.asarray(loss_nodes, dtype=int)
        self.n, self.p = T.shape[1], disc.dg.shape[1]

    # -- the forcing, in the modal basis of an operating point ------------------------------
    def forcing(self, o: int | np.ndarray, T: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``V⁻¹ (dΦ T + dΓ w)`` (B, n, p) for temperatures ``T`` (B, n) and inputs ``w`` (B, m) of
        ``Γ`` at operating point ``o`` (one for all rows, or one per row), in the modal basis of
        ``Φ`` there (:meth:`~thermal_edge.lptn.discretise.DiscreteDerivatives.forcing`). The losses' own
        dependence on θ, ``Γ_P ∂P/∂θ``, is the callers' to add.
        """
        d = self.d
        _, Vi = d.basis(o)
        # y = V⁻¹ T + Ht w and v = Yt w, one row per step
        y = np.einsum("...ac,...c->...a", Vi, T) + np.einsum("...am,...m->...a", d.Ht[o], w)
        return d.forcing(o, y, np.einsum("...em,...m->...e", d.Yt[o], w))

    # -- runs ---------------------------------------------------------------------------------
    def run(self, held: np.ndarray, closed: bool, rows: np.ndarray | None) -> np.ndarray:
        """``S`` (N, rows, p) (all nodes when ``rows`` is None).

        ``held[k]`` is True where the inputs of step ``k`` equal those of step ``k − 1``;
        ``closed`` allows the closed form over held runs (the losses are affine in temperature).
        """
        N = self.T.shape[0]
        steps = N - 1
        keep = np.arange(self.n) if rows is None else np.asarray(rows, dtype=int)
        S = np.zeros((N, len(keep), self.p))
        s = np.zeros((self.n, self.p))
        starts = np.nonzero(~held[:steps])[0] if steps > 0 else np.zeros(0, dtype=int)
        bounds = list(starts) + [steps]
        runs = [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b - a >= MIN_HELD] if closed else []
        forms = self._held_runs(runs, keep) if runs else []
        stepped = np.ones(steps, dtype=bool)
        for (a, b), form in zip(runs, forms):
            stepped[a:b] &= form is None
        # the steps the recursion takes one by one, their forcing BLOCK steps at a time (across
        # the gaps between held runs), consumed in order
        ks = np.nonzero(stepped)[0]
        uo, count = np.unique(self.ops[ks], return_counts=True)
        self.d.build_dphit(uo[count >= FEW_STEPS])  # the dense derivatives the stepping needs, built together
        blocks = (self._forcing(ks[c: c + BLOCK]) for c in range(0, len(ks), BLOCK))
        X = np.zeros((0, self.n, self.p))
        used = 0  # rows of X consumed
        mats, mi = self.mats, self.mi
        full = rows is None

        def step(a: int, b: int, s: np.ndarray) -> np.ndarray:
            """Steps ``a .. b−1`` from ``S[a] = s`` (all nodes); fills ``S[a+1 .. b]``."""
            nonlocal X, used
            while a < b:
                if used == len(X):
                    X, used = next(blocks), 0
                m = min(b - a, len(X) - used)
                Xb = X[used: used + m]  # becomes S[a + 1 .. a + m] in place
                for i in range(m):
                    Xb[i] += mats[mi[a + i]] @ s
                    s = Xb[i]
                S[a + 1: a + m + 1] = Xb if full else Xb[:, keep]
                used += m
                a += m
            return s

        pending = 0  # first step not yet propagated
        longest = max((b - a for a, b in runs), default=0)
        work = np.empty((2 * self.n + 1, -(-longest // POW_BLOCK) * POW_BLOCK))
        for (a, b), form in zip(runs, forms):
            if form is None:
                continue
            s = form.apply(step(pending, a, s), S[a + 1: b + 1], work)
            pending = b
        step(pending, steps, s)
        return S

    def _forcing(self, ks: np.ndarray) -> np.ndarray:
        """The forcing ``X`` (len(ks), n, p) of the recursion at steps ``ks``, node coordinates."""
        d = self.d
        X = np.empty((len(ks), self.n, self.p))
        ob = self.ops[ks]
        w = np.concatenate([self.U[ks], self.P[ks]], axis=1)
        dP = self.loss_theta(ks, self.T[ks])
        uo, inv, count = np.unique(ob, return_inverse=True, return_counts=True)
        few = np.nonzero(count[inv] < FEW_STEPS)[0]  # operating points used by a few steps (a ramp)
        if len(few):
            X[few] = self.forcing(ob[few], self.T[ks[few]], w[few])
        for o in uo[count >= FEW_STEPS]:
            sel = np.nonzero(ob == o)[0]
            X[sel] = self.forcing(o, self.T[ks[sel]], w[sel])
        X = np.matmul(d.Q[ob], X)  # back to node coordinates (V = diag(1/s) Q)
        X /= d.s[:, None]
        if np.any(dP):  # Γ_P ∂P/∂θ
            X += d.Gam[ob][:, :, self.nb:] @ dP
        return X

    def _held_runs(self, runs: list[tuple[int, int]], keep: np.ndarray) -> list[_HeldRun | None]:
        """The closed form (see the module docstring) of each held run ``(a, b)`` of steps ``a .. b−1``.

        None where it does not apply: the closed-loop transition is not symmetrisable (a loss law
        couples nodes) or has an eigenvalue outside (0, 1).
        """
        d, n, p = self.d, self.n, self.p
        a_ = np.array([a for a, _ in runs])
        o_ = self.ops[a_]
        L = np.array([b - a for a, b in runs])
        # runs with the same transition (operating point and current: a set point met again)
        # share its modes and the part of the forcing that is linear in temperature
        seen: dict[bytes, int] = {}
        ui = np.array([seen.setdefault(self.mats[self.mi[a]].tobytes(), len(seen)) for a in a_])
        rep = np.unique(ui, return_index=True)[1]
        members = np.split(np.argsort(ui, kind="stable"), np.cumsum(np.bincount(ui))[:-1])
        m = self._modes(o_[rep], np.stack([self.mats[self.mi[a]] for a in a_[rep]]))
        Xf, w0 = self._probe_forcing(a_, o_)
        # per run: ξ_k = ξ∞ + μ^k δ
        mur = m.mu[ui]
        xinf = (m.Xi[ui] @ (d.Gam[o_] @ w0[:, :, None]))[..., 0] / (1.0 - mur)
        delta = (m.Xi[ui] @ self.T[a_][:, :, None])[..., 0] - xinf
        with np.errstate(under="ignore"):
            muL = mur ** L[:, None]
            mu1 = mur ** (L[:, None] - 1)
        # mode pairs (b = n: the constant forcing, μ = 1): R = 1/(μ_a − μ_b) splits a well-apart
        # pair's divided differences over the power basis; close pairs keep theirs, and a mode
        # with itself has DD_k(μ, μ) = k μ^(k−1)
        diff = m.mu[:, :, None] - np.concatenate([m.mu, np.ones((len(rep), 1))], axis=1)[:, None, :]
        close = np.abs(diff) < CLOSE
        R = np.where(close, 0.0, 1.0 / np.where(close, 1.0, diff))
        dg = np.arange(n)
        close[:, dg, dg] = False
        # F_u[j, a, b]: the forcing of parameter j on mode a per unit of mode b; only its products
        # with the runs' vectors leave the loop (all small arrays: per transition, not per run)
        nr = len(keep)
        Fx, g1, g2 = np.empty((len(runs), n, p)), np.empty((len(runs), n, p)), np.empty((len(runs), n, p))
        CFR, diagF = np.empty((len(rep), p, nr, n)), np.empty((len(rep), n, p))
        Fcl: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        has_close = close.any(axis=(1, 2))
        # the losses' part of the forcing per unit T at each loss node, in the modal basis of Φ (pn, tv)
        tv = self.loss_nodes
        Bl = (Xf[rep, 1:] - Xf[rep, :1]).transpose(0, 3, 2, 1).reshape(len(rep), p * n, len(tv))
        Omt = m.Om[:, tv]
        for u, sel in enumerate(members):
            # V⁻¹ X = (dΦ̃ V⁻¹ + Bl E_tv) T, T = V rQ2 ξ: F = Q2r (dΦ̃ rQ2 + Bl Om[tv])
            Fu = d.dphit(int(o_[rep[u]])).reshape(p * n, n) @ m.rQ2[u]
            Fu += Bl[u] @ Omt[u]
            Fu = m.Q2r[u] @ Fu.reshape(p, n, n)
            diagF[u] = Fu[:, dg, dg].T
            if has_close[u]:
                ia, ib = np.nonzero(close[u, :, :n])
                Fcl[u] = (ia, ib, Fu[:, ia, ib])
            Fx[sel] = (Fu.reshape(p * n, n) @ xinf[sel].T).reshape(p, n, -1).transpose(2, 1, 0)
            Fu *= R[u, :, :n]
            CFR[u] = m.Om[u, keep] @ Fu
            G = (Fu.reshape(p * n, n) @ np.concatenate([delta[sel], delta[sel] * muL[sel]]).T).reshape(p, n, -1)
            g1[sel], g2[sel] = G[:, :, : len(sel)].transpose(2, 1, 0), G[:, :, len(sel):].transpose(2, 1, 0)
        h = Fx + np.matmul(m.Q2r[ui], Xf[:, 0])  # the constant forcing of each mode, F ξ∞ + X(0)
        # coefficients of the chosen rows on the time basis μ_b^k (b ≤ n), k μ_a^(k−1) (a < n)
        C = m.Om[ui][:, keep]  # ξ -> chosen rows
        Ct = np.swapaxes(C, 1, 2)[..., None]  # (r, a, rows, 1)
        Rn = R[ui][:, :, n]
        coef = np.empty((len(runs), 2 * n + 1, nr, p))
        coef[:, :n] = -CFR[ui].transpose(0, 3, 2, 1) * delta[:, :, None, None]  # μ_b^k of F δ_b
        coef[:, n] = -(C * Rn[:, None, :]) @ h  # μ_n^k = 1 of the constant forcing
        coef[:, :n] += Ct * (g1 + Rn[:, :, None] * h)[:, :, None, :]  # μ_a^k of both
        coef[:, n + 1:] = Ct * (diagF[ui] * delta[:, :, None])[:, :, None, :]
        # σ_L without the part of σ_0, in ξ: the same sums at k = L
        endG = muL[:, :, None] * g1 - g2 + (L[:, None] * mu1 * delta)[:, :, None] * diagF[ui]
        with np.errstate(under="ignore"):
            endG += divided_powers(mur, np.ones_like(mur), L[:, None].astype(float))[:, :, None] * h
        # close pairs (none in most models): their divided differences at the end of the run, and
        # as extra terms for every step
        extra: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = [None] * len(runs)
        for u, (ia, ib, Fab) in Fcl.items():
            an = np.nonzero(close[u, :, n])[0]  # modes close to μ = 1
            for i in members[u]:
                cc = (Fab * delta[i, ib]).T  # pairs b < n (pair, p)
                with np.errstate(under="ignore"):
                    endG[i, ia] += divided_powers(mur[i, ia], mur[i, ib], float(L[i]))[:, None] * cc
                pa, pb = np.concatenate([ia, an]), np.concatenate([ib, np.full(len(an), n)])
                cc = np.concatenate([cc, h[i, an]])
                extra[i] = (pa, pb, C[i].T[pa][:, :, None] * cc[:, None, :])
        mue = np.concatenate([mur, np.ones((len(runs), 1))], axis=1)
        return [_HeldRun(mue[i], coef[i], C[i], m.Om[u], m.Xi[u], muL[i], endG[i], extra[i]) if m.ok[u] else None
                for i, u in enumerate(ui)]

    def _modes(self, ops: np.ndarray, M: np.ndarray) -> _Modes:
        """Eigendecomposition of the transitions ``M`` (U, n, n) at operating points ``ops`` (U,):
        in the modal basis of ``Φ``, ``diag(r)^-1 V⁻¹ M V diag(r)`` with ``r = √phi`` is
        symmetric (up to round-off) when no loss law couples nodes."""
        d = self.d
        V, Vi = d.basis(ops)  # modal basis of Φ at each operating point
        r = np.sqrt(d.phi[ops])
        Sym = (Vi @ M @ V) * r[:, None, :] / r[:, :, None]
        asym = np.max(np.abs(Sym - np.swapaxes(Sym, -1, -2)), axis=(1, 2)) / np.max(np.abs(Sym), axis=(1, 2))
        mu, Q2 = np.linalg.eigh((Sym + np.swapaxes(Sym, -1, -2)) / 2.0)
        ok = (asym < 1e-9) & (mu.min(axis=1) > -1e-12) & (mu.max(axis=1) < 1.0)
        rQ2 = r[:, :, None] * Q2
        Q2r = np.swapaxes(Q2, -1, -2) / r[:, None, :]
        # modes far faster than the step (e^(λ dt) below round-off) are zero after one step
        return _Modes(mu=np.maximum(mu, 1e-300), ok=ok, rQ2=rQ2, Q2r=Q2r, Om=V @ rQ2, Xi=Q2r @ Vi)

    def _probe_forcing(self, a_: np.ndarray, o_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The forcing ``V⁻¹ X`` (runs, 1 + tv, n, p) of held runs starting at steps ``a_`` (at
        operating points ``o_``) with T = 0 and with a unit step at each loss node, the
        temperature entering ``dΦ`` kept at 0: the constant part and the losses' part per kelvin;
        and the inputs ``w`` (runs, m) of ``Γ`` at T = 0."""
        d, n, p = self.d, self.n, self.p
        tv = self.loss_nodes
        nt = 1 + len(tv)
        probes = np.zeros((len(a_), nt, n))
        probes[:, np.arange(1, nt), tv] = 1.0
        ks, flat = np.repeat(a_, nt), probes.reshape(-1, n)
        P = self.losses(ks, flat).reshape(len(a_), nt, -1)
        dPdth = self.loss_theta(ks, flat).reshape(len(a_), nt, -1, p)
        wp = np.concatenate([np.broadcast_to(self.U[a_][:, None], (len(a_), nt, self.nb)), P], axis=-1)
        d.build_dphit(o_)  # dense derivatives at the runs' operating points, built together
        Xf = np.empty((len(a_), nt, n, p))
        for o in np.unique(o_):
            sel = np.nonzero(o_ == o)[0]
            X = self.forcing(int(o), np.zeros((len(sel) * nt, n)), wp[sel].reshape(len(sel) * nt, -1))
            GPt = d.basis(int(o))[1] @ d.Gam[o][:, self.nb:]  # V⁻¹ Γ_P
            dP = dPdth[sel].reshape(len(sel) * nt, -1, p)
            X += (GPt @ dP.transpose(1, 0, 2).reshape(dP.shape[1], -1)).reshape(n, -1, p).transpose(1, 0, 2)
            Xf[sel] = X.reshape(len(sel), nt, n, p)
        return Xf, wp[:, 0]


class _Modes(NamedTuple):
    """Closed-loop modes ``ξ`` of transitions (leading axis): eigenvalues ``mu`` and whether the
    closed form applies (``ok``); ``rQ2``/``Q2r`` map ``ξ`` to the modal basis of ``Φ`` and back,
    ``Om``/``Xi`` to node temperatures and back."""

    mu: np.ndarray
    ok: np.ndarray
    rQ2: np.ndarray
    Q2r: np.ndarray
    Om: np.ndarray
    Xi: np.ndarray


class _HeldRun:
    """One held run in closed form: ``σ_k = μ^k σ_0 + Σ_b G[:, b] DD_k(μ, μ_b)`` with ``μ_n = 1``.

    ``coef`` (2n+1, rows, p) are the coefficients of the chosen rows on the time basis ``μ^k``
    (``mue``, n+1 modes) and ``k μ^(k−1)`` without the part of ``σ_0``; ``extra`` holds close
    pairs with their own divided differences. :meth:`apply` adds the part of ``σ_0`` and
    evaluates every step.
    """

    def __init__(self, mue: np.ndarray, coef: np.ndarray, C: np.ndarray, Om: np.ndarray, Xi: np.ndarray,
                 muL: np.ndarray, endG: np.ndarray, extra: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> None:
        self.mue, self.coef, self.C, self.Om, self.Xi, self.muL, self.endG, self.extra = mue, coef, C, Om, Xi, muL, endG, extra
        self.logmue = np.log(mue)

    def apply(self, s0: np.ndarray, out: np.ndarray, work: np.ndarray) -> np.ndarray:
        """Fill ``out`` (L, rows, p) with the chosen rows of ``S`` over the run of ``L`` steps from
        ``S`` (n, p) at its start; return the full ``S`` at its end. ``work`` is scratch space of
        at least (2n+1, L rounded up to :data:`POW_BLOCK`), shared by the runs (fresh memory
        costs a page fault per 4 KiB)."""
        L, nr, p = out.shape
        sig0 = self.Xi @ s0
        n = len(sig0)
        coef = self.coef.reshape(2 * n + 1, nr * p).copy()
        coef[:n] += (self.C.T[:, :, None] * sig0[:, None, :]).reshape(n, nr * p)  # μ^k σ_0
        # the basis [μ^k, k μ^(k−1)] at k = 1 .. L, in place, one row per function (contiguous
        # passes); μ^k in blocks: μ^(jB + i) = μ^(jB) μ^i, i = 1 .. B
        k = np.arange(1.0, L + 1.0)
        nb = -(-L // POW_BLOCK)
        blocks = work[: n + 1, : nb * POW_BLOCK].reshape(n + 1, nb, POW_BLOCK)
        assert np.may_share_memory(blocks, work)  # a view: the product below fills work
        first = np.exp(np.maximum(self.logmue[:, None] * np.arange(1.0, POW_BLOCK + 1.0), LOG_FLOOR))
        offset = np.exp(np.maximum(self.logmue[:, None] * (POW_BLOCK * np.arange(nb)), LOG_FLOOR))
        np.multiply(offset[:, :, None], first[:, None, :], out=blocks)
        basis = work[:, :L]
        Pw = basis[: n + 1]
        basis[n + 1:, 0] = 1.0
        np.multiply(Pw[:n, :-1], k[1:], out=basis[n + 1:, 1:])
        rows = out.reshape(L, nr * p)
        np.matmul(basis.T, coef, out=rows)
        if self.extra is not None:
            ia, ib, cc = self.extra
            rows += divided_powers(self.mue[ia][None, :], self.mue[ib][None, :], k[:, None]) @ cc.reshape(len(ia), nr * p)
        return self.Om @ (self.muL[:, None] * sig0 + self.endG)


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

