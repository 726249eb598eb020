"""The linear recursion of a stretch of steps with one discretisation, run vectorised in time.

Over steps where the operating point (and so ``Φ``, ``Γ``) stays the same, the simulation and the
sensitivities both follow

    x[k+1] = Φ x[k] + f[k] + Γ_P D[k] x[k][tv]

with a forcing ``f`` known for the whole stretch in advance (inputs, or the sensitivities'
``dΦ T + dΓ w``) and the temperature feedback of the losses ``D[k] = ∂P/∂T`` at step ``k`` (loss
sources × loss nodes; it changes every step when the current does). In the modal basis of ``Φ``
(``Φ = V diag(μ) V⁻¹`` with real ``0 < μ < 1``, :class:`~thermal_edge.lptn.discretise.Discrete`)
the open loop is ``n`` independent first-order filters, run in time by blocked matrix products
(:func:`modal_scan`) over all modes and columns at once.

The feedback enters only through the few loss nodes. Writing ``y[k] = E x[k]`` for their rows
(``E = V[tv]``), the stretch is the fixed point of ``y = y₀ + 𝓛(D y)`` with ``𝓛`` the strictly
causal filter from the loss inputs to the loss nodes. The iteration ``y ← y₀ + 𝓛(D y)`` is
exact in the limit: its ``m``-th iterate equals the true ``y`` on the first ``m`` steps of the
stretch (causality), and beyond them the error contracts by the loop gain ``‖𝓛‖·max‖D‖``
(a resistance times ``∂P/∂T``: a few per cent for a copper loss). It stops when an iteration
changes nothing at round-off (``ROUND_OFF`` of the largest entry); a stretch that does not
converge within ``MAX_ITER`` iterations is reported so the caller can step it instead.
"""
from __future__ import annotations

import numpy as np

#: an iteration that changes the loss nodes' values by less than this fraction of their
#: largest magnitude has converged (the stepped recursion's own round-off is of this order)
ROUND_OFF = 1e-14
#: iterations of the feedback before a stretch is given back to the step-by-step recursion
MAX_ITER = 40
#: shortest stretch of one operating point run vectorised (its set-up costs about this many steps)
MIN_STRETCH = 32
#: steps per block of :func:`modal_scan` (its flops grow with it, its passes over the blocks shrink)
BLOCK = 16


