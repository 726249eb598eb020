"""The linear recursion of a stretch of steps with one discretisation, run vectorised in time.

Over steps where the operating point (and so ``Φ``, ``Γ``) stays the same, the simulation and the
sensitivities both follow

    x[k+1] = Φ x[k] + f[k] + Γ_P D[k] x[k][tv]

with a forcing ``f`` known for the whole stretch in advance (inputs, or the sensitivities'
``dΦ T + dΓ w``) and the temperature feedback of affine losses ``D[k] = ∂P/∂T`` at step ``k``
(loss sources × loss nodes; it changes every step when the current does). In the modal basis of
``Φ`` (``Φ = V diag(μ) V⁻¹`` with real ``0 ≤ μ < 1``, :class:`~thermal_edge.lptn.discretise.Discrete`)
the open loop is ``n`` independent first-order filters, run in time by blocked matrix products
(:func:`modal_scan`) over all modes and columns at once.

The feedback is low-rank twice over, and solved exactly (no iteration):

* in space: it reads only the loss nodes, ``y[k] = E x[k]`` with ``E = V[tv]`` (a few rows);
* in time: the series ``D[k]`` has a small rank ``r`` (a copper loss ``∝ i²`` gives
  ``D[k] = i[k]² C``: rank one), ``D[k] = Σ_ρ s[k, ρ] C_ρ`` from its singular value
  decomposition (terms below round-off of the largest are dropped).

So ``x = x₀ + 𝓛z`` with the open-loop response ``x₀`` and ``z[k] = (s[k, ρ] y[k])_ρ`` fed through
``G C_ρ`` (``G = V⁻¹ Γ_P``). The loss nodes obey ``y = y₀ + E 𝓛 z``: lower block-triangular
in time. It is solved in blocks of :data:`TIME_BLOCK` steps: inside a block a unit
lower-triangular system of ``TIME_BLOCK · ntv`` unknowns (forward substitution: exact up to
round-off, with the same operations the stepped recursion does, reordered), and the feedback's
modal state ``q`` carried from block to block exactly. Then ``x = scan(f + G C z)``.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg import solve_triangular

#: shortest stretch of one operating point run vectorised (its set-up costs about this many steps)
MIN_STRETCH = 32
#: steps per block of :func:`modal_scan` (its flops grow with it, its passes over the blocks shrink)
BLOCK = 16
#: steps per block of the loss nodes' triangular solve
TIME_BLOCK = 64
#: terms of the feedback's time series below this fraction of the largest are round-off
RANK_TOL = 1e-15


def modal_scan(mu: np.ndarray, f: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """``x[k+1] = μ ∘ x[k] + f[k]``, ``k = 0 .. L−1``, for all modes and columns at once.

    In blocks of :data:`BLOCK` steps: inside a block, each mode's response to the block's
    forcing is one product with the lower-triangular Toeplitz matrix of ``μ^(i−l)`` (a batched
    matrix product); the states at the block starts follow the same recursion with ``μ^BLOCK``
    over the blocks' end values (this function, one level up).

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
    inner = np.matmul(toep[:, None], f.reshape(n, nb, B, c))  # zero-state response in each block
    if nb == 1:
        starts = x0[:, None]
    else:
        ends = modal_scan(pw[:, B], np.ascontiguousarray(inner[:, :-1, B - 1]), x0)
        starts = np.concatenate([x0[:, None], ends], axis=1)  # (n, nb, c)
    inner += pw[:, None, 1:, None] * starts[:, :, None]
    return inner.reshape(n, nb * B, c)[:, :L]


