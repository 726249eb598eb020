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

Both ``Φ`` are functions of ``C⁻¹A = V Λ V⁻¹`` with ``V = C^-½ Q`` (``Q`` the orthonormal
eigenvectors of ``Ã``), so the derivatives are kept in that modal basis, ``dΦ̃ = V⁻¹ dΦ V`` and
``dΓ̃ = V⁻¹ dΓ``, where ZOH gets them from the rank-one factors of ``dA`` and ``dW`` without any
dense product per parameter; :attr:`Discrete.dPhi` and :attr:`Discrete.dGam` give the dense
node-coordinate forms on demand. The method is the type of the result: :class:`Discrete`
without derivatives, :class:`ZohDerivatives` or :class:`EulerDerivatives` with them;
:func:`derive` adds the derivatives to a discretisation already made, from its eigendecomposition.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from ..errors import ThermalEdgeError
from .network import Continuous


class UnstableDiscretisation(ThermalEdgeError, ValueError):
    """Explicit Euler would diverge at the requested step."""


class NotPassive(ThermalEdgeError, ValueError):
    """The network's system matrix is not negative definite (a node not tied to any boundary, or a
    non-passive T-model)."""


@dataclass(frozen=True)
class Discrete:
    """``Φ`` (K, n, n) and ``Γ`` (K, n, m) of one step at ``K`` operating points, and the modal basis.

    The modal basis of operating point ``k`` is ``V_k = diag(1/s) Q_k``: ``Φ = V diag(mu) V⁻¹``
    and ``V⁻¹ (Φ − I) A⁻¹ = diag(phi) Q_kᵀ diag(1/s)`` (``phi = (mu − 1)/λ``, positive). Both
    methods give this; the derivatives, which they compute differently, are in the subclasses
    :class:`ZohDerivatives` and :class:`EulerDerivatives` (:func:`discretise` returns one of them
    when the continuous system carries derivatives).
    """

    Phi: np.ndarray
    Gam: np.ndarray
    substeps: int  # Euler sub-steps per step (1 for ZOH)
    s: np.ndarray  # √c (n,)
    Q: np.ndarray  # orthonormal eigenvectors of C^-½ A C^-½ (K, n, n)
    mu: np.ndarray  # eigenvalues of Φ (K, n)
    phi: np.ndarray  # (mu − 1)/λ (K, n)
    lam: np.ndarray  # eigenvalues λ of C⁻¹A (K, n), 1/s

    def basis(self, ops: int | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The modal basis ``V = diag(1/s) Q`` of ``Φ`` at these operating points, and ``V⁻¹``."""
        Q = self.Q[ops]
        return Q / self.s[:, None], np.swapaxes(Q, -1, -2) * self.s


@dataclass(frozen=True)
class DiscreteDerivatives(Discrete):
    """A discretisation with its exact derivatives by ``p`` parameters, in the modal basis.

    ``V⁻¹ dΦ_j V`` is built per operating point when first needed (:meth:`dphit`, by the
    method's :meth:`_build`); :meth:`forcing` applies it to vectors. ``V⁻¹ dΓ_j`` is kept
    factored, ``dPhit_j Ht − diag(phi) Zh diag(dg_j) Yt`` with ``Ht = V⁻¹ A⁻¹ W`` (K, n, m),
    ``Zh = Qᵀ C^-½ Z`` (K, n, e), ``Yt = Vᵀ − Zᵀ A⁻¹ W`` (K, e, m) from the rank-one factors of
    :class:`~thermal_edge.lptn.network.Continuous`: ``dΓ w = V (dPhit (Ht w) − phi ∘ Zh (dg ∘ Yt w))``
    costs no more than ``dΦ T``.
    """

    Ht: np.ndarray
    Zh: np.ndarray
    Yt: np.ndarray
    dg: np.ndarray  # (K, p, e) derivatives of the edges' conductances
    _dense: dict[int, np.ndarray] = field(default_factory=dict, init=False, repr=False, compare=False)
    _joined: dict[int, np.ndarray] = field(default_factory=dict, init=False, repr=False, compare=False)

    def _build(self, ops: np.ndarray) -> np.ndarray:
        """``V⁻¹ dΦ_j V`` (len(ops), p, n, n) at these operating points (the method's own way)."""
        raise NotImplementedError

    def _forcing_rows(self, o: np.ndarray, y: np.ndarray, low: np.ndarray) -> np.ndarray:
        """:meth:`forcing` with one operating point per row; ``low = phi ∘ v`` (B, n, e)."""
        raise NotImplementedError

    def build_dphit(self, ops: int | Sequence[int] | np.ndarray) -> None:
        """Build ``V⁻¹ dΦ_j V`` at these operating points where not built yet (together: cheaper
        than one by one)."""
        todo = sorted({int(o) for o in np.atleast_1d(ops)} - self._dense.keys())
        if todo:
            self._dense.update(zip(todo, self._build(np.array(todo))))

    def dphit(self, ops: int | Sequence[int] | np.ndarray) -> np.ndarray:
        """``V⁻¹ dΦ_j V`` (len(ops), p, n, n) at the given operating points (built once each);
        (p, n, n) for a single one."""
        self.build_dphit(ops)
        ops = np.asarray(ops)
        if ops.ndim == 0:
            return self._dense[int(ops)]
        if not len(ops):
            return np.zeros((0, self.dg.shape[1], self.Phi.shape[1], self.Phi.shape[1]))
        return np.stack([self._dense[int(o)] for o in ops])

    def forcing(self, o: int | np.ndarray, y: np.ndarray, v: np.ndarray, left: np.ndarray | None = None) -> np.ndarray:
        """``V⁻¹ (dΦ_j T_i + dΓ_j w_i)`` (B, n, p) from ``y = V⁻¹ T + Ht w`` (B, n) and
        ``v = Yt w`` (B, e): ``dPhit_j y − phi ∘ Zh (dg_j ∘ v)``.

        ``o`` is one operating point for all rows (its dense ``dPhit``: one product for all rows
        and parameters) or one per row (B,), which each method does its own way
        (:meth:`_forcing_rows`). With one operating point, ``left`` (n, n) gives the forcing in
        another basis, ``left V⁻¹ (...)``, folded into the factors (no product per row).
        """
        p, B = self.dg.shape[1], len(y)
        if np.ndim(o) == 0:
            n = len(self.phi[o])
            dp, low = self.dphit(o), self.phi[o][:, None] * self.Zh[o]
            if left is not None:
                dp, low = left @ dp, left @ low
            X: np.ndarray = (dp.reshape(p * n, n) @ y.T).reshape(p, n, B).transpose(2, 1, 0)
            lowv = (v[:, :, None] * self.dg[o].T).transpose(1, 0, 2).reshape(-1, B * p)  # (e, B p)
            X -= (low @ lowv).reshape(n, B, p).transpose(1, 0, 2)
            return X
        return self._forcing_rows(np.asarray(o), y, self.phi[o][:, :, None] * v[:, None, :])

    def joined(self, o: int) -> np.ndarray:
        """``[dPhit_j | V⁻¹ dΓ_j]`` (n p, n + m) at operating point ``o``, rows mode-major
        (row ``a p + j``: mode ``a``, parameter ``j``); built once per operating point.

        With ``ξ = [V⁻¹ T; w]`` (n + m, B) one product gives the forcing ``V⁻¹ (dΦ_j T + dΓ_j w)``
        of ``B`` steps as (n, p, B), time last (what a filter in time wants): the factored ``dΓ``
        folded into a dense block costs ``m`` columns instead of a gather and scatter over the
        edges of every parameter (:meth:`forcing`).
        """
        key = int(o)
        if key not in self._joined:
            p, n = self.dg.shape[1], self.Phi.shape[1]
            dp = self.dphit(key)
            low = (self.Zh[key][None] * self.dg[key][:, None, :]) @ self.Yt[key]  # (p, n, m)
            dgam = dp @ self.Ht[key] - self.phi[key][None, :, None] * low
            both = np.concatenate([dp, dgam], axis=2)  # (p, n, n + m)
            self._joined[key] = np.ascontiguousarray(both.transpose(1, 0, 2)).reshape(n * p, -1)
        return self._joined[key]

    @property
    def dPhit(self) -> np.ndarray:
        """``V⁻¹ ∂Φ/∂θ_j V`` (K, p, n, n) at every operating point."""
        return self.dphit(np.arange(self.Phi.shape[0]))

    @property
    def dGamt(self) -> np.ndarray:
        """``V⁻¹ ∂Γ/∂θ_j`` (K, p, n, m)."""
        low = (self.Zh[:, None] * self.dg[:, :, None, :]) @ self.Yt[:, None]
        out: np.ndarray = self.dPhit @ self.Ht[:, None] - self.phi[:, None, :, None] * low
        return out

    @property
    def dPhi(self) -> np.ndarray:
        """``∂Φ/∂θ_j`` (K, p, n, n) in node coordinates."""
        V, Vi = self.basis(np.arange(self.Phi.shape[0]))
        return sandwich(V, self.dPhit, Vi)

    @property
    def dGam(self) -> np.ndarray:
        """``∂Γ/∂θ_j`` (K, p, n, m) in node coordinates."""
        out: np.ndarray = self.basis(np.arange(self.Phi.shape[0]))[0][:, None] @ self.dGamt
        return out


@dataclass(frozen=True)
class ZohDerivatives(DiscreteDerivatives):
    """Zero-order hold: ``dΦ`` by the Daleckii–Krein formula from the divided differences ``Dd``
    (K, n, n) of exp, the capacity term ``Wc`` (K, n, n; None when no parameter is a capacity) and
    ``r = dc/2c`` (p, n) (:func:`_zoh_dense`)."""

    Dd: np.ndarray
    Wc: np.ndarray | None
    r: np.ndarray

    def _build(self, ops: np.ndarray) -> np.ndarray:
        return _zoh_dense(self.Dd[ops], None if self.Wc is None else self.Wc[ops], self.Zh[ops], self.dg[ops],
                          self.Q[ops], self.r)

    def _forcing_rows(self, o: np.ndarray, y: np.ndarray, low: np.ndarray) -> np.ndarray:
        """Edge by edge, ``(ẑ ẑᵀ ∘ D) y = ẑ ∘ (D (ẑ ∘ y))``, joined with the factored ``dΓ`` in one
        product: about ``n² (e + nc)`` flops a row, cheaper than building ``dPhit`` for an
        operating point that a few steps use (a ramp)."""
        Zh = self.Zh[o]  # (B, n, e)
        X: np.ndarray = (Zh * -(self.Dd[o] @ (Zh * y[:, :, None]) + low)) @ np.swapaxes(self.dg[o], 1, 2)
        nz = np.nonzero(np.any(self.r != 0.0, axis=0))[0]
        if len(nz):
            assert self.Wc is not None
            Qc = np.swapaxes(self.Q[o][:, nz, :], 1, 2)  # (B, n, nc)
            X += (Qc * (self.Wc[o] @ (Qc * y[:, :, None]))) @ self.r[:, nz].T
        return X


@dataclass(frozen=True)
class EulerDerivatives(DiscreteDerivatives):
    """Explicit Euler with sub-steps: ``V⁻¹ dΦ_j V`` (K, p, n, n) computed densely at once
    (:func:`_euler_derivatives`)."""

    dense: np.ndarray

    def _build(self, ops: np.ndarray) -> np.ndarray:
        out: np.ndarray = self.dense[ops]
        return out

    def _forcing_rows(self, o: np.ndarray, y: np.ndarray, low: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.einsum("bjac,bc->baj", self.dphit(o), y) - (self.Zh[o] * low) @ np.swapaxes(self.dg[o], 1, 2)
        return out


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
    out: np.ndarray = (a @ right).reshape(K, p, n, n)
    return out


#: explicit Euler needs a spectral radius below 1 by more than the eigenvalues' round-off
EULER_MARGIN = 1e-9


#: sub-steps explicit Euler takes on its own at most (without ``max_substep_s``): beyond, the
#: model's fastest node is too fast for the method at this step (zoh is the method for it)
MAX_AUTO_SUBSTEPS = 1000


def euler_substeps(lam: np.ndarray, dt: float, max_substep: float | None) -> int:
    """Number of Euler sub-steps: ``ceil(dt / max_substep)``; refuses if that is unstable.

    Without ``max_substep``: one step where that is stable, else as few equal sub-steps as are
    (with a margin: ``h |λ| ≤ 1.8``), so that a step longer than the model was written for (an
    adapter's decimated window, a candidate of a fit with a small capacity) stays stable; more
    than :data:`MAX_AUTO_SUBSTEPS` are refused. ``lam`` are the eigenvalues (1/s, negative) of
    ``C⁻¹A`` over all operating points.
    """
    fastest = float(-lam.min()) if lam.size else 0.0
    if max_substep is None:
        m = 1 if 1.0 - dt * fastest > -1.0 + EULER_MARGIN else math.ceil(dt * fastest / 1.8)
        m = min(m, MAX_AUTO_SUBSTEPS + 1)  # beyond: refused below
    else:
        m = max(1, math.ceil(dt / max_substep - 1e-9))
    h = dt / m
    if m > MAX_AUTO_SUBSTEPS:
        raise UnstableDiscretisation(
            f"explicit Euler would need more than {MAX_AUTO_SUBSTEPS} sub-steps of the {dt:g} s step (the fastest "
            f"node's time constant is {1.0 / fastest:.3g} s); use method zoh"
        )
    # the eigenvalues are negative: the radius reaches 1 on the side of the fastest mode, 1 + h λ = -1
    # (an undamped oscillation), which round-off may compute a hair inside
    if 1.0 + h * float(lam.min()) <= -1.0 + EULER_MARGIN:
        rho = float(np.max(np.abs(1.0 + h * lam)))
        h_max = 2.0 / fastest
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
    Qt = np.swapaxes(Qm, -1, -2)
    if method == "zoh":
        m = 1
        x = lam * dt
        mu = np.exp(x)
        phi = np.expm1(x) / lam
        # Φ − I from expm1 so that slow modes (Φ ≈ I) keep their digits in Γ = (Φ − I) H
        Em1 = (Qm * np.expm1(x)[:, None, :]) @ Qt
        PmI = Em1 / s[:, None] * s[None, :]
    elif method == "euler":
        m = euler_substeps(lam, dt, max_substep)
        h = dt / m
        mu = (1.0 + h * lam) ** m
        pos = 1.0 + h * lam > 0.0  # there μ − 1 = expm1(m log1p(hλ)), without cancellation
        phi = np.where(pos, np.expm1(m * np.log1p(np.where(pos, h * lam, 0.0))), mu - 1.0) / lam
        F = cont.A / cont.c[:, None]
        Phi1 = eye + h * F
        PmI = h * F
        for _ in range(m - 1):  # Φ1^(k+1) − I = Φ1 (Φ1^k − I) + (Φ1 − I), without cancellation
            PmI = Phi1 @ PmI + h * F
    else:
        raise ValueError(f"unknown discretisation method {method!r} (zoh, euler)")
    Phi = PmI + eye
    # Γ = (Φ − I) A⁻¹ W = V diag(phi) V⁻¹ C⁻¹ W with V = C^-½ Q: through the eigenvectors (two
    # products) instead of a solve, and with phi = (μ − 1)/λ the slow modes keep their digits
    QtW = Qt @ (cont.W / s[:, None])  # V⁻¹ C⁻¹ W
    d = Discrete(Phi=Phi, Gam=(Qm * phi[:, None, :]) @ QtW / s[:, None], substeps=m, s=s, Q=Qm, mu=mu, phi=phi,
                 lam=lam)
    return d if cont.dg is None else derive(d, cont, dt, method)


def derive(d: Discrete, cont: Continuous, dt: float, method: str = "zoh") -> DiscreteDerivatives:
    """The discretisation ``d`` of ``cont`` with the exact derivatives ``cont`` carries.

    ``d`` is :func:`discretise` of ``cont`` without derivatives (the same ``A``, ``W``, ``c``,
    ``dt`` and ``method``); its eigendecomposition serves the derivatives, so that a simulation
    can be followed by its sensitivities without discretising again: ``derive(discretise(c), c')``
    is ``discretise(c')`` to the last bit when ``c'`` is ``c`` with derivatives.
    """
    assert cont.dc is not None and cont.dZ is not None and cont.dV is not None and cont.dg is not None
    s, Qm, lam = d.s, d.Q, d.lam
    Qt = np.swapaxes(Qm, -1, -2)
    QtW = Qt @ (cont.W / s[:, None])  # V⁻¹ C⁻¹ W
    values = {f.name: getattr(d, f.name) for f in fields(Discrete)}
    H = (Qm * (1.0 / lam)[:, None, :]) @ QtW / s[:, None]  # A⁻¹ W = V diag(1/λ) V⁻¹ C⁻¹ W
    factors = dict(
        Ht=QtW / lam[:, :, None],  # V⁻¹ H
        Zh=Qt @ (cont.dZ / s[:, None]),
        Yt=np.swapaxes(cont.dV, -1, -2) - np.swapaxes(cont.dZ, -1, -2) @ H,
        dg=cont.dg,
    )
    if method == "zoh":
        Dd, Wc, r = _zoh_divided_differences(cont, dt, lam, d.mu)
        return ZohDerivatives(**values, **factors, Dd=Dd, Wc=Wc, r=r)
    if method != "euler":
        raise ValueError(f"unknown discretisation method {method!r} (zoh, euler)")
    m = d.substeps
    h = dt / m
    Phi1 = np.eye(cont.A.shape[-1]) + h * (cont.A / cont.c[:, None])
    Vi = Qt * s  # V⁻¹
    return EulerDerivatives(**values, **factors, dense=sandwich(Vi, _euler_derivatives(cont, Phi1, h, m), Qm / s[:, None]))


def _zoh_divided_differences(cont: Continuous, dt: float, lam: np.ndarray,
                             mu: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """``D`` (K, n, n), ``Wc`` (K, n, n) or None, and ``r`` (p, n) of the ZOH derivative (:func:`_zoh_dense`)."""
    assert cont.dc is not None
    # divided differences of exp(λ dt) w.r.t. λ, (e^a − e^b)/(a − b) · dt with a = λ dt, written as
    # e^max(a,b) · (1 − e^−|a−b|)/|a−b| so that neither overflows nor cancels (expm1 keeps its
    # digits for close eigenvalues; equal ones have the limit 1)
    x = lam * dt
    ad = np.subtract(x[:, :, None], x[:, None, :])
    np.abs(ad, out=ad)
    q = np.negative(ad)
    np.expm1(q, out=q)
    with np.errstate(invalid="ignore"):
        q /= ad  # −(1 − e^−|a−b|)/|a−b|
    q[ad == 0.0] = -1.0
    Dd = np.maximum(mu[:, :, None], mu[:, None, :])
    Dd *= q
    Dd *= -dt
    r = cont.dc / (2.0 * cont.c)
    Wc = None
    if np.any(r):
        Wc = np.subtract(mu[:, :, None], mu[:, None, :])
        q = np.add(lam[:, :, None], lam[:, None, :], out=q)
        q *= Dd
        Wc -= q
    return Dd, Wc, r


def _zoh_dense(Dd: np.ndarray, Wc: np.ndarray | None, Zh: np.ndarray, dg: np.ndarray, Qm: np.ndarray,
               r: np.ndarray) -> np.ndarray:
    """``V⁻¹ dΦ_j V`` (K, p, n, n) of the ZOH step, from the rank-one factors of ``dA``.

    In the basis ``Q`` of ``Ã`` the derivative of ``exp(Ã dt)`` is ``(Qᵀ dÃ Q) ∘ D`` with ``D``
    the divided differences of ``exp`` on the eigenvalues (Daleckii–Krein). With ``r = dc/2c``
    and ``R = Qᵀ diag(r) Q``: ``Qᵀ dÃ Q = −Zh diag(dg) Zhᵀ − R ∘ (λ_a + λ_b)``, and the
    similarity ``C^-½`` adds ``R ∘ (μ_a − μ_b)``: a capacity parameter adds ``R ∘ Wc`` with
    ``Wc = μ_a − μ_b − (λ_a + λ_b) D``.
    """
    K, n, _ = Dd.shape
    p = dg.shape[1]
    dPhit = np.empty((K, p, n, n))
    for j in range(p):
        e = np.nonzero(np.any(dg[:, j] != 0.0, axis=0))[0]  # the few edges of this parameter
        if len(e):
            Zg = Zh[:, :, e] * dg[:, j][:, e][:, None, :]
            np.matmul(-Zg, np.swapaxes(Zh[:, :, e], -1, -2), out=dPhit[:, j])
            dPhit[:, j] *= Dd
        else:
            dPhit[:, j] = 0.0
        nz = np.nonzero(r[j])[0]  # the nodes whose capacity depends on it
        if len(nz):
            assert Wc is not None
            Qn = Qm[:, nz, :]
            dPhit[:, j] += (np.swapaxes(Qn, -1, -2) @ (r[j, nz, None] * Qn)) * Wc
    return dPhit


def _euler_derivatives(cont: Continuous, Phi1: np.ndarray, h: float, m: int) -> np.ndarray:
    """``dΦ_j`` (K, p, n, n) of ``m`` Euler sub-steps ``Φ = Φ1^m``, ``Φ1 = I + h C⁻¹A``."""
    assert cont.dc is not None and cont.dA is not None
    n = Phi1.shape[-1]
    F = cont.A / cont.c[:, None]
    dPhi1: np.ndarray = h * (cont.dA - cont.dc[None, :, :, None] * F[:, None]) / cont.c[None, None, :, None]
    if m == 1:
        return dPhi1
    pows = [np.broadcast_to(np.eye(n), Phi1.shape)]
    for _ in range(m - 1):
        pows.append(pows[-1] @ Phi1)
    out: np.ndarray = sum(pows[i][:, None] @ dPhi1 @ pows[m - 1 - i][:, None] for i in range(m))
    return out
