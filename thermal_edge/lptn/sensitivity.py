"""Forward sensitivities ``S_k = ∂T_k/∂θ`` of a simulated run (paper eqs. 35–37).

``S[k+1] = M_k S[k] + X_k`` with the transition ``M_k = Φ + Γ_P ∂P/∂T`` of the simulation and
the forcing ``X_k = dΦ T_k + dΓ w_k + Γ_P ∂P/∂θ``. Three exact ways, chosen per run of steps:

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
* **Stretches at one operating point** whose loss feedback changes every step (a noisy
  current): the forcing of the whole stretch in one product, then the linear filter of
  :class:`~thermal_edge.lptn.stretch.NodeStretch` (modes of ``Φ``, the feedback solved exactly
  as a low-rank block-triangular system in time).
* **Step by step** otherwise: the forcing for a block of steps as products per operating point
  (in the modal basis of :class:`~thermal_edge.lptn.discretise.DiscreteDerivatives`; the Daleckii–Krein
  form row by row at a ramp's operating points), then the recursion.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import NamedTuple

import numpy as np

from .discretise import DiscreteDerivatives
from .expr import Value
from .held import POW_BLOCK, Transitions, power_basis
from .scratch import Scratch
from .stretch import RANK_TOL, NodeStretch, padded_length
from .transitions import StepMatrices

#: shortest run of held inputs worth the closed form (its set-up costs about as much as 60 steps)
MIN_HELD = 64
#: eigenvalue pairs closer than this keep their divided differences: split over the power
#: basis a pair loses about 1e-16/gap of relative accuracy to cancellation
CLOSE = 1e-6
BLOCK = 256  # time steps per block of the step-by-step forcing
#: an operating point used by fewer stepped steps than this gets the Daleckii–Krein form vector by
#: vector instead of its dense derivative (a ramp: a new speed every step)
FEW_STEPS = 8

#: a function of steps (B,) and temperatures (B, n) with the inputs of those steps: the losses
#: (B, nl) in W, or ``∂P/∂θ`` (B, nl, p) in W per parameter unit
AtSteps = Callable[[np.ndarray, np.ndarray], np.ndarray]

def divided_powers(x: np.ndarray, y: np.ndarray, k: np.ndarray | float) -> np.ndarray:
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
        out: np.ndarray = np.exp((k - 1) * top) * ratio
        return out


class Sensitivities:
    """The sensitivity recursion of one simulated run.

    Parameters
    ----------
    disc : DiscreteDerivatives
        Discretisation with modal derivatives at every operating point.
    ops : ndarray (N-1,)
        Operating point of each step.
    mats : StepMatrices
        The transition matrix ``M`` of each step, computed a block at a time.
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
    slopes : ndarray (N-1, nl, len(loss_nodes)), optional
        ``∂P/∂T`` of losses affine in temperature at each step (W/K): what the stretches run
        vectorised in time need (:meth:`run`).
    prepared : mapping, optional
        The simulation's stretches ``(a, b)`` already set up (shared: their set-up depends on
        the feedback only).
    loss_wrt : bool, optional
        Whether some loss law depends on a parameter asked for (default True); without,
        ``∂P/∂θ`` is zero and the stretches skip it.
    held : Transitions, optional
        The closed-loop modes of the held runs :meth:`run` is given (the simulation's,
        :func:`~thermal_edge.lptn.held.transitions`); needed when it is given any.
    """

    def __init__(self, disc: DiscreteDerivatives, ops: np.ndarray, mats: StepMatrices, T: np.ndarray,
                 U: np.ndarray, P: np.ndarray, losses: AtSteps, loss_theta: AtSteps, loss_nodes: np.ndarray,
                 slopes: np.ndarray | None = None, prepared: Mapping[tuple[int, int], NodeStretch] | None = None,
                 loss_wrt: bool = True, held: Transitions | None = None) -> None:
        self.d, self.ops, self.mats = disc, ops, mats
        self.slopes, self.prepared, self.loss_wrt, self.held = slopes, dict(prepared or {}), loss_wrt, held
        self.scratch = Scratch()  # the stretches' large temporaries, reused from one to the next
        self.T, self.U, self.P, self.nb = T, U, P, U.shape[1]
        self.losses, self.loss_theta, self.loss_nodes = losses, loss_theta, np.asarray(loss_nodes, dtype=int)
        self.n, self.p = T.shape[1], disc.dg.shape[1]

    # -- the forcing, in the modal basis of an operating point ------------------------------
    def forcing(self, o: int | np.ndarray, T: np.ndarray, w: np.ndarray, left: np.ndarray | None = None) -> np.ndarray:
        """``V⁻¹ (dΦ T + dΓ w)`` (B, n, p) for temperatures ``T`` (B, n) and inputs ``w`` (B, m) of
        ``Γ`` at operating point ``o`` (one for all rows, or one per row), in the modal basis of
        ``Φ`` there (:meth:`~thermal_edge.lptn.discretise.DiscreteDerivatives.forcing`). The losses' own
        dependence on θ, ``Γ_P ∂P/∂θ``, is the callers' to add.
        """
        d = self.d
        _, Vi = d.basis(o)
        # y = V⁻¹ T + Ht w and v = Yt w, one row per step
        if np.ndim(o) == 0:
            y, v = T @ Vi.T + w @ d.Ht[o].T, w @ d.Yt[o].T
        else:
            y = np.einsum("...ac,...c->...a", Vi, T) + np.einsum("...am,...m->...a", d.Ht[o], w)
            v = np.einsum("...em,...m->...e", d.Yt[o], w)
        return d.forcing(o, y, v, left)

    # -- runs ---------------------------------------------------------------------------------
    def run(self, runs: list[tuple[int, int]], spans: list[tuple[int, int]], rows: np.ndarray | None,
            S0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``S`` (N, rows, p) (all nodes when ``rows`` is None) from ``S[0] = S0`` (n, p; default
        zero: an initial state that does not depend on θ), and ``S`` at the last sample (n, p).

        ``runs`` are the held runs ``(a, b)`` (steps ``a .. b−1``) to try in closed form
        (:func:`held_runs`), ``spans`` the stretches at one operating point to run vectorised in
        time (:func:`~thermal_edge.lptn.stretch.stretches`; they need ``slopes``); the other
        steps are stepped.
        """
        N = self.T.shape[0]
        steps = N - 1
        keep = np.arange(self.n) if rows is None else np.asarray(rows, dtype=int)
        S = np.zeros((N, len(keep), self.p))
        s = np.zeros((self.n, self.p)) if S0 is None else np.array(S0, dtype=float)
        S[0] = s[keep]
        forms = self._held_runs(runs, keep) if runs else []
        stepped = np.ones(steps, dtype=bool)
        for (a, b), form in zip(runs, forms):
            stepped[a:b] &= form is None
        for a, b in spans:
            stepped[a:b] = False
        # the steps the recursion takes one by one, their forcing BLOCK steps at a time (across
        # the gaps between held runs), consumed in order
        ks = np.nonzero(stepped)[0]
        uo, count = np.unique(self.ops[ks], return_counts=True)
        self.d.build_dphit(uo[count >= FEW_STEPS])  # the dense derivatives the stepping needs, built together
        blocks = (self._forcing(ks[c: c + BLOCK]) for c in range(0, len(ks), BLOCK))
        X = np.zeros((0, self.n, self.p))
        used = 0  # rows of X consumed
        full = rows is None

        def step(a: int, b: int, s: np.ndarray) -> np.ndarray:
            """Steps ``a .. b−1`` from ``S[a] = s`` (all nodes); fills ``S[a+1 .. b]``."""
            nonlocal X, used
            while a < b:
                if used == len(X):
                    X, used = next(blocks), 0
                m = min(b - a, len(X) - used)
                Xb = X[used: used + m]  # becomes S[a + 1 .. a + m] in place
                for lo, hi, ms, mi in self.mats.segments(a, a + m):
                    for k in range(lo, hi):
                        Xk = Xb[k - a]
                        Xk += ms[mi[k]] @ s
                        s = Xk
                S[a + 1: a + m + 1] = Xb if full else Xb[:, keep]
                used += m
                a += m
            return s

        pending = 0  # first step not yet propagated
        longest = max((b - a for a, b in runs), default=0)
        work = np.empty((2 * self.n + 1, -(-longest // POW_BLOCK) * POW_BLOCK))
        events = sorted([(a, b, form) for (a, b), form in zip(runs, forms) if form is not None]
                        + [(a, b, None) for a, b in spans], key=lambda e: e[0])
        for a, b, form in events:
            s = step(pending, a, s)
            if form is None:
                s = self._span(a, b, s, S[a + 1: b + 1], keep)
            else:
                s = form.apply(s, S[a + 1: b + 1], work)
            pending = b
        s = step(pending, steps, s)
        return S, s

    def _span(self, a: int, b: int, s: np.ndarray, out: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Steps ``a .. b−1`` at one operating point from ``S[a] = s`` (n, p), vectorised in time
        (:class:`~thermal_edge.lptn.stretch.NodeStretch`, the simulation's where it ran the same
        stretch): the forcing of all steps in one product (:meth:`stretch_forcing`), then the
        filter. Fills ``out`` (b − a, rows, p); returns ``S[b]``."""
        assert self.slopes is not None
        d, o = self.d, int(self.ops[a])
        ns = self.prepared.get((a, b))
        if ns is None:
            V, Vi = d.basis(o)
            ns = NodeStretch(V, Vi, d.mu[o], d.Gam[o][:, self.nb:], self.loss_nodes, self.slopes[a:b])
        w = np.concatenate([self.U[a:b], self.P[a:b]], axis=1)
        dP = self.loss_theta(np.arange(a, b), self.T[a:b]) if self.loss_wrt else None
        Lp = padded_length(b - a)
        # the simulation's modal temperatures of the stretch, when it ran it (no V⁻¹ T again)
        modal = ns.modal[:, 0] if ns.modal is not None and ns.modal.shape[1] == 1 else None
        X = self.stretch_forcing(o, self.T[a:b], w, dP, Lp, out=self.scratch.get("forcing", (self.n, self.p, Lp)),
                                 modal=modal)
        rows, end = ns.solve(X, s, keep, self.scratch)
        out[:] = rows.transpose(2, 0, 1)
        return end

    def stretch_forcing(self, o: int, T: np.ndarray, w: np.ndarray, dP: np.ndarray | None,
                        Lp: int | None = None, out: np.ndarray | None = None,
                        modal: np.ndarray | None = None) -> np.ndarray:
        """``V⁻¹ (dΦ_j T_i + dΓ_j w_i + Γ_P ∂P/∂θ_j)`` as (n, p, Lp) (time last, for
        :meth:`~thermal_edge.lptn.stretch.Stretch.solve`; zero past the ``B`` steps, ``Lp ≥ B``,
        default ``B``) for temperatures ``T`` (B, n), inputs ``w`` (B, m) of ``Γ`` and the
        losses' derivatives ``dP`` (B, nl, p) at operating point ``o`` (None: no loss law
        depends on a parameter asked for). ``out`` (n, p, Lp), optional, receives it; ``modal``
        (n, B), optional, is ``V⁻¹ T`` already known (the simulation's states of the stretch).

        One product of ``[dPhit_j | V⁻¹ dΓ_j]`` stacked mode-major
        (:meth:`~thermal_edge.lptn.discretise.DiscreteDerivatives.joined`) with ``[V⁻¹ T; w]``,
        ``w`` through its singular value decomposition;
        the losses' own parameters add ``V⁻¹ Γ_P ∂P/∂θ_j`` one parameter at a time.
        """
        d, n, p, B = self.d, self.n, self.p, len(T)
        J = d.joined(o)
        _, Vi = d.basis(o)
        Lp = B if Lp is None else Lp
        # the inputs of a stretch have a small rank (a constant part, the current's square and
        # the copper losses' temperature terms): w = Ub Wt with Wt (r, m), so V⁻¹ dΓ_j w costs
        # r columns of the product instead of m (terms below RANK_TOL of the largest are round-off)
        # (the singular values and right vectors of w from its triangular factor: a long, narrow
        # w decomposes several times faster so; its left factor is then w Wtᵀ)
        _, sv, Wt = np.linalg.svd(np.linalg.qr(w, mode="r"))
        r = int(np.count_nonzero(sv > RANK_TOL * sv[0])) if len(sv) and sv[0] > 0.0 else 0
        Jr = np.concatenate([J[:, :n], J[:, n:] @ Wt[:r].T], axis=1)
        xi = np.zeros((n + r, Lp))
        if modal is None:
            np.matmul(Vi, T.T, out=xi[:n, :B])
        else:
            xi[:n, :B] = modal
        np.matmul(Wt[:r], w.T, out=xi[n:, :B])
        X = np.matmul(Jr, xi, out=None if out is None else out.reshape(n * p, Lp)).reshape(n, p, Lp)
        if dP is not None:
            live = np.nonzero(np.any(dP != 0.0, axis=(0, 1)))[0]  # the loss parameters
            if len(live):
                GPt = Vi @ d.Gam[o][:, self.nb:]
                for j in live:
                    X[:, j, :B] += GPt @ dP[:, :, j].T
        return X

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
        X = np.asarray(np.matmul(d.Q[ob], X))  # back to node coordinates (V = diag(1/s) Q)
        X /= d.s[:, None]
        if np.any(dP):  # Γ_P ∂P/∂θ
            X += d.Gam[ob][:, :, self.nb:] @ dP
        return X

    def _held_runs(self, runs: list[tuple[int, int]], keep: np.ndarray) -> list[_HeldRun | None]:
        """The closed form (see the module docstring) of each held run ``(a, b)`` of steps ``a .. b−1``.

        None where it does not apply: the closed-loop transition is not symmetrisable (a loss law
        couples nodes) or has an eigenvalue outside (0, 1).

        In steps: runs with the same transition share its modes (the simulation's
        :class:`~thermal_edge.lptn.held.Transitions`); each run's
        temperatures in those modes, ``ξ_k = ξ∞ + μ^k δ`` (:meth:`_run_states`); the forcing in
        the modes per transition, applied to each run's states (:meth:`_modal_forcing`); from
        those, the coefficients of the chosen rows on the time basis (:meth:`_coefficients`), the
        sensitivity at each run's end (:meth:`_ends`) and the terms of close eigenvalue pairs
        (:meth:`_close_pairs`).
        """
        starts = np.array([a for a, _ in runs])
        lengths = np.array([b - a for a, b in runs])
        ops = self.ops[starts]
        tr = self.held
        assert tr is not None and len(tr.index) == len(runs)  # the simulation's, of the same runs
        probe, w0 = self._probe_forcing(starts, ops)
        st = self._run_states(tr, starts, ops, lengths, w0)
        pairs = _ModePairs.of(tr.modes.mu)
        fo = self._modal_forcing(tr, ops, probe, st, pairs, keep)
        # the constant forcing of each mode, F ξ∞ + X(0)
        const = fo.F_xinf + np.matmul(tr.modes.Q2r[tr.index], probe[:, 0])
        to_rows = tr.modes.Om[tr.index][:, keep]  # ξ -> chosen rows, per run
        coef = self._coefficients(tr, st, pairs, fo, const, to_rows)
        end = self._ends(tr, st, lengths, fo, const)
        extra = self._close_pairs(tr, st, lengths, pairs, fo, const, to_rows, end)
        mu_ext = np.concatenate([st.mu, np.ones((len(runs), 1))], axis=1)  # with μ_n = 1 of the constant forcing
        modes = tr.modes
        return [_HeldRun(mu_ext[i], coef[i], to_rows[i], modes.Om[u], modes.Xi[u], st.mu_end[i], end[i], extra[i])
                if modes.ok[u] else None for i, u in enumerate(tr.index)]

    def _run_states(self, tr: Transitions, starts: np.ndarray, ops: np.ndarray, lengths: np.ndarray,
                    w0: np.ndarray) -> _RunStates:
        """Each run's temperatures in its modes, ``ξ_k = ξ∞ + μ^k δ``, and the powers ``μ^L``, ``μ^(L−1)``."""
        modes = tr.modes
        mu = modes.mu[tr.index]
        xi_inf = (modes.Xi[tr.index] @ (self.d.Gam[ops] @ w0[:, :, None]))[..., 0] / (1.0 - mu)
        delta = (modes.Xi[tr.index] @ self.T[starts][:, :, None])[..., 0] - xi_inf
        with np.errstate(under="ignore"):
            mu_end = mu ** lengths[:, None]
            mu_before_end = mu ** (lengths[:, None] - 1)
        return _RunStates(mu, xi_inf, delta, mu_end, mu_before_end)

    def _modal_forcing(self, tr: Transitions, ops: np.ndarray, probe: np.ndarray, st: _RunStates,
                       pairs: _ModePairs, keep: np.ndarray) -> _ModalForcing:
        """The forcing ``F_u[j, a, b]`` of parameter ``j`` on mode ``a`` per unit of mode ``b`` of each
        transition ``u``, applied to the runs' states: only these products leave the loop (all
        small arrays: per transition, not per run)."""
        d, n, p = self.d, self.n, self.p
        modes, runs = tr.modes, len(tr.index)
        nr, ntr = len(keep), len(tr.first)
        F_xinf, F_delta, F_delta_end = np.empty((runs, n, p)), np.empty((runs, n, p)), np.empty((runs, n, p))
        rows_F, diag_F = np.empty((ntr, p, nr, n)), np.empty((ntr, n, p))
        close_F: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        diag = np.arange(n)
        # the losses' part of the forcing per unit T at each loss node, in the modal basis of Φ (pn, tv)
        tv = self.loss_nodes
        per_kelvin = (probe[tr.first, 1:] - probe[tr.first, :1]).transpose(0, 3, 2, 1).reshape(ntr, p * n, len(tv))
        Om_tv = modes.Om[:, tv]
        for u, sel in enumerate(tr.members):
            # V⁻¹ X = (dΦ̃ V⁻¹ + per_kelvin E_tv) T, T = V rQ2 ξ: F = Q2r (dΦ̃ rQ2 + per_kelvin Om[tv])
            F = d.dphit(int(ops[tr.first[u]])).reshape(p * n, n) @ modes.rQ2[u]
            F += per_kelvin[u] @ Om_tv[u]
            F = modes.Q2r[u] @ F.reshape(p, n, n)
            diag_F[u] = F[:, diag, diag].T
            if pairs.any_close[u]:
                ia, ib = np.nonzero(pairs.close[u, :, :n])
                close_F[u] = (ia, ib, F[:, ia, ib])
            F_xinf[sel] = (F.reshape(p * n, n) @ st.xi_inf[sel].T).reshape(p, n, -1).transpose(2, 1, 0)
            F *= pairs.split[u, :, :n]
            rows_F[u] = modes.Om[u, keep] @ F
            G = (F.reshape(p * n, n) @ np.concatenate([st.delta[sel], st.delta[sel] * st.mu_end[sel]]).T).reshape(p, n, -1)
            F_delta[sel], F_delta_end[sel] = G[:, :, : len(sel)].transpose(2, 1, 0), G[:, :, len(sel):].transpose(2, 1, 0)
        return _ModalForcing(F_xinf, F_delta, F_delta_end, rows_F, diag_F, close_F)

    def _coefficients(self, tr: Transitions, st: _RunStates, pairs: _ModePairs, fo: _ModalForcing,
                      const: np.ndarray, to_rows: np.ndarray) -> np.ndarray:
        """Coefficients (runs, 2n+1, rows, p) of the chosen rows on the time basis ``μ_b^k`` (b ≤ n)
        and ``k μ_a^(k−1)`` (a < n), without the part of ``σ_0``."""
        n = self.n
        split_const = pairs.split[tr.index][:, :, n]  # 1/(μ_a − 1)
        to_rows_t = np.swapaxes(to_rows, 1, 2)[..., None]  # (r, a, rows, 1)
        coef = np.empty((len(tr.index), 2 * n + 1, to_rows.shape[1], self.p))
        coef[:, :n] = -fo.rows_F[tr.index].transpose(0, 3, 2, 1) * st.delta[:, :, None, None]  # μ_b^k of F δ_b
        coef[:, n] = -(to_rows * split_const[:, None, :]) @ const  # μ_n^k = 1 of the constant forcing
        coef[:, :n] += to_rows_t * (fo.F_delta + split_const[:, :, None] * const)[:, :, None, :]  # μ_a^k of both
        coef[:, n + 1:] = to_rows_t * (fo.diag_F[tr.index] * st.delta[:, :, None])[:, :, None, :]
        return coef

    def _ends(self, tr: Transitions, st: _RunStates, lengths: np.ndarray, fo: _ModalForcing,
              const: np.ndarray) -> np.ndarray:
        """``σ_L`` (runs, n, p) of each run without the part of ``σ_0``, in ``ξ``: the sums of
        :meth:`_coefficients` at ``k = L`` (close pairs: :meth:`_close_pairs` adds theirs)."""
        end: np.ndarray = st.mu_end[:, :, None] * fo.F_delta - fo.F_delta_end
        end += (lengths[:, None] * st.mu_before_end * st.delta)[:, :, None] * fo.diag_F[tr.index]
        with np.errstate(under="ignore"):
            end += divided_powers(st.mu, np.ones_like(st.mu), lengths[:, None].astype(float))[:, :, None] * const
        return end

    def _close_pairs(self, tr: Transitions, st: _RunStates, lengths: np.ndarray, pairs: _ModePairs,
                     fo: _ModalForcing, const: np.ndarray, to_rows: np.ndarray,
                     end: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """The close eigenvalue pairs (none in most models), which keep their divided differences:
        their part of each run's end is added to ``end``; returned per run as extra terms for
        every step (pairs, their modes and coefficients on the chosen rows), None without any."""
        n = self.n
        extra: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = [None] * len(tr.index)
        for u, (ia, ib, F_ab) in fo.close_F.items():
            near_one = np.nonzero(pairs.close[u, :, n])[0]  # modes close to μ = 1
            for i in tr.members[u]:
                c = (F_ab * st.delta[i, ib]).T  # pairs b < n (pair, p)
                with np.errstate(under="ignore"):
                    end[i, ia] += divided_powers(st.mu[i, ia], st.mu[i, ib], float(lengths[i]))[:, None] * c
                pa, pb = np.concatenate([ia, near_one]), np.concatenate([ib, np.full(len(near_one), n)])
                c = np.concatenate([c, const[i, near_one]])
                extra[i] = (pa, pb, to_rows[i].T[pa][:, :, None] * c[:, None, :])
        return extra

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


class _RunStates(NamedTuple):
    """Per held run, in its modes: ``mu`` (runs, n), the fixed point ``xi_inf`` and the initial
    departure from it ``delta`` (``ξ_k = ξ∞ + μ^k δ``), ``mu_end = μ^L`` and ``mu_before_end = μ^(L−1)``."""

    mu: np.ndarray
    xi_inf: np.ndarray
    delta: np.ndarray
    mu_end: np.ndarray
    mu_before_end: np.ndarray


class _ModePairs(NamedTuple):
    """Mode pairs ``(a, b)`` per transition, ``b = n`` the constant forcing (``μ = 1``):
    ``split = 1/(μ_a − μ_b)`` splits a well-apart pair's divided differences over the power
    basis; ``close`` pairs keep theirs (a mode with itself has ``DD_k(μ, μ) = k μ^(k−1)`` and is
    not one of them)."""

    split: np.ndarray
    close: np.ndarray
    any_close: np.ndarray

    @classmethod
    def of(cls, mu: np.ndarray) -> _ModePairs:
        n = mu.shape[1]
        diff = mu[:, :, None] - np.concatenate([mu, np.ones((len(mu), 1))], axis=1)[:, None, :]
        close = np.abs(diff) < CLOSE
        split = np.where(close, 0.0, 1.0 / np.where(close, 1.0, diff))
        diag = np.arange(n)
        close[:, diag, diag] = False
        return cls(split, close, close.any(axis=(1, 2)))


class _ModalForcing(NamedTuple):
    """The forcing in the modes, per run: on the fixed point (``F_xinf``), on ``δ`` and on ``δ μ^L``
    (both scaled by the pair split); per transition: the chosen rows of the split forcing
    (``rows_F``), its diagonal (``diag_F``) and its close pairs (``close_F``)."""

    F_xinf: np.ndarray
    F_delta: np.ndarray
    F_delta_end: np.ndarray
    rows_F: np.ndarray
    diag_F: np.ndarray
    close_F: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]


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
        power_basis(self.logmue, L, work[: n + 1])
        basis = work[:, :L]
        Pw = basis[: n + 1]
        basis[n + 1:, 0] = 1.0
        np.multiply(Pw[:n, :-1], k[1:], out=basis[n + 1:, 1:])
        rows = out.reshape(L, nr * p)
        np.matmul(basis.T, coef, out=rows)
        if self.extra is not None:
            ia, ib, cc = self.extra
            rows += divided_powers(self.mue[ia][None, :], self.mue[ib][None, :], k[:, None]) @ cc.reshape(len(ia), nr * p)
        sigma: np.ndarray = self.Om @ (self.muL[:, None] * sig0 + self.endG)
        return sigma


def held_runs(held: np.ndarray, closed: bool, min_len: int = MIN_HELD) -> list[tuple[int, int]]:
    """The runs ``(a, b)`` of steps ``a .. b−1`` with held inputs (``held``, :func:`held_steps`) at
    least ``min_len`` long (default :data:`MIN_HELD`); none unless ``closed`` (the closed form is
    allowed)."""
    steps = len(held)
    if not closed or not steps:
        return []
    bounds = np.append(np.nonzero(~held)[0], steps)
    long = np.nonzero(np.diff(bounds) >= min_len)[0]  # inputs that vary every step: few long runs
    return list(zip(bounds[long].tolist(), bounds[long + 1].tolist()))


def held_steps(env: Mapping[str, Value], steps: int) -> np.ndarray:
    """``held[k]``: every input series of ``env`` has the same value at step ``k`` as at ``k − 1``."""
    held = np.ones(steps, dtype=bool)
    if steps:
        held[0] = False
    for v in env.values():
        a = np.asarray(v)
        if a.ndim == 1 and len(a) > steps >= 2:
            held[1:] &= a[1:steps] == a[: steps - 1]
    return held