def solve_stretch(mu: np.ndarray, f: np.ndarray, x0: np.ndarray, G: np.ndarray, E: np.ndarray,
                  D: np.ndarray) -> np.ndarray:
    """``x[k+1] = μ ∘ x[k] + f[k] + G D[k] E x[k]`` over a stretch (see the module docstring).

    Parameters
    ----------
    mu, f, x0 : see :func:`modal_scan`.
    G : ndarray (n, nl)
        ``V⁻¹ Γ_P``: how each loss source enters the modes.
    E : ndarray (ntv, n)
        ``V[tv]``: the loss nodes' temperatures from the modes.
    D : ndarray (L, nl, ntv)
        ``∂P/∂T`` at each step (W/K).

    Returns
    -------
    ndarray (n, L, c)
        ``x[1] .. x[L]``.
    """
    n, L, c = f.shape
    ntv = E.shape[0]
    D2 = D.reshape(L, -1)
    cols = np.nonzero(np.any(D2 != 0.0, axis=0))[0]  # a loss law reads one node or a few: most are zero
    x = modal_scan(mu, f, x0)
    if not len(cols):
        return x
    U_, sv, Wt = np.linalg.svd(D2[:, cols], full_matrices=False)
    r = int(np.count_nonzero(sv > RANK_TOL * sv[0]))
    s = U_[:, :r] * sv[:r]  # (L, r)
    Wfull = np.zeros((r, D2.shape[1]))
    Wfull[:, cols] = Wt[:r]
    GC = np.concatenate([G @ Wfull[k].reshape(D.shape[1], ntv) for k in range(r)], axis=1)  # (n, r ntv)
    # the open-loop loss-node values y₀[k] = E x₀[k], k = 0 .. L−1
    B = TIME_BLOCK
    nblk = -(-L // B)
    y0 = np.zeros((nblk * B, ntv, c))
    y0[0] = E @ x0
    y0[1:L] = np.tensordot(E, x[:, : L - 1], axes=1).transpose(1, 0, 2)
    sp = np.zeros((nblk * B, r))
    sp[:L] = s
    with np.errstate(under="ignore"):
        pw = mu[None, :] ** np.arange(B + 1)[:, None]  # (B+1, n)
    H = np.einsum("an,mn,nq->maq", E, pw[: B], GC).reshape(B, ntv, r, ntv)  # E diag(μ^m) G C_ρ
    Ep = (E[None] * pw[:B, None, :]).reshape(B * ntv, n)  # E diag(μ^i), stacked
    R = (pw[B - 1:: -1][:B, :, None] * GC[None]).transpose(1, 0, 2).reshape(n, B * r * ntv)  # diag(μ^(B−1−l)) G C
    i = np.arange(B)
    lag = i[:, None] - 1 - i[None, :]  # m = i − 1 − l for l < i
    below = lag >= 0
    # the block's coupling of step l into step i per unit s[l, ρ], laid out (ρ, i a, l b)
    Hl = np.where(below[:, :, None, None, None], H[np.maximum(lag, 0)], 0.0)  # (i, l, a, ρ, b)
    Hl = np.ascontiguousarray(Hl.transpose(3, 0, 2, 1, 4)).reshape(r, B * ntv, B, ntv)
    muB = pw[B][:, None]
    q = np.zeros((n, c))
    z = np.empty((nblk * B, r * ntv, c))
    eye = np.eye(B * ntv).reshape(B * ntv, B, ntv)
    for j in range(nblk):
        blk = slice(j * B, (j + 1) * B)
        T = eye - Hl[0] * sp[blk, 0][:, None]
        for k in range(1, r):
            T -= Hl[k] * sp[blk, k][:, None]
        T = T.reshape(B * ntv, B * ntv)
        rhs = y0[blk].reshape(B * ntv, c) + Ep @ q
        y = solve_triangular(T, rhs, lower=True, unit_diagonal=True, check_finite=False).reshape(B, ntv, c)
        zb = (sp[blk][:, :, None, None] * y[:, None]).reshape(B, r * ntv, c)
        z[blk] = zb
        q = muB * q + R @ zb.reshape(B * r * ntv, c)
    g = np.tensordot(GC, z[:L], axes=([1], [1]))  # (n, L, c)
    return x + modal_scan(mu, g, np.zeros((n, c)))


def solve_nodes(V: np.ndarray, Vi: np.ndarray, mu: np.ndarray, GP: np.ndarray, tv: np.ndarray,
                forcing: Callable[[], np.ndarray], x0: np.ndarray, D: np.ndarray) -> np.ndarray:
    """A stretch of ``x[k+1] = (Φ + Γ_P D[k] E_tv) x[k] + V f[k]`` at one operating point.

    Parameters
    ----------
    V, Vi : ndarray (n, n)
        The modal basis ``V`` of ``Φ`` and ``V⁻¹`` at the operating point.
    mu : ndarray (n,)
        The eigenvalues ``μ`` of ``Φ``.
    GP : ndarray (n, nl)
        ``Γ_P``, K/W.
    tv : ndarray of int (ntv,)
        Nodes whose temperatures the loss laws read.
    forcing : callable
        ``forcing()``: the forcing (n, L, c) of every step in the modal basis of ``Φ``.
    x0 : ndarray (n, c)
        State in node coordinates at the stretch's start.
    D : ndarray (L, nl, ntv)
        ``∂P/∂T`` at each step, W/K.

    Returns
    -------
    ndarray (n, L, c)
        Modal states (``V⁻¹ x``) at steps 1 .. L.
    """
    if not len(tv) or not np.any(D):
        return modal_scan(mu, forcing(), Vi @ x0)
    return solve_stretch(np.maximum(mu, 0.0), forcing(), Vi @ x0, Vi @ GP, V[tv], D)


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
