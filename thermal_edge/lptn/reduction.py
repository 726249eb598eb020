"""A reduced-order basis for large models: slow observable modes plus static (adjoint) responses.

The network is symmetrisable: ``C⁻¹A`` is similar to the symmetric ``C^-½ A C^-½``, so its modes
are real, ``C``-orthogonal vectors ``v_i`` with decay rates ``λ_i < 0``. At a reference
(parameters ``θ_ref``, operating point ``u_ref``) an output row ``s`` (a sensor or a limited
node) responds to input channel ``j`` (a boundary temperature, a loss source) through the modes
with residues ``r_isj = c_si b_ij / λ_i`` (``c = v_i[s]``, ``b = v_iᵀ W``: the mode's share of the
output's static gain is ``−r_isj``).

The basis ``V`` (``C_ref``-orthonormal, n × r) holds

* the slow modes that matter at the outputs: modes are taken in order of their largest relative
  contribution ``μ_i Σ_j |r_isj| / Σ_j |G_sj|`` (``μ_i = exp(λ_i Δt)`` at ``Δt`` = 1 s, ``G``
  the static gain) until the dropped ones sum to at most ``tol`` of every output's static gain;
* static corrections: the adjoint static responses ``A⁻¹ e_s`` of the output rows, their
  first-order changes with the operating point (``−A⁻¹ ∂A/∂u A⁻¹ e_s``) and with the strength of
  the losses' temperature feedback, optionally with parameters, and the static response to the
  boundary temperatures (a machine at rest), orthogonalised against the modes. ``A`` is
  symmetric, so a Galerkin projection whose basis holds ``A⁻¹ e_s`` reproduces the static
  response of row ``s`` to *any* input exactly: ``e_sᵀ V (VᵀAV)⁻¹ Vᵀ = e_sᵀ A⁻¹`` (write
  ``A⁻¹ e_s = V y``, then ``e_sᵀ = yᵀ VᵀA``). The steady state at the outputs is exact at the
  reference and to first order around it.

Error bound (:meth:`Reduction.bound`). In the modal coordinates at the reference the projected
system is block diagonal: the kept modes exactly, and a *correction block* (the static vectors'
part outside them) that stands for the dropped modes with the same static gain at the outputs.
For inputs held over each step of ``Δt`` a mode ``i`` of the full or the reduced model, driven by
the scalar series ``β_i = b_i · w``, deviates from its static response to the previous step's
input by at most ``μ_i osc(β_i)/|λ_i|`` (the state is an exponentially weighted mean of past
inputs; ``osc`` the range over the run), plus the decay of its initial departure. So at every
sample, for an initial state in the basis,

    |y_full − y_reduced|_s ≤ Σ_{dropped and correction modes i} |c_si| μ_i osc(β_i) / |λ_i|

for the system at the reference with the losses taken as inputs (their series over the run).
Other operating points and parameters, and the temperature feedback of the losses, are not
covered by it: :mod:`.reduced` and the ladder benchmark measure the error against the full
model beside the bound.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .losses import LossLaws
from .model import Model, ModelError
from .network import Network

#: default tolerance: the dropped modes' share of each output's static gain (at Δt = 1 s)
TOL = 3e-3
#: singular values of the static vectors below this fraction of the largest are dependent
RANK_TOL = 1e-10


@dataclass(frozen=True)
class Reduction:
    """A reduced basis of a model and what its error bound needs.

    Attributes
    ----------
    V : ndarray (n, r)
        The basis, ``C_ref``-orthonormal (``Vᵀ diag(c_ref) V = I``); the first :attr:`modes`
        columns are modes at the reference.
    modes : int
        Modes kept.
    c_ref : ndarray (n,)
        Capacities at the reference, J/K: the initial state of a run is projected with them.
    theta : ndarray
        Reference parameters (model order).
    op : dict
        Reference operating point: values of the inputs that enter conductances.
    rows : tuple of str
        The output nodes the basis was chosen for (sensors, then limited nodes).
    lam_dropped, c_dropped, b_dropped : ndarray
        Decay rates (1/s) of the dropped modes, how the output rows read them (rows, m) and how
        the input channels drive them (m, channels).
    lam_corr, c_corr, b_corr : ndarray
        The same for the modes of the correction block.
    tol : float
        The tolerance the modes were chosen with.
    """

    V: np.ndarray
    modes: int
    c_ref: np.ndarray
    theta: np.ndarray
    op: dict[str, float]
    rows: tuple[str, ...]
    lam_dropped: np.ndarray
    c_dropped: np.ndarray
    b_dropped: np.ndarray
    lam_corr: np.ndarray
    c_corr: np.ndarray
    b_corr: np.ndarray
    tol: float

    @property
    def size(self) -> int:
        """Dimension of the reduced model."""
        return int(self.V.shape[1])

    def bound(self, dt: float, w: np.ndarray) -> np.ndarray:
        """The error bound (K) of each output row over a run (see the module docstring).

        Each dropped or correction mode ``i`` is driven by the scalar series ``β_i = b_i · w``; it
        deviates from its static response by at most ``μ_i osc(β_i)/|λ_i|``, which row ``s``
        reads with weight ``|c_si|``. (``osc(b·w) ≤ Σ_j |b_j| osc(w_j)``: inputs that move together,
        as the losses of one law at many nodes do, are counted together.)

        Parameters
        ----------
        dt : float
            Step of the run, s.
        w : ndarray (N, channels)
            The run's inputs at each step: boundary temperatures (°C), then the loss sources (W).
        """
        w = np.asarray(w, dtype=float)
        out: np.ndarray = np.zeros(len(self.rows))
        for lam, c, b in ((self.lam_dropped, self.c_dropped, self.b_dropped), (self.lam_corr, self.c_corr, self.b_corr)):
            if len(lam) and len(w):
                beta = w @ b.T  # (N, m)
                out += np.abs(c) @ (np.exp(lam * dt) * np.ptp(beta, axis=0) / np.abs(lam))
        return out


def output_rows(model: Model) -> tuple[str, ...]:
    """The nodes a reduced model is built to reproduce: the sensors, then the limited nodes."""
    seen: dict[str, None] = {}
    for x in (*model.sensors.values(), *(lim.node for lim in model.limits)):
        seen.setdefault(x, None)
    return tuple(seen)


def check_reducible(model: Model, net: Network | None = None) -> None:
    """Refuse a model the reduced path does not handle.

    Raises
    ------
    ModelError
        The model has algebraic points (the reduced operators are built from the lumped
        network's incidence), a loss law not affine in the temperatures, or no output node.
    """
    net = Network(model) if net is None else net
    if net.n_points != net.n:
        raise ModelError(f"model {model.name}: the reduced path needs a lumped network (it has "
                         f"{net.n_points - net.n} algebraic points)")
    laws = LossLaws(model)
    if laws.nonaffine:
        bad = model.losses[laws.nonaffine[0]].key
        raise ModelError(f"model {model.name}: {bad}: the reduced path needs loss laws affine in the temperatures")
    if not output_rows(model):
        raise ModelError(f"model {model.name}: the reduced path needs a sensor or a limit to reproduce")


def reduce(model: Model, theta: np.ndarray | None = None, op: Mapping[str, float] | None = None,
           tol: float = TOL, derivatives: Sequence[str] = (), dt: float = 1.0,
           net: Network | None = None) -> Reduction:
    """Build the reduced basis of ``model`` at a reference (see the module docstring).

    Parameters
    ----------
    model : Model
        A lumped network with loss laws affine in the temperatures (:func:`check_reducible`).
    theta : ndarray, optional
        Reference parameters (default nominal).
    op : mapping, optional
        Reference values of the inputs that enter conductances (default 0: standstill).
    tol : float
        The dropped modes' share of each output's static gain, at the step ``dt``.
    derivatives : sequence of str, optional
        Parameters whose first-order change the static vectors follow (default none: on the
        generated chain models they double the basis to move the outputs by a few mK).
    dt : float
        The step (s) the modes are chosen for: a mode that decays within a step hardly matters.
    net : Network, optional
        The model's network, when the caller has it (building one takes a while for large models).

    Returns
    -------
    Reduction
    """
    net = Network(model) if net is None else net
    check_reducible(model, net)
    n = net.n
    theta = model.nominal() if theta is None else np.asarray(theta, dtype=float)
    ref = {k: float((op or {}).get(k, 0.0)) for k in net.matrix_inputs}
    names = tuple(derivatives)
    wrt = list(model.parameter_index(names)) if names else []
    cont = net.continuous(theta, {k: np.array([v]) for k, v in ref.items()}, 1, wrt)
    A, W, c = cont.A[0], cont.W[0], cont.c
    s = np.sqrt(c)
    lam, Q = np.linalg.eigh(A / np.outer(s, s))
    Vf = Q / s[:, None]  # C-orthonormal modes
    rows = output_rows(model)
    ri = np.array([model.node_index(x) for x in rows])
    B = Q.T @ (W / s[:, None])  # (n, channels)
    res = Vf[ri].T[:, :, None] * B[:, None, :] / lam[:, None, None]  # (n, rows, channels)
    keep = _choose_modes(lam, res, tol, dt)
    drop = np.setdiff1d(np.arange(n), keep)
    Vm = Vf[:, keep]
    # static corrections: adjoint static responses of the rows and their parameter derivatives
    E = np.zeros((n, len(ri)))
    E[ri, np.arange(len(ri))] = 1.0
    X0 = np.linalg.solve(A, E)
    # and the static response to the boundary temperatures (a machine at rest is at them: a
    # uniform state), so that such an initial state is in the basis
    parts = [X0, np.linalg.solve(A, W[:, : net.n_bound])]
    if wrt:
        # ∂A/∂θ_j = −Z diag(dg_j) Zᵀ (rank-one factors of the edges): all parameters in one solve
        assert cont.dZ is not None and cont.dg is not None
        Z, dg = cont.dZ[0], cont.dg[0]
        ZX = Z.T @ X0  # (e, rows)
        dAX = -np.concatenate([Z @ (dg[j][:, None] * ZX) for j in range(len(wrt))], axis=1)
        parts.append(-np.linalg.solve(A, dAX))
    parts += _operating_point_vectors(net, theta, ref, A, X0)
    parts += _feedback_vectors(model, net, theta, A, X0)
    X = np.concatenate(parts, axis=1)
    X -= Vm @ (Vm.T @ (c[:, None] * X))  # C-orthogonal to the kept modes
    U, sv, _ = np.linalg.svd(s[:, None] * X, full_matrices=False)
    Vc = U[:, sv > RANK_TOL * sv[0]] / s[:, None] if len(sv) and sv[0] > 0 else np.zeros((n, 0))
    # the correction block's own modes at the reference, for the bound
    lc, Qc = np.linalg.eigh(Vc.T @ A @ Vc)
    Wc = Vc @ Qc
    # orthonormal to round-off (the projection of an initial state relies on it): a QR keeps the
    # span of every leading block of columns, so the modes stay first
    Qv, Rv = np.linalg.qr(s[:, None] * np.concatenate([Vm, Vc], axis=1))
    V = Qv * np.sign(np.diag(Rv)) / s[:, None]
    return Reduction(V=V, modes=len(keep), c_ref=c.copy(), theta=theta.copy(), op=ref,
                     rows=rows, lam_dropped=lam[drop], c_dropped=Vf[np.ix_(ri, drop)], b_dropped=B[drop], lam_corr=lc,
                     c_corr=Wc[ri], b_corr=Wc.T @ W, tol=tol)


def _choose_modes(lam: np.ndarray, res: np.ndarray, tol: float, dt: float = 1.0) -> np.ndarray:
    """Indices (ascending) of the fewest modes, taken by relevance, whose dropped rest contributes
    at most ``tol`` of every output's static gain (with unit input ranges, at step ``dt``)."""
    e = np.exp(lam * dt)[:, None] * np.abs(res).sum(axis=2)  # (n, rows)
    gain = np.abs(res.sum(axis=0)).sum(axis=1)  # static gain of each row over all channels
    gain = np.where(gain > 0, gain, np.inf)  # a row nothing reaches asks for no mode
    rel = e / gain
    order = np.argsort(-rel.max(axis=1), kind="stable")
    rest = np.concatenate([np.cumsum(rel[order][::-1], axis=0)[::-1], np.zeros((1, rel.shape[1]))])
    k = int(np.argmax(rest.max(axis=1) <= tol))
    return np.sort(order[:k])


def _operating_point_vectors(net: Network, theta: np.ndarray, ref: dict[str, float], A: np.ndarray,
                             X0: np.ndarray) -> list[np.ndarray]:
    """``−A⁻¹ ∂A/∂u A⁻¹ e_s`` for each input ``u`` that enters conductances: the first-order change
    of the rows' static responses with the operating point. ``∂g/∂u`` is a one-sided difference
    (laws such as ``|n|^0.8`` have no two-sided one at standstill); only its pattern over the
    edges matters, the vectors are orthonormalised."""
    if not ref:
        return []
    n = net.n
    inc = net.inc[:, :n]
    base = {k: np.array([v]) for k, v in ref.items()}
    g0, _ = net.conductances(theta, base, 1)
    out = []
    ZX = inc @ X0  # (E, rows)
    for k, v in ref.items():
        h = 1e-4 * max(abs(v), 1.0)
        g1, _ = net.conductances(theta, {**base, k: np.array([v + h])}, 1)
        dg = (g1[0] - g0[0]) / h
        if np.any(dg):
            out.append(np.linalg.solve(A, inc.T @ (dg[:, None] * ZX)))
    return out


def _feedback_vectors(model: Model, net: Network, theta: np.ndarray, A: np.ndarray, X0: np.ndarray) -> list[np.ndarray]:
    """``A⁻¹ F A⁻¹ e_s`` with ``F = M_D ∂P/∂T`` the temperature feedback of the losses: the first-order
    change of the rows' static responses with the feedback's strength (a copper loss's slope grows
    with the current squared; its pattern over the nodes, taken at unit inputs, stays)."""
    laws = LossLaws(model)
    if not laws.temperature_dependent:
        return []
    env = net.env(theta, {k: np.ones(1) for k in model.inputs})
    D = laws.dT(env, None, 1)[0]  # (n_loss, ntv)
    F = net.loss_map[: net.n] @ D  # (n, ntv): columns at the nodes the laws read
    return [np.linalg.solve(A, F @ X0[laws.nodes])]
