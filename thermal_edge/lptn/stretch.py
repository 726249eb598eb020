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
from scipy.linalg.lapack import dtrtrs

#: shortest stretch of one operating point run vectorised (its set-up costs about this many steps)
MIN_STRETCH = 32
#: steps per block of :func:`modal_scan` (its flops grow with it, its passes over the blocks shrink)
BLOCK = 16
#: steps per block of the loss nodes' triangular solve
TIME_BLOCK = 16
#: terms of the feedback's time series below this fraction of the largest are round-off
RANK_TOL = 1e-15
#: powers ``μ^i`` below this are set to zero: they are far below round-off of any term, and
#: subnormal numbers would slow every product they enter by an order of magnitude
TINY = 1e-280


def powers(mu: np.ndarray, B: int) -> np.ndarray:
    """``μ^i`` (n, B+1) for ``i = 0 .. B``, those below :data:`TINY` set to zero."""
    with np.errstate(under="ignore"):
        pw = mu[:, None] ** np.arange(B + 1)
    pw[pw < TINY] = 0.0
    return pw


def modal_scan(mu: np.ndarray, f: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """``x[k+1] = μ ∘ x[k] + f[k]``, ``k = 0 .. L−1``, for all modes and columns at once.

    In blocks of :data:`BLOCK` steps: inside a block, each mode's response to the block's
    forcing is one product with the lower-triangular Toeplitz matrix of ``μ^(i−l)`` (one matrix
    product per mode over all blocks and columns, time being the last axis); the states at the
    block starts follow the same recursion with ``μ^BLOCK`` over the blocks' end values (this
    function, one level up).

    Parameters
    ----------
    mu : ndarray (n,)
        Eigenvalues of the transition (dimensionless, in [0, 1)).
    f : ndarray (n, c, L)
        Forcing per mode, column and step (the units of ``x``).
    x0 : ndarray (n, c)
        State at the stretch's first step.

    Returns
    -------
    ndarray (n, c, L)
        ``x[1] .. x[L]``.
    """
    n, c, L = f.shape
    B = BLOCK if L > BLOCK else L
    nb = -(-L // B)
    if nb * B != L:
        f = np.concatenate([f, np.zeros((n, c, nb * B - L))], axis=2)
    pw = powers(mu, B)
    i = np.arange(B)
    lag = i[None, :] - i[:, None]  # (l, i): the response at step i of the block to its input l
    toep = np.where(lag >= 0, pw[:, np.maximum(lag, 0)], 0.0)  # (n, B, B)
    F = f.reshape(n, c * nb, B)
    out = np.matmul(F, toep)  # zero-state response inside each block
    if nb == 1:
        out += x0[:, :, None] * pw[:, None, 1:]
    else:
        ends = out[:, :, B - 1].reshape(n, c, nb)[:, :, :-1]
        starts = np.empty((n, c, nb))
        starts[:, :, 0] = x0
        starts[:, :, 1:] = modal_scan(pw[:, B], ends, x0)
        out += starts.reshape(n, c * nb, 1) * pw[:, None, 1:]
    res: np.ndarray = out.reshape(n, c, nb * B)[:, :, :L]
    return res


class Stretch:
    """``x[k+1] = μ ∘ x[k] + f[k] + G D[k] E x[k]`` over a stretch (see the module docstring).

    What depends on the feedback only (its rank, the blocks' triangular matrices) is built once
    and serves every :meth:`solve` (the simulation's temperatures and the sensitivities).

    Parameters
    ----------
    mu : ndarray (n,)
        Eigenvalues of the transition (dimensionless, in [0, 1)).
    G : ndarray (n, nl)
        ``V⁻¹ Γ_P``: how each loss source enters the modes.
    E : ndarray (ntv, n)
        ``V[tv]``: the loss nodes' temperatures from the modes.
    D : ndarray (L, nl, ntv)
        ``∂P/∂T`` at each step (W/K).
    """

    def __init__(self, mu: np.ndarray, G: np.ndarray, E: np.ndarray, D: np.ndarray) -> None:
        self.mu, self.E, self.L = np.maximum(mu, 0.0), E, D.shape[0]
        n, ntv, L = len(mu), E.shape[0], D.shape[0]
        D2 = D.reshape(L, -1)
        cols = np.nonzero(np.any(D2 != 0.0, axis=0))[0]  # a loss law reads one node or a few: most are zero
        self.r = 0
        if not len(cols):
            return
        U_, sv, Wt = np.linalg.svd(D2[:, cols], full_matrices=False)
        r = self.r = int(np.count_nonzero(sv > RANK_TOL * sv[0]))
        Wfull = np.zeros((r, D2.shape[1]))
        Wfull[:, cols] = Wt[:r]
        GC = np.concatenate([G @ Wfull[k].reshape(D.shape[1], ntv) for k in range(r)], axis=1)  # (n, r ntv)
        B = TIME_BLOCK
        nblk = self.nblk = -(-L // B)
        sp = np.zeros((nblk * B, r))
        sp[:L] = U_[:, :r] * sv[:r]
        pw = powers(self.mu, B).T  # (B+1, n)
        i = np.arange(B)
        lag = i[:, None] - 1 - i[None, :]  # m = i − 1 − l for l < i
        below = lag >= 0
        # every block's unit lower-triangular system for its loss-node values (blk, B ntv, B ntv):
        # y_i − Σ_{l<i} E diag(μ^(i−1−l)) G Σ_ρ s[l, ρ] C_ρ y_l = y₀_i + E diag(μ^i) q
        K = (E[None] * pw[:B, None, :]) @ GC  # (B, ntv, r ntv): E diag(μ^m) G C
        He = np.where(below[:, None, :, None], K[np.maximum(lag, 0)].transpose(0, 2, 1, 3), 0.0)
        He = He.reshape(B, ntv, B, r, ntv)
        spb = sp.reshape(nblk, B, r)
        A = -np.einsum("ialgb,jlg->jialb", He, spb, optimize=True) if r > 1 else \
            -(He[None, :, :, :, 0] * spb[:, None, None, :, 0, None])
        A = A.reshape(nblk, B * ntv, B * ntv)
        A += np.eye(B * ntv)
        self.At = np.swapaxes(A, 1, 2)  # Fortran order of each block's matrix, for LAPACK without a copy
        self.Ep = (E[None] * pw[:B, None, :]).reshape(B * ntv, n)  # E diag(μ^i), stacked
        # each block's carry from its loss-node values: Σ_l diag(μ^(B−1−l)) G Σ_ρ s[l, ρ] C_ρ y_l
        Rl = (pw[B - 1:: -1][:B, :, None] * GC[None]).reshape(B, n, r, ntv).transpose(2, 1, 0, 3)  # (ρ, n, l, b)
        Rj = Rl[0][None] * spb[:, None, :, 0, None]
        for k in range(1, r):
            Rj += Rl[k][None] * spb[:, None, :, k, None]
        self.Rj = Rj.reshape(nblk, n, B * ntv)
        self.muB = pw[B][:, None]
        self.pw, self.GC, self.spb = pw, GC, spb

    def solve(self, f: np.ndarray, x0: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The recursion from ``x[0] = x0`` under the forcing ``f``.

        Parameters
        ----------
        f : ndarray (n, c, L)
            Forcing per mode, column and step.
        x0 : ndarray (n, c)
            State at the stretch's first step.
        W : ndarray (nr, n)
            The rows wanted at every step, from the modes.

        Returns
        -------
        rows : ndarray (nr, c, L)
            ``W x[1] .. W x[L]``.
        end : ndarray (n, c)
            ``x[L]``.
        """
        n, c, L = f.shape
        mu, E = self.mu, self.E
        ntv, nr = E.shape[0], W.shape[0]
        x = modal_scan(mu, f, x0)
        rows = (W @ x.reshape(n, -1) if x.flags.c_contiguous else np.tensordot(W, x, axes=1)).reshape(nr, c, L)
        end = x[:, :, -1].copy()
        if not self.r:
            return rows, end
        B, nblk, r, pw = TIME_BLOCK, self.nblk, self.r, self.pw
        m = r * ntv
        # the open-loop loss-node values y₀[k] = E x₀[k], k = 0 .. L−1, padded to whole blocks
        y0 = np.zeros((nblk * B, ntv, c))
        y0[0] = E @ x0
        y0[1:L] = (E @ x[:, :, : L - 1].reshape(n, -1) if x.flags.c_contiguous
                   else np.tensordot(E, x[:, :, : L - 1], axes=1)).reshape(ntv, c, L - 1).transpose(2, 0, 1)
        At, Ep, Rj, muB = self.At, self.Ep, self.Rj, self.muB
        qs = np.zeros((nblk + 1, n, c))  # feedback modal state at each block's start (and the end)
        Y = np.empty((nblk, B * ntv, c))
        rhs0 = y0.reshape(nblk, B * ntv, c)
        rhs = np.empty((B * ntv, c))
        carry = np.empty((n, c))
        for j in range(nblk):
            np.matmul(Ep, qs[j], out=rhs)
            rhs += rhs0[j]
            Yj = Y[j] = dtrtrs(At[j], rhs, lower=0, trans=1, unitdiag=1)[0]
            np.matmul(Rj[j], Yj, out=carry)
            np.multiply(muB, qs[j], out=qs[j + 1])
            qs[j + 1] += carry
        z = (self.spb[:, :, :, None, None] * Y.reshape(nblk, B, 1, ntv, c)).reshape(nblk, B * m, c)
        # the feedback's part of the wanted rows: from each block's start state and inside the block
        Wp = (W[None] * pw[1: B + 1, None, :]).reshape(B * nr, n)  # W diag(μ^(i+1))
        fb = (Wp @ qs[:nblk].transpose(1, 0, 2).reshape(n, nblk * c)).reshape(B, nr, nblk, c)
        fb += (_inputs_to_rows(W, pw, self.GC, B) @ z.transpose(1, 0, 2).reshape(B * m, nblk * c)).reshape(B, nr, nblk, c)
        rows += fb.transpose(1, 3, 2, 0).reshape(nr, c, nblk * B)[:, :, :L]
        if nblk * B == L:
            end_fb = qs[nblk]
        else:  # the last block is partial: its state at step L from its start and its inputs
            last = L - (nblk - 1) * B
            zl = z[-1].reshape(B, m, c)[:last]
            carry_l = pw[last - 1:: -1][:last, :, None] * self.GC[None]  # diag(μ^(last−1−l)) G C
            end_fb = pw[last][:, None] * qs[nblk - 1] + np.tensordot(carry_l, zl, axes=([0, 2], [0, 1]))
        return rows, end + end_fb


def solve_stretch(mu: np.ndarray, f: np.ndarray, x0: np.ndarray, G: np.ndarray, E: np.ndarray,
                  D: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``x[k+1] = μ ∘ x[k] + f[k] + G D[k] E x[k]`` over a stretch: :meth:`Stretch.solve` once.

    Parameters
    ----------
    mu, G, E, D : see :class:`Stretch`.
    f, x0, W : see :meth:`Stretch.solve`.

    Returns
    -------
    rows : ndarray (nr, c, L)
        ``W x[1] .. W x[L]``.
    end : ndarray (n, c)
        ``x[L]``.
    """
    return Stretch(mu, G, E, D).solve(f, x0, W)


def _inputs_to_rows(W: np.ndarray, pw: np.ndarray, GC: np.ndarray, B: int) -> np.ndarray:
    """``W diag(μ^(i−l)) G C`` for ``l ≤ i`` (the state after step ``i`` of the block from input ``l``),
    as (B nr, B m)."""
    i = np.arange(B)
    lag = i[:, None] - i[None, :]
    K = (W[None] * pw[:B, None, :]) @ GC
    full = np.where((lag >= 0)[:, None, :, None], K[np.maximum(lag, 0)].transpose(0, 2, 1, 3), 0.0)
    return full.reshape(B * W.shape[0], B * GC.shape[1])


class NodeStretch:
    """A stretch at one operating point in node coordinates: ``x[k+1] = (Φ + Γ_P D[k] E_tv) x[k] + V f[k]``.

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
    D : ndarray (L, nl, ntv)
        ``∂P/∂T`` at each step, W/K.
    """

    def __init__(self, V: np.ndarray, Vi: np.ndarray, mu: np.ndarray, GP: np.ndarray, tv: np.ndarray,
                 D: np.ndarray) -> None:
        self.V, self.Vi = V, Vi
        self.core = Stretch(mu, Vi @ GP, V[tv], D)

    def solve(self, f: np.ndarray, x0: np.ndarray, keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The stretch from ``x0``.

        Parameters
        ----------
        f : ndarray (n, c, L)
            The forcing of every step in the modal basis of ``Φ``.
        x0 : ndarray (n, c)
            State in node coordinates at the stretch's start.
        keep : ndarray of int, optional
            The nodes wanted at every step (default all).

        Returns
        -------
        rows : ndarray (len(keep), c, L)
            ``x[1] .. x[L]`` at the ``keep`` nodes.
        end : ndarray (n, c)
            ``x[L]`` at every node.
        """
        W = self.V if keep is None else self.V[keep]
        rows, end = self.core.solve(f, self.Vi @ x0, W)
        return rows, self.V @ end


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


def varying_steps(D: np.ndarray, window: int = MIN_STRETCH) -> np.ndarray:
    """Steps (L,) whose neighbourhood of ``window`` steps has the feedback ``D`` (L, ...) change on
    at least a quarter of its steps: where a noisy current makes a transition per step. Elsewhere
    (held inputs) the step-by-step recursion reuses one transition over many steps and is cheaper
    than the vectorised stretch.

    >>> varying_steps(np.array([1.0, 2, 3, 4, 4, 4, 4, 4]), window=4).tolist()
    [True, True, True, True, True, True, False, False]
    """
    L = len(D)
    change = np.zeros(L)
    if L > 1:
        change[1:] = np.any((D[1:] != D[:-1]).reshape(L - 1, -1), axis=1)
    # changes among the steps k − window/2 .. k + window/2 − 1 (clipped at the ends)
    cs = np.concatenate([[0.0], np.cumsum(change)])
    k = np.arange(L)
    lo, hi = np.clip(k - window // 2, 0, L), np.clip(k + (window - window // 2), 0, L)
    busy: np.ndarray = 4 * (cs[hi] - cs[lo]) >= window
    return busy


def covered(spans: list[tuple[int, int]], steps: int) -> np.ndarray:
    """Boolean mask (steps,) of the steps inside ``spans``."""
    mask = np.zeros(steps, dtype=bool)
    for a, b in spans:
        mask[a:b] = True
    return mask
