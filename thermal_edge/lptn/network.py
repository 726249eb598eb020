"""The numeric network: conductance laws -> Laplacian -> Schur elimination -> ``A``, ``W``.

For a batch of ``K`` operating points (values of the inputs that enter conductances) and a
parameter vector ``θ`` this module returns the continuous system (``docs/method/lptn.md``)::

    C dT/dt = A T + W w,      w = [U; P]  (boundary temperatures, then the loss sources)

with ``A = −(L_DD − L_DQ X)``, ``X = L_QQ⁻¹ L_QD`` and ``W = [K_DU − Xᵀ K_QU,  M_D − Xᵀ M_Q]``
(``M`` maps loss sources to points), and, for any subset of parameters, the exact derivatives
``dA``, ``dW`` and ``dc`` from the symbolic derivatives of the laws.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from .expr import Compiled, Expr, Value
from .model import MissingInputError, Model, ModelError


@dataclass
class Continuous:
    """Continuous system at ``K`` operating points; derivatives over ``p`` chosen parameters.

    Shapes: ``A`` (K, n, n) W/K, ``W`` (K, n, m), ``c`` (n,) J/K, ``dc`` (p, n).

    The derivatives of ``A`` and ``W`` are kept in factored form: each conductance ``g_e`` whose
    law depends on a chosen parameter changes them by rank one, ``∂A/∂g_e = −z_e z_eᵀ`` and
    ``∂W/∂g_e = −z_e v_eᵀ`` (see :meth:`Network._derivatives`), so ``dA_j = −Z diag(dg_j) Zᵀ``
    with ``Z`` (K, n, e), ``V`` (K, m, e) and ``dg`` (K, p, e) over the ``e`` edges that take part.
    :attr:`dA` and :attr:`dW` build the dense arrays on demand.
    """

    A: np.ndarray
    W: np.ndarray
    c: np.ndarray
    dc: np.ndarray | None = None
    dZ: np.ndarray | None = None
    dV: np.ndarray | None = None
    dg: np.ndarray | None = None
    #: the elimination's solves ``X``, ``HK``, ``HM`` (:meth:`Network._derivatives`), kept when
    #: asked for (:meth:`Network.continuous` with ``solves``) so that the derivatives can follow
    solves: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _dense(self, right: np.ndarray | None) -> np.ndarray | None:
        """``−Z diag(dg_j) rightᵀ`` for every parameter ``j``."""
        if self.dZ is None or self.dg is None or right is None:
            return None
        out: np.ndarray = -((self.dZ[:, None] * self.dg[:, :, None, :]) @ np.swapaxes(right, -1, -2)[:, None])
        return out

    @property
    def dA(self) -> np.ndarray | None:
        """``∂A/∂θ_j`` (K, p, n, n), W/K per parameter unit."""
        return self._dense(self.dZ)

    @property
    def dW(self) -> np.ndarray | None:
        """``∂W/∂θ_j`` (K, p, n, m)."""
        return self._dense(self.dV)


def _outer_rows(a: np.ndarray, b: np.ndarray) -> sparse.csr_matrix:
    """The row-wise outer products ``a[e] ⊗ b[e]`` flattened, (E, ca·cb), built sparse: an edge has
    at most two ends, and the dense (E, ca, cb) array of a model of hundreds of nodes is gigabytes."""
    e1, i = np.nonzero(a)
    e2, j = np.nonzero(b)
    rows, cols, vals = [], [], []
    for e in np.unique(e1):
        ii, jj = i[e1 == e], j[e2 == e]
        for x in ii:
            for y in jj:
                rows.append(e)
                cols.append(x * b.shape[1] + y)
                vals.append(a[e, x] * b[e, y])
    return sparse.csr_matrix((vals, (rows, cols)), shape=(a.shape[0], a.shape[1] * b.shape[1]))


class _Law:
    """A compiled law and the compiled derivatives with respect to the parameters it uses."""

    def __init__(self, expr: Expr, params: Sequence[str]) -> None:
        self.expr = expr
        self.f: Compiled = expr.compile()
        self.d: dict[int, Compiled] = {i: expr.diff(p).compile() for i, p in enumerate(params) if p in expr.free()}


class Network:
    """Numeric form of a :class:`Model` (built once; evaluated for any ``θ`` and operating points)."""

    def __init__(self, model: Model) -> None:
        self.model = model
        params = model.parameter_names
        self.n = n = len(model.nodes)
        pts = list(model.nodes) + list(model.points)
        self.n_points = len(pts)
        index = {p: i for i, p in enumerate(pts)}
        bnames = list(model.boundaries)
        bindex = {b: i for i, b in enumerate(bnames)}
        self.n_bound = len(bnames)
        self.n_loss = len(model.losses)
        E = len(model.edges)
        self.inc = np.zeros((E, self.n_points))
        self.binc = np.zeros((E, self.n_bound))
        for e, edge in enumerate(model.edges):
            self.inc[e, index[edge.a]] += 1.0
            if edge.b in bindex:
                self.binc[e, bindex[edge.b]] = 1.0
            else:
                self.inc[e, index[edge.b]] -= 1.0
        self.pinc = (self.inc > 0) * (self.binc.sum(axis=1, keepdims=True) > 0)  # point side of boundary edges
        # each edge's (at most two) ends among the algebraic points: index into them and sign (0: none)
        self._end_q = np.zeros((2, E), dtype=int)
        self._end_s = np.zeros((2, E))
        for e in range(E):
            for k, q in enumerate(np.nonzero(self.inc[e, n:])[0]):
                self._end_q[k, e], self._end_s[k, e] = q, self.inc[e, n + q]
        # sparse scatter matrices: edge conductances -> flattened Laplacian and point-boundary block
        self._scatter_L = _outer_rows(self.inc, self.inc)
        self._scatter_K = _outer_rows(self.pinc, self.binc)
        # L_QQ is block diagonal: the algebraic points fall apart into small groups (the face
        # points of one T-model element and their neighbours); solve each size of group at once
        qq = np.abs(self.inc[:, n:]).T @ np.abs(self.inc[:, n:]) > 0
        _, label = connected_components(sparse.csr_matrix(qq), directed=False)
        groups: dict[int, list[np.ndarray]] = {}
        for c in range(label.max() + 1 if len(label) else 0):
            members = np.nonzero(label == c)[0]
            groups.setdefault(len(members), []).append(members)
        self._qq_groups = [np.array(g) for g in groups.values()]  # (groups, size) per size
        self.loss_map = np.zeros((self.n_points, self.n_loss))
        for j, loss in enumerate(model.losses):
            self.loss_map[index[loss.point], j] = 1.0
        self._q_losses = np.nonzero(np.any(self.loss_map[n:] != 0.0, axis=0))[0]  # losses at algebraic points
        #: the algebraic point of each of those (a loss source sits at one point, weight 1)
        self._q_loss_point = np.array([int(np.argmax(self.loss_map[n:, j])) for j in self._q_losses], dtype=int)
        self.edge_laws = [_Law(e.g, params) for e in model.edges]
        #: the conductances the file gives between nodes (an arc's T-model has a negative one by design)
        self._given = np.array([i for i, e in enumerate(model.edges) if e.key.startswith("conductances[")], dtype=int)
        self._live: dict[tuple[int, ...], np.ndarray] = {}
        self.cap_laws = [_Law(c, params) for c in model.capacities]
        used: set[str] = set()
        for edge in model.edges:
            used |= edge.g.free()
        for name in reversed(list(model.derived)):  # derived inputs are declared in dependency order
            if name in used:
                used |= model.derived[name].free()
        #: raw inputs that enter conductances: an operating point is a value of these
        self.matrix_inputs: tuple[str, ...] = tuple(sorted(used & set(model.inputs)))
        self.derived = [(k, v.free(), v.compile()) for k, v in model.derived.items()]
        self._parameter_names = model.parameter_names

    # -- environments ---------------------------------------------------------------------
    def env(self, theta: np.ndarray, inputs: Mapping[str, Value]) -> dict[str, Value]:
        """Name -> value mapping for laws: parameters (floats), inputs and derived inputs (arrays)."""
        env: dict[str, Value] = dict(zip(self._parameter_names, np.asarray(theta, dtype=float).tolist()))
        env.update(inputs)
        for k, free, f in self.derived:
            if free <= env.keys():  # an operating point carries only the inputs conductances use
                v = f(env)
                # a scalar stays a numpy scalar (cheap arithmetic for one tick), a series an array
                env[k] = np.float64(v) if isinstance(v, (float, np.floating)) else np.asarray(v, dtype=float)
        return env

    # -- capacities -----------------------------------------------------------------------
    def capacities(self, theta: np.ndarray, wrt: Sequence[int] = ()) -> tuple[np.ndarray, np.ndarray]:
        """Capacities ``c`` (n,) in J/K and their derivatives ``dc`` (len(wrt), n)."""
        env = dict(zip(self.model.parameter_names, (float(v) for v in theta)))
        c = np.array([float(law.f(env)) for law in self.cap_laws])
        dc = np.zeros((len(wrt), self.n))
        for j, pi in enumerate(wrt):
            for i, law in enumerate(self.cap_laws):
                if pi in law.d:
                    dc[j, i] = float(law.d[pi](env))
        return c, dc

    # -- conductances ---------------------------------------------------------------------
    def live_edges(self, wrt: Sequence[int]) -> np.ndarray:
        """Edges whose conductance law depends on one of the parameters ``wrt``."""
        key = tuple(wrt)
        if key not in self._live:
            self._live[key] = np.array([e for e, law in enumerate(self.edge_laws) if any(pi in law.d for pi in wrt)], dtype=int)
        return self._live[key]

    def conductances(
        self, theta: np.ndarray, op: Mapping[str, np.ndarray], K: int, wrt: Sequence[int] = ()
    ) -> tuple[np.ndarray, np.ndarray]:
        """Edge conductances ``g`` (K, E) in W/K and ``dg`` (K, p, e) at ``K`` operating points, the
        latter for the :meth:`live_edges` of ``wrt`` only."""
        env = self.env(theta, op)
        g = np.empty((K, len(self.edge_laws)))
        for e, law in enumerate(self.edge_laws):
            g[:, e] = law.f(env)
        if len(self._given):
            self._check_given(g, op)
        return g, self._conductance_derivatives(env, K, wrt)

    def _check_given(self, g: np.ndarray, op: Mapping[str, np.ndarray]) -> None:
        """A conductance of the file negative or not finite (a division by 0) at an operating point:
        the law's error, named with that point (a law of the parameters alone is refused when the
        model is loaded)."""
        gg = g[:, self._given]
        bad = ~((gg >= 0.0) & np.isfinite(gg))
        if not bad.any():
            return
        k, i = (int(x) for x in np.argwhere(bad)[0])
        e = int(self._given[i])
        m = self.model
        at = ", ".join(f"{name} {float(np.broadcast_to(op[name], (len(g),))[k]):.4g}" for name in m.inputs if name in op)
        why = "must not be negative" if g[k, e] < 0.0 else "must be finite (a division by 0?)"
        raise ModelError(f"{m.where}: {m.edges[e].key}: the conductance is {g[k, e]:.4g} W/K at {at}: a conductance {why}")

    def _conductance_derivatives(self, env: Mapping[str, Value], K: int, wrt: Sequence[int]) -> np.ndarray:
        """``dg`` (K, p, e) of the :meth:`live_edges` of ``wrt`` in the law environment ``env``."""
        live = self.live_edges(wrt)
        dg = np.zeros((K, len(wrt), len(live)))
        for i, e in enumerate(live):
            law = self.edge_laws[e]
            for j, pi in enumerate(wrt):
                if pi in law.d:
                    dg[:, j, i] = law.d[pi](env)
        return dg

    def _assemble(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Laplacian (..., N, N) and point-boundary block (..., N, nb) from edge values (..., E)."""
        lead = g.shape[:-1]
        flat = g.reshape(-1, g.shape[-1])
        npt, nb = self.n_points, self.n_bound
        L = np.asarray((self._scatter_L.T @ flat.T).T).reshape(*lead, npt, npt)
        KU = np.asarray((self._scatter_K.T @ flat.T).T).reshape(*lead, npt, nb)
        return L, KU

    def solve_qq(self, LQQ: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """``L_QQ⁻¹ rhs`` for ``L_QQ`` (K, q, q) and ``rhs`` (K, q, r), block by block.

        The blocks (a T-model element's face points and their neighbours, at most a few points)
        are inverted and multiplied: for many right-hand sides on tiny blocks that is several
        times faster than LAPACK's solve, and as accurate for these well-conditioned blocks.
        """
        out = np.empty(np.broadcast_shapes(rhs.shape, LQQ.shape[:-1] + rhs.shape[-1:]))
        for g in self._qq_groups:  # g: (groups, size)
            blocks = LQQ[:, g[:, :, None], g[:, None, :]]
            if g.shape[1] == 1:  # single points (most of them): a division, not a LAPACK call each
                out[:, g] = rhs[:, g] / blocks
            elif g.shape[1] == 2:  # pairs: the adjugate over the determinant
                a, b, c, d = blocks[..., 0, 0], blocks[..., 0, 1], blocks[..., 1, 0], blocks[..., 1, 1]
                inv = np.stack([np.stack([d, -b], axis=-1), np.stack([-c, a], axis=-1)], axis=-2)
                out[:, g] = (inv / (a * d - b * c)[..., None, None]) @ rhs[:, g]
            else:
                out[:, g] = np.linalg.inv(blocks) @ rhs[:, g]
        return out

    def _derivatives(self, X: np.ndarray, HK: np.ndarray, HM: np.ndarray, live: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rank-one factors ``Z`` (K, n, e) and ``V`` (K, m, e) of ``dA``, ``dW`` for the ``live`` edges.

        The Schur complement's derivative with respect to one conductance is rank one: with
        ``u`` the edge's incidence vector, ``y = L_QQ⁻¹ u_Q`` and ``z = u_D − L_DQ y``,
        ``∂A/∂g = −z zᵀ`` and ``∂W/∂g = −z vᵀ`` with ``v = [ũ_U + K_QUᵀ y; M_Qᵀ y]`` (``ũ_U`` the
        edge's incidence on the boundaries). ``L_QQ`` is symmetric, so ``L_DQ y = Xᵀ u_Q``,
        ``K_QUᵀ y = HKᵀ u_Q`` and ``M_Qᵀ y = HMᵀ u_Q`` with ``X``, ``HK``, ``HM`` the solves of
        ``L_QD``, ``K_QU`` and the losses at algebraic points (K, q, ·), with one factorisation;
        ``u_Q`` has at most two entries (the edge's ends), so each product is two gathers.
        """
        n = self.n
        K = X.shape[0]
        uD = self.inc[live, :n].T
        if self.n_points > n and len(live):
            ends = [(self._end_q[k][live], self._end_s[k][live]) for k in range(2)]

            def through(H: np.ndarray) -> np.ndarray:  # Hᵀ u_Q (K, c, e)
                (qa, sa), (qb, sb) = ends
                return np.swapaxes(H[:, qa] * sa[:, None] + H[:, qb] * sb[:, None], 1, 2)

            Z = uD - through(X)
            V = np.zeros((K, self.n_bound + self.n_loss, len(live)))
            V[:, : self.n_bound] = -self.binc[live].T + through(HK)
            V[:, self.n_bound + self._q_losses] = through(HM)
        else:
            Z = np.broadcast_to(uD, (K, *uD.shape))
            V = np.broadcast_to(np.concatenate([-self.binc[live].T, np.zeros((self.n_loss, len(live)))]),
                                (K, self.n_bound + self.n_loss, len(live)))
        return np.ascontiguousarray(Z), np.ascontiguousarray(V)

    def point_temperatures(
        self, theta: np.ndarray, op: Mapping[str, np.ndarray] | None, T: np.ndarray, U: np.ndarray, P: np.ndarray
    ) -> np.ndarray:
        """Temperatures (°C) of all points, dynamic nodes first, at one operating point.

        The algebraic points follow from ``0 = M_Q P − L_QD T − L_QQ T_Q + K_QU U`` (W balance).
        """
        op = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in (op or {}).items()}
        g, _ = self.conductances(theta, op, 1)
        L, KU = self._assemble(g[0])
        n = self.n
        rhs = self.loss_map[n:] @ P - L[n:, :n] @ T + KU[n:] @ U
        if self.n_points == n:
            return np.asarray(T, float)
        return np.concatenate([T, self.solve_qq(L[None, n:, n:], rhs[None, :, None])[0, :, 0]])

    def continuous(
        self, theta: np.ndarray, op: Mapping[str, np.ndarray] | None = None, K: int = 1, wrt: Sequence[int] = (),
        solves: bool = False,
    ) -> Continuous:
        """The eliminated continuous system at ``K`` operating points (see module docstring).

        Parameters
        ----------
        theta : ndarray
            Full parameter vector (model order).
        op : mapping
            Values (arrays of length ``K``) of :attr:`matrix_inputs` (others are ignored).
        wrt : sequence of int
            Parameter indices to differentiate with respect to (none: no derivatives).
        solves : bool, optional
            Keep the solves the derivatives need (:attr:`Continuous.solves`), so that
            :meth:`derivatives` can add them later for any parameters. They are the solves the
            derivatives by ``wrt`` use: the system is the same to the last bit either way.
        """
        op = {k: np.asarray(v, dtype=float) for k, v in (op or {}).items()}
        missing = [k for k in self.matrix_inputs if k not in op]
        if missing:
            raise MissingInputError(f"operating point lacks input(s) {', '.join(missing)} of model {self.model.name}",
                                    tuple(missing))
        n, nb = self.n, self.n_bound
        g, dg = self.conductances(theta, op, K, wrt)
        L, KU = self._assemble(g)
        D, Q = slice(0, n), slice(n, None)
        LQQ, LQD = L[:, Q, Q], L[:, Q, D]
        if self.n_points > n:
            # one factorisation for the elimination and, with derivatives, the solves they need
            MQ = self.loss_map[Q][:, self._q_losses]
            full = len(wrt) or solves
            rhs = np.concatenate([LQD, KU[:, Q], np.broadcast_to(MQ, (K, *MQ.shape))], axis=-1) if full else LQD
            XH = self.solve_qq(LQQ, rhs)
            X, HK, HM = XH[..., :n], XH[..., n:n + nb], XH[..., n + nb:]
        else:
            X, HK, HM = np.zeros((K, 0, n)), np.zeros((K, 0, nb)), np.zeros((K, 0, len(self._q_losses)))
        Xt = np.swapaxes(X, -1, -2)
        A = -(L[:, D, D] - L[:, D, Q] @ X)
        B = KU[:, D, :] - Xt @ KU[:, Q, :]
        # M_D − Xᵀ M_Q: a loss source at an algebraic point q reaches the nodes through X[q]
        W = np.concatenate([B, np.broadcast_to(self.loss_map[D], (K, n, self.n_loss))], axis=-1)
        W[:, :, nb + self._q_losses] -= np.swapaxes(X[:, self._q_loss_point], 1, 2)
        c, dc = self.capacities(theta, wrt)
        cont = Continuous(A=A, W=W, c=c, solves=(X, HK, HM) if solves else None)
        if len(wrt):
            cont.dZ, cont.dV = self._derivatives(X, HK, HM, self.live_edges(wrt))
            cont.dg, cont.dc = dg, dc
        return cont

    def derivatives(self, cont: Continuous, theta: np.ndarray, op: Mapping[str, np.ndarray] | None,
                    wrt: Sequence[int]) -> Continuous:
        """``cont`` with its derivatives by the parameters ``wrt`` added, what
        :meth:`continuous` with ``wrt`` gives, from the solves ``cont`` kept (made by
        :meth:`continuous` with ``solves`` at the same ``theta`` and ``op``): no second assembly
        nor elimination."""
        if cont.solves is None:
            raise ValueError("derivatives: the continuous system kept no solves (continuous(..., solves=True))")
        op = {k: np.asarray(v, dtype=float) for k, v in (op or {}).items()}
        K = cont.A.shape[0]
        dg = self._conductance_derivatives(self.env(theta, op), K, wrt)
        _, dc = self.capacities(theta, wrt)
        dZ, dV = self._derivatives(*cont.solves, self.live_edges(wrt))
        return replace(cont, dZ=dZ, dV=dV, dg=dg, dc=dc)