def modal_scan(mu: np.ndarray, f: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """``x[k+1] = μ ∘ x[k] + f[k]``, ``k = 0 .. L−1``, for all modes and columns at once.

    In blocks of :data:`BLOCK` steps: inside a block, each mode's response to the block's
    forcing is one product with the lower-triangular Toeplitz matrix of ``μ^(i−l)`` (a batched
    matrix product over the modes); the states at the block starts follow the same recursion
    with ``μ^BLOCK`` over the blocks' end values (this function, one level up).

    Parameters
    ----------
    mu : ndarray (n,)
        Eigenvalues of the transition (dimensionless, in [0, 1)).
    f : ndarray (n, L, c)
        Forcing per mode, step and column (the units of ``x``).
    x0 : ndarray (n, c)
        State at the stretch's first step.

    Returns
    -------
    ndarray (n, L, c)
        ``x[1] .. x[L]``.
    """
    n, L, c = f.shape
    B = BLOCK if L > BLOCK else L
    nb = -(-L // B)
    if nb * B != L:
        f = np.concatenate([f, np.zeros((n, nb * B - L, c))], axis=1)
    with np.errstate(under="ignore"):
        pw = mu[:, None] ** np.arange(B + 1)  # (n, B+1), integer powers
    i = np.arange(B)
    lag = i[:, None] - i[None, :]
    toep = np.where(lag >= 0, pw[:, np.maximum(lag, 0)], 0.0)  # (n, B, B)
    fb = f.reshape(n, nb, B, c).transpose(0, 2, 1, 3).reshape(n, B, nb * c)
    inner = (toep @ fb).reshape(n, B, nb, c)  # zero-state response inside each block
    if nb == 1:
        starts = x0[:, None]
    else:
        ends = modal_scan(pw[:, B], np.ascontiguousarray(inner[:, B - 1, :-1]), x0)
        starts = np.concatenate([x0[:, None], ends], axis=1)  # (n, nb, c)
    inner += pw[:, 1:, None, None] * starts[:, None]
    return inner.transpose(0, 2, 1, 3).reshape(n, nb * B, c)[:, :L]


def solve_stretch(mu: np.ndarray, f: np.ndarray, x0: np.ndarray, G: np.ndarray | None = None,
                  E: np.ndarray | None = None, D: np.ndarray | None = None) -> np.ndarray | None:
    """``x[k+1] = μ ∘ x[k] + f[k] + G D[k] E x[k]`` over a stretch (see the module docstring).

    Parameters
    ----------
    mu, f, x0 : see :func:`modal_scan` (``f`` is not modified).
    G : ndarray (n, nl), optional
        ``V⁻¹ Γ_P``: how each loss source enters the modes.
    E : ndarray (ntv, n), optional
        ``V[tv]``: the loss nodes' temperatures from the modes.
    D : ndarray (L, nl, ntv), optional
        ``∂P/∂T`` at each step (W/K); without it (or all zero) the stretch is open loop.

    Returns
    -------
    ndarray (n, L, c) or None
        ``x[1] .. x[L]``; None if the feedback did not converge to round-off (step it instead).
    """
    x = modal_scan(mu, f, x0)
    if D is None or G is None or E is None or not np.any(D):
        return x

    def loss_nodes(x: np.ndarray) -> np.ndarray:
        """``y[k] = E x[k]`` at ``k = 0 .. L−1`` (ntv, L, c)."""
        y = np.tensordot(E, x[:, :-1], axes=1)
        return np.concatenate([(E @ x0)[:, None], y], axis=1)

    y = loss_nodes(x)
    for _ in range(MAX_ITER):
        u = np.einsum("klt,tkc->lkc", D, y)  # loss inputs (nl, L, c)
        x = modal_scan(mu, f + np.tensordot(G, u, axes=1), x0)
        y_new = loss_nodes(x)
        change = float(np.max(np.abs(y_new - y)))
        y = y_new
        if change <= ROUND_OFF * float(np.max(np.abs(y))):
            return x
    return None


def step_modal(mu: np.ndarray, f: np.ndarray, x0: np.ndarray, G: np.ndarray, E: np.ndarray,
               D: np.ndarray) -> np.ndarray:
    """:func:`solve_stretch` step by step (the same recursion, for a stretch the iteration does
    not settle)."""
    out = np.empty_like(f)
    x = x0
    for k in range(f.shape[1]):
        x = mu[:, None] * x + f[:, k] + G @ (D[k] @ (E @ x))
        out[:, k] = x
    return out


def solve_nodes(V: np.ndarray, Vi: np.ndarray, phi: np.ndarray, mu: np.ndarray, GP: np.ndarray,
                tv: np.ndarray, f: np.ndarray, x0: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A stretch of ``x[k+1] = (Φ + Γ_P D[k] E_tv) x[k] + V f[k]`` at one operating point.

    The feedback's mean over the stretch, ``D̄``, is folded into the transition
    ``M̄ = Φ + Γ_P D̄ E_tv``; in the modal basis of ``Φ``, scaled by ``r = √phi``, ``M̄`` is
    symmetric (the loss laws read the node they heat, :class:`~thermal_edge.lptn.discretise.Discrete`),
    so ``M̄ = Ω diag(μ̄) Ω⁻¹`` with real ``μ̄``. Only the departures ``D[k] − D̄`` (the noise of
    the current) are left to the iteration of :func:`solve_stretch`, which then settles in a few
    passes. Where ``M̄`` is not symmetrisable or the iteration does not settle, the stretch is
    stepped in the modal basis of ``Φ`` (:func:`step_modal`).

    Parameters
    ----------
    V, Vi : ndarray (n, n)
        The modal basis ``V`` of ``Φ`` and ``V⁻¹`` at the operating point.
    phi, mu : ndarray (n,)
        ``(μ − 1)/λ`` and the eigenvalues ``μ`` of ``Φ``.
    GP : ndarray (n, nl)
        ``Γ_P``, K/W.
    tv : ndarray of int (ntv,)
        Nodes whose temperatures the loss laws read.
    f : ndarray (n, L, c)
        Forcing in the modal basis of ``Φ`` (``V⁻¹`` times node forcing).
    x0 : ndarray (n, c)
        State in node coordinates at the stretch's start.
    D : ndarray (L, nl, ntv)
        ``∂P/∂T`` at each step, W/K.

    Returns
    -------
    Om : ndarray (n, n)
        Map from the returned modal states to node coordinates.
    xi : ndarray (n, L, c)
        Modal states at steps 1 .. L.
    """
    GPt = Vi @ GP
    if not len(tv) or not np.any(D):
        return V, modal_scan(mu, f, Vi @ x0)
    Dbar = D.mean(axis=0)
    Mt = np.diag(mu) + GPt @ Dbar @ V[tv]  # M̄ in the modal basis of Φ
    r = np.sqrt(phi)
    Sym = Mt * r[None, :] / r[:, None]
    asym = float(np.max(np.abs(Sym - Sym.T)) / np.max(np.abs(Sym)))
    if asym < 1e-9:
        mub, Q2 = np.linalg.eigh((Sym + Sym.T) / 2.0)
        if mub.min() > -1e-12 and mub.max() < 1.0:
            rQ2, Q2r = r[:, None] * Q2, Q2.T / r[None, :]
            Om = V @ rQ2
            xi = solve_stretch(np.maximum(mub, 0.0), np.tensordot(Q2r, f, axes=1), Q2r @ (Vi @ x0),
                               Q2r @ GPt, Om[tv], D - Dbar)
            if xi is not None:
                return Om, xi
    return V, step_modal(mu, f, Vi @ x0, GPt, V[tv], D)


def stretches(ops: np.ndarray, eligible: np.ndarray, min_len: int = MIN_STRETCH) -> list[tuple[int, int]]:
    """Maximal runs ``(a, b)`` of steps ``a .. b−1``, all ``eligible`` and at one operating point,
    at least ``min_len`` long.

    >>> stretches(np.array([0, 0, 0, 1, 1, 0]), np.array([True, True, True, True, False, True]), 2)
    [(0, 3)]
    """
    cut = np.ones(len(ops) + 1, dtype=bool)
    cut[1:-1] = (ops[1:] != ops[:-1]) | (eligible[1:] != eligible[:-1])
    bounds = np.nonzero(cut)[0]
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if eligible[a] and b - a >= min_len]


def covered(spans: list[tuple[int, int]], steps: int) -> np.ndarray:
    """Boolean mask (steps,) of the steps inside ``spans``."""
    mask = np.zeros(steps, dtype=bool)
    for a, b in spans:
        mask[a:b] = True
    return mask
