"""Simulation and exact sensitivities of a reduced model, for large networks.

The reduced model is the Galerkin projection of the network onto a fixed basis ``V``
(:mod:`.reduction`): temperatures ``T ≈ V z`` with

    M(θ) ż = A_r(θ, u) z + B_r(θ, u) U + L_r P,     M = Vᵀ C V,  A_r = Vᵀ A V,  B_r = Vᵀ K_DU,  L_r = Vᵀ M_D

— again a passive thermal network (``M`` positive definite, ``A_r`` symmetric negative definite),
small (tens of states for hundreds of nodes). Because ``V`` does not depend on the parameters,
the derivatives of the reduced system are exact and cheap: a conductance changes ``A_r`` by
``−(Vᵀz_e)(Vᵀz_e)ᵀ`` and a capacity changes ``M`` by ``Vᵀ diag(dc) V``. The reduced model is
discretised as the full one (zero-order hold, in the eigenbasis of the pencil ``(A_r, M)``; the
derivative of ``Φ`` by the Daleckii–Krein formula), and its forward sensitivities follow the
same recursion as the full model's (:mod:`.simulate`), on ``r`` instead of ``n`` states. So an
optimiser that uses it minimises the reduced model's objective with that objective's exact
gradient; how far the reduced model is from the full one is bounded at the reference
(:meth:`~thermal_edge.lptn.reduction.Reduction.bound`) and measured elsewhere.

Losses are affine in the temperatures (the copper law): ``P = P0 + D T`` with the slope series
``D[k]`` of low rank in time (``i²`` times a fixed pattern: rank one), so the feedback enters the
reduced step as ``Σ_ρ s_ρ[k] K_ρ`` with small fixed matrices ``K_ρ``.

:func:`simulator_for` picks the path: the exact dense :class:`~thermal_edge.lptn.simulate.Simulator`
up to :data:`REDUCE_ABOVE` nodes, this one above (where it applies).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.linalg.blas import dgemm as _gemm
from scipy.linalg.blas import dgemv as _gemv

from .expr import Value
from .losses import LossLaws
from .model import Model, ModelError
from .network import Network
from .reduction import TOL, Reduction, check_reducible, reduce
from .simulate import Simulator, Trajectory, unique_rows

#: node count above which :func:`simulator_for` uses the reduced model: the dense adaptation step
#: (screening + 3 SQP iterations over a 3 h window) passes 1 s between 80 and 160 nodes
REDUCE_ABOVE = 150
#: terms of the loss slopes' time series below this fraction of the largest are round-off
SLOPE_RANK_TOL = 1e-13


@dataclass(frozen=True)
class _Projected:
    """A basis and the network's pieces projected on it: ``Zr = inc V`` (E, r), ``Lr = Vᵀ M_D``
    (r, n_loss), ``Vtv = V[tv]`` (the loss laws' nodes)."""

    red: Reduction
    Zr: np.ndarray
    Lr: np.ndarray
    Vtv: np.ndarray


class _Run(NamedTuple):
    """A simulated run and what its sensitivities reuse: the basis and step, the environment,
    operating points (values and per step), boundary inputs, the reduced inputs ``q``, the loss
    slopes (``Kr``, ``s``), the operators and their modes, and the states ``z``, ``T``, ``P``."""

    b: _Projected
    dt: float
    env: dict[str, Value]
    op: dict[str, np.ndarray]
    ops: np.ndarray
    Ub: np.ndarray
    q: np.ndarray
    Kr: list[np.ndarray]
    s: np.ndarray
    M: np.ndarray
    A: np.ndarray
    U: np.ndarray
    lam: np.ndarray
    Phi: np.ndarray
    G: np.ndarray
    Ai: np.ndarray
    z: np.ndarray
    T: np.ndarray
    P: np.ndarray


class ReducedSimulator:
    """Simulates the reduced model of a lumped network, with exact sensitivities (see the module
    docstring); the interface of :class:`~thermal_edge.lptn.simulate.Simulator`.

    Parameters
    ----------
    model : Model
        A lumped network with loss laws affine in the temperatures.
    reduction : Reduction, optional
        The basis for every step (default: :func:`~thermal_edge.lptn.reduction.reduce` at the
        nominal parameters, standstill and ``tol``, for each step a run uses, on first use).
    tol : float
        Tolerance of the default bases.
    """

    def __init__(self, model: Model, reduction: Reduction | None = None, tol: float = TOL) -> None:
        self.net = net = Network(model)
        check_reducible(model, net)
        self.model = model
        self.tol = tol
        self.fixed = reduction
        self._bases: dict[float, _Projected] = {}
        self._last: tuple[tuple[object, ...], _Run] | None = None
        self.n = net.n
        self.losses = LossLaws(model)
        self.tv = self.losses.nodes
        free_ops = set(model.inputs) | set(model.derived)
        #: edges whose conductance depends on the operating point
        self.op_edges = np.array([e for e, edge in enumerate(model.edges) if edge.g.free() & free_ops], dtype=int)
        self.static_edges = np.setdiff1d(np.arange(len(model.edges)), self.op_edges)

    def reduction(self, dt: float) -> Reduction:
        """The basis used for runs with step ``dt`` (s): the one given, else built at the nominal
        parameters for this step on first use (the modes that matter depend on the step) and kept."""
        return self._basis(dt).red

    def _basis(self, dt: float) -> _Projected:
        key = float(dt)
        if key not in self._bases:
            red = self.fixed if self.fixed is not None else reduce(self.model, tol=self.tol, dt=key, net=self.net)
            net, V = self.net, red.V
            self._bases[key] = _Projected(red, net.inc[:, : net.n] @ V, V.T @ net.loss_map[: net.n], V[self.tv])
        return self._bases[key]

    # -----------------------------------------------------------------------------------------
    def _operators(self, b: _Projected, theta: np.ndarray, op: Mapping[str, np.ndarray],
                   K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``M`` (r, r), ``A_r`` (K, r, r) and ``B_r`` (K, r, nb) at ``K`` operating points."""
        net, V, Zr, binc = self.net, b.red.V, b.Zr, self.net.binc
        r = V.shape[1]
        g, _ = net.conductances(theta, op, K)
        st, ov = self.static_edges, self.op_edges
        Zs, Zo = Zr[st], Zr[ov]
        A = np.broadcast_to(-(Zs.T * g[0, st]) @ Zs, (K, r, r)).copy()
        B = np.broadcast_to((Zs.T * g[0, st]) @ binc[st], (K, r, binc.shape[1])).copy()
        if len(ov):
            ZoT = Zo.T[None] * g[:, None, ov]  # (K, r, eo)
            A -= ZoT @ Zo
            B += ZoT @ binc[ov]
        c, _ = net.capacities(theta)
        return (V.T * c) @ V, A, B

    def _derivatives(self, b: _Projected, theta: np.ndarray, op: Mapping[str, np.ndarray], K: int,
                     wrt: Sequence[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``dM`` (p, r, r), ``dA`` (K, p, r, r) and ``dB`` (K, p, r, nb) by the parameters ``wrt``."""
        net, V, Zr, binc = self.net, b.red.V, b.Zr, self.net.binc
        r, p = V.shape[1], len(wrt)
        _, dg = net.conductances(theta, op, K, wrt)
        _, dc = net.capacities(theta, wrt)
        live = net.live_edges(wrt)
        Zl = Zr[live]  # (e, r)
        dM = np.stack([(V.T * dc[j]) @ V for j in range(p)]) if p else np.zeros((0, r, r))
        moving = np.isin(live, self.op_edges)
        fixed = ~moving
        dA = np.empty((K, p, r, r))
        dB = np.empty((K, p, r, binc.shape[1]))
        Zf, Zm = Zl[fixed], Zl[moving]
        bf, bm = binc[live[fixed]], binc[live[moving]]
        for j in range(p):
            dA[:, j] = -(Zf.T * dg[0, j, fixed]) @ Zf
            dB[:, j] = (Zf.T * dg[0, j, fixed]) @ bf
        if moving.any():
            ZmT = Zm.T[None, None] * dg[:, :, None, moving]  # (K, p, r, em)
            dA -= ZmT @ Zm
            dB += ZmT @ bm
        return dM, dA, dB

    @staticmethod
    def _modes(M: np.ndarray, A: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
        """Eigenbasis of the pencil ``(A_r, M)`` at every operating point: ``U`` (K, r, r) with
        ``Uᵀ M U = I``, rates ``lam`` (K, r), and ``Φ``, ``G = (Φ − I) A_r⁻¹``, ``A_r⁻¹``."""
        Lc = np.linalg.cholesky(M)
        Li = np.linalg.inv(Lc)
        lam, Qm = np.linalg.eigh(Li @ A @ Li.T)
        if np.any(lam >= 0):
            raise ModelError(f"reduced system matrix has a non-negative eigenvalue ({float(lam.max()):.3g} 1/s)")
        U = Li.T @ Qm
        Ut = np.swapaxes(U, 1, 2)
        x = lam * dt
        Phi = (U * np.exp(x)[:, None, :]) @ Ut @ M
        G = (U * (np.expm1(x) / lam)[:, None, :]) @ Ut
        Ai = (U / lam[:, None, :]) @ Ut
        return U, lam, Phi, G, Ai

    # -----------------------------------------------------------------------------------------
    def simulate(self, theta: np.ndarray, inputs: Mapping[str, np.ndarray], dt: float, T0: np.ndarray,
                 wrt: Sequence[str] | None = None, rows: Sequence[str] | None = None) -> Trajectory:
        """Simulate the reduced model; arguments and result as
        :meth:`~thermal_edge.lptn.simulate.Simulator.simulate` (``T`` at every node is ``V z``).

        The last run is kept: an optimiser asks for the value at a point and then for its
        gradient, and the second call only adds the sensitivities to the first's simulation.
        """
        model = self.model
        theta = np.asarray(theta, dtype=float)
        names = tuple(wrt or ())
        widx = list(model.parameter_index(names)) if names else []
        missing = [c for c in model.inputs if c not in inputs]
        if missing:
            raise KeyError(f"run lacks input column(s) {', '.join(missing)} needed by model {model.name}")
        T0 = np.asarray(T0, dtype=float)
        key = (theta.tobytes(), float(dt), T0.tobytes(),
               tuple(np.ascontiguousarray(inputs[c], dtype=float).tobytes() for c in model.inputs))
        if self._last is not None and self._last[0] == key:
            st = self._last[1]
        else:
            st = self._simulate(theta, inputs, float(dt), T0)
            self._last = (key, st)
        traj = Trajectory(T=st.T, P=st.P, wrt=names, nodes=model.nodes)
        if names:
            keep = np.arange(self.n) if rows is None else np.array([model.node_index(x) for x in rows], dtype=int)
            Sz = self._sensitivities(st, theta, widx)
            N, r, p = Sz.shape
            traj.S = (st.b.red.V[keep] @ Sz.transpose(1, 0, 2).reshape(r, N * p)).reshape(len(keep), N, p).transpose(1, 0, 2)
        return traj

    def _simulate(self, theta: np.ndarray, inputs: Mapping[str, np.ndarray], dt: float, T0: np.ndarray) -> _Run:
        model, net = self.model, self.net
        b = self._basis(dt)
        red, r = b.red, b.red.V.shape[1]
        N = len(next(iter(inputs.values())))
        env = net.env(theta, {k: np.asarray(v, dtype=float) for k, v in inputs.items()})
        steps = max(N - 1, 0)
        if net.matrix_inputs:
            keys = np.stack([np.broadcast_to(np.asarray(env[k], dtype=float), (N,))[: max(steps, 1)]
                             for k in net.matrix_inputs], axis=1)
            uniq, ops = unique_rows(keys)
            op = {k: uniq[:, i] for i, k in enumerate(net.matrix_inputs)}
        else:
            uniq, ops, op = np.zeros((1, 0)), np.zeros(max(steps, 1), dtype=int), {}
        K = len(uniq)
        M, A, B = self._operators(b, theta, op, K)
        U_, lam, Phi, G, Ai = self._modes(M, A, dt)
        Ub = np.zeros((N, 0))
        if model.boundaries:
            Ub = np.stack([np.broadcast_to(np.asarray(inputs[c], dtype=float), (N,)) for c in model.boundaries.values()],
                          axis=1)
        P0 = self.losses.power(env, None, N)
        law, col, slope = self.losses.slope_entries(env, None, N)
        Kr, s = self._slopes(b, law, col, slope, steps)
        ops = ops[:steps]
        # the input-driven part of each step's reduced input, q = B_r U + L_r P0 (N-1, r)
        q = P0[:steps] @ b.Lr.T
        for o in range(K):
            sel = np.nonzero(ops == o)[0]
            q[sel] += Ub[sel] @ B[o].T
        gq = np.empty_like(q)
        for o in range(K):
            sel = np.nonzero(ops == o)[0]
            gq[sel] = q[sel] @ G[o].T
        z = np.empty((N, r))
        z[0] = red.V.T @ (red.c_ref * T0)
        self._run(z, Phi, G, Kr, s, ops, gq)
        T = z @ red.V.T
        to_law = np.zeros((len(law), P0.shape[1]))  # the laws are affine in the temperatures: P = P0 + slope · T
        to_law[np.arange(len(law)), law] = 1.0
        P = P0 + (slope * T[:, self.tv[col]]) @ to_law
        return _Run(b, dt, env, op, ops, Ub, q, Kr, s, M, A, U_, lam, Phi, G, Ai, z, T, P)

    @staticmethod
    def _slopes(b: _Projected, law: np.ndarray, col: np.ndarray, D: np.ndarray,
                steps: int) -> tuple[list[np.ndarray], np.ndarray]:
        """The loss slopes (entries ``D`` (N, e) of laws ``law`` at loss-node columns ``col``) over
        the steps as ``Σ_ρ s[k, ρ] C_ρ`` (singular value decomposition over time): ``K_ρ = L_r C_ρ
        V_tv`` (r, r) and ``s`` (steps, rank)."""
        D = D[:steps]
        live = np.nonzero(np.any(D != 0.0, axis=0))[0] if steps else np.zeros(0, dtype=int)
        if not len(live):
            return [], np.zeros((steps, 0))
        Us, sv, Wt = np.linalg.svd(D[:, live], full_matrices=False)
        rank = int(np.count_nonzero(sv > SLOPE_RANK_TOL * sv[0]))
        Ll, Vl = b.Lr[:, law[live]], b.Vtv[col[live]]
        Kr = [(Ll * Wt[i]) @ Vl for i in range(rank)]
        return Kr, Us[:, :rank] * sv[:rank]

    def _sensitivities(self, st: _Run, theta: np.ndarray, widx: list[int]) -> np.ndarray:
        """``∂z_k/∂θ`` (N, r, p) by the forward recursion ``S_{k+1} = (Φ + Σ s K̃) S_k + F_k`` with
        ``F = dΦ (z + h) + G (−dA h + dB U + L_r ∂P/∂θ)``, ``h = A_r⁻¹ y`` the static response to the
        step's reduced input ``y = B_r U + L_r P`` (the step is ``z⁺ = Φ z + G y``)."""
        b, env, ops, z, T, Ub, q, s, Kr = st.b, st.env, st.ops, st.z, st.T, st.Ub, st.q, st.s, st.Kr
        M, U_, lam, Phi, G, Ai, dt = st.M, st.U, st.lam, st.Phi, st.G, st.Ai, st.dt
        N = len(z)
        dM, dA, dB = self._derivatives(b, theta, st.op, Phi.shape[0], widx)
        p, r = len(widx), b.red.V.shape[1]
        steps = len(ops)
        K = Phi.shape[0]
        Sz = np.zeros((N, r, p))
        if not steps:
            return Sz
        y = q.copy()
        for rho, Kq in enumerate(Kr):
            y += s[:, rho: rho + 1] * (z[:steps] @ Kq.T)
        dPdth = self.losses.dtheta(env, T, widx, N)[:steps]  # (steps, nl, p)
        F = np.empty((steps, r, p))
        Ut = np.swapaxes(U_, 1, 2)
        for o in range(K):
            sel = np.nonzero(ops == o)[0]
            if not len(sel):
                continue
            # V⁻¹ dΦ V in the pencil's eigenbasis (Daleckii–Krein): D ∘ (Uᵀ dA U − Uᵀ dM U Λ)
            lo = lam[o]
            Dd = divided_exp(lo * dt) * dt
            Ht = Ut[o] @ dA[o] @ U_[o] - (Ut[o] @ dM @ U_[o]) * lo[None, None, :]
            dPhi = U_[o] @ (Dd * Ht) @ Ut[o] @ M  # (p, r, r)
            h = y[sel] @ Ai[o].T  # (B, r)
            nb = len(sel)
            X = (dPhi.reshape(p * r, r) @ (z[sel] + h).T).reshape(p, r, nb)
            # G (−dA h + dB U + L_r ∂P/∂θ): the parameters' products stacked, then one product with G
            dAB = np.concatenate([dA[o], dB[o]], axis=2).reshape(p * r, -1)
            inner = (dAB @ np.concatenate([-h, Ub[sel]], axis=1).T).reshape(p, r, nb).transpose(1, 2, 0)
            inner += (b.Lr @ dPdth[sel].transpose(1, 0, 2).reshape(-1, nb * p)).reshape(r, nb, p)
            X += (G[o] @ inner.reshape(r, nb * p)).reshape(r, nb, p).transpose(2, 0, 1)
            F[sel] = X.transpose(2, 1, 0)
        self._run(Sz, Phi, G, Kr, s, ops, F)
        return Sz

    @staticmethod
    def _run(x: np.ndarray, Phi: np.ndarray, G: np.ndarray, Kr: list[np.ndarray], s: np.ndarray, ops: np.ndarray,
             f: np.ndarray) -> None:
        """``x[k+1] = (Φ_o + Σ_ρ s[k, ρ] G_o K_ρ) x[k] + f[k]`` over the steps, in place (``x[0]``
        given; ``x`` (N, r) or (N, r, p)). A step is a few tiny products: BLAS is called directly
        (``y ← α A x + y``), numpy's dispatch would cost more than the arithmetic."""
        terms = [[np.asfortranarray(Phi[o])] + [np.asfortranarray(G[o] @ Kq) for Kq in Kr] for o in range(Phi.shape[0])]
        coef = np.concatenate([np.ones((len(ops), 1)), s[:, : len(Kr)]], axis=1).tolist()
        gemm = x.ndim == 3
        opl = ops.tolist()
        for k, o in enumerate(opl):
            y = f[k].copy(order="F") if gemm else f[k].copy()
            xk = x[k]
            for a, mat in zip(coef[k], terms[o]):
                y = _gemm(a, mat, xk, 1.0, y, overwrite_c=True) if gemm else _gemv(a, mat, xk, 1.0, y, overwrite_y=True)
            x[k + 1] = y


def divided_exp(x: np.ndarray) -> np.ndarray:
    """Divided differences ``(e^a − e^b)/(a − b)`` of ``exp`` over all pairs of ``x`` (its limit
    ``e^a`` on equal values), written ``e^max(a,b) (1 − e^−|a−b|)/|a−b|``: it neither overflows
    nor cancels for close values.

    >>> bool(np.allclose(divided_exp(np.array([0.0, 1.0])), [[1.0, np.e - 1.0], [np.e - 1.0, np.e]]))
    True
    """
    d = np.abs(x[:, None] - x[None, :])
    top = np.exp(np.maximum(x[:, None], x[None, :]))
    small = d < 1e-12
    out: np.ndarray = top * np.where(small, 1.0, -np.expm1(-d) / np.where(small, 1.0, d))
    return out


#: what an estimator simulates with: either path, one interface
AnySimulator = Simulator | ReducedSimulator


def simulator_for(model: Model, reduce_above: int = REDUCE_ABOVE) -> AnySimulator:
    """The simulator an estimator uses for ``model``: the exact dense one up to ``reduce_above``
    nodes (and for any model the reduced path does not handle), the reduced one above."""
    if len(model.nodes) > reduce_above:
        try:
            check_reducible(model)
        except ModelError:
            return Simulator(model)
        return ReducedSimulator(model)
    return Simulator(model)
